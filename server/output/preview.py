"""Still previews of a mesh: a small pure-NumPy z-buffer rasteriser with Lambert shading, and a PNG writer.

Meant for looking at faces and animation frames without a GPU or a viewer::

    render_png(face.vertices, face.triangles, "front.png", view="three_quarter")

The camera is orthographic and looks at the mesh along −z of the chosen view (the face's own axes are
MPEG-4: y up, z towards the viewer), so ``front`` shows the face as a person opposite it would see it.
"""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

#: Yaw of the model (degrees about +y) for each named view; positive turns the face's left towards the viewer.
VIEWS: dict[str, float] = {"front": 0.0, "three_quarter": 35.0, "side": 90.0, "back": 180.0,
                           "three_quarter_right": -35.0, "side_right": -90.0}

_LIGHT = np.array([-0.35, 0.45, 0.82])
_LIGHT = _LIGHT / np.linalg.norm(_LIGHT)


def view_rotation(view: str | float, pitch: float = 0.0) -> np.ndarray:
    """``(3, 3)`` rotation taking model coordinates to camera coordinates for a named view or a yaw in degrees."""
    if isinstance(view, str):
        if view not in VIEWS:
            raise ValueError(f"unknown view {view!r}; use one of {', '.join(VIEWS)} or a yaw angle in degrees")
        yaw = VIEWS[view]
    else:
        yaw = float(view)
    a, b = np.radians(-yaw), np.radians(pitch)
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return rx @ ry


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``(V, 3)`` area-weighted unit vertex normals (zero for unused vertices)."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, t[:, k], fn) if len(t) < 50_000 else _add_rows(n, t[:, k], fn)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(norm > 0, norm, 1.0)


def _add_rows(out: np.ndarray, idx: np.ndarray, rows: np.ndarray) -> None:
    for c in range(out.shape[1]):
        out[:, c] += np.bincount(idx, weights=rows[:, c], minlength=out.shape[0])


def render_image(vertices: np.ndarray, triangles: np.ndarray, *, size: tuple[int, int] = (512, 512),
                 view: str | float = "front", colors: np.ndarray | None = None, pitch: float = 0.0,
                 center: np.ndarray | None = None, extent: float | None = None,
                 background: tuple[int, int, int] = (40, 44, 52), smooth: bool = True,
                 chunk: int = 65536) -> np.ndarray:
    """Rasterise a triangle mesh to an ``(H, W, 3) uint8`` image.

    Args:
        vertices: ``(V, 3)`` positions (any units).
        triangles: ``(F, 3)`` vertex ids.
        size: ``(width, height)`` in pixels.
        view: ``"front"``, ``"three_quarter"``, ``"side"`` (see ``VIEWS``) or a yaw angle in degrees.
        colors: ``None`` (skin grey), ``(3,)``, per-vertex ``(V, 3)`` or per-triangle ``(F, 3)`` RGB in
            0–1 (floats) or 0–255 (uint8).
        pitch: extra tilt in degrees (positive looks from above).
        center, extent: model-space point at the image centre and the width (model units) shown;
            default: the whole mesh.
        smooth: interpolate vertex normals (else flat shading).
        chunk: triangles rasterised per vectorised batch.
    """
    w, h = int(size[0]), int(size[1])
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    rot = view_rotation(view, pitch)
    cam = v @ rot.T
    if center is None:
        used = cam[np.unique(t)] if len(t) else cam
        lo, hi = used.min(axis=0), used.max(axis=0)
        mid = (lo + hi) / 2
        span = max((hi[0] - lo[0]) / w, (hi[1] - lo[1]) / h) * 1.08
    else:
        mid = rot @ np.asarray(center, dtype=np.float64)
        span = float(extent if extent is not None else 1.0) / w
    span = span if span > 0 else 1.0
    sx = (cam[:, 0] - mid[0]) / span + w / 2
    sy = (mid[1] - cam[:, 1]) / span + h / 2
    depth = -cam[:, 2]

    zbuf = np.full(h * w, np.inf)
    tbuf = np.full(h * w, -1, dtype=np.int64)
    bbuf = np.zeros((h * w, 3))
    for start in range(0, len(t), chunk):
        _raster_chunk(t[start:start + chunk], start, sx, sy, depth, w, h, zbuf, tbuf, bbuf)

    img = np.empty((h * w, 3))
    img[:] = np.asarray(background, dtype=np.float64) / 255.0
    hit = tbuf >= 0
    if hit.any():
        tri = tbuf[hit]
        bary = bbuf[hit]
        corners = t[tri]
        if smooth:
            vn = vertex_normals(cam, t)
            n = np.einsum("pk,pkc->pc", bary, vn[corners])
        else:
            n = np.cross(cam[corners[:, 1]] - cam[corners[:, 0]], cam[corners[:, 2]] - cam[corners[:, 0]])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        # Flat normals decide which side we see (smooth ones can disagree at silhouettes).
        fn = np.cross(cam[corners[:, 1]] - cam[corners[:, 0]], cam[corners[:, 2]] - cam[corners[:, 0]])
        back = fn[:, 2] < 0
        n[back] *= -1
        base = _base_colors(colors, len(v), len(t), tri, corners, bary)
        base[back] *= 0.55
        lambert = np.clip(n @ _LIGHT, 0.0, 1.0)
        fill = np.clip(n @ np.array([0.6, -0.2, 0.77]), 0.0, 1.0)
        shade = 0.22 + 0.68 * lambert + 0.18 * fill
        spec = np.clip(n[:, 2], 0, 1) ** 40 * 0.12
        img[hit] = base * shade[:, None] + spec[:, None]
    return (np.clip(img, 0, 1).reshape(h, w, 3) * 255 + 0.5).astype(np.uint8)


