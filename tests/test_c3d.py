"""The one C3D path (``protocol.markers_file``): what real writers produce reads the same, and hostile
bytes give a MarkerFileError (an InputError through ``read_take``), never a crash, hang or partial take.

ezc3d appears here only as an independent writer and reader of well-formed files.
"""

from __future__ import annotations

import struct
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from facecast.protocol.errors import FileFormatError, ProtocolError
from facecast.protocol.markers_file import MarkerFileError, MarkerTake, read_c3d, write_c3d
from facecast.server.errors import InputError
from facecast.server.mocap.io import read_take, write_take

#: The issue's file: a header, then a parameter section that ezc3d segfaults on ("\xff") or spins
#: on ("\x80") with the GIL held.
SEGFAULT_C3D = b"\x02\x50" + bytes(510) + b"\x01\x50\x02\x54\xff"
SPIN_C3D = SEGFAULT_C3D[:-1] + b"\x80"


def _take(rng, t=12, m=4, units="mm") -> MarkerTake:
    xyz = rng.normal(size=(t, m, 3)) * 40.0 + [0.0, 1600.0, 0.0]
    xyz[3, 1] = np.nan
    xyz[5] = np.nan
    return MarkerTake([f"M{i}" if i else "HEAD 1" for i in range(m)], xyz, 120.0, units)


def _ezc3d_write(take: MarkerTake, path, analog_channels: int = 0) -> None:
    """A C3D written by ezc3d (points, and optionally analog channels at 5 samples per frame)."""
    import ezc3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [take.fps]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(take.names)
    c.add_parameter("POINT", "UNITS", take.units)
    pts = np.ones((4, take.xyz.shape[1], take.xyz.shape[0]))
    pts[:3] = np.moveaxis(take.xyz, (0, 1, 2), (2, 1, 0))
    c["data"]["points"] = pts
    if analog_channels:
        c["parameters"]["ANALOG"]["RATE"]["value"] = [take.fps * 5]
        c["parameters"]["ANALOG"]["LABELS"]["value"] = [f"A{i}" for i in range(analog_channels)]
        c["data"]["analogs"] = np.random.default_rng(0).normal(
            size=(1, analog_channels, take.xyz.shape[0] * 5)
        )
    c.write(str(path))


def _ezc3d_read(path) -> MarkerTake:
    import ezc3d

    c = ezc3d.c3d(str(path))
    pts = np.asarray(c["data"]["points"], dtype=np.float64)
    xyz = np.moveaxis(pts[:3], (0, 1, 2), (2, 1, 0))
    names = [s.strip() for s in c["parameters"]["POINT"]["LABELS"]["value"]]
    for key in ("LABELS2", "LABELS3"):
        names += [s.strip() for s in c["parameters"]["POINT"].get(key, {}).get("value", [])]
    return MarkerTake(names, xyz, float(c["parameters"]["POINT"]["RATE"]["value"][0]))


@pytest.mark.parametrize("analog", [0, 3])
def test_files_ezc3d_writes_read_the_same(tmp_path, rng, analog):
    take = _take(rng)
    path = tmp_path / "ez.c3d"
    _ezc3d_write(take, path, analog)
    back = read_c3d(path.read_bytes(), where=str(path))
    assert back.names == take.names and back.fps == 120.0 and back.units == "mm" and back.t0 == 0
    assert np.array_equal(np.isnan(back.xyz), np.isnan(take.xyz))
    np.testing.assert_allclose(back.xyz, take.xyz, atol=1e-3, equal_nan=True)  # float32 storage
    np.testing.assert_array_equal(back.xyz, _ezc3d_read(path).xyz)


def test_the_generators_writer_and_ezc3d_give_the_same_take(tmp_path, rng):
    """write_take (the generator's writer, now pure) and ezc3d: identical through read_take."""
    take = _take(rng)
    _ezc3d_write(take, tmp_path / "ez.c3d")
    ours, theirs = (
        read_take(write_take(take, tmp_path / "pure.c3d")),
        read_take(tmp_path / "ez.c3d"),
    )
    assert (ours.names, ours.fps, ours.units, ours.t0) == (
        theirs.names,
        theirs.fps,
        theirs.units,
        theirs.t0,
    )
    np.testing.assert_array_equal(ours.xyz, theirs.xyz)


