"""Benchmark: radarpc's FFTRadNet against the official model file, outputs and batch-1 CPU speed.

Imports ``FFTRadNet/model/FFTRadNet.py`` from a local clone of valeoai/RADIal (``--radial-repo``;
nothing of it is copied into radarpc), builds the official model with random weights and
non-trivial BN statistics, loads the same weights into radarpc's model through
:func:`radarpc.experiments.radial_detection.official.official_to_radarpc`, and on a random normalised input of the
full RADIal size ``(1, 32, 512, 256)`` prints one JSON object with:

* ``match``: max |ours - official| / max |official| of the detection and freespace maps (fp32,
  requirement: <= 1e-4), for the plain model and for each fast path; the largest difference of
  the classification logits (``max_logit_diff``) and whether it stays below
  ``threshold_logit_margin`` (``decoding_decidable``: otherwise rounding alone may move cells of
  the random map across the 0.05 threshold, as bf16's does); and whether the decoded
  detections (:func:`radarpc.models.targets.decode_detections`, threshold 0.05, NMS 0.05) are the
  same (scores within 1e-4, range and azimuth within 1e-3 m / deg; ``same_beyond_margin`` also
  accepts a difference in cells within 1e-4 of the 0.05 threshold);
* ``bound`` (with ``--peak``): the model's convolution GMAC a frame
  (:func:`radarpc.models.complexity.conv_gmac`), the CPU's best GMAC/s per
  dtype (a 4096^3 matrix product and the model's largest convolution alone), and from them the
  fastest the detection-only network could run and its speedup over the measured official time;
* ``speed``: batch-1 inference seconds/frame (best and median of ``--repeats``, methods
  interleaved pass by pass so load from other processes hits them alike) and frames/s ratios to
  the official model measured in the same run, also in process CPU seconds (``cpu_s``: on a loaded
  machine, with ``--threads 1``, a steadier measure of the work than wall time), for:
  ``official``; ``plain`` (radarpc, as built); ``fused`` (BN folded, pre-encoder as one GEMM:
  :func:`~radarpc.models.fast.batchnorm.fuse_for_inference`); ``fused_cl`` (+ channels-last);
  ``fused_cl_det`` (+ the freespace head skipped: detections only, the decoded detections are
  unchanged); ``bf16`` (autocast, only where the CPU has native bf16: AVX512-BF16 or AMX);
  ``compiled`` (``torch.compile`` of ``fused_cl_det``) and ``compiled_frozen`` (the same with
  Inductor's ``freezing``: weights as constants, prepacked for oneDNN), both with ``--compile``;
  ``bf16_compiled_frozen`` (``compiled_frozen`` under bf16 autocast, with ``--compile`` where
  ``bf16`` runs); ``winograd`` (``fused_cl_det`` with its 3 x 3 stride-1 layers of at least
  ``--winograd-min-channels`` channels as Winograd F(4x4, 3x3):
  :func:`radarpc.models.fast.winograd.winograd_for_inference`; its first pass compiles the transforms);
  ``fourier_winograd`` (``winograd`` with the pre-encoder, stem and first ReLU computed per Doppler
  frequency: :func:`radarpc.models.fast.fourier_stem.fourier_stem_for_inference`); ``fast``
  (:func:`radarpc.models.fast.fast_inference`, detections only: ``fourier_winograd`` with
  the detection head collapsed into one correlation and activations fused into convolutions).

``THP_MEM_ALLOC_ENABLE`` (PyTorch's switch for 2 MB pages on large CPU allocations) is reported:
it changes every path's time, since each pass allocates its large maps afresh.

The random weights put every cell near probability 0.5, so the classification bias is shifted
until ``--detections / 2`` to ``2 --detections`` cells lie above RADIal's 0.05 candidate
threshold, placed in the widest gap between consecutive cells' logits there
(``threshold_logit_margin``: how far the nearest cell is from it), so that rounding-level
differences cannot move a cell across it.

The official model file imports ``torchvision.transforms.transforms.Sequence`` without using it;
when torchvision does not import (absent, or a CUDA wheel on a CPU-only torch) a stand-in module
with that one name is registered (reported as ``torchvision``).

Usage::

    python benchmarks/fftradnet_official.py --radial-repo path/to/RADIal [--repeats 3] [--threads 2] [--compile] [--peak]
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import statistics
import sys
import time
import types
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from radarpc.machine import cpu_has_native_bf16, cpu_model
from radarpc.models.fast.batchnorm import randomise_batchnorm_
from radarpc.models.complexity import conv_gmac, time_interleaved
from radarpc.experiments.radial_detection.official import official_to_radarpc
from radarpc.models.fast.batchnorm import fuse_for_inference
from radarpc.models.fftradnet import fftradnet
from radarpc.models.fast import fast_inference
from radarpc.models.fast.fourier_stem import fourier_stem_for_inference
from radarpc.models.targets import decode_detections
from radarpc.models.fast.winograd import winograd_for_inference
from radarpc.training.loop import autocast_context


def _import_official(repo: Path):
    """The official ``FFTRadNet`` class from the clone, with a stand-in for an absent torchvision."""
    path = repo / "FFTRadNet" / "model" / "FFTRadNet.py"
    if not path.is_file():
        raise SystemExit(f"--radial-repo {repo}: no FFTRadNet/model/FFTRadNet.py (expected a clone of valeoai/RADIal)")
    note = "installed"
    try:
        import torchvision.transforms.transforms  # noqa: F401
    except Exception as e:   # absent, or a CUDA wheel whose C operators do not load on a CPU torch
        for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
            del sys.modules[name]
        note = f"not importable ({type(e).__name__}): stand-in module providing transforms.transforms.Sequence"
        tv, tr, trt = (types.ModuleType(n) for n in
                       ("torchvision", "torchvision.transforms", "torchvision.transforms.transforms"))
        trt.Sequence = Sequence                        # the only name the model file imports
        sys.modules.update({"torchvision": tv, "torchvision.transforms": tr, "torchvision.transforms.transforms": trt})
    spec = importlib.util.spec_from_file_location("radial_official_fftradnet", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.FFTRadNet, note


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.double() - b.double()).abs().max() / b.double().abs().max())


def _logit(det: torch.Tensor) -> torch.Tensor:
    """Classification logits of a detection map (channel 0 holds probabilities)."""
    p = det[:, 0].double().clamp(1e-12, 1 - 1e-12)
    return torch.log(p / (1 - p))


def _compare_detections(det: torch.Tensor, ref: torch.Tensor, tol: float = 1e-4) -> dict:
    """Decoded detections of ``det`` against those of ``ref``: a row matches if its range and
    azimuth are within 1e-3 (m, deg) and its score within ``tol``. ``same``: every row matched both
    ways; ``same_beyond_margin``: every unmatched row scores below ``0.05 + tol`` (a cell within
    rounding of the candidate threshold, which either side may keep). Both after NMS and for the
    candidates before it: random weights give candidates whose scores differ by ~1e-6, so that
    rounding can change NMS's order, which a trained model's separated peaks do not."""
    return {"nms": _compare_rows(decode_detections(det), decode_detections(ref), tol),
            "candidates": _compare_rows(decode_detections(det, nms_iou=None), decode_detections(ref, nms_iou=None), tol)}


def _compare_rows(da, db, tol: float) -> dict:
    a, b = da.rows().double(), db.rows().double()

    def unmatched(x, y):
        if not len(y):
            return x
        close = ((x[:, None, 1:] - y[None, :, 1:]).abs().le(1e-3).all(-1)
                 & (x[:, None, 0] - y[None, :, 0]).abs().le(tol))
        return x[~close.any(1)]

    ua, ub = unmatched(a, b), unmatched(b, a)
    return {"ours": len(a), "official": len(b), "same": not len(ua) and not len(ub),
            "same_beyond_margin": bool((torch.cat([ua[:, 0], ub[:, 0]]) < 0.05 + tol).all())}


def _peak(bf16: bool) -> dict:
    """The fastest arithmetic this CPU gives, per dtype: a 4096^3 ``torch.mm`` and the model's
    largest convolution alone (the backbone's 3 x 3 stem, 192 -> 192 channels on 512 x 256,
    channels-last), in GMAC/s (best of 3 after a warm-up)."""
    dtypes = [torch.float32] + ([torch.bfloat16] if bf16 else [])
    g = torch.Generator().manual_seed(0)
    out = {}
    with torch.inference_mode():
        for dt in dtypes:
            a, b = (torch.randn(4096, 4096, generator=g).to(dt) for _ in range(2))
            stem = torch.nn.Conv2d(192, 192, 3, padding=1).to(dt).eval()
            x = torch.randn(1, 192, 512, 256, generator=g).to(dt).contiguous(memory_format=torch.channels_last)
            for name, f, gmac in (("mm_4096", lambda: torch.mm(a, b), 4096 ** 3 / 1e9),
                                  ("stem_conv", lambda: stem(x), 512 * 256 * 192 * 192 * 9 / 1e9)):
                f()
                ts = []
                for _ in range(3):
                    t = time.perf_counter()
                    f()
                    ts.append(time.perf_counter() - t)
                out.setdefault(str(dt).removeprefix("torch."), {})[name] = round(gmac / min(ts), 1)
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--radial-repo", type=Path, required=True, help="local clone of valeoai/RADIal")
    p.add_argument("--repeats", type=int, default=3, help="timed passes per method (after one warm-up)")
    p.add_argument("--threads", type=int, default=torch.get_num_threads())
    p.add_argument("--compile", action="store_true", help="also time torch.compile (slow to compile)")
    p.add_argument("--only", nargs="+", metavar="METHOD", help="time only these methods (and the official model)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--peak", action="store_true",
                   help="also measure the CPU's peak GMAC/s per dtype and the model's GMAC: the speed bound")
    p.add_argument("--winograd-min-channels", type=int, default=96,
                   help="the winograd path converts 3 x 3 layers with at least this many input and output channels")
    p.add_argument("--winograd-tile-rows", type=int, default=4, help="the winograd path's block height in 4-row tiles")
    p.add_argument("--detections", type=int, default=40, help="about this many cells at or above probability 0.05 (before NMS)")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    Official, tv_note = _import_official(a.radial_repo)

    g = torch.Generator().manual_seed(a.seed)
    torch.manual_seed(a.seed)
    official = Official(mimo_layer=192, channels=[32, 40, 48, 56], blocks=[3, 6, 6, 3]).eval()
    randomise_batchnorm_(official, g)
    x = torch.randn(1, 32, 512, 256, generator=g)                     # a normalised input
    # Random weights put every cell near probability 0.5; shift the classification bias so that
    # about --detections cells reach RADIal's 0.05 candidate threshold, as a trained model's map.
    t = time.perf_counter()
    with torch.inference_mode():
        p0 = official(x)["Detection"][0, 0].double().clamp(1e-12, 1 - 1e-12)
    calib_s = time.perf_counter() - t
    logit = torch.log(p0 / (1 - p0)).flatten()
    top = torch.topk(logit, 2 * a.detections + 1).values
    gaps = top[:-1] - top[1:]                          # gap below the k-th largest logit, k = 1..2n
    k = a.detections // 2 + int(torch.argmax(gaps[a.detections // 2:]))
    q = (top[k] + top[k + 1]) / 2          # the candidate threshold in the widest gap of ranks n/2..2n
    margin = float(gaps[k]) / 2
    with torch.no_grad():
        official.detection_header.clshead.bias -= float(q - torch.log(torch.tensor(0.05 / 0.95)))
    ours = fftradnet().eval()
    missing, unexpected = ours.load_state_dict(official_to_radarpc(official.state_dict()), strict=False)
    assert set(missing) == {"input_mean", "input_std"} and not unexpected, (missing, unexpected)

    fused = fuse_for_inference(ours)
    fused_cl = fuse_for_inference(ours).to(memory_format=torch.channels_last)
    fused_cl_det = fuse_for_inference(ours).to(memory_format=torch.channels_last)
    fused_cl_det.freespace_head = None
    x_cl = x.contiguous(memory_format=torch.channels_last)

    def run_official():
        o = official(x)
        return o["Detection"], o["Segmentation"]

    methods: dict[str, Callable[[], tuple[torch.Tensor, torch.Tensor | None]]] = {
        "official": run_official,
        "plain": lambda: tuple(ours.forward_channels(x)),
        "fused": lambda: tuple(fused.forward_channels(x)),
        "fused_cl": lambda: tuple(fused_cl.forward_channels(x_cl)),
        "fused_cl_det": lambda: tuple(fused_cl_det.forward_channels(x_cl)),
    }
    winograd = winograd_for_inference(fused_cl_det, min_channels=a.winograd_min_channels,
                                      tile_rows=a.winograd_tile_rows)
    methods["winograd"] = lambda: tuple(winograd.forward_channels(x_cl))
    fourier_winograd = winograd_for_inference(fourier_stem_for_inference(fused_cl_det),
                                              min_channels=a.winograd_min_channels, tile_rows=a.winograd_tile_rows)
    methods["fourier_winograd"] = lambda: tuple(fourier_winograd.forward_channels(x_cl))
    fast = fast_inference(ours, detections_only=True, winograd_min_channels=a.winograd_min_channels)
    methods["fast"] = lambda: tuple(fast.forward_channels(x_cl))
    skipped = {}
    if cpu_has_native_bf16():
        def run_bf16():
            with autocast_context("bf16", torch.device("cpu")):
                d, f = fused_cl_det.forward_channels(x_cl)
            return d.float(), f
        methods["bf16"] = run_bf16
    else:
        skipped["bf16"] = "no native bf16 on this CPU (needs AVX512-BF16 or AMX; emulated bf16 is slower than fp32)"
    if a.compile:
        import torch._inductor.config as inductor_config

        compiled = torch.compile(fused_cl_det.forward_channels)
        methods["compiled"] = lambda: tuple(compiled(x_cl))
        frozen_model = fuse_for_inference(ours).to(memory_format=torch.channels_last)
        frozen_model.freespace_head = None
        frozen = torch.compile(frozen_model.forward_channels)   # its own module: compiled anew, frozen

        def run_frozen():
            # freezing: weights become constants, so Inductor prepacks them for oneDNN
            with inductor_config.patch(freezing=True):
                return tuple(frozen(x_cl))
        methods["compiled_frozen"] = run_frozen
        if "bf16" in methods:
            bf16_model = fuse_for_inference(ours).to(memory_format=torch.channels_last)
            bf16_model.freespace_head = None
            bf16_frozen = torch.compile(bf16_model.forward_channels)

            def run_bf16_frozen():
                with inductor_config.patch(freezing=True), autocast_context("bf16", torch.device("cpu")):
                    d, f = bf16_frozen(x_cl)
                return d.float(), f
            methods["bf16_compiled_frozen"] = run_bf16_frozen
    else:
        skipped["compiled"] = "not requested (--compile)"

    if a.only:
        unknown = set(a.only) - set(methods) - {"bf16", "compiled", "compiled_frozen", "bf16_compiled_frozen"}
        if unknown:
            raise SystemExit(f"--only: unknown methods {sorted(unknown)}; choose from {sorted(methods)}")
        methods = {k: f for k, f in methods.items() if k == "official" or k in a.only}
    first, outs = {}, {}
    with torch.inference_mode():
        for k, f in methods.items():                               # warm-up (and compile), outputs kept
            t = time.perf_counter()
            outs[k] = f()
            first[k] = time.perf_counter() - t
        timed = time_interleaved({k: (lambda f: lambda i: f())(f) for k, f in methods.items()}, 1, a.repeats,
                                 warmup=0)
    times = {k: list(t.wall_s) for k, t in timed.items()}
    cpu = {k: list(t.cpu_s) for k, t in timed.items()}
    ref_det, ref_fs = outs["official"]
    match = {}
    for k, (det, fs) in outs.items():
        if k == "official":
            continue
        logit_diff = float((_logit(det) - _logit(ref_det)).abs().max())
        match[k] = {"detection_rel": _rel(det, ref_det),
                    "freespace_rel": None if fs is None else _rel(fs, ref_fs),
                    "max_logit_diff": logit_diff,
                    # beyond the margin a cell may cross the candidate threshold by rounding alone:
                    # then the decoded detections test the random map's flatness, not the path
                    "decoding_decidable": logit_diff < margin,
                    "decoded_detections": _compare_detections(det, ref_det)}
    best = {k: min(times[k]) for k in methods}
    best_cpu = {k: min(cpu[k]) for k in methods}
    speed = {k: {"best_s": round(best[k], 4), "median_s": round(statistics.median(times[k]), 4),
                 "first_s": round(first[k], 3), "fps": round(1 / best[k], 4),
                 "speedup_vs_official": round(best["official"] / best[k], 3),
                 "cpu_s": round(best_cpu[k], 4),
                 "cpu_speedup_vs_official": round(best_cpu["official"] / best_cpu[k], 3)} for k in methods}
    bound = {}
    if a.peak:
        gmac = {"both_heads": conv_gmac(ours, x, forward=ours.forward_channels),
                "detections_only": conv_gmac(fused_cl_det, x_cl, forward=fused_cl_det.forward_channels)}
        peak = _peak("bf16" in methods)
        # at the best GMAC/s measured for a dtype, the detection-only network needs at least this
        floor = {dt: gmac["detections_only"] / max(v.values()) for dt, v in peak.items()}
        bound = {"gmac": {k: round(v, 1) for k, v in gmac.items()}, "peak_gmac_per_s": peak,
                 "floor_s_detections_only": {k: round(v, 3) for k, v in floor.items()},
                 "max_speedup_vs_official": {k: round(best["official"] / v, 2) for k, v in floor.items()}}
    with open("/proc/loadavg") as f:
        load = f.read().split()[:3]
    print(json.dumps({
        "cpu": cpu_model(), "threads": a.threads, "torch": torch.__version__, "loadavg": load,
        "THP_MEM_ALLOC_ENABLE": os.environ.get("THP_MEM_ALLOC_ENABLE"),
        "repeats": a.repeats, "torchvision": tv_note, "official_first_pass_s": round(calib_s, 3),
        "official_decoded_detections": decode_detections(ref_det).num_detections,
        "threshold_logit_margin": round(margin, 6),
        "requirement": {
            **({"plain_within_1e-4": match["plain"]["detection_rel"] <= 1e-4
                and match["plain"]["freespace_rel"] <= 1e-4} if "plain" in match else {}),
            # the speed target: >= 3x the official frames/s, fp32, the same decoded detections
            **({"fast_3x_same_detections": speed["fast"]["speedup_vs_official"] >= 3
                and match["fast"]["decoding_decidable"]
                and match["fast"]["decoded_detections"]["nms"]["same"]} if "fast" in match else {})},
        "match": match, "speed": speed, "bound": bound, "skipped": skipped,
    }, indent=1))


if __name__ == "__main__":
    main()
