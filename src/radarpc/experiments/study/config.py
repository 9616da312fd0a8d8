"""The study configs: a density sweep and the ablations, strictly loaded from YAML.

A study names its data (existing RADIal roots, or seeded simulations that one command brings
back), the sensor, the densities, its models (each a detection experiment config of
:mod:`radarpc.experiments.radial_detection`, with model overrides and the point-store
enrichments it reads), the seeds, the training budget of every run and the evaluation::

    name: density-sweep
    sensor: radial
    data:
      simulate:                         # or roots: [path, ...]
        - {sequences: 2000, frames_per_sequence: 1, seed: 0}
    densities: [0.007, 0.016, 0.057, 0.19, 0.564]
    models:
      - name: pointpillars-s
        experiment: ../detection/pointpillars-s-radial-easy.yaml     # relative to this file
      - name: spectralpillars-s
        experiment: ../detection/spectralpillars-s-radial-easy.yaml
        enrich: [rd3, sector32]
    seeds: 2
    budget: {epochs: 6, time_limit_min: 20}

An ``experiment`` is the path of a detection experiment YAML (relative to the study file) or the
experiment itself as a mapping. Unknown keys, values of the wrong type and bad values are
refused with the file and the field named, as every radarpc config.

What a config means as runs is :mod:`radarpc.experiments.study.grid`'s.

The FPS study (:class:`FPSConfig`, the paper's Table 2) names models by registry variant and
overrides (or a training run folder, whose weights it loads), each with its input: points,
sparse RD at each density, or dense RD cubes; and how they are timed::

    name: fps
    sensor: radial
    data:
      simulate: [{sequences: 3, frames_per_sequence: 8, seed: 0}]
    densities: [0.007, 0.016, 0.057, 0.19, 0.564]
    models:
      - {name: fftradnet, variant: fftradnet, input: dense}
      - {name: sparse-rd-fftradnet, variant: fftradnet, input: sparse-rd}
      - {name: spectralpillars, variant: spectralpillars, enrich: [rd3, sector32]}
      - {name: spectralpillars-s-on-radial-s, variant: spectralpillars-s, sensor: radial-s, enrich: [rd3, sector32]}
    timing: {frames: 8, repeats: 5, warmup: 2, threads: 2, modes: [plain, fast]}

What it measures is :mod:`radarpc.experiments.study.fps`'s.
"""
from __future__ import annotations

import dataclasses
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from radarpc.config import from_dict, load_yaml_mapping, to_dict
from radarpc.dsp.density import check_density
from radarpc.experiments.radial_detection.config import (ExperimentConfig, experiment_from_dict, load_experiment,
                                                         with_train)
from radarpc.io import DataFileError
from radarpc.models import ModelSpec
from radarpc.pipelines.pointclouds import ConvertSettings
from radarpc.sensors.radial import DDMARadarConfig, radial_sensor

__all__ = ["SimulateSpec", "DataSpec", "ConversionSpec", "Budget", "EvaluationSpec", "ModelEntry",
           "DensitySweepConfig", "AxesSection", "EnrichmentSection", "RDComparisonSection", "AblationConfig",
           "AXIS_ARMS", "AXIS_FEATURES", "ENRICHMENT_ARMS", "TimingSpec", "FPSModel", "FPSConfig", "FPS_INPUTS",
           "FPS_MODES", "STUDY_KINDS", "TRAINING_KINDS", "load_density_sweep", "load_ablation", "load_fps", "load_study"]

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]{0,63}")


def _check_name(name: str, what: str) -> None:
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ValueError(f"{what} {name!r} must be 1-64 letters, digits, '.', '_', '+' or '-' (it names folders), "
                         f"starting with a letter or digit")


def _positive_int(value: Any, what: str, low: int = 1) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ValueError(f"{what} must be an integer >= {low}, got {value!r}")


@dataclass(frozen=True)
class SimulateSpec:
    """One simulated RADIal root (``radarpc simulate radial``, no camera or laser): deterministic
    in its fields and the study's sensor, so a fresh machine makes the same frames again."""

    sequences: int                          # sequences; the last is test, the one before val
    frames_per_sequence: int
    seed: int = 0                           # simulator seed
    scenes: str | None = None               # scene presets, e.g. "city" or "city,highway"; None: all three

    def __post_init__(self) -> None:
        _positive_int(self.sequences, "simulate.sequences", 3)        # a train, a val and a test sequence
        _positive_int(self.frames_per_sequence, "simulate.frames_per_sequence")
        _positive_int(self.seed, "simulate.seed", 0)
        if self.scenes is not None:
            from radarpc.sim.scenes import scene_mix

            scene_mix(self.scenes)                                     # an unknown preset fails here

    @property
    def frames(self) -> int:
        return self.sequences * self.frames_per_sequence


