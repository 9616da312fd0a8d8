"""Reusable scratch buffers for repeated batched calls.

The beamformers need several scratch tensors of a few to tens of MB per call (GEMM outputs of a
block of snapshots against the whole angle grid). Allocating them afresh on every call lets the
C allocator hand back fresh pages that the kernel must fault in and zero, which on CPU costs as
much as some of the arithmetic. A :class:`Workspace` keeps one growing buffer per (name, device,
dtype) and hands out views of it. Views are valid until the next request of the same name, so a
workspace is only for scratch that never leaves the function that asked for it. Each thread gets
its own buffers, so a module holding a workspace can be called from several threads at once.
"""
from __future__ import annotations

import math
import threading

import torch

__all__ = ["Workspace"]


class Workspace:
    """Per-thread cache of scratch buffers, grown on demand and reused across calls.

    Examples
    --------
    >>> ws = Workspace()
    >>> a = ws.empty("gemm_out", (4, 8), torch.float32, torch.device("cpu"))
    >>> a.shape, ws.nbytes
    (torch.Size([4, 8]), 128)
    """

    def __init__(self) -> None:
        self._local = threading.local()

    def _buffers(self) -> dict[tuple[str, torch.device, torch.dtype], torch.Tensor]:
        bufs = getattr(self._local, "buffers", None)
        if bufs is None:
            bufs = self._local.buffers = {}
        return bufs

    def empty(self, name: str, shape: tuple[int, ...], dtype: torch.dtype,
              device: torch.device | str) -> torch.Tensor:
        """An uninitialised tensor of ``shape``: a view of the cached buffer ``name`` (grown if
        too small). A later request of the same ``name`` in the same thread may overwrite it."""
        if any(int(s) < 0 for s in shape):
            raise ValueError(f"workspace buffer {name!r}: negative size in shape {tuple(shape)}")
        device = torch.device(device)
        n = math.prod(int(s) for s in shape)
        key = (name, device, dtype)
        bufs = self._buffers()
        buf = bufs.get(key)
        if buf is None or buf.numel() < n:
            buf = bufs[key] = torch.empty(n, dtype=dtype, device=device)
        return buf[:n].view(tuple(int(s) for s in shape))

    @property
    def nbytes(self) -> int:
        """Bytes held by this thread's buffers."""
        return sum(b.numel() * b.element_size() for b in self._buffers().values())

    def clear(self) -> None:
        """Release this thread's buffers."""
        self._buffers().clear()

    def __getstate__(self) -> dict:
        return {}                                      # buffers are scratch: never copied or pickled

    def __setstate__(self, state: dict) -> None:
        self._local = threading.local()
