"""Host arrays the device uses in place (``CL_MEM_USE_HOST_PTR`` on host-memory devices)."""

from __future__ import annotations

import numpy as np
from numpy.typing import DTypeLike

#: Byte alignment of host arrays the kernels read or write in place.
ALIGN = 128


def aligned_empty(shape: tuple[int, ...], dtype: DTypeLike, align: int = ALIGN) -> np.ndarray:
    """``np.empty`` whose data pointer is ``align``-byte aligned (what zero-copy buffers want)."""
    dt = np.dtype(dtype)
    n = int(np.prod(shape)) * dt.itemsize
    raw = np.empty(n + align, dtype=np.uint8)
    off = (-raw.ctypes.data) % align
    return raw[off : off + n].view(dt).reshape(shape)