@dataclass(frozen=True)
class DataSpec:
    """The study's data: RADIal-layout roots on this machine, or simulations (exactly one of the two).
    Several roots train together (the frames of each split of every root).

    ``drop_cubes`` (simulations only) deletes a simulated root's RD cubes once every point store
    and sparse-RD root the study's remaining runs need has been made from it (and no dense run is
    left to train on them): the pillar models read only the stores, labels and freespace, and the
    roots are made one after another, so the disk holds the cubes of one root at a time (a
    full-size ``radial`` cube is 16.8 MB). A later input that needs them simulates them again,
    frame for frame the same."""

    roots: tuple[str, ...] = ()
    simulate: tuple[SimulateSpec, ...] = ()
    drop_cubes: bool = False

    def __post_init__(self) -> None:
        if bool(self.roots) == bool(self.simulate):
            raise ValueError("data: give exactly one of roots (RADIal-layout folders) and simulate (a list of "
                             f"simulations), got {'both' if self.roots else 'neither'}")
        if self.drop_cubes and self.roots:
            raise ValueError("data.drop_cubes deletes the cubes of simulated roots, which can be made again; "
                             "it does not apply to data.roots")
        names = [Path(r).name for r in self.roots]
        if len(set(names)) != len(names):
            raise ValueError(f"data.roots: folder names must differ (they identify the data in the result rows, "
                             f"across machines), got {names}")
        seeds = [s.seed for s in self.simulate]
        if len(set(seeds)) != len(seeds):
            raise ValueError(f"data.simulate: each simulation needs its own seed, got seeds {seeds}")


@dataclass(frozen=True)
class ConversionSpec:
    """How every root becomes points (or a sparse-RD root) at a target density: the settings of
    :class:`~radarpc.pipelines.pointclouds.ConvertSettings` but the density and the enrichments,
    which the grid sets per run. ``per-dataset`` (default) calibrates one CFAR threshold tau per
    root on its training split, as the seed's fixed thresholds; ``per-frame`` picks one per frame."""

    density_mode: str = "per-dataset"
    window: tuple[int, int] = (9, 9)         # CA-CFAR window, full odd sizes (the seed's 9 x 9)
    guard: tuple[int, int] = (3, 3)          # CA-CFAR guard (the seed's 3 x 3)
    envelope: str = "replicas"               # the seed's eq. 1
    calibration_frames: int | None = None    # training frames tau is calibrated on (None: all)
    beamforming: str = "auto"                # how directions are found (the same points whichever)
    batch_size: int = 8                      # frames per forward pass (speed only)

    def __post_init__(self) -> None:
        self.settings(0.05, ())                                         # validates every field once
        _positive_int(self.batch_size, "conversion.batch_size")

    def settings(self, density: float, enrich: tuple[str, ...]) -> ConvertSettings:
        """The conversion of every frame of a root at ``density`` with ``enrich``."""
        return ConvertSettings(density=density, density_mode=self.density_mode, enrich=tuple(enrich),
                               window=tuple(self.window), guard=tuple(self.guard), envelope=self.envelope,
                               split="all", calibration_frames=self.calibration_frames,
                               beamforming=self.beamforming)


@dataclass(frozen=True)
class Budget:
    """What one training run may take: its length (``epochs`` or ``max_steps``, replacing the
    experiment's; neither keeps the experiment's own) and ``time_limit_min``, minutes of wall time
    after which a run is stopped and scored with its best weights so far (its result row says it
    was cut, and where: then its result depends on the machine's speed)."""

    epochs: int | None = None
    max_steps: int | None = None
    time_limit_min: float | None = None

    def __post_init__(self) -> None:
        if self.epochs is not None and self.max_steps is not None:
            raise ValueError(f"budget: give epochs or max_steps, not both (got {self.epochs} and {self.max_steps})")
        if self.epochs is not None:
            _positive_int(self.epochs, "budget.epochs")
        if self.max_steps is not None:
            _positive_int(self.max_steps, "budget.max_steps")
        if self.time_limit_min is not None and not self.time_limit_min > 0:
            raise ValueError(f"budget.time_limit_min must be > 0 minutes, got {self.time_limit_min}")

    def apply(self, cfg: ExperimentConfig) -> ExperimentConfig:
        """``cfg`` with the budget's run length."""
        if self.epochs is not None:
            return with_train(cfg, epochs=self.epochs, max_steps=0)
        if self.max_steps is not None:
            return with_train(cfg, epochs=0, max_steps=self.max_steps)
        return cfg


