"""BML 1.0 (the SAIBA Behavior Markup Language): the subset facecast performs, read from a client's bytes.

One ``<bml>`` block (namespace ``http://www.bml-initiative.org/bml/bml-1.0`` or none) holding
behaviours, each with a unique ``id`` and sync points:

=================================== ================================================================
behaviour                           sync points (in order)
=================================== ================================================================
``<speech audio= >`` + ``<text>``    start, end, and each ``<sync id>`` mark in the text
``<faceLexeme lexeme= amount= >``    start, attackPeak, relax, end
``<faceFacs au= side= amount= >``    start, attackPeak, relax, end
``<face lexeme=|au= >``              as faceLexeme / faceFacs (the pre-1.0 element)
``<gaze target= influence= >``       start, ready, relax, end
``<head lexeme= amount= repetition>`` start, ready, strokeStart, stroke, strokeEnd, relax, end
=================================== ================================================================

A sync point's attribute is a time in seconds from the block's start (``"1.5"``) or a reference
``[block:]behaviour:point [± seconds]`` (``"s1:tm2"``, ``"g1:end + 0.5"``). ``stroke-start``,
``stroke-end``, ``attack`` / ``ready`` (faces) are read as ``strokeStart``, ``strokeEnd`` and
``attackPeak``. ``audio`` (facecast's extension) names the speech's recording: a relative path
without ``..``, resolved by whoever performs the block, never here.

The parser is pure (no I/O) and safe on hostile XML: stdlib expat with any DOCTYPE refused (so no
entity declarations, no billion laughs, no external entities), and limits on size, depth, element
count, attribute and text length. Anything malformed or unsupported raises ``BmlError`` naming the
line and element; times are only parsed here, ``server/bml`` resolves them.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, ClassVar
from xml.parsers import expat

from .errors import BmlError
from .errors import show_token as _show

__all__ = [
    "AUDIO_SUFFIXES",
    "BML_NS",
    "EXPRESSION_LEXEMES",
    "FACE_LEXEMES",
    "FACS_UNITS",
    "MAX_BML_BYTES",
    "Behaviour",
    "BmlBlock",
    "BmlError",
    "Face",
    "Gaze",
    "Head",
    "Speech",
    "SyncMark",
    "SyncRef",
    "audio_name_problem",
    "parse_bml",
]

BML_NS = "http://www.bml-initiative.org/bml/bml-1.0"
#: Largest BML document read, bytes.
MAX_BML_BYTES = 1024 * 1024
#: Deepest element nesting (``bml > speech > text > sync`` is 4).
MAX_DEPTH = 8
#: Most elements in a document, and behaviours in a block.
MAX_ELEMENTS = 4096
MAX_BEHAVIOURS = 512
#: Most attributes on an element, and characters in one attribute's value.
MAX_ATTRIBUTES = 32
MAX_ATTRIBUTE_CHARS = 1000
#: Most characters of a speech's text (the transcript aligner's limit).
MAX_TEXT_CHARS = 10000
#: Largest time in seconds a sync attribute may give (absolute or offset).
MAX_SECONDS = 3600.0

#: Sync points of each behaviour kind, in their temporal order.
SYNC_POINTS: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {
        "speech": ("start", "end"),
        "face": ("start", "attackPeak", "relax", "end"),
        "gaze": ("start", "ready", "relax", "end"),
        "head": ("start", "ready", "strokeStart", "stroke", "strokeEnd", "relax", "end"),
    }
)
_ALIASES = {"stroke-start": "strokeStart", "stroke-end": "strokeEnd", "attack-peak": "attackPeak"}
_FACE_ALIASES = {"attack": "attackPeak", "ready": "attackPeak"}

#: The six MPEG-4 expressions (FAP 2), as face lexemes.
EXPRESSION_LEXEMES: tuple[str, ...] = ("JOY", "SADNESS", "ANGER", "FEAR", "DISGUST", "SURPRISE")
#: Face lexemes: BML 1.0's core list, SMILE and FROWN, and the expressions (upper case; a client
#: may write any case). ``server/bml/lexemes.py`` maps each to FAPs.
FACE_LEXEMES: tuple[str, ...] = (
    "OBLIQUE_BROWS",
    "RAISE_BROWS",
    "RAISE_LEFT_BROW",
    "RAISE_RIGHT_BROW",
    "LOWER_BROWS",
    "LOWER_LEFT_BROW",
    "LOWER_RIGHT_BROW",
    "LOWER_MOUTH_CORNERS",
    "LOWER_LEFT_MOUTH_CORNER",
    "LOWER_RIGHT_MOUTH_CORNER",
    "RAISE_MOUTH_CORNERS",
    "RAISE_LEFT_MOUTH_CORNER",
    "RAISE_RIGHT_MOUTH_CORNER",
    "OPEN_MOUTH",
    "OPEN_LIPS",
    "WIDEN_EYES",
    "CLOSE_EYES",
    "SMILE",
    "FROWN",
    *EXPRESSION_LEXEMES,
)
#: FACS action units ``<faceFacs au=>`` takes (``server/bml/lexemes.py`` maps each to FAPs).
FACS_UNITS: tuple[int, ...] = (1, 2, 4, 5, 6, 7, 9, 10, 12, 15, 17, 20, 25, 26, 43, 45)
HEAD_LEXEMES: tuple[str, ...] = ("NOD", "SHAKE", "TILT")
GAZE_TARGETS: tuple[str, ...] = ("camera", "user")
GAZE_INFLUENCES: tuple[str, ...] = ("EYES", "HEAD", "NECK")
GAZE_DIRECTIONS: tuple[str, ...] = (
    "RIGHT",
    "LEFT",
    "UP",
    "DOWN",
    "UPRIGHT",
    "UPLEFT",
    "DOWNRIGHT",
    "DOWNLEFT",
)
SIDES: tuple[str, ...] = ("BOTH", "LEFT", "RIGHT")

_BEHAVIOURS = ("speech", "face", "faceLexeme", "faceFacs", "gaze", "head")
_SUPPORTED = ", ".join(_BEHAVIOURS)
_ID = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]{0,63}\Z")
_POINT = r"[A-Za-z_][A-Za-z0-9_]*(?:-[A-Za-z_][A-Za-z0-9_]*)*"
_NUMBER = r"[0-9]+(?:\.[0-9]*)?(?:[eE][+-]?[0-9]+)?|\.[0-9]+(?:[eE][+-]?[0-9]+)?"
_MARK = re.compile(f"(?:{_POINT})\\Z")
_ABSOLUTE = re.compile(rf"\s*(?P<sign>[+-]?)(?P<num>{_NUMBER})\s*\Z")
_REFERENCE = re.compile(
    rf"\s*(?:(?P<block>[A-Za-z_][A-Za-z0-9_.-]*):)?(?P<id>[A-Za-z_][A-Za-z0-9_.-]*):"
    rf"(?P<point>{_POINT})\s*(?:(?P<sign>[+-])\s*(?P<num>{_NUMBER})\s*)?\Z"
)


@dataclass(frozen=True)
class SyncRef:
    """When a sync point happens: ``offset`` seconds after sync point ``point`` of behaviour ``ref``,
    or, with ``ref`` None, ``offset`` seconds after the block's start."""

    ref: str | None
    point: str
    offset: float

    def __str__(self) -> str:
        if self.ref is None:
            return f"{self.offset:g}"
        off = f" {'+' if self.offset >= 0 else '-'} {abs(self.offset):g}" if self.offset else ""
        return f"{self.ref}:{self.point}{off}"


