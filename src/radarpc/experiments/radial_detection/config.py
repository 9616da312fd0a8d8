"""The RADIal detection experiment's config: a model of the registry, targets, loss, training.

An experiment YAML names its model as a variant of :data:`radarpc.models.MODELS` and the fields
that differ from it; every other section takes its defaults when left out::

    name: spectralpillars-s-easy
    model:
      variant: spectralpillars-s
      overrides: {}
    difficult: false
    train:
      epochs: 6

The resolved config is stored whole with every run (``run.json``, ``config.yaml`` and inside every
weights file) and is all :meth:`ExperimentConfig.build_model` needs to rebuild the model. Run
folders and YAML files written before the model registry (with a ``fftradnet:`` or ``pillars:``
section holding the whole model config) are read by :func:`experiment_from_dict` into the same
form, so older runs still evaluate and resume.
"""
from __future__ import annotations

import dataclasses
import math
import os
import typing
from dataclasses import dataclass, field
from typing import Any, Callable

from torch import nn

from radarpc.config import from_dict, load_yaml_mapping, to_dict
from radarpc.eval.detection import DetectionReport
from radarpc.models import MODELS, ModelSpec
from radarpc.models.heads import DETECTION_SHAPE
from radarpc.models.losses import LossConfig
from radarpc.models.targets import TargetConfig
from radarpc.training.loop import TrainConfig

__all__ = ["ExperimentConfig", "experiment_from_dict", "load_experiment", "canonical_key", "with_train",
           "validation_metrics", "REQUIRED_SECTIONS"]


def validation_metrics(freespace: bool) -> tuple[str, ...]:
    """The metrics validation reports (``train.select_metric`` is one of them): the scalar
    scores of RADIal's detection report, and the freespace mIoU of a model with a freespace head."""
    hints = typing.get_type_hints(DetectionReport)
    scores = tuple(f.name for f in dataclasses.fields(DetectionReport) if hints[f.name] is float)
    return scores + (("freespace_miou",) if freespace else ())