@dataclass(frozen=True)
class EvaluationSpec:
    """How each finished run is scored: its best-validation weights on ``split``, RADIal's metrics
    at IoU 0.5 (the study's number: F1 at confidence 0.2), easy mode or every label as the run's
    experiment trained. ``fps_frames`` and ``batch_size`` change the speed, not the scores."""

    split: str = "test"
    fps_frames: int = 20                     # frames timed at batch 1 (frames/s in the result row); 0: not timed
    batch_size: int = 4

    def __post_init__(self) -> None:
        if self.split not in ("train", "val", "test", "all"):
            raise ValueError(f"evaluation.split must be one of train, val, test, all; got {self.split!r}")
        _positive_int(self.fps_frames, "evaluation.fps_frames", 0)
        _positive_int(self.batch_size, "evaluation.batch_size")


@dataclass(frozen=True)
class ModelEntry:
    """A model of the study: a detection experiment, model overrides on top of its own, and the
    enrichments of the point stores it reads (a pillar model) or of the set its sparse-RD cubes
    keep (an FFTRadNet at a density: ``rdN`` masks ``S*(tau)``)."""

    experiment: ExperimentConfig
    name: str = ""                           # folder and legend name; default the model variant
    overrides: dict = field(default_factory=dict)
    enrich: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.experiment, ExperimentConfig):
            raise ValueError(f"experiment must be a detection experiment config, got {type(self.experiment).__name__}")
        if not isinstance(self.overrides, dict):
            raise ValueError(f"overrides must be a mapping of model config fields, got {type(self.overrides).__name__}")
        object.__setattr__(self, "name", self.name or self.experiment.model.variant)
        _check_name(self.name, "model name")
        object.__setattr__(self, "enrich", ConvertSettings(density=0.05, enrich=tuple(self.enrich)).enrich)
        self.resolved()                                                  # the overrides must build

    __hash__ = None          # holds dicts

    def resolved(self) -> ExperimentConfig:
        """The experiment with the overrides applied to its model."""
        if not self.overrides:
            return self.experiment
        return dataclasses.replace(self.experiment, model=self.experiment.model.replace(**self.overrides))

    @property
    def input_kind(self) -> str:
        return self.experiment.model.input_kind


def _check_sensor(sensor: str) -> DDMARadarConfig:
    return radial_sensor(sensor)


def _check_densities(densities: tuple[float, ...], sensor: DDMARadarConfig) -> tuple[float, ...]:
    if not densities:
        raise ValueError("densities: give at least one target density")
    for d in densities:
        check_density(d, sensor)
    if len(set(densities)) != len(densities):
        raise ValueError(f"densities: each density once, got {list(densities)}")
    return tuple(sorted(densities))


def _check_fits(entry: ModelEntry, sensor: DDMARadarConfig, where: str) -> None:
    """An RD model must read the sensor's cubes (a mismatch fails here, not after hours of conversion)."""
    if entry.input_kind != "rd":
        return
    c = entry.resolved().model.config
    if (c.n_range, c.n_doppler, c.n_rx) != sensor.rd_shape:
        raise ValueError(f"{where}: model {entry.resolved().model.variant!r} reads ({c.n_range}, {c.n_doppler}, "
                         f"{c.n_rx}) cubes, sensor {sensor.name!r} makes {sensor.rd_shape}; pick the variant of "
                         f"this sensor (fftradnet-s for radial-s)")


def _check_unique(names: list[str], what: str) -> None:
    seen = set()
    for n in names:
        if n in seen:
            raise ValueError(f"{what}: the name {n!r} is given twice (names name the run folders)")
        seen.add(n)


@dataclass(frozen=True)
class _Common:
    """Fields every study shares."""

    name: str
    sensor: str
    data: DataSpec
    densities: tuple[float, ...]
    seeds: int = 1                           # runs per model and density: train.seed 0 .. seeds - 1
    budget: Budget = field(default_factory=Budget)
    conversion: ConversionSpec = field(default_factory=ConversionSpec)
    evaluation: EvaluationSpec = field(default_factory=EvaluationSpec)

    def _check_common(self) -> DDMARadarConfig:
        _check_name(self.name, "study name")
        sensor = _check_sensor(self.sensor)
        object.__setattr__(self, "densities", _check_densities(tuple(self.densities), sensor))
        _positive_int(self.seeds, "seeds")
        return sensor


