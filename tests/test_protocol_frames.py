"""Binary frames: byte layout, round trips, and clean rejection of garbage (hypothesis)."""

from __future__ import annotations

import struct
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from facecast.protocol import frames as fr
from facecast.protocol.errors import FrameError, ProtocolError
from facecast.protocol.quantize import quantize_int16

finite32 = st.floats(-1e6, 1e6, width=32)


def vertex_arrays(max_v: int = 64):
    return hnp.arrays(np.float32, st.tuples(st.integers(0, max_v), st.just(3)), elements=finite32)


def test_header_layout_is_as_documented():
    v = np.arange(6, dtype=np.float32).reshape(2, 3)
    b = fr.encode_vertices_f32(v, seq=7, t=1.25, wall=1700000000.5)
    assert len(b) == 32 + 12 * 2 and fr.HEADER_SIZE == 32
    assert b[:4] == b"FCST" and b[4] == 1 and b[5] == 1
    assert struct.unpack_from("<HIIdd", b, 6) == (0, 7, 2, 1.25, 1700000000.5)
    assert np.array_equal(np.frombuffer(b, "<f4", offset=32), v.ravel())


def test_i16_layout_and_error_bound(rng):
    v = (rng.standard_normal((500, 3)) * 80).astype(np.float32)
    b = fr.encode_vertices_i16(v, seq=1, t=0.0)
    assert len(b) == 56 + 6 * 500
    offset = np.frombuffer(b, "<f4", 3, 32)
    scale = np.frombuffer(b, "<f4", 3, 44)
    q = np.frombuffer(b, "<i2", offset=56).reshape(-1, 3)
    assert np.all(np.abs(offset + q * scale - v) <= scale * 0.5 + 1e-4 * np.abs(v).max())
    f = fr.decode(b)
    assert np.array_equal(f.positions(), offset + q.astype(np.float32) * scale)


def test_payload_is_a_view_not_a_copy():
    b = fr.encode_vertices_f32(np.ones((10, 3), np.float32), seq=0, t=0)
    f = fr.decode(b)
    assert not f.vertices.flags.owndata and not f.vertices.flags.writeable
    ba = bytearray(b)
    f2 = fr.decode(ba)
    ba[32:36] = struct.pack("<f", 5.0)
    assert f2.vertices[0, 0] == 5.0  # shares memory with the message


@given(vertex_arrays(), st.integers(0, 2**32 - 1), st.floats(0, 1e6), st.floats(0, 2e9))
def test_f32_round_trip(v, seq, t, wall):
    f = fr.decode(fr.encode_vertices_f32(v, seq=seq, t=t, wall=wall))
    assert isinstance(f, fr.VertexFrame) and f.header.kind is fr.Kind.VERTICES_F32
    assert (f.header.seq, f.header.t, f.header.wall, f.header.count) == (seq, t, wall, len(v))
    assert np.array_equal(f.vertices, v)


@given(vertex_arrays().filter(lambda a: len(a) > 0))
def test_i16_round_trip(v):
    f = fr.decode(fr.encode_vertices_i16(v, seq=3, t=0.5))
    assert f.header.kind is fr.Kind.VERTICES_I16 and f.vertices.dtype == np.int16
    err = np.abs(f.positions() - v)
    # half a quantisation step, plus float32 rounding of offset + q * scale
    assert np.all(err <= f.scale * 0.5 + 1e-6 * (np.abs(v).max(axis=0) + 1) * 4)


def _reference_quantize_int16(vertices):
    """The plain broadcast formula the wire has always carried (the old ``protocol/quantize.py``)."""
    v = np.asarray(vertices, dtype=np.float32)
    lo, hi = v.min(axis=0), v.max(axis=0)
    offset = ((lo + hi) / 2).astype(np.float32)
    scale = np.maximum((hi - lo) / np.float32(65534.0), np.float32(1e-12)).astype(np.float32)
    q = np.clip(np.rint((v - offset) / scale), -32767, 32767).astype(np.int16)
    return q, offset, scale


@pytest.mark.parametrize("n", [1, 255, 256, 257, 513, 24_850])
def test_quantiser_equals_the_reference_on_face_sized_arrays(n, rng):
    v = (rng.standard_normal((n, 3)) * 90 + [0, 20, 60]).astype(np.float32)
    for a, b in zip(quantize_int16(v), _reference_quantize_int16(v)):
        assert a.dtype == b.dtype and np.array_equal(a, b)


