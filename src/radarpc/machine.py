"""What machine a measurement ran on (for the benchmark scripts and run reports), and which torch
devices it has (:func:`check_device`)."""
from __future__ import annotations

import os
import platform
from pathlib import Path

__all__ = ["check_device", "cpu_has_native_bf16", "cpu_model", "cpu_flags", "isa_flags", "ISA_FLAGS", "load_average",
           "machine_record", "numeric_libraries", "physical_memory_bytes"]

ISA_FLAGS = ("sse4_2", "avx", "avx2", "fma", "f16c", "avx_vnni", "avx512f", "avx512bw", "avx512vl", "avx512_vnni",
             "avx512_bf16", "avx512_fp16", "amx_tile", "amx_bf16", "amx_int8", "asimd", "sve", "sve2")
"""The vector instruction sets a timing depends on, as ``/proc/cpuinfo`` names them (x86 and Arm)."""


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
    return bool(cpu_flags(cpuinfo) & {"avx512_bf16", "amx_bf16"})


def cpu_flags(cpuinfo: str | None = None) -> frozenset[str]:
    """The CPU's feature flags: the ``flags`` lines (x86) or ``Features`` lines (Arm) of
    ``/proc/cpuinfo``, every processor's together (empty where the file cannot be read).

    Parameters
    ----------
    cpuinfo : str, optional
        The text of ``/proc/cpuinfo``; read from the file when not given.
    """
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text(errors="replace")
        except OSError:
            return frozenset()
    flags: set[str] = set()
    for line in cpuinfo.splitlines():
        key = line.split(":", 1)[0].strip()
        if key in ("flags", "Features") and ":" in line:
            flags.update(line.split(":", 1)[1].split())
    return frozenset(flags)


def isa_flags(cpuinfo: str | None = None) -> list[str]:
    """The vector instruction sets of :data:`ISA_FLAGS` the CPU has, in that order (e.g.
    ``["sse4_2", "avx", "avx2", "fma", "f16c"]`` on an AVX2 machine without AVX-512)."""
    flags = cpu_flags(cpuinfo)
    return [f for f in ISA_FLAGS if f in flags]


def load_average() -> list[float] | None:
    """The system's load average over 1, 5 and 15 minutes (None where the system does not tell)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except (AttributeError, OSError):
        return None


def machine_record() -> dict:
    """What a timing ran on: the CPU model, the logical CPUs of the machine and those this process
    may run on, the vector instruction sets (:func:`isa_flags`), torch's CPU kernel level and
    thread count, and the physical memory."""
    import torch

    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = os.cpu_count()
    return {"cpu": cpu_model(), "logical_cpus": os.cpu_count(), "usable_cpus": usable, "isa": isa_flags(),
            "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(), "torch_threads": torch.get_num_threads(),
            "memory_bytes": physical_memory_bytes()}


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
