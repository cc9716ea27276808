"""The ASCII MPEG-4 FAP file (``.fap``, "FAP 2.1" text format): pure reader and writer.

Syntax (see ``docs/mpeg4-reference.md`` §5)::

    # comment (a '#' in column 1, anywhere)
    <version> <sequence name, may contain spaces> <fps> <number of frames>
    <68 mask flags 0/1>                      } once per frame
    <frame number> <values of the set flags> }

A set flag 1 (viseme) contributes 4 integers (select1, select2, blend, def), a set flag 2
(expression) 6 (select1, intensity1, select2, intensity2, init_face, expression_def); every other
set flag one value in its FAPU. Greta writes 69 flags (the 69th always 0) and one value per set
flag also for FAPs 1/2; both are read. Values outside the nominal ranges (e.g. negative FAP 3) are
kept: real files contain them.

``read_fap(text)`` keeps what is needed to write the same file again: the values as they were
(``int`` for integer tokens, ``float`` otherwise), the mask width, frame numbers, comments, line
ends and trailing spaces, so ``write_fap(read_fap(x))`` reproduces the Xface files byte for byte and
``write_fap(read_fap(write_fap(f))) == write_fap(f)`` for any valid ``FapFile``.

Malformed input raises ``FapFormatError`` (a ``ValueError``) with the 1-based line number.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from .errors import FileFormatError
from .errors import show_token as _show

#: Number of MPEG-4 FAPs (2 high-level + 66 low-level).
N_FAPS = 68
#: Mask widths accepted: the standard 68, and Greta's 69 (its last flag always 0).
MASK_WIDTHS = (68, 69)
#: Number of values a set flag contributes in the standard layout.
HIGH_LEVEL_FIELDS = {1: 4, 2: 6}
#: Largest id of ``viseme_select1/2`` and of ``expression_select1/2``.
MAX_VISEME, MAX_EXPRESSION = 14, 6

Number = int | float

#: A decimal number. Unambiguous (one way to match), so matching is linear in the token's length:
#: ``\d+\.?\d*`` backtracked quadratically on a long run of digits followed by a letter.
_NUMBER = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?$")
_INT = re.compile(r"^[+-]?\d+$")


class FapFormatError(FileFormatError):
    """A ``.fap`` text that cannot be read (or a ``FapFile`` that cannot be written).

    ``line`` is the 1-based line number at fault (0 when not tied to a line), ``where`` the file.
    """

    def __init__(self, message: str, *, line: int = 0, where: str = "") -> None:
        loc = ":".join(x for x in (where, str(line) if line else "") if x)
        super().__init__(message, where=loc)
        self.line = line
        self.where = where
        self.reason = message


@dataclass(frozen=True)
class FapFrame:
    """One frame: ``mask`` (0/1 per flag, ``mask_width`` long), its ``number`` and its ``values``.

    ``values`` lists the numbers after the frame number exactly as stored: in FAP order, 4 for a
    set FAP 1 and 6 for a set FAP 2 (or a single value each when ``single_high_level``, the Greta
    layout).
    """

    number: int
    mask: tuple[int, ...]
    values: tuple[Number, ...]
    single_high_level: bool = False

    def faps(self) -> dict[int, Number]:
        """Low-level FAPs present in this frame: FAP number (3..68) -> value (in its FAPU)."""
        out: dict[int, Number] = {}
        i = 0
        for k in range(1, min(len(self.mask), N_FAPS) + 1):
            if not self.mask[k - 1]:
                continue
            n = 1 if self.single_high_level else HIGH_LEVEL_FIELDS.get(k, 1)
            if k > 2:
                out[k] = self.values[i]
            i += n
        return out

    def _high_level(self, k: int) -> tuple[Number, ...] | None:
        if len(self.mask) < k or not self.mask[k - 1]:
            return None
        start = 0 if k == 1 else (self._width_of(1) if self.mask[0] else 0)
        return tuple(self.values[start : start + self._width_of(k)])

    def _width_of(self, k: int) -> int:
        return 1 if self.single_high_level else HIGH_LEVEL_FIELDS[k]

    @property
    def viseme(self) -> tuple[Number, ...] | None:
        """FAP 1 fields ``(select1, select2, blend, def)`` (one value in the Greta layout), or None."""
        return self._high_level(1)

    @property
    def expression(self) -> tuple[Number, ...] | None:
        """FAP 2 fields ``(select1, intensity1, select2, intensity2, init_face, def)``, or None."""
        return self._high_level(2)

    @classmethod
    def build(
        cls,
        number: int,
        faps: dict[int, Number],
        *,
        viseme: tuple[int, ...] | None = None,
        expression: tuple[int, ...] | None = None,
        mask_width: int = N_FAPS,
    ) -> FapFrame:
        """A frame from low-level values ``{fap: value}`` (3..68) and optional FAP 1 / FAP 2 fields."""
        mask = [0] * mask_width
        values: list[Number] = []
        if viseme is not None:
            mask[0] = 1
            values.extend(viseme)
        if expression is not None:
            mask[1] = 1
            values.extend(expression)
        for k in sorted(faps):
            if not 3 <= k <= N_FAPS:
                raise FapFormatError(f"FAP {k} is out of range; low-level FAPs are 3..68")
            mask[k - 1] = 1
            values.append(faps[k])
        return cls(number, tuple(mask), tuple(values))


@dataclass(frozen=True)
class FapFile:
    """A decoded ``.fap`` file.

    Attributes:
        version: the version token as written (``"2.1"``).
        name: sequence name (may contain spaces and backslashes; never a newline).
        fps: frame rate (``int`` as in every known file; a ``float`` is kept if written so).
        frames: the frames in file order.
        comments: ``(i, text)``: comment line ``text`` (starting with ``#``) stood before frame ``i``
            (``-1``: before the header; ``len(frames)``: after the last frame).
        newline: ``"\\r\\n"`` or ``"\\n"``.
        trailing_space: frame lines end with a space (both Xface and Greta do this).
        header_trailing_space: the header line ends with a space.
        final_newline: the text ends with a line end.
    """

    version: str = "2.1"
    name: str = "facecast"
    fps: Number = 25
    frames: tuple[FapFrame, ...] = ()
    comments: tuple[tuple[int, str], ...] = ()
    newline: str = "\n"
    trailing_space: bool = True
    header_trailing_space: bool = False
    final_newline: bool = True

    @property
    def mask_width(self) -> int:
        """Flags per mask line (68, or 69 for Greta files); 68 for an empty file."""
        return len(self.frames[0].mask) if self.frames else N_FAPS

    @property
    def duration(self) -> float:
        """Seconds covered by the frames at ``fps``."""
        return len(self.frames) / float(self.fps) if self.fps else 0.0

    def __len__(self) -> int:
        return len(self.frames)


#: Integers have at most this many digits (Python refuses to parse over 4,300; no FAP needs 19).
MAX_DIGITS = 18


def _int(tok: str, line: int, where: str, what: str) -> int:
    """An integer token (already matched by ``_INT``) of at most ``MAX_DIGITS`` digits."""
    digits = len(tok.lstrip("+-"))
    if digits > MAX_DIGITS:
        raise FapFormatError(
            f"{what} {_show(tok)} has {digits} digits; integers have at most {MAX_DIGITS}",
            line=line,
            where=where,
        )
    return int(tok)


def _number(tok: str, line: int, where: str, what: str) -> Number:
    if _INT.match(tok):
        return _int(tok, line, where, what)
    if _NUMBER.match(tok):
        v = float(tok)
        if math.isfinite(v):
            return v
    raise FapFormatError(
        f"{what} {_show(tok)} is not a number; every value must be an integer "
        "(or a decimal number)",
        line=line,
        where=where,
    )


def read_fap(text: str, *, where: str = "") -> FapFile:
    """Parse ``.fap`` text (see the module docstring); ``where`` names the file in errors."""
    if not isinstance(text, str):
        raise TypeError("read_fap takes str; decode the bytes first (ASCII/UTF-8)")
    raw = text.split("\n")
    final_newline = raw[-1] == ""
    if final_newline:
        raw.pop()
    newline = "\r\n" if raw and raw[0].endswith("\r") else "\n"
    lines = [r.removesuffix("\r") for r in raw]

    comments: list[tuple[int, str]] = []
    content: list[tuple[int, str]] = []  # (line number, text) of non-comment, non-empty lines
    for n, ln in enumerate(lines, start=1):
        if ln.startswith("#"):
            comments.append((n, ln))
        elif ln.strip():
            if "\x00" in ln:
                raise FapFormatError(
                    "binary data (NUL byte) in a text .fap file", line=n, where=where
                )
            content.append((n, ln))
    if not content:
        raise FapFormatError(
            "empty file: expected a header line '<version> <name> <fps> <number of frames>'",
            line=len(lines),
            where=where,
        )

    hline, header = content[0]
    tokens = header.split()
    if len(tokens) < 3:
        raise FapFormatError(
            f"header: {_show(header.strip())} has {len(tokens)} fields; expected "
            "'<version> <name> <fps> <number of frames>'",
            line=hline,
            where=where,
        )
    version = tokens[0]
    if not _NUMBER.match(version):
        raise FapFormatError(
            f"header: version {_show(version)} is not a number (expected e.g. 2.1)",
            line=hline,
            where=where,
        )
    usage = "; expected '<version> <name> <fps> <number of frames>'"
    if (
        not _NUMBER.match(tokens[-2])
        or not math.isfinite(float(tokens[-2]))
        or float(tokens[-2]) <= 0
    ):
        raise FapFormatError(
            f"header: frame rate {_show(tokens[-2])} is not a positive number" + usage,
            line=hline,
            where=where,
        )
    fps = _number(tokens[-2], hline, where, "frame rate")
    if not _INT.match(tokens[-1]) or tokens[-1].startswith("-"):
        raise FapFormatError(
            f"header: number of frames {_show(tokens[-1])} is not a non-negative integer" + usage,
            line=hline,
            where=where,
        )
    n_declared = _int(tokens[-1], hline, where, "header: number of frames")
    name = header.strip()[len(tokens[0]) :].strip()  # between the version and the last two fields
    name = name[: len(name) - len(tokens[-1])].rstrip()
    name = name[: len(name) - len(tokens[-2])].rstrip() if len(tokens) > 3 else ""

    body = content[1:]
    frames: list[FapFrame] = []
    trailing = None
    width = None
    for i in range(0, len(body), 2):
        mline, mtext = body[i]
        if i + 1 >= len(body):
            raise FapFormatError(
                f"truncated: frame {len(frames)} has a mask line but no values line; "
                "the file was cut short",
                line=mline,
                where=where,
            )
        vline, vtext = body[i + 1]
        if trailing is None:
            trailing = mtext.endswith(" ")
        flags = mtext.split()
        for tok in flags:
            if tok not in ("0", "1"):
                raise FapFormatError(
                    f"mask flag {_show(tok)} is not 0 or 1 (is a mask or values line "
                    "missing before this one?)",
                    line=mline,
                    where=where,
                )
        mask = tuple(int(t) for t in flags)
        if width is None:
            if len(mask) not in MASK_WIDTHS:
                raise FapFormatError(
                    f"mask line has {len(mask)} flags; expected 68 (or 69)", line=mline, where=where
                )
            width = len(mask)
        elif len(mask) != width:
            raise FapFormatError(
                f"mask line has {len(mask)} flags but the first mask line has {width}; "
                "every mask line must have the same width",
                line=mline,
                where=where,
            )
        if width > N_FAPS and any(mask[N_FAPS:]):
            raise FapFormatError(
                f"flag {N_FAPS + 1 + mask[N_FAPS:].index(1)} is set: FAP number out of "
                f"range (FAPs are 1..{N_FAPS}); the extra flag must be 0",
                line=mline,
                where=where,
            )
        vals = vtext.split()
        number_tok, vals = vals[0], vals[1:]
        if not _INT.match(number_tok) or number_tok.startswith("-"):
            raise FapFormatError(
                f"frame number {_show(number_tok)} must be a non-negative integer",
                line=vline,
                where=where,
            )
        number = _int(number_tok, vline, where, "frame number")
        n_set = sum(mask)
        n_full = n_set + (3 if mask[0] else 0) + (5 if mask[1] else 0)
        single = False
        if len(vals) != n_full:
            if (mask[0] or mask[1]) and len(vals) == n_set:
                single = True  # Greta layout: one value per flag also for FAPs 1/2
            else:
                raise FapFormatError(
                    f"frame {number_tok} has {len(vals)} values but its mask (line {mline}) "
                    f"sets {n_set} flags, which need {n_full} values "
                    "(4 for FAP 1, 6 for FAP 2, 1 for each other FAP)",
                    line=vline,
                    where=where,
                )
        values = tuple(_number(t, vline, where, "value") for t in vals)
        frame = FapFrame(number, mask, values, single)
        _check_high_level(frame, vline, where)
        frames.append(frame)

    if len(frames) != n_declared:
        at = body[-1][0] if body else hline
        raise FapFormatError(
            f"the header declares {n_declared} frames but the file holds {len(frames)}; "
            "fix the count in the header or complete the file",
            line=at,
            where=where,
        )

    # Comments are anchored to the frame that follows them.
    starts = [body[2 * i][0] for i in range(len(frames))]
    anchored: list[tuple[int, str]] = []
    for n, text_ in comments:
        if n < hline:
            anchored.append((-1, text_))
        else:
            anchored.append((sum(1 for s in starts if s < n), text_))
    return FapFile(
        version=version,
        name=name,
        fps=fps,
        frames=tuple(frames),
        comments=tuple(anchored),
        newline=newline,
        trailing_space=bool(trailing) if trailing is not None else True,
        header_trailing_space=header.endswith(" "),
        final_newline=final_newline,
    )


def _check_high_level(frame: FapFrame, line: int, where: str) -> None:
    if frame.single_high_level:
        return
    for fields, maximum, what in (
        (frame.viseme, MAX_VISEME, "viseme"),
        (frame.expression, MAX_EXPRESSION, "expression"),
    ):
        if fields is None:
            continue
        if not all(isinstance(v, int) for v in fields):
            raise FapFormatError(
                f"{what} fields must be integers, got {list(fields)}", line=line, where=where
            )
        selects = (fields[0], fields[1]) if what == "viseme" else (fields[0], fields[2])
        for s in selects:
            if not 0 <= s <= maximum:
                raise FapFormatError(
                    f"{what} id {s} is out of range 0..{maximum}", line=line, where=where
                )


def _fmt(v: Number) -> str:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise FapFormatError(f"value {v!r} is not a number")
    if isinstance(v, float):
        if not math.isfinite(v):
            raise FapFormatError(f"value {v!r} is not finite")
        return repr(v)
    if abs(int(v)) >= 10**MAX_DIGITS:
        raise FapFormatError(f"integer {v} has more than {MAX_DIGITS} digits")
    return str(int(v))


def write_fap(f: FapFile) -> str:
    """The ``.fap`` text of ``f``; raises ``FapFormatError`` if ``f`` could not be read back."""
    if not _NUMBER.match(f.version):
        raise FapFormatError(f"version {f.version!r} is not a number")
    if any(c in f.name for c in "\r\n\x00") or f.name != f.name.strip():
        raise FapFormatError("the sequence name must be one line without leading/trailing spaces")
    if f.newline not in ("\n", "\r\n"):
        raise FapFormatError("newline must be '\\n' or '\\r\\n'")
    if isinstance(f.fps, bool) or not isinstance(f.fps, (int, float)) or not f.fps > 0:
        raise FapFormatError(f"frame rate {f.fps!r} must be a positive number")
    out: list[str] = []
    comments = sorted(f.comments, key=lambda c: c[0])
    for j, text in comments:
        if not text.startswith("#") or any(c in text for c in "\r\n"):
            raise FapFormatError(f"comment {text!r} must be one line starting with '#'")
        if not -1 <= j <= len(f.frames):
            raise FapFormatError(f"comment anchor {j} is outside -1..{len(f.frames)}")

    def emit_comments(i: int) -> None:
        out.extend(t for j, t in comments if j == i)

    emit_comments(-1)
    parts = [f.version] + ([f.name] if f.name else []) + [_fmt(f.fps), str(len(f.frames))]
    out.append(" ".join(parts) + (" " if f.header_trailing_space else ""))
    tail = " " if f.trailing_space else ""
    width = f.mask_width
    for i, fr in enumerate(f.frames):
        emit_comments(i)
        if len(fr.mask) != width or width not in MASK_WIDTHS:
            raise FapFormatError(
                f"frame {i}: mask has {len(fr.mask)} flags; all masks must have 68 (or 69)"
            )
        if any(b not in (0, 1) for b in fr.mask) or any(fr.mask[N_FAPS:]):
            raise FapFormatError(f"frame {i}: mask flags must be 0/1 and flag 69 must be 0")
        n_set = sum(fr.mask)
        need = (
            n_set
            if fr.single_high_level
            else n_set + (3 if fr.mask[0] else 0) + (5 if fr.mask[1] else 0)
        )
        if len(fr.values) != need:
            raise FapFormatError(f"frame {i}: {len(fr.values)} values for a mask that needs {need}")
        if isinstance(fr.number, bool) or not isinstance(fr.number, int) or fr.number < 0:
            raise FapFormatError(
                f"frame {i}: frame number {fr.number!r} must be a non-negative int"
            )
        _check_high_level(fr, 0, "")
        out.append(" ".join(str(b) for b in fr.mask) + tail)
        out.append(" ".join([str(fr.number)] + [_fmt(v) for v in fr.values]) + tail)
    emit_comments(len(f.frames))
    text = f.newline.join(out)
    return text + f.newline if f.final_newline else text