@given(vertex_arrays(600).filter(lambda a: len(a) > 0))
def test_quantiser_equals_the_reference(v):
    for a, b in zip(quantize_int16(v), _reference_quantize_int16(v)):
        assert a.dtype == b.dtype and np.array_equal(a, b)


def test_i16_wire_bytes_of_a_real_face_frame_are_the_reference_formulas(rng):
    from facecast.server.faces import load_face

    rest = load_face("default").vertices  # (24848, 3) float32: the built-in head
    frame = (rest + rng.normal(scale=0.5, size=rest.shape)).astype(np.float32)
    for v in (rest, frame, frame.astype(np.float64), frame[::-1]):
        q, offset, scale = _reference_quantize_int16(v)
        want = b"".join(
            (
                struct.pack("<4sBBHIIdd", b"FCST", 1, 2, 0, 41, len(v), 2.5, 1700000000.0),
                struct.pack("<3f3f", *offset.tolist(), *scale.tolist()),
                q.astype("<i2").tobytes(),
            )
        )
        assert fr.encode_vertices_i16(v, seq=41, t=2.5, wall=1700000000.0) == want


def test_empty_vertex_frames_round_trip():
    for enc in ("f32", "i16"):
        f = fr.decode(fr.encode_vertices(np.zeros((0, 3), np.float32), enc, seq=0, t=0))
        assert f.positions().shape == (0, 3)


@given(
    hnp.arrays(np.int16, st.integers(0, 400)),
    st.sampled_from([8000, 16000, 44100, 48000]),
    st.integers(0, 2**40),
)
def test_pcm_i16_round_trip(s, rate, offset):
    f = fr.decode(fr.encode_pcm(s, rate=rate, sample_offset=offset, seq=2, wall=3.0))
    assert isinstance(f, fr.PcmChunk) and f.header.kind is fr.Kind.PCM_I16
    assert (f.rate, f.sample_offset, f.header.t) == (rate, offset, offset / rate)
    assert np.array_equal(f.samples, s)
    assert np.allclose(f.as_float32(), s / 32768.0)


@given(hnp.arrays(np.float32, st.integers(0, 400), elements=st.floats(-1, 1, width=32)))
def test_pcm_f32_round_trip(s):
    f = fr.decode(fr.encode_pcm(s, rate=16000, sample_offset=0, seq=0))
    assert f.header.kind is fr.Kind.PCM_F32 and np.array_equal(f.as_float32(), s)


@given(
    hnp.arrays(
        np.float32,
        st.tuples(st.integers(0, 50), st.just(3)),
        elements=st.one_of(finite32, st.just(np.float32("nan"))),
    )
)
def test_markers_round_trip(m):
    f = fr.decode(fr.encode_markers(m, seq=9, t=2.0))
    assert isinstance(f, fr.MarkerFrame)
    assert np.array_equal(f.markers, m, equal_nan=True)


@given(
    hnp.arrays(np.float32, 68, elements=st.one_of(finite32, st.just(np.float32("nan")))),
    st.one_of(st.none(), st.tuples(st.integers(0, 14), st.integers(0, 14), st.integers(0, 63))),
    st.one_of(
        st.none(),
        st.tuples(st.integers(0, 6), st.integers(0, 63), st.integers(0, 6), st.integers(0, 63)),
    ),
)
def test_fap_round_trip(values, viseme, expression):
    b = fr.encode_faps(values, seq=1, t=0.04, wall=5.0, viseme=viseme, expression=expression)
    assert len(b) == 312
    f = fr.decode(b)
    assert isinstance(f, fr.FapFrame)
    assert np.array_equal(f.values, values, equal_nan=True)
    assert f.viseme == viseme and f.expression == expression


def test_fap_accepts_faceState_indexing():
    faps = np.zeros(69)
    faps[3] = 120.0
    f = fr.decode(fr.encode_faps(faps, seq=0, t=0))
    assert f.values[2] == 120.0  # values[k - 1] = FAP k


def _valid_frames() -> list[bytes]:
    v = np.linspace(-1, 1, 30, dtype=np.float32).reshape(10, 3)
    return [
        fr.encode_vertices_f32(v, seq=1, t=0),
        fr.encode_vertices_i16(v, seq=1, t=0),
        fr.encode_pcm(np.zeros(16, np.int16), rate=16000, sample_offset=0, seq=0),
        fr.encode_pcm(np.zeros(16, np.float32), rate=16000, sample_offset=0, seq=0),
        fr.encode_markers(v, seq=0, t=0),
        fr.encode_faps(np.zeros(68), seq=0, t=0, viseme=(1, 2, 3)),
    ]


