"""Scene presets of the RADIal simulator (city, countryside, highway) and their mix.

Each preset is a :class:`radarpc.sim.road.RoadSceneConfig`; a :class:`SceneMix` gives each
sequence one preset with the mix's weights. The default mix has RADIal's proportions (its
statistics figure: city 31 %, countryside 32 %, highway 38 % of frames).

The presets of a run are a stratified draw rather than independent ones: sequence ``q`` gets
the preset whose share of ``[0, 1)`` (in the mix's order) holds ``u_q = frac(u_0 + q g)``, with
``g = (sqrt 5 - 1) / 2`` and ``u_0`` drawn from ``default_rng([seed, SCENE_MIX_STREAM])``. The
golden-ratio sequence fills ``[0, 1)`` evenly, so any run's first ``N`` sequences hold each preset
within 2.5 sequences of its share (seed 0, 6 sequences: 2 / 2 / 2; 30: 9 / 10 / 11), where
independent draws would leave a small run's mix far from RADIal's (the per-preset traffic differs
two-fold, and so would the run's statistics). A sequence's preset still depends on
``(seed, sequence)`` only, not on the run's size.

The traffic statistics in the presets' notes count labelled vehicles (those
:func:`radarpc.sim.radial_labels.labelled_vehicles` keeps for the full-size ``radial`` sensor,
+-75 deg). "Measured" is over 4,000 frames (sequences 0..99 of 10 frames, seeds 0..3); the
"stated range" is what a seeded batch of 120 frames must give (frames 0, 3, 6, 9 of sequences
0..29, seed 0: ``tests/sim/test_scenes.py``), wide enough for the batch's sampling spread.
Mixed in the default proportions the presets give 1.36 labelled vehicles per frame, 31 % of
frames without one, 6 % of the labelled vehicles parked (3,000 frames: sequences 0..299 of 10
frames, seed 0). Traffic is sparse and lasts a sequence, so a run of few sequences scatters
widely around that (6 sequences: about +-0.5 vehicles per frame).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Sequence

import numpy as np

from radarpc.config import from_dict
from radarpc.sim.road import RoadSceneConfig

__all__ = [
    "CITY",
    "COUNTRYSIDE",
    "HIGHWAY",
    "SCENE_PRESETS",
    "SceneMix",
    "DEFAULT_MIX",
    "SCENE_MIX_STREAM",
    "scene_mix",
]

CITY = RoadSceneConfig(
    name="city", lane_width_m=3.2, lanes_same=(1, 2), lanes_opposite=(1, 1), straight_prob=0.7,
    curvature_1pm=(-1 / 80, 1 / 80), ego_speed_mps=(0.0, 14.0), ego_accel_mps2=(-1.0, 1.0),
    lane_speed_mps=(5.0, 14.0), traffic_per_km=(1.0, 3.5), min_gap_m=6.0, truck_fraction=0.06,
    parking_prob=0.25, parking_row_m=(10.0, 30.0), parking_occupancy=(0.3, 0.8),
    intersection_prob=0.3, intersection_ahead_m=(15.0, 60.0), red_prob=0.5, queue_vehicles=(0, 2),
    cross_speed_mps=(5.0, 12.0), cross_traffic_per_km=(3.0, 12.0), turn_prob=0.6,
    guard_rail_prob=0.0, pole_spacing_m=(20.0, 35.0), building_prob=0.9, building_setback_m=(3.0, 6.0),
    trees_per_100m=2.0, tree_setback_m=(1.0, 3.0), clutter_per_100m=40.0,
    pedestrians=(1, 6), cyclists=(0, 2))
"""City streets: one or two lanes each way, parked rows, intersections, facades, pedestrians.

Measured: 2.0 labelled vehicles per frame, 27 % of frames without one; of the labelled
vehicles 21 % parked, 33 % stopped or queued, 5 % trucks; 370 scatterers per frame.
Stated range: 1.3..2.6 vehicles per frame, 10..45 % empty frames, 10..40 % parked, 15..55 %
stopped or queued, <= 15 % trucks.
"""

COUNTRYSIDE = RoadSceneConfig(
    name="countryside", lane_width_m=3.3, lanes_same=(1, 1), lanes_opposite=(1, 1), straight_prob=0.4,
    curvature_1pm=(-1 / 150, 1 / 150), ego_speed_mps=(12.0, 24.0), ego_accel_mps2=(-0.6, 0.6),
    lane_speed_mps=(12.0, 25.0), traffic_per_km=(3.0, 7.0), min_gap_m=15.0, truck_fraction=0.12,
    guard_rail_prob=0.2, pole_spacing_m=(40.0, 80.0), building_prob=0.1, building_setback_m=(8.0, 20.0),
    trees_per_100m=6.0, tree_setback_m=(2.0, 12.0), field_clutter_per_100m=50.0, field_depth_m=(3.0, 40.0),
    clutter_per_100m=30.0, pedestrians=(0, 1), cyclists=(0, 1))
"""Country roads: one lane each way, moderate speed, trees and fields (diffuse clutter).

Measured: 0.87 labelled vehicles per frame, 39 % of frames without one, 13 % trucks, all
moving; 300 scatterers per frame.
Stated range: 0.5..1.2 vehicles per frame, 25..60 % empty frames, 5..35 % trucks, none parked,
stopped or queued.
"""

HIGHWAY = RoadSceneConfig(
    name="highway", lane_width_m=3.6, lanes_same=(2, 3), lanes_opposite=(2, 3), median_m=4.0,
    median_rail=True, straight_prob=0.5, curvature_1pm=(-1 / 600, 1 / 600), ego_speed_mps=(22.0, 33.0),
    ego_accel_mps2=(-0.5, 0.5), lane_speed_mps=(22.0, 36.0), traffic_per_km=(1.5, 3.5), min_gap_m=25.0,
    truck_fraction=0.3, guard_rail_prob=1.0, guard_rail_spacing_m=3.0, pole_spacing_m=(50.0, 100.0),
    building_prob=0.0, clutter_per_100m=25.0, pedestrians=(0, 0), cyclists=(0, 0))
"""Highways: two or three lanes per carriageway, guard rails on both sides and in the median,
high speeds, many trucks.

