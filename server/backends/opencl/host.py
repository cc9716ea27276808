"""Host arrays the device uses in place (``CL_MEM_USE_HOST_PTR`` on host-memory devices)."""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from numpy.typing import DTypeLike

from .kernels import build, cl_source

if TYPE_CHECKING:
    from typing_extensions import Self

log = logging.getLogger(__name__)

#: Byte alignment of host arrays the kernels read or write in place.
ALIGN = 128


def aligned_empty(shape: tuple[int, ...], dtype: DTypeLike, align: int = ALIGN) -> np.ndarray:
    """``np.empty`` whose data pointer is ``align``-byte aligned (what zero-copy buffers want)."""
    dt = np.dtype(dtype)
    n = int(np.prod(shape)) * dt.itemsize
    raw = np.empty(n + align, dtype=np.uint8)
    off = (-raw.ctypes.data) % align
    return raw[off : off + n].view(dt).reshape(shape)


class HostKernel:
    """Kernel ``KERNEL`` of ``<SOURCE>.cl`` (built with ``DEFINES``) on an OpenCL context whose
    device works in host memory, with its queue and a lock (kernel arguments belong to the kernel
    object: one launch at a time)."""

    SOURCE: ClassVar[str]
    KERNEL: ClassVar[str]
    DEFINES: ClassVar[dict[str, object]] = {}

    def __init__(self, context: Any) -> None:
        import pyopencl as cl

        self._cl = cl
        self.context = context
        self.queue = cl.CommandQueue(context)
        self._kernel = cl.Kernel(build(context, cl_source(self.SOURCE), self.DEFINES), self.KERNEL)
        self._lock = threading.Lock()

    @classmethod
    def for_deformer(cls, deformer: Any) -> Self | None:
        """One on ``deformer``'s context if it is a zero-copy OpenCL deformer, else None (a NumPy
        deformer, or a device whose memory is not host memory)."""
        ctx = getattr(deformer, "context", None)
        if ctx is None or not getattr(deformer, "zero_copy", False):
            return None
        return cls(ctx)

    @classmethod
    def shared(cls, deformer: Any, failure: str) -> Self | None:
        """The one ``cls`` of ``deformer``'s OpenCL context (built on first use, thread-safe), or
        None: not a zero-copy OpenCL deformer, or a device that fails to build it (``failure``
        is logged as a warning once; the host path serves instead)."""
        ctx = getattr(deformer, "context", None)
        if ctx is None or not getattr(deformer, "zero_copy", False):
            return None
        with _shared_lock:
            hit = _shared.get((cls, id(ctx)))
            if hit is None:
                try:
                    k: HostKernel | None = cls(ctx)
                except Exception:
                    log.warning(failure, exc_info=True)
                    k = None
                hit = _shared[cls, id(ctx)] = (ctx, k)  # holding ctx keeps id(ctx) unique
            return hit[1]  # type: ignore[return-value]

    def _host(self, arr: np.ndarray, flags: Any) -> Any:
        """A buffer over ``arr`` itself (``USE_HOST_PTR``): no copy on a host-memory device."""
        cl = self._cl
        return cl.Buffer(self.context, flags | cl.mem_flags.USE_HOST_PTR, hostbuf=arr)


_shared: dict[tuple[type, int], tuple[Any, HostKernel | None]] = {}
_shared_lock = threading.Lock()
