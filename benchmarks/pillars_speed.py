"""Benchmark: batch-1 inference frames/s of polar PointPillars / SpectralPillars against FFTRadNet.

Simulates ``--frames`` road frames of the chosen sensor (:class:`~radarpc.sim.radial_writer.SimulatedRADIal`),
extracts their spectral point clouds at ``--density`` (5.7 % by default, RADIal's) with
:class:`~radarpc.dsp.SpectralPointCloud` (plain for PointPillars, ``rd3 + sector32`` for
SpectralPillars), and times, batch 1, passes interleaved method by method so that load from other
processes hits them alike:

* ``fftradnet`` (radarpc's model as built), ``fftradnet_fused``
  (:func:`radarpc.models.fast.batchnorm.fuse_for_inference`) and ``fftradnet_fused_cl`` (+ channels-last
  weights): RD cube -> detections and freespace; ``fftradnet_fused_cl_det``: the same with the
  freespace head skipped (detections only, what the detection metrics use);
* for each pillar model, as built, fused (:func:`radarpc.models.fast.batchnorm.fuse_for_inference`) and
  fused with channels-last weights (``_fused_cl``; the scatter's canvas is channels-last already),
  and ``_fused_cl_det`` (detections only): ``<model>`` the network on the ready point cloud (point
  extraction excluded) and ``<model>+points`` RD cube -> point cloud -> network (extraction
  included). The ``_det`` rows are compared with ``fftradnet_fused_cl_det``, the others with each
  full FFTRadNet. The pillar models' freespace head convolves the 128 x 224 map and resizes its
  logits (``freespace_upsample_logits``); ``_fused_cl_fs256`` runs the same weights in the official
  head's order, the features resized to 256 x 224 first (~32 GMAC at full size, most of a pillar
  model's work), as FFTRadNet does;
* where the CPU has native bf16 (:func:`radarpc.machine.cpu_has_native_bf16`), ``fftradnet_bf16``,
  ``fftradnet_bf16_det``, ``<model>_bf16`` and ``<model>_bf16_det``: the fused channels-last
  models under bf16 autocast (the point extraction stays fp32), compared with the FFTRadNet bf16
  path with the same heads;
* with ``--winograd``, ``fftradnet_winograd_det`` and ``<model>_winograd_det``: the ``_fused_cl_det``
  models with their wide 3 x 3 stride-1 layers as Winograd F(4x4, 3x3)
  (:func:`radarpc.models.fast.winograd.winograd_for_inference`; the first pass compiles the transforms),
  compared with ``fftradnet_fourier_winograd_det`` (``fftradnet_winograd_det`` with the pre-encoder,
  stem and first ReLU as :func:`radarpc.models.fast.fourier_stem.fourier_stem_for_inference`),
  ``fftradnet_winograd_det`` and ``fftradnet_fused_cl_det``; and ``fftradnet_fast_det`` and
  ``<model>_fast_det``: :func:`radarpc.models.fast.fast_inference` (detections only; the
  Winograd rows with the detection head collapsed into one correlation, activations fused into the
  convolutions, and FFTRadNet's pre-encoder and stem per Doppler frequency), compared with
  ``fftradnet_fast_det``, ``fftradnet_fourier_winograd_det`` and ``fftradnet_winograd_det``.

Weights are random (the speed does not depend on them). Prints one JSON object: per method the
best and median seconds per frame, frames/s, and the frames/s ratio to each FFTRadNet method; the
points per frame and achieved density; the per-part time of the fused pillar models (pillars,
backbone, detection head, freespace head); threads, CPU and load average. Timings are only
meaningful on a quiet machine.

Sizes (``--size``): ``full`` (RADIal cubes 512 x 256 x 16, ``polar_pointpillars``, ``spectralpillars``,
``fftradnet``), ``s`` (``radial-s`` cubes and the ``_s`` models), ``tiny`` (``radial-s`` cubes,
``pillars_tiny`` and ``fftradnet_tiny``; a quick check that the script runs).

Usage::

    python benchmarks/pillars_speed.py --size full --threads 2 --frames 4 --repeats 5
    python benchmarks/pillars_speed.py --size tiny --frames 2 --repeats 2
"""
from __future__ import annotations

import argparse
import os


def _parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", choices=("full", "s", "tiny"), default="full", help="model and sensor sizes")
    p.add_argument("--threads", type=int, default=2, help="torch / BLAS threads")
    p.add_argument("--frames", type=int, default=4, help="distinct simulated frames")
    p.add_argument("--repeats", type=int, default=5, help="timed passes over the frames (best and median)")
    p.add_argument("--density", type=float, default=0.057, help="point-cloud density (fraction of RD cells)")
    p.add_argument("--seed", type=int, default=0, help="simulator seed")
    p.add_argument("--winograd", action="store_true",
                   help="also time the detection-only models with Winograd 3 x 3 layers (compiles on the first pass)")
    return p.parse_args()


