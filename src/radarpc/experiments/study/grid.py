"""A study as a grid of runs: arms (a model on one kind of input) x densities x seeds.

Both study kinds become one :class:`Grid` (:func:`density_sweep_grid`, :func:`ablation_grid`),
which :func:`radarpc.experiments.study.runner.run_grid` trains, scores and records. A run is
identified by its :attr:`GridRun.id`, ``density-XXX/ARM/seedN`` (``XXX`` the density in per mille,
``057`` for 5.7 %) or ``dense/ARM/seedN`` for a density-free run: its run folder under the study's
output, and the name of its result row.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from radarpc.config import to_dict
from radarpc.experiments.radial_detection.config import ExperimentConfig, with_train
from radarpc.experiments.study.config import (AblationConfig, Budget, ConversionSpec, DataSpec, DensitySweepConfig,
                                              EvaluationSpec, ModelEntry)
from radarpc.models import ModelSpec

__all__ = ["INPUT_KINDS", "GROUPS", "Arm", "GridRun", "Grid", "density_folder", "density_sweep_grid", "ablation_grid",
           "study_grid"]

INPUT_KINDS = ("points", "sparse-rd", "dense")
"""What a run reads: point stores at its density, sparse-RD roots at its density, or the dense cubes."""
GROUPS = ("models", "axes", "enrichments", "rd-comparison")
"""Arms drawn and tabulated together (one figure and one table each)."""


def density_folder(density: float | None) -> str:
    """``density-XXX`` with ``XXX`` the density in per mille, at least three digits before the point
    and as many after it as the density needs (``0.057`` -> ``density-057``, ``0.0072`` ->
    ``density-007.2``, ``0.564`` -> ``density-564``); ``dense`` for None."""
    if density is None:
        return "dense"
    text = f"{density * 1000:.6g}"
    whole, _, frac = text.partition(".")
    return f"density-{whole.zfill(3)}" + (f".{frac}" if frac else "")


@dataclass(frozen=True)
class Arm:
    """One curve of a study: a model on one kind of input.

    Attributes
    ----------
    name : str
        Folder name (unique in the study).
    label : str
        Legend and table name.
    group : str
        One of :data:`GROUPS`.
    experiment : ExperimentConfig
        The detection experiment, model overrides applied, before the budget and the seed.
    input : str
        One of :data:`INPUT_KINDS`.
    enrich : tuple of str
        Enrichments of the point stores (``points``) or of the masked set (``sparse-rd``).
    """

    name: str
    label: str
    group: str
    experiment: ExperimentConfig
    input: str
    enrich: tuple[str, ...] = ()

    __hash__ = None

    def __post_init__(self) -> None:
        if self.input not in INPUT_KINDS:
            raise ValueError(f"arm {self.name!r}: input must be one of {INPUT_KINDS}, got {self.input!r}")
        if self.group not in GROUPS:
            raise ValueError(f"arm {self.name!r}: group must be one of {GROUPS}, got {self.group!r}")
        want = "points" if self.input == "points" else "rd"
        if self.experiment.input_kind != want:
            raise ValueError(f"arm {self.name!r}: {self.input} input needs a model reading {want}, "
                             f"{self.experiment.model.variant!r} reads {self.experiment.input_kind}")


@dataclass(frozen=True)
class GridRun:
    """One training run of a grid: an arm at a density (None: dense) with a seed."""

    arm: Arm
    density: float | None
    seed: int

    __hash__ = None

    @property
    def id(self) -> str:
        """``density-XXX/ARM/seedN`` (:func:`density_folder`): the run folder under the study output."""
        return f"{density_folder(self.density)}/{self.arm.name}/seed{self.seed}"

    @property
    def row_name(self) -> str:
        """The result row's file name: the id with ``__`` for ``/`` and ``.json``."""
        return self.id.replace("/", "__") + ".json"

    def experiment(self, budget: Budget) -> ExperimentConfig:
        """What this run trains: the arm's experiment with the budget's length and this seed."""
        return with_train(budget.apply(self.arm.experiment), seed=self.seed)