@dataclass(frozen=True)
class DensitySweepConfig(_Common):
    """The density sweep (seed Figs. 5-7, Table 2): every model at every density, ``seeds`` runs
    each, and the optional dense ``reference`` (an FFTRadNet on the full cubes), density-free.

    A pillar model reads the point stores of its enrichments at each density; an FFTRadNet in
    ``models`` reads sparse-RD roots (the cubes masked to the detected set) at each density."""

    models: tuple[ModelEntry, ...] = ()
    reference: ModelEntry | None = None

    def __post_init__(self) -> None:
        sensor = self._check_common()
        if not self.models:
            raise ValueError("models: give at least one model to sweep")
        for k, m in enumerate(self.models):
            _check_fits(m, sensor, f"models[{k}] ({m.name})")
        if self.reference is not None:
            if self.reference.input_kind != "rd":
                raise ValueError(f"reference: the dense reference reads RD cubes; {self.reference.name!r} reads "
                                 f"{self.reference.input_kind}")
            if self.reference.enrich:
                raise ValueError(f"reference: the dense reference reads whole cubes; drop enrich "
                                 f"{list(self.reference.enrich)}")
            _check_fits(self.reference, sensor, "reference")
        _check_unique([m.name for m in self.models] + ([self.reference.name] if self.reference else []),
                      "models and reference")

    __hash__ = None


AXIS_FEATURES: dict[str, tuple[str, ...]] = {
    "base": ("r", "a", "e"),
    "+Ae": ("r", "a", "e", "Ae"),
    "+d": ("r", "a", "e", "d"),
    "+Ae+d": ("r", "a", "e", "d", "Ae"),
    "+v": ("r", "a", "e", "v"),
}
"""The point axes of each arm of the axis ablation (seed Fig. 5): the spatial coordinates
``[r, a, e]``, plus the angle-spectrum amplitude ``Ae``, the consolidated Doppler index ``d``, or
both; and, beyond the seed, ``+v``: the resolved radial velocity in place of ``d`` (the index
wraps every DDMA slot; ``v`` does not). Every arm keeps PointPillars' pillar decoration
(``pillar_offset``), which is not a point axis."""
AXIS_ARMS = ("base", "+Ae", "+d", "+Ae+d")
"""The seed's four arms, the default."""
ENRICHMENT_ARMS = ("none", "rd", "sector", "both")
"""The enrichment ablation's arms (seed Fig. 6): none, the RD neighbourhood (``rdN``, more points),
the angle-sector descriptor (``sectorA``, more features per point), both (SpectralPillars)."""
_AXIS_FOLDER = {"base": "base", "+Ae": "Ae", "+d": "d", "+Ae+d": "Ae-d", "+v": "v"}


@dataclass(frozen=True)
class AxesSection:
    """The axis ablation: ``model`` (a pillar model on plain points) with each arm's point axes."""

    model: ModelEntry
    arms: tuple[str, ...] = AXIS_ARMS

    def __post_init__(self) -> None:
        bad = [a for a in self.arms if a not in AXIS_FEATURES]
        if bad or not self.arms or len(set(self.arms)) != len(self.arms):
            raise ValueError(f"axes.arms: each once, from {list(AXIS_FEATURES)}; got {list(self.arms)}")
        if self.model.input_kind != "points":
            raise ValueError(f"axes.model: the axis ablation needs a pillar model, {self.model.name!r} reads "
                             f"{self.model.input_kind}")
        if self.model.enrich:
            raise ValueError(f"axes.model: the axis ablation runs on plain points; drop enrich {list(self.model.enrich)}")

    __hash__ = None

    def entries(self) -> list[tuple[str, str, ModelEntry]]:
        """``(arm, label, entry)`` of every arm: the model with the arm's features."""
        out = []
        for arm in self.arms:
            features = AXIS_FEATURES[arm] + ("pillar_offset",)
            entry = dataclasses.replace(self.model, name=f"axes-{_AXIS_FOLDER[arm]}",
                                        overrides={**self.model.overrides, "features": list(features)})
            out.append((arm, "[" + ", ".join(AXIS_FEATURES[arm]) + "]", entry))
        return out


