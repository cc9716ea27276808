"""The ASCII .fap reader/writer: real Xface files, Greta-style files, malformed input, property tests."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facecast.protocol.fap_file import FapFile, FapFormatError, FapFrame, read_fap, write_fap

XFACE = ["anger.fap", "beg.fap", "disgust.fap", "happy-for.fap", "joy.fap"]


def _mask(*faps: int, width: int = 68) -> str:
    return " ".join("1" if k in faps else "0" for k in range(1, width + 1))


@pytest.mark.parametrize("name", XFACE)
def test_real_xface_files_round_trip_byte_for_byte(data_dir, name):
    text = (data_dir / "xface" / "faps" / name).read_bytes().decode("ascii")
    f = read_fap(text, where=name)
    assert f.version == "2.1" and f.fps == 25 and f.mask_width == 68
    assert f.name == r"C:\Users\balci\Work\FACE\exml2fap\files\TempFile"
    assert f.newline == "\r\n" and f.trailing_space and not f.header_trailing_space
    assert len(f) == int(text.split("\r\n")[0].split()[-1])
    assert [fr.number for fr in f.frames] == list(range(len(f)))
    assert write_fap(f) == text
    # FAP 3 (open_jaw) is present and moves somewhere in the clip; FAPs 1/2 never set.
    assert any(fr.faps().get(3, 0) > 100 for fr in f.frames)
    assert all(fr.viseme is None and fr.expression is None for fr in f.frames)


def test_masks_change_between_frames(data_dir):
    f = read_fap((data_dir / "xface" / "faps" / "beg.fap").read_text(), where="beg.fap")
    assert len({fr.mask for fr in f.frames}) > 1
    blink = [fr.faps().get(19) for fr in f.frames]
    assert 1024 in blink and None in blink


def test_greta_style_header_with_spaces_69_wide_mask_lf():
    text = (
        "2.1 AU Interpolation_1131.fap 25 1 \n"
        + _mask(19, 20, 21, 22, width=69)
        + " \n0 626 626 133 133 \n"
    )
    f = read_fap(text)
    assert f.name == "AU Interpolation_1131.fap"
    assert f.mask_width == 69 and f.newline == "\n" and f.header_trailing_space
    assert f.frames[0].faps() == {19: 626, 20: 626, 21: 133, 22: 133}
    assert write_fap(f) == text


def test_high_level_fields_four_and_six_values_and_greta_single_values():
    text = (
        "# made by hand\n2.1 my name 30 2\n" + _mask(1, 2, 3) + "\n0 3 10 40 1 1 63 4 20 0 1 512\n"
        "# second frame\n" + _mask(1, 5) + "\n1 14 0 63 0 -7\n"
    )
    f = read_fap(text)
    a, b = f.frames
    assert (
        a.viseme == (3, 10, 40, 1) and a.expression == (1, 63, 4, 20, 0, 1) and a.faps() == {3: 512}
    )
    assert b.viseme == (14, 0, 63, 0) and b.expression is None and b.faps() == {5: -7}
    assert f.comments == ((-1, "# made by hand"), (1, "# second frame"))
    assert write_fap(f) == text
    g = read_fap("2.1 x 25 1\n" + _mask(1, 3) + "\n0 5 100\n")  # one value per flag (Greta)
    assert g.frames[0].single_high_level and g.frames[0].faps() == {3: 100}


def test_floats_are_kept_and_written_back_exactly():
    f = read_fap("2.1 x 25 1\n" + _mask(3, 48) + "\n0 12.5 -0.000125\n")
    assert f.frames[0].faps() == {3: 12.5, 48: -0.000125}
    assert read_fap(write_fap(f)) == f


BAD = [
    ("", 0, "empty"),
    ("2.1 x 25\n", 1, "header"),
    ("2.1 x 25 2\n" + _mask(3) + "\n0 5\n" + _mask(3) + "\n", 4, "truncated"),
    ("2.1 x 25 1\n" + " ".join(["0"] * 67) + "\n0\n", 2, "67 flags"),
    ("2.1 x 25 2\n" + _mask(3) + "\n0 5\n" + _mask(3, width=69) + "\n1 5\n", 4, "same width"),
    ("2.1 x 25 1\n" + _mask(3) + "\n0 five\n", 3, "not a number"),
    ("2.1 x 25 1\n" + _mask(3, 69, width=69) + "\n0 5 6\n", 2, "out of range"),
    ("2.1 x 25 1\n" + _mask(1) + "\n0 15 0 0 0\n", 3, "viseme id 15"),
    ("2.1 x 25 1\n" + _mask(3, 4) + "\n0 5\n", 3, "need 2 values"),
    ("2.1 x 25 3\n" + _mask(3) + "\n0 5\n", 3, "declares 3 frames"),
    ("2.1 x 25 1\n" + _mask(3).replace("1", "2") + "\n0 5\n", 2, "not 0 or 1"),
    ("2.1 x 0 1\n" + _mask(3) + "\n0 5\n", 1, "frame rate"),
    ("2.1 x 25 1\n" + _mask(3) + "\n-1 5\n", 3, "frame number"),
    ("2.1 x 25 1\n" + _mask(3) + "\n0 nan\n", 3, "not a number"),
]


@pytest.mark.parametrize(("text", "line", "words"), BAD)
def test_malformed_input_names_the_line(text, line, words):
    with pytest.raises(FapFormatError) as e:
        read_fap(text, where="bad.fap")
    assert e.value.line == line
    assert words in str(e.value) and str(e.value).startswith("bad.fap")


# -- property tests -----------------------------------------------------------------------------

values = st.one_of(
    st.integers(-(10**9), 10**9), st.floats(allow_nan=False, allow_infinity=False, width=64)
)


@st.composite
def frames(draw, width: int, number: int):
    faps = draw(st.dictionaries(st.integers(3, 68), values, max_size=12))
    vis = draw(
        st.none()
        | st.tuples(st.integers(0, 14), st.integers(0, 14), st.integers(0, 63), st.integers(0, 1))
    )
    expr = draw(
        st.none()
        | st.tuples(
            st.integers(0, 6),
            st.integers(0, 63),
            st.integers(0, 6),
            st.integers(0, 63),
            st.integers(0, 1),
            st.integers(0, 1),
        )
    )
    return FapFrame.build(number, faps, viseme=vis, expression=expr, mask_width=width)


names = st.text(
    st.characters(blacklist_categories=("Cs",), blacklist_characters="\r\n\x00"), max_size=30
).map(str.strip)


@st.composite
def fap_files(draw):
    width = draw(st.sampled_from([68, 69]))
    n = draw(st.integers(0, 5))
    numbers = draw(st.lists(st.integers(0, 1000), min_size=n, max_size=n))
    fr = tuple(draw(frames(width, k)) for k in numbers)
    comments = draw(
        st.lists(st.tuples(st.integers(-1, n), names.map(lambda s: "#" + s)), max_size=3)
    )
    return FapFile(
        version=draw(st.sampled_from(["2.1", "1.0", "2"])),
        name=draw(names),
        fps=draw(st.integers(1, 240) | st.floats(0.5, 240)),
        frames=fr,
        comments=tuple(sorted(comments, key=lambda c: c[0])),
        newline=draw(st.sampled_from(["\n", "\r\n"])),
        trailing_space=draw(st.booleans()),
        header_trailing_space=draw(st.booleans()),
        final_newline=draw(st.booleans()),
    )


@settings(max_examples=80, deadline=None)
@given(fap_files())
def test_write_read_write_is_identical(f):
    text = write_fap(f)
    g = read_fap(text)
    assert write_fap(g) == text
    assert g.frames == f.frames and g.name == f.name and g.fps == f.fps and len(g) == len(f)
    for a, b in zip(f.frames, g.frames):
        assert a.faps() == b.faps() and a.viseme == b.viseme and a.expression == b.expression


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=300))
def test_garbage_is_rejected_cleanly(text):
    try:
        read_fap(text)
    except FapFormatError as e:
        assert e.line >= 0 and str(e)


@settings(max_examples=60, deadline=None)
@given(fap_files(), st.data())
def test_corrupted_files_fail_with_a_line_number_or_still_parse(f, data):
    text = write_fap(f)
    lines = text.split(f.newline)
    i = data.draw(st.integers(0, max(0, len(lines) - 1)))
    lines[i] = data.draw(st.sampled_from(["", "x", "0 1", "1 " * 70, "# c"]))
    try:
        read_fap(f.newline.join(lines))
    except FapFormatError as e:
        assert 0 <= e.line <= len(lines)
