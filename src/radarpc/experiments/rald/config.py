"""RaLD's experiment configs: stage 1 (the occupancy autoencoder) and stage 2 (the latent diffusion
model), told apart by their ``stage`` key.

A RaLD experiment YAML names its stage, its model (a variant of :data:`radarpc.models.MODELS` and
the fields that differ) and its training; the other sections take their defaults when left out::

    name: rald-ae-s                   # stage 1
    stage: autoencoder
    model: {variant: rald-ae-s}
    data: {points: 10000, queries: 10000, occupied_fraction: 0.0625, partition: frustum}
    train: {epochs: 20, select_metric: loss, select_mode: min}

    name: rald-s                      # stage 2: trained against a stage-1 run (radarpc train --ae RUN)
    stage: diffusion
    model: {variant: rald-dit-s}
    radar: {max_intensity_db: 45.0}
    loss: {p_mean: -1.2, p_std: 1.2}
    train: {epochs: 20, select_metric: loss, select_mode: min}

``stage`` is what ``radarpc train`` reads first: a config with a ``stage`` key is a RaLD
experiment of that stage (:data:`STAGES`), one without it a detection experiment
(:mod:`radarpc.experiments.radial_detection.config`). The stage must match what the model reads
(:data:`STAGE_INPUT`: the autoencoder reads LiDAR points, the diffusion model RaLD's radar cube),
so a model given to the wrong stage is refused with both named.

Stage 2 takes the LiDAR side from its stage-1 run: the points per frame, the partition and the
cell size the autoencoder was trained with (the latents are only meaningful in those coordinates).

The resolved config is stored whole with every run (``run.json``, ``config.yaml`` and inside every
weights file) and is all the run's model needs to be rebuilt.
"""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from typing import Any, Callable

import torch

from radarpc.config import from_dict, load_yaml_mapping, to_dict
from radarpc.data.coloradar import RALD_MAX_INTENSITY_DB
from radarpc.models import ModelSpec
from radarpc.models.latent_dit import LatentDiTConfig
from radarpc.rald.frustum import FrustumGrid
from radarpc.rald.voxels import PARTITIONS, CartesianGrid, cartesian_points, model_coords, partition_grid
from radarpc.sensors.coloradar import AWR1843_FOV, RadarFOV
from radarpc.training.loop import TrainConfig

__all__ = ["STAGES", "STAGE_INPUT", "AUTOENCODER_METRICS", "DIFFUSION_METRICS", "REQUIRED_SECTIONS", "LidarData",
           "RadarInput", "EDMLossConfig", "AutoencoderExperiment", "DiffusionExperiment", "RaldExperiment",
           "experiment_from_dict", "load_experiment", "canonical_key", "with_train", "without_locators",
           "RUN_REFERENCES"]

STAGES: tuple[str, ...] = ("autoencoder", "diffusion")
"""RaLD's two training stages, the values of a config's ``stage`` key."""

STAGE_INPUT: dict[str, str] = {"autoencoder": "lidar", "diffusion": "radar"}
"""The ``input_kind`` of the models each stage trains (:attr:`radarpc.models.ModelSpec.input_kind`)."""

AUTOENCODER_METRICS: dict[str, str] = {"loss": "min", "bce": "min", "kl": "min", "iou": "max",
                                       "accuracy": "max", "recall": "max"}
"""Stage 1's validation metrics and the direction in which each improves (``train.select_mode``)."""

DIFFUSION_METRICS: dict[str, str] = {"loss": "min", "loss_other_radar": "min", "radar_gain": "max"}
"""Stage 2's validation metrics and their directions: the EDM loss with fixed noise; at the sampler's
noise levels, the loss with each frame conditioned on another frame's radar and its excess over the
loss with the frame's own radar, the radar's gain (:func:`radarpc.experiments.rald.task.evaluate_diffusion`)."""

REQUIRED_SECTIONS = ("name", "stage", "model", "train")
"""Keys a RaLD experiment YAML must give: its name, stage, model and training."""