@dataclass(frozen=True)
class Behaviour:
    """One behaviour: its ``id``, the ``element`` it was written as, its ``line`` in the document,
    and ``sync``: the constraints its attributes put on its sync points (canonical names)."""

    kind: ClassVar[str] = ""
    id: str
    element: str
    line: int
    sync: Mapping[str, SyncRef]

    def points(self) -> tuple[str, ...]:
        """Its sync points, in temporal order."""
        return SYNC_POINTS[self.kind]


@dataclass(frozen=True)
class SyncMark:
    """A ``<sync id>`` inside a speech's text: ``chars`` characters and ``words`` words precede it."""

    id: str
    chars: int
    words: int
    line: int


@dataclass(frozen=True)
class Speech(Behaviour):
    """Speech: ``audio`` (a relative file name, as written) and/or ``text`` with sync ``marks``."""

    kind: ClassVar[str] = "speech"
    audio: str | None = None
    text: str | None = None
    marks: tuple[SyncMark, ...] = ()

    def points(self) -> tuple[str, ...]:
        """start, the marks in text order, end."""
        return ("start", *(m.id for m in self.marks), "end")


@dataclass(frozen=True)
class Face(Behaviour):
    """A facial expression: a ``lexeme`` (``FACE_LEXEMES``) or a FACS action unit ``au`` on
    ``side``, at ``amount`` (0..1) of its full strength."""

    kind: ClassVar[str] = "face"
    lexeme: str | None = None
    au: int | None = None
    side: str = "BOTH"
    amount: float = 1.0


