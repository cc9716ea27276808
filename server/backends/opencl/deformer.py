"""The OpenCL backend (PyOpenCL): the NumPy reference's results, near the memory-bandwidth limit.

Per frame the device reads the resident operator, rest positions and rigid groups, and writes the
vertices; only the frame's parameters (transforms and ``D``, a few hundred bytes) go up. On a CPU
device (PoCL) device memory is host memory, so kernels read the parameters from, and write the
vertices straight into, NumPy arrays (``CL_MEM_USE_HOST_PTR``): no upload or read-back copies. On
other devices the vertices are copied back from a resident buffer.

One work-item deforms a *slice* of 16 consecutive vertices as float16 vectors: ``u = B·D``, plus
the rest position, then its rigid transform (jaw, eyes, head), all in one kernel; batches loop
over frames inside the kernel, so a slice's operator stays in L1 from frame to frame. The slice
goes out as (V, 3) rows through a fixed 3x8 shuffle network; launches whose data outgrow half the
last-level cache write with non-temporal stores (``STREAM_FRACTION``). Per frame the host sets only
the launch's buffers (the other kernel arguments are set once). PoCL's worker threads are pinned
one per CPU (``select.pin_pocl_workers``).

The operator's device format is ``packing``'s; the kernels' sources are ``kernels``'.
"""

from __future__ import annotations

import functools
import logging
import threading
from collections.abc import Callable
from typing import Any, Concatenate, ParamSpec, TypeVar

import numpy as np

from ...deform.operator import Operator
from ..select import context_label, default_context
from .host import aligned_empty
from .kernels import deform_program
from .packing import SLICE, pack_operator

log = logging.getLogger(__name__)

#: Work-group size (in slices) of the deform kernel; in vertices for the others.
LOCAL_SLICES = 64
LOCAL_SIZE = 128
#: Floats per rigid transform on the device (4 float4 columns of the 3x4 matrix).
T_FLOATS = 16
#: Write the vertices with non-temporal (streaming) stores when a launch's data -- resident operator
#: and rest positions plus the frames it writes -- exceed this fraction of the device's last-level
#: cache (CPU devices; ``deform``/``deform_batch``): allocating the output in the cache would evict
#: the operator the next frame reads again, and costs a read of every output line first (memcpy
#: streams large copies for the same reasons). 500k vertices: 23 MB per frame, 32 MB L3 here:
#: 12% less CPU per frame. Smaller faces keep ordinary stores (their output stays in cache for the
#: consumer).
STREAM_FRACTION = 0.5


_P = ParamSpec("_P")
_R = TypeVar("_R")


def _serialised(
    method: Callable[Concatenate[OpenCLDeformer, _P], _R],
) -> Callable[Concatenate[OpenCLDeformer, _P], _R]:
    """Run ``method`` under the deformer's lock: one queue and one parameter block per deformer,
    so calls from several threads (server sessions) take turns."""

    @functools.wraps(method)
    def wrapper(self: OpenCLDeformer, /, *args: _P.args, **kwargs: _P.kwargs) -> _R:
        with self._lock:
            return method(self, *args, **kwargs)

    return wrapper