Measured: 1.15 labelled vehicles per frame, 34 % of frames without one, 33 % trucks, all
moving; 285 scatterers per frame.
Stated range: 0.8..1.8 vehicles per frame, 15..50 % empty frames, 15..50 % trucks, none parked,
stopped or queued.
"""

SCENE_PRESETS: dict[str, RoadSceneConfig] = {"city": CITY, "countryside": COUNTRYSIDE, "highway": HIGHWAY}
"""The presets by name (the choices of ``radarpc simulate radial --scenes``)."""

SCENE_MIX_STREAM = 0x5CE4E
"""Second word of the seed of the mix's offset, ``default_rng([seed, SCENE_MIX_STREAM])``: a
stream of its own, apart from the scenes' ``default_rng([seed, sequence])``."""
_GOLDEN = (5 ** 0.5 - 1) / 2


@dataclass(frozen=True)
class SceneMix:
    """Presets and the share of sequences each gets.

    Parameters
    ----------
    presets : tuple of RoadSceneConfig
        Distinct names.
    weights : tuple of float
        Relative shares (> 0; normalised by their sum).
    """

    presets: tuple[RoadSceneConfig, ...]
    weights: tuple[float, ...]

    def __post_init__(self) -> None:
        if not self.presets or len(self.presets) != len(self.weights):
            raise ValueError(f"a scene mix needs one weight per preset (at least one), got "
                             f"{len(self.presets)} presets and {len(self.weights)} weights")
        names = [p.name for p in self.presets]
        if len(set(names)) != len(names):
            raise ValueError(f"scene mix preset names must be distinct, got {names}")
        if not all(np.isfinite(w) and w > 0 for w in self.weights):
            raise ValueError(f"scene mix weights must be finite and > 0, got {self.weights}")

    @classmethod
    def single(cls, preset: RoadSceneConfig) -> "SceneMix":
        """Every sequence of ``preset``."""
        return cls((preset,), (1.0,))

    def preset(self, seed: int, sequence: int) -> RoadSceneConfig:
        """The preset of ``sequence`` of a run seeded ``seed`` (stratified: see the module notes)."""
        if len(self.presets) == 1:
            return self.presets[0]
        cum = np.cumsum(self.weights) / float(np.sum(self.weights))
        u0 = np.random.default_rng([int(seed), SCENE_MIX_STREAM]).random()
        u = (u0 + int(sequence) * _GOLDEN) % 1.0
        return self.presets[min(int(np.searchsorted(cum, u, side="right")), len(self.presets) - 1)]

    def to_dict(self) -> dict:
        """JSON-able: ``{"mix": {name: weight}, "presets": {name: config fields}}``."""
        return {"mix": {p.name: float(w) for p, w in zip(self.presets, self.weights)},
                "presets": {p.name: asdict(p) for p in self.presets}}

    @classmethod
    def from_dict(cls, d: dict, where: str = "scene mix") -> "SceneMix":
        """Inverse of :meth:`to_dict` (the ``scene.json`` of a simulated root).

        Raises
        ------
        ValueError
            ``d`` lacks ``mix`` or ``presets``, their names differ, or a preset's fields are not
            :class:`RoadSceneConfig`'s; the message starts with ``where``.
        """
        if not isinstance(d, dict) or not isinstance(d.get("mix"), dict) or not isinstance(d.get("presets"), dict):
            raise ValueError(f"{where}: expected {{'mix': {{name: weight}}, 'presets': {{name: fields}}}}, "
                             f"got {type(d).__name__} with keys {sorted(d) if isinstance(d, dict) else []}")
        if list(d["mix"]) != list(d["presets"]):
            raise ValueError(f"{where}: the mix names {list(d['mix'])} differ from the presets' {list(d['presets'])}")
        presets = tuple(from_dict(RoadSceneConfig, d["presets"][name], where=f"{where}: preset {name!r}")
                        for name in d["mix"])
        return cls(presets, tuple(float(w) for w in d["mix"].values()))


DEFAULT_MIX = SceneMix((CITY, COUNTRYSIDE, HIGHWAY), (0.31, 0.32, 0.38))
"""RADIal's proportions of frames (its figure: 31 / 32 / 38 %, normalised)."""


def scene_mix(names: str | Sequence[str]) -> SceneMix:
    """The default mix restricted to the named presets (their relative weights kept).

    Parameters
    ----------
    names : str or sequence of str
        Preset names, or one comma-separated string of them (e.g. ``"city,highway"``).

    Raises
    ------
    ValueError
        An unknown or repeated name, or none; the message lists the known names.
    """
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",")]
    names = list(names)
    known = ", ".join(SCENE_PRESETS)
    bad = [n for n in names if n not in SCENE_PRESETS]
    if not names or bad:
        raise ValueError(f"unknown scene preset(s) {', '.join(map(repr, bad)) or '(none given)'}: expected "
                         f"comma-separated names from {known}")
    if len(set(names)) != len(names):
        raise ValueError(f"scene presets named twice in {','.join(names)}: expected distinct names from {known}")
    weight = dict(zip((p.name for p in DEFAULT_MIX.presets), DEFAULT_MIX.weights))
    return SceneMix(tuple(SCENE_PRESETS[n] for n in names), tuple(weight[n] for n in names))