@dataclass(frozen=True)
class Gaze(Behaviour):
    """Look at a named ``target`` (``camera``/``user``) or at ``point`` (x, y, z in the face's mesh
    units and axes), turned by ``offset_angle`` degrees towards ``offset_direction``; ``influence``
    EYES (eyes only) or HEAD/NECK (head and eyes)."""

    kind: ClassVar[str] = "gaze"
    target: str | None = None
    point: tuple[float, float, float] | None = None
    influence: str = "EYES"
    offset_angle: float = 0.0
    offset_direction: str = "RIGHT"


@dataclass(frozen=True)
class Head(Behaviour):
    """A head movement: ``lexeme`` NOD, SHAKE or TILT, ``amount`` 0..1 of the performer's full
    gesture, ``repetition`` strokes (NOD, SHAKE)."""

    kind: ClassVar[str] = "head"
    lexeme: str = "NOD"
    amount: float = 1.0
    repetition: int = 1


@dataclass(frozen=True)
class BmlBlock:
    """A parsed ``<bml>`` block: its ``id`` and its ``behaviours`` in document order."""

    id: str
    behaviours: tuple[Behaviour, ...] = ()
    composition: str = "MERGE"
    by_id: Mapping[str, Behaviour] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "by_id", MappingProxyType({b.id: b for b in self.behaviours}))


# ---------------------------------------------------------------------------------------- XML


@dataclass
class _Node:
    tag: str  # local name
    ns: str  # namespace URI ('' for none)
    attrs: dict[str, str]
    line: int
    children: list[_Node | str] = field(default_factory=list)


def _tree(data: bytes, where: str) -> _Node:
    """The document's element tree, parsed by expat with DTDs refused and the limits checked."""
    parser = expat.ParserCreate(namespace_separator=" ")
    parser.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)
    parser.buffer_text = True
    stack: list[_Node] = []
    root: list[_Node] = []
    count = [0, 0]  # elements, text characters

    def refuse(reason: str, element: str = "") -> None:
        raise BmlError(reason, line=parser.CurrentLineNumber, element=element, where=where)

    def doctype(name: str, *_: object) -> None:
        refuse(
            "a DOCTYPE (DTD) is not allowed in BML: entities and external references are refused; "
            "remove the <!DOCTYPE ...> declaration"
        )

    def entity(name: str, *_: object) -> None:
        refuse(f"entity declaration {_show(name)} is not allowed in BML")

    def external(*_: object) -> int:
        refuse("external entities are not allowed in BML")
        return 0

    def start(name: str, attrs: dict[str, str]) -> None:
        ns, _, local = name.rpartition(" ")
        count[0] += 1
        if count[0] > MAX_ELEMENTS:
            refuse(f"more than {MAX_ELEMENTS} elements; split the performance", local)
        if len(stack) >= MAX_DEPTH:
            refuse(f"elements nested deeper than {MAX_DEPTH}", local)
        if len(attrs) > MAX_ATTRIBUTES:
            refuse(f"more than {MAX_ATTRIBUTES} attributes", local)
        plain: dict[str, str] = {}
        for key, value in attrs.items():
            if len(value) > MAX_ATTRIBUTE_CHARS:
                refuse(
                    f"attribute {_show(key)} is longer than {MAX_ATTRIBUTE_CHARS} characters", local
                )
            if " " not in key:  # namespaced attributes are other tools' extensions: ignored
                plain[key] = value
        node = _Node(local, ns, plain, parser.CurrentLineNumber)
        if stack:
            stack[-1].children.append(node)
        else:
            root.append(node)
        stack.append(node)

    def end(name: str) -> None:
        stack.pop()

    def chars(text: str) -> None:
        count[1] += len(text)
        if count[1] > MAX_BML_BYTES:
            refuse("too much text")
        if stack:
            stack[-1].children.append(text)

    parser.StartDoctypeDeclHandler = doctype
    parser.EntityDeclHandler = entity
    parser.UnparsedEntityDeclHandler = entity
    parser.NotationDeclHandler = entity
    parser.ExternalEntityRefHandler = external
    parser.StartElementHandler = start
    parser.EndElementHandler = end
    parser.CharacterDataHandler = chars
    try:
        parser.Parse(data, True)
    except BmlError:  # raised by a handler above: expat stops and lets it through
        raise
    except expat.ExpatError as e:
        raise BmlError(
            f"not well-formed XML: {expat.ErrorString(e.code)} (column {e.offset + 1})",
            line=e.lineno,
            element=stack[-1].tag if stack else "",
            where=where,
        ) from None
    except (ValueError, LookupError, UnicodeError, RecursionError, MemoryError) as e:  # encodings
        raise BmlError(f"cannot read the XML: {str(e)[:200]}", where=where) from None
    if not root:
        raise BmlError("no <bml> element", where=where)
    return root[0]


