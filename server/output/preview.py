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

from ..deform.normals import vertex_normals
from .atomic import write_bytes_atomic

#: Yaw of the model (degrees about +y) for each named view; positive turns the face's left towards the viewer.
VIEWS: dict[str, float] = {
    "front": 0.0,
    "three_quarter": 35.0,
    "side": 90.0,
    "back": 180.0,
    "three_quarter_right": -35.0,
    "side_right": -90.0,
}

_LIGHT = np.array([-0.35, 0.45, 0.82])
_LIGHT = _LIGHT / np.linalg.norm(_LIGHT)


def view_rotation(view: str | float, pitch: float = 0.0) -> np.ndarray:
    """``(3, 3)`` rotation taking model coordinates to camera coordinates for a named view or a yaw in degrees."""
    if isinstance(view, str):
        if view not in VIEWS:
            raise ValueError(
                f"unknown view {view!r}; use one of {', '.join(VIEWS)} or a yaw angle in degrees"
            )
        yaw = VIEWS[view]
    else:
        yaw = float(view)
    a, b = np.radians(-yaw), np.radians(pitch)
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return rx @ ry


def render_image(
    vertices: np.ndarray,
    triangles: np.ndarray,
    *,
    size: tuple[int, int] = (512, 512),
    view: str | float = "front",
    colors: np.ndarray | None = None,
    pitch: float = 0.0,
    center: np.ndarray | None = None,
    extent: float | None = None,
    background: tuple[int, int, int] = (40, 44, 52),
    smooth: bool = True,
    chunk: int = 65536,
) -> np.ndarray:
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
        mask = np.zeros(len(cam), dtype=bool)
        mask[t.ravel()] = True
        used = cam[mask] if len(t) else cam
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

    coef, boxes, ok = _setup(t, sx, sy, depth, w, h)
    zbuf = np.full(h * w, np.inf)
    tbuf = np.full(h * w, -1, dtype=np.int64)
    for start in range(0, len(t), chunk):
        ids = np.arange(start, min(start + chunk, len(t)))
        _raster_chunk(ids[ok[ids]], coef, boxes, w, zbuf, tbuf)
    hit_pix = np.nonzero(tbuf >= 0)[0]
    bbuf = np.zeros((h * w, 3))
    if len(hit_pix):
        tri = tbuf[hit_pix]
        cx, cy = hit_pix % w + 0.5, hit_pix // w + 0.5
        c = coef[tri]
        l0 = c[:, 0] * cx + c[:, 1] * cy + c[:, 2]
        l1 = c[:, 3] * cx + c[:, 4] * cy + c[:, 5]
        bbuf[hit_pix] = np.stack([l0, l1, 1 - l0 - l1], -1).clip(0, 1)

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
            n = np.cross(
                cam[corners[:, 1]] - cam[corners[:, 0]], cam[corners[:, 2]] - cam[corners[:, 0]]
            )
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        # Flat normals decide which side we see (smooth ones can disagree at silhouettes).
        fn = np.cross(
            cam[corners[:, 1]] - cam[corners[:, 0]], cam[corners[:, 2]] - cam[corners[:, 0]]
        )
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


def _setup(t, sx, sy, depth, w, h):
    """Per-triangle plane coefficients ``(F, 9)`` (barycentric l0, l1 and depth as a*x + b*y + c in pixel
    coordinates), integer pixel boxes ``(F, 4)`` and which triangles can cover a pixel centre."""
    x0, x1, x2 = sx[t[:, 0]], sx[t[:, 1]], sx[t[:, 2]]
    y0, y1, y2 = sy[t[:, 0]], sy[t[:, 1]], sy[t[:, 2]]
    z0, z1, z2 = depth[t[:, 0]], depth[t[:, 1]], depth[t[:, 2]]
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    ok = np.isfinite(area) & (np.abs(area) > 1e-12)
    inv = np.where(ok, 1.0 / np.where(ok, area, 1.0), 0.0)
    a0, b0, c0 = (y1 - y2) * inv, (x2 - x1) * inv, (x1 * y2 - x2 * y1) * inv
    a1, b1, c1 = (y2 - y0) * inv, (x0 - x2) * inv, (x2 * y0 - x0 * y2) * inv
    dz0, dz1 = z0 - z2, z1 - z2
    coef = np.stack(
        [
            a0,
            b0,
            c0,
            a1,
            b1,
            c1,
            a0 * dz0 + a1 * dz1,
            b0 * dz0 + b1 * dz1,
            z2 + c0 * dz0 + c1 * dz1,
        ],
        -1,
    )
    with np.errstate(invalid="ignore"):
        xmin = np.clip(np.floor(np.minimum(np.minimum(x0, x1), x2) - 0.5), 0, w)
        xmax = np.clip(np.ceil(np.maximum(np.maximum(x0, x1), x2) - 0.5), -1, w - 1)
        ymin = np.clip(np.floor(np.minimum(np.minimum(y0, y1), y2) - 0.5), 0, h)
        ymax = np.clip(np.ceil(np.maximum(np.maximum(y0, y1), y2) - 0.5), -1, h - 1)
    ok &= np.isfinite(xmin + xmax + ymin + ymax)
    boxes = np.stack(
        [
            np.where(ok, xmin, 0),
            np.where(ok, xmax, -1),
            np.where(ok, ymin, 0),
            np.where(ok, ymax, -1),
        ],
        -1,
    ).astype(np.int64)
    ok &= (boxes[:, 1] >= boxes[:, 0]) & (boxes[:, 3] >= boxes[:, 2])
    return coef, boxes, ok


