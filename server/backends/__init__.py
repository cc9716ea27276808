"""Backends run the per-frame work: out = T[group] · (rest + B·D), then normals.

``make_deformer(face, operator, backend=...)`` returns an object with the ``Deformer`` interface of
``numpy_backend.NumpyDeformer``; the OpenCL backend gives the same results within float32 tolerance.
"""
from __future__ import annotations

from .numpy_backend import NumpyDeformer, quantize_int16, dequantize_int16, vertex_normals

__all__ = ["NumpyDeformer", "make_deformer", "quantize_int16", "dequantize_int16", "vertex_normals"]


def make_deformer(face, operator, backend: str = "auto", device: str | None = None):
    """A deformer for ``face`` and ``operator`` on ``backend`` (``auto`` | ``numpy`` | ``opencl``)."""
    if backend in ("auto", "opencl"):
        try:
            from .opencl_backend import OpenCLDeformer, default_context  # noqa: F401
        except ImportError:
            if backend == "opencl":
                raise
        else:
            ctx = default_context(device)
            if ctx is not None:
                return OpenCLDeformer(face.vertices, face.triangles, face.rigid_group, operator, context=ctx)
            if backend == "opencl":
                from ..errors import FacecastError
                raise FacecastError("no working OpenCL device; install pocl-opencl-icd or use --backend numpy")
    return NumpyDeformer(face.vertices, face.triangles, face.rigid_group, operator)
