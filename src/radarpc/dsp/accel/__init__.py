"""Accelerated paths of the DSP core, behind the core's own functions, and the one switch over them.

The core (:mod:`radarpc.dsp`) computes every step with one exact torch path. This package holds
what exists only for speed, each tested for equality with the core path it replaces:

* :mod:`~radarpc.dsp.accel.rxsum`: ``A = sum_rx |R|`` on CPU (behind
  :func:`radarpc.dsp.ddma.rx_magnitude_sum`): the C kernel of :mod:`~radarpc.dsp.accel.native`
  when it is built, else the torch formula in cache-sized row blocks;
* :mod:`~radarpc.dsp.accel.screened`: the screened bfloat16 beamformer (the ``"screened"`` and
  ``"auto"`` beamforming modes; its selection step runs in C when the kernels are built) and
  :func:`~radarpc.dsp.accel.screened.measured_choice`, the one-off timing that picks ``"auto"``'s
  beamformer (the core's :func:`radarpc.dsp.beamform_modes.beamform` runs the mode);
* :mod:`~radarpc.dsp.accel.subspace`: the subspace beamformer (``"subspace"``), a certified
  block low-rank float32 screen of the dictionary; its screen and selection run in C when built;
* :mod:`~radarpc.dsp.accel.native`: the optional C kernels (``_rxsum.c``, ``_screen.c``; a
  pure-Python install runs without them) and their thread pool;
* :mod:`~radarpc.dsp.accel.workspace`: reusable scratch buffers of the beamformers.

The switch: :func:`enabled` is ``True`` unless the environment variable ``RADARPC_NO_NATIVE`` is
set (to anything but empty or ``0``) or a :func:`disabled` block is running. When it is off, the
core functions run their torch path, the C kernels are not used, and ``"auto"`` beamforming runs
the core's exact beamformer; an explicit ``"screened"`` or ``"subspace"`` still runs that screen,
selecting in torch.
"""
from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator

__all__ = ["DISABLE_ENV", "enabled", "disabled"]

DISABLE_ENV = "RADARPC_NO_NATIVE"
"""Environment variable: any value other than empty or ``0`` turns the accelerated paths off
(read at every call; inherited by worker processes)."""

_off = 0                                   # open disabled() blocks, process-wide
_off_lock = threading.Lock()


def enabled() -> bool:
    """Whether the core functions may dispatch to the accelerated paths.

    Returns
    -------
    bool
        ``False`` inside a :func:`disabled` block or when ``RADARPC_NO_NATIVE`` is set.
    """
    return _off == 0 and os.environ.get(DISABLE_ENV, "") in ("", "0")


@contextlib.contextmanager
def disabled() -> Iterator[None]:
    """Run the block on the core torch paths only (process-wide, all threads; blocks may nest).

    Examples
    --------
    >>> with disabled():
    ...     enabled()
    False
    """
    global _off
    with _off_lock:
        _off += 1
    try:
        yield
    finally:
        with _off_lock:
            _off -= 1