def _raster_chunk(ids, coef, boxes, w, zbuf, tbuf) -> None:
    """Z-buffer the triangles ``ids``: small ones grouped by box size through fixed pixel stencils (no
    per-fragment index arithmetic), large ones by enumerating their boxes."""
    if not len(ids):
        return
    bw = boxes[ids, 1] - boxes[ids, 0] + 1
    bh = boxes[ids, 3] - boxes[ids, 2] + 1
    pix_parts, z_parts, tri_parts = [], [], []
    small = (bw <= 12) & (bh <= 12)
    key = bw * 16 + bh
    for kk in np.nonzero(np.bincount(key[small], minlength=1))[0]:
        sel = ids[small & (key == kk)]
        kw, kh = int(kk // 16), int(kk % 16)
        dx, dy = np.meshgrid(np.arange(kw), np.arange(kh))
        px = (boxes[sel, 0][:, None] + dx.ravel()[None, :]).ravel()
        py = (boxes[sel, 2][:, None] + dy.ravel()[None, :]).ravel()
        _fragments(np.repeat(sel, kw * kh), px, py, coef, w, pix_parts, z_parts, tri_parts)
    big = ids[~small]
    for part in np.array_split(big, max(1, int((bw[~small] * bh[~small]).sum() // 2_000_000) + 1)):
        if not len(part):
            continue
        pw = boxes[part, 1] - boxes[part, 0] + 1
        cnt = pw * (boxes[part, 3] - boxes[part, 2] + 1)
        owner = np.repeat(part, cnt)
        local = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        pwo = np.repeat(pw, cnt)
        _fragments(
            owner,
            boxes[owner, 0] + local % pwo,
            boxes[owner, 2] + local // pwo,
            coef,
            w,
            pix_parts,
            z_parts,
            tri_parts,
        )
    if not pix_parts:
        return
    pix, z, tri = np.concatenate(pix_parts), np.concatenate(z_parts), np.concatenate(tri_parts)
    zmin, zmax = float(z.min()), float(z.max())
    zq = ((z - zmin) * ((2**31 - 2) / max(zmax - zmin, 1e-12))).astype(np.int64)
    order = np.argsort((pix << 31) | zq)
    pix_s = pix[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = pix_s[1:] != pix_s[:-1]
    win = order[first]
    pw = pix[win]
    closer = z[win] < zbuf[pw]
    zbuf[pw[closer]] = z[win[closer]]
    tbuf[pw[closer]] = tri[win[closer]]


def _fragments(owner, px, py, coef, w, pix_parts, z_parts, tri_parts) -> None:
    cx, cy = px + 0.5, py + 0.5
    l0 = coef[owner, 0] * cx + coef[owner, 1] * cy + coef[owner, 2]
    l1 = coef[owner, 3] * cx + coef[owner, 4] * cy + coef[owner, 5]
    inside = np.nonzero((l0 >= -1e-9) & (l1 >= -1e-9) & (l0 + l1 <= 1 + 1e-9))[0]
    owner, cx, cy = owner[inside], cx[inside], cy[inside]
    pix_parts.append(py[inside] * w + px[inside])
    z_parts.append(coef[owner, 6] * cx + coef[owner, 7] * cy + coef[owner, 8])
    tri_parts.append(owner)


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write an ``(H, W, 3)`` or ``(H, W, 4)`` uint8 image as PNG (zlib + struct, no imaging library)."""
    img = np.ascontiguousarray(image, dtype=np.uint8)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise ValueError(f"image must be (H, W, 3|4) uint8, not {img.shape}")
    hgt, wid, ch = img.shape
    raw = np.concatenate(
        [np.zeros((hgt, 1), dtype=np.uint8), img.reshape(hgt, wid * ch)], axis=1
    ).tobytes()

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + kind
            + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    header = struct.pack(">IIBBBBB", wid, hgt, 8, 2 if ch == 3 else 6, 0, 0, 0)
    png = (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw, 6))
        + chunk(b"IEND", b"")
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(path, png)
    return path


def render_png(
    vertices: np.ndarray,
    triangles: np.ndarray,
    path: str | Path,
    *,
    size: tuple[int, int] = (512, 512),
    view: str | float = "front",
    colors: np.ndarray | None = None,
    **options,
) -> Path:
    """Render a mesh (see ``render_image`` for the options) and write it to ``path`` as PNG."""
    return write_png(
        path, render_image(vertices, triangles, size=size, view=view, colors=colors, **options)
    )
