"""The learned baseline's experiment config: a supervised radar-to-occupancy network (RPDNet-style),
``stage: occupancy``.

A YAML names the stage, the model (a variant of :data:`radarpc.models.MODELS` whose forward
reads RaLD's radar cube and writes occupancy logits: ``rpdnet``, ``rpdnet-s``, ``rpdnet-tiny``)
and its training; the other sections take their defaults when left out::

    name: rpdnet-s
    stage: occupancy
    model: {variant: rpdnet-s}
    radar: {max_intensity_db: 45.0}
    target: {cell: [0.25, 5.625, 2.5], occupied_weight: 4.0}
    train: {max_steps: 1000, epochs: 0, select_metric: iou, select_mode: max}

``stage`` is what ``radarpc train`` reads first (as for RaLD's two stages,
:mod:`radarpc.experiments.rald.config`): :data:`STAGE` here, ``autoencoder`` or ``diffusion``
there, no stage a detection experiment.

The target grid: the frustum (range x azimuth x elevation) of the sensor's field of view cut into
``target.cell`` cells (:meth:`radarpc.rald.frustum.FrustumGrid.from_fov`); its shape must be the
model's output shape (:attr:`radarpc.models.rpdnet.RPDNetConfig.out_shape`), checked here with
both named. The default cells, 0.25 m x 5.625 deg x 2.5 deg, cut AWR1843's field of view (15.863 m,
+-90 deg, +-20 deg) into 64 x 32 x 16 cells: half the resolution of RaLD's 128 x 64 x 32 cube along
every axis, the output of ``out_stride: 2``.

The resolved config is stored whole with every run (``run.json``, ``config.yaml`` and inside every
weights file) and is all the run's model needs to be rebuilt.
"""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from typing import Any, Callable

from radarpc.config import from_dict, load_yaml_mapping, to_dict
from radarpc.experiments.rald.config import RadarInput
from radarpc.models import ModelSpec
from radarpc.models.rpdnet import RPDNetConfig
from radarpc.rald.frustum import FrustumGrid
from radarpc.sensors.coloradar import AWR1843_FOV, RadarFOV
from radarpc.training.loop import TrainConfig

__all__ = ["STAGE", "METRICS", "REQUIRED_SECTIONS", "DEFAULT_CELL", "OccupancyTarget", "OccupancyExperiment",
           "is_occupancy_config", "experiment_from_dict", "load_experiment", "canonical_key", "with_train"]

STAGE = "occupancy"
"""The ``stage`` value of the learned baseline's configs (one supervised stage)."""

METRICS: dict[str, str] = {"loss": "min", "iou": "max", "precision": "max", "recall": "max", "f1": "max"}
"""Validation metrics (per frame, then averaged) and the direction in which each improves."""

REQUIRED_SECTIONS = ("name", "stage", "model", "train")
"""Keys a baseline experiment YAML must give."""

DEFAULT_CELL = (0.25, 5.625, 2.5)
"""Target cells (m, deg, deg): 64 x 32 x 16 over AWR1843's field of view."""


@dataclass(frozen=True)
class OccupancyTarget:
    """The training target: the LiDAR truth's occupancy of a coarse frustum grid, and the loss's
    weight on occupied cells.

    The loss is the weighted binary cross-entropy over the ``N`` cells of a frame,
    ``L = (1/N) sum_c [ w y_c (-log sigma(s_c)) + (1 - y_c) (-log(1 - sigma(s_c))) ]``, ``s_c`` the
    logit and ``y_c`` the truth of cell ``c``, ``w = occupied_weight``.

    Why weight the occupied cells: they are few (2.6-4 % of the default grid in simulated
    hallways and labs), and the radar localises a surface only to within several angular cells. The
    prediction ``p`` that minimises the expected loss of a cell whose posterior occupancy is ``q``
    is ``p* = w q / (w q + 1 - q)``, so ``p* > 1/2`` exactly when ``q > 1 / (1 + w)``: the weight
    sets the posterior above which the cloud (cells with ``sigma(s) > 0.5``) keeps a cell. Plain
    BCE (``w = 1``) keeps only cells more likely occupied than not, which on a radar's spread-out
    evidence leaves most surfaces without a point; full class balancing (``w = (1 - pi) / pi``,
    24-37 here) keeps every cell with a 2.6-4 % chance and floods the field of view. ``w = 4``
    keeps the cells with a posterior above 0.2.
    """

    cell: tuple[float, float, float] = DEFAULT_CELL   # range (m), azimuth (deg), elevation (deg)
    occupied_weight: float = 4.0                      # w: occupied cells' weight in the BCE (see above)

    def __post_init__(self) -> None:
        cell = tuple(float(c) for c in self.cell)
        if len(cell) != 3 or not all(math.isfinite(c) and c > 0 for c in cell):
            raise ValueError(f"target.cell must be 3 sizes > 0 (range m, azimuth deg, elevation deg), got {self.cell}")
        object.__setattr__(self, "cell", cell)
        if not (math.isfinite(self.occupied_weight) and self.occupied_weight > 0):
            raise ValueError(f"target.occupied_weight must be a finite number > 0, got {self.occupied_weight}")

    def grid(self, fov: RadarFOV = AWR1843_FOV) -> FrustumGrid:
        """The target grid over ``fov`` (:meth:`~radarpc.rald.frustum.FrustumGrid.from_fov`)."""
        return FrustumGrid.from_fov(fov, self.cell)