@dataclass(frozen=True)
class EnrichmentSection:
    """The enrichment ablation: ``model`` (a pillar model) on stores with no enrichment, the RD
    neighbourhood ``rd``, the angle-sector descriptor ``sector`` (read as the ``sector`` feature),
    or both."""

    model: ModelEntry
    arms: tuple[str, ...] = ENRICHMENT_ARMS
    rd: str = "rd3"                          # the RD neighbourhood (the seed's 3 x 3)
    sector: str = "sector32"                 # the angle-sector descriptor (the seed's 32 azimuth sectors)

    def __post_init__(self) -> None:
        bad = [a for a in self.arms if a not in ENRICHMENT_ARMS]
        if bad or not self.arms or len(set(self.arms)) != len(self.arms):
            raise ValueError(f"enrichments.arms: each once, from {list(ENRICHMENT_ARMS)}; got {list(self.arms)}")
        if self.model.input_kind != "points":
            raise ValueError(f"enrichments.model: needs a pillar model, {self.model.name!r} reads {self.model.input_kind}")
        if self.model.enrich:
            raise ValueError(f"enrichments.model: the arms set the enrichments; drop enrich {list(self.model.enrich)}")
        if ConvertSettings(density=0.05, enrich=(self.rd,)).point_cloud_config().neighbourhood is None:
            raise ValueError(f"enrichments.rd must name an RD neighbourhood (rdN, e.g. rd3), got {self.rd!r}")
        if ConvertSettings(density=0.05, enrich=(self.sector,)).point_cloud_config().sectors is None:
            raise ValueError(f"enrichments.sector must name an angle-sector descriptor (sectorA or sectorAxE, e.g. "
                             f"sector32), got {self.sector!r}")
        features = self.model.resolved().model.config.features
        if "sector" in features:
            raise ValueError(f"enrichments.model: its features {list(features)} already read 'sector'; the arms "
                             f"add it (give the model without it, e.g. pointpillars-s)")

    __hash__ = None

    def entries(self) -> list[tuple[str, str, ModelEntry]]:
        """``(arm, label, entry)`` of every arm: the store's enrichments and the model's features."""
        from radarpc.dsp.pointcloud import SpectralPointCloudConfig

        sa, se = SpectralPointCloudConfig(tau=1.0, enrich=(self.sector,)).sectors
        base = self.model.resolved().model.config.features
        with_sector = tuple(base) + ("sector",)
        out = []
        for arm in self.arms:
            enrich = {"none": (), "rd": (self.rd,), "sector": (self.sector,), "both": (self.rd, self.sector)}[arm]
            overrides = dict(self.model.overrides)
            if arm in ("sector", "both"):
                overrides.update(features=list(with_sector), n_sector=sa * se)
            label = {"none": "no enrichment", "rd": self.rd, "sector": self.sector,
                     "both": f"{self.rd} + {self.sector} (SpectralPillars)"}[arm]
            name = "enrich-" + ("-".join(enrich) if enrich else "none")
            out.append((arm, label, dataclasses.replace(self.model, name=name, overrides=overrides, enrich=enrich)))
        return out


@dataclass(frozen=True)
class RDComparisonSection:
    """Spectral points against sparse RD at equal density (seed Fig. 7): ``points`` (SpectralPillars,
    its stores' enrichments in its ``enrich``) and ``sparse_rd`` (an FFTRadNet on the cubes masked to
    the detected set) at each density, and the optional ``dense`` FFTRadNet benchmark."""

    points: ModelEntry
    sparse_rd: ModelEntry
    dense: ModelEntry | None = None

    def __post_init__(self) -> None:
        if self.points.input_kind != "points":
            raise ValueError(f"rd_comparison.points: needs a pillar model, {self.points.name!r} reads "
                             f"{self.points.input_kind}")
        for what, m in (("sparse_rd", self.sparse_rd), ("dense", self.dense)):
            if m is not None and m.input_kind != "rd":
                raise ValueError(f"rd_comparison.{what}: needs an FFTRadNet (RD cubes), {m.name!r} reads {m.input_kind}")
        if self.dense is not None and self.dense.enrich:
            raise ValueError(f"rd_comparison.dense: the dense benchmark reads whole cubes; drop enrich "
                             f"{list(self.dense.enrich)}")

    __hash__ = None


@dataclass(frozen=True)
class AblationConfig(_Common):
    """The ablations (seed Figs. 5-7): point axes, enrichments, and points against sparse RD, each
    section optional (at least one), at every density with ``seeds`` runs."""

    axes: AxesSection | None = None
    enrichments: EnrichmentSection | None = None
    rd_comparison: RDComparisonSection | None = None

    def __post_init__(self) -> None:
        sensor = self._check_common()
        if self.axes is None and self.enrichments is None and self.rd_comparison is None:
            raise ValueError("an ablation needs at least one of axes, enrichments and rd_comparison")
        names = []
        if self.axes is not None:
            names += [e.name for _, _, e in self.axes.entries()]
        if self.enrichments is not None:
            names += [e.name for _, _, e in self.enrichments.entries()]
        if self.rd_comparison is not None:
            c = self.rd_comparison
            for what, m in (("points", c.points), ("sparse_rd", c.sparse_rd), ("dense", c.dense)):
                if m is not None:
                    _check_fits(m, sensor, f"rd_comparison.{what}")
                    names.append(m.name)
        _check_unique(names, "ablation arms (rd_comparison names must differ from axes-* and enrich-* too)")

    __hash__ = None