# ------------------------------------------------------------------------------------ values


class _Reader:
    """Reads one element's attributes, refusing (BmlError with line and element) what is wrong."""

    def __init__(self, node: _Node, where: str) -> None:
        self.node, self.where = node, where
        self.used: set[str] = set()

    def refuse(self, reason: str, line: int | None = None) -> BmlError:
        return BmlError(
            reason,
            line=self.node.line if line is None else line,
            element=self.node.tag,
            where=self.where,
        )

    def get(self, name: str) -> str | None:
        self.used.add(name)
        return self.node.attrs.get(name)

    def number(self, name: str, default: float, lo: float, hi: float) -> float:
        raw = self.get(name)
        if raw is None:
            return default
        value = _number(raw)
        if not (math.isfinite(value) and lo <= value <= hi):
            raise self.refuse(f"{name}={_show(raw)} must be a number from {lo:g} to {hi:g}")
        return value

    def choice(self, name: str, options: tuple[str, ...], default: str | None) -> str | None:
        raw = self.get(name)
        if raw is None:
            return default
        value = raw.strip().upper().replace("_", "")  # UP_RIGHT: UPRIGHT (no option has '_')
        if value not in options:
            raise self.refuse(
                f"{name}={_show(raw)} is not supported; supported: {', '.join(options)}"
            )
        return value

    def check_known(self, extra: tuple[str, ...]) -> None:
        known = sorted(self.used | set(extra))
        for key in self.node.attrs:
            if key not in self.used and key not in extra:
                raise self.refuse(f"unknown attribute {_show(key)}; known: {', '.join(known)}")


def _number(text: str) -> float:
    """A plain decimal number (no nan, inf, '_' or hex), else nan."""
    m = _ABSOLUTE.match(text)
    return float(m["sign"] + m["num"]) if m else math.nan


def _sync_ref(raw: str, block: str) -> SyncRef | str:
    """The reference in a sync attribute, or why it is not one."""
    if len(raw) > 200:
        return "is too long"
    m = _ABSOLUTE.match(raw)
    if m:
        value = float(m["sign"] + m["num"])
        if not (math.isfinite(value) and 0.0 <= value <= MAX_SECONDS):
            return f"must be from 0 to {MAX_SECONDS:g} seconds after the block's start"
        return SyncRef(None, "", value)
    m = _REFERENCE.match(raw)
    if not m:
        return (
            "is neither seconds ('1.5') nor a reference 'behaviour:syncpoint [+|- seconds]' "
            "('s1:tm1', 'g1:end + 0.5')"
        )
    if m["block"] is not None and m["block"] != block:
        return f"refers to BML block {_show(m['block'])}; only this block ({_show(block)}) is known"
    offset = 0.0
    if m["num"] is not None:
        offset = float(m["num"]) * (-1.0 if m["sign"] == "-" else 1.0)
        if not (math.isfinite(offset) and abs(offset) <= MAX_SECONDS):
            return f"has an offset beyond ±{MAX_SECONDS:g} seconds"
    point = _ALIASES.get(m["point"], m["point"])
    return SyncRef(m["id"], point, offset)