@pytest.mark.parametrize("processor", ["intel", "dec"])
@pytest.mark.parametrize("scale", [-1.0, 0.1])
def test_ezc3d_reads_what_the_pure_writer_writes(tmp_path, rng, processor, scale):
    take = _take(rng, t=30, m=300)  # 300 markers: labels continue in POINT:LABELS2
    path = tmp_path / "pure.c3d"
    path.write_bytes(write_c3d(take, processor=processor, scale=scale))
    ours, theirs = read_c3d(path.read_bytes()), _ezc3d_read(path)
    assert ours.names == theirs.names == take.names and ours.fps == theirs.fps == 120.0
    np.testing.assert_array_equal(ours.xyz, theirs.xyz)
    np.testing.assert_allclose(ours.xyz, take.xyz, atol=abs(scale) / 2 if scale > 0 else 1e-3)


@pytest.mark.parametrize("processor", ["intel", "dec", "mips"])
@pytest.mark.parametrize("scale", [-1.0, -0.05, 0.1])
def test_processor_types_and_storage_round_trip(rng, processor, scale):
    take = _take(rng)
    take.t0 = 0.5
    back = read_c3d(write_c3d(take, processor=processor, scale=scale))
    assert back.names == take.names and back.fps == 120.0 and back.t0 == pytest.approx(0.5)
    assert np.array_equal(np.isnan(back.xyz), np.isnan(take.xyz))
    np.testing.assert_allclose(back.xyz, take.xyz, atol=scale / 2 if scale > 0 else 1e-3)


def test_a_take_over_65535_frames_keeps_every_frame(rng):
    take = MarkerTake(["A"], rng.normal(size=(70_000, 1, 3)), 250.0, "mm")
    back = read_c3d(write_c3d(take))
    assert back.n_frames == 70_000
    np.testing.assert_allclose(back.xyz, take.xyz, atol=1e-5)


def test_the_server_writes_and_reads_c3d_without_ezc3d(tmp_path, rng):
    """read_take/write_take are the pure path: ezc3d is never loaded in the server's process."""
    path = write_take(_take(rng), tmp_path / "take.c3d")
    code = textwrap.dedent(f"""
        import sys
        sys.modules["ezc3d"] = None  # importing it would raise
        from facecast.server.mocap.io import read_take
        take = read_take({str(path)!r})
        assert take.n_frames == 12 and "HEAD 1" in take.names
    """)
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def _truncations(rng) -> list[bytes]:
    good = write_c3d(_take(rng))  # header, parameters, 12 frames x 4 points x 16 bytes, padding
    assert len(good) == 2048
    return [good[:n] for n in (900, 964, 1092, 1536, 1024 + 12 * 64 - 1)]


def test_truncated_files_are_refused_not_read_in_part(rng):
    good = write_c3d(_take(rng))
    for cut in _truncations(rng):
        with pytest.raises(MarkerFileError, match="cut short|no 3-D points|parameter"):
            read_c3d(cut, where="t.c3d")
    data_cut = good[: 1024 + 5 * 4 * 16]  # 5 of 12 frames
    with pytest.raises(MarkerFileError, match="declares 12 frames of 4 points but holds 5"):
        read_c3d(data_cut)


def _param_file(entry: bytes, header_scale: float = -1.0) -> bytes:
    """A one-block parameter section holding ``entry`` after a POINT group; no data."""
    header = bytearray(512)
    header[0:2] = b"\x02\x50"
    header[2:4] = struct.pack("<H", 1)
    header[6:10] = struct.pack("<HH", 1, 1)
    header[12:16] = struct.pack("<f", header_scale)
    header[16:18] = struct.pack("<H", 3)
    header[20:24] = struct.pack("<f", 60.0)
    group = bytes([5, 0xFF]) + b"POINT" + struct.pack("<h", 3) + b"\x00"
    section = (b"\x01\x50\x01\x54" + group + entry).ljust(512, b"\x00")
    return bytes(header) + section + struct.pack("<4f", 1, 2, 3, 0).ljust(512, b"\x00")