FPS_INPUTS = ("points", "sparse-rd", "dense")
"""What an FPS model reads: point clouds at each density (pillar models), RD cubes masked to the
detected set at each density (``sparse-rd``), or the whole cubes (``dense``, no density)."""
FPS_MODES = ("plain", "fast")
"""How a model runs: as built (eval mode), or :func:`radarpc.models.fast.fast_inference`'s copy."""


@dataclass(frozen=True)
class TimingSpec:
    """How every measurement of the FPS study is timed: batch 1, ``warmup`` untimed passes over
    the first frame, then ``repeats`` timed sweeps over the first ``frames`` frames of ``split``
    (the median sweep and the range in the table), each in a fresh process with ``threads`` torch
    threads, in each of ``modes``."""

    frames: int = 20                         # frames of the split timed (all of them when it has fewer)
    split: str = "test"
    repeats: int = 5                         # timed sweeps over the frames
    warmup: int = 2                          # untimed passes first (compilation, first allocations)
    threads: int | None = None               # torch (and OpenMP / BLAS) threads; None: torch's default
    modes: tuple[str, ...] = FPS_MODES
    detections_only: bool = False            # drop the freespace head (both heads run by default, as trained)

    def __post_init__(self) -> None:
        _positive_int(self.frames, "timing.frames")
        _positive_int(self.repeats, "timing.repeats")
        _positive_int(self.warmup, "timing.warmup", 0)
        if self.threads is not None:
            _positive_int(self.threads, "timing.threads")
        if self.split not in ("train", "val", "test", "all"):
            raise ValueError(f"timing.split must be one of train, val, test, all; got {self.split!r}")
        modes = tuple(self.modes)
        if not modes or any(m not in FPS_MODES for m in modes) or len(set(modes)) != len(modes):
            raise ValueError(f"timing.modes: each once, from {list(FPS_MODES)}; got {list(modes)}")
        object.__setattr__(self, "modes", modes)
        if not isinstance(self.detections_only, bool):
            raise ValueError(f"timing.detections_only must be true or false, got {self.detections_only!r}")


def _run_model(run: str) -> ModelSpec:
    """The model a training run folder trained (its ``run.json``), after checking it has best weights."""
    from radarpc.runs import read_json
    from radarpc.training.loop import BEST_WEIGHTS

    folder = Path(run)
    key = read_json(folder / "run.json")
    if not isinstance(key, dict) or not isinstance(key.get("experiment"), dict):
        raise DataFileError(folder / "run.json", "is missing or not a detection training run's key (run: a "
                                                 "folder of `radarpc train`)")
    if not (folder / BEST_WEIGHTS).is_file():
        raise FileNotFoundError(f"run: {folder} has no {BEST_WEIGHTS} (the run has not validated yet)")
    return experiment_from_dict(key["experiment"], where=str(folder / "run.json")).model


