"""What a model's forward pass costs: its multiply-accumulates, its batch-1 frames/s and the
memory one pass needs.

* :func:`conv_gmac` counts the multiply-accumulates of the convolutions with forward hooks on one
  real pass, so it follows whatever the forward actually runs (a skipped head costs nothing).
  Divided by a CPU's best GMAC/s it gives the fastest the network could run there.
* :func:`frames_per_second` times a per-frame function at batch 1: warm-up passes, then timed
  sweeps over the frames; the :class:`Rate` is their median with the lowest and highest sweep
  (the spread says how steady the machine was). :func:`time_interleaved` times several methods
  pass by pass, so that load from other processes hits them alike (the benchmark scripts').
  Both synchronise a CUDA device before reading the clock (:func:`synchronize`).
* :class:`PeakMemory` measures the memory a block of code needs above what was resident when it
  started: on a CUDA device ``torch.cuda.max_memory_allocated`` (reset at the start), on a CPU the
  process's peak resident set size (Linux: ``VmHWM``, reset at the start through
  ``/proc/self/clear_refs``, after the free heap has been returned to the system). Python's
  ``tracemalloc`` does not see torch's allocations, so it is not used.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import gc
import math
import resource
import statistics
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import torch

__all__ = ["conv_gmac", "Rate", "frames_per_second", "SweepTimes", "time_interleaved", "synchronize",
           "Memory", "PeakMemory", "MEMORY_METHODS"]


def conv_gmac(model: torch.nn.Module, *inputs: torch.Tensor, forward: Callable | None = None) -> float:
    """Multiply-accumulates of every convolution in one forward pass, in GMAC.

    Each output element of a ``Conv2d`` takes ``kernel elements x input channels per group`` MACs;
    each input element of a ``ConvTranspose2d`` feeds ``kernel elements x output channels per
    group`` outputs. Other layers are not counted.

    Parameters
    ----------
    model : torch.nn.Module
        Its ``Conv2d`` and ``ConvTranspose2d`` submodules are counted.
    *inputs : Tensor
        The pass's inputs.
    forward : callable, optional
        What to run on ``inputs`` (e.g. ``model.forward_channels``); ``model`` itself by default.

    Returns
    -------
    float
        GMAC of the pass (run under ``torch.inference_mode``).
    """
    total = [0]

    def hook(conv, inp, out):
        # weight[0]: (in / groups, kh, kw) for a convolution, (out / groups, kh, kw) for a transposed one
        n = inp[0].numel() if isinstance(conv, torch.nn.ConvTranspose2d) else out.numel()
        total[0] += n * conv.weight[0].numel()
    hooks = [m.register_forward_hook(hook) for m in model.modules()
             if isinstance(m, (torch.nn.Conv2d, torch.nn.ConvTranspose2d))]
    try:
        with torch.inference_mode():
            (forward or model)(*inputs)
    finally:
        for h in hooks:
            h.remove()
    return total[0] / 1e9


# ---- time ---------------------------------------------------------------------------------------
def synchronize(device: torch.device | str | None) -> None:
    """Wait for ``device``'s queued work (CUDA only; CPU work is done when the call returns)."""
    if device is not None and torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


@dataclass(frozen=True)
class Rate:
    """Batch-1 frames/s measured in ``repeats`` timed sweeps over the same frames, after warm-up.

    Attributes
    ----------
    median, low, high : float
        The median, lowest and highest of the sweeps' rates (NaN without frames).
    repeats : int
        Timed sweeps.
    sweeps : tuple of float
        Every sweep's rate, in the order they ran.
    """

    median: float
    low: float
    high: float
    repeats: int
    sweeps: tuple[float, ...] = ()

    def text(self) -> str:
        """``"12.3 frames/s (11.9-12.8 over 5 sweeps)"``, three significant digits (0.047 stays 0.047)."""
        if math.isnan(self.median):
            return "n/a frames/s (no frames)"
        return f"{self.median:.3g} frames/s ({self.low:.3g}-{self.high:.3g} over {self.repeats} sweeps)"

    @classmethod
    def of(cls, rates: list[float]) -> "Rate":
        """The rate of the sweeps ``rates`` (frames/s each)."""
        if not rates:
            return cls(math.nan, math.nan, math.nan, 0)
        return cls(float(statistics.median(rates)), min(rates), max(rates), len(rates), tuple(rates))


