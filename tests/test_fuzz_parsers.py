"""Fuzzing every parser of client files with hypothesis over mutated real and generated files: the
only outcomes allowed are a parse or the project's own error (a 4xx), never another exception.

Seeds: takes written by facecast's C3D writer (Intel, DEC, MIPS; float and int16) and by ezc3d (with
analog channels), TRC and CSV takes, the Xface .fap files, the shipped ICT FaceKit annotation.
Longer runs with crash and hang detection: ``python bench/fuzz_parsers.py``.
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_c3d import _ezc3d_write

from facecast.protocol.fap_file import FapFormatError, read_fap
from facecast.protocol.markers_file import (
    MarkerFileError,
    MarkerTake,
    read_take,
    write_c3d,
    write_csv,
    write_trc,
)
from facecast.server.errors import InputError
from facecast.server.faces.ict import ANNOTATION
from facecast.server.faces.loaders import face_from_annotation, parse_annotation

FUZZ = settings(
    max_examples=150,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def _bench_fuzz():
    """bench/fuzz_parsers.py, the one home of the interesting tokens both fuzzers draw."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "bench_fuzz_parsers", Path(__file__).parents[1] / "bench" / "fuzz_parsers.py"
    )
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_BENCH = _bench_fuzz()
#: Stands for an integer of 4,301 digits (json.dumps cannot write one; json.loads refuses it).
HUGE_INT = _BENCH.HUGE_INT
TOKENS = list(_BENCH.INTERESTING_TOKENS)


def _take() -> MarkerTake:
    xyz = np.random.default_rng(3).normal(size=(6, 3, 3)) * 40.0 + [0.0, 1600.0, 0.0]
    xyz[2, 1] = np.nan
    return MarkerTake(["CHIN", "LIP_L", "HEAD 1"], xyz, 120.0, "mm")


def _ezc3d_seed(take: MarkerTake, tmp_path_factory) -> list[bytes]:
    """The take as ezc3d writes it, with analog channels (none without ezc3d)."""
    try:
        import ezc3d  # noqa: F401
    except ImportError:
        return []
    path = tmp_path_factory.mktemp("ez") / "ez.c3d"
    _ezc3d_write(take, path, analog_channels=2)
    return [path.read_bytes()]


