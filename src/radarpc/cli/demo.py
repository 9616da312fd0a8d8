"""``radarpc demo``: both papers' pipelines end to end, a trained detector included, on the embedded
simulator (or on a real RADIal root).

::

    radarpc demo                      # under 10 minutes on 2 CPU cores: writes demo/REPORT.md
    radarpc demo --tiny               # the same steps at toy sizes in well under a minute: demo-tiny/
    radarpc demo --data path/to/RADIal --device cuda

RADIal side: simulate a RADIal-layout dataset (skipped with ``--data``) -> check it -> spectral
point clouds at three densities (one CFAR threshold tau per density, calibrated on the training
split) -> a figure of the test frame with the most labelled vehicles (RD spectrum, CFAR cells,
points) -> train SpectralPillars on the middle density's points and a dense FFTRadNet on the RD
cubes -> score SpectralPillars on each density's points, FFTRadNet on the cubes and the classical
detector (CFAR points, Doppler gating, clustering) on each density's points with RADIal's metrics.
ColoRadar side: simulate ColoRadar-layout runs -> check them -> the OS-CFAR baseline tuned on val
-> Chamfer distance and EMD against the LiDAR on test. Then ``REPORT.md`` explains every step, the
numbers and the figures (:mod:`radarpc.cli.demo_report`).

Every step is the ``radarpc`` command a user would type, printed before it runs, so the demo
doubles as a tour. A step that finished is recorded in ``steps/NAME.json`` (its command, settings,
seconds, CPU seconds and the machine's load); a rerun reuses a finished step whose command is unchanged and whose
earlier steps were all reused, and says so, so that a killed demo resumes where it stopped (the
commands themselves resume their half-done work) and a finished one rewrites the same report.
"""
from __future__ import annotations

import json
import os
import shlex
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

__all__ = ["DemoConfig", "TINY_SIZES", "DemoStep", "DemoPaths", "DemoStepFailed", "figure_frame", "fftradnet_spec",
           "experiment_configs", "run_demo", "add_parser", "STEPS_DIR", "DISPLAY_FLAGS"]

STEPS_DIR = "steps"
"""Folder of the demo output holding one record per finished step."""

DISPLAY_FLAGS = frozenset({"--no-progress", "--quiet"})
"""Options of the steps' commands that change what they print, not what they write: a rerun with or
without them reuses a finished step."""


