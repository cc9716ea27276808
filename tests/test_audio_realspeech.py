"""Lip-sync on real speech: speaker-disjoint folds from the data, robustness to the recording
channel, the transcript path, calibration, and the cue / Rhubarb output formats."""

from __future__ import annotations

import json
import shutil
import sys
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
import scipy.signal
import soundfile as sf

from facecast.server.audio.io import read_audio
from facecast.server.audio.pipeline import lipsync
from facecast.server.cli import main
from facecast.server.errors import InputError

BENCH = Path(__file__).resolve().parents[1] / "bench" / "lipsync"
needs_espeak = pytest.mark.skipif(
    shutil.which("espeak-ng") is None,
    reason="espeak-ng is not installed (Debian package; CI has it)",
)


@pytest.fixture(scope="module")
def bobby(data_dir):
    return data_dir / "speech" / "bobby_16bit_16khz.wav"


@pytest.fixture(scope="module")
def bench_modules():
    sys.path.insert(0, str(BENCH))
    try:
        import corpus
        import folds

        yield corpus, folds
    finally:
        sys.path.remove(str(BENCH))


def test_folds_hold_out_every_real_speaker_once(data_dir, bench_modules):
    """Every recording of ../shared/data/real-speech has a speaker; every speaker (and bobby,
    mary) is held out in exactly one fold, so no fold scores a voice it trained on."""
    corpus, folds = bench_modules
    speakers = {
        corpus.speaker_of(f"{p.parent.name}/{p.stem}")
        for p in (data_dir / "real-speech").glob("*/*.txt")
    }
    held = [s for fold in folds.FOLDS for s in fold]
    assert len(held) == len(set(held))
    assert set(held) == speakers | {"bobby", "mary"}


def test_real_alignment_is_reproducible(data_dir, bench_modules, tmp_path):
    """The PocketSphinx alignment fixture of one recording, made twice from the data, is the
    same and covers its words with the classes the transcript implies."""
    pytest.importorskip("pocketsphinx")
    corpus, _ = bench_modules
    wav = data_dir / "real-speech" / "pocketsphinx-cards" / "001.wav"
    text = corpus.normalise_text((wav.with_suffix(".txt")).read_text())
    a, b = corpus.align(wav, text, real=True), corpus.align(wav, text, real=True)
    assert a == b
    names = [p for _, _, p in a if p != "SIL"]
    assert names[:3] == ["T", "EH", "N"]  # "ten of clubs"


def _classes(path_or_x, sr=None) -> np.ndarray:
    from facecast.server.audio.classify import CLASS_VISEMES

    if sr is None:
        path_or_x, sr = read_audio(path_or_x)
    ls = lipsync(path_or_x, sr)
    vis = ls.labels_at(ls.track.t)[0]
    inv = {int(v): i for i, v in enumerate(CLASS_VISEMES)}
    return np.array([inv[int(v)] for v in vis])


def test_level_rate_stereo_and_noise_variants_give_the_same_classes(bobby, tmp_path, rng):
    x, sr = read_audio(bobby)
    ref = _classes(x, sr)
    variants = {
        "quiet (-26 dB)": (0.05 * x, sr, 0.97),
        "loud (x3, peak < 1)": (np.clip(3 * x, -1, 1), sr, 0.97),
        "stereo": (np.stack([x, 0.8 * x], axis=1), sr, 0.97),
        "44.1 kHz": (scipy.signal.resample_poly(x, 441, 160), 44100, 0.95),
        # measured: 8 kHz (no band above 4 kHz: sibilants change) 0.76; white noise 30 dB under
        # the mean speech power (fills the pauses of this quiet recording) 0.58, 40 dB 0.75
        "8 kHz": (scipy.signal.resample_poly(x, 1, 2), 8000, 0.65),
        "noise 30 dB SNR": (x + rng.normal(0, np.sqrt(np.mean(x**2) / 1000), len(x)), sr, 0.5),
        "noise 40 dB SNR": (x + rng.normal(0, np.sqrt(np.mean(x**2) / 1e4), len(x)), sr, 0.65),
    }
    for name, (y, r, min_agree) in variants.items():
        got = _classes(y, r)
        n = min(len(got), len(ref))
        assert abs(len(got) - len(ref)) <= 1, name
        assert np.mean(got[:n] == ref[:n]) >= min_agree, (name, np.mean(got[:n] == ref[:n]))