@st.composite
def mutated(draw, seeds: list[bytes], text: bool = False) -> bytes:
    """A seed with 1-4 mutations: bits, bytes, 16/32-bit words, insertions, deletions, cuts, repeats,
    and for text a replaced token."""
    b = bytearray(draw(st.sampled_from(seeds)))
    for _ in range(draw(st.integers(1, 4))):
        n = len(b)
        pos = draw(st.integers(0, max(n - 1, 0)))
        op = draw(
            st.sampled_from(
                ["flip", "byte", "word", "insert", "delete", "cut", "repeat"]
                + (["token"] * 3 if text else [])
            )
        )
        if op == "flip" and n:
            b[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "byte" and n:
            b[pos] = draw(st.sampled_from([0, 1, 0x7F, 0x80, 0xFF]) | st.integers(0, 255))
        elif op == "word" and n >= 4:
            size = draw(st.sampled_from([2, 4]))
            fmt = draw(st.sampled_from("<>")) + ("h" if size == 2 else "i")
            lo, hi = (-(2 ** (8 * size - 1)), 2 ** (8 * size - 1) - 1)
            v = draw(st.sampled_from([0, -1, 1, lo, hi, 255, 512]) | st.integers(lo, hi))
            pos = min(pos - pos % 2, n - size)
            b[pos : pos + size] = struct.pack(fmt, v)
        elif op == "insert":
            b[pos:pos] = draw(st.binary(min_size=1, max_size=16))
        elif op == "delete" and n:
            del b[pos : pos + draw(st.integers(1, 64))]
        elif op == "cut":
            del b[pos:]
        elif op == "repeat" and n:
            b[pos:pos] = b[pos : pos + draw(st.integers(1, 256))] * draw(st.integers(1, 4))
        elif op == "token":
            lines = bytes(b).split(b"\n")
            i = draw(st.integers(0, len(lines) - 1))
            sep = b"\t" if b"\t" in lines[i] else b"," if b"," in lines[i] else b" "
            cells = lines[i].split(sep)
            j = draw(st.integers(0, len(cells) - 1))
            cells[j] = draw(st.sampled_from(TOKENS) | st.text(max_size=8)).encode("utf-8")
            lines[i] = sep.join(cells)
            b = bytearray(b"\n".join(lines))
    return bytes(b)


def _check_take(take: MarkerTake) -> None:
    assert take.xyz.shape == (take.n_frames, len(take.names), 3) and take.n_frames > 0
    assert not np.isinf(take.xyz).any() and np.isfinite(take.fps) and take.fps > 0


@pytest.fixture(scope="module")
def c3d_seeds(tmp_path_factory) -> list[bytes]:
    take = _take()
    return [
        write_c3d(take),
        write_c3d(take, processor="dec", scale=0.1),
        write_c3d(take, processor="mips", scale=-0.5),
        *_ezc3d_seed(take, tmp_path_factory),
    ]


def test_c3d_fuzz(c3d_seeds):
    @FUZZ
    @given(mutated(c3d_seeds))
    def check(data):
        try:
            _check_take(read_take(data, ".c3d", where="f.c3d"))  # the one reading path
        except MarkerFileError:
            pass

    check()


@pytest.mark.parametrize("fmt", ["trc", "csv"])
def test_text_take_fuzz(fmt):
    seed = (write_trc if fmt == "trc" else write_csv)(_take()).encode()

    @FUZZ
    @given(mutated([seed], text=True))
    def check(data):
        try:
            _check_take(read_take(data, f".{fmt}", where=f"f.{fmt}"))
        except MarkerFileError:
            pass

    check()


def test_fap_fuzz(data_dir):
    seeds = [p.read_bytes() for p in sorted((data_dir / "xface" / "faps").glob("*.fap"))]
    assert seeds

    @FUZZ
    @given(mutated(seeds, text=True))
    def check(data):
        try:
            f = read_fap(data.decode("utf-8", errors="replace"), where="f.fap")
        except FapFormatError as e:
            assert e.line >= 0 and len(str(e)) < 1000
        else:
            for frame in f.frames:
                frame.faps()

    check()


JSON_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**30), 10**30)
    | st.floats(allow_nan=False)
    | st.sampled_from(["mm", "+y", "-z", "skin", "", "x", HUGE_INT]),
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.dictionaries(
            st.sampled_from(
                [
                    "units",
                    "axes",
                    "up",
                    "forward",
                    "parts",
                    "pivots",
                    "feature_points",
                    "2.1",
                    "skin",
                    "jaw",
                    "x",
                ]
            ),
            inner,
            max_size=4,
        )
    ),
    max_leaves=8,
)


@st.composite
def mutated_annotation(draw, seed: bytes) -> bytes:
    """The annotation with one value (anywhere in the tree) replaced, or its bytes mutated."""
    if draw(st.booleans()):
        return draw(mutated([seed]))
    doc = json.loads(seed)
    nodes: list[tuple[object, object]] = []

    def walk(x, depth=0):
        items = x.items() if isinstance(x, dict) else enumerate(x) if isinstance(x, list) else ()
        for k, v in items:
            if depth < 2 or len(nodes) < 400:
                nodes.append((x, k))
                walk(v, depth + 1)

    walk(doc)
    container, key = draw(st.sampled_from(nodes))
    container[key] = draw(JSON_VALUES)
    return json.dumps(doc).replace(f'"{HUGE_INT}"', "9" * 4301).encode()  # over int()'s limit


def test_annotation_fuzz():
    seed = ANNOTATION.read_bytes()
    vertices, triangles = np.zeros((26719, 3), np.float32), np.array([[0, 1, 2]], np.int32)

    @FUZZ
    @given(mutated_annotation(seed))
    def check(data):
        try:
            face = face_from_annotation(
                "f", vertices, triangles, parse_annotation(data, where="f.json"), where="f.json"
            )
        except InputError as e:
            assert "f.json" in str(e) and len(str(e)) < 1000
        else:
            assert all(0 <= v < 26719 for v in face.feature_points.values())

    check()
