"""Face topology for thin clients: rest vertices, triangles, parts and rigid groups in one binary blob.

Layout (all little-endian; every section starts on a 4-byte boundary; see ``protocol/TOPOLOGY.md``)::

    offset  size  field
    0       4     magic b"FCTP"
    4       2     version (u16) = 1
    6       2     flags (u16) = 0 (reserved)
    8       4     V vertices (u32)
    12      4     F triangles (u32)
    16      2     P part names (u16)
    18      2     G rigid group names (u16)
    20      4     N names length in bytes (u32)
    24      4     mm per mesh unit (f32)
    28      4     total length of the blob in bytes (u32)
    32      N     names: UTF-8, P part names then G group names, each ending in b"\\n"; zero-padded to 4
    ...     12V   vertices: (V, 3) f32, x y z per vertex
    ...     12F   triangles: (F, 3) u32 vertex ids
    ...     V     part id per vertex (u8): index into the part names, 255 = in no part; zero-padded to 4
    ...     V     rigid group per vertex (u8): index into the group names; zero-padded to 4

Pure encode/decode; no I/O.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from .errors import FileFormatError

MAGIC = b"FCTP"
VERSION = 1
HEADER = struct.Struct("<4sHHIIHHIfI")  # 32 bytes
NO_PART = 255
MAX_PARTS = 255


class TopologyError(FileFormatError):
    """A blob that is not a valid facecast topology (or a mesh the format cannot carry)."""


@dataclass
class Topology:
    """Decoded topology. ``vertices (V,3) f32``, ``triangles (F,3) u32``, ``part_ids (V,) u8``,
    ``rigid_group (V,) u8``; ``mm_per_unit`` converts mesh units to millimetres."""

    vertices: np.ndarray
    triangles: np.ndarray
    part_ids: np.ndarray
    part_names: list[str]
    rigid_group: np.ndarray
    group_names: list[str]
    mm_per_unit: float = 1.0

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])


def _pad(n: int) -> int:
    return (-n) % 4


def part_ids_from_parts(
    n_vertices: int, parts: dict[str, np.ndarray], order: list[str]
) -> np.ndarray:
    """``(V,) u8`` part index per vertex; a vertex in several parts gets the last one in ``order``."""
    ids = np.full(n_vertices, NO_PART, dtype=np.uint8)
    for i, name in enumerate(order):
        ids[np.asarray(parts[name], dtype=np.int64)] = i
    return ids


def encode_topology(topo: Topology) -> bytes:
    """The binary form of ``topo`` (layout in the module docstring)."""
    v = np.ascontiguousarray(topo.vertices, dtype="<f4")
    t = np.ascontiguousarray(topo.triangles, dtype="<u4")
    if v.ndim != 2 or v.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 3:
        raise TopologyError(
            f"vertices must be (V,3) and triangles (F,3); got {v.shape} and {t.shape}"
        )
    n = v.shape[0]
    parts = np.ascontiguousarray(topo.part_ids, dtype=np.uint8)
    groups = np.ascontiguousarray(topo.rigid_group, dtype=np.uint8)
    if parts.shape != (n,) or groups.shape != (n,):
        raise TopologyError("part_ids and rigid_group need one entry per vertex")
    if len(topo.part_names) > MAX_PARTS or len(topo.group_names) > MAX_PARTS:
        raise TopologyError(f"at most {MAX_PARTS} part names and group names")
    for name in [*topo.part_names, *topo.group_names]:
        if "\n" in name:
            raise TopologyError(f"names may not contain a newline: {name!r}")
    names = "".join(f"{s}\n" for s in [*topo.part_names, *topo.group_names]).encode("utf-8")
    body = [
        names,
        b"\0" * _pad(len(names)),
        v.tobytes(),
        t.tobytes(),
        parts.tobytes(),
        b"\0" * _pad(n),
        groups.tobytes(),
        b"\0" * _pad(n),
    ]
    total = HEADER.size + sum(len(b) for b in body)
    head = HEADER.pack(
        MAGIC,
        VERSION,
        0,
        n,
        t.shape[0],
        len(topo.part_names),
        len(topo.group_names),
        len(names),
        float(topo.mm_per_unit),
        total,
    )
    return b"".join([head, *body])


def decode_topology(data: bytes | bytearray | memoryview) -> Topology:
    """Inverse of ``encode_topology``; TopologyError names what is wrong with a bad blob."""
    buf = memoryview(data).cast("B")
    if len(buf) < HEADER.size:
        raise TopologyError(
            f"blob of {len(buf)} bytes is shorter than the {HEADER.size}-byte header"
        )
    magic, version, _flags, n, f, p, g, n_names, mm, total = HEADER.unpack_from(buf, 0)
    if magic != MAGIC:
        raise TopologyError(f"bad magic {bytes(magic)!r}; expected {MAGIC!r}")
    if version != VERSION:
        raise TopologyError(f"unsupported topology version {version}; this decoder reads {VERSION}")
    expected = HEADER.size + n_names + _pad(n_names) + 12 * n + 12 * f + 2 * (n + _pad(n))
    if total != expected or len(buf) != total:
        raise TopologyError(
            f"length mismatch: header says {total} bytes, counts imply {expected}, "
            f"blob has {len(buf)}"
        )
    off = HEADER.size
    try:
        names = bytes(buf[off : off + n_names]).decode("utf-8").split("\n")
    except UnicodeDecodeError as e:
        raise TopologyError(f"names are not UTF-8: {e}") from None
    if names[-1:] != [""] and n_names:
        raise TopologyError("names section must end with a newline")
    names = names[:-1] if n_names else []
    if len(names) != p + g:
        raise TopologyError(f"header says {p} part and {g} group names; found {len(names)} names")
    off += n_names + _pad(n_names)
    verts = np.frombuffer(buf, dtype="<f4", count=3 * n, offset=off).reshape(n, 3)
    off += 12 * n
    tris = np.frombuffer(buf, dtype="<u4", count=3 * f, offset=off).reshape(f, 3)
    off += 12 * f
    part_ids = np.frombuffer(buf, dtype=np.uint8, count=n, offset=off)
    off += n + _pad(n)
    groups = np.frombuffer(buf, dtype=np.uint8, count=n, offset=off)
    if f and int(tris.max()) >= n:
        raise TopologyError(f"triangle vertex id {int(tris.max())} out of range (V = {n})")
    if n and int(groups.max()) >= g:
        raise TopologyError(f"rigid group id {int(groups.max())} out of range (G = {g})")
    bad = part_ids[(part_ids >= p) & (part_ids != NO_PART)]
    if len(bad):
        raise TopologyError(f"part id {int(bad[0])} out of range (P = {p}; {NO_PART} = no part)")
    return Topology(verts, tris, part_ids, names[:p], groups, names[p:], float(mm))
