"""What machine a measurement ran on (for the benchmark scripts and run reports), and which torch
devices it has (:func:`check_device`)."""
from __future__ import annotations

import os
import platform
from pathlib import Path

__all__ = ["check_device", "cpu_has_native_bf16", "cpu_model", "numeric_libraries", "physical_memory_bytes"]


def cpu_model() -> str:
    """The CPU's ``model name`` from ``/proc/cpuinfo`` (what ``lscpu`` shows), else the platform's
    processor or machine string."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        return platform.processor() or platform.machine()
    return platform.processor() or platform.machine()


def physical_memory_bytes() -> int | None:
    """The machine's physical memory in bytes (POSIX ``sysconf``), or None where it cannot be read."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


def cpu_has_native_bf16(cpuinfo: str | None = None) -> bool:
    """Whether the CPU computes bf16 natively (the ``avx512_bf16`` or ``amx_bf16`` flag).

    Elsewhere torch emulates bf16, which is slower than fp32; so this decides what the training
    loop's ``precision: auto`` means on a CPU and whether a benchmark times a bf16 path.

    Parameters
    ----------
    cpuinfo : str, optional
        The text of ``/proc/cpuinfo``; read from the file when not given (False if unreadable).
    """
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text(errors="replace")
        except OSError:
            return False
    flags = set()
    for line in cpuinfo.splitlines():
        if line.startswith("flags"):
            flags.update(line.split(":", 1)[1].split())
    return bool(flags & {"avx512_bf16", "amx_bf16"})


def numeric_libraries() -> dict[str, str]:
    """Versions of torch and numpy, torch's CPU kernel level and the BLAS numpy runs with.

    A benchmark that compares radarpc with a numpy baseline records these, because the
    baseline's speed depends on which BLAS build and kernel it gets. The BLAS kernel
    (``architecture``, e.g. ``SkylakeX``) comes from ``threadpoolctl`` when it is installed;
    otherwise only numpy's build-time BLAS name and version are given.
    """
    import numpy as np
    import torch

    out = {"torch": torch.__version__, "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
           "numpy": np.__version__}
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        blas = getattr(np.__config__, "CONFIG", {}).get("Build Dependencies", {}).get("blas", {})   # numpy >= 1.26
        out["numpy_blas"] = f"{blas.get('name', '?')} {blas.get('version', '?')}"
        return out
    for pool in threadpool_info():
        if pool.get("user_api") == "blas" and "numpy" in pool.get("filepath", ""):
            out["numpy_blas"] = (f"{pool.get('internal_api')} {pool.get('version')} "
                                 f"({pool.get('architecture', '?')}, {pool.get('num_threads')} threads)")
            break
    return out


def check_device(device: "str | object", what: str = "device") -> "object":
    """``torch.device(device)`` after checking that this machine has it.

    Parameters
    ----------
    device : str or torch.device
        E.g. ``"cpu"``, ``"cuda"``, ``"cuda:1"``.
    what : str
        How the messages name it (a CLI passes its flag, ``"--device"``).

    Returns
    -------
    torch.device

    Raises
    ------
    ValueError
        Not a device name, or a CUDA device this machine (or this torch build) does not have.
    """
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"{what} {device!r} is not a torch device (expected e.g. cpu, cuda or cuda:1): {e}") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch build has no CUDA" if torch.version.cuda is None else "no CUDA GPU is visible"
            raise ValueError(f"{what} {device!r}: CUDA is not available ({why}; torch {torch.__version__}); "
                             f"use --device cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"{what} {device!r}: only {torch.cuda.device_count()} CUDA device(s) are visible")
    return dev
