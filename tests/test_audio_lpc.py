"""LPC analysis and resampling against independent truth (scipy, synthetic AR processes, tones)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.signal

from facecast.server.audio.io import StreamResampler, resample
from facecast.server.audio.lpc import analyze, autocorrelate, levinson, zero_crossing_rate


def stable_ar(rng: np.random.Generator, order: int) -> np.ndarray:
    """A random stable all-pole polynomial ``[1, a1..ap]``: pole pairs with radius 0.5-0.9 at
    well-separated angles (like formants; clustered poles make the problem ill-conditioned)."""
    n = order // 2
    r = rng.uniform(0.5, 0.9, n)
    th = np.linspace(0.3, 2.8, n) + rng.uniform(-0.1, 0.1, n)
    poles = np.concatenate([r * np.exp(1j * th), r * np.exp(-1j * th)])
    return np.real(np.poly(poles))


@pytest.mark.parametrize("order", [2, 4, 8, 12])
def test_levinson_recovers_known_ar_coefficients(rng, order):
    a = stable_ar(rng, order)
    x = scipy.signal.lfilter([1.0], a, rng.standard_normal(100_000))
    r = autocorrelate(x[None], max_lag=order)[0]
    a_hat, k, err = levinson(r, order=order)
    np.testing.assert_allclose(a_hat, a, atol=0.03)
    assert np.all(np.abs(k) < 1)
    assert err / len(x) == pytest.approx(1.0, rel=0.03)  # unit-variance innovation


def test_levinson_matches_solve_toeplitz(rng):
    frames = rng.standard_normal((16, 200)) * np.hamming(200)
    r = autocorrelate(frames, max_lag=12)
    a, _, _ = levinson(r, order=12)
    for i in range(len(frames)):
        ref = scipy.linalg.solve_toeplitz(r[i, :12], -r[i, 1:13])
        np.testing.assert_allclose(a[i, 1:], ref, atol=1e-9)


def test_autocorrelate_matches_fftconvolve(rng):
    y = rng.standard_normal(200)
    ref = scipy.signal.fftconvolve(y, y[::-1])[199 : 199 + 13]
    np.testing.assert_allclose(autocorrelate(y, max_lag=12), ref, atol=1e-9)


def test_first_reflection_coefficient_of_ar1():
    x = scipy.signal.lfilter([1.0], [1.0, -0.8], np.random.default_rng(1).standard_normal(100_000))
    _, k, _ = levinson(autocorrelate(x, max_lag=3), order=3)
    assert k[0] == pytest.approx(-0.8, abs=0.01)
    np.testing.assert_allclose(k[1:], 0, atol=0.02)


def test_digital_silence_gives_zero_coefficients():
    _, k, err = levinson(np.zeros((3, 13)), order=12)
    assert np.all(k == 0) and np.all(err == 0)


@pytest.mark.parametrize("freq", [100.0, 700.0, 2000.0])
def test_zero_crossing_rate_of_a_tone(freq):
    sr = 10000
    t = np.arange(200) / sr
    z = zero_crossing_rate(np.sin(2 * np.pi * freq * t + 0.3)[None], sr=sr)[0]
    assert z == pytest.approx(2 * freq * 0.010, abs=0.6)  # crossings per 10 ms


def test_analyze_frames_are_centred_every_10ms(rng):
    x = rng.standard_normal(10_050) * 0.1
    f = analyze(x, sr=10000)
    assert len(f) == 101 and f.k.shape == (101, 12)
    np.testing.assert_allclose(f.times[:3], [0.0, 0.01, 0.02])
    # frame 0 holds only half a frame of signal: ~3 dB less power than a full frame
    assert f.energy_db[0] < f.energy_db[50] - 1.5


@pytest.mark.parametrize("sr", [8000, 16000, 44100, 48000])
def test_resample_to_analysis_rate_keeps_tones_and_removes_aliases(sr):
    t = np.arange(sr) / sr
    y = resample(np.sin(2 * np.pi * 1000 * t), sr, 10000)
    assert len(y) == 10000
    spec = np.abs(np.fft.rfft(y[1000:9000] * np.hanning(8000)))
    assert np.argmax(spec) * 10000 / 8000 == pytest.approx(1000, abs=2)
    assert np.sqrt(np.mean(y[1000:9000] ** 2)) == pytest.approx(np.sqrt(0.5), rel=0.01)
    if sr > 16000:  # a 7 kHz tone would alias to 3 kHz; the anti-aliasing filter removes it
        z = resample(np.sin(2 * np.pi * 7000 * t), sr, 10000)
        assert np.sqrt(np.mean(z[1000:9000] ** 2)) < 0.01


@pytest.mark.parametrize("sr", [8000, 16000, 22050, 44100, 48000])
def test_stream_resampler_equals_batch(rng, sr):
    x = rng.standard_normal(sr // 4)
    s = StreamResampler(sr, 10000)
    out, i = [], 0
    while i < len(x):
        n = int(rng.integers(1, 600))
        out.append(s.push(x[i : i + n]))
        i += n
    y = np.concatenate(out)
    ref = resample(x, sr, 10000)
    assert len(ref) - 30 < len(y) <= len(ref)
    np.testing.assert_allclose(y, ref[: len(y)], atol=1e-12)


def test_blockwise_analysis_equals_one_block(rng, monkeypatch):
    from facecast.server.audio import lpc

    x = rng.standard_normal(5_000) * 0.1
    whole = analyze(x, sr=10000)
    monkeypatch.setattr(lpc, "BLOCK", 7)
    monkeypatch.setattr(lpc, "SMALL", 0)  # the same (vectorised) arithmetic as the whole
    parts = analyze(x, sr=10000)
    # equal to rounding: the autocorrelation's matrix product (``_autocorr_basis``) may round
    # differently for another number of rows
    np.testing.assert_allclose(parts.k, whole.k, rtol=0, atol=1e-10)
    np.testing.assert_allclose(parts.energy_db, whole.energy_db, rtol=0, atol=1e-10)


def test_autocorrelation_basis_equals_the_inverse_fft(rng):
    """``p @ _autocorr_basis(n, order)`` is the first ``order + 1`` lags of ``irfft(p, n)``."""
    from facecast.server.audio.lpc import _autocorr_basis

    for n in (256, 512):
        y = rng.standard_normal((5, n // 2 + 20))
        spec = np.fft.rfft(y, n=n)
        p = spec.real**2 + spec.imag**2
        np.testing.assert_allclose(
            p @ _autocorr_basis(n, 12), np.fft.irfft(p, n=n)[:, :13], rtol=0, atol=1e-10
        )


def test_scalar_path_for_few_frames_equals_the_vectorised_one(rng, monkeypatch):
    """``levinson`` and ``cepstrum`` loop per frame on a few frames (the live path's chunks);
    the result is the vectorised one's, to rounding, digital silence included."""
    from facecast.server.audio import lpc

    frames = rng.standard_normal((6, 200))
    frames[2] = 0.0
    r = lpc.autocorrelate(frames, max_lag=12)
    small = levinson(r, order=12)
    small_cep = lpc.cepstrum(small[0])
    monkeypatch.setattr(lpc, "SMALL", 0)
    rows = levinson(r, order=12)
    for got, ref in zip((*small, small_cep), (*rows, lpc.cepstrum(rows[0]))):
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    assert np.all(small[1][2] == 0) and small[2][2] == 0


def test_decaying_filter_tail_gives_finite_features(monkeypatch):
    """A filter's decaying tail reaches the denormal range: its frames are digital silence
    (k = 0), not NaN from an underflowing prediction error, on the vectorised path and on the
    live path's per-frame one (found in the training augmentation's filtered copies)."""
    import scipy.signal

    from facecast.server.audio import lpc

    x = np.zeros(120_000)
    x[0] = 1.0
    for b in ([1.0], [1.0, -1.0], [1.0, -2.0, 1.0]):
        y = scipy.signal.lfilter(b, [1.0, -0.99], x)  # below 1e-300 after ~69000 samples
        f = analyze(y, sr=10000)
        assert np.isfinite(f.k).all() and np.isfinite(f.cep).all()
        assert not f.k[-10:].any()  # the tail's last frames: silence
    monkeypatch.setattr(lpc, "SMALL", 10**9)  # every frame through the scalar loop
    f = analyze(scipy.signal.lfilter([1.0], [1.0, -0.99], x), sr=10000)
    assert np.isfinite(f.k).all() and np.isfinite(f.cep).all()
