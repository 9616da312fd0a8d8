"""Speed of the RADIal-format simulator: frames per second, printed as JSON (one object per line).

For each sensor (``radial`` 512 x 256 x 16, ``radial-s`` 128 x 64 x 16) and device (CPU, and CUDA
when present) it times, over frames of procedural road scenes:

* ``synth``: :func:`radarpc.sim.rd.synthesize_rd` of the frame's scatterers, thermal noise included;
* ``synth_ideal``: the same with an ideal receiver (:func:`radarpc.sensors.radial.ideal_receiver`:
  no IF filter, leakage or phase-noise skirts), interleaved frame by frame with ``synth`` so that
  ``receiver_cost_ratio`` (median of the per-frame ratios) compares the two under the same load;
* ``frame``: the whole frame as the on-the-fly dataset makes it (scene, labels, freespace mask,
  synthesis: :meth:`RadialSimulator.frame`).

Times are per frame: the median and the best (least disturbed by other processes on a shared
machine); the 1-minute load average is reported alongside. ``cube_std`` is the per-channel
real/imaginary standard deviation of the cubes (all frames pooled; median, min and max over the
``2 n_rx`` channels), to compare with a real root's normalisation statistics (FFTRadNet's
``input_std``).

Usage::

    python benchmarks/simulate.py [--threads 2] [--frames 20] [--sensors radial radial-s]
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import torch

from radarpc.sensors.radial import ideal_receiver, radial_sensor
from radarpc.sim.radial_writer import RadialSimulator
from radarpc.sim.rd import synthesize_rd
from radarpc.machine import cpu_model


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def bench(sensor: str, device: torch.device, n_frames: int, seed: int) -> dict:
    cfg = radial_sensor(sensor)
    n_seq = 4
    sim = RadialSimulator(cfg, n_seq, n_frames, seed, device=device)
    frames = [(q, i) for i in range(n_frames) for q in range(n_seq)][:n_frames]
    scenes = [sim.geometry(q, i)[0] for q, i in frames]
    gens = [sim.noise_generator(q, i) for q, i in frames]
    n_scat = [len(f.scatterers) for f in scenes]
    for _ in range(2):                                     # warm-up
        synthesize_rd(cfg, scenes[0].scatterers, generator=gens[0], device=device)
    ideal = ideal_receiver(cfg)
    synth_t, ideal_t, whole_t, var = [], [], [], []
    for (q, i), f, g in zip(frames, scenes, gens):
        _sync(device)
        t0 = time.perf_counter()
        rd = synthesize_rd(cfg, f.scatterers, generator=g, device=device)
        _sync(device)
        synth_t.append(time.perf_counter() - t0)
        var.append(torch.view_as_real(rd).reshape(-1, 2 * cfg.n_rx).double().var(0).cpu().numpy())
        g0 = sim.noise_generator(q, i)
        _sync(device)
        t0 = time.perf_counter()
        synthesize_rd(ideal, f.scatterers, generator=g0, device=device)
        _sync(device)
        ideal_t.append(time.perf_counter() - t0)
    for q, i in frames:
        t0 = time.perf_counter()
        rd = sim.frame(q, i).rd
        _sync(device)
        whole_t.append(time.perf_counter() - t0)
    synth, whole = float(np.median(synth_t)), float(np.median(whole_t))
    std = np.sqrt(np.mean(var, axis=0))                     # (2 n_rx,) pooled over frames
    return {
        "benchmark": "simulate_radial",
        "sensor": sensor,
        "rd_shape": list(cfg.rd_shape),
        "device": str(device),
        "threads": torch.get_num_threads(),
        "frames": len(frames),
        "scatterers_mean": float(np.mean(n_scat)),
        "synth_ms_per_frame": round(1e3 * synth, 2),          # median over frames
        "synth_frames_per_s": round(1.0 / synth, 2),
        "synth_ms_best": round(1e3 * min(synth_t), 2),        # least disturbed by other processes
        "synth_ideal_ms_per_frame": round(1e3 * float(np.median(ideal_t)), 2),
        "receiver_cost_ratio": round(float(np.median(np.divide(synth_t, ideal_t))), 3),
        "cube_std": {"median": round(float(np.median(std))), "min": round(float(std.min())),
                     "max": round(float(std.max()))},
        "frame_ms_per_frame": round(1e3 * whole, 2),
        "frame_frames_per_s": round(1.0 / whole, 2),
        "frame_ms_best": round(1e3 * min(whole_t), 2),
        "mb_per_frame": round(rd.numel() * rd.element_size() / 1e6, 2),
        "torch": torch.__version__,
        "cpu": cpu_model(),
        "load_average_1min": round(os.getloadavg()[0], 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    ap.add_argument("--frames", type=int, default=20, help="frames timed per case (default 20)")
    ap.add_argument("--sensors", nargs="+", default=["radial", "radial-s"])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    for dev in devices:
        for s in args.sensors:
            print(json.dumps(bench(s, dev, args.frames, args.seed)), flush=True)


if __name__ == "__main__":
    main()
