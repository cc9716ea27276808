"""Audio files → visemes and FAPs: the lipsync CLI on real speech, the render driver, bad input."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import soundfile as sf

from facecast.server.audio.driver import load
from facecast.server.audio.io import read_audio
from facecast.server.cli import main
from facecast.server.drivers import load_animation
from facecast.server.errors import InputError

VOWEL_VISEMES = {10, 11, 12, 13, 14}


@pytest.fixture(scope="module")
def bobby(data_dir):
    return data_dir / "speech" / "bobby_16bit_16khz.wav"


def lipsync_json(capsys, *args) -> dict:
    assert main(["lipsync", *map(str, args), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_lipsync_json_on_real_speech(bobby, capsys):
    out = lipsync_json(capsys, bobby)
    info = sf.info(str(bobby))
    assert out["fps"] == 100
    frames = out["frames"]
    assert len(frames) == int(info.frames / info.samplerate * 100) + 1
    assert set(frames[0]) == {"t", "viseme", "weight"}
    t = np.array([f["t"] for f in frames])
    np.testing.assert_allclose(t, np.arange(len(t)) / 100, atol=1e-6)
    vis = np.array([f["viseme"] for f in frames])
    w = np.array([f["weight"] for f in frames])
    assert vis.min() >= 0 and vis.max() <= 14 and w.min() >= 0 and w.max() <= 1
    # "Bobby ripped the ledger": silence before the first word (phones start at 65 ms), the
    # first /b/ closes the lips, vowels follow, and the voiced middle is not silent.
    assert vis[0] == 0 and w[0] == 0
    assert VOWEL_VISEMES & set(vis[10:40].tolist())
    assert np.mean(vis[10:100] != 0) > 0.9 and w[10:100].mean() > 0.3


def test_lipsync_fps_option(bobby, capsys):
    out = lipsync_json(capsys, bobby, "--fps", "25")
    assert out["fps"] == 25 and abs(out["frames"][1]["t"] - 0.04) < 1e-9


def test_driver_gives_animation_with_jaw_and_lip_faps(bobby):
    anim = load(bobby, None, fps=25)
    assert anim.fps == 25 and anim.source == str(bobby)
    assert anim.states[3].t == pytest.approx(0.12)
    faps = np.array([s.faps for s in anim.states])
    assert faps.shape[1] == 69
    assert faps[:, 3].max() > 100  # open_jaw in MNS units
    assert faps[:, 5].min() < -50  # lower lip goes down with the jaw
    assert np.all(faps[:, 19:39] == 0)  # eyes and brows untouched
    assert all(s.viseme is None for s in anim.states)  # FAP 1 would add the mouth a second time
    # only 20 ms of silence before the /b/ voice bar: the jaw starts nearly closed and opens
    # widest in the first vowel (AA of "Bobby", 84-233 ms)
    assert faps[0, 3] < 0.5 * faps[:, 3].max()
    assert 0.08 <= anim.states[int(np.argmax(faps[:, 3]))].t <= 0.24


def test_driver_fap1_mode_and_the_faces_own_viseme_shapes(bobby):
    from types import SimpleNamespace

    from facecast.server.mpeg4 import VISEMES

    anim = load(bobby, None, fps=25, fap1=True)
    for s in anim.states:
        s1, s2, blend = s.viseme
        assert 0 <= s1 <= 14 and 0 <= s2 <= 14 and 0 <= blend <= 63 and not s.faps.any()
    # 20 ms of silence, then the /b/: the lips are closed at t=0 either way (silence, or the
    # closure's strong dominance reaching 20 ms ahead of it)
    assert anim.states[0].viseme[0] in (0, 1)
    assert {s.viseme[0] for s in anim.states} & VOWEL_VISEMES
    # a face with its own (here: doubled) viseme table gets doubled FAPs
    ref = np.array([s.faps for s in load(bobby, None, fps=25).states])
    face = SimpleNamespace(visemes=VISEMES * 2)
    np.testing.assert_allclose(
        np.array([s.faps for s in load(bobby, face, fps=25).states]), 2 * ref, atol=1e-9
    )


def test_render_dispatch_reaches_the_audio_driver(bobby):
    anim = load_animation(bobby, None, fps=50)
    assert len(anim) == int(sf.info(str(bobby)).duration * 50) + 1


def test_stereo_8bit_and_other_rates_give_the_same_track(bobby, tmp_path, capsys):
    x, sr = read_audio(bobby)
    ref = np.array([f["viseme"] for f in lipsync_json(capsys, bobby)["frames"]])
    stereo = tmp_path / "stereo.wav"
    sf.write(stereo, np.stack([x, x], axis=1), sr, subtype="PCM_16")
    u8 = tmp_path / "u8.wav"
    sf.write(u8, x, sr, subtype="PCM_U8")
    import scipy.signal

    hi = tmp_path / "44k.flac"
    sf.write(hi, scipy.signal.resample_poly(x, 441, 160), 44100, subtype="PCM_24")
    y, _ = read_audio(u8)  # offset-binary 8 bit decodes to the same waveform (±1 LSB)
    assert np.abs(y - x).max() <= 1.01 / 128
    # 8-bit quantisation noise sits only ~24 dB under this quiet recording's peaks, which moves
    # the silence threshold; the track is rougher but still speech
    for path, min_agree in ((stereo, 0.99), (u8, 0.5), (hi, 0.85)):
        vis = np.array([f["viseme"] for f in lipsync_json(capsys, path)["frames"]])
        n = min(len(vis), len(ref))
        assert abs(len(vis) - len(ref)) <= 1
        assert np.mean(vis[:n] == ref[:n]) >= min_agree, path.name


def test_silence_only_is_all_rest(tmp_path, capsys):
    p = tmp_path / "silence.wav"
    sf.write(p, np.zeros(8000), 8000)
    frames = lipsync_json(capsys, p)["frames"]
    assert len(frames) == 101
    assert all(f["viseme"] == 0 and f["weight"] == 0 for f in frames)


def test_low_noise_only_is_all_rest(tmp_path, capsys, rng):
    p = tmp_path / "noise.wav"
    sf.write(p, rng.normal(0, 1e-4, 16000), 16000)
    frames = lipsync_json(capsys, p)["frames"]
    assert all(f["viseme"] == 0 for f in frames)


def test_clipped_speech_still_works_and_warns(bobby, tmp_path, capsys, caplog):
    x, sr = read_audio(bobby)
    p = tmp_path / "clipped.wav"
    sf.write(p, np.clip(x * 20, -1, 1), sr)
    with caplog.at_level(logging.WARNING):
        frames = lipsync_json(capsys, p)["frames"]
    assert "clipped" in caplog.text
    assert VOWEL_VISEMES & {f["viseme"] for f in frames}


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("corrupt.wav", b"RIFF\x10\x00\x00\x00WAVEfmt garbage" * 3, "cannot decode"),
        ("empty.wav", b"", "cannot decode"),
        ("speech.mp3", b"ID3", "unsupported audio type"),
    ],
)
def test_bad_files_are_refused_with_the_file_named(tmp_path, capsys, name, content, message):
    p = tmp_path / name
    p.write_bytes(content)
    with pytest.raises(InputError, match=message) as e:
        load(p, None)
    assert str(p) in str(e.value)
    assert main(["lipsync", str(p), "--json"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("facecast: ") and str(p) in err and len(err.strip().splitlines()) == 1


def test_missing_file_and_zero_length_audio(tmp_path):
    with pytest.raises(InputError, match="no such audio file"):
        load(tmp_path / "nope.wav", None)
    p = tmp_path / "zero.wav"
    sf.write(p, np.zeros(0), 16000)
    with pytest.raises(InputError, match="no audio samples"):
        load(p, None)


def test_explicit_calibration_options(bobby, capsys):
    auto = lipsync_json(capsys, bobby)["frames"]
    loud = lipsync_json(capsys, bobby, "--max-db", "-6")["frames"]  # a much louder reference

    def voiced_weight(frames):  # vowels and weak consonants: intensity from energy
        return np.mean([f["weight"] for f in frames if f["viseme"] in VOWEL_VISEMES | {8}])

    assert voiced_weight(loud) < 0.8 * voiced_weight(auto)
    assert main(["lipsync", str(bobby), "--silence-db", "-20", "--max-db", "-30"]) == 2
    assert "--max-db" in capsys.readouterr().err
