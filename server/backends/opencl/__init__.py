"""The OpenCL backend (PyOpenCL): the NumPy reference's results, near the memory-bandwidth limit.

- ``deformer``: ``OpenCLDeformer``, per-frame deformation and normals with resident buffers;
- ``packing``: an ``Operator`` in the deform kernel's format (``pack_operator``; pure NumPy);
- ``kernels``: the kernels' OpenCL C (the generated deform kernel, ``*.cl`` files) and building it;
- ``quantize``: ``DeviceQuantizer``, int16 wire frames on the device, bit for bit the host's;
- ``compact``: ``DeviceCompact``, a batch's compact residual planes on the device (the host's bytes);
- ``host``: aligned host arrays the device reads and writes in place.

Device selection is ``..select``'s (``default_context``).
"""

from __future__ import annotations

from ..select import context_label, default_context, probe_devices
from .deformer import OpenCLDeformer
from .host import ALIGN, aligned_empty
from .packing import SLICE, PackedOperator, pack_operator
from .quantize import DeviceQuantizer

__all__ = [
    "ALIGN",
    "SLICE",
    "DeviceQuantizer",
    "OpenCLDeformer",
    "PackedOperator",
    "aligned_empty",
    "context_label",
    "default_context",
    "pack_operator",
    "probe_devices",
]