def frames_per_second(run_frame: Callable[[object], object], frames: list, device: torch.device | str | None = None,
                      repeats: int = 5, warmup: int = 2) -> Rate:
    """Batch-1 frames/s of ``run_frame`` over ``frames``.

    ``warmup`` untimed passes over the first frame (first-call compilation and allocation), then
    ``repeats`` timed sweeps over all of them; a sweep's rate is its frames over its wall time,
    with the device synchronised before the clock is read at either end.

    Parameters
    ----------
    run_frame : callable
        Called with each frame; its result is not kept.
    frames : list
        The inputs, already on ``device``. Empty: a NaN rate.
    device : torch.device or str, optional
        Where ``run_frame`` computes (a CUDA device is synchronised; None or a CPU is not).
    repeats, warmup : int
        Timed sweeps (>= 1) and untimed first passes (>= 0).

    Returns
    -------
    Rate
    """
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise ValueError(f"repeats must be an integer >= 1, got {repeats!r}")
    if isinstance(warmup, bool) or not isinstance(warmup, int) or warmup < 0:
        raise ValueError(f"warmup must be an integer >= 0, got {warmup!r}")
    if not frames:
        return Rate.of([])
    rates = []
    for _ in range(warmup):
        run_frame(frames[0])
    for _ in range(repeats):
        synchronize(device)
        t0 = time.perf_counter()
        for f in frames:
            run_frame(f)
        synchronize(device)
        rates.append(len(frames) / max(time.perf_counter() - t0, 1e-12))
    return Rate.of(rates)


@dataclass(frozen=True)
class SweepTimes:
    """One method's times in :func:`time_interleaved`, per frame.

    Attributes
    ----------
    wall_s : tuple of float
        Wall seconds per frame of each timed pass.
    cpu_s : tuple of float
        Process CPU seconds per frame of each timed pass (all threads: on a loaded machine with
        one thread a steadier measure of the work than wall time).
    first_s : float or None
        Wall seconds per frame of the first warm-up pass (compilation and first allocations);
        None without warm-up.
    """

    wall_s: tuple[float, ...]
    cpu_s: tuple[float, ...]
    first_s: float | None


def time_interleaved(methods: Mapping[str, Callable[[int], object]], n_frames: int, repeats: int, *,
                     warmup: int = 1, device: torch.device | str | None = None) -> dict[str, SweepTimes]:
    """Times of each method over the same frames, the methods interleaved pass by pass.

    Every pass runs each method over frames ``0 .. n_frames - 1`` in turn (``method(i)``), so that
    load from other processes hits the methods alike; the first ``warmup`` passes are not timed.

    Returns
    -------
    dict
        :class:`SweepTimes` by method name.
    """
    if isinstance(n_frames, bool) or not isinstance(n_frames, int) or n_frames < 1:
        raise ValueError(f"n_frames must be an integer >= 1, got {n_frames!r}")
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise ValueError(f"repeats must be an integer >= 1, got {repeats!r}")
    wall: dict[str, list[float]] = {k: [] for k in methods}
    cpu: dict[str, list[float]] = {k: [] for k in methods}
    first: dict[str, float | None] = {k: None for k in methods}
    for rep in range(warmup + repeats):
        for name, fn in methods.items():
            synchronize(device)
            t0, c0 = time.perf_counter(), time.process_time()
            for i in range(n_frames):
                fn(i)
            synchronize(device)
            t, c = (time.perf_counter() - t0) / n_frames, (time.process_time() - c0) / n_frames
            if rep == 0 and warmup:
                first[name] = t
            if rep >= warmup:
                wall[name].append(t)
                cpu[name].append(c)
    return {k: SweepTimes(tuple(wall[k]), tuple(cpu[k]), first[k]) for k in methods}


# ---- memory -------------------------------------------------------------------------------------
MEMORY_METHODS = {
    "cuda-max-allocated": "torch.cuda.max_memory_allocated, reset at the start, above the memory allocated then",
    "rss-peak-reset": "the process's peak resident set size (VmHWM, reset at the start through /proc/self/clear_refs) "
                      "above its resident set size at the start, the free heap returned to the system first",
    "maxrss-delta": "the growth of the process's peak resident set size (getrusage ru_maxrss) over the block: a lower "
                    "bound when the process had peaked higher before it",
}
"""How :class:`PeakMemory` measured, by the name its :class:`Memory` carries."""


