"""``VERTICES_COMPACT`` frames: error-bounded, rigid-aware, temporally predicted vertex streams.

A session's compact stream needs, on both sides, the face's topology (``topology.py``): its rest
vertices ``rest (V, 3) float32`` and rigid group per vertex ``groups (V,) uint8``. Each frame sends

- one rigid transform per group, ``(G, 3, 4) float32`` (``[R | t]``, world = R · local + t);
- the vertices in their group's local frame, quantised on a grid of ``step`` (face units, fixed
  for the session): integer cells ``q (V, 3) int32``, position = R_g · (q · step) + t_g;
- ``q`` minus a reference: for a **key** frame the rest mesh on the same grid
  (``base = floor(rest / step + 0.5)``, float64), for a **delta** frame the ``q`` of the key frame
  it names; the difference is differenced again along the vertex order per axis and zigzagged to
  ``uint32``; most of these are 0, so the payload (format 2) is a bitmap of the non-zero ones per
  axis, then only those, as byte planes, deflated (zlib format): deflate sees 8-25 % of the bytes
  it saw in format 1 (all the values), and ISA-L codes that as small as zlib-ng coded format 1 in
  under half the time (``bench/compact_stream.py``).

A delta depends only on its key, so a viewer that skips any number of deltas still decodes every
frame it gets exactly; a viewer that missed the key waits for the next one (``None`` from
``CompactDecoder.decode``), never showing a wrong face. ``README.md`` beside this file gives
every byte. With ``step = 2 · tolerance / √3 · (1 − m)`` (``m``: ``float_margin``, 2⁻⁸ and more
for large coordinates) a vertex rounded to its cell is within
``tolerance`` (Euclidean) of the input; the encoder keeps a vertex's reference cell instead when
that is within the tolerance too, which turns small motions into zeros.

Decoding raises only ``FrameError``; encoders raise ``ValueError`` for bad arguments.
"""

from __future__ import annotations

import math
import struct
import threading
import zlib
from dataclasses import dataclass
from types import ModuleType

import numpy as np

try:  # zlib-ng: the same deflate streams (Z_RLE output is byte for byte zlib's size), ~2x faster
    from zlib_ng import zlib_ng

    _deflate: ModuleType = zlib_ng
except ImportError:  # pragma: no cover - a platform without its wheel
    _deflate = zlib
try:  # ISA-L: on format 2's bitmaps and values as small as zlib-ng's Z_RLE, in under half the time
    from isal import isal_zlib

    _isal: ModuleType | None = isal_zlib
except ImportError:  # pragma: no cover - a platform without its wheel
    _isal = None

from .errors import FrameError
from .frames import HEADER_SIZE, MAX_VERTICES, Header, Kind, _header, parse_header

__all__ = [
    "KEY",
    "MAX_GROUPS",
    "CompactDecoder",
    "CompactEncoder",
    "CompactFrame",
    "grid_base",
    "parse_compact",
    "step_for_tolerance",
]

#: Header flag bit of a key frame.
KEY = 1
#: Most rigid groups a frame may carry.
MAX_GROUPS = 255
#: Version of the compact frame layout (sub-header bytes 42-43); 1 (no bitmaps) is not read.
FORMAT = 2
#: ref (u32), step (f32), G (u8), planes (u8), format (u16), zlen (u32), nnz (u32): 20 bytes after
#: the header.
_SUB = struct.Struct("<IfBBHII")
SUB_SIZE = _SUB.size
#: Largest grid step a decoder accepts (face units); with |R| <= 1 and |q| < 2^31 positions stay finite.
MAX_STEP = 1e6
#: Cells are kept within ±2²³ so ``q · step`` is exact in float32.
_MAX_CELL = 1 << 23