ARGS = _parse() if __name__ == "__main__" else None
if ARGS is not None:  # BLAS threads must be fixed before numpy/torch load their thread pools
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(ARGS.threads)

import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402

import torch  # noqa: E402

from radarpc.dsp import SpectralPointCloud  # noqa: E402
from radarpc.machine import cpu_has_native_bf16, cpu_model  # noqa: E402
from radarpc.models.complexity import time_interleaved  # noqa: E402
from radarpc.models.fftradnet import fftradnet, fftradnet_s, fftradnet_tiny  # noqa: E402
from radarpc.models import pillars  # noqa: E402
from radarpc.models.fast.batchnorm import fuse_for_inference  # noqa: E402
from radarpc.models.fast import fast_inference  # noqa: E402
from radarpc.models.fast.fourier_stem import fourier_stem_for_inference  # noqa: E402
from radarpc.models.fast.winograd import winograd_for_inference  # noqa: E402
from radarpc.sensors.radial import RADIAL, RADIAL_S  # noqa: E402
from radarpc.sim.radial_writer import SimulatedRADIal  # noqa: E402
from radarpc.training.loop import autocast_context  # noqa: E402

SIZES = {   # sensor, FFTRadNet factory, {pillar model: (factory, enrichments of its point clouds)}
    "full": (RADIAL, fftradnet, {"pointpillars": (pillars.polar_pointpillars, ()),
                                     "spectralpillars": (pillars.spectralpillars, ("rd3", "sector32"))}),
    "s": (RADIAL_S, fftradnet_s, {"pointpillars-s": (pillars.polar_pointpillars_s, ()),
                                      "spectralpillars-s": (pillars.spectralpillars_s, ("rd3", "sector32"))}),
    "tiny": (RADIAL_S, fftradnet_tiny, {"pillars-tiny": (pillars.pillars_tiny, ())}),
}


def _detections_only(model: torch.nn.Module) -> torch.nn.Module:
    """``model`` without its freespace head: ``forward`` then returns the detection map alone."""
    model.freespace_head = None
    return model


def _bf16_autocast(model: torch.nn.Module) -> Callable[[object], object]:
    """``model``'s forward under the training loop's bf16 autocast (the point extraction before it
    stays fp32)."""
    def run(x):
        with autocast_context("bf16", torch.device("cpu")):
            return model(x)
    return run


def part_times(model: pillars.PointPillars, cloud, repeats: int) -> dict[str, float]:
    """Best seconds of each part of ``model`` on one cloud."""
    best: dict[str, float] = {}

    def tick(name: str, fn: Callable[[], torch.Tensor]) -> torch.Tensor:
        t0 = time.perf_counter()
        out = fn()
        best[name] = min(best.get(name, float("inf")), time.perf_counter() - t0)
        return out

    for _ in range(repeats + 1):
        canvas = tick("pillars (VFE + scatter)", lambda: model.scatter(*model.vfe(cloud), len(cloud)))
        x = tick("backbone", lambda: model.backbone(canvas))
        tick("detection head", lambda: model.detection_head(x))
        if model.freespace_head is not None:
            tick("freespace head", lambda: model.freespace_head(x))
    return {k: round(v, 4) for k, v in best.items()}


