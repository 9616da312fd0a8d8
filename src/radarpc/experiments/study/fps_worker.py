"""One row of the FPS study, measured in a process of its own.

:mod:`radarpc.experiments.study.fps` starts ``python -m radarpc.experiments.study.fps_worker JOB
RESULT`` for every row, with the thread count in the environment (``OMP_NUM_THREADS`` and its
kin, read when torch loads): the process loads one model in one mode, the frames it is timed on
and, for the extraction path, the point-cloud module, then :func:`measure` times

* ``network``: the model alone on its stored input (the point store's clouds, the sparse-RD
  root's masked cubes, or the dense cubes), and
* ``pipeline``: the RD cube through the extraction at the row's density and the model
  (:class:`~radarpc.dsp.pointcloud.SpectralPointCloud` then the pillar model, or
  :func:`~radarpc.dsp.sparse_rd.encoded_sparse_rd` then FFTRadNet; none for a dense model),

each at batch 1 under ``torch.inference_mode``: ``warmup`` untimed passes over the first frame,
then ``repeats`` timed sweeps over the frames
(:func:`~radarpc.models.complexity.frames_per_second`), with the memory of the sweeps
(:class:`~radarpc.models.complexity.PeakMemory`: its working memory is what one inference needs
above the resident weights and frames). The result is one JSON object written to ``RESULT``;
a bad input exits with status 2 and one line on stderr.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Callable

import torch

from radarpc.io import DataFileError, atomic_write
from radarpc.machine import check_device, load_average, machine_record
from radarpc.models.complexity import PeakMemory, frames_per_second

__all__ = ["measure", "main", "PATHS"]

PATHS = ("network", "pipeline")
"""What a row times: the network alone on its stored input, and extraction + network from the RD cube."""


def _model(job: dict, device: torch.device) -> torch.nn.Module:
    """The row's model in eval mode on ``device``: fresh weights of the variant, or the run's best."""
    if job["model"]["run"] is not None:
        from radarpc.experiments.radial_detection.evaluation import load_trained

        _, model, _ = load_trained(job["model"]["run"], device)
    else:
        from radarpc.models import build_model

        model = build_model(job["model"]["variant"], job["model"]["overrides"]).to(device).eval()
    if job["timing"]["detections_only"]:
        model.freespace_head = None
    return model


def _timed(run_frame: Callable[[object], object], frames: list, device: torch.device, timing: dict) -> dict:
    """Warm-up (the first pass timed alone), then the timed sweeps inside a memory probe."""
    t0 = time.perf_counter()
    for k in range(timing["warmup"]):
        run_frame(frames[0])
        if k == 0:
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            first = time.perf_counter() - t0
    with PeakMemory(device) as probe:
        rate = frames_per_second(run_frame, frames, device, repeats=timing["repeats"], warmup=0)
    return {"rate": {"median": rate.median, "low": rate.low, "high": rate.high, "repeats": rate.repeats,
                     "sweeps": list(rate.sweeps)},
            "memory": probe.memory.to_dict(), "frames": len(frames),
            "first_pass_s": first if timing["warmup"] else None}


def measure(job: dict) -> dict:
    """Time the row ``job`` describes (see the module docstring); its result as a JSON-able dict.

    ``job`` (written by :mod:`radarpc.experiments.study.fps`): ``model`` (``variant``,
    ``overrides``, ``run``), ``mode`` (``plain`` or ``fast``), ``input`` (``points``,
    ``sparse-rd``, ``dense``), ``root`` (the dataset root of the cubes), ``stored`` (the point store
    or sparse-RD root; None for dense), ``settings`` (the conversion at the row's density), ``tau``
    (the root's calibrated threshold; None per frame), ``timing`` (the study's timing section) and
    ``device``.
    """
    from radarpc.data.radial import RADIal

    timing = job["timing"]
    if timing["threads"] is not None:
        torch.set_num_threads(int(timing["threads"]))
    device = check_device(job["device"], "--device")
    model = _model(job, device)
    parameters = sum(p.numel() for p in model.parameters())
    if job["mode"] == "fast":
        from radarpc.models.fast import fast_inference

        runner = fast_inference(model, detections_only=timing["detections_only"])
    else:
        runner = model
    split, n = timing["split"], timing["frames"]
    reader = RADIal(job["root"], split=split, device=device)
    kind = job["input"]
    extract = None
    if kind == "points":
        from radarpc.data.point_dataset import PointCloudDataset

        stored = PointCloudDataset(job["stored"], job["root"], split)
        nums = list(stored.frame_ids[:n])
        inputs = [stored[k].points.to(device) for k in range(len(nums))]
    elif kind == "sparse-rd":
        stored = RADIal(job["stored"], split=split, device=device)
        nums = list(stored.frame_ids[:n])
        inputs = [stored.cube(stored.index_of(num))[None] for num in nums]        # (1, Nr, Nd, Nrx) each
    else:
        nums = list(reader.frame_ids[:n])
        inputs = [reader.cube(reader.index_of(num))[None] for num in nums]
    if not nums:
        raise ValueError(f"{job['stored'] or job['root']}: no frame of the {split!r} split to time (timing.split)")
    cubes = [reader.cube(reader.index_of(num))[None] for num in nums] if kind != "dense" else inputs
    if kind != "dense":
        from radarpc.pipelines.pointclouds import ConvertSettings, build_point_cloud

        spc = build_point_cloud(reader, ConvertSettings.from_dict(job["settings"]), job["tau"], device)
        if kind == "points":
            extract = spc
        else:
            from radarpc.dsp.sparse_rd import encoded_sparse_rd

            def extract(cube):
                return encoded_sparse_rd(spc, cube)[0]

    out = {"parameters": parameters, "frames": nums, "paths": {}}
    with torch.inference_mode():
        if kind == "points":
            out["points_per_frame"] = sum(c.num_points for c in inputs) / len(inputs)
            out["pipeline_points_per_frame"] = sum(extract(c).num_points for c in cubes) / len(cubes)
        elif kind == "sparse-rd":
            out["cells_per_frame"] = sum(int((c[0].abs().sum(-1) > 0).sum()) for c in inputs) / len(inputs)
            out["pipeline_cells_per_frame"] = sum(int((extract(c)[0].abs().sum(-1) > 0).sum())
                                                  for c in cubes) / len(cubes)
        load_start = load_average()
        t0 = time.perf_counter()
        out["paths"]["network"] = _timed(runner, inputs, device, timing)
        if extract is not None:
            out["paths"]["pipeline"] = _timed(lambda cube: runner(extract(cube)), cubes, device, timing)
        out["seconds"] = time.perf_counter() - t0
        out["load_average"] = {"start": load_start, "end": load_average()}
    out["machine"] = machine_record()
    out["device"] = str(device)
    out["device_name"] = torch.cuda.get_device_name(device) if device.type == "cuda" else None
    out["threads"] = torch.get_num_threads()
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m radarpc.experiments.study.fps_worker JOB RESULT``: measure the row of the JSON
    file ``JOB`` and write its result to ``RESULT``; exit status 2 with one line on a bad input."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print("usage: python -m radarpc.experiments.study.fps_worker JOB.json RESULT.json", file=sys.stderr)
        return 2
    job = json.loads(Path(args[0]).read_text(encoding="utf-8"))
    try:
        result = measure(job)
    except (ValueError, DataFileError, FileNotFoundError) as e:
        print(f"{type(e).__name__}: {e}", file=sys.stderr)
        return 2
    with atomic_write(Path(args[1]), "w") as f:
        json.dump(result, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