def float_margin(tolerance: float, extent: float = 0.0) -> float:
    """Share of ``tolerance`` kept for float32 arithmetic (the encoder's and decoders'
    transforms) with coordinates up to ``extent`` (face units) from the origin: 2⁻⁸, plus 2⁻²¹
    per grid step of extent (their rounding grows with the coordinates; measured: about 2⁻²⁴
    per step on each side). Raises ``ValueError`` when no grid fits (tolerance too small)."""
    if not (math.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance must be a positive number, got {tolerance}")
    if not (math.isfinite(extent) and extent >= 0):
        raise ValueError(f"extent must be a finite number >= 0, got {extent}")
    m = 2.0**-8 + extent / (2.0 * tolerance / math.sqrt(3.0)) * 2.0**-21
    if m > 0.5:
        raise ValueError(
            f"tolerance {tolerance:g} is too small for coordinates up to {extent:g} in float32"
        )
    return m


def step_for_tolerance(tolerance: float, extent: float = 0.0) -> float:
    """Grid step (face units, as float32) whose rounding error is within ``tolerance`` (face
    units, Euclidean) for coordinates up to ``extent`` from the origin: ``2 · tol / √3`` less
    ``float_margin`` of it."""
    m = float_margin(tolerance, extent)
    return float(np.float32(2.0 * tolerance / math.sqrt(3.0) * (1.0 - m)))


def grid_base(rest: np.ndarray, step: float) -> np.ndarray:
    """``(V, 3) int32`` cells of the rest vertices: ``floor(rest / step + 0.5)`` in float64."""
    b = np.floor(np.asarray(rest, np.float32).astype(np.float64) / float(np.float32(step)) + 0.5)
    if b.size and np.abs(b).max() >= _MAX_CELL:
        raise ValueError(
            "the rest mesh spans more than 2^23 grid steps: the tolerance is too small"
        )
    return b.astype(np.int32)


def _unzigzag_planes(raw: bytes | memoryview, planes: int, n: int) -> np.ndarray:
    """``raw``: ``planes`` byte planes (little end first) of ``n`` zigzagged values, as
    ``CompactEncoder.encode`` writes them -> ``(n,)`` signed integers, in the narrowest type
    that holds them (int8 for one plane, int16 for two, else int32)."""
    p = np.frombuffer(raw, np.uint8, planes * n).reshape(planes, n)
    if planes == 1:
        u = p[0]
    elif planes == 2:
        u = p[1].astype(np.uint16)
        u <<= np.uint16(8)
        u |= p[0]
    else:
        u = p[0].astype(np.uint32)
        for k in range(1, planes):
            u |= p[k].astype(np.uint32) << np.uint32(8 * k)
    one = u.dtype.type(1)
    v: np.ndarray = u >> one
    v ^= -(u & one)  # two's complement negation of 0 or 1: all zeros or all ones
    return v.view(v.dtype.str.replace("u", "i"))


def bitmap_size(n_vertices: int) -> int:
    """Bytes of one axis's bitmap of non-zero values: ``ceil(V / 8)``."""
    return (n_vertices + 7) // 8


def pack_payload(zz: np.ndarray, planes: int) -> tuple[int, bytes]:
    """``zz (3, V)``: zigzagged values (any integer type; only their low ``planes`` bytes are
    kept) -> ``(nnz, raw)``: the count of non-zero ones and the payload before deflate: per axis a
    bitmap of the non-zero values (``bitmap_size(V)`` bytes, bit ``i % 8`` of byte ``i // 8``,
    least significant first), then the ``nnz`` non-zero values (axis-major, vertex order) as
    ``planes`` byte planes, little end first."""
    mask = zz != 0
    bits = np.packbits(mask, axis=1, bitorder="little")  # (3, ceil(V / 8)): each axis padded
    vals = np.compress(mask.reshape(-1), zz.reshape(-1))
    k = len(vals)
    if planes > 1 and vals.itemsize > 1:  # byte planes: byte 0 of every value, then byte 1...
        vals = np.ascontiguousarray(vals.view(np.uint8).reshape(k, vals.itemsize)[:, :planes].T)
    return k, bits.tobytes() + vals.tobytes()


def unpack_payload(raw: bytes | memoryview, planes: int, nnz: int, n_vertices: int) -> np.ndarray:
    """``pack_payload``'s ``raw`` (exactly ``3 bitmap_size(V) + planes nnz`` bytes) -> the
    differences ``(3, V) int32`` (un-zigzagged). Raises ``FrameError`` when the bitmaps' set bits
    are not ``nnz``, a bit past ``V`` is set, or a value marked non-zero is 0."""
    n, nb = n_vertices, bitmap_size(n_vertices)
    bits = np.frombuffer(raw, np.uint8, 3 * nb).reshape(3, nb)
    if n % 8 and bits[:, -1].max(initial=0) >> (n % 8):
        raise FrameError("bitmap bits past the last vertex must be 0", where="payload")
    mask = np.unpackbits(bits, axis=1, count=n, bitorder="little").view(bool)
    if int(np.count_nonzero(mask)) != nnz:
        raise FrameError(
            f"the bitmaps mark {int(np.count_nonzero(mask))} non-zero values, nnz says {nnz}",
            where="payload",
        )
    d = _unzigzag_planes(memoryview(raw)[3 * nb :], planes, nnz)
    if nnz and not d.all():
        raise FrameError("a value the bitmap marks as non-zero is 0", where="payload")
    dd = np.zeros((3, n), np.int32)
    dd.reshape(-1)[mask.reshape(-1)] = d
    return dd


_scratch = threading.local()


def _scratch_buffers(n: int) -> dict[str, np.ndarray]:
    """This thread's scratch arrays for frames of ``n`` vertices, shared by all its encoders: a
    server encoding many sessions' frames on a few threads touches one set of them, which stays
    in the CPU cache, instead of one set per session (about 2 MB each on the 25k-vertex head)."""
    have: dict[int, dict[str, np.ndarray]] | None = getattr(_scratch, "by_n", None)
    if have is None:
        have = _scratch.by_n = {}
    b = have.get(n)
    if b is None:
        if len(have) >= 4:  # a few faces per thread at most; drop the others
            have.clear()
        b = have[n] = {
            "vt": np.ones((4, n), np.float32),  # homogeneous: rows x, y, z, 1
            "local": np.empty((3, n), np.float32),
            "fd": np.empty((3, n), np.float32),
            "ddf": np.empty((3, n), np.float32),
            "dd": np.empty((3, n), np.int32),
            "dist": np.empty(n, np.float32),
            "move": np.empty(n, bool),
            "movef": np.empty(n, np.float32),
            "i8": np.empty((3, n), np.int8),
            "i16": np.empty((3, n), np.int16),
            "s8": np.empty((3, n), np.int8),
            "s16": np.empty((3, n), np.int16),
            "s32": np.empty((3, n), np.int32),
        }
    return b


def world_to_cells(tr: np.ndarray, step: float | np.ndarray) -> np.ndarray:
    """``(..., 3, 4) float32`` maps from world to the local frames of rigid transforms
    ``tr (..., 3, 4)`` in grid steps of ``step`` (or of steps broadcast against ``tr``):
    ``[R⁻¹ / step | −R⁻¹ t / step]``, in float64 and then rounded (a stack of many frames'
    transforms gives each the bits it gets alone)."""
    m = np.empty(tr.shape, np.float64)
    m[..., :3] = np.linalg.inv(tr[..., :3].astype(np.float64)) * (1.0 / step)
    m[..., 3:] = -np.matmul(m[..., :3], tr[..., 3:].astype(np.float64))
    return m.astype(np.float32)


def rigid_motions(tr: np.ndarray) -> np.ndarray:
    """``(J,) bool``: whether each of ``tr (J, G, 3, 4) float32``'s transform sets is finite with
    ``|det R - 1| <= 1e-3`` for every group (one LAPACK call for the stack: per set, the same
    determinants as alone, at a fraction of the call's ~20 us)."""
    finite = np.isfinite(tr).all(axis=(1, 2, 3))
    rot = np.where(finite[:, None, None, None], tr[..., :3], np.float32(1))  # no NaN warnings
    off = np.any(np.abs(np.linalg.det(rot) - 1) > 1e-3, axis=1)
    ok: np.ndarray = finite & ~off
    return ok


#: A group in more runs of the vertex order than this is transformed over all vertices and kept
#: where it belongs (one matmul and one masked copy: cheaper than gathering and scattering it).
_MAX_RUNS = 8


@dataclass(frozen=True, slots=True)
class _GroupPlan:
    """How to move every vertex by its group's ``(3, 4)`` transform, fast: the largest group over
    all vertices (one matmul), then each other group over its few runs of the vertex order, or
    over all vertices with a masked copy when it is scattered."""

    first: int
    others: tuple[tuple[int, tuple[slice, ...] | np.ndarray], ...]

    @staticmethod
    def of(groups: np.ndarray, n_groups: int) -> _GroupPlan:
        sizes = np.bincount(groups, minlength=n_groups)
        first = int(sizes.argmax())
        others: list[tuple[int, tuple[slice, ...] | np.ndarray]] = []
        for g in range(n_groups):
            idx = np.flatnonzero(groups == g)
            if g == first or not len(idx):
                continue
            cuts = np.flatnonzero(np.diff(idx) != 1) + 1
            if len(cuts) < _MAX_RUNS:
                others.append(
                    (g, tuple(slice(int(a[0]), int(a[-1]) + 1) for a in np.split(idx, cuts)))
                )
            else:
                others.append((g, groups == g))
        return _GroupPlan(first, tuple(others))

    def apply(self, m: np.ndarray, vt: np.ndarray, out: np.ndarray, tmp: np.ndarray) -> None:
        """``out (3, V) = m[group] @ vt (4, V)`` per vertex (``vt`` homogeneous: last row 1);
        ``tmp (3, V)`` scratch."""
        np.matmul(m[self.first], vt, out=out)
        for g, where in self.others:
            if isinstance(where, tuple):
                for sp in where:
                    np.matmul(m[g], vt[:, sp], out=out[:, sp])
            else:
                np.matmul(m[g], vt, out=tmp)
                np.copyto(out, tmp, where=where)


@dataclass(frozen=True, slots=True)
class CompactFrame:
    """A parsed compact frame before decoding (no state needed)."""

    header: Header
    ref: int  #: seq of the key frame this frame is relative to (a key names itself)
    step: float  #: grid step, face units
    transforms: np.ndarray  #: (G, 3, 4) float32
    planes: int
    nnz: int  #: non-zero values the payload carries
    payload: memoryview  #: zlib stream

    @property
    def key(self) -> bool:
        return bool(self.header.flags & KEY)


def parse_compact(data: bytes | bytearray | memoryview) -> CompactFrame:
    """Check a compact frame's header, sub-header and length (not its zlib stream)."""
    h = parse_header(data)
    if h.kind is not Kind.VERTICES_COMPACT:
        raise FrameError(f"expected a VERTICES_COMPACT frame, got {h.kind.name}", where="byte 5")
    if h.count > MAX_VERTICES:
        raise FrameError(
            f"count {h.count} is over the limit of {MAX_VERTICES}", where="bytes 12-15"
        )
    if len(data) < HEADER_SIZE + SUB_SIZE:
        raise FrameError(
            f"compact frame of {len(data)} bytes is shorter than its "
            f"{HEADER_SIZE + SUB_SIZE}-byte headers"
        )
    ref, step, g, planes, fmt, zlen, nnz = _SUB.unpack_from(data, HEADER_SIZE)
    if fmt != FORMAT:
        raise FrameError(
            f"compact format {fmt} is not supported (this decoder reads format {FORMAT})",
            where="bytes 42-43",
        )
    if not (math.isfinite(step) and 0 < step <= MAX_STEP):
        raise FrameError(f"grid step must be in (0, {MAX_STEP:g}], got {step}", where="bytes 36-39")
    if g < 1:
        raise FrameError("a compact frame carries at least one transform", where="byte 40")
    if not 1 <= planes <= 4:
        raise FrameError(f"planes must be 1-4, got {planes}", where="byte 41")
    if nnz > 3 * h.count:
        raise FrameError(f"nnz {nnz} is over the frame's 3 x {h.count} values", where="bytes 48-51")
    if h.flags & KEY and ref != h.seq:
        raise FrameError(
            f"a key frame must name itself: ref {ref} != seq {h.seq}", where="bytes 32-35"
        )
    size = HEADER_SIZE + SUB_SIZE + 48 * g + zlen
    if len(data) != size:
        what = "truncated" if len(data) < size else "has trailing bytes"
        raise FrameError(
            f"compact frame with {g} transforms and {zlen} payload bytes must be "
            f"{size} bytes, got {len(data)} ({what})"
        )
    o = HEADER_SIZE + SUB_SIZE
    tr = np.frombuffer(data, "<f4", 12 * g, o).reshape(g, 3, 4)
    if not (np.isfinite(tr).all() and np.abs(tr[:, :, :3]).max() <= 1.001):
        raise FrameError(
            "transforms must be finite with rotation entries in [-1.001, 1.001]",
            where=f"bytes {o}-{o + 48 * g - 1}",
        )
    return CompactFrame(h, ref, step, tr, planes, nnz, memoryview(data)[o + 48 * g :])


class CompactEncoder:
    """Encodes one session's vertex frames (once for all viewers).

    Args:
        rest: ``(V, 3)`` rest vertices of the face (as in its topology), face units.
        groups: ``(V,)`` rigid group of each vertex (as in its topology).
        tolerance: largest distance of a decoded vertex from the input, face units.
        key_interval: a key frame at least every this many frames (e.g. 250 ms of the session's fps).
        key_seconds: and at least every this many seconds of media time ``t`` (None: no limit).
        level, strategy: the deflate coder (decoders do not care): None, ISA-L's level 1 when
            installed (else zlib-ng's level 1); a number, zlib-ng's ``level`` and ``strategy``.
    """

    def __init__(
        self,
        rest: np.ndarray,
        groups: np.ndarray,
        *,
        tolerance: float,
        key_interval: int = 15,
        key_seconds: float | None = None,
        level: int | None = None,
        strategy: int = zlib.Z_RLE,
    ) -> None:
        self.rest = np.ascontiguousarray(rest, np.float32)
        if self.rest.ndim != 2 or self.rest.shape[1] != 3:
            raise ValueError(f"rest must be (V, 3), got {self.rest.shape}")
        self.groups = np.ascontiguousarray(groups, np.uint8)
        if self.groups.shape != (len(self.rest),):
            raise ValueError("groups needs one entry per rest vertex")
        self.n_groups = int(self.groups.max()) + 1 if len(self.groups) else 1
        if key_interval < 1:
            raise ValueError("key_interval must be >= 1")
        self.tolerance = float(tolerance)
        # coordinates up to twice the rest mesh's from the origin (motion, head pose) keep the bound
        extent = 2.0 * float(np.abs(self.rest).max(initial=0.0))
        self._margin = float_margin(self.tolerance, extent)
        self.step = step_for_tolerance(self.tolerance, extent)
        self.key_interval, self.strategy = int(key_interval), int(strategy)
        self.level = None if level is None else int(level)
        self.key_seconds = key_seconds
        self._key_t = 0.0
        self.base = grid_base(self.rest, self.step)
        self.base_t = np.ascontiguousarray(self.base.T)
        self._base_f = self.base_t.astype(np.float32)  # cells < 2^23 are exact in float32
        self._plan = _GroupPlan.of(self.groups, self.n_groups)
        self._keep2 = np.float32((self.tolerance * (1 - self._margin) / self.step) ** 2)
        self._key_f: np.ndarray | None = None  # cells of the last key frame, as float32 (exact)
        self._key_max: float | None = None  # largest |cell| of ``_key_f`` (on first need)
        self._base_max = float(np.abs(self.base).max(initial=0))
        self._key_seq = 0
        self._since_key = 0
        self._want_key = True

    @property
    def keep2(self) -> float:
        """Squared distance (grid steps²) within which a vertex keeps its reference cell."""
        return float(self._keep2)

    def request_key(self) -> None:
        """Make the next frame a key frame (a new viewer, or a viewer asked for one)."""
        self._want_key = True

    def _matrices(self, tr: np.ndarray) -> np.ndarray:
        """``(G, 3, 4) float32`` maps from world to each group's local frame in grid steps."""
        return world_to_cells(tr, self.step)

    def _local(self, v: np.ndarray, m: np.ndarray, b: dict[str, np.ndarray]) -> np.ndarray:
        """``(3, V) float32`` positions in their group's local frame, in grid steps (axis-major),
        in the scratch buffers ``b`` (``_GroupPlan``, on homogeneous coordinates:
        ``vt``'s last row stays 1, so the translation comes with the matmul)."""
        vt, out = b["vt"], b["local"]
        np.copyto(vt[:3], v.T)
        self._plan.apply(m, vt, out, b["fd"])
        return out

    @staticmethod
    def _zigzag(dd: np.ndarray, b: dict[str, np.ndarray]) -> tuple[int, np.ndarray]:
        """``dd (3, V) float32`` integers -> (planes, zz): ``planes`` bytes hold every zigzagged
        value ``(d << 1) ^ (d >> 31)``, and ``zz (3, V)`` those values, converted to, and
        zigzagged in, the narrowest integer type that holds them (most frames: int8): fewer bytes
        through every pass (``d + d`` for ``d << 1``: the same bits, and NumPy adds small integers
        faster)."""
        lo, hi = int(dd.min()), int(dd.max())
        top = max(2 * hi, -2 * lo - 1)  # largest zigzagged value
        planes = 1 if top < 1 << 8 else 2 if top < 1 << 16 else 3 if top < 1 << 24 else 4
        if planes <= 2:
            d, s = (b["i8"], b["s8"]) if planes == 1 else (b["i16"], b["s16"])
        else:
            d, s = b["dd"], b["s32"]
        bits = 8 * d.itemsize - 1
        np.copyto(d, dd, casting="unsafe")  # (float32 -> int: exact, the values fit)
        np.right_shift(d, bits, out=s)
        np.add(d, d, out=d)
        np.bitwise_xor(d, s, out=d)
        return planes, d

    def _ref_max(self, is_key: bool) -> float:
        """Largest ``|cell|`` of this frame's reference: the rest mesh's or the held key's."""
        if is_key or self._key_f is None:
            return self._base_max
        if self._key_max is None:
            self._key_max = float(np.abs(self._key_f).max(initial=0))
        return self._key_max

    def encode(
        self,
        vertices: np.ndarray,
        transforms: np.ndarray | None = None,
        *,
        seq: int,
        t: float,
        wall: float = 0.0,
        key: bool = False,
    ) -> bytes:
        """One frame: ``vertices (V, 3)`` face units, ``transforms (G, 3, 4)`` (None = identity)
        the rigid pose of each group (the better they match the motion the smaller the frame)."""
        v, tr, m, is_key, ref_f = self.prepare(vertices, transforms, t=t, key=key)
        b = _scratch_buffers(len(v))
        local = self._local(v, m, b)
        # fd = local - ref (in cells) serves twice: the reference cell is kept where it is within
        # the tolerance too (small motions cost nothing), elsewhere r = rint(fd), which equals
        # rint(local) - ref (the subtraction is exact: ref is an integer near local, Sterbenz).
        fd, dist = b["fd"], b["dist"]
        np.subtract(local, ref_f, out=fd)
        np.einsum("ij,ij->j", fd, fd, out=dist)  # squared distance, one pass
        # |local| <= |ref| + |fd|: one check of V distances (also refuses NaN and infinities)
        # keeps every cell, residual and difference below 2^24, exact in float32
        if not float(dist.max(initial=0)) < (_MAX_CELL - 1 - self._ref_max(is_key)) ** 2:
            raise ValueError(
                "vertices must be finite and within 2^23 grid steps of their group's origin"
            )
        move = np.greater(dist, self._keep2, out=b["move"])
        np.rint(fd, out=fd)
        movef = b["movef"]
        np.copyto(movef, move)
        r = np.multiply(fd, movef, out=fd)  # (3, V) residual cells as float32, 0 where kept
        dd = b["ddf"]  # differences along the vertex order, exact in float32 (below 2^24)
        dd[:, 0] = r[:, 0]
        np.subtract(r[:, 1:], r[:, :-1], out=dd[:, 1:])
        planes, zz = self._zigzag(dd, b)
        nnz, raw = pack_payload(zz, planes)
        # the decoder's q = base + r: cells < 2^23, exact in float32
        new_key = np.add(self._base_f, r) if is_key else None
        return self.finish(tr, is_key, planes, nnz, raw, new_key, seq=seq, t=t, wall=wall)

    def prepare(
        self,
        vertices: np.ndarray,
        transforms: np.ndarray | None = None,
        *,
        t: float,
        key: bool = False,
        matrices: bool = True,
        checked: bool = False,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool, np.ndarray]:
        """The first half of ``encode`` (no change of state): checks the arguments and returns
        ``(v (V, 3), tr (G, 3, 4), m (G, 3, 4), is_key, ref (3, V))``, all float32: the vertices,
        the transforms, the maps from world to each group's cells, whether this frame is a key
        frame and the reference cells its residuals are taken from (for other encoders of the
        same stream, e.g. on an OpenCL device, which then call ``finish``). ``matrices=False``:
        ``m`` is left out (empty), for a caller that computes many frames' at once
        (``world_to_cells`` of their transforms, with ``step``). ``checked``: ``transforms`` are
        known to be finite rigid motions (``rigid_motions`` of a stack said so), not checked again."""
        v = np.asarray(vertices, np.float32)
        if v.shape != self.rest.shape:
            raise ValueError(f"vertices must be {self.rest.shape}, got {v.shape}")
        g = self.n_groups
        if transforms is None:
            tr = np.zeros((g, 3, 4), np.float32)
            tr[:, :, :3] = np.eye(3, dtype=np.float32)
        else:
            tr = np.asarray(transforms, np.float32)
            if tr.ndim != 3 or tr.shape[1:] != (3, 4) or tr.shape[0] < g:
                raise ValueError(f"transforms must be ({g}, 3, 4), got {tr.shape}")
            tr = np.ascontiguousarray(tr[:g])
            if not checked and not rigid_motions(tr[None])[0]:
                raise ValueError("transforms must be finite rigid motions (det R = 1)")
        is_key = (
            key
            or self._want_key
            or self._key_f is None
            or self._since_key + 1 >= self.key_interval
            or (self.key_seconds is not None and not 0 <= t - self._key_t < self.key_seconds)
        )
        ref_f = self._base_f if is_key else self._key_f
        assert ref_f is not None  # the first frame is a key frame
        m = self._matrices(tr) if matrices else np.empty((0, 3, 4), np.float32)
        return v, tr, m, is_key, ref_f

    def deflate(self, raw: bytes | bytearray | memoryview) -> bytes:
        """``raw`` as one zlib stream, by this encoder's coder (``level`` None: ISA-L's level 1
        when installed, else zlib-ng's level 1 with ``strategy``)."""
        if self.level is None and _isal is not None:
            return bytes(_isal.compress(raw, 1))
        # Z_RLE: runs and Huffman codes only; on these sparse bytes smaller and faster than
        # the default LZ77 search (bench/compact_stream.py)
        zc = _deflate.compressobj(
            1 if self.level is None else self.level, zlib.DEFLATED, 15, 9, self.strategy
        )
        return bytes(zc.compress(raw) + zc.flush())

    def finish(
        self,
        tr: np.ndarray,
        is_key: bool,
        planes: int,
        nnz: int,
        raw: bytes | bytearray | memoryview,
        new_key: np.ndarray | None,
        *,
        seq: int,
        t: float,
        wall: float = 0.0,
    ) -> bytes:
        """The second half of ``encode``: the frame of ``prepare``'s ``tr`` and ``is_key`` with
        ``raw``, its payload before deflate (``pack_payload``'s, ``nnz`` non-zero values of
        ``planes`` bytes); a key frame's ``new_key (3, V) float32`` cells become the reference of
        the deltas that follow (kept: the caller must not reuse it)."""
        seq = int(seq) & 0xFFFFFFFF
        z = self.deflate(raw)
        if is_key:
            assert new_key is not None
            self._key_f, self._key_max = new_key, None
            self._key_seq, self._since_key, self._want_key = seq, 0, False
            self._key_t = float(t)
        else:
            self._since_key += 1
        hdr = _header(  # the one header packer (frames.py)
            Kind.VERTICES_COMPACT, seq, len(self.rest), float(t), float(wall), KEY if is_key else 0
        )
        sub = _SUB.pack(self._key_seq, self.step, len(tr), planes, FORMAT, len(z), nnz)
        return b"".join((hdr, sub, tr.astype("<f4").tobytes(), z))


class CompactDecoder:
    """Decodes one session's compact stream for one viewer.

    Args:
        rest, groups: the face's topology (rest vertices and rigid group per vertex).
    """

    def __init__(self, rest: np.ndarray, groups: np.ndarray) -> None:
        self.rest = np.ascontiguousarray(rest, np.float32)
        self.groups = np.ascontiguousarray(groups, np.uint8)
        if self.rest.ndim != 2 or self.rest.shape[1] != 3 or self.groups.shape != (len(self.rest),):
            raise ValueError("rest must be (V, 3) and groups (V,)")
        self.n_groups = int(self.groups.max()) + 1 if len(self.groups) else 1
        self._plan = _GroupPlan.of(self.groups, self.n_groups)
        n = len(self.rest)
        self._p = np.ones((4, n), np.float32)  # homogeneous cell positions: rows x, y, z, 1
        self._out = np.empty((3, n), np.float32)
        self._tmp = np.empty((3, n), np.float32)
        self._base: tuple[float, np.ndarray] | None = None
        self._key: tuple[int, float, np.ndarray] | None = None  # seq, step, q

    @property
    def key_seq(self) -> int | None:
        """Seq of the key frame held (None before the first)."""
        return None if self._key is None else self._key[0]

    def decode(self, data: bytes | bytearray | memoryview) -> tuple[Header, np.ndarray] | None:
        """``(header, vertices (V, 3) float32)``, or None for a delta whose key frame this decoder
        has not got (skip it and wait for the next key). Raises ``FrameError`` on a bad frame."""
        f = parse_compact(data)
        n = len(self.rest)
        if f.header.count != n:
            raise FrameError(
                f"frame has {f.header.count} vertices, the face has {n}", where="bytes 12-15"
            )
        g = f.transforms.shape[0]
        if g < self.n_groups:
            raise FrameError(
                f"frame has {g} transforms, the face has {self.n_groups} rigid groups",
                where="byte 40",
            )
        if f.key:
            if self._base is None or self._base[0] != f.step:
                try:
                    self._base = (f.step, np.ascontiguousarray(grid_base(self.rest, f.step).T))
                except ValueError as e:
                    raise FrameError(str(e), where="bytes 36-39") from None
            ref = self._base[1]
        elif self._key is None or self._key[0] != f.ref:
            return None
        elif self._key[1] != f.step:
            raise FrameError(
                "a delta frame's grid step differs from its key frame's", where="bytes 36-39"
            )
        else:
            ref = self._key[2]
        want = 3 * bitmap_size(n) + f.planes * f.nnz
        d = _deflate.decompressobj()
        try:
            raw = d.decompress(f.payload, max(want, 1))  # (0 would mean no limit)
        except (zlib.error, _deflate.error) as e:
            raise FrameError(f"payload is not a valid zlib stream: {e}", where="payload") from None
        if len(raw) != want or not d.eof or d.unconsumed_tail or d.unused_data:
            raise FrameError(
                f"payload must inflate to exactly {want} bytes (3 bitmaps of {n} bits, "
                f"{f.planes} planes of {f.nnz} values) and end there",
                where="payload",
            )
        dd = unpack_payload(raw, f.planes, f.nnz, n)
        q = np.cumsum(dd, axis=1, dtype=np.int32)  # wraps modulo 2^32, as specified
        q += ref
        if f.key:
            self._key = (f.header.seq, f.step, q)
        return f.header, self._positions(q, f.step, f.transforms)

    def _positions(self, q: np.ndarray, step: float, tr: np.ndarray) -> np.ndarray:
        """``q (3, V)`` cells -> ``(V, 3) float32`` positions: ``(R · step) q + t`` per group (the
        step folded into the transforms, as compact.js does: the cells convert to float32
        exactly, below 2^23), written out one axis at a time (a strided copy per axis costs a
        quarter of NumPy's (3, V) -> (V, 3) transposition)."""
        p = self._p
        np.copyto(p[:3], q, casting="unsafe")
        m = tr.astype(np.float32)  # (a copy: the frame's transforms stay as sent)
        m[:, :, :3] *= np.float32(step)
        self._plan.apply(m, p, self._out, self._tmp)
        out = np.empty((len(self.rest), 3), np.float32)
        for a in range(3):
            out[:, a] = self._out[a]
        return out
