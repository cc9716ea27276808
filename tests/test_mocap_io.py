"""Marker take readers and writers: C3D, TRC, CSV round trips with occlusions; units; errors
(C3D in depth: test_c3d.py)."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.protocol.markers_file import (
    MarkerFileError,
    MarkerTake,
    read_csv,
    read_trc,
    write_csv,
    write_trc,
)
from facecast.server.errors import InputError
from facecast.server.mocap.io import detect_units, read_take, write_take


def _take(rng, units="mm", scale=1.0) -> MarkerTake:
    xyz = (rng.normal(size=(25, 4, 3)) * 40.0 + [0.0, 1600.0, 0.0]) * scale
    xyz[3, 1] = np.nan  # one occluded marker
    xyz[7] = np.nan  # a frame with nothing visible
    xyz[10:14, 2] = np.nan  # a gap
    return MarkerTake(["CHIN", "LIP_L", "LIP_R", "HEAD 1"], xyz, 120.0, units)


@pytest.mark.parametrize("suffix", [".c3d", ".trc", ".csv"])
def test_round_trip_keeps_positions_occlusions_rate_and_names(tmp_path, rng, suffix):
    take = _take(rng)
    back = read_take(write_take(take, tmp_path / f"take{suffix}"))
    assert back.names == take.names
    assert back.fps == pytest.approx(120.0)
    assert back.units == "mm"
    assert np.array_equal(np.isnan(back.xyz), np.isnan(take.xyz))
    np.testing.assert_allclose(
        back.xyz, take.xyz, atol=1e-3 if suffix == ".c3d" else 1e-9, equal_nan=True
    )


def test_units_are_detected_when_undeclared(tmp_path, rng):
    take = _take(rng, units=None, scale=0.001)  # metres, not declared
    text = write_csv(take)
    assert "units" not in text
    path = tmp_path / "take.csv"
    path.write_text(text)
    assert read_take(path).units == "m"
    assert detect_units(take.xyz * 1000) == "mm"


def test_declared_units_that_make_no_face_are_refused(tmp_path, rng):
    take = _take(rng, units="m")  # values are millimetres, declared metres -> a 100 m face
    path = write_take(take, tmp_path / "take.trc")
    with pytest.raises(InputError, match="not a face.*suggests mm"):
        read_take(path)
    assert read_take(path, units="mm").units == "mm"


def test_trc_errors_name_the_line():
    good = write_trc(MarkerTake(["A", "B"], np.ones((3, 2, 3)), 60.0, "mm"))
    lines = good.splitlines()
    lines[6] = lines[6].replace("1.0", "oops", 1)
    with pytest.raises(MarkerFileError, match=r"t\.trc:7"):
        read_trc("\n".join(lines), where="t.trc")
    with pytest.raises(MarkerFileError, match="not a TRC"):
        read_trc("hello", where="t.trc")


def test_csv_errors_name_the_problem():
    with pytest.raises(MarkerFileError, match="first column must be 'time'"):
        read_csv("x,A_x,A_y,A_z\n0,1,2,3\n")
    with pytest.raises(MarkerFileError, match="_x, <name>_y"):
        read_csv("time,A_x,A_y,B_z\n0,1,2,3\n")
    with pytest.raises(MarkerFileError, match=":3: 3 cells"):
        read_csv("time,A_x,A_y,A_z\n0,1,2,3\n0.1,1,2\n")


def test_unreadable_files_are_input_errors(tmp_path):
    bad = tmp_path / "take.c3d"
    bad.write_bytes(b"not a c3d file at all")
    with pytest.raises(InputError, match="take.c3d"):
        read_take(bad)
    with pytest.raises(InputError, match="no such take"):
        read_take(tmp_path / "missing.trc")


@pytest.mark.parametrize("fmt", ["trc", "csv"])
def test_text_round_trip_property(fmt):
    from hypothesis import given, settings
    from hypothesis import strategies as st
    from hypothesis.extra.numpy import arrays

    coords = arrays(
        np.float64,
        st.tuples(st.integers(2, 6), st.integers(1, 4), st.just(3)),
        elements=st.one_of(st.floats(-1e4, 1e4, allow_nan=False), st.just(np.nan)),
    )

    @settings(max_examples=40, deadline=None)
    @given(coords)
    def check(xyz):
        take = MarkerTake([f"m{i}" for i in range(xyz.shape[1])], xyz, 120.0, "mm")
        back = read_trc(write_trc(take)) if fmt == "trc" else read_csv(write_csv(take))
        assert back.names == take.names and back.fps == 120.0
        np.testing.assert_array_equal(back.xyz, xyz)

    check()
