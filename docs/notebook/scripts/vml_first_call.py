"""How often torch's first CPU transcendental call in a process comes out at reduced accuracy.

On torch 2.13's CPU wheel (MKL 2024.2, OpenMP) on a 2-core Intel Xeon VM (and, by the symptom,
an AMD EPYC one), the first MKL VML call (``sqrt``, ``sin``, ``cos``, ``exp``, ``log``, ``tanh``,
``erf``, ...) that an OpenMP worker thread ran after MKL or oneDNN work came out of some
processes at reduced accuracy on the worker's share of the tensor, and every later call exact
(docs/results/vml_first_call.md). Run to run it moved NMS and true-positive decisions of the same
weights, so :func:`radarpc.boxes.ra_to_box_xy` computes boxes with numpy on the CPU.

Each trial is a fresh Python process running what a pillar model's forward starts with (a
Linear + GELU on 156 points, scattered into a 4 x 8 x 128 x 224 canvas, one 3 x 3 convolution,
which triggered it more often than a lone GEMM), then ``torch.sqrt`` of a
114,688-element float32 tensor twice (over torch's 32,768-element grain, so the work is split
between threads); the trial is inaccurate when the two calls differ. The same trial runs with
``MKL_NUM_THREADS=1`` (torch then runs one thread too); then the box positions of 114,688
detections are the first call after the forward, once as torch computes them (``R sin A``,
``R cos A``: the baseline) and once through :func:`radarpc.boxes.ra_to_box_xy`, whose
two calls must agree in every process::

    python docs/notebook/scripts/vml_first_call.py --processes 40

Prints one JSON object.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys


def trial(first: str) -> dict:
    """One process's trial (see the module docstring); ``first`` is ``"sqrt"``, ``"boxes_torch"`` or
    ``"boxes"``."""
    import torch
    import torch.nn.functional as F

    from radarpc.boxes import ra_to_box_xy

    g = torch.Generator().manual_seed(0)
    x = torch.rand(114_688, generator=g) + 0.1
    n, c, (h, w) = 156, 8, (128, 224)
    with torch.inference_mode():
        feat = F.gelu(F.linear(torch.randn(n, 12, generator=g), torch.randn(c, 12, generator=g)))   # (N, C)
        canvas = feat.new_zeros(4 * h * w, c).index_copy_(0, torch.randperm(4 * h * w, generator=g)[:n], feat)
        F.conv2d(canvas.view(4, h, w, c).permute(0, 3, 1, 2), torch.randn(c, c, 3, 3, generator=g), padding=1)
    r, az = x * 100, (x - 0.6) * 150                                           # m, degrees
    if first == "sqrt":
        y1, y2 = torch.sqrt(x), torch.sqrt(x)
    elif first == "boxes_torch":
        def boxes(r, az):
            a = torch.deg2rad(az)
            return torch.stack([r * torch.sin(a), r * torch.cos(a)], dim=-1)

        y1, y2 = boxes(r, az), boxes(r, az)
    else:
        y1, y2 = ra_to_box_xy(r, az), ra_to_box_xy(r, az)
    err = ((y1 - y2).abs().max() / y2.abs().max()).item()                  # relative to the largest
    return {"threads": torch.get_num_threads(), "max_rel_error": err}


def run(first: str, processes: int, env: dict[str, str]) -> dict:
    errors, threads = [], set()
    for _ in range(processes):
        res = subprocess.run([sys.executable, __file__, "--child", first], capture_output=True, text=True,
                             env={**os.environ, **env})
        if res.returncode != 0:
            raise SystemExit(f"vml_first_call.py: the {first!r} trial failed (exit {res.returncode}):\n"
                             f"{res.stderr[-2000:]}")
        t = json.loads(res.stdout)
        errors.append(t["max_rel_error"])
        threads.add(t["threads"])
    return {"first_call": first, "env": env, "torch_threads": sorted(threads), "processes": processes,
            "inaccurate": sum(e > 0 for e in errors), "max_rel_error": max(errors)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--processes", type=int, default=20, help="fresh processes per case")
    ap.add_argument("--child", choices=("sqrt", "boxes_torch", "boxes"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.processes < 1:
        ap.error(f"--processes must be >= 1, got {args.processes}")
    if args.child:
        print(json.dumps(trial(args.child)))
        return
    import torch

    cases = [run("sqrt", args.processes, {}), run("sqrt", args.processes, {"MKL_NUM_THREADS": "1"}),
             run("boxes_torch", args.processes, {}), run("boxes", args.processes, {})]
    print(json.dumps({"torch": torch.__version__, "cpu_capability": torch.backends.cpu.get_cpu_capability(),
                      "cases": cases}))


if __name__ == "__main__":
    main()