@dataclass(frozen=True)
class OccupancyExperiment:
    """The learned baseline: radar cube in, occupancy logits of the target grid out.

    Attributes
    ----------
    name : str
        Shown in logs and reports.
    model : ModelSpec
        A radar-to-occupancy variant of :data:`radarpc.models.MODELS` (``rpdnet``, ``rpdnet-s``,
        ``rpdnet-tiny``).
    stage : str
        ``"occupancy"`` (:data:`STAGE`).
    radar : RadarInput
        RaLD's normalisation of the intensity cube (the diffusion model's input).
    target : OccupancyTarget
        The grid and the loss's weight.
    train : TrainConfig
        The optimisation; ``select_metric`` one of :data:`METRICS`.
    """

    name: str
    model: ModelSpec
    stage: str = STAGE
    radar: RadarInput = field(default_factory=RadarInput)
    target: OccupancyTarget = field(default_factory=OccupancyTarget)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        if self.stage != STAGE:
            raise ValueError(f"experiment {self.name!r}: stage {self.stage!r} given to the occupancy baseline's "
                             f"config (stage: {STAGE})")
        if not isinstance(self.model, ModelSpec):
            raise ValueError(f"experiment {self.name!r}: model must be a ModelSpec (variant and overrides), "
                             f"got {type(self.model).__name__}")
        if not isinstance(self.model.config, RPDNetConfig):
            raise ValueError(f"experiment {self.name!r}: stage {STAGE!r} trains a radar-to-occupancy network "
                             f"(rpdnet, rpdnet-s, rpdnet-tiny), but model {self.model.variant!r} is a "
                             f"{type(self.model.config).__name__} model")
        grid, out = self.target.grid().shape, self.model.config.out_shape
        if grid != out:
            raise ValueError(f"experiment {self.name!r}: target.cell {list(self.target.cell)} cuts the field of view "
                             f"into {grid[0]} x {grid[1]} x {grid[2]} cells, but model {self.model.variant!r} "
                             f"writes {out[0]} x {out[1]} x {out[2]} (radar_shape / out_stride); change target.cell "
                             f"or the model's radar_shape / out_stride")
        t = self.train
        if t.select_metric not in METRICS:
            raise ValueError(f"train.select_metric {t.select_metric!r} is not a validation metric of the occupancy "
                             f"baseline; one of {', '.join(METRICS)}")
        if t.select_mode != METRICS[t.select_metric]:
            raise ValueError(f"train.select_mode {t.select_mode!r}: {t.select_metric} is better when "
                             f"{'lower' if METRICS[t.select_metric] == 'min' else 'higher'}; set select_mode: "
                             f"{METRICS[t.select_metric]}")

    __hash__ = None          # the model overrides are a dict

    @property
    def input_kind(self) -> str:
        return self.model.input_kind

    def build_model(self):
        """The network (:class:`~radarpc.models.rpdnet.RPDNet`) with fresh weights."""
        return self.model.build()


def is_occupancy_config(d: Any) -> bool:
    """Whether a config mapping (a YAML's, a run key's ``experiment``) is this baseline's
    (``stage: occupancy``)."""
    return isinstance(d, dict) and d.get("stage") == STAGE


def experiment_from_dict(d: Any, *, where: str = "experiment") -> OccupancyExperiment:
    """The experiment of a plain dict, built strictly (unknown keys and wrong types refused, the
    message starting with ``where``)."""
    if not isinstance(d, dict):
        raise ValueError(f"{where}: expected a mapping (an occupancy baseline config), got {type(d).__name__}")
    return from_dict(OccupancyExperiment, d, where=where)


def load_experiment(path: str | os.PathLike, *, notice: Callable[[str], None] | None = None) -> OccupancyExperiment:
    """Read a baseline experiment YAML (strict safe loading: :func:`radarpc.config.load_yaml_mapping`;
    unknown keys, values of the wrong type and bad values name the file and the field).

    Parameters
    ----------
    path : path-like
    notice : callable, optional
        Told, in one line, which sections the file leaves out and so take their defaults.

    Raises
    ------
    ValueError
        The file is not a valid baseline config or lacks one of :data:`REQUIRED_SECTIONS`.
    """
    d = load_yaml_mapping(path)
    missing = [k for k in REQUIRED_SECTIONS if k not in d]
    if missing:
        raise ValueError(f"{path}: no {', '.join(repr(k) for k in missing)} (an occupancy baseline config names its "
                         f"{', '.join(REQUIRED_SECTIONS)}; see configs/rpdnet-s.yaml)")
    cfg = experiment_from_dict(d, where=str(path))
    left_out = [k for k in ("radar", "target") if k not in d]
    if notice is not None and left_out:
        notice(f"{path}: {', '.join(left_out)} not given, so the defaults apply")
    return cfg


def canonical_key(stored: Any, *, num_workers: int | None = None) -> Any:
    """A stored run key read through the config types, so that it compares equal to the key the
    same run has today (fields added since take their defaults); ``num_workers`` replaces the
    stored ``train.num_workers`` (loader processes do not change what a run computes)."""
    if not isinstance(stored, dict) or not isinstance(stored.get("experiment"), dict):
        return stored
    try:
        cfg = experiment_from_dict(stored["experiment"], where="run.json: experiment")
    except ValueError:
        return stored                        # not readable: compared raw, and refused as different
    if num_workers is not None:
        cfg = with_train(cfg, num_workers=num_workers)
    return {**stored, "experiment": to_dict(cfg)}


def with_train(cfg: OccupancyExperiment, **changes: Any) -> OccupancyExperiment:
    """``cfg`` with fields of its :class:`TrainConfig` replaced."""
    return dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, **changes))