@dataclass(frozen=True)
class Memory:
    """The memory a block of code needed (:class:`PeakMemory`).

    Attributes
    ----------
    method : str
        A key of :data:`MEMORY_METHODS`.
    baseline_bytes : int
        Resident (CPU) or allocated (CUDA) at the start of the block.
    peak_bytes : int
        The peak during the block (for ``maxrss-delta``: the process's peak since it started).
    working_bytes : int
        What the block needed above the baseline: ``peak - baseline`` (``maxrss-delta``: the
        peak's growth during the block).
    """

    method: str
    baseline_bytes: int
    peak_bytes: int
    working_bytes: int

    def to_dict(self) -> dict:
        return {"method": self.method, "baseline_bytes": self.baseline_bytes, "peak_bytes": self.peak_bytes,
                "working_bytes": self.working_bytes}


_STATUS = Path("/proc/self/status")
_CLEAR_REFS = Path("/proc/self/clear_refs")


def _status_kb(field: str) -> int | None:
    try:
        for line in _STATUS.read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def _maxrss_bytes() -> int:
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(r) if sys.platform == "darwin" else int(r) * 1024        # bytes on macOS, KiB elsewhere


def _trim_heap() -> None:
    """Return the C heap's free memory to the system (glibc's ``malloc_trim``; elsewhere nothing),
    so that the resident set holds what is in use."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        libc.malloc_trim(ctypes.c_size_t(0))
    except (OSError, AttributeError, TypeError):
        return


class PeakMemory:
    """Measure the memory the ``with`` block needs above what is resident when it starts.

    On a CUDA device: ``torch.cuda.reset_peak_memory_stats`` at the start, then
    ``max_memory_allocated`` above ``memory_allocated`` at the start (``cuda-max-allocated``). On a
    CPU (Linux): garbage collection and ``malloc_trim`` (so that freed memory does not count in the
    baseline and get reused unseen), ``VmRSS`` as the baseline, the peak ``VmHWM`` reset through
    ``/proc/self/clear_refs``, and ``VmHWM`` at the end (``rss-peak-reset``); where the peak cannot be
    reset, the growth of ``getrusage``'s ``ru_maxrss`` (``maxrss-delta``, a lower bound: run the block
    in a fresh process). The whole process counts: run nothing else in it meanwhile.

    Examples
    --------
    >>> with PeakMemory("cpu") as probe:
    ...     x = torch.ones(1 << 20)
    >>> probe.memory.working_bytes >= 0
    True
    """

    def __init__(self, device: torch.device | str | None = None) -> None:
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.memory: Memory | None = None
        self._method = ""
        self._baseline = 0
        self._start_peak = 0

    def __enter__(self) -> "PeakMemory":
        gc.collect()
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self._method, self._baseline = "cuda-max-allocated", int(torch.cuda.memory_allocated(self.device))
            return self
        _trim_heap()
        rss = _status_kb("VmRSS")
        reset = False
        if rss is not None:
            try:
                _CLEAR_REFS.write_text("5")                 # 5: reset the peak resident set size (Linux >= 4.0)
                reset = (_status_kb("VmHWM") or 0) <= (_status_kb("VmRSS") or 0) + 64   # KiB: the reset took
            except OSError:
                reset = False
        if reset:
            self._method, self._baseline = "rss-peak-reset", (_status_kb("VmRSS") or rss) * 1024
        else:
            self._method = "maxrss-delta"
            self._baseline = rss * 1024 if rss is not None else _maxrss_bytes()
            self._start_peak = _maxrss_bytes()
        return self

    def __exit__(self, *exc) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            peak = int(torch.cuda.max_memory_allocated(self.device))
            working = peak - self._baseline
        elif self._method == "rss-peak-reset":
            peak = (_status_kb("VmHWM") or 0) * 1024
            working = peak - self._baseline
        else:
            peak = _maxrss_bytes()
            working = peak - self._start_peak
        self.memory = Memory(self._method, self._baseline, peak, max(0, working))
