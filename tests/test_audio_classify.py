"""The shipped 12-10-5 vowel network on vowels it never heard: a formant synthesiser written here
(pulse train through second-order resonators at textbook formant frequencies), two speakers."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from facecast.server.audio.classify import VOWELS, WEIGHTS, VowelNet, default_net
from facecast.server.audio.pipeline import features_of

#: F1-F3 (Hz) of /a e i o u/ for an adult male (Spanish-like five-vowel system).
FORMANTS = {
    "a": (730, 1150, 2600),
    "e": (470, 1850, 2500),
    "i": (290, 2250, 2950),
    "o": (480, 850, 2450),
    "u": (310, 750, 2300),
}


def formant_vowel(
    v: str, *, sr: int = 16000, f0: float = 110.0, scale: float = 1.0, dur: float = 0.5
) -> np.ndarray:
    n = int(sr * dur)
    x = np.zeros(n)
    x[np.arange(0, n, sr / f0).astype(int)] = 1.0
    x = scipy.signal.lfilter([1.0], [1.0, -0.97], x)  # glottal spectral roll-off
    for f, bw in zip([f * scale for f in FORMANTS[v]] + [3500 * scale], (80, 90, 120, 150)):
        r = np.exp(-np.pi * bw / sr)
        x = scipy.signal.lfilter([1 - r], [1, -2 * r * np.cos(2 * np.pi * f / sr), r * r], x)
    return 0.5 * x / np.abs(x).max()


def test_weights_ship_with_the_package():
    assert WEIGHTS.is_file()
    net = VowelNet.load(WEIGHTS)
    assert net.w1.shape == (12, 10) and net.w2.shape == (10, 5)


@pytest.mark.parametrize(("f0", "scale"), [(110.0, 1.0), (210.0, 1.15)], ids=["male", "female"])
def test_network_classifies_synthetic_vowels(f0, scale):
    """Majority vote per vowel: at least 4 of 5 exact; the source's own confusions (e/i, o/u,
    pairs that also look alike on the mouth) are the only ones tolerated."""
    net = default_net()
    partner = {"a": "a", "e": "i", "i": "e", "o": "u", "u": "o"}
    exact = 0
    for _i, v in enumerate(VOWELS):
        f = features_of(formant_vowel(v, f0=f0, scale=scale), 16000)
        k = f.k[5:-5]
        np.testing.assert_allclose(net.proba(k).sum(1), 1.0)
        votes = np.bincount(net.predict(k), minlength=5)
        got = VOWELS[int(np.argmax(votes))]
        assert got in (v, partner[v]), f"/{v}/ classified as {dict(zip(VOWELS, votes.tolist()))}"
        exact += got == v
    assert exact >= 4


def test_missing_weights_say_how_to_train(tmp_path):
    from facecast.server.errors import FacecastError

    with pytest.raises(FacecastError, match="facecast.server.audio.train"):
        VowelNet.load(tmp_path / "none.npz")


def test_missing_frame_weights_name_the_real_ship_command(tmp_path):
    """The frame network's missing-weights message names a command that exists in the repo."""
    from pathlib import Path

    from facecast.server.audio.classify import FrameNet
    from facecast.server.errors import FacecastError

    with pytest.raises(FacecastError, match="run 'python bench/lipsync/frames.py ship'"):
        FrameNet.load(tmp_path / "none.npz")
    assert (Path(__file__).resolve().parents[1] / "bench" / "lipsync" / "frames.py").is_file()


@pytest.mark.slow
def test_training_command_is_reproducible(tmp_path):
    import shutil

    from facecast.server.audio import train

    if shutil.which("espeak-ng") is None:
        pytest.skip("espeak-ng is not installed (Debian package; CI has it)")
    outs = []
    for i in range(2):
        out = tmp_path / f"net{i}.npz"
        assert (
            train.main(["--per-vowel", "3", "--epochs", "3", "--seed", "7", "--out", str(out)]) == 0
        )
        outs.append(VowelNet.load(out))
    np.testing.assert_array_equal(outs[0].w1, outs[1].w1)
    np.testing.assert_array_equal(outs[0].w2, outs[1].w2)
    assert outs[0].w1.shape == (12, 10)


def test_merged_frame_networks_give_the_members_geometric_mean():
    """``merge_frame_nets``: one wider network whose output is the members' normalised product
    (what ``bench/lipsync/frames.py`` ships), and members with other inputs are refused."""
    from facecast.server.audio.train import fit_frames, merge_frame_nets

    rng = np.random.default_rng(0)
    X = rng.normal(size=(400, 6)).astype(np.float32)
    y = rng.integers(0, 10, 400)
    offsets = np.array([-1, 0, 1])
    nets = [fit_frames(X, y, offsets, hidden=5, epochs=2, seed=s) for s in range(3)]
    merged = merge_frame_nets(nets)
    assert merged.w1.shape == (6, 15) and merged.w2.shape == (15, 10)
    logp = np.mean([np.log(n.proba_stacked(X)) for n in nets], axis=0)
    expect = np.exp(logp) / np.exp(logp).sum(axis=1, keepdims=True)
    np.testing.assert_allclose(merged.proba_stacked(X), expect, atol=1e-5)
    other = fit_frames(X + 1, y, offsets, hidden=5, epochs=1)
    with pytest.raises(ValueError, match="share their inputs"):
        merge_frame_nets([nets[0], other])
    for n in nets:  # the speaker normalisation is an input too: kept, and must agree
        n.norm_mean = np.ones(40)
    np.testing.assert_array_equal(merge_frame_nets(nets).norm_mean, np.ones(40))
    nets[1].norm_mean = np.zeros(40)
    with pytest.raises(ValueError, match="share their inputs"):
        merge_frame_nets(nets)