@dataclass(frozen=True)
class LidarData:
    """What the autoencoder reads and learns from each frame, and the coordinates it works in.

    RaLD's official values are the defaults (``configs/ae/*.yml``: ``num_samples: 10000``,
    ``query_ratio: 0.0625``, view-cone mode with cells of 0.05 m x 0.25 deg x 0.5 deg).

    The model's coordinates: a radar-frame point ``p`` (x forward, y left, z up) is first taken to
    the model's frame, ``M p`` (:meth:`model_frame`: ``M`` the identity, or with ``mirror_azimuth``
    the left-right mirror ``y -> -y``, so that azimuth counts positive to the right as in the
    official code's ``cartesian2polar``), then into the grid's coordinates (polar for frustum cells)
    and mapped affinely to ``[-1, 1]`` per axis over the grid (:meth:`to_model`). Occupancy, queries
    and decoded cells all live in the model's frame; :meth:`to_radar` maps model coordinates back
    to radar-frame metres (``M`` is its own inverse).
    """

    points: int = 10_000                 # LiDAR points per frame the encoder reads (resampled, see task.py)
    queries: int = 10_000                # occupancy queries per frame (decoder inputs with labels)
    occupied_fraction: float = 0.0625    # floor(queries * this) queries lie in occupied cells, the rest in empty ones
    partition: str = "frustum"           # "frustum" (RaLD's polar cells) or "cartesian" (voxels): PARTITIONS
    cell: tuple[float, float, float] | None = None   # cell size (m, deg, deg or m, m, m); None: the partition's default
    max_range_m: float | None = None     # frustum grid's far edge; None: the field of view's range in whole cells
                                         # (15.9 m at 0.05 m); the official checkpoints' pc_range: 15.8
    mirror_azimuth: bool = False         # model frame mirrored left-right (azimuth positive to the right, the
                                         # official code's convention); radarpc's frame is left-positive

    def __post_init__(self) -> None:
        for k in ("points", "queries"):
            v = getattr(self, k)
            if isinstance(v, bool) or int(v) != v or v < 1:
                raise ValueError(f"data.{k} must be an integer >= 1, got {v!r}")
        if not (math.isfinite(self.occupied_fraction) and 0.0 < self.occupied_fraction < 1.0):
            raise ValueError(f"data.occupied_fraction must be in (0, 1), got {self.occupied_fraction}")
        n_occupied = math.floor(self.queries * self.occupied_fraction + 1e-9)
        if not 1 <= n_occupied < self.queries:
            raise ValueError(f"data: {self.queries} queries x occupied_fraction {self.occupied_fraction} gives "
                             f"{n_occupied} occupied queries; need at least one occupied and one empty query")
        if self.partition not in PARTITIONS:
            raise ValueError(f"data.partition must be one of {list(PARTITIONS)}, got {self.partition!r}")
        if self.cell is not None:
            object.__setattr__(self, "cell", tuple(float(c) for c in self.cell))
        if self.max_range_m is not None:
            if self.partition != "frustum":
                raise ValueError(f"data.max_range_m is the frustum grid's far edge; partition {self.partition!r} "
                                 f"covers the field of view (leave max_range_m null)")
            if not (math.isfinite(self.max_range_m) and self.max_range_m > 0):
                raise ValueError(f"data.max_range_m must be a finite range > 0 (metres), got {self.max_range_m}")
        if not isinstance(self.mirror_azimuth, bool):
            raise ValueError(f"data.mirror_azimuth must be true or false, got {self.mirror_azimuth!r}")
        try:
            self.grid()
        except ValueError as e:
            raise ValueError(f"data: partition {self.partition!r} with cell {self.cell}"
                             + (f" and max_range_m {self.max_range_m}" if self.max_range_m is not None else "")
                             + f": {e}") from None

    @property
    def n_occupied(self) -> int:
        """Occupied queries per frame: ``floor(queries * occupied_fraction)`` (625 of 10,000 in RaLD)."""
        return math.floor(self.queries * self.occupied_fraction + 1e-9)

    def grid(self, fov: RadarFOV = AWR1843_FOV) -> FrustumGrid | CartesianGrid:
        """The occupancy grid over ``fov``: RaLD's frustum cells or Cartesian voxels
        (:func:`radarpc.rald.voxels.partition_grid`), the frustum's range ending at ``max_range_m``
        when given (a whole number of cells)."""
        grid = partition_grid(self.partition, fov, self.cell)
        if self.max_range_m is not None:
            grid = dataclasses.replace(grid, range_m=(grid.range_m[0], float(self.max_range_m)))
        return grid

    def model_frame(self, xyz: torch.Tensor) -> torch.Tensor:
        """Radar-frame points ``(..., 3)`` in the model's frame (the same points, ``y`` negated with
        ``mirror_azimuth``); also the inverse map."""
        xyz = torch.as_tensor(xyz)
        return xyz * xyz.new_tensor((1.0, -1.0, 1.0)) if self.mirror_azimuth else xyz

    def to_model(self, xyz: torch.Tensor, grid: FrustumGrid | CartesianGrid | None = None) -> torch.Tensor:
        """The model's coordinates ``(..., 3)`` in ``[-1, 1]`` of radar-frame points in metres
        (:meth:`model_frame`, then :func:`radarpc.rald.voxels.model_coords` on ``grid``, default
        :meth:`grid`)."""
        return model_coords(self.grid() if grid is None else grid, self.model_frame(xyz))

    def to_radar(self, u: torch.Tensor, grid: FrustumGrid | CartesianGrid | None = None) -> torch.Tensor:
        """Radar-frame points in metres of model coordinates ``(..., 3)`` (queries, decoded
        points): the inverse of :meth:`to_model`."""
        return self.model_frame(cartesian_points(self.grid() if grid is None else grid, u))


