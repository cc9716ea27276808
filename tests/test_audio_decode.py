"""Decoding uploaded audio: streaming to the analysis rate in bounded memory, header limits, hostile
files (lying or truncated headers, absurd rates, no channels) and a fuzz over mutated real files."""

from __future__ import annotations

import itertools
import struct
import tempfile
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import scipy.signal
import soundfile as sf
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facecast.server.audio.io import (
    MAX_RATIO_TERM,
    BlockResampler,
    conversion_ratio,
    decode_audio,
    read_audio,
    resample,
)
from facecast.server.audio.lpc import ANALYSIS_RATE
from facecast.server.audio.pipeline import lipsync, lipsync_file
from facecast.server.errors import InputError


@pytest.fixture(scope="module")
def speech(data_dir) -> tuple[np.ndarray, int]:
    x, sr = sf.read(str(data_dir / "speech" / "bobby_16bit_16khz.wav"))
    return x, sr


def flac_with_total_samples(src: bytes, total: int) -> bytes:
    """``src`` (a FLAC file) with STREAMINFO's 36-bit total-samples field set to ``total``."""
    b = bytearray(src)
    assert b[:4] == b"fLaC" and b[4] & 0x7F == 0  # the first metadata block is STREAMINFO
    b[21] = (b[21] & 0xF0) | ((total >> 32) & 0x0F)
    b[22:26] = (total & 0xFFFFFFFF).to_bytes(4, "big")
    return bytes(b)


def wav_field(src: bytes, offset: int, fmt: str, value: int) -> bytes:
    """``src`` (a WAV) with a field of its ``fmt `` chunk (``offset`` from the chunk id) replaced."""
    b = bytearray(src)
    i = b.find(b"fmt ")
    b[i + offset : i + offset + struct.calcsize(fmt)] = struct.pack(fmt, value)
    return bytes(b)


@pytest.mark.parametrize("sr", [16000, 44100, 48000, 8000, 22050, 383993])
def test_block_resampler_equals_resample_poly_on_any_blocks(sr, rng):
    up, down = conversion_ratio(sr, ANALYSIS_RATE)
    assert max(up, down) <= MAX_RATIO_TERM and abs(sr * up / down / ANALYSIS_RATE - 1) < 1e-3
    for n in (1, 7, 5000, 60000):
        x = rng.normal(size=n)
        rs, parts, i = BlockResampler(up, down), [], 0
        while i < n:
            k = int(rng.integers(1, 20000))
            parts.append(rs.push(x[i : i + k]))
            i += k
        y = np.concatenate(parts + [rs.flush()])
        ref = scipy.signal.resample_poly(x, up, down)
        assert len(y) == len(ref) == rs.n_out(n)
        np.testing.assert_allclose(y, ref, rtol=0, atol=1e-12)


def test_decode_equals_the_whole_file_path(speech, tmp_path):
    x, sr = speech
    stereo = tmp_path / "stereo.flac"
    sf.write(stereo, np.stack([x, 0.5 * x], axis=1), sr, subtype="PCM_24")
    d = decode_audio(stereo, ANALYSIS_RATE)
    ref = resample(sf.read(str(stereo))[0].mean(axis=1), sr, ANALYSIS_RATE)
    assert d.x.dtype == np.float32 and d.rate == ANALYSIS_RATE and d.channels == 2
    assert d.source_rate == sr and d.seconds == pytest.approx(len(x) / sr)
    np.testing.assert_allclose(d.x, ref, atol=1e-6)
    y, rate = read_audio(stereo)  # the native-rate reader goes through the same blocks
    assert rate == sr and y.dtype == np.float64
    np.testing.assert_allclose(y, 0.75 * x, atol=1e-6)


def test_lipsync_file_gives_the_batch_track(speech, data_dir):
    x, sr = speech
    ref = lipsync(x, sr, fps=25).track
    got = lipsync_file(data_dir / "speech" / "bobby_16bit_16khz.wav", fps=25).track
    assert len(got.t) == len(ref.t)
    assert np.mean(got.select1 == ref.select1) > 0.99
    np.testing.assert_allclose(got.faps, ref.faps, atol=1e-2)


def test_an_odd_rate_keeps_exact_frame_times(speech, tmp_path):
    x, sr = speech
    odd = tmp_path / "odd.wav"
    sf.write(odd, scipy.signal.resample_poly(x, 44056, sr), 44056)  # NTSC pull-down rate
    d = decode_audio(odd, ANALYSIS_RATE)
    assert d.rate != ANALYSIS_RATE and abs(d.rate / ANALYSIS_RATE - 1) < 1e-3
    ls = lipsync_file(odd, fps=100)
    assert abs(ls.features.hop * d.rate - 100) < 1e-9  # 100 samples of the actual rate per hop
    assert ls.duration == pytest.approx(len(x) / sr, abs=1e-4)
    ref = lipsync_file(tmp_path / "odd.wav", fps=100)
    assert np.array_equal(ls.visemes, ref.visemes)