class OpenCLDeformer:
    """Per-frame deformation on an OpenCL device; the interface of ``NumpyDeformer``.

    ``out[v] = T[g[v]] · [rest[v] + (B·D)[v]; 1]``. Operator, rest positions, rigid groups and
    triangle adjacency are uploaded once and stay on the device; kernels are built and run once at
    construction (PoCL caches the compiled code under ``cache_dir("pocl")``).

    Args:
        rest: ``(V, 3) float32`` neutral vertices.
        triangles: ``(F, 3) int32``.
        rigid_group: ``(V,) uint8`` group index per vertex.
        operator: the compiled ``Operator`` (K controls).
        context: a ``pyopencl.Context`` (default: ``default_context()``).
        zero_copy: let kernels read parameters from and write results into host arrays directly
            (default, and only possible, on CPU devices; False forces the copying path).
        slice_size: vertices per work-item (8 or 16; see ``SLICE``).
    """

    def __init__(
        self,
        rest: np.ndarray,
        triangles: np.ndarray,
        rigid_group: np.ndarray,
        operator: Operator,
        context: Any = None,
        *,
        zero_copy: bool | None = None,
        slice_size: int = SLICE,
    ) -> None:
        import pyopencl as cl

        self._cl = cl
        self._lock = threading.RLock()
        ctx = context if context is not None else default_context()
        if ctx is None:
            from ...errors import FacecastError

            raise FacecastError(
                "no working OpenCL device; install pocl-opencl-icd or use --backend numpy"
            )
        self.context = ctx
        self.device = ctx.devices[0]
        self.name = f"opencl:{context_label(ctx)}"
        self.queue = cl.CommandQueue(ctx)
        self.rest = np.ascontiguousarray(rest, dtype=np.float32)
        self.triangles = np.ascontiguousarray(triangles, dtype=np.int32)
        self.operator = operator
        self.n_vertices = int(self.rest.shape[0])
        self.n_controls = int(operator.n_controls)
        self.n_faces = int(self.triangles.shape[0])
        if operator.n_vertices != self.n_vertices:
            raise ValueError(
                f"operator has {operator.n_vertices} vertices, the mesh {self.n_vertices}"
            )
        group = np.ascontiguousarray(rigid_group, dtype=np.uint8)
        self.n_groups = int(group.max(initial=0)) + 1
        cpu = bool(self.device.type & cl.device_type.CPU)
        # Zero-copy only where device memory is host memory (PoCL and other CPU drivers).
        self.zero_copy = cpu if zero_copy is None else bool(zero_copy and cpu)

        if slice_size not in (8, 16):
            raise ValueError("slice_size must be 8 or 16")
        self.packed = pack_operator(operator, slice_size)
        p = self.packed
        S = p.slice
        self._program = deform_program(
            ctx, {"AXES": p.axes, "IDX_T": p.idx_ctype, "DENSE": int(p.dense), "SLICE": S}
        )
        self._k_deform = cl.Kernel(self._program, "deform")
        self._k_deform_stream = cl.Kernel(self._program, "deform_stream")
        self._cache_bytes = int(self.device.global_mem_cache_size) if cpu else 0
        self._resident_bytes = (
            self.packed.nbytes + 12 * self.packed.n_padded
        )  # operator and rest positions
        self._k_face_normals = cl.Kernel(self._program, "face_normals")
        self._k_vertex_normals = cl.Kernel(self._program, "vertex_normals")

        ro = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR

        def nonempty(a: np.ndarray) -> np.ndarray:  # OpenCL buffers cannot be empty
            return a if a.size else np.zeros(1, a.dtype)

        self._col_ptr = cl.Buffer(ctx, ro, hostbuf=nonempty(p.col_ptr))
        self._id_ptr = cl.Buffer(ctx, ro, hostbuf=nonempty(p.id_ptr))
        self._ids = cl.Buffer(ctx, ro, hostbuf=nonempty(p.ids))
        self._w = cl.Buffer(ctx, ro, hostbuf=nonempty(p.weights))
        n_slices = p.n_padded // S
        rest_p = np.zeros((p.n_padded, 3), np.float32)
        rest_p[: self.n_vertices] = self.rest
        group_p = np.zeros(p.n_padded, np.uint8)
        group_p[: self.n_vertices] = group
        group_p[self.n_vertices :] = group_p[max(0, self.n_vertices - 1)]
        gs = group_p.reshape(n_slices, S)
        sgroup = np.where((gs == gs[:, :1]).all(axis=1), gs[:, 0], 255).astype(np.uint8)
        self._rest = cl.Buffer(
            ctx, ro, hostbuf=np.ascontiguousarray(rest_p.reshape(n_slices, S, 3).transpose(0, 2, 1))
        )
        self._sgroup = cl.Buffer(ctx, ro, hostbuf=sgroup)
        self._sgroup_host = sgroup
        self._group = cl.Buffer(ctx, ro, hostbuf=group_p)
        self._n_slices = n_slices
        self._global_slices = -(-n_slices // LOCAL_SLICES) * LOCAL_SLICES
        # Per-frame parameters: transforms, then D as float4 rows with an all-zero control K at the end.
        self._pstride = -(-(self.n_groups * T_FLOATS + 4 * (self.n_controls + 1)) // 16) * 16
        self._params_host = aligned_empty((self._pstride,), np.float32)
        self._params_host[:] = 0
        if self.zero_copy:  # the kernel reads the host array itself: no upload command per frame
            self._params_single = self._host_buffer(self._params_host, cl.mem_flags.READ_ONLY)
        else:
            self._params_single = cl.Buffer(ctx, cl.mem_flags.READ_ONLY, self._params_host.nbytes)
        self._params = self._params_single
        self._verts = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, max(12, 12 * self.n_vertices))
        self._global = (-(-max(1, self.n_vertices) // LOCAL_SIZE) * LOCAL_SIZE,)
        self._set_deform_args()
        self._warm_up()

    # ----------------------------------------------------------------------------------- helpers
    def _prepare_normals(self) -> None:
        """Upload triangles and the vertex -> triangle adjacency (CSR) once."""
        cl = self._cl
        F, V = self.n_faces, self.n_vertices
        flat = self.triangles.ravel().astype(np.int64)
        order = np.argsort(flat, kind="stable")
        adj = (order // 3).astype(np.uint32)
        adj_ptr = np.zeros(V + 1, dtype=np.uint32)
        np.cumsum(np.bincount(flat, minlength=V), out=adj_ptr[1:])
        ro = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        self._tri = cl.Buffer(
            self.context, ro, hostbuf=self.triangles if F else np.zeros(3, np.int32)
        )
        self._adj = cl.Buffer(self.context, ro, hostbuf=adj if adj.size else np.zeros(1, np.uint32))
        self._adj_ptr = cl.Buffer(self.context, ro, hostbuf=adj_ptr)
        self._fn = cl.Buffer(self.context, cl.mem_flags.READ_WRITE, max(12, 12 * F))

    def _warm_up(self) -> None:
        """Run every kernel once so that the first real frame pays no compilation."""
        self._prepare_normals()
        D = np.zeros((self.n_controls, 3), np.float32)
        T = np.tile(np.eye(3, 4, dtype=np.float32), (self.n_groups, 1, 1))
        v = self.deform(D, T)
        self.normals(v)

    def _check(
        self, D: np.ndarray, transforms: np.ndarray, batch: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        D = np.asarray(D, dtype=np.float32)
        T = np.asarray(transforms, dtype=np.float32)
        lead = D.shape[:1] if batch else ()
        D = D.reshape(lead + (self.n_controls, 3))
        if T.ndim != len(lead) + 3 or T.shape[-2:] != (3, 4) or T.shape[: len(lead)] != lead:
            raise ValueError(f"transforms must be {lead + ('G', 3, 4)}, not {T.shape}")
        if T.shape[-3] < self.n_groups:
            raise ValueError(
                f"the mesh has {self.n_groups} rigid groups; transforms has {T.shape[-3]}"
            )
        if not (np.isfinite(D).all() and np.isfinite(T).all()):
            # (zero weights would otherwise spread a NaN to vertices that do not use the control)
            from ...errors import InputError

            raise InputError(
                "control displacements and transforms must be finite (fill mocap gaps first)",
                where="D" if not np.isfinite(D).all() else "transforms",
            )
        return D, T[..., : self.n_groups, :, :]

    def _fill_params(self, D: np.ndarray, T: np.ndarray) -> np.ndarray:
        """``(n, pstride) float32`` parameter block for frames ``D (n, K, 3)``, ``T (n, G, 3, 4)``."""
        n = D.shape[0]
        if n == 1:
            P = self._params_host
        else:
            P = aligned_empty((n, self._pstride), np.float32)
            P[:] = 0
        P = P.reshape(n, self._pstride)
        gt = self.n_groups * T_FLOATS
        cols = P[:, :gt].reshape(n, self.n_groups, 4, 4)
        cols[..., :3] = T.transpose(0, 1, 3, 2)  # column c of each 3x4 transform as a float4
        Dv = P[:, gt : gt + 4 * (self.n_controls + 1)].reshape(n, self.n_controls + 1, 4)
        Dv[:, : self.n_controls, :3] = D
        return P

    def _upload_params(self, P: np.ndarray) -> None:
        """Make ``P`` (from ``_fill_params``) the parameters of the next launch."""
        cl = self._cl
        single = P.base is self._params_host or P is self._params_host
        if self.zero_copy:
            self._params = (
                self._params_single if single else self._host_buffer(P, cl.mem_flags.READ_ONLY)
            )
            return
        self._params = (
            self._params_single
            if single
            else cl.Buffer(self.context, cl.mem_flags.READ_ONLY, P.nbytes)
        )
        cl.enqueue_copy(self.queue, self._params, P, is_blocking=False)

    def _set_deform_args(self) -> None:
        """Set the deform kernels' resident arguments once (see ``_launch_deform``)."""
        self._arg_frames = {}
        for k in (self._k_deform, self._k_deform_stream):
            k.set_args(
                np.uint32(self.n_vertices),
                np.uint32(self.n_controls),
                self._col_ptr,
                self._id_ptr,
                self._ids,
                self._w,
                self._rest,
                self._sgroup,
                self._group,
                self._params,
                np.uint32(self._pstride // 4),
                np.uint32(self.n_groups),
                np.uint32(1),
                self._verts,
            )
            self._arg_frames[k] = 1

    def _streams(self, n_frames: int, out: np.ndarray | None = None) -> bool:
        """Whether a launch writing ``n_frames`` frames (into ``out``, else the resident vertex
        buffer) uses non-temporal stores (see ``STREAM_FRACTION``; they need 32-byte aligned frames)."""
        big = (
            self._resident_bytes + n_frames * 12 * self.n_vertices
            > STREAM_FRACTION * self._cache_bytes
        )
        if not (big and self._cache_bytes) or self.n_vertices < self.packed.slice:
            return False
        return not (
            (n_frames > 1 and (12 * self.n_vertices) % 32)
            or (out is not None and out.ctypes.data % 32)
        )

    def _launch_deform(self, n_frames: int, out_buf: Any, stream: bool = False) -> Any:
        """Enqueue the deform kernel (``deform_stream`` if ``stream``), setting only the per-launch
        arguments: buffers cost 0.2 us to set, a scalar ~20 us through PyOpenCL (``Kernel.__call__``
        setting all fourteen cost ~60 us a frame, a third of a 25k-vertex frame), so the frame
        count is set only when it changes."""
        k = self._k_deform_stream if stream else self._k_deform
        k.set_arg(9, self._params)
        if n_frames != self._arg_frames[k]:
            k.set_arg(12, np.uint32(n_frames))
            self._arg_frames[k] = n_frames
        k.set_arg(13, out_buf)
        return self._cl.enqueue_nd_range_kernel(
            self.queue, k, (self._global_slices,), (LOCAL_SLICES,)
        )

    def _host_buffer(self, arr: np.ndarray, flags: Any = None) -> Any:
        """A buffer whose storage is host array ``arr`` (``CL_MEM_USE_HOST_PTR``): on a CPU device
        the kernels read and write ``arr`` itself."""
        cl = self._cl
        flags = cl.mem_flags.READ_WRITE if flags is None else flags
        return cl.Buffer(self.context, flags | cl.mem_flags.USE_HOST_PTR, hostbuf=arr)

    def _host_out(self, arr: np.ndarray) -> Any:
        return self._host_buffer(arr, self._cl.mem_flags.WRITE_ONLY)

    def _sync_host(self, buf: Any, arr: np.ndarray, event: Any) -> None:
        """Wait for ``event`` (the kernel writing ``buf``) and make ``arr``, the host storage of
        ``buf``, hold its results: on a host-memory device it already does."""
        if self.zero_copy:
            event.wait()
            return
        cl = self._cl
        mapped, _ = cl.enqueue_map_buffer(
            self.queue, buf, cl.map_flags.READ, 0, arr.shape, arr.dtype, is_blocking=True
        )
        mapped.base.release(self.queue)

    # ------------------------------------------------------------------------------- interface
    def displacements(self, D: np.ndarray) -> np.ndarray:
        """``u = B·D``: ``D (K, 3)`` -> ``(V, 3) float32``."""
        T = np.zeros((self.n_groups, 3, 4), np.float32)
        T[:, :, :3] = np.eye(3, dtype=np.float32)
        return self.deform(D, T) - self.rest

    @_serialised
    def deform(
        self, D: np.ndarray, transforms: np.ndarray, out: np.ndarray | None = None
    ) -> np.ndarray:
        """One frame: ``D (K, 3)``, ``transforms (G, 3, 4)`` -> vertices ``(V, 3) float32``.

        ``out`` (a C-contiguous ``(V, 3) float32`` array) receives the result if given.
        """
        D, T = self._check(D, transforms, batch=False)
        self._upload_params(self._fill_params(D[None], T[None]))
        if out is None:
            out = aligned_empty((self.n_vertices, 3), np.float32)
        elif (
            out.shape != (self.n_vertices, 3)
            or out.dtype != np.float32
            or not out.flags.c_contiguous
        ):
            raise ValueError("out must be a C-contiguous (V, 3) float32 array")
        if self.n_vertices == 0:
            return out
        if self.zero_copy:  # the kernel writes straight into ``out``
            buf = self._host_out(out)
            self._sync_host(buf, out, self._launch_deform(1, buf, self._streams(1, out)))
        else:
            self._launch_deform(1, self._verts, self._streams(1))
            self._cl.enqueue_copy(self.queue, out, self._verts, is_blocking=True)
        return out

    @_serialised
    def deform_batch(
        self, D: np.ndarray, transforms: np.ndarray, out: np.ndarray | None = None
    ) -> np.ndarray:
        """Many frames in one launch: ``D (T, K, 3)``, ``transforms (T, G, 3, 4)`` -> ``(T, V, 3)``.

        ``out`` (a C-contiguous ``(T, V, 3) float32`` array) receives the frames if given.
        """
        D, T = self._check(D, transforms, batch=True)
        n = D.shape[0]
        if out is None:
            out = aligned_empty((n, self.n_vertices, 3), np.float32)
        elif (
            out.shape != (n, self.n_vertices, 3)
            or out.dtype != np.float32
            or not out.flags.c_contiguous
        ):
            raise ValueError("out must be a C-contiguous (T, V, 3) float32 array")
        if n == 0 or self.n_vertices == 0:
            return out
        frame_bytes = 12 * self.n_vertices
        max_alloc = int(self.device.max_mem_alloc_size)
        chunk = max(1, min(n, max_alloc // frame_bytes, 65535))
        for a in range(0, n, chunk):
            b = min(n, a + chunk)
            self._upload_params(self._fill_params(D[a:b], T[a:b]))
            if self.zero_copy:
                buf = self._host_out(out[a:b])
                self._sync_host(
                    buf, out[a:b], self._launch_deform(b - a, buf, self._streams(b - a, out[a:b]))
                )
            else:
                buf = self._cl.Buffer(
                    self.context, self._cl.mem_flags.WRITE_ONLY, (b - a) * frame_bytes
                )
                self._launch_deform(b - a, buf, self._streams(b - a))
                self._cl.enqueue_copy(self.queue, out[a:b], buf, is_blocking=True)
        return out

    @_serialised
    def normals(self, vertices: np.ndarray) -> np.ndarray:
        """Area-weighted unit vertex normals ``(V, 3) float32`` of deformed ``vertices (V, 3)``."""
        cl = self._cl
        v = np.ascontiguousarray(vertices, dtype=np.float32).reshape(self.n_vertices, 3)
        out = aligned_empty((self.n_vertices, 3), np.float32)
        if self.n_vertices == 0:
            return out
        cl.enqueue_copy(self.queue, self._verts, v, is_blocking=False)
        self._launch_normals()
        cl.enqueue_copy(self.queue, out, self._nbuf(), is_blocking=True)
        return out

    def _nbuf(self) -> Any:
        if not hasattr(self, "_normals_out"):
            self._normals_out = self._cl.Buffer(
                self.context, self._cl.mem_flags.READ_WRITE, max(12, 12 * self.n_vertices)
            )
        return self._normals_out

    def _launch_normals(self) -> None:
        F = self.n_faces
        if F:
            self._k_face_normals(
                self.queue,
                (-(-F // LOCAL_SIZE) * LOCAL_SIZE,),
                (LOCAL_SIZE,),
                np.uint32(F),
                self._tri,
                self._verts,
                self._fn,
            )
        self._k_vertex_normals(
            self.queue,
            self._global,
            (LOCAL_SIZE,),
            np.uint32(self.n_vertices),
            self._adj_ptr,
            self._adj,
            self._fn,
            self._nbuf(),
        )

    # ------------------------------------------------------------------------ measuring aids
    def bytes_per_frame(self) -> int:
        """Bytes one ``deform`` frame moves at least: the operator as stored, rest positions, slice
        groups (and per-vertex groups of mixed slices), the frame's parameters and the output."""
        p = self.packed
        mixed = int(np.count_nonzero(self._sgroup_host == 255)) * p.slice
        return int(
            p.nbytes
            + 12 * p.n_padded
            + len(self._sgroup_host)
            + mixed
            + 4 * self._pstride
            + 12 * self.n_vertices
        )

    def format_description(self) -> str:
        """The operator's device format, in words."""
        p = self.packed
        if p.dense:
            return "dense, slice-major float32"
        return (
            f"slices of {p.slice}: {100 * p.shared_fraction:.0f}% shared columns, others ELL; "
            f"{p.idx_ctype} ids; {p.axes} float32 weight plane{'s' if p.axes > 1 else ''}; "
            f"{p.slice * p.n_columns / max(1, self.operator.nnz):.2f} stored weights per non-zero"
        )

    @_serialised
    def upload_frame(self, D: np.ndarray, transforms: np.ndarray, wait: bool = False) -> None:
        """Send one frame's ``D`` and transforms (for ``run_kernel_resident``)."""
        D, T = self._check(D, transforms, batch=False)
        self._upload_params(self._fill_params(D[None], T[None]))
        if wait:
            self.queue.finish()

    @_serialised
    def run_kernel_resident(self, wait: bool = False) -> None:
        """Deform the uploaded frame into the resident vertex buffer (with ``deform``'s stores)."""
        self._launch_deform(1, self._verts, self._streams(1))
        if wait:
            self.queue.finish()

    @_serialised
    def read_resident(self) -> np.ndarray:
        """Copy the resident vertex buffer to a new host array (the non-zero-copy read-back)."""
        out = aligned_empty((self.n_vertices, 3), np.float32)
        self._cl.enqueue_copy(self.queue, out, self._verts, is_blocking=True)
        return out