@dataclass(frozen=True)
class RadarInput:
    """How the radar cube becomes the diffusion model's input (:func:`radarpc.data.coloradar.rald_intensity`):
    the intensity clipped to ``[0, max_intensity_db]`` dB and divided by it, then upsampled to the
    model's ``radar_shape``. RaLD: 45 dB. The Doppler channel is not an input: RaLD's diffusion
    configs read the intensity alone (``use_radar_dopp: false``)."""

    max_intensity_db: float = RALD_MAX_INTENSITY_DB

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_intensity_db) and self.max_intensity_db > 0):
            raise ValueError(f"radar.max_intensity_db must be a finite number > 0, got {self.max_intensity_db}")


@dataclass(frozen=True)
class EDMLossConfig:
    """EDM's training noise levels: ``ln(sigma) ~ N(p_mean, p_std^2)`` (RaLD and EDM: -1.2, 1.2).
    ``sigma_data`` is the model's (:class:`radarpc.models.latent_dit.LatentDiTConfig`)."""

    p_mean: float = -1.2
    p_std: float = 1.2

    def __post_init__(self) -> None:
        if not math.isfinite(self.p_mean):
            raise ValueError(f"loss.p_mean must be finite, got {self.p_mean}")
        if not (math.isfinite(self.p_std) and self.p_std > 0):
            raise ValueError(f"loss.p_std must be a finite number > 0, got {self.p_std}")


def _check_common(name: str, stage: str, want_stage: str, model: Any, train: TrainConfig,
                  metrics: dict[str, str]) -> None:
    if stage != want_stage:
        raise ValueError(f"experiment {name!r}: stage {stage!r} given to the {want_stage} stage's config")
    if not isinstance(model, ModelSpec):
        raise ValueError(f"experiment {name!r}: model must be a ModelSpec (variant and overrides), "
                         f"got {type(model).__name__}")
    kind = STAGE_INPUT[stage]
    if model.input_kind != kind:
        other = next((s for s, k in STAGE_INPUT.items() if k == model.input_kind), None)
        hint = f"it is a {other} model (stage: {other})" if other else "it is not a RaLD model"
        raise ValueError(f"experiment {name!r}: stage {stage!r} trains a model that reads {kind!r} inputs, but "
                         f"model {model.variant!r} reads {model.input_kind!r}; {hint}")
    if train.select_metric not in metrics:
        raise ValueError(f"train.select_metric {train.select_metric!r} is not a validation metric of the {stage} "
                         f"stage; one of {', '.join(metrics)}")
    if train.select_mode != metrics[train.select_metric]:
        raise ValueError(f"train.select_mode {train.select_mode!r}: {train.select_metric} is better when "
                         f"{'lower' if metrics[train.select_metric] == 'min' else 'higher'}; set select_mode: "
                         f"{metrics[train.select_metric]}")


