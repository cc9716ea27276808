"""The live driver: same frames as the batch pipeline within its look-ahead, media time, latency
and damaged streams (NaN chunks, late, duplicated and missing chunks)."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.server.audio.io import read_audio
from facecast.server.audio.live import AudioLiveDriver
from facecast.server.audio.pipeline import lipsync
from facecast.server.errors import InputError


@pytest.fixture(scope="module")
def speech(data_dir):
    return read_audio(data_dir / "speech" / "bobby_16bit_16khz.wav")


def stream(drv, x, sr, rng=None, chunk=320, t0=0.0):
    states, i = [], 0
    while i < len(x):
        n = int(rng.integers(1, 900)) if rng is not None else chunk
        states += drv.push(x[i : i + n].astype(np.float32), t0 + i / sr)
        i += n
    return states + drv.flush()


@pytest.mark.parametrize(("lookahead", "fps"), [(0.05, 100.0), (0.12, 30.0)])
def test_live_equals_batch_with_the_same_lookahead(speech, rng, lookahead, fps):
    x, sr = speech
    cal = lipsync(x, sr).calibration
    drv = AudioLiveDriver(None, sr, lookahead=lookahead, fps=fps, calibration=cal)
    states = stream(drv, x, sr, rng)
    ref = lipsync(
        x.astype(np.float32), sr, fps=fps, lookahead=drv.coart_lookahead, calibration=cal
    ).track
    assert len(states) == len(ref.t)
    np.testing.assert_allclose([s.t for s in states], ref.t, atol=1e-9)
    # the stream resampler's flush and the batch resampler end the signal slightly differently
    # (io.py): the last analysis frame differs at about -68 dB; states it can reach are exempt
    net = drv.net
    reach = (net.future + drv.med_half + 2) * drv.hop + drv.coart_lookahead
    n = int(np.sum(ref.t < len(x) / sr - reach))
    assert n > 0.5 * len(ref.t)
    np.testing.assert_allclose(np.array([s.faps for s in states])[:n], ref.faps[:n], atol=1e-6)
    assert all(s.viseme is None for s in states)
    drv = AudioLiveDriver(None, sr, lookahead=lookahead, fps=fps, calibration=cal, fap1=True)
    states = stream(drv, x, sr, rng)
    assert [s.viseme[0] for s in states][:n] == ref.select1[:n].tolist()
    assert [s.viseme[1] for s in states][:n] == ref.select2[:n].tolist()


def test_longer_lookahead_approaches_free_batch(speech):
    x, sr = speech
    free = lipsync(x, sr).track
    agree = []
    for la in (0.04, 0.3):
        drv = AudioLiveDriver(
            None, sr, lookahead=la, fps=100, calibration=lipsync(x, sr).calibration, fap1=True
        )
        vis = np.array([s.viseme[0] for s in stream(drv, x, sr)])
        agree.append(np.mean(vis == free.select1))
    assert agree[1] >= agree[0] and agree[1] > 0.9


def test_default_latency_budget_and_states_wait_for_their_audio(speech):
    x, sr = speech
    drv = AudioLiveDriver(None, sr)  # default look-ahead
    assert drv.latency <= 0.06
    got_after = []
    for i in range(0, len(x), 16):  # 1 ms chunks
        end = min(len(x), i + 16) / sr
        got_after += [end - s.t for s in drv.push(x[i : i + 16], i / sr)]
    lat = np.array(got_after)
    assert lat.min() >= drv.latency - 1e-9  # never emitted before its audio arrived
    assert lat.max() <= drv.latency + 16 / sr + 1e-9  # and not held longer than needed


def test_states_carry_the_audio_media_time(speech):
    x, sr = speech
    drv = AudioLiveDriver(None, sr, fps=50)
    states = stream(drv, x, sr, t0=12.5)
    t = np.array([s.t for s in states])
    assert t[0] == pytest.approx(12.5)
    np.testing.assert_allclose(np.diff(t), 0.02, atol=1e-9)


def test_running_calibration_finds_silence_and_speech(speech):
    x, sr = speech
    drv = AudioLiveDriver(None, sr, fps=100, fap1=True)
    vis = np.array([s.viseme[0] for s in stream(drv, x, sr)])
    assert vis[0] == 0 and np.mean(vis[10:100] != 0) > 0.8
    assert {10, 11, 12, 13, 14} & set(vis.tolist())


def test_nan_chunk_is_refused_and_the_driver_survives(speech):
    x, sr = speech
    drv = AudioLiveDriver(None, sr, fps=100)
    first = drv.push(x[:3200], 0.0)
    bad = x[3200:3520].astype(np.float32).copy()
    bad[5] = np.nan
    with pytest.raises(InputError, match="NaN") as e:
        drv.push(bad, 0.2)
    assert "t=0.200" in str(e.value)
    rest = drv.push(x[3520:], 0.22) + drv.flush()  # the lost 20 ms are filled with silence
    t = np.array([s.t for s in first + rest])
    np.testing.assert_allclose(t, np.arange(len(t)) / 100, atol=1e-9)
    assert len(t) == int(len(x) / sr * 100) + 1


def test_late_duplicate_and_overlapping_chunks(speech, caplog):
    x, sr = speech
    drv = AudioLiveDriver(None, sr, fps=100)
    states = drv.push(x[:4800], 0.0)
    assert drv.push(x[1600:3200], 0.1) == []  # entirely old: dropped
    assert drv.dropped_chunks == 1
    states += drv.push(x[4000:8000], 0.25)  # overlaps 50 ms: trimmed
    states += drv.push(x[8000:], 0.5) + drv.flush()
    t = np.array([s.t for s in states])
    assert np.all(np.diff(t) > 0)
    np.testing.assert_allclose(t, np.arange(len(t)) / 100, atol=1e-9)
    assert "dropped" in caplog.text and "trimmed" in caplog.text


def test_long_gap_restarts_the_stream(speech):
    x, sr = speech
    drv = AudioLiveDriver(None, sr, fps=100)
    a = drv.push(x[:8000], 0.0)
    b = drv.push(x[8000:], 10.0) + drv.flush()
    t = np.array([s.t for s in a + b])
    assert np.all(np.diff(t) > 0) and t[-1] > 10.0 and t[len(a)] <= 0.5 + 1e-9


def test_int16_and_stereo_chunks_are_accepted(speech):
    x, sr = speech
    drv = AudioLiveDriver(None, sr, fps=100)
    pcm = (x[:3200] * 32767).astype(np.int16)
    drv.push(np.stack([pcm, pcm], axis=1), 0.0)
    with pytest.raises(InputError):
        drv.push(np.zeros((2, 2, 2)), 0.2)
    with pytest.raises(InputError):
        AudioLiveDriver(None, 100)  # rate out of range


def test_clipping_stream_warns_once(speech, caplog):
    x, sr = speech
    drv = AudioLiveDriver(None, sr, fps=100)
    loud = np.clip(x * 30, -1, 1).astype(np.float32)
    for i in range(0, len(loud), 1600):
        drv.push(loud[i : i + 1600], i / sr)
    assert caplog.text.count("clipping") == 1


def test_running_calibration_on_quiet_speech(speech):
    x, sr = speech  # peaks at -26 dB full scale; scaled to -46 dB
    drv = AudioLiveDriver(None, sr, fps=100, fap1=True)
    vis = np.array([s.viseme[0] for s in stream(drv, x * 0.1, sr)])
    assert np.mean(np.isin(vis[10:100], [10, 11, 12, 13, 14])) > 0.3


def test_median_of_three_fast_path_equals_scipy(rng):
    """``median_filter_proba``'s default length (3) is computed without scipy; it is exactly
    scipy's running median (edges repeated), on short and long inputs."""
    import scipy.ndimage

    from facecast.server.audio.visemes import median_filter_proba

    for n in (1, 2, 3, 50):
        p = rng.random((n, 10))
        np.testing.assert_array_equal(
            median_filter_proba(p, 3), scipy.ndimage.median_filter(p, size=(3, 1), mode="nearest")
        )
