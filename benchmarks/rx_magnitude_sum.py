"""Benchmark: the RD magnitude sum ``A = sum_rx |R|`` on full-size RADIal cubes, native vs torch.

Prints one JSON object per thread count (1 and 2 by default) with, per method, the best and
median ms/frame over ``--repeats`` passes, frames/s and the GB/s of cube read, plus the ratios to
the torch fallback and to the read floor, measured in the same run (methods are interleaved pass
by pass so that load from other processes hits them alike):

* ``native``: :func:`radarpc.dsp.accel.native.rx_magnitude_sum_native` (kernel ``auto``), and each
  other kernel this CPU can run (``native/avx``, ``native/scalar``, ...);
* ``torch``: :func:`radarpc.dsp.accel.rxsum.rx_magnitude_sum_blocked`, the blocked torch
  implementation (what a build without the C kernels runs);
* ``core``: :func:`radarpc.dsp.ddma.rx_magnitude_sum` with the accel switch off, the core's
  one-pass torch formula (what ``RADARPC_NO_NATIVE=1`` runs);
* ``read_floor``: ``torch.view_as_real(x).sum()``, one pass over the cube with trivial arithmetic;
* ``native_after_torch_op``: the native kernel started right after a parallel torch op, with no
  pause. Every other method is timed after a ``--gap-ms`` pause: torch's OpenMP workers keep
  spinning for about a millisecond after a parallel region, and on a 2-core machine they then
  compete with the native kernel's pool thread (and with the next torch op's own threads less).

Usage::

    python benchmarks/rx_magnitude_sum.py --batch 8 --threads 1 2 --repeats 15
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable

import torch

from radarpc.dsp import accel
from radarpc.dsp.accel.native import native_available, native_kernels, rx_magnitude_sum_native
from radarpc.dsp.accel.rxsum import rx_magnitude_sum_blocked
from radarpc.dsp.ddma import rx_magnitude_sum
from radarpc.machine import cpu_model
from radarpc.sensors.radial import RADIAL


def _parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=8, help="full RADIal frames per call")
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts to time")
    p.add_argument("--repeats", type=int, default=15, help="timed passes per method (best and median reported)")
    p.add_argument("--gap-ms", type=float, default=20.0,
                   help="pause before each timed call (lets torch's OpenMP workers stop spinning)")
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args()


def _core(x: torch.Tensor) -> torch.Tensor:
    with accel.disabled():
        return rx_magnitude_sum(x)


def _methods(threads: int) -> dict[str, Callable[[torch.Tensor], object]]:
    m: dict[str, Callable[[torch.Tensor], object]] = {}
    if native_available():
        m["native"] = lambda x: rx_magnitude_sum_native(x, threads=threads)
        for k in native_kernels(RADIAL.rd_shape[-1])[1:]:
            m[f"native/{k}"] = lambda x, k=k: rx_magnitude_sum_native(x, threads=threads, kernel=k)
    m["torch"] = rx_magnitude_sum_blocked
    m["core"] = _core
    m["read_floor"] = lambda x: torch.view_as_real(x).sum()
    return m


def _time(f: Callable[[torch.Tensor], object], x: torch.Tensor, gap_s: float) -> float:
    time.sleep(gap_s)
    t0 = time.perf_counter()
    f(x)
    return time.perf_counter() - t0


def main() -> None:
    args = _parse()
    g = torch.Generator().manual_seed(args.seed)
    x = torch.randn((args.batch, *RADIAL.rd_shape), dtype=torch.complex64, generator=g)   # (B, Nr, Nd, Nrx)
    gbytes = x.numel() * x.element_size() / 1e9
    for threads in args.threads:
        torch.set_num_threads(threads)
        methods = _methods(threads)
        if "native" in methods:                                      # same values as the core
            a, b = methods["native"](x), _core(x)
            max_rel = float(((a - b).abs() / b.abs().clamp_min(1e-30)).max())
        else:
            max_rel = None
        times: dict[str, list[float]] = {k: [] for k in methods}
        for f in methods.values():                                   # warm-up (pool threads, page faults)
            f(x)
        spin = torch.ones(1 << 20)
        if "native" in methods:
            times["native_after_torch_op"] = []
        for _ in range(args.repeats):
            for name, f in methods.items():
                times[name].append(_time(f, x, args.gap_ms * 1e-3))
            if "native" in methods:
                time.sleep(args.gap_ms * 1e-3)
                spin.mul(2.0).sum()                                  # parallel torch op, then no pause
                times["native_after_torch_op"].append(_time(methods["native"], x, 0.0))
        res = {}
        for name, ts in times.items():
            best = min(ts)
            res[name] = {"ms_per_frame": round(best / args.batch * 1e3, 4),
                         "median_ms_per_frame": round(statistics.median(ts) / args.batch * 1e3, 4),
                         "frames_per_s": round(args.batch / best, 1),
                         "gb_per_s": round(gbytes / best, 2)}
        floor = res["read_floor"]["ms_per_frame"]
        torch_ms = res["torch"]["ms_per_frame"]
        for r in res.values():
            r["vs_torch_speedup"] = round(torch_ms / r["ms_per_frame"], 2)
            r["vs_read_floor"] = round(r["ms_per_frame"] / floor, 2)
        print(json.dumps({
            "benchmark": "rx_magnitude_sum", "frame_shape": list(RADIAL.rd_shape), "batch": args.batch,
            "device": "cpu", "threads": threads, "cpu": cpu_model(), "repeats": args.repeats,
            "native_available": native_available(),
            "native_kernel": native_kernels(RADIAL.rd_shape[-1])[0] if native_available() else None,
            "native_vs_torch_max_rel_diff": max_rel, "results": res,
        }))


if __name__ == "__main__":
    main()