def _check_scenes(name: str, scenes: tuple[str, ...] | None) -> None:
    if scenes is None:
        return
    if not scenes or not all(isinstance(x, str) and x for x in scenes):
        raise ValueError(f"experiment {name!r}: scenes must be a non-empty list of scene names (e.g. [hallway, "
                         f"classroom]) or null for every scene, got {list(scenes)!r}")
    twice = sorted({x for x in scenes if scenes.count(x) > 1})
    if twice:
        raise ValueError(f"experiment {name!r}: scenes names {', '.join(twice)} twice")


@dataclass(frozen=True)
class AutoencoderExperiment:
    """RaLD's stage 1: the LiDAR occupancy autoencoder.

    Attributes
    ----------
    name : str
        Shown in logs and reports.
    model : ModelSpec
        An autoencoder variant of :data:`radarpc.models.MODELS` (``rald-ae``, ``rald-ae-s``, ...).
    stage : str
        ``"autoencoder"``.
    data : LidarData
        Points, queries and the occupancy partition.
    train : TrainConfig
        The optimisation; ``select_metric`` one of :data:`AUTOENCODER_METRICS`.
    scenes : tuple of str or None
        Train and validate on the runs of these scenes only (scene names as
        :func:`radarpc.data.coloradar.scene_of_run` gives them, e.g. ``lab``); None: every scene.
        The others are held out (the seed's Tables 5-8).
    """

    name: str
    model: ModelSpec
    stage: str = "autoencoder"
    data: LidarData = field(default_factory=LidarData)
    train: TrainConfig = field(default_factory=TrainConfig)
    scenes: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        _check_common(self.name, self.stage, "autoencoder", self.model, self.train, AUTOENCODER_METRICS)
        _check_scenes(self.name, self.scenes)
        mc = self.model.config
        if mc.query_type == "fps" and self.data.points < mc.n_latents:
            raise ValueError(f"experiment {self.name!r}: query_type 'fps' picks n_latents={mc.n_latents} of the "
                             f"input points, but data.points is {self.data.points}")

    __hash__ = None          # the model overrides are a dict

    @property
    def input_kind(self) -> str:
        return self.model.input_kind

    def build_model(self):
        """The autoencoder with fresh weights."""
        return self.model.build()