@needs_espeak
def test_transcript_aligns_when_it_matches_and_is_refused_when_not(bobby, capsys):
    assert (
        main(["lipsync", str(bobby), "--text", "Bobby ripped the ledger.", "--format", "cues"]) == 0
    )
    cues = json.loads(capsys.readouterr().out)["cues"]
    names = [c["name"] for c in cues]
    assert names[0] == "sil" and "PP" in names and "aa" in names  # b-o-bby: lips close, jaw opens
    wrong = "seven of the children said that their shoes were wet through"
    assert main(["lipsync", str(bobby), "--text", wrong]) == 2
    err = capsys.readouterr().err
    assert "does not match the audio" in err and len(err.strip().splitlines()) == 1
    assert main(["lipsync", str(bobby), "--text", "   "]) == 2
    assert "empty" in capsys.readouterr().err


@needs_espeak
def test_transcript_far_too_short_for_the_audio_is_refused(data_dir, capsys):
    """A one-word transcript for seconds of speech would be spoken at under 4 phones per second
    of sound: refused, saying so, whatever the network makes of its few phones."""
    wav = (
        data_dir
        / "real-speech"
        / "pocketsphinx-librivox"
        / "sense_and_sensibility_01_austen_64kb-0870.wav"
    )
    assert main(["lipsync", str(wav), "--text", "no"]) == 2
    err = capsys.readouterr().err
    assert "does not match the audio" in err and "per second" in err, err


def test_rhubarb_json_and_tsv_are_well_formed(bobby, capsys, tmp_path):
    assert main(["lipsync", str(bobby), "--format", "rhubarb"]) == 0
    out = json.loads(capsys.readouterr().out)
    dur = sf.info(str(bobby)).duration
    assert out["metadata"] == {"soundFile": str(bobby), "duration": round(dur, 2)}
    cues = out["mouthCues"]
    assert cues[0]["start"] == 0 and cues[-1]["end"] == round(dur, 2)
    for a, b in pairwise(cues):
        assert a["end"] == b["start"] and a["value"] != b["value"]
    assert all(
        c["end"] > c["start"] and c["value"] in "ABCDEFGHX" and len(c["value"]) == 1 for c in cues
    )
    assert {"A", "X"} <= {c["value"] for c in cues}
    path = tmp_path / "cues.tsv"
    assert main(["lipsync", str(bobby), "--format", "rhubarb-tsv", "-o", str(path)]) == 0
    lines = path.read_text().splitlines()
    rows = [line.split("\t") for line in lines]
    assert all(len(r) == 2 for r in rows)
    assert [float(r[0]) for r in rows[:-1]] == [c["start"] for c in cues]
    assert [r[1] for r in rows[:-1]] == [c["value"] for c in cues]
    assert rows[-1] == [f"{round(dur, 2):.2f}", "X"]


def test_named_cue_segments_tile_the_track(bobby, capsys):
    assert main(["lipsync", str(bobby), "--format", "cues"]) == 0
    out = json.loads(capsys.readouterr().out)
    cues = out["cues"]
    assert cues[0]["start"] == 0
    assert all(a["end"] == pytest.approx(b["start"]) for a, b in pairwise(cues))
    assert set(cues[0]) == {"start", "end", "viseme", "name"}


def _formant_a(sr: int, dur: float) -> np.ndarray:
    n = int(sr * dur)
    x = np.zeros(n)
    x[np.arange(0, n, sr / 120).astype(int)] = 1.0
    for f, bw in ((730, 80), (1150, 90), (2600, 120)):
        r = np.exp(-np.pi * bw / sr)
        x = scipy.signal.lfilter([1 - r], [1, -2 * r * np.cos(2 * np.pi * f / sr), r * r], x)
    return x / np.abs(x).max()


