"""Backends run the per-frame work: out = T[group] · (rest + B·D), then normals.

``make_deformer(face, operator, backend=...)`` returns an object with the ``Deformer`` interface of
``numpy_backend.NumpyDeformer``; the OpenCL backend gives the same results within float32 tolerance.
"""

from __future__ import annotations

import logging

from .numpy_backend import NumpyDeformer, dequantize_int16, quantize_int16, vertex_normals

__all__ = ["NumpyDeformer", "dequantize_int16", "make_deformer", "quantize_int16", "vertex_normals"]


_fallback_logged = False


def _note_fallback(reason: str) -> None:
    """Say once per process that deformation runs on NumPy, and why."""
    global _fallback_logged
    if not _fallback_logged:
        _fallback_logged = True
        logging.getLogger(__name__).warning("deformation runs on NumPy: %s", reason)


def make_deformer(face, operator, backend: str = "auto", device: str | None = None):
    """A deformer for ``face`` and ``operator`` on ``backend`` (``auto`` | ``numpy`` | ``opencl``).

    ``auto`` uses the first OpenCL device that builds the probe kernel (or the one ``device``
    names, see ``select.default_context``) and falls back to NumPy, saying so once, when there is
    none; ``opencl`` raises ``FacecastError`` instead.
    """
    from ..errors import FacecastError

    if backend not in ("auto", "numpy", "opencl"):
        raise FacecastError(
            f"unknown backend {backend!r}; use auto, numpy or opencl", where="backend"
        )
    if backend in ("auto", "opencl"):
        try:
            from .opencl import OpenCLDeformer, default_context
        except ImportError as e:  # PyOpenCL (or its ICD loader) missing
            if backend == "opencl":
                raise FacecastError(f"the OpenCL backend needs PyOpenCL: {e}") from e
            _note_fallback(f"PyOpenCL unavailable ({e})")
        else:
            ctx = default_context(device)
            if ctx is None:
                if backend == "opencl":
                    what = (
                        f"no working OpenCL device matches {device!r}"
                        if device
                        else "no working OpenCL device"
                    )
                    raise FacecastError(
                        f"{what}; install pocl-opencl-icd, check `facecast info`, "
                        "or use --backend numpy"
                    )
                # (select.default_context has already said, once, that NumPy is used and why)
            else:
                try:
                    return OpenCLDeformer(
                        face.vertices, face.triangles, face.rigid_group, operator, context=ctx
                    )
                except Exception as e:  # a kernel variant that fails to build or run on this device
                    if backend == "opencl":
                        raise FacecastError(
                            f"OpenCL deformer failed on {ctx.devices[0].name.strip()}: {e}"
                        ) from e
                    _note_fallback(
                        f"OpenCL deformer failed ({str(e).splitlines()[0] if str(e) else e!r})"
                    )
    return NumpyDeformer(face.vertices, face.triangles, face.rigid_group, operator)