@pytest.mark.parametrize("i", range(6))
def test_every_truncation_and_extension_is_rejected(i):
    b = _valid_frames()[i]
    fr.decode(b)
    for n in range(len(b)):
        with pytest.raises(FrameError):
            fr.decode(b[:n])
    with pytest.raises(FrameError, match="trailing"):
        fr.decode(b + b"\0")


@pytest.mark.parametrize(
    ("offset", "value", "match"),
    [
        (0, b"XCST", "magic"),
        (4, b"\x02", "version"),
        (5, b"\x09", "kind"),
        (6, b"\x04\x00", "flag"),
        (12, struct.pack("<I", 2**31), "limit|bytes"),
        (16, struct.pack("<d", float("nan")), "finite"),
    ],
)
def test_bad_header_fields_are_named(offset, value, match):
    b = bytearray(_valid_frames()[0])
    b[offset : offset + len(value)] = value
    with pytest.raises(FrameError, match=match):
        fr.decode(bytes(b))


def test_bad_sub_headers():
    pcm = bytearray(_valid_frames()[2])
    pcm[32:36] = struct.pack("<I", 0)
    with pytest.raises(FrameError, match="sample rate"):
        fr.decode(pcm)
    pcm = bytearray(_valid_frames()[2])
    pcm[36:38] = struct.pack("<H", 2)
    with pytest.raises(FrameError, match="mono"):
        fr.decode(pcm)
    fap = bytearray(_valid_frames()[5])
    fap[32] = 20
    with pytest.raises(FrameError, match="viseme"):
        fr.decode(fap)
    fap = bytearray(_valid_frames()[5])
    fap[40:44] = struct.pack("<f", float("inf"))
    with pytest.raises(FrameError, match="finite"):
        fr.decode(fap)
    i16 = bytearray(_valid_frames()[1])
    i16[44:48] = struct.pack("<f", 0.0)
    with pytest.raises(FrameError, match="scale"):
        fr.decode(i16)


def test_kinds_filter():
    with pytest.raises(FrameError, match="not accepted"):
        fr.decode(_valid_frames()[0], kinds=frozenset({fr.Kind.FAPS}))


@settings(max_examples=300)
@given(st.binary(max_size=400))
def test_garbage_raises_only_frame_error(data):
    try:
        fr.decode(data)
    except FrameError:
        pass


@settings(max_examples=300)
@given(st.integers(0, 5), st.data())
def test_mutated_frames_decode_or_raise_frame_error(i, data):
    b = bytearray(_valid_frames()[i])
    for _ in range(data.draw(st.integers(1, 4))):
        pos = data.draw(st.integers(0, len(b) - 1))
        b[pos] = data.draw(st.integers(0, 255))
    try:
        f = fr.decode(bytes(b))
    except FrameError:
        return
    assert f.header.kind in fr.Kind


def test_errors_share_one_root_with_close_code():
    with pytest.raises(ProtocolError) as e:
        fr.decode(b"nope")
    assert e.value.close_code == 4400 and isinstance(e.value, ValueError)


def test_encoders_refuse_bad_shapes():
    with pytest.raises(ValueError):
        fr.encode_vertices_f32(np.zeros((4, 2)), seq=0, t=0)
    with pytest.raises(TypeError):
        fr.encode_pcm(np.zeros(4, np.float64), rate=16000, sample_offset=0, seq=0)
    with pytest.raises(ValueError):
        fr.encode_faps(np.zeros(10), seq=0, t=0)
    with pytest.raises(ValueError):
        fr.encode_vertices(np.zeros((1, 3)), "f16", seq=0, t=0)


def _loaded_after(imports: str, forbidden: tuple[str, ...]) -> str:
    code = (
        f"import sys, {imports}; bad = [m for m in sys.modules if m in {forbidden!r} or "
        "m.startswith(('facecast.server', 'facecast.client'))]; print(','.join(bad))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return r.stdout.strip()


def test_importing_protocol_loads_no_io_or_server_code():
    io = (
        "asyncio",
        "socket",
        "ssl",
        "selectors",
        "fastapi",
        "starlette",
        "uvicorn",
        "websockets",
        "httpx",
    )
    assert (
        _loaded_after(
            "facecast.protocol.frames, facecast.protocol.errors, facecast.protocol.quantize", io
        )
        == ""
    )
    # pydantic itself imports ``socket`` and ``selectors`` (through email.utils), so messages are checked without it
    assert (
        _loaded_after(
            "facecast.protocol.messages", tuple(m for m in io if m not in ("socket", "selectors"))
        )
        == ""
    )
