"""Write a simulated dataset in ColoRadar's on-disk layout.

::

    OUT/
      simulation.json                      resolved simulator settings (resume key)
      calib/single_chip/{waveform_cfg,antenna_cfg,heatmap_cfg,coupling_calib}.txt
      calib/cascade/{waveform_cfg,antenna_cfg,heatmap_cfg,coupling_calib}.txt, phase_frequency_calib.txt
      calib/transforms/base_to_{single_chip,cascade,lidar,imu}.txt
      {scene}_run{k}/
        single_chip/adc_samples/data/frame_{i}.bin       int16 [tx, rx, chirps, samples, 2]
        single_chip/adc_samples/timestamps.txt
        cascade/heatmaps/data/heatmap_{i}.bin            float32 [el, az, range, 2]
        cascade/heatmaps/timestamps.txt
        lidar/pointclouds/lidar_pointcloud_{i}.bin       float32 [N, 4] x y z intensity (LiDAR frame)
        lidar/timestamps.txt
        groundtruth/groundtruth_poses.txt                x y z qx qy qz qw (world <- base)
        groundtruth/timestamps.txt

Timestamps are Unix seconds. Radar frames are ~10 Hz (with jitter); LiDAR scans are 10 Hz with a
run-specific phase offset and start one period before the first radar frame and end one after,
so nearest-timestamp pairing is needed; poses are 20 Hz. The cascade heatmap of frame ``i`` is
stamped 13 ms after single-chip frame ``i`` but drawn from the same scatterers (seen from the
cascade's mount), a simplification of the real, independently triggered sensors.

The root is a :class:`radarpc.runs.RunFolder` keyed by ``simulation.json``: it is locked against a
second concurrent writer; every file is written atomically; an interrupted job resumes (existing
files of the right size are kept, temp files of the killed job removed) when called again with
the same settings; a non-empty folder written with other settings is refused unless
``overwrite=True``. Each frame draws its randomness from a generator seeded by
``(seed, scene, run, frame, sensor)``, so resumed output is identical to an uninterrupted one.

Held-out scenes: each run ``{scene}_run{k}`` is its own seeded layout of the scene kind
(:func:`radarpc.sim.indoor.make_scene` with ``(seed, scene, k)``), not another path through one
shared layout, so the run-level splits of :func:`radarpc.data.coloradar.split_runs` (last run of a
kind ``test``, the one before ``val``) test on geometry never seen in training.
"""
from __future__ import annotations

import dataclasses
import json
import os
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from tqdm import tqdm

from radarpc.io import atomic_write
from radarpc.runs import RunFolder, read_json
from radarpc.data.coloradar_format import write_calib
from radarpc.sensors.coloradar import DEFAULT_CALIB, ColoRadarCalib
from radarpc.sim.coloradar_synth import (
    LidarConfig,
    RadarSimConfig,
    cascade_heatmap,
    lidar_scan,
    radar_scatterers,
    sensor_pose,
    synthesize_tdm_adc,
)
from radarpc.sim.indoor import SCENE_KINDS, Scene, make_scene

__all__ = ["RunTimeline", "run_timeline", "run_name", "frame_generator", "write_coloradar", "write_run"]

_EPOCH = 1_614_000_000.0   # Feb 2021, like the dataset


def run_name(scene: str, run: int) -> str:
    """Folder name of run ``run`` of ``scene``: ``{scene}_run{run}`` (ColoRadar's suffix)."""
    return f"{scene}_run{run}"


@dataclass(frozen=True)
class RunTimeline:
    """Timestamps (scene seconds) of one run's sensors."""

    radar: np.ndarray       # (F,) single-chip frames
    cascade: np.ndarray     # (F,) cascade heatmaps
    lidar: np.ndarray       # (F + 2,) LiDAR scans
    poses: np.ndarray       # (P,) ground-truth poses
    epoch: float            # Unix time of scene time 0