def test_decoding_memory_follows_the_analysis_rate_not_the_file(tmp_path, rng):
    seconds, sr = 60, 48000
    p = tmp_path / "long.wav"
    sf.write(
        p, (0.1 * rng.standard_normal((seconds * sr, 2))).astype(np.float32), sr, subtype="PCM_16"
    )
    tracemalloc.start()
    try:
        d = decode_audio(p, ANALYSIS_RATE)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    out = d.x.nbytes  # 2.4 MB; decoding the whole file as float64 needs 46 MB
    assert out == seconds * ANALYSIS_RATE * 4
    assert peak < out + 12 * 2**20, (
        f"peak {peak / 2**20:.1f} MiB for {out / 2**20:.1f} MiB of output"
    )


def test_the_frame_network_memory_does_not_grow_with_the_file(rng):
    """The frame network stacked the whole file's context inputs at once (10 min: 211 MB per
    copy, 1.5 GB peak RSS for a 20 min file); now it works in blocks, with the same output."""
    from facecast.server.audio.classify import default_frame_net, stack_context

    net = default_frame_net()
    F = rng.standard_normal((60000, 44))  # 10 min of frames
    tracemalloc.start()
    try:
        p = net.proba(F)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < p.nbytes + 64 * 2**20, f"peak {peak / 2**20:.0f} MiB for {len(F)} frames"
    part = F[:5000]
    norm = net.speaker_norm()
    inputs = part if norm is None else norm(part)
    np.testing.assert_allclose(
        net.proba(part), net.proba_stacked(stack_context(inputs, net.offsets)), atol=1e-6
    )


def test_lipsync_file_with_calibration_and_transcript_matches_the_signal_path(data_dir, tmp_path):
    """``facecast lipsync --calibrate/--text`` decode in bounded blocks (``lipsync_file``,
    ``calibration_file``) and give what ``calibration_from`` + ``align_text`` give on the signal."""
    from facecast.server.audio.align import align_text
    from facecast.server.audio.pipeline import calibration_file, calibration_from

    wav = data_dir / "speech" / "bobby_16bit_16khz.wav"
    x, sr = read_audio(wav)
    t = np.arange(2 * sr) / sr
    rec = np.concatenate([0.001 * np.sin(2 * np.pi * 50 * t), 0.5 * np.sin(2 * np.pi * 220 * t)])
    sf.write(tmp_path / "cal.wav", rec, sr, subtype="FLOAT")
    cal = calibration_file(tmp_path / "cal.wav")
    ref_cal = calibration_from(rec, sr)
    assert cal.silence_db == pytest.approx(ref_cal.silence_db, abs=0.5)
    assert cal.max_db == pytest.approx(ref_cal.max_db, abs=0.5)
    if __import__("shutil").which("espeak-ng") is None:
        pytest.skip("espeak-ng absent")
    text = "Bobby ripped the ledger."
    got = lipsync_file(wav, fps=100, calibration=cal, text=text)
    ref = align_text(x, sr, text, fps=100, calibration=cal)
    assert np.mean(got.visemes == ref.visemes) > 0.97
    with pytest.raises(InputError, match="transcript is empty"):
        lipsync_file(tmp_path / "missing.wav", text="  ")  # refused before any decoding


def test_a_flac_declaring_2_to_the_36_samples_is_refused_before_any_allocation(speech, tmp_path):
    x, sr = speech
    good = tmp_path / "good.flac"
    sf.write(good, x, sr)
    huge = tmp_path / "huge.flac"
    huge.write_bytes(flac_with_total_samples(good.read_bytes(), 2**36 - 1))
    with pytest.raises(InputError, match=r"over the limit of 3600 s; send a shorter file") as e:
        decode_audio(huge, ANALYSIS_RATE)
    assert "68719476735 samples" in str(e.value)
    unknown = tmp_path / "unknown.flac"  # 0 = "not known" in STREAMINFO
    unknown.write_bytes(flac_with_total_samples(good.read_bytes(), 0))
    with pytest.raises(InputError, match="does not say how many samples"):
        decode_audio(unknown, ANALYSIS_RATE)
    lying = tmp_path / "lying.flac"  # longer than the stream, under the limit
    lying.write_bytes(flac_with_total_samples(good.read_bytes(), 10 * len(x)))
    with pytest.raises(InputError, match="damaged or truncated|truncated"):
        decode_audio(lying, ANALYSIS_RATE)