@dataclass(frozen=True)
class Grid:
    """Every run of a study and what they share.

    Attributes
    ----------
    kind : str
        ``"density-sweep"`` or ``"ablation"``.
    name : str
        The study's name.
    sensor : str
    data : DataSpec
    conversion : ConversionSpec
    budget : Budget
    evaluation : EvaluationSpec
    densities : tuple of float
    arms : tuple of Arm
    runs : tuple of GridRun
        In training order: seed by seed (a killed study has whole curves of the first seeds),
        within a seed the dense runs first, then density by density.
    config : dict
        The study config, resolved (recorded in every result row).
    """

    kind: str
    name: str
    sensor: str
    data: DataSpec
    conversion: ConversionSpec
    budget: Budget
    evaluation: EvaluationSpec
    densities: tuple[float, ...]
    arms: tuple[Arm, ...]
    runs: tuple[GridRun, ...]
    config: dict

    __hash__ = None


def _runs(arms: list[Arm], densities: tuple[float, ...], seeds: int) -> tuple[GridRun, ...]:
    out = []
    for seed in range(seeds):
        out += [GridRun(a, None, seed) for a in arms if a.input == "dense"]
        for d in densities:
            out += [GridRun(a, d, seed) for a in arms if a.input != "dense"]
    return tuple(out)


def _arm(entry: ModelEntry, group: str, label: str | None = None, dense: bool = False) -> Arm:
    kind = "dense" if dense else ("points" if entry.input_kind == "points" else "sparse-rd")
    cfg = entry.resolved()
    # overrides as the fields that differ from the variant: two arms that build the same model
    # (the axis arm +Ae+d and the enrichment arm "none") are the same run, with the same key
    cfg = dataclasses.replace(cfg, model=ModelSpec.matching(cfg.model.variant, cfg.model.config))
    return Arm(entry.name, label or entry.name, group, cfg, kind, tuple(entry.enrich))


def _grid(kind: str, cfg: Any, arms: list[Arm]) -> Grid:
    return Grid(kind, cfg.name, cfg.sensor, cfg.data, cfg.conversion, cfg.budget, cfg.evaluation, cfg.densities,
                tuple(arms), _runs(arms, cfg.densities, cfg.seeds), to_dict(cfg))


def density_sweep_grid(cfg: DensitySweepConfig) -> Grid:
    """The runs of a density sweep: each model at each density (sparse RD for an FFTRadNet), and
    the dense reference."""
    arms = [_arm(m, "models") for m in cfg.models]
    if cfg.reference is not None:
        arms.append(_arm(cfg.reference, "models", f"{cfg.reference.name} (dense)", dense=True))
    return _grid("density-sweep", cfg, arms)


def ablation_grid(cfg: AblationConfig) -> Grid:
    """The runs of the ablations: the axis arms, the enrichment arms, sparse RD against points and
    the dense benchmark."""
    arms: list[Arm] = []
    if cfg.axes is not None:
        arms += [_arm(e, "axes", label) for _, label, e in cfg.axes.entries()]
    if cfg.enrichments is not None:
        arms += [_arm(e, "enrichments", label) for _, label, e in cfg.enrichments.entries()]
    if cfg.rd_comparison is not None:
        c = cfg.rd_comparison
        arms.append(_arm(c.sparse_rd, "rd-comparison", f"{c.sparse_rd.name} (sparse RD)"))
        arms.append(_arm(c.points, "rd-comparison", f"{c.points.name} (points)"))
        if c.dense is not None:
            arms.append(_arm(c.dense, "rd-comparison", f"{c.dense.name} (dense)", dense=True))
    return _grid("ablation", cfg, arms)


def study_grid(cfg: DensitySweepConfig | AblationConfig) -> Grid:
    """The grid of either study kind."""
    if isinstance(cfg, DensitySweepConfig):
        return density_sweep_grid(cfg)
    if isinstance(cfg, AblationConfig):
        return ablation_grid(cfg)
    raise TypeError(f"expected a DensitySweepConfig or an AblationConfig, got {type(cfg).__name__}")