@dataclass(frozen=True)
class DiffusionExperiment:
    """RaLD's stage 2: the radar-conditioned latent diffusion model, trained on the latents of a
    frozen stage-1 autoencoder.

    Attributes
    ----------
    name : str
    model : ModelSpec
        A diffusion variant of :data:`radarpc.models.MODELS` (``rald-dit``, ``rald-dit-s``, ...);
        its ``n_latents`` and ``latent_dim`` must be the autoencoder's (checked when the
        stage-1 run is loaded).
    stage : str
        ``"diffusion"``.
    radar : RadarInput
        RaLD's normalisation of the intensity cube.
    loss : EDMLossConfig
        The training noise levels.
    train : TrainConfig
        The optimisation; ``select_metric`` ``"loss"`` (:data:`DIFFUSION_METRICS`).
    scenes : tuple of str or None
        Train and validate on the runs of these scenes only (as :class:`AutoencoderExperiment`'s);
        None: every scene.
    """

    name: str
    model: ModelSpec
    stage: str = "diffusion"
    radar: RadarInput = field(default_factory=RadarInput)
    loss: EDMLossConfig = field(default_factory=EDMLossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    scenes: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        _check_common(self.name, self.stage, "diffusion", self.model, self.train, DIFFUSION_METRICS)
        _check_scenes(self.name, self.scenes)
        if not isinstance(self.model.config, LatentDiTConfig):
            raise ValueError(f"experiment {self.name!r}: stage 'diffusion' trains a latent diffusion model (rald-dit, "
                             f"...), but model {self.model.variant!r} is a {type(self.model.config).__name__} model"
                             f" (a radar-to-occupancy network trains with stage: occupancy)")

    __hash__ = None

    @property
    def input_kind(self) -> str:
        return self.model.input_kind

    def build_model(self):
        """The diffusion model (:class:`~radarpc.models.latent_dit.LatentDiT`) with fresh weights."""
        return self.model.build()


RaldExperiment = AutoencoderExperiment | DiffusionExperiment
_CLASSES: dict[str, type] = {"autoencoder": AutoencoderExperiment, "diffusion": DiffusionExperiment}


def experiment_from_dict(d: Any, *, where: str = "experiment") -> RaldExperiment:
    """The experiment of a plain dict (a YAML file's, or a run key's ``experiment``): the class its
    ``stage`` names, built strictly (unknown keys and wrong types refused, the message starting
    with ``where``).

    Raises
    ------
    ValueError
        Not a mapping, no or an unknown ``stage``, or anything the config refuses.
    """
    if not isinstance(d, dict):
        raise ValueError(f"{where}: expected a mapping (a RaLD experiment config), got {type(d).__name__}")
    stage = d.get("stage")
    if stage not in _CLASSES:
        raise ValueError(f"{where}: stage must be one of {', '.join(STAGES)} (the RaLD training stage), "
                         f"got {stage!r}" if "stage" in d else
                         f"{where}: no 'stage' (a RaLD experiment config names its stage: {', '.join(STAGES)})")
    return from_dict(_CLASSES[stage], d, where=where)


def load_experiment(path: str | os.PathLike, *, notice: Callable[[str], None] | None = None) -> RaldExperiment:
    """Read a RaLD experiment YAML (strict safe loading: :func:`radarpc.config.load_yaml_mapping`;
    unknown keys, values of the wrong type and bad values name the file and the field).

    Parameters
    ----------
    path : path-like
    notice : callable, optional
        Told, in one line, which data sections the file leaves out and so take their defaults.

    Raises
    ------
    ValueError
        The file is not a valid RaLD experiment config or lacks one of :data:`REQUIRED_SECTIONS`.
    """
    d = load_yaml_mapping(path)
    missing = [k for k in REQUIRED_SECTIONS if k not in d]
    if missing:
        raise ValueError(f"{path}: no {', '.join(repr(k) for k in missing)} (a RaLD experiment config names its "
                         f"{', '.join(REQUIRED_SECTIONS)}; see configs/rald-ae-s.yaml and configs/rald-s.yaml)")
    cfg = experiment_from_dict(d, where=str(path))
    sections = ("data",) if cfg.stage == "autoencoder" else ("radar", "loss")
    left_out = [k for k in sections if k not in d]
    if notice is not None and left_out:
        notice(f"{path}: {', '.join(left_out)} not given, so RaLD's defaults apply")
    return cfg


def canonical_key(stored: Any, *, num_workers: int | None = None) -> Any:
    """A stored run key read through the config types, so that it compares equal to the key the
    same run has today: the experiment (fields added since take their defaults) and, for stage 2,
    the recorded stage-1 run's key the same way, without the places of the runs it builds on in turn
    (:func:`without_locators`; the reference's own ``path`` is the run folder's locator).

    ``num_workers`` replaces the stored ``train.num_workers`` (loader processes do not change what
    a run computes, so a run may resume with another count); the stage-1 key inside a stage-2 key
    keeps its own.
    """
    if not isinstance(stored, dict) or not isinstance(stored.get("experiment"), dict):
        return stored
    try:
        cfg = experiment_from_dict(stored["experiment"], where="run.json: experiment")
    except ValueError:
        return stored                        # not readable: compared raw, and refused as different
    if num_workers is not None:
        cfg = with_train(cfg, num_workers=num_workers)
    out = {**stored, "experiment": to_dict(cfg)}
    for ref in RUN_REFERENCES:                 # the stage-1 run, and the run a fine-tuning started from
        r = stored.get(ref)
        if isinstance(r, dict) and isinstance(r.get("run"), dict):
            out[ref] = {**r, "run": without_locators(canonical_key(r["run"]))}
    return out


RUN_REFERENCES = ("ae", "init")
"""The entries of a run key that name another run (``{"path", "run", "weights_sha256"}``)."""


def without_locators(key: Any) -> Any:
    """A run key without where the runs it builds on lie: the ``path`` of its :data:`RUN_REFERENCES`,
    and of theirs inside their recorded keys, at every depth (a run is known by its key and weights'
    digest; its folder may move)."""
    if not isinstance(key, dict):
        return key
    out = dict(key)
    for ref in RUN_REFERENCES:
        r = out.get(ref)
        if isinstance(r, dict):
            out[ref] = {k: without_locators(v) if k == "run" else v for k, v in r.items() if k != "path"}
    return out


def with_train(cfg: RaldExperiment, **changes: Any) -> RaldExperiment:
    """``cfg`` with fields of its :class:`TrainConfig` replaced."""
    return dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, **changes))