def test_calibration_recording(bobby, tmp_path, capsys, rng):
    """The source's calibration: room noise, then a loud /a/; the loud /a/ sets intensity 1, so
    speech quieter than it gets lower weights than with the file's own calibration."""
    from facecast.server.audio.pipeline import calibration_from

    sr = 16000
    _x, _ = read_audio(bobby)
    noise = rng.normal(0, 1e-3, sr)
    cal_sig = np.concatenate([noise, 0.9 * _formant_a(sr, 1.0) + rng.normal(0, 1e-3, sr)])
    cal = calibration_from(cal_sig, sr)
    assert cal.max_db > cal.silence_db + 15
    p = tmp_path / "cal.wav"
    sf.write(p, cal_sig, sr)
    assert main(["lipsync", str(bobby), "--json"]) == 0
    auto = json.loads(capsys.readouterr().out)["frames"]
    assert main(["lipsync", str(bobby), "--json", "--calibrate", str(p)]) == 0
    calibrated = json.loads(capsys.readouterr().out)["frames"]
    speech = [i for i, f in enumerate(auto) if f["viseme"] >= 10]
    assert np.mean([calibrated[i]["weight"] for i in speech]) < np.mean(
        [auto[i]["weight"] for i in speech]
    )
    flat = tmp_path / "flat.wav"
    sf.write(flat, noise, sr)
    with pytest.raises(InputError, match="loud sustained /a/"):
        calibration_from(noise, sr)
    assert main(["lipsync", str(bobby), "--calibrate", str(flat)]) == 2
    assert "loud sustained /a/" in capsys.readouterr().err


def test_output_file_errors_are_reported_not_raised(bobby, tmp_path, capsys):
    missing = tmp_path / "no" / "such" / "dir" / "cues.json"
    assert main(["lipsync", str(bobby), "--format", "cues", "-o", str(missing)]) == 2
    err = capsys.readouterr().err
    assert "cannot write the output" in err and str(missing) in err
    assert not missing.parent.exists()
    assert main(["lipsync", str(bobby), "--json", "--format", "rhubarb"]) == 2
    assert "--json contradicts" in capsys.readouterr().err


def test_speed_copy_stretches_the_classes_with_the_audio(bench_modules, rng):
    """The training set's speed-changed copy (``frames.speed_copy``) reads the audio ``factor``
    times slower: its frame classes follow, each run ``factor`` times longer, in order."""
    sys.path.insert(0, str(BENCH))
    try:
        import frames
    finally:
        sys.path.remove(str(BENCH))
    sr = 16000
    truth = np.repeat(np.arange(10), 20)  # 2 s, ten classes of 200 ms
    x = 0.1 * rng.standard_normal(2 * sr)
    for factor in (0.9, 1.1):
        F, t = frames.speed_copy(x, sr, truth, factor, rng)
        assert len(F) == len(t) == pytest.approx(200 * factor, abs=2)
        assert np.all(np.diff(t) >= 0) and set(t) == set(range(10))
        assert np.abs(np.bincount(t)[1:-1] - 20 * factor).max() <= 1


def test_live_calibrated_training_features_are_what_the_live_driver_computes(
    bench_modules, bobby, monkeypatch
):
    """``frames.live_calibrated`` (the training copies' calibration columns) equals the live
    driver's own: the running calibration of the stream's frame energies, frame by frame."""
    from facecast.server.audio.classify import CALIBRATION_COLUMNS, calibration_columns
    from facecast.server.audio.live import AudioLiveDriver, RunningCalibration

    sys.path.insert(0, str(BENCH))
    try:
        import frames
    finally:
        sys.path.remove(str(BENCH))
    x, sr = read_audio(bobby)
    F, e = frames.utterance_features(x, sr)
    drv = AudioLiveDriver(None, sr, fps=100.0)
    seen: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    update = RunningCalibration.update

    def spy(self, energy_db):
        sil, mx = update(self, energy_db)
        seen.append((np.asarray(energy_db), sil, mx))
        return sil, mx

    monkeypatch.setattr(RunningCalibration, "update", spy)
    for i in range(0, len(x), 320):
        drv.push(x[i : i + 320].astype(np.float32), i / sr)
    drv.flush()
    e_live, sil, mx = (np.concatenate(v) for v in zip(*seen))
    assert len(e_live) == len(e)
    live = np.stack(calibration_columns(e_live, sil, mx), axis=1)
    got = frames.live_calibrated(F, e)
    np.testing.assert_allclose(got[:, CALIBRATION_COLUMNS], live, atol=0.02)
    other = np.ones(F.shape[1], dtype=bool)
    other[CALIBRATION_COLUMNS] = False
    np.testing.assert_array_equal(got[:, other], F[:, other])
    assert not np.allclose(got, F)  # the first frames' levels differ from the whole file's