def _syncs(r: _Reader, kind: str, block: str) -> dict[str, SyncRef]:
    """The sync attributes of a behaviour of ``kind`` (canonical point names)."""
    points = SYNC_POINTS[kind]
    names = {p: p for p in points}
    names.update({a: p for a, p in _ALIASES.items() if p in points})
    if kind == "face":
        names.update(_FACE_ALIASES)
    out: dict[str, SyncRef] = {}
    for attr, point in names.items():
        raw = r.get(attr)
        if raw is None:
            continue
        if point in out:
            raise r.refuse(f"sync point {point} is given twice ({attr} and another name)")
        ref = _sync_ref(raw, block)
        if isinstance(ref, str):
            raise r.refuse(f"{attr}={_show(raw)} {ref}")
        out[point] = ref
    return out


# ------------------------------------------------------------------------------- behaviours


#: Suffixes of a speech's recording.
AUDIO_SUFFIXES: tuple[str, ...] = (".wav", ".flac", ".ogg")


def audio_name_problem(name: str) -> str | None:
    """Why ``name`` cannot name a speech's recording, or None: it must be a relative path of at
    most 255 printable characters, without ``..``, empty or drive parts, ending in an audio
    suffix. Whoever performs the block resolves it among the files it was given (next to the BML
    file, or the files uploaded with it), never elsewhere."""
    if not name or len(name) > 255 or not name.isprintable():
        return "must be a file name of 1 to 255 printable characters"
    parts = name.replace("\\", "/").split("/")
    if name.startswith(("/", "\\")) or ":" in name:
        return "must be a relative file name (no absolute path, drive or URL)"
    if any(p in ("", ".", "..") for p in parts):
        return "must not contain '..', '.' or empty path parts"
    if not name.lower().endswith(AUDIO_SUFFIXES):
        return f"must end with {', '.join(AUDIO_SUFFIXES)}"
    return None


def _speech(node: _Node, r: _Reader, common: dict[str, Any], block: str) -> Speech:
    audio = r.get("audio")
    if audio is not None:
        audio = audio.strip()
        problem = audio_name_problem(audio)
        if problem:
            raise r.refuse(f"audio={_show(audio)} {problem} (e.g. audio='hello.wav')")
    r.check_known(())
    text: str | None = None
    marks: list[SyncMark] = []
    for child in node.children:
        if isinstance(child, str):
            if child.strip():
                raise r.refuse("text of a speech goes inside its <text> element")
            continue
        if child.tag != "text" or child.ns not in ("", BML_NS):
            raise BmlError(
                "unsupported in <speech>; it takes one <text> (with <sync id> marks)",
                line=child.line,
                element=child.tag,
                where=r.where,
            )
        if text is not None:
            raise BmlError(
                "a speech has one <text>", line=child.line, element="text", where=r.where
            )
        parts: list[str] = []
        for part in child.children:
            if isinstance(part, str):
                parts.append(part)
                continue
            pr = _Reader(part, r.where)
            if part.tag != "sync" or part.ns not in ("", BML_NS):
                raise pr.refuse("unsupported in <text>; it takes words and <sync id='...'/> marks")
            if part.children:
                raise pr.refuse("a <sync> mark is empty: <sync id='tm1'/>")
            mid = (pr.get("id") or "").strip()
            pr.check_known(())
            if not _MARK.match(mid) or len(mid) > 64:
                raise pr.refuse(
                    f"id={_show(mid)} must be a name (letters, digits, '_', '-'; e.g. 'tm1')"
                )
            if mid in ("start", "end") or any(m.id == mid for m in marks):
                raise pr.refuse(
                    f"sync id {_show(mid)} is used twice in this speech (or is start/end)"
                )
            before = " ".join("".join(parts).split())
            marks.append(SyncMark(mid, len(before), len(before.split()), part.line))
        text = " ".join("".join(parts).split())
        if len(text) > MAX_TEXT_CHARS:
            raise BmlError(
                f"the text is longer than {MAX_TEXT_CHARS} characters",
                line=child.line,
                element="text",
                where=r.where,
            )
    if audio is None:
        raise r.refuse(
            "a speech needs its recording: audio='hello.wav' (its <text>, if any, is the "
            "transcript, aligned to the audio; facecast does not synthesise speech)"
        )
    if marks and not (text or "").strip():
        raise r.refuse("sync marks need words around them in the <text>")
    return Speech(**common, audio=audio, text=text or None, marks=tuple(marks))