def test_the_duration_limit_is_configurable(speech, tmp_path, monkeypatch):
    x, sr = speech  # 1.19 s
    p = tmp_path / "s.wav"
    sf.write(p, x, sr)
    monkeypatch.setenv("FACECAST_MAX_AUDIO_SECONDS", "1")
    with pytest.raises(InputError, match=r"lasts 1 s .* over the limit of 1 s"):
        lipsync_file(p)
    assert decode_audio(p, max_seconds=2).seconds == pytest.approx(len(x) / sr)
    monkeypatch.setenv("FACECAST_MAX_AUDIO_SECONDS", "lots")
    with pytest.raises(InputError, match="FACECAST_MAX_AUDIO_SECONDS"):
        decode_audio(p)


def test_truncated_and_lying_headers_are_refused(speech, tmp_path):
    x, sr = speech
    wav = tmp_path / "s.wav"
    sf.write(wav, x, sr, subtype="PCM_16")
    raw = wav.read_bytes()
    cases = {
        "cut.wav": (
            raw[: len(raw) // 2],
            "truncated: its header declares 1.19 s of audio, it holds 0.60 s",
        ),
        "nochannels.wav": (wav_field(raw, 10, "<H", 0), "cannot decode audio \\(.*[Cc]hannel"),
        "rate1.wav": (wav_field(raw, 12, "<I", 1), "sample rate 1 Hz is outside"),
        "rate2g.wav": (wav_field(raw, 12, "<I", 2**31 - 1), "sample rate 2147483647 Hz is outside"),
        "header.wav": (raw[:30], "cannot decode"),
    }
    flac = tmp_path / "s.flac"
    sf.write(flac, x, sr)
    cases["cut.flac"] = (
        flac.read_bytes()[: len(flac.read_bytes()) // 2],
        "damaged or truncated|truncated",
    )
    for name, (content, message) in cases.items():
        p = tmp_path / name
        p.write_bytes(content)
        with pytest.raises(InputError, match=message) as e:
            decode_audio(p, ANALYSIS_RATE)
        assert str(p) in str(e.value) and str(e.value).count(str(p)) == 1, (
            name
        )  # named once, by where


def test_many_channels_and_float_nan_samples(tmp_path):
    p = tmp_path / "nan.wav"
    sf.write(p, np.array([0.1, np.nan, 0.2, 0.0] * 100), 16000, subtype="FLOAT")
    with pytest.raises(InputError, match="NaN/inf samples \\(first at sample 1\\)"):
        decode_audio(p, ANALYSIS_RATE)
    p = tmp_path / "many.wav"
    sf.write(p, np.full((1600, 200), 0.25), 16000, subtype="PCM_16")  # 200 channels: averaged
    d = decode_audio(p, ANALYSIS_RATE)
    assert d.channels == 200 and len(d.x) == 1000
    np.testing.assert_allclose(d.x[100:-100], 0.25, atol=1e-3)


# ---- fuzz: mutated real files give a decode or the project's error, nothing else ----


def _seed_files(x: np.ndarray, sr: int) -> list[tuple[str, bytes]]:
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, data, subtype in (
            ("a.wav", x, "PCM_16"),
            ("b.wav", x, "FLOAT"),
            ("c.wav", np.stack([x, x], 1), "PCM_U8"),
            ("d.flac", x, "PCM_16"),
            ("e.flac", np.stack([x, -x], 1), "PCM_24"),
            ("f.ogg", x, None),
        ):
            p = Path(tmp) / name
            sf.write(p, data, sr, subtype=subtype)
            out.append((name, p.read_bytes()))
    return out


@pytest.fixture(scope="module")
def seed_files(speech):
    x, sr = speech
    return _seed_files(x[:3000], sr)


def mutate(
    data: bytes, edits: list[tuple[int, int]], cut: int | None, words: list[tuple[int, int]]
) -> bytes:
    b = bytearray(data)
    for pos, val in edits:
        b[pos % len(b)] = val
    for pos, word in words:  # 32-bit fields: sizes, rates, counts
        i = pos % max(1, len(b) - 4)
        b[i : i + 4] = word.to_bytes(4, "little")
    if cut is not None:
        b = b[: cut % (len(b) + 1)]
    return bytes(b)


@settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    which=st.integers(0, 5),
    edits=st.lists(st.tuples(st.integers(0, 60), st.integers(0, 255)), max_size=6),
    far=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=4),
    words=st.lists(
        st.tuples(
            st.integers(0, 80),
            st.sampled_from([0, 1, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF, 0x80000000, 44100]),
        ),
        max_size=2,
    ),
    cut=st.none() | st.integers(0, 10**6),
)
def test_fuzz_mutated_audio_decodes_or_raises_input_error(
    seed_files, which, edits, far, words, cut
):
    name, data = seed_files[which]
    blob = mutate(data, edits + far, cut, words)
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / name
        p.write_bytes(blob)
        try:
            d = decode_audio(p, ANALYSIS_RATE, max_seconds=60)
        except InputError:
            return
        assert (
            d.x.dtype == np.float32 and np.isfinite(d.x).all() and np.abs(d.x).max(initial=0) <= 1
        )
        assert d.seconds <= 60 and len(d.x) <= 60 * ANALYSIS_RATE * 1.001 + 1