@dataclass(frozen=True)
class ExperimentConfig:
    """A detection experiment: the model, targets, loss and training settings.

    Attributes
    ----------
    name : str
        Shown in logs and reports.
    model : ModelSpec
        A variant of :data:`radarpc.models.MODELS` and its overrides. FFTRadNet variants read RD
        cubes (``--data`` a RADIal root, or a sparse-RD root for the sparse-RD baseline); the
        pillar variants read a point store (``--points``).
    difficult : bool
        Train and validate with RADIal's ``Difficult`` labels, as RADIal's ``1-Train.py`` does
        (its ``3-Evaluation.py`` drops them unless given ``--difficult``: ``radarpc evaluate --no-difficult``).
    statistics_frames : int
        Training frames (evenly spaced) whose cubes give FFTRadNet's input normalisation.
    mirror_probability : float in [0, 1]
        Share of training frames mirrored about the boresight (:mod:`radarpc.data.augment`), drawn
        per frame and epoch; point inputs only (mirroring an RD cube would need the array's
        geometry). 0 (default) trains on the frames as they are.
    rotation_max_deg : float >= 0
        Training frames rotated about the radar's vertical axis by an angle drawn per frame and
        epoch from the multiples of 0.4 deg within +-``rotation_max_deg``
        (:class:`~radarpc.data.augment.RotatedFrames`); point inputs only, and not with the
        ``sector`` feature, which would need the angle spectrum itself rotated. 0 (default): none.
    superpose_probability : float in [0, 1]
        Share of training frames whose RD cube is summed with another training frame's, their
        labels joined and freespace intersected (:class:`~radarpc.data.augment.SuperposedFrames`):
        the radar's view of both scenes at once, twice the vehicles a forward pass. RD inputs
        only (a point cloud of two scenes is not the union of their CFAR points). 0 (default): none.
    targets, loss, train :
        RADIal's encoding, the loss weights and the optimisation.
    """

    name: str
    model: ModelSpec
    difficult: bool = True
    statistics_frames: int = 256
    mirror_probability: float = 0.0
    rotation_max_deg: float = 0.0
    superpose_probability: float = 0.0
    targets: TargetConfig = field(default_factory=TargetConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        if not isinstance(self.model, ModelSpec):
            raise ValueError(f"experiment {self.name!r}: model must be a ModelSpec (variant and overrides), "
                             f"got {type(self.model).__name__}")
        if self.input_kind not in ("rd", "points"):
            rald = (" (a RaLD experiment config names its stage: autoencoder or diffusion)"
                    if self.input_kind in ("lidar", "radar") else "")
            raise ValueError(f"experiment {self.name!r}: model {self.model.variant!r} reads {self.input_kind!r} "
                             f"inputs, not RADIal's RD cubes or spectral points; choose a detection model{rald}")
        known = validation_metrics(bool(getattr(self.model.config, "freespace", False)))
        if self.train.select_metric not in known:
            raise ValueError(f"train.select_metric {self.train.select_metric!r} is not a validation metric of this "
                             f"experiment; one of {', '.join(known)}")
        if (self.targets.n_range, self.targets.n_azimuth) != DETECTION_SHAPE:
            raise ValueError(f"targets: n_range x n_azimuth = {self.targets.n_range} x {self.targets.n_azimuth}, but "
                             f"the models' detection map is {DETECTION_SHAPE[0]} x {DETECTION_SHAPE[1]}")
        if self.statistics_frames < 1:
            raise ValueError(f"statistics_frames must be >= 1, got {self.statistics_frames}")
        if not 0.0 <= self.mirror_probability <= 1.0:
            raise ValueError(f"mirror_probability must be in [0, 1], got {self.mirror_probability}")
        if self.mirror_probability > 0 and self.input_kind == "rd":
            raise ValueError(f"experiment {self.name!r}: mirror_probability applies to point inputs only "
                             f"(mirroring an RD cube would need the array's geometry); set it to 0")
        if not (math.isfinite(self.rotation_max_deg) and self.rotation_max_deg >= 0):
            raise ValueError(f"rotation_max_deg must be a finite angle >= 0, got {self.rotation_max_deg}")
        if self.rotation_max_deg > 0 and self.input_kind == "rd":
            raise ValueError(f"experiment {self.name!r}: rotation_max_deg applies to point inputs only "
                             f"(rotating an RD cube would need the array's geometry); set it to 0")
        if self.rotation_max_deg > 0 and "sector" in self.model.config.features:
            raise ValueError(f"experiment {self.name!r}: rotation_max_deg cannot rotate the 'sector' feature "
                             f"(maxima of the angle spectrum over fixed sectors); drop the feature or set "
                             f"rotation_max_deg to 0")
        if not 0.0 <= self.superpose_probability <= 1.0:
            raise ValueError(f"superpose_probability must be in [0, 1], got {self.superpose_probability}")
        if self.superpose_probability > 0 and self.input_kind == "points":
            raise ValueError(f"experiment {self.name!r}: superpose_probability applies to RD cubes only "
                             f"(a point cloud of two scenes is not the union of their CFAR points); set it to 0")

    __hash__ = None          # the model overrides are a dict

    @property
    def input_kind(self) -> str:
        """``"rd"`` (cubes) or ``"points"``: what the model reads."""
        return self.model.input_kind

    def build_model(self) -> nn.Module:
        """The model with fresh weights."""
        return self.model.build()


def _legacy_model(d: dict, where: str) -> dict:
    """A config dict written before the model registry (a ``fftradnet:`` or ``pillars:`` section
    with the whole model config) with its model as a variant and the fields that differ from it.

    The variant is the experiment's name where that is a variant of the same family, else the
    family's full-size variant; the overrides make the resolved config the stored one exactly.
    """
    d = dict(d)
    sections = {k: d.pop(k) for k in ("fftradnet", "pillars") if k in d}
    given = {k: v for k, v in sections.items() if v is not None}
    if len(given) != 1:
        raise ValueError(f"{where}: an experiment written before the model registry needs exactly one of "
                         f"'fftradnet' and 'pillars', got {sorted(given) or 'neither'}")
    family, stored = next(iter(given.items()))
    if not isinstance(stored, dict):
        raise ValueError(f"{where}: {family}: expected a mapping of model config fields, got {type(stored).__name__}")
    name = d.get("name")
    variant = name if isinstance(name, str) and name in MODELS and name.startswith(
        "fftradnet" if family == "fftradnet" else ("pointpillars", "spectralpillars", "pillars")) \
        else ("fftradnet" if family == "fftradnet" else "pointpillars")
    base = to_dict(ModelSpec(variant).config)
    unknown = sorted(set(stored) - set(base))
    if unknown:
        raise ValueError(f"{where}: {family}: unknown keys {unknown} (known: {sorted(base)})")
    d["model"] = {"variant": variant, "overrides": {k: v for k, v in stored.items() if base[k] != v}}
    return d


def experiment_from_dict(d: Any, *, where: str = "experiment") -> ExperimentConfig:
    """The :class:`ExperimentConfig` of a plain dict (a YAML file's or a run key's ``experiment``);
    a dict written before the model registry is read as :func:`_legacy_model` says.

    Raises
    ------
    ValueError
        Not a mapping, unknown or missing keys, or values a config refuses; the message starts
        with ``where``.
    """
    if isinstance(d, dict) and "model" not in d and ("fftradnet" in d or "pillars" in d):
        d = _legacy_model(d, where)
    return from_dict(ExperimentConfig, d, where=where)


REQUIRED_SECTIONS = ("name", "model", "train")
"""Keys an experiment YAML must give: what it is called, what it trains and for how long."""


def load_experiment(path: str | os.PathLike, *, notice: Callable[[str], None] | None = None) -> ExperimentConfig:
    """Read an experiment YAML (strict safe loading: :func:`radarpc.config.load_yaml_mapping`;
    unknown keys, values of the wrong type and bad values name the file and the field).

    Parameters
    ----------
    path : path-like
    notice : callable, optional
        Told, in one line, which sections the file leaves out and so take their defaults.

    Raises
    ------
    ValueError
        The file is not a valid experiment config, or lacks one of :data:`REQUIRED_SECTIONS`.
    """
    d = load_yaml_mapping(path)
    missing = [k for k in REQUIRED_SECTIONS
               if k not in d and not (k == "model" and ("fftradnet" in d or "pillars" in d))]
    if missing:
        raise ValueError(f"{path}: no {', '.join(repr(k) for k in missing)} (an experiment config names its "
                         f"{', '.join(REQUIRED_SECTIONS)}; see configs/)")
    cfg = experiment_from_dict(d, where=str(path))
    # the sections that change what a run learns; the scalar switches' defaults are all "off"
    left_out = [k for k in ("difficult", "targets", "loss") if k not in d]
    if notice is not None and left_out:
        notice(f"{path}: {', '.join(left_out)} not given, so the defaults apply"
               + (" (difficult: true, every label trains and scores)" if "difficult" in left_out else ""))
    return cfg


def canonical_key(stored: dict, *, num_workers: int | None = None) -> dict:
    """A stored run key read through the config types: fields added since it was written take
    their defaults and a pre-registry model section its registry form, so that it compares equal
    to the key the same run has today.

    ``num_workers`` replaces the stored ``train.num_workers``: loader processes do not change what a
    run computes (each item is a function of its index and the epoch), so a run may resume with
    another count.
    """
    if not isinstance(stored, dict) or not isinstance(stored.get("experiment"), dict):
        return stored
    try:
        cfg = experiment_from_dict(stored["experiment"], where="run.json: experiment")
    except ValueError:
        return stored                        # not readable: compared raw, and refused as different
    if num_workers is not None:
        cfg = with_train(cfg, num_workers=num_workers)
    return {**stored, "experiment": to_dict(cfg)}


def with_train(cfg: ExperimentConfig, **changes: Any) -> ExperimentConfig:
    """``cfg`` with fields of its :class:`TrainConfig` replaced."""
    return dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, **changes))