@dataclass(frozen=True)
class FPSModel:
    """A model of the FPS study: a registry variant with overrides (random weights: the speed does
    not depend on them), or the model and best weights of a training run folder (``run``), on one
    input kind.

    ``input`` defaults to ``points`` for a pillar model and ``dense`` for an FFTRadNet (give
    ``sparse-rd`` for the cubes masked to the detected set at each density). ``enrich`` names the
    point clouds' enrichments (the store a pillar model reads, and the extraction timed with it),
    or, for sparse RD, those of the set the mask keeps (``rdN``: ``S*(tau)``). ``sensor`` (default
    the study's) is the radar whose cubes and points it reads."""

    name: str = ""                           # row and legend name; default the variant
    variant: str | None = None               # a key of radarpc.models.MODELS
    overrides: dict = field(default_factory=dict)
    run: str | None = None                   # a training run folder instead of variant and overrides
    input: str | None = None                 # points, sparse-rd or dense
    enrich: tuple[str, ...] = ()
    sensor: str | None = None                # default the study's sensor

    __hash__ = None          # holds a dict

    def __post_init__(self) -> None:
        if (self.variant is None) == (self.run is None):
            raise ValueError("a model needs exactly one of variant (a registry name, with overrides) and run (a "
                             f"training run folder), got {'both' if self.variant else 'neither'}")
        if not isinstance(self.overrides, dict):
            raise ValueError(f"overrides must be a mapping of model config fields, got {type(self.overrides).__name__}")
        if self.run is not None and self.overrides:
            raise ValueError(f"run {self.run}: a run's model is the one it trained; drop overrides "
                             f"{sorted(self.overrides)}")
        spec = ModelSpec(self.variant, self.overrides) if self.variant is not None else _run_model(self.run)
        object.__setattr__(self, "_spec", spec)
        object.__setattr__(self, "name", self.name or spec.variant)
        _check_name(self.name, "model name")
        if spec.input_kind not in ("points", "rd"):
            raise ValueError(f"model {self.name!r}: the FPS study times the detection models (points or RD cubes); "
                             f"{spec.variant!r} reads {spec.input_kind}")
        kind = self.input or ("points" if spec.input_kind == "points" else "dense")
        if kind not in FPS_INPUTS:
            raise ValueError(f"model {self.name!r}: input must be one of {list(FPS_INPUTS)}, got {kind!r}")
        if (kind == "points") != (spec.input_kind == "points"):
            raise ValueError(f"model {self.name!r}: {spec.variant!r} reads "
                             f"{'point clouds' if spec.input_kind == 'points' else 'RD cubes'}; input {kind!r} "
                             f"needs {'a pillar model' if kind == 'points' else 'an FFTRadNet'}")
        object.__setattr__(self, "input", kind)
        pc = ConvertSettings(density=0.05, enrich=tuple(self.enrich)).point_cloud_config()
        object.__setattr__(self, "enrich", pc.enrich)
        if kind == "dense" and self.enrich:
            raise ValueError(f"model {self.name!r}: dense input reads whole cubes; drop enrich {list(self.enrich)}")
        if kind == "points":
            c = spec.config
            if "sector" in c.features and (pc.sectors is None or pc.sectors[0] * pc.sectors[1] != c.n_sector):
                raise ValueError(f"model {self.name!r}: its features read a {c.n_sector}-wide 'sector' descriptor; "
                                 f"enrich needs sectorA or sectorAxE with A x E = {c.n_sector} (e.g. "
                                 f"sector{c.n_sector}), got {list(self.enrich)}")
            if "rd_patch" in c.features and (pc.patch is None or pc.patch ** 2 != c.n_patch):
                raise ValueError(f"model {self.name!r}: its features read a {c.n_patch}-wide 'rd_patch'; enrich "
                                 f"needs rdN or patchN with N x N = {c.n_patch}, got {list(self.enrich)}")
        if self.sensor is not None:
            _check_sensor(self.sensor)

    @property
    def spec(self) -> ModelSpec:
        """The model: the variant with its overrides, or the run's."""
        return self._spec


@dataclass(frozen=True)
class FPSConfig:
    """The FPS study (the paper's Table 2): batch-1 frames/s of every model at every density (a
    dense model once), with and without point extraction, in each timing mode; parameters and the
    memory of one inference. The data gives the frames timed and the inputs made from them (point
    stores and sparse-RD roots at each density, one CFAR threshold per root calibrated on its
    training split as the density sweep's)."""

    name: str
    sensor: str
    data: DataSpec
    densities: tuple[float, ...]
    models: tuple[FPSModel, ...] = ()
    conversion: ConversionSpec = field(default_factory=ConversionSpec)
    timing: TimingSpec = field(default_factory=TimingSpec)

    __hash__ = None

    def __post_init__(self) -> None:
        _check_name(self.name, "study name")
        _check_sensor(self.sensor)
        if not self.models:
            raise ValueError("models: give at least one model to time")
        if self.data.drop_cubes:
            raise ValueError("data.drop_cubes: the FPS study times point extraction from the RD cubes, so it keeps "
                             "them; drop data.drop_cubes")
        n_roots = len(self.data.roots or self.data.simulate)
        if n_roots != 1:
            raise ValueError(f"data: the FPS study times the frames of one root; give one root or one simulation, got "
                             f"{n_roots}")
        sensors = {}
        for k, m in enumerate(self.models):
            sensor = m.sensor or self.sensor
            if self.data.roots and sensor != self.sensor:
                raise ValueError(f"models[{k}] ({m.name}): sensor {sensor!r}, but data.roots are of the study's "
                                 f"sensor {self.sensor!r} (models of another sensor need simulated data)")
            sensors[sensor] = radial_sensor(sensor)
            if m.input != "points":
                c = m.spec.config
                if (c.n_range, c.n_doppler, c.n_rx) != sensors[sensor].rd_shape:
                    raise ValueError(f"models[{k}] ({m.name}): {m.spec.variant!r} reads ({c.n_range}, {c.n_doppler}, "
                                     f"{c.n_rx}) cubes, sensor {sensor!r} makes {sensors[sensor].rd_shape}; pick the "
                                     f"variant of this sensor (fftradnet-s for radial-s) or set the model's sensor")
        densities = None
        for sensor in sensors.values():
            densities = _check_densities(tuple(self.densities), sensor)
        object.__setattr__(self, "densities", densities)
        _check_unique([m.name for m in self.models], "models")

    def sensor_of(self, model: FPSModel) -> str:
        """The sensor ``model`` reads."""
        return model.sensor or self.sensor