def main(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    sensor, fft_factory, pillar_models = SIZES[args.size]
    sim = SimulatedRADIal(sensor, 1, args.frames, args.seed, split="all")
    cubes = [sim.cube(i)[None] for i in range(args.frames)]                       # (1, Nr, Nd, Nrx) each
    extractors = {enrich: SpectralPointCloud(sensor, sim.calibration, density=args.density, enrich=enrich)
                  for enrich in {e for _, e in pillar_models.values()}}
    with torch.no_grad():
        clouds = {enrich: [spc(c) for c in cubes] for enrich, spc in extractors.items()}

    fftnet = fft_factory().eval()
    methods: dict[str, Callable[[int], object]] = {
        "fftradnet": lambda i: fftnet(cubes[i]),
        "fftradnet_fused": (lambda m: lambda i: m(cubes[i]))(fuse_for_inference(fftnet)),
        "fftradnet_fused_cl": (lambda m: lambda i: m(cubes[i]))(
            fuse_for_inference(fftnet).to(memory_format=torch.channels_last)),
        "fftradnet_fused_cl_det": (lambda m: lambda i: m(cubes[i]))(
            _detections_only(fuse_for_inference(fftnet).to(memory_format=torch.channels_last))),
    }
    bf16 = cpu_has_native_bf16()
    if bf16:
        methods["fftradnet_bf16"] = (lambda m: lambda i: m(cubes[i]))(
            _bf16_autocast(fuse_for_inference(fftnet).to(memory_format=torch.channels_last)))
        methods["fftradnet_bf16_det"] = (lambda m: lambda i: m(cubes[i]))(_bf16_autocast(
            _detections_only(fuse_for_inference(fftnet).to(memory_format=torch.channels_last))))
    if args.winograd:
        methods["fftradnet_winograd_det"] = (lambda m: lambda i: m(cubes[i]))(winograd_for_inference(
            _detections_only(fuse_for_inference(fftnet).to(memory_format=torch.channels_last))))
        methods["fftradnet_fourier_winograd_det"] = (lambda m: lambda i: m(cubes[i]))(winograd_for_inference(
            fourier_stem_for_inference(
                _detections_only(fuse_for_inference(fftnet).to(memory_format=torch.channels_last)))))
        methods["fftradnet_fast_det"] = (lambda m: lambda i: m(cubes[i]))(fast_inference(fftnet, detections_only=True))
    points = {}
    parts = {}
    for name, (factory, enrich) in pillar_models.items():
        model = factory().eval()
        fused = fuse_for_inference(model)
        fused_cl = fuse_for_inference(model).to(memory_format=torch.channels_last)
        fused_cl_det = _detections_only(fuse_for_inference(model).to(memory_format=torch.channels_last))
        spc, cl = extractors[enrich], clouds[enrich]
        variants = [("", model), ("_fused", fused), ("_fused_cl", fused_cl), ("_fused_cl_det", fused_cl_det)]
        if model.freespace_head is not None and model.freespace_head.upsample_logits:
            # the same weights through the official head's order (features resized to 256 rows, then
            # convolved): what the resized logits save, measured in this run
            fused_cl_fs256 = fuse_for_inference(model).to(memory_format=torch.channels_last)
            fused_cl_fs256.freespace_head.upsample_logits = False
            variants.append(("_fused_cl_fs256", fused_cl_fs256))
        if bf16:
            variants += [("_bf16", _bf16_autocast(fused_cl)), ("_bf16_det", _bf16_autocast(fused_cl_det))]
        if args.winograd:
            variants.append(("_winograd_det", winograd_for_inference(fused_cl_det)))
            variants.append(("_fast_det", fast_inference(model, detections_only=True)))
        for suffix, m in variants:
            methods[name + suffix] = (lambda m, cl: lambda i: m(cl[i]))(m, cl)
            methods[name + suffix + "+points"] = (lambda m, spc: lambda i: m(spc(cubes[i])))(m, spc)
        points[name] = {"enrich": list(enrich),
                        "points_per_frame": round(sum(c.num_points for c in cl) / len(cl), 1),
                        "density_achieved": round(float(torch.cat([c.density for c in cl]).mean()), 5)}
        with torch.no_grad():
            parts[name + "_fused"] = part_times(fused, cl[0], args.repeats)

    load_before = os.getloadavg()[0]
    with torch.no_grad():
        # one warm-up pass, then the timed passes, the methods interleaved
        times = {k: list(t.wall_s) for k, t in time_interleaved(methods, args.frames, args.repeats).items()}
    speed = {}
    for name, t in times.items():
        best, med = min(t), statistics.median(t)
        speed[name] = {"s_per_frame": round(best, 4), "s_per_frame_median": round(med, 4),
                       "frames_per_s": round(1 / best, 3)}
    for name, row in speed.items():
        if name.startswith("fftradnet"):
            continue
        if "_bf16" in name:          # against the FFTRadNet path of the same precision and heads
            refs = ("fftradnet_bf16_det",) if "_det" in name else ("fftradnet_bf16",)
        elif "_fast" in name:
            refs = ("fftradnet_fast_det", "fftradnet_fourier_winograd_det", "fftradnet_winograd_det")
        elif "_winograd" in name:
            refs = ("fftradnet_fourier_winograd_det", "fftradnet_winograd_det", "fftradnet_fused_cl_det")
        elif "_det" in name:
            refs = ("fftradnet_fused_cl_det",)
        else:
            refs = ("fftradnet", "fftradnet_fused", "fftradnet_fused_cl")
        for ref in refs:
            row[f"ratio_vs_{ref}"] = round(speed[ref]["s_per_frame"] / row["s_per_frame"], 2)
    n_params = {name: sum(p.numel() for p in f().parameters()) for name, (f, _) in pillar_models.items()}
    n_params["fftradnet"] = sum(p.numel() for p in fftnet.parameters())
    print(json.dumps({
        "size": args.size, "sensor": sensor.name, "rd_shape": list(sensor.rd_shape), "batch": 1,
        "frames": args.frames, "repeats": args.repeats, "density_target": args.density,
        "threads": args.threads, "cpu": cpu_model(), "native_bf16": bf16, "torch": torch.__version__,
        "load_avg_1min": [load_before, os.getloadavg()[0]],
        "parameters": n_params, "point_clouds": points, "speed": speed, "parts_s": parts,
    }, indent=1), flush=True)


if __name__ == "__main__":
    main(ARGS)