def _param(name: bytes, ptype: int, dims: tuple, values: bytes, nxt: int | None = None) -> bytes:
    body = bytes([ptype & 0xFF, len(dims), *dims]) + values + b"\x00"
    return (
        bytes([len(name), 1])
        + name
        + struct.pack("<h", 2 + len(body) if nxt is None else nxt)
        + body
    )


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        (
            _param(b"RATE", 4, (), struct.pack("<f", 60.0), nxt=-40) + bytes([4, 1]),
            "points -40 bytes back",
        ),
        (_param(b"USED", 3, (), b"\x01\x00\x00"), "type 3"),
        (_param(b"RATE", 4, (0,), b""), "POINT:RATE has no value"),
        (_param(b"USED", 2, (200, 200), b""), "declares 80000 bytes"),
        (_param(b"RATE", -1, (2,), b"60"), "POINT:RATE must be a number"),
        (_param(b"SCALE", 4, (), struct.pack("<f", 0.0)), "POINT:SCALE is 0.0"),
        (_param(b"USED", 4, (), struct.pack("<f", float("nan"))), "POINT:USED is nan"),
    ],
)
def test_malformed_parameters_say_what_is_wrong(entry, message):
    with pytest.raises(MarkerFileError, match=message):
        read_c3d(_param_file(entry), where="bad.c3d")


def test_well_formed_parameter_file_reads_and_zero_length_text_is_empty():
    labels = _param(b"LABELS", -1, (0, 1), b"")  # zero-length character dimension: no label
    take = read_c3d(_param_file(labels))
    assert take.names == ["M000"] and take.xyz.tolist() == [[[1.0, 2.0, 3.0]]]


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"\x00\x50" + bytes(600), "block 0"),
        (b"\x09\x50" + bytes(600), "past the end"),
        (b"\x02\x50" + bytes(510) + b"\x01\x50\x02\x57", "processor type 87"),
        (SEGFAULT_C3D, "no 3-D points"),
        (SPIN_C3D, "no 3-D points"),
    ],
    ids=["block0", "past-end", "processor", "segfault", "spin"],
)
def test_bad_headers_say_what_is_wrong(data, message):
    with pytest.raises(MarkerFileError, match=message):
        read_c3d(data)


def test_file_format_errors_share_the_protocol_root():
    assert issubclass(MarkerFileError, FileFormatError) and issubclass(
        FileFormatError, ProtocolError
    )
    assert issubclass(MarkerFileError, ValueError) and MarkerFileError("x").status == 400


def test_the_crash_and_hang_files_are_input_errors_in_a_live_process(tmp_path, rng):
    """The issue's segfault and 100 %-CPU files, and truncated takes, through the server's reader.

    Run in a subprocess with a timeout, so that a regression fails this test instead of hanging or
    killing pytest.
    """
    files = [SEGFAULT_C3D, SPIN_C3D, *_truncations(rng)]
    for i, data in enumerate(files):
        (tmp_path / f"f{i}.c3d").write_bytes(data)
    code = textwrap.dedent(f"""
        from facecast.server.errors import InputError
        from facecast.server.mocap.io import read_take
        for i in range({len(files)}):
            try:
                read_take({str(tmp_path)!r} + f"/f{{i}}.c3d", units="mm")
            except InputError as e:
                print(i, "refused:", e)
            else:
                raise SystemExit(f"file {{i}} was read")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.count("refused") == len(files)
    with pytest.raises(InputError, match="f0.c3d"):
        read_take(tmp_path / "f0.c3d")


def test_units_with_no_string_are_no_units():
    units = _param(b"UNITS", -1, (2, 0), b"")  # found by bench/fuzz_parsers.py: an IndexError
    assert read_c3d(_param_file(units)).units is None


def test_overlapping_parameters_are_not_copied():
    """5,000 entries 10 bytes apart, each declaring 65 kB of values over the next ones: reading them
    must not copy each (325 MB) but view the file's bytes."""
    import tracemalloc

    entries = b"".join(
        bytes([2, 1, k & 0xFF, 65 + (k >> 8)]) + struct.pack("<h", 6) + b"\x01\x02\xff\xff"
        for k in range(5000)
    )
    section = (
        b"\x01\x50\xff\x54" + bytes([5, 0xFF]) + b"POINT" + struct.pack("<h", 3) + b"\x00" + entries
    )
    data = b"\x02\x50" + bytes(510) + section + bytes(65025)
    tracemalloc.start()
    try:
        with pytest.raises(MarkerFileError, match="no 3-D points"):
            read_c3d(data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20e6, f"{peak / 1e6:.0f} MB"