STUDY_KINDS: dict[str, type] = {"density-sweep": DensitySweepConfig, "ablation": AblationConfig, "fps": FPSConfig}
"""The study kinds (the ``radarpc experiment`` subcommands) and their config types."""
TRAINING_KINDS = ("density-sweep", "ablation")
"""The kinds whose runs train (a grid of :mod:`radarpc.experiments.study.grid`); ``fps`` times."""

# where model entries sit in each kind's YAML: (section, key) pairs, a key of None for a list
_ENTRY_PLACES = {
    "density-sweep": [("models", None), ("reference", "")],
    "ablation": [("axes", "model"), ("enrichments", "model"), ("rd_comparison", "points"),
                 ("rd_comparison", "sparse_rd"), ("rd_comparison", "dense")],
    "fps": [],
}


def _resolve_runs(models: Any, base: Path) -> Any:
    """The FPS models with their ``run`` folders resolved relative to ``base`` (the study file's folder)."""
    if not isinstance(models, list):
        return models
    out = []
    for m in models:
        if isinstance(m, dict) and isinstance(m.get("run"), str) and not Path(m["run"]).is_absolute():
            m = {**m, "run": str(base / m["run"])}
        out.append(m)
    return out


def _inline_experiment(entry: Any, base: Path, where: str) -> Any:
    """A model entry mapping with its ``experiment`` path (relative to ``base``) replaced by the
    experiment's resolved mapping; an inline mapping is left to the config types."""
    if not isinstance(entry, dict) or not isinstance(entry.get("experiment"), str):
        return entry
    path = Path(entry["experiment"])
    path = path if path.is_absolute() else base / path
    try:
        cfg = load_experiment(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"{where}.experiment: {entry['experiment']!r} (resolved to {path}) does not "
                                f"exist; the path is relative to the study config") from None
    return {**entry, "experiment": to_dict(cfg)}


def load_study(path: str | os.PathLike, kind: str, *, notice: Callable[[str], None] | None = None):
    """Read a study config of ``kind`` (a key of :data:`STUDY_KINDS`) from YAML, strictly.

    Experiment paths (and an FPS model's run folder) are resolved relative to the file and their
    experiments loaded whole.

    Raises
    ------
    ValueError
        The file, or an experiment it names, is not a valid config; the message names the file
        and the field.
    FileNotFoundError
        The file or an experiment it names does not exist.
    """
    if kind not in STUDY_KINDS:
        raise ValueError(f"unknown study kind {kind!r}; one of {', '.join(STUDY_KINDS)}")
    path = Path(path)
    d = load_yaml_mapping(path)
    base = path.parent
    for section, key in _ENTRY_PLACES[kind]:
        if section not in d:
            continue
        if key is None and isinstance(d[section], list):
            d[section] = [_inline_experiment(e, base, f"{path}: {section}[{k}]") for k, e in enumerate(d[section])]
        elif key == "":
            d[section] = _inline_experiment(d[section], base, f"{path}: {section}")
        elif isinstance(d[section], dict) and key in d[section]:
            d[section] = {**d[section], key: _inline_experiment(d[section][key], base, f"{path}: {section}.{key}")}
    if kind == "fps" and "models" in d:
        d["models"] = _resolve_runs(d["models"], base)
    cfg = from_dict(STUDY_KINDS[kind], d, where=str(path))
    if notice is not None and kind in TRAINING_KINDS and "budget" not in d:
        notice(f"{path}: no budget given, so every run trains as long as its experiment says")
    return cfg


def load_density_sweep(path: str | os.PathLike, **kw) -> DensitySweepConfig:
    """:func:`load_study` of a density sweep."""
    return load_study(path, "density-sweep", **kw)


def load_ablation(path: str | os.PathLike, **kw) -> AblationConfig:
    """:func:`load_study` of an ablation."""
    return load_study(path, "ablation", **kw)


def load_fps(path: str | os.PathLike, **kw) -> FPSConfig:
    """:func:`load_study` of an FPS study."""
    return load_study(path, "fps", **kw)