def run_timeline(frames: int, duration: float, rng: np.random.Generator, epoch: float = _EPOCH) -> RunTimeline:
    """Radar at ~10 Hz, LiDAR at 10 Hz with a random phase, poses at 20 Hz, covering ``frames``."""
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    t0 = 0.3
    radar = t0 + np.arange(frames) * 0.1 + rng.uniform(-0.003, 0.003, frames)
    cascade = radar + 0.013
    off = float(rng.uniform(0.02, 0.08))
    lidar = t0 - 0.1 + off + np.arange(frames + 2) * 0.1
    end = max(radar[-1], lidar[-1], cascade[-1]) + 0.2
    poses = np.arange(0.0, end, 0.05)
    return RunTimeline(radar, cascade, lidar, poses, epoch)


def frame_generator(seed: int, *key) -> torch.Generator:
    """CPU generator seeded by ``crc32(json([seed, *key]))``; the writer uses
    ``(seed, scene, run, frame, sensor)`` with sensor in ``radar, adc, heatmap, lidar``."""
    g = torch.Generator()
    g.manual_seed(zlib.crc32(json.dumps([int(seed), *key]).encode()) & 0x7FFFFFFF)
    return g


def _write_bin(path: Path, arr: np.ndarray) -> None:
    with atomic_write(path, "wb") as f:
        f.write(np.ascontiguousarray(arr).tobytes())