def _base_colors(colors, nv, nf, tri, corners, bary) -> np.ndarray:
    if colors is None:
        return np.tile(np.array([0.86, 0.70, 0.60]), (len(tri), 1))
    c = np.asarray(colors)
    c = c.astype(np.float64) / (255.0 if c.dtype == np.uint8 or c.max(initial=0) > 1.0 else 1.0)
    if c.ndim == 1:
        return np.tile(c[:3], (len(tri), 1))
    if c.shape[0] == nv:
        return np.einsum("pk,pkc->pc", bary, c[corners][:, :, :3])
    if c.shape[0] == nf:
        return c[tri, :3].copy()
    raise ValueError(f"colors must be (3,), (V={nv}, 3) or (F={nf}, 3), not {c.shape}")


def _raster_chunk(tc, offset, sx, sy, depth, w, h, zbuf, tbuf, bbuf) -> None:
    x0, x1, x2 = sx[tc[:, 0]], sx[tc[:, 1]], sx[tc[:, 2]]
    y0, y1, y2 = sy[tc[:, 0]], sy[tc[:, 1]], sy[tc[:, 2]]
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    xmin = np.clip(np.floor(np.minimum(np.minimum(x0, x1), x2) - 0.5), 0, w).astype(np.int64)
    xmax = np.clip(np.ceil(np.maximum(np.maximum(x0, x1), x2) - 0.5), -1, w - 1).astype(np.int64)
    ymin = np.clip(np.floor(np.minimum(np.minimum(y0, y1), y2) - 0.5), 0, h).astype(np.int64)
    ymax = np.clip(np.ceil(np.maximum(np.maximum(y0, y1), y2) - 0.5), -1, h - 1).astype(np.int64)
    bw = xmax - xmin + 1
    bh = ymax - ymin + 1
    ok = (np.abs(area) > 1e-12) & (bw > 0) & (bh > 0)
    ok &= np.isfinite(area)
    idx = np.nonzero(ok)[0]
    if not len(idx):
        return
    counts = bw[idx] * bh[idx]
    # Split very large batches of fragments to bound memory.
    parts = np.array_split(idx, int(counts.sum() // 4_000_000) + 1)
    for part in parts:
        cnt = bw[part] * bh[part]
        if cnt.sum() == 0:
            continue
        owner = np.repeat(part, cnt)
        local = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        px = xmin[owner] + local % bw[owner]
        py = ymin[owner] + local // bw[owner]
        cx, cy = px + 0.5, py + 0.5
        a = area[owner]
        l0 = ((x1[owner] - cx) * (y2[owner] - cy) - (x2[owner] - cx) * (y1[owner] - cy)) / a
        l1 = ((x2[owner] - cx) * (y0[owner] - cy) - (x0[owner] - cx) * (y2[owner] - cy)) / a
        l2 = 1.0 - l0 - l1
        inside = (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
        if not inside.any():
            continue
        owner, px, py = owner[inside], px[inside], py[inside]
        l0, l1, l2 = l0[inside], l1[inside], l2[inside]
        tri = tc[owner]
        z = l0 * depth[tri[:, 0]] + l1 * depth[tri[:, 1]] + l2 * depth[tri[:, 2]]
        pix = py * w + px
        order = np.lexsort((z, pix))
        pix_s = pix[order]
        first = np.ones(len(order), dtype=bool)
        first[1:] = pix_s[1:] != pix_s[:-1]
        win = order[first]
        pw = pix[win]
        closer = z[win] < zbuf[pw]
        win, pw = win[closer], pw[closer]
        zbuf[pw] = z[win]
        tbuf[pw] = owner[win] + offset
        bbuf[pw, 0], bbuf[pw, 1], bbuf[pw, 2] = l0[win], l1[win], l2[win]


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write an ``(H, W, 3)`` or ``(H, W, 4)`` uint8 image as PNG (zlib + struct, no imaging library)."""
    img = np.ascontiguousarray(image, dtype=np.uint8)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise ValueError(f"image must be (H, W, 3|4) uint8, not {img.shape}")
    hgt, wid, ch = img.shape
    raw = np.concatenate([np.zeros((hgt, 1), dtype=np.uint8), img.reshape(hgt, wid * ch)], axis=1).tobytes()

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", wid, hgt, 8, 2 if ch == 3 else 6, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(png)
    tmp.replace(path)
    return path


def render_png(vertices: np.ndarray, triangles: np.ndarray, path: str | Path, *,
               size: tuple[int, int] = (512, 512), view: str | float = "front",
               colors: np.ndarray | None = None, **options) -> Path:
    """Render a mesh (see ``render_image`` for the options) and write it to ``path`` as PNG."""
    return write_png(path, render_image(vertices, triangles, size=size, view=view, colors=colors, **options))