def test_frame_network_dropout_is_reproducible_and_trains():
    """``fit_frames(dropout=...)`` (the shipped recipe's): the same seed gives the same weights,
    the weights differ from training without it, and the network still learns a separable task;
    without it no random numbers are drawn for it (the weights are as before it existed)."""
    from facecast.server.audio.train import fit_frames

    rng = np.random.default_rng(1)
    X = rng.normal(size=(600, 6)).astype(np.float32)
    y = (X[:, 0] > 0).astype(np.int64) + 2 * (X[:, 1] > 0)
    offsets = np.array([0])
    kw = {"hidden": 8, "epochs": 20, "batch": 32, "lr": 1e-2, "seed": 4}
    a, b = (fit_frames(X, y, offsets, dropout=0.3, **kw) for _ in range(2))
    plain = fit_frames(X, y, offsets, **kw)
    zero = fit_frames(X, y, offsets, dropout=0.0, **kw)
    np.testing.assert_array_equal(a.w1, b.w1)
    np.testing.assert_array_equal(a.w2, b.w2)
    np.testing.assert_array_equal(plain.w1, zero.w1)
    assert not np.array_equal(a.w1, plain.w1)
    assert np.mean(np.argmax(a.proba_stacked(X), 1) == y) > 0.9


def _feature_rows(rng: np.random.Generator, n: int) -> np.ndarray:
    """``(n, 44)`` random frame-feature rows, about half of them speech (column 26 > 0)."""
    F = rng.normal(size=(n, 44)) + 3.0
    F[:, 26] = rng.normal(size=n)
    return F


def test_speaker_norm_is_causal_and_the_same_in_any_chunks():
    """``SpeakerNorm`` (the frame network's per-speaker normalisation): the live path's chunks of
    any size give the rows the whole file gives (loop and filter paths alike); a row depends on
    no later row; silent frames do not move the mean; the spectral columns of a steady speaker
    end near 0 (its own mean taken out) and the other columns are untouched."""
    from facecast.server.audio.classify import SPECTRAL_COLUMNS, SpeakerNorm

    rng = np.random.default_rng(2)
    F = _feature_rows(rng, 700)
    mean = rng.normal(size=40)
    whole = SpeakerNorm(mean)(F)
    for size in (1, 2, 4, 5, 37, 4096):
        norm = SpeakerNorm(mean)
        chunked = np.concatenate([norm(F[i : i + size]) for i in range(0, len(F), size)])
        np.testing.assert_allclose(chunked, whole, atol=1e-12)
    np.testing.assert_allclose(SpeakerNorm(mean)(F[:300]), whole[:300], atol=1e-12)
    other = np.setdiff1d(np.arange(44), SPECTRAL_COLUMNS)
    np.testing.assert_array_equal(whole[:, other], F[:, other])
    silent = F.copy()
    silent[:, 26] = -1.0
    np.testing.assert_allclose(
        SpeakerNorm(mean)(silent)[:, SPECTRAL_COLUMNS], F[:, SPECTRAL_COLUMNS] - mean
    )
    steady = np.tile(F[:1], (3000, 1))
    steady[:, 26] = 1.0
    assert np.abs(SpeakerNorm(mean)(steady)[-1, SPECTRAL_COLUMNS]).max() < 1e-3


def test_frame_network_speaker_norm_is_saved_and_applied(tmp_path):
    """A ``FrameNet`` with ``norm_mean`` keeps it through save/load and reads its inputs through a
    fresh ``SpeakerNorm`` per utterance; one without reads them as they come."""
    from facecast.server.audio.classify import FrameNet, SpeakerNorm, stack_context
    from facecast.server.audio.train import fit_frames

    rng = np.random.default_rng(3)
    F = _feature_rows(rng, 300)
    offsets = np.array([-1, 0, 1])
    X = stack_context(F, offsets)
    net = fit_frames(X, rng.integers(0, 10, len(X)), offsets, hidden=5, epochs=1)
    plain = net.proba(F)
    np.testing.assert_allclose(plain, net.proba_stacked(X), atol=1e-6)
    net.save(tmp_path / "plain.npz")
    assert FrameNet.load(tmp_path / "plain.npz").norm_mean is None
    net.norm_mean = rng.normal(size=40)
    net.save(tmp_path / "norm.npz")
    loaded = FrameNet.load(tmp_path / "norm.npz")
    np.testing.assert_array_equal(loaded.norm_mean, net.norm_mean)
    expect = net.proba_stacked(stack_context(SpeakerNorm(net.norm_mean)(F), offsets))
    np.testing.assert_allclose(loaded.proba(F), expect, atol=1e-6)
    np.testing.assert_allclose(loaded.proba(F), loaded.proba(F))  # no state left behind
    assert not np.allclose(loaded.proba(F), plain, atol=1e-3)