def _face(node: _Node, r: _Reader, common: dict[str, Any], element: str) -> Face:
    kind = r.get("type")  # SmartBody's <face type="facs" au=...>
    au_raw = r.get("au")
    lexeme_raw = r.get("lexeme")
    facs = element == "faceFacs" or (element == "face" and au_raw is not None)
    if kind is not None and kind.strip().lower() not in ("facs", "lexeme"):
        raise r.refuse(f"type={_show(kind)} is not supported; supported: facs, lexeme")
    amount = r.number("amount", 1.0, 0.0, 1.0)
    side = r.choice("side", SIDES, "BOTH") or "BOTH"
    if facs:
        if lexeme_raw is not None:
            raise r.refuse("give either au (FACS) or lexeme, not both")
        if au_raw is None:
            raise r.refuse(f"au is required: one of {', '.join(map(str, FACS_UNITS))}")
        au = int(au_raw) if au_raw.strip().isdigit() and len(au_raw) < 4 else -1
        if au not in FACS_UNITS:
            raise r.refuse(
                f"au={_show(au_raw)} is not supported; supported: {', '.join(map(str, FACS_UNITS))}"
            )
        r.check_known(())
        return Face(**common, au=au, side=side, amount=amount)
    if element == "faceLexeme" and au_raw is not None:
        raise r.refuse("au goes with <faceFacs>; <faceLexeme> takes a lexeme")
    if lexeme_raw is None:
        raise r.refuse(f"lexeme is required; supported: {', '.join(FACE_LEXEMES)}")
    lexeme = lexeme_raw.strip().upper()
    if lexeme not in FACE_LEXEMES:
        raise r.refuse(
            f"lexeme={_show(lexeme_raw)} is not supported; supported: {', '.join(FACE_LEXEMES)}"
        )
    if side != "BOTH":
        raise r.refuse("side goes with FACS units (<faceFacs au= side=>); lexemes name their side")
    r.check_known(())
    return Face(**common, lexeme=lexeme, amount=amount)


def _gaze(node: _Node, r: _Reader, common: dict[str, Any]) -> Gaze:
    raw = r.get("target")
    if raw is None or not raw.strip():
        raise r.refuse("target is required: camera, user, or a point 'x y z' (mesh units)")
    target: str | None = raw.strip().lower()
    point: tuple[float, float, float] | None = None
    if target not in GAZE_TARGETS:
        cells = raw.replace(",", " ").split()
        values = [_number(c) for c in cells]
        if len(values) != 3 or not all(math.isfinite(v) and abs(v) <= 1e6 for v in values):
            raise r.refuse(
                f"target={_show(raw)} is not supported; supported: camera, user, or a point "
                "'x y z' (three numbers, mesh units)"
            )
        target, point = None, (values[0], values[1], values[2])
        if r.get("offsetAngle") is not None:
            raise r.refuse("offsetAngle goes with a named target (camera, user), not a point")
    influence = r.choice("influence", GAZE_INFLUENCES, "EYES") or "EYES"
    angle = r.number("offsetAngle", 0.0, -90.0, 90.0)
    direction = r.choice("offsetDirection", GAZE_DIRECTIONS, "RIGHT") or "RIGHT"
    r.check_known(())
    return Gaze(
        **common,
        target=target,
        point=point,
        influence=influence,
        offset_angle=angle,
        offset_direction=direction,
    )