@dataclass(frozen=True)
class DemoConfig:
    """Sizes of a demo run. The defaults take under 10 minutes on 2 idle CPU cores
    (:data:`TINY_SIZES`: well under a minute)."""

    out: Path = Path("demo")                # the demo's folder (REPORT.md, steps/, data, runs)
    tiny: bool = False                      # toy sizes (TINY_SIZES); the report says so
    data: Path | None = None                # a RADIal root (real or simulated) instead of the simulation
    sensor: str = "radial-s"                # simulated RADIal-like sensor: radial-s (fast) or radial (full size)
    sequences: int = 150                    # simulated RADIal sequences (2/3 train, 1/6 val, 1/6 test)
    frames_per_sequence: int = 4            # frames per sequence
    scenes: str | None = None               # simulated scene presets (None: RADIal's mix of city, countryside, highway)
    seed: int = 0                           # simulator seed
    densities: tuple[float, float, float] = (0.02, 0.057, 0.2)   # point-cloud densities; the middle one trains
    enrich: str = "rd3,sector32"            # SpectralPillars' enrichments (RD neighbourhoods, 32 angle sectors)
    pillars: str = "spectralpillars-s"      # SpectralPillars variant of radarpc.models.MODELS
    fftradnet: str = "fftradnet-s"          # FFTRadNet variant (its input sizes follow the root's sensor)
    # The step budgets hold the demo under 10 minutes on 2 AVX2-only cores in fp32 (README); a GPU
    # or more time buys more with --pillars-steps / --fftradnet-steps.
    pillars_steps: int = 200                # SpectralPillars optimizer steps
    fftradnet_steps: int = 60               # FFTRadNet optimizer steps
    batch_size: int = 4                     # training batch (both models)
    statistics_frames: int = 64             # training frames of FFTRadNet's input normalisation
    num_workers: int = 0                    # data-loading processes of training
    precision: str = "auto"                 # training precision: auto (bf16 where the CPU has it natively), fp32
    fps_frames: int = 20                    # frames timed for the models' frames/s (0: not timed)
    colo_scenes: str = "hallway,outdoor"    # ColoRadar scenes (3 runs each: train, val, test)
    colo_runs_per_scene: int = 3            # runs per scene
    colo_frames: int = 6                    # radar frames per run
    colo_lidar_beams: int = 32              # LiDAR beams (64 for the real sensor's pattern)
    colo_lidar_azimuth_steps: int = 1024    # LiDAR azimuth steps
    quick_tune: bool = False                # OS-CFAR tuned on a 3-setting grid instead of the full search
    max_tune_frames: int = 32               # validation frames of the OS-CFAR tuning
    device: str | None = None               # torch device; None: a GPU when there is one, else the CPU
    progress: bool = True                   # the commands' progress bars

    def __post_init__(self) -> None:
        if len(self.densities) != 3 or not all(0 < a < b for a, b in zip(self.densities, self.densities[1:])):
            raise ValueError(f"densities must be three increasing fractions of RD cells, got {self.densities}")
        for name in ("sequences", "frames_per_sequence", "pillars_steps", "fftradnet_steps", "batch_size",
                     "statistics_frames", "colo_runs_per_scene", "colo_frames", "colo_lidar_beams",
                     "colo_lidar_azimuth_steps", "max_tune_frames"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.data is None and self.sequences < 3:
            raise ValueError(f"sequences must be >= 3 (a train, a val and a test sequence), got {self.sequences}")
        if self.fps_frames < 0 or self.num_workers < 0:
            raise ValueError(f"fps_frames and num_workers must be >= 0, got {self.fps_frames}, {self.num_workers}")

    @classmethod
    def preset(cls, tiny: bool = False, **changes) -> "DemoConfig":
        """The default sizes, or with ``tiny`` those of :data:`TINY_SIZES`; ``changes`` on top."""
        return cls(**{**(TINY_SIZES if tiny else {}), "tiny": tiny, **changes})

    @property
    def middle(self) -> float:
        """The density SpectralPillars trains at."""
        return self.densities[1]


TINY_SIZES: dict = dict(
    sequences=3, frames_per_sequence=3, scenes="city", seed=75,
    pillars="pillars-tiny", fftradnet="fftradnet-tiny", pillars_steps=3, fftradnet_steps=2, batch_size=2,
    statistics_frames=3, precision="fp32", fps_frames=0,
    colo_scenes="hallway", colo_frames=1, colo_lidar_beams=8, colo_lidar_azimuth_steps=256,
    quick_tune=True, max_tune_frames=1,
)
"""What ``--tiny`` changes: 9 city frames of ``radial-s`` (3 sequences: train, val, test; seed 75,
whose test sequence has the most vehicles in its last frame), the tests' tiny models for a few
steps, no frames/s timing, one hallway frame per ColoRadar run and a 3-setting OS-CFAR grid. Its
numbers mean nothing; it shows every step in seconds."""


@dataclass
class DemoStep:
    """One step of the demo: a ``radarpc`` command and what it must leave behind.

    Attributes
    ----------
    name : str
        Shown in the progress lines and the report.
    slug : str
        File name of its record (``steps/{slug}.json``).
    part : str
        ``"radial"`` or ``"coloradar"``: a step is reused only if every earlier step of its part was.
    argv : list of str
        The command, without the leading ``radarpc``.
    why : str
        One sentence for the report: what the step does and why.
    outputs : list of Path
        Files or folders the step must have written.
    figures : list of (Path, str)
        The figures among them, each with the caption the report gives it.
    key : dict
        Settings the command reads from files the demo writes (an experiment config), compared
        with the record's as the command is.
    replaces_stale : bool
        The command refuses an output made with other settings unless ``--overwrite``, which the
        demo passes when the step finished earlier and cannot be reused (other settings, or an
        earlier step ran again): that output is the demo's own and out of date. Without such a
        record the command runs as given, so that a killed run of the same settings resumes.
    """

    name: str
    slug: str
    part: str
    argv: list[str]
    why: str
    outputs: list[Path] = field(default_factory=list)
    figures: list[tuple[Path, str]] = field(default_factory=list)
    key: dict = field(default_factory=dict)
    replaces_stale: bool = False
    record: dict | None = None          # what the step measured, once run or reused
    reused: bool = False

    @property
    def command(self) -> str:
        return "radarpc " + shlex.join(self.argv)


# ---- the frame the figures draw -----------------------------------------------------------------
def _most_labelled(ds) -> tuple[int, int]:
    """``(numSample, vehicles)`` of the frame of ``ds`` with the most labelled vehicles, the first
    in numSample order on a tie."""
    counts = [len(ds.label_tensor(i)) for i in range(len(ds.frame_ids))]
    best = max(range(len(counts)), key=lambda i: (counts[i], -i))       # frame_ids ascend
    return ds.frame_ids[best], counts[best]


def figure_frame(root: str | Path) -> tuple[int, int, str]:
    """The frame the demo draws: the test frame with the most labelled vehicles (the first such in
    numSample order on a tie); of every frame when the root has no test split or no test frame
    has a vehicle.

    Returns ``(numSample, number of labelled vehicles, split chosen from)``.
    """
    from radarpc.data.radial import RADIal

    try:
        test = RADIal(root, split="test")
    except ValueError:                                  # fewer than 3 sequences: no test split
        test = None
    if test is not None:
        frame, n = _most_labelled(test)
        if n > 0:
            return frame, n, "test"
    return (*_most_labelled(RADIal(root, split="all")), "all")


# ---- what the demo writes where -----------------------------------------------------------------
def density_tag(density: float) -> str:
    """``0.057`` -> ``"057"``: thousandths of the RD cells, the stores' and folders' names."""
    return f"{round(1000 * density):03d}"


@dataclass(frozen=True)
class DemoPaths:
    """The demo's outputs under ``cfg.out``."""

    cfg: DemoConfig

    @property
    def out(self) -> Path:
        return Path(self.cfg.out)

    @property
    def radial_root(self) -> Path:
        return Path(self.cfg.data) if self.cfg.data is not None else self.out / "sim_radial"

    def store(self, density: float) -> Path:
        return self.out / "points" / f"pc_{density_tag(density)}.parquet"

    def config(self, model: str) -> Path:
        return self.out / "configs" / f"{model}.yaml"

    def run(self, model: str) -> Path:
        return self.out / "runs" / model

    def classical(self, density: float) -> Path:
        return self.out / "runs" / "classical" / f"pc_{density_tag(density)}"

    def eval_stem(self, density: float | None) -> str:
        """The stem of ``radarpc evaluate``'s files for a run trained in RADIal's easy mode: its own
        data (``density`` None or the middle one), or the store of another density."""
        if density is None or density == self.cfg.middle:
            return "eval_test_easy"
        return f"eval_test_on_{self.store(density).stem}_easy"

    @property
    def colo_root(self) -> Path:
        return self.out / "sim_colo"

    @property
    def oscfar(self) -> Path:
        return self.out / "preds" / "oscfar"

    @property
    def density_figure(self) -> Path:
        return self.out / "f1_density.png"


# ---- the experiment configs the demo trains -----------------------------------------------------
def fftradnet_spec(variant: str, sensor):
    """The :class:`~radarpc.models.ModelSpec` of FFTRadNet ``variant`` reading ``sensor``'s cubes: its
    input sizes set to the sensor's, and the range strides that bring its ``n_range`` bins to the
    128-row detection map.

    Raises
    ------
    ValueError
        The sensor's range bins are not 128, 256 or 512 (the strides halve the range twice at most).
    """
    from radarpc.models import ModelSpec, build_model
    from radarpc.models.heads import DETECTION_SHAPE

    rows = DETECTION_SHAPE[0]
    strides = {rows: (1, 1), 2 * rows: (2, 1), 4 * rows: (2, 2)}.get(sensor.n_range)
    if strides is None:
        raise ValueError(f"sensor {sensor.name!r} has {sensor.n_range} range bins; a dense FFTRadNet reaches its "
                         f"{rows}-row detection map from {rows}, {2 * rows} or {4 * rows} (the radial-s and radial "
                         f"sensors)")
    want = {"n_range": sensor.n_range, "n_doppler": sensor.n_doppler, "n_rx": sensor.n_rx, "n_tx": sensor.n_tx,
            "slot_width": sensor.slot_width, "range_strides": strides}
    base = build_model(variant, device="meta").cfg
    return ModelSpec(variant, {k: list(v) if isinstance(v, tuple) else v for k, v in want.items()
                               if getattr(base, k) != v})


def experiment_configs(cfg: DemoConfig, sensor) -> dict:
    """``{"spectralpillars": ExperimentConfig, "fftradnet": ExperimentConfig}``: the demo's two
    trainings, with the recipe of ``configs/detection/*-easy.yaml`` (cross-entropy, trained and
    scored in RADIal's easy mode, without its ``Difficult`` labels) and the demo's step budget."""
    from radarpc.experiments.radial_detection.config import ExperimentConfig
    from radarpc.models import ModelSpec
    from radarpc.models.losses import LossConfig
    from radarpc.models.pillars import SPECTRAL_FEATURES
    from radarpc.training.loop import TrainConfig

    def train(steps: int) -> TrainConfig:
        return TrainConfig(epochs=0, max_steps=steps, batch_size=cfg.batch_size, eval_batch_size=cfg.batch_size,
                           num_workers=cfg.num_workers, precision=cfg.precision, seed=0,
                           checkpoint_every=max(steps // 4, 1), warmup_fraction=0.3)

    pillars = ModelSpec(cfg.pillars)
    if tuple(pillars.config.features) != SPECTRAL_FEATURES:      # a generic size: SpectralPillars' features
        pillars = pillars.replace(features=list(SPECTRAL_FEATURES))
    common = dict(difficult=False, loss=LossConfig(focal_gamma=0.0))
    return {
        "spectralpillars": ExperimentConfig(name=f"demo-spectralpillars ({cfg.pillars})", model=pillars,
                                            train=train(cfg.pillars_steps), **common),
        "fftradnet": ExperimentConfig(name=f"demo-fftradnet ({cfg.fftradnet})",
                                      model=fftradnet_spec(cfg.fftradnet, sensor),
                                      statistics_frames=cfg.statistics_frames, train=train(cfg.fftradnet_steps),
                                      **common),
    }


# ---- the steps ----------------------------------------------------------------------------------
def _radial_steps(cfg: DemoConfig, paths: DemoPaths, device: str, sensor_name: str) -> list[DemoStep]:
    """The RADIal steps up to the conversions (the rest need the root: :func:`_model_steps`)."""
    root = paths.radial_root
    quiet = [] if cfg.progress else ["--no-progress"]
    steps = []
    if cfg.data is None:
        scenes = ["--scenes", cfg.scenes] if cfg.scenes else []
        n = cfg.sequences * cfg.frames_per_sequence
        steps.append(DemoStep(
            "simulate RADIal", "simulate-radial", "radial",
            ["simulate", "radial", "--out", str(root), "--sensor", sensor_name, "--sequences", str(cfg.sequences),
             "--frames-per-sequence", str(cfg.frames_per_sequence), "--seed", str(cfg.seed), *scenes,
             "--no-camera", "--no-laser", "--device", device, *quiet],
            f"{n} road scenes ({cfg.sequences} sequences of {cfg.frames_per_sequence} frames) seen by the "
            f"`{sensor_name}` radar, written in RADIal's layout: complex range-Doppler (RD) cubes, vehicle labels "
            f"and freespace maps. The simulator stands in for the real dataset, which cannot be downloaded "
            f"everywhere.", outputs=[root / "labels.csv"]))
    steps.append(DemoStep(
        "check RADIal", "check-radial", "radial",
        ["info", str(root), "--check", "--plot", str(paths.out / "radial_info.png")],
        "Reads every file of the root and summarises it (frames, splits, labels), so that a broken file "
        "fails here and not in the middle of a training.",
        outputs=[paths.out / "radial_info.png"],
        figures=[(paths.out / "radial_info.png", "the RADIal root: label ranges and azimuths, vehicle "
                                                 "positions from above, the RD power of one frame")]))
    for d in cfg.densities:
        store = paths.store(d)
        trains = " SpectralPillars trains on these points." if d == cfg.middle else ""
        steps.append(DemoStep(
            f"point clouds at {100 * d:g} %", f"points-{density_tag(d)}", "radial",
            ["pointcloud", str(root), "--density", f"{d:g}", "--density-mode", "per-dataset", "--enrich", cfg.enrich,
             "--out", str(store), "--device", device, *(["--quiet"] if not cfg.progress else [])],
            f"Spectral point clouds keeping {100 * d:g} % of the RD cells: one CFAR threshold tau calibrated on the "
            f"training frames for that density, a point per detected cell with its range, azimuth, elevation, "
            f"Doppler and beam amplitude, enriched with {cfg.enrich} (3 x 3 RD neighbourhoods, 32 angle-sector "
            f"maxima).{trains}", outputs=[store]))
    return steps


def _model_steps(cfg: DemoConfig, paths: DemoPaths, device: str, frame: int, frame_note: str,
                 configs: dict) -> list[DemoStep]:
    """Frame figure, trainings, evaluations and the classical rows."""
    from radarpc.config import to_dict

    root, mid = paths.radial_root, cfg.middle
    quiet = [] if cfg.progress else ["--no-progress"]
    sp, fft = paths.run("spectralpillars"), paths.run("fftradnet")
    frame_png = paths.out / "frame.png"
    fig = f"frame{frame:06d}"
    steps = [DemoStep(
        "frame figure", "frame-figure", "radial",
        ["show", str(root), "--frame", str(frame), "--store", str(paths.store(mid)), "--out", str(frame_png),
         "--device", device],
        f"Draws frame {frame} ({frame_note}): the RD spectrum, the CFAR envelope with its detections, and the "
        f"{100 * mid:g} % points from above with the labelled vehicles.", outputs=[frame_png],
        figures=[(frame_png, f"frame {frame}: (a) the RD spectrum summed over receivers with the cells kept at "
                             f"{100 * mid:g} % in red, (b) the DDMA-consolidated envelope E(r, l) with the CFAR "
                             f"peaks, (c) the points from above, coloured by radial velocity, with the labelled "
                             f"vehicles as RADIal's 4 m x 1.8 m boxes")])]
    for model, run, extra, why in (
            ("spectralpillars", sp, ["--points", str(paths.store(mid))],
             f"SpectralPillars ({configs['spectralpillars'].model.variant}) learns to find vehicles and freespace "
             f"from the {100 * mid:g} % points: the points are gathered into polar pillars, encoded, and a 2-D "
             f"network predicts RADIal's range-azimuth detection map."),
            ("fftradnet", fft, [],
             f"FFTRadNet ({configs['fftradnet'].model.variant}) learns the same task from the whole RD cube (density "
             f"100 %): the dense benchmark the point clouds are measured against.")):
        c = configs[model]
        steps.append(DemoStep(
            f"train {'SpectralPillars' if model == 'spectralpillars' else 'FFTRadNet'}", f"train-{model}", "radial",
            ["train", str(paths.config(model)), "--data", str(root), *extra, "--out", str(run), "--device", device,
             *quiet],
            f"{why} {c.train.max_steps} optimizer steps of {c.train.batch_size} frames; the weights of the best "
            f"validation F1 are kept.", outputs=[run / "best.safetensors"], key={"experiment": to_dict(c)},
            replaces_stale=True))
    timing = ["--fps-frames", str(cfg.fps_frames)]
    for d in cfg.densities:
        stem = paths.eval_stem(d)
        own = d == mid
        shown = ["--show-frames", str(frame)] if own else []
        figs = [(sp / "figures" / f"{stem}_labels.png",
                 f"SpectralPillars on the {100 * d:g} % points: what became of the test labels at each confidence "
                 f"threshold, and the false alarms per frame")]
        if own:
            figs = [(sp / "figures" / f"{stem}_{fig}.png",
                     f"SpectralPillars on frame {frame}: its {100 * d:g} % points from above with the labelled "
                     f"(green) and predicted (red, confidence >= 0.2) boxes, and the predicted vehicle probability "
                     f"over range and azimuth"),
                    (sp / "figures" / "learning_curve.png",
                     "SpectralPillars' training: validation F1 and training loss against training time"), *figs]
        steps.append(DemoStep(
            f"evaluate SpectralPillars at {100 * d:g} %", f"evaluate-spectralpillars-{density_tag(d)}", "radial",
            ["evaluate", str(sp), "--split", "test", *([] if own else ["--points", str(paths.store(d))]), *shown,
             *timing, "--device", device],
            "Scores the trained SpectralPillars on the test frames " + (
                "of the points it trained on." if own else
                f"converted at {100 * d:g} % instead: how the same detector fares with fewer or more points."),
            outputs=[sp / f"{stem}.json"], figures=figs))
    stem = paths.eval_stem(None)
    steps.append(DemoStep(
        "evaluate FFTRadNet", "evaluate-fftradnet", "radial",
        ["evaluate", str(fft), "--split", "test", "--show-frames", str(frame), *timing, "--device", device],
        "Scores the trained FFTRadNet on the test cubes.", outputs=[fft / f"{stem}.json"],
        figures=[(fft / "figures" / f"{stem}_{fig}.png",
                  f"FFTRadNet on frame {frame}: the labelled (green) and predicted (red, confidence >= 0.2) boxes "
                  f"from above (it reads no points), and its predicted vehicle probability"),
                 (fft / "figures" / "learning_curve.png",
                  "FFTRadNet's training: validation F1 and training loss against training time"),
                 (fft / "figures" / f"{stem}_labels.png",
                  "FFTRadNet: what became of the test labels at each confidence threshold")]))
    for d in cfg.densities:
        out = paths.classical(d)
        steps.append(DemoStep(
            f"classical detector at {100 * d:g} %", f"classical-{density_tag(d)}", "radial",
            ["baseline", "detect", str(paths.store(d)), "--data", str(root), "--split", "test", "--no-difficult",
             "--out", str(out)],
            f"The reference without learning, on the {100 * d:g} % points: estimate the ego speed, keep the points "
            f"that move against the ground, cluster them from above, one detection per cluster.",
            outputs=[out / "eval_test_easy.json"],
            figures=[(out / "figures" / "eval_test_easy_labels.png",
                      f"the classical detector on the {100 * d:g} % points: what became of the test labels at each "
                      f"confidence threshold")]))
    return steps


def _coloradar_steps(cfg: DemoConfig, paths: DemoPaths, device: str) -> list[DemoStep]:
    colo, preds = paths.colo_root, paths.oscfar
    quiet = [] if cfg.progress else ["--no-progress"]
    scenes = [s.strip() for s in cfg.colo_scenes.split(",") if s.strip()]
    n = len(scenes) * cfg.colo_runs_per_scene * cfg.colo_frames
    return [
        DemoStep("simulate ColoRadar", "simulate-coloradar", "coloradar",
                 ["simulate", "coloradar", "--out", str(colo), "--scenes", cfg.colo_scenes,
                  "--runs-per-scene", str(cfg.colo_runs_per_scene), "--frames", str(cfg.colo_frames),
                  "--seed", str(cfg.seed), "--lidar-beams", str(cfg.colo_lidar_beams),
                  "--lidar-azimuth-steps", str(cfg.colo_lidar_azimuth_steps), "--device", device, *quiet],
                 f"{n} indoor/outdoor radar frames ({', '.join(scenes)}; {cfg.colo_runs_per_scene} runs per scene: "
                 f"train, val, test) of the handheld ColoRadar rig, each with its radar data cube and a LiDAR scan "
                 f"({cfg.colo_lidar_beams} beams): the ground truth a radar point cloud is measured against.",
                 outputs=[colo / "simulation.json"]),
        DemoStep("check ColoRadar", "check-coloradar", "coloradar",
                 ["info", str(colo), "--plot", str(paths.out / "coloradar_info.png")],
                 "Summarises the ColoRadar root and draws one frame.", outputs=[paths.out / "coloradar_info.png"],
                 figures=[(paths.out / "coloradar_info.png",
                           "the ColoRadar root: one radar frame's intensity and its LiDAR scan")]),
        DemoStep("OS-CFAR baseline", "oscfar", "coloradar",
                 ["baseline", "os-cfar", str(colo), "--split", "test", "--out", str(preds),
                  "--max-tune-frames", str(cfg.max_tune_frames), *(["--quick-tune"] if cfg.quick_tune else [])],
                 "The classical radar point cloud RaLD is compared with: ordered-statistic CFAR on the radar cube, "
                 "its threshold and windows tuned on the validation frames for the smallest Chamfer distance, then "
                 "a cloud for every test frame.", outputs=[preds / "index.json"]),
        DemoStep("Chamfer / EMD", "chamfer-emd", "coloradar",
                 ["evaluate-points", str(preds), "--data", str(colo), "--split", "test", "--figures"],
                 "Scores each OS-CFAR cloud against the LiDAR points inside the radar's field of view.",
                 outputs=[preds / "metrics.json"],
                 figures=[*((preds / "figures" / f"{s}.png",
                             f"a {s} test frame: the radar cube, the LiDAR truth and the OS-CFAR cloud, from above "
                             f"(top) and as range against elevation (bottom)") for s in scenes),
                          *((preds / "figures" / f"cdf_{m}.png",
                             f"the empirical CDF of the per-frame {what} of the OS-CFAR clouds, a panel per scene "
                             f"and one of all test frames (as RaLD's Figs. 6-7)")
                            for m, what in (("chamfer", "Chamfer distance"), ("emd", "EMD"),
                                            ("emd_equal", "equal-size EMD")))]),
    ]


# ---- running a step -----------------------------------------------------------------------------
class DemoStepFailed(Exception):
    """A step's command failed (it printed why) or left an output out; ``code`` is the exit code."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


def _load() -> float | None:
    """The 1-minute load average (None where the system has none)."""
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


def _record_path(paths: DemoPaths, step: DemoStep) -> Path:
    return paths.out / STEPS_DIR / f"{step.slug}.json"


def _without_display(argv: list[str]) -> list[str]:
    return [a for a in argv if a not in DISPLAY_FLAGS]


def _finished_record(paths: DemoPaths, step: DemoStep) -> dict | None:
    """The record of ``step`` when it finished with this command (:data:`DISPLAY_FLAGS` aside) and
    settings and its outputs are there; else None."""
    from radarpc.runs import read_json

    path = _record_path(paths, step)
    if not path.is_file():
        return None
    try:
        rec = read_json(path)
    except ValueError:
        return None
    if not isinstance(rec, dict) or not isinstance(rec.get("argv"), list):
        return None
    if _without_display(rec["argv"]) != _without_display(step.argv) or \
            rec.get("key") != json.loads(json.dumps(step.key)):
        return None
    return rec if all(p.exists() for p in step.outputs) else None


def _execute(step: DemoStep, paths: DemoPaths, number: str, may_reuse: bool,
             say: Callable[[str], None]) -> None:
    """Run ``step`` (or reuse it), check its outputs and write its record."""
    from radarpc.cli import baseline, evaluate, evaluate_points, info, pointcloud, show, simulate, train
    from radarpc.cli.runner import build_parser, run_command
    from radarpc.io import atomic_write

    rec = _finished_record(paths, step) if may_reuse else None
    if rec is not None:
        step.record, step.reused = rec, True
        say(f"\n[{number}] {step.name}: reused, finished earlier in {rec['seconds']:.1f} s "
            f"({_record_path(paths, step)}): {step.command}")
        return
    argv = step.argv
    stale = _record_path(paths, step)
    if step.replaces_stale and stale.is_file():
        argv = [*argv, "--overwrite"]
        stale.unlink()              # a kill from here on leaves a half-done run of these settings: it resumes
    say(f"\n[{number}] {step.name}\n$ radarpc {shlex.join(argv)}")
    load = _load()
    t0, c0 = time.perf_counter(), time.process_time()
    parser = build_parser([simulate, info, pointcloud, show, train, evaluate, baseline, evaluate_points])
    code = run_command(parser, argv)
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    if code != 0:
        raise DemoStepFailed(f"step {step.name!r} failed (exit code {code}): radarpc {shlex.join(argv)}; fix what it "
                             f"says and run the demo again: the finished steps are reused", code)
    missing = [str(p) for p in step.outputs + [f for f, _ in step.figures] if not p.exists()]
    if missing:
        raise DemoStepFailed(f"step {step.name!r} finished but did not write {', '.join(missing)}", 1)
    step.record = {"argv": step.argv, "key": step.key, "seconds": round(seconds, 2), "cpu_seconds": round(cpu, 2),
                   "load_1min": load,
                   "finished_utc": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())}
    path = _record_path(paths, step)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as f:
        json.dump(step.record, f, indent=1)
    say(f"[{number}] {step.name}: done in {seconds:.1f} s ({cpu:.1f} s of CPU"
        + ("" if load is None else f", load {load:.2f} at start") + ")")


def run_demo(cfg: DemoConfig, *, say: Callable[[str], None] | None = None) -> Path:
    """Run (or reuse) every step of the demo into ``cfg.out``; write and return ``REPORT.md``."""
    import torch

    from radarpc.cli.demo_report import write_report
    from radarpc.config import load_yaml_mapping, save_yaml, to_dict
    from radarpc.data.radial import root_sensor
    from radarpc.sensors.radial import radial_sensor

    say = say or (lambda s: print(s, flush=True))
    device = cfg.device or ("cuda" if torch.cuda.is_available() else "cpu")
    paths = DemoPaths(cfg)
    if cfg.data is not None and not (Path(cfg.data) / "labels.csv").is_file():
        raise FileNotFoundError(f"--data {cfg.data}: not a RADIal root (no labels.csv)")
    sensor = root_sensor(cfg.data)[0] if cfg.data is not None else radial_sensor(cfg.sensor)
    configs = experiment_configs(cfg, sensor)          # fails before any work for a sensor FFTRadNet cannot read
    paths.out.mkdir(parents=True, exist_ok=True)
    say(f"radarpc demo{' --tiny' if cfg.tiny else ''} into {paths.out} on {device}: "
        + (f"the RADIal root {cfg.data}" if cfg.data is not None else f"simulated `{sensor.name}` data")
        + " and simulated ColoRadar runs")

    t_all = time.perf_counter()
    steps = _radial_steps(cfg, paths, device, sensor.name)
    # every step, for the [k/N] counter: frame figure, 2 trainings, evaluations, classical rows, ColoRadar
    total = len(steps) + 1 + 2 + len(cfg.densities) + 1 + len(cfg.densities) + 4
    reuse = {"radial": True, "coloradar": True}
    done: list[DemoStep] = []

    def execute(step: DemoStep) -> None:
        _execute(step, paths, f"{len(done) + 1}/{total}", reuse[step.part], say)
        reuse[step.part] = reuse[step.part] and step.reused
        done.append(step)

    for step in steps:
        execute(step)
    frame, n_vehicles, split = figure_frame(paths.radial_root)
    where = "the test frame" if split == "test" else "the frame of any split"
    frame_note = f"{where} with the most labelled vehicles, {n_vehicles}"
    for name, c in configs.items():                 # written when they change: a rerun leaves them as they are
        if not paths.config(name).is_file() or load_yaml_mapping(paths.config(name)) != to_dict(c):
            save_yaml(c, paths.config(name))
    for step in _model_steps(cfg, paths, device, frame, frame_note, configs) + _coloradar_steps(cfg, paths, device):
        execute(step)
    report = write_report(cfg, paths, done, device=device, frame=frame, frame_note=frame_note, configs=configs)
    ran = [s for s in done if not s.reused]
    say(f"\n{len(done) - len(ran)} of {len(done)} steps reused, {len(ran)} run in "
        f"{time.perf_counter() - t_all:.1f} s; the report: {report}")
    return report


def add_parser(sub) -> None:
    import argparse
    import sys

    from radarpc.cli.options import plain_text

    d, t = DemoConfig(), DemoConfig.preset(tiny=True)
    p = sub.add_parser("demo", help="both papers' pipelines end to end on the embedded simulator, a trained "
                                    "detector included (resumable)",
                       description=plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=None, help=f"the demo's folder (default {d.out}, with --tiny demo-tiny)")
    p.add_argument("--tiny", action="store_true",
                   help=f"toy sizes: {t.sequences * t.frames_per_sequence} simulated frames, the tests' tiny models "
                        f"for a few steps, one ColoRadar frame per run (well under a minute; the numbers mean "
                        f"nothing)")
    p.add_argument("--data", default=None, metavar="ROOT",
                   help="run the RADIal part on this RADIal root (real or simulated) instead of simulating one")
    p.add_argument("--sensor", choices=("radial-s", "radial"), default=d.sensor,
                   help=f"simulated RADIal-like sensor (default {d.sensor}; radial = full 512x256x16 cubes, "
                        f"far slower)")
    p.add_argument("--sequences", type=int, default=None,
                   help=f"simulated RADIal sequences (default {d.sequences}, --tiny {t.sequences})")
    p.add_argument("--frames-per-sequence", type=int, default=None,
                   help=f"frames per RADIal sequence (default {d.frames_per_sequence}, --tiny {t.frames_per_sequence})")
    p.add_argument("--colo-frames", type=int, default=None,
                   help=f"radar frames per ColoRadar run (default {d.colo_frames}, --tiny {t.colo_frames}; scenes "
                        f"{d.colo_scenes}, {d.colo_runs_per_scene} runs each)")
    p.add_argument("--seed", type=int, default=None, help=f"simulator seed (default {d.seed}, --tiny {t.seed})")
    p.add_argument("--pillars-steps", type=int, default=None,
                   help=f"SpectralPillars optimizer steps (default {d.pillars_steps}, --tiny {t.pillars_steps})")
    p.add_argument("--fftradnet-steps", type=int, default=None,
                   help=f"FFTRadNet optimizer steps (default {d.fftradnet_steps}, --tiny {t.fftradnet_steps}; in "
                        f"radarpc's longer trainings it found vehicles by about 1,000 steps of 8 frames)")
    p.add_argument("--batch-size", type=int, default=None,
                   help=f"training batch of both models (default {d.batch_size}, --tiny {t.batch_size})")
    p.add_argument("--device", default=None,
                   help="torch device: cpu, cuda, cuda:1, ... (default: a GPU when there is one, else the CPU)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars in the steps")

    def run(a) -> int:
        changes = {k: v for k, v in (("sequences", a.sequences), ("frames_per_sequence", a.frames_per_sequence),
                                     ("colo_frames", a.colo_frames), ("seed", a.seed),
                                     ("pillars_steps", a.pillars_steps), ("fftradnet_steps", a.fftradnet_steps),
                                     ("batch_size", a.batch_size)) if v is not None}
        out = Path(a.out) if a.out is not None else Path("demo-tiny" if a.tiny else "demo")
        cfg = DemoConfig.preset(a.tiny, out=out, sensor=a.sensor, device=a.device, progress=not a.no_progress,
                                data=None if a.data is None else Path(a.data), **changes)
        try:
            run_demo(cfg)
        except DemoStepFailed as e:
            print(f"radarpc demo: {e}", file=sys.stderr)
            return e.code
        return 0

    p.set_defaults(func=run)

