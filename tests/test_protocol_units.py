"""The one unit table: faces, marker takes, layouts and live hellos read units the same way."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.protocol.markers_file import MarkerFileError, MarkerTake, normalise_units
from facecast.protocol.units import UNIT_MM, UNIT_SPELLINGS, unit_name


def test_the_table():
    assert UNIT_MM == {"mm": 1.0, "cm": 10.0, "dm": 100.0, "m": 1000.0, "in": 25.4}
    assert set(UNIT_SPELLINGS.values()) == set(UNIT_MM)


@pytest.mark.parametrize(
    ("text", "name"),
    [
        ("mm", "mm"),
        ("Millimeters", "mm"),
        ("millimetre.", "mm"),
        (" CM ", "cm"),
        ("centimetres", "cm"),
        ("decimeter", "dm"),
        ("m", "m"),
        ("Metres", "m"),
        ("meter", "m"),
        ("in", "in"),
        ("Inches", "in"),
        ("inch", "in"),
    ],
)
def test_spellings(text, name):
    assert unit_name(text) == name and normalise_units(text) == name


@pytest.mark.parametrize("text", ["", "furlong", "mmm", "kilometers", "feet"])
def test_unknown_units_are_refused_naming_the_table(text):
    assert unit_name(text) is None
    with pytest.raises(MarkerFileError, match="use one of mm, cm, dm, m, in"):
        normalise_units(text, where="t.trc:3")


@pytest.mark.parametrize("junk", [5, 1.5, ["mm"], {"u": "mm"}])
def test_a_layout_unit_that_is_not_text_is_a_file_error(junk):
    with pytest.raises(MarkerFileError):
        normalise_units(junk)  # type: ignore[arg-type]


def test_takes_and_faces_convert_with_the_same_factors():
    from facecast.server.faces.face import UNIT_MM as face_table

    assert face_table is UNIT_MM
    xyz = np.ones((1, 1, 3))
    for u, f in UNIT_MM.items():
        assert MarkerTake(["a"], xyz, 60.0, u).in_mm()[0, 0, 0] == f


@pytest.mark.parametrize("fmt", ["c3d", "trc", "csv"])
def test_writers_refuse_units_outside_the_table(fmt):
    from facecast.protocol import markers_file as mf

    take = MarkerTake(["a", "b"], np.ones((2, 2, 3)), 60.0, "furlong")
    with pytest.raises(MarkerFileError, match="'furlong' are not one of mm, cm, dm, m, in"):
        getattr(mf, f"write_{fmt}")(take)