def _write_lines(path: Path, lines: Sequence[str]) -> None:
    with atomic_write(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def _done(run: RunFolder | None, path: Path, nbytes: int) -> bool:
    # a part of a resumed run is kept when it has its full size: files are written atomically, so
    # a wrong size means a file damaged afterwards (or of another layout), which is redone
    return run is not None and run.done(path, check=lambda p: p.stat().st_size == nbytes)


def write_run(run_dir: str | os.PathLike, scene: Scene, frames: int, *, seed: int, key: tuple,
              calib: ColoRadarCalib = DEFAULT_CALIB, radar: RadarSimConfig = RadarSimConfig(),
              lidar: LidarConfig = LidarConfig(), run: RunFolder | None = None,
              device: torch.device | str | None = None, progress=None) -> tuple[int, int]:
    """Write one run folder (see the module docstring).

    ``run``: the started dataset root ``run_dir`` is in, whose finished files are kept (None
    writes every file). ``progress``: a tqdm bar or None. Returns ``(written, kept)``: radar
    frames and LiDAR scans simulated now, and those kept from an earlier run.
    """
    written = kept = 0
    run_dir = Path(run_dir)
    rng = np.random.default_rng(zlib.crc32(json.dumps([int(seed), *key, "timeline"]).encode()))
    # slow the rig down if the path is too short for the requested number of frames
    need = 0.1 * (frames + 3) + 0.5
    if scene.trajectory.duration < need:
        scene = dataclasses.replace(scene, trajectory=dataclasses.replace(
            scene.trajectory, speed=scene.trajectory.length / need))
    tl = run_timeline(frames, scene.trajectory.duration, rng)
    ep = tl.epoch + 1000.0 * (zlib.crc32(json.dumps(list(key)).encode()) % 10_000)
    # timestamps as written, and the scene times a reader recovers from them (text minus the
    # first pose time): the sensors are simulated at exactly those times
    txt = {k: [f"{ep + t:.6f}" for t in getattr(tl, k)] for k in ("radar", "cascade", "lidar", "poses")}
    t_ref = float(txt["poses"][0])
    times = {k: np.array([float(x) for x in v]) - t_ref for k, v in txt.items()}
    # ground truth and timestamps first (cheap, deterministic)
    poses = [np.concatenate(scene.trajectory.pose(float(t))) for t in times["poses"]]
    _write_lines(run_dir / "groundtruth" / "groundtruth_poses.txt",
                 [" ".join(f"{v:.9f}" for v in p) for p in poses])
    _write_lines(run_dir / "groundtruth" / "timestamps.txt", txt["poses"])
    _write_lines(run_dir / "single_chip" / "adc_samples" / "timestamps.txt", txt["radar"])
    _write_lines(run_dir / "lidar" / "timestamps.txt", txt["lidar"])
    has_cc = calib.cascade is not None and calib.base_to_cascade is not None
    if has_cc:
        _write_lines(run_dir / "cascade" / "heatmaps" / "timestamps.txt", txt["cascade"])
    sc_to_cc = calib.base_to_cascade.inverse() @ calib.base_to_single_chip if has_cc else None
    adc_dir = run_dir / "single_chip" / "adc_samples" / "data"
    hm_dir = run_dir / "cascade" / "heatmaps" / "data"
    for i, t in enumerate(times["radar"]):
        f_adc, f_hm = adc_dir / f"frame_{i}.bin", hm_dir / f"heatmap_{i}.bin"
        need_adc = not _done(run, f_adc, calib.single_chip.adc_nbytes)
        need_hm = has_cc and not _done(run, f_hm, calib.cascade.heatmap_nbytes)
        written, kept = (written + 1, kept) if need_adc or need_hm else (written, kept + 1)
        if need_adc or need_hm:
            dev = torch.device(device) if device is not None else torch.device("cpu")
            gen = _to_device(frame_generator(seed, *key, i, "radar"), dev)
            pose, vel = sensor_pose(scene, float(t), calib.base_to_single_chip)
            scat = radar_scatterers(scene, float(t), pose, vel, cfg=radar, generator=gen, device=dev)
            if need_adc:
                adc = synthesize_tdm_adc(scat, calib.single_chip, cfg=radar,
                                     generator=_to_device(frame_generator(seed, *key, i, "adc"), scat.points.device))
                _write_bin(f_adc, adc.cpu().numpy())
            if need_hm:
                hm = cascade_heatmap(scat.to_frame(sc_to_cc), calib.cascade, cfg=radar,
                                     generator=_to_device(frame_generator(seed, *key, i, "heatmap"), scat.points.device))
                _write_bin(f_hm, hm.cpu().numpy())
        if progress is not None:
            progress.update(1)
    n_l = lidar.beams * lidar.azimuth_steps * 16
    for j, t in enumerate(times["lidar"]):
        f_l = run_dir / "lidar" / "pointclouds" / f"lidar_pointcloud_{j}.bin"
        if _done(run, f_l, n_l):
            kept += 1
        else:
            written += 1
            pose, _ = sensor_pose(scene, float(t), calib.base_to_lidar)
            dev = torch.device(device) if device is not None else torch.device("cpu")
            cloud = lidar_scan(scene, float(t), pose, cfg=lidar,
                               generator=_to_device(frame_generator(seed, *key, j, "lidar"), dev), device=dev)
            _write_bin(f_l, cloud.cpu().numpy().astype(np.float32))
        if progress is not None:
            progress.update(1)
    return written, kept


def _to_device(gen: torch.Generator, device: torch.device) -> torch.Generator:
    if device.type == "cpu":
        return gen
    g = torch.Generator(device=device)
    g.manual_seed(int(gen.initial_seed()))
    return g


def _recorded_runs(manifest: Path) -> list[str]:
    """The run folders an earlier simulation recorded in its ``simulation.json`` (none when the file
    is missing or malformed: then the folder is not a simulation's and nothing more is owned)."""
    stored = read_json(manifest)
    if not isinstance(stored, dict) or not isinstance(stored.get("scenes"), list) \
            or not isinstance(stored.get("runs_per_scene"), int):
        return []
    return [run_name(str(kind), k) for kind in stored["scenes"] for k in range(stored["runs_per_scene"])]


def write_coloradar(out: str | os.PathLike, scenes: Sequence[str], runs_per_scene: int, frames: int,
                    seed: int = 0, *, overwrite: bool = False, lidar_beams: int = 64,
                    lidar_azimuth_steps: int = 1024, calib: ColoRadarCalib = DEFAULT_CALIB,
                    radar: RadarSimConfig = RadarSimConfig(), device: torch.device | str | None = None,
                    progress: bool = True,
                    on_finish: Callable[[int, int], None] | None = None) -> Path:
    """Simulate ``runs_per_scene`` runs of each scene, ``frames`` radar frames each, into ``out``.

    Parameters
    ----------
    out : path-like
        Dataset root (created).
    scenes : sequence of str
        Scene kinds from :data:`radarpc.sim.indoor.SCENE_KINDS`.
    runs_per_scene, frames : int
        Runs per scene (folders ``{scene}_run{k}``) and radar frames per run.
    seed : int
        Master seed; run ``k`` of scene kind ``s`` is ``make_scene(s, seed, k)``: its own layout,
        path and people (held-out layouts under the run-level splits).
    overwrite : bool
        Replace a non-empty folder made with other settings: its ``simulation.json``, ``calib/``
        and the run folders of this simulation are deleted first (other entries stay). A partial
        run with the same settings is resumed either way.
    lidar_beams, lidar_azimuth_steps : int
        LiDAR pattern (OS1-64: 64 x 1024).
    device : torch device, optional
        Where to synthesize (CPU default; CUDA when given).
    progress : bool
        Show a tqdm bar.
    on_finish : callable, optional
        Told ``(written, kept)``: radar frames and LiDAR scans simulated now, and those kept
        from an earlier, interrupted run.

    Returns
    -------
    pathlib.Path
        ``out``.

    Raises
    ------
    radarpc.runs.RunMismatchError
        (a ``FileExistsError``) ``out`` is not empty and was not written with these settings,
        without ``overwrite``.
    radarpc.runs.OutputBusyError
        (a ``FileExistsError``) another process is writing ``out``.
    """
    scenes = list(scenes)
    bad = [s for s in scenes if s not in SCENE_KINDS]
    if not scenes or bad:
        raise ValueError(f"scenes must be a non-empty list from {SCENE_KINDS}, got {scenes}")
    if runs_per_scene < 1 or frames < 1:
        raise ValueError(f"runs_per_scene and frames must be >= 1, got {runs_per_scene}, {frames}")
    if lidar_beams < 1 or lidar_azimuth_steps < 1:
        raise ValueError(f"lidar_beams and lidar_azimuth_steps must be >= 1, got {lidar_beams}, {lidar_azimuth_steps}")
    out = Path(out)
    lidar = LidarConfig(beams=int(lidar_beams), azimuth_steps=int(lidar_azimuth_steps))
    settings = {"format": "coloradar", "generator": "radarpc.sim.coloradar_writer", "version": 3,
                "scenes": scenes, "runs_per_scene": int(runs_per_scene), "frames": int(frames),
                "seed": int(seed), "lidar": dataclasses.asdict(lidar), "radar": dataclasses.asdict(radar),
                "single_chip": calib.single_chip.name,
                "cascade": calib.cascade.name if calib.cascade is not None else None}
    # an overwrite also removes the runs of the simulation it replaces
    owned = sorted({run_name(kind, k) for kind in scenes for k in range(runs_per_scene)}
                   | set(_recorded_runs(out / "simulation.json"))) + ["calib"]
    folder = RunFolder(out, {"simulation.json": settings}, what="dataset root", indent=1, owned=owned)
    total = len(scenes) * runs_per_scene * (2 * frames + 2)
    written = kept = 0
    with folder.start(overwrite=overwrite, write_manifests=False), \
            tqdm(total=total, desc="simulate coloradar", unit="file", disable=not progress) as bar:
        folder.write_manifest("simulation.json", settings)    # on resume too, as a fresh run writes it
        write_calib(out / "calib", calib)
        for kind in scenes:
            for k in range(runs_per_scene):
                scene = make_scene(kind, seed, k)
                w, kp = write_run(out / run_name(kind, k), scene, frames, seed=seed, key=(kind, k), calib=calib,
                                  radar=radar, lidar=lidar, run=folder, device=device, progress=bar)
                written, kept = written + w, kept + kp
    if on_finish is not None:
        on_finish(written, kept)
    return out