def test_a_live_producers_big_chunk_does_not_swing_memory(rng):
    """A 1 Mi-sample PCM chunk swung the server's memory by 600 MB (the streaming resampler
    gathered outputs × taps at once); now it is computed in slices, with the same output."""
    from facecast.server.audio.io import StreamResampler
    from facecast.server.audio.live import AudioLiveDriver

    x = 0.1 * rng.standard_normal(1 << 20)
    rs = StreamResampler(16000, ANALYSIS_RATE)
    y = np.concatenate([rs.push(x[:1000]), rs.push(x[1000:])])
    np.testing.assert_allclose(y, resample(x, 16000, ANALYSIS_RATE)[: len(y)], atol=1e-12)
    assert len(y) > 0.99 * len(x) * 10 / 16
    drv = AudioLiveDriver(None, 16000)
    drv.push(x[:1000].astype(np.float32), 0.0)
    tracemalloc.start()
    try:
        drv.push(x[1000:].astype(np.float32), 1000 / 16000)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 150 * 2**20, f"peak {peak / 2**20:.0f} MiB for a {len(x)}-sample chunk"


def test_a_live_producers_odd_rate_builds_a_small_resampler():
    """A hello may declare any rate up to 384 kHz: 383993 Hz needed a 7.7M-tap filter (1.5 s and
    ~450 MB per resampler, built twice per producer); the live resampler uses the same bounded ratio
    as file decoding, so its filter stays small and its output rate within the tolerance."""
    from facecast.server.audio.io import MAX_RATIO_TERM, RATE_TOLERANCE, StreamResampler

    r = StreamResampler(383993, ANALYSIS_RATE)
    assert max(r.up, r.down) <= MAX_RATIO_TERM
    assert len(r.h) <= 20 * MAX_RATIO_TERM + 1
    assert abs(383993 * r.up / r.down / ANALYSIS_RATE - 1.0) <= RATE_TOLERANCE
    common = StreamResampler(44100, ANALYSIS_RATE)
    assert (common.up, common.down) == (100, 441)  # common rates stay exact


@pytest.mark.parametrize("rate", [16000, 44100, 48000])
def test_stream_resampler_reused_plans_give_the_batch_output(rng, rate):
    """The streaming resampler keeps the gather plans of recurring chunk shapes (live chunks):
    equal chunks, then chunks of varying length, still give ``resample``'s samples."""
    from facecast.server.audio.io import StreamResampler

    x = 0.1 * rng.standard_normal(rate)
    n = rate // 50  # 20 ms
    sizes = [n] * 20 + [7, 1, n, 3 * n + 5, n, n] * 3
    bounds = np.cumsum([0, *sizes])
    rs = StreamResampler(rate, ANALYSIS_RATE)
    y = np.concatenate([rs.push(x[a:b]) for a, b in itertools.pairwise(bounds)])
    want = resample(x[: bounds[-1]], rate, ANALYSIS_RATE)[: len(y)]
    np.testing.assert_allclose(y, want, atol=1e-12)
    assert len(y) > 0.9 * bounds[-1] * ANALYSIS_RATE / rate


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int16, np.uint8])
def test_validate_pcm_copies_clips_and_refuses_non_finite(dtype, rng):
    """``validate_pcm``: a fresh float64 array in [-1, 1] (never the caller's), unchanged below
    the clip level; loud floats are clipped; NaN, inf and -inf are refused wherever they are."""
    from facecast.server.audio.io import validate_pcm

    info = np.iinfo(dtype) if np.dtype(dtype).kind in "iu" else None
    x = (
        rng.integers(info.min, int(info.max) + 1, 500).astype(dtype)
        if info is not None
        else (rng.uniform(-0.9, 0.9, 500)).astype(dtype)
    )
    y = validate_pcm(x, 16000)
    assert y.dtype == np.float64 and not np.shares_memory(x, y)
    assert np.all(np.abs(y) <= 1.0)
    if info is None:
        np.testing.assert_array_equal(y, x.astype(np.float64))
        y[:] = 0  # the caller's samples are untouched
        assert np.any(x != 0)
        loud = x.astype(np.float64) * 3
        np.testing.assert_array_equal(validate_pcm(loud, 16000), np.clip(loud, -1, 1))
        for bad in (np.nan, np.inf, -np.inf):
            z = x.copy()
            z[123] = bad
            with pytest.raises(InputError, match="first at sample 123"):
                validate_pcm(z, 16000)
    assert validate_pcm(x[:0], 16000, allow_empty=True).shape == (0,)
    with pytest.raises(InputError, match="no audio samples"):
        validate_pcm(x[:0], 16000)