def _head(node: _Node, r: _Reader, common: dict[str, Any]) -> Head:
    lexeme = r.choice("lexeme", HEAD_LEXEMES, None)
    if lexeme is None:
        raise r.refuse(f"lexeme is required; supported: {', '.join(HEAD_LEXEMES)}")
    amount = r.number("amount", 1.0, 0.0, 1.0)
    rep = r.number("repetition", 1.0, 1.0, 20.0)
    if rep != int(rep):
        raise r.refuse(f"repetition={_show(r.node.attrs['repetition'])} must be a whole number")
    r.check_known(())
    return Head(**common, lexeme=lexeme, amount=amount, repetition=int(rep))


def _behaviour(node: _Node, block: str, where: str) -> Behaviour:
    if node.ns not in ("", BML_NS) or node.tag not in _BEHAVIOURS:
        raise BmlError(
            f"unsupported behaviour; supported: {_SUPPORTED}",
            line=node.line,
            element=node.tag,
            where=where,
        )
    r = _Reader(node, where)
    bid = (r.get("id") or "").strip()
    if not _ID.match(bid):
        raise r.refuse(
            f"id={_show(bid)} must be a name of at most 64 letters, digits, '_', '.', '-' "
            "starting with a letter (every behaviour needs one, unique in the block)"
        )
    kind = {"faceLexeme": "face", "faceFacs": "face"}.get(node.tag, node.tag)
    common = {
        "id": bid,
        "element": node.tag,
        "line": node.line,
        "sync": MappingProxyType(_syncs(r, kind, block)),
    }
    if kind != "speech" and any(isinstance(c, _Node) or c.strip() for c in node.children):
        raise r.refuse(f"<{node.tag}> takes no content")
    if kind == "speech":
        return _speech(node, r, common, block)
    if kind == "face":
        return _face(node, r, common, node.tag)
    if kind == "gaze":
        return _gaze(node, r, common)
    return _head(node, r, common)


def parse_bml(data: bytes | str, *, where: str = "") -> BmlBlock:
    """Parse a BML document holding one ``<bml>`` block.

    Args:
        data: the document's bytes (any encoding expat reads; UTF-8 by default) or text.
        where: the document's name for messages (a file name).
    Raises:
        BmlError: malformed XML, a DOCTYPE, a limit passed, an unsupported behaviour or attribute,
            a bad value; the message names the line and element.
    """
    raw = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    if len(raw) > MAX_BML_BYTES:
        raise BmlError(
            f"the BML document is {len(raw)} bytes, more than {MAX_BML_BYTES}; split the "
            "performance into shorter blocks",
            where=where,
        )
    root = _tree(raw, where)
    r = _Reader(root, where)
    if root.tag != "bml" or root.ns not in ("", BML_NS):
        raise r.refuse(f"the document's root must be <bml> (namespace {BML_NS} or none)")
    block = (r.get("id") or "bml1").strip()
    if not _ID.match(block):
        raise r.refuse(f"id={_show(block)} must be a name (letters, digits, '_', '.', '-')")
    composition = r.choice("composition", ("MERGE", "APPEND", "REPLACE"), "MERGE") or "MERGE"
    r.check_known(("characterId",))
    behaviours: list[Behaviour] = []
    seen: dict[str, int] = {}
    for child in root.children:
        if isinstance(child, str):
            if child.strip():
                raise r.refuse("text outside a behaviour (speech text goes in <speech><text>)")
            continue
        b = _behaviour(child, block, where)
        if b.id in seen:
            raise BmlError(
                f"id {_show(b.id)} is already used by the behaviour on line {seen[b.id]}",
                line=b.line,
                element=b.element,
                where=where,
            )
        seen[b.id] = b.line
        behaviours.append(b)
        if len(behaviours) > MAX_BEHAVIOURS:
            raise BmlError(
                f"more than {MAX_BEHAVIOURS} behaviours; split the performance",
                line=b.line,
                element=b.element,
                where=where,
            )
    if not behaviours:
        raise r.refuse(f"the block has no behaviours; supported: {_SUPPORTED}")
    return BmlBlock(block, tuple(behaviours), composition)
