"""Seeded procedural road scenes for the RADIal-like radar: point scatterers that move in time.

A scene is a multi-lane road whose centre line is a circular arc of constant curvature
``kappa`` (straight when 0) starting at the world origin along ``+x`` (world frame: y left, z up,
ground at ``z = 0``). Everything on the road is placed in road coordinates ``(s, l)``: arc length
along the centre line and lateral offset (left positive), with world position

.. math::

    x = \frac{\sin \kappa s}{\kappa} - l \sin \kappa s, \qquad
    y = \frac{1 - \cos \kappa s}{\kappa} + l \cos \kappa s

and road heading ``kappa s``. Traffic keeps to the right: the ego direction's lanes lie at
``l < 0``, the oncoming ones at ``l > median_m``. The ego vehicle drives along one of its lanes
(``ds/dt`` changing linearly in time); the radar sits at its front at height ``radar_height_m``,
looking along the lane's heading, with the axes of :mod:`radarpc.sensors.radial` (x forward, y
left, z up).

Content (all generated once per sequence from ``numpy.random.default_rng([seed, sequence])``;
the presets of :mod:`radarpc.sim.scenes` set the amounts):

* moving vehicles (cars, trucks): per lane a Poisson stream (``traffic_per_km``, at least
  ``min_gap_m`` apart) at one speed per lane, so they never collide; ego-lane traffic is ahead
  and faster than the ego;
* parked cars (:data:`PARKED`) in parking rows along the kerb, zero ground speed;
* intersections (straight roads only): a perpendicular cross street. At a red light for the
  main road the ego stands (speed 0) behind a queue: the first vehicle at the stop line is
  :data:`STOPPED`, those behind it :data:`QUEUED`, in every approach lane of both directions,
  while cross traffic passes. At a green light the cross street's approaches hold stopped and
  queued vehicles and a vehicle of the rightmost lane may turn right into the cross street
  along a quarter circle;
* every vehicle is an extended set of scatterers: rear and front faces, sides, four strong
  corners, wheels whose rim points rotate (micro-Doppler, rim speed 0 .. 2 v), and under-body
  points (axles, exhaust) that the radar reaches only via the ground;
* guard rails (points every ``guard_rail_spacing_m`` and stronger posts; a median rail between
  separated carriageways), lamp poles, building facades behind a sidewalk, trees and diffuse
  field clutter, weak road-surface clutter, pedestrians (swinging legs) and cyclists;
* multipath (:mod:`radarpc.sim.multipath`): ground bounce of every vehicle and person
  scatterer, under-body returns, mirror ghosts of vehicles' strong scatterers (``rcs >=
  ghost_min_rcs_m2``) off guard rails (up to 1 m high) and facades, where the wall exists at
  the specular point. Static clutter gets no ground-bounce paths: they lie within ``2 h z / d`` of
  its range at nearly its Doppler, so they mostly rescale its (random) RCS, and leaving them out
  keeps the scatterer count (the synthesis cost) near 300 a frame;
* occlusion: a scatterer whose line of sight crosses another vehicle's footprint is attenuated by
  ``occlusion_loss_db`` (radar sees partly under and around cars); faces pointing away from the
  radar are not seen.

Radial velocities are those of the motion relative to the radar (``<p, v_obj - v_radar> / |p|``),
so static clutter has ``-v_ego cos(az) cos(el)``. Frames at ``t = i * frame_period_s`` are
consistent in time: world velocities are the time derivatives of world positions
(``ds/dt (1 - kappa l)`` along the road heading; along their tracks for crossing and turning
vehicles).

Scatterer owners (:attr:`RoadFrame.owner`): the vehicle's index for its direct, ground-bounce
and under-body returns, ``-1`` for static clutter and people, :data:`GHOST_OWNER` for mirror
ghosts (which belong to no vehicle: labels and visibility ignore them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from radarpc.sim.multipath import (
    bistatic_fields,
    ground_image,
    mirror_through_line,
    path_fields,
)
from radarpc.sim.rd import Scatterers

__all__ = [
    "RoadSceneConfig",
    "RoadGeometry",
    "VehicleTruth",
    "RoadFrame",
    "RoadScene",
    "footprint_crossings",
    "road_to_world",
    "CAR",
    "TRUCK",
    "KIND_NAMES",
    "MOVING",
    "STOPPED",
    "QUEUED",
    "PARKED",
    "STATE_NAMES",
    "GHOST_OWNER",
    "PATH_NAMES",
]

CAR = 0
"""``VehicleTruth.kind`` of a car."""
TRUCK = 1
"""``VehicleTruth.kind`` of a truck."""
KIND_NAMES: tuple[str, ...] = ("car", "truck")
"""Names of the ``VehicleTruth.kind`` codes."""
MOVING = 0
"""``VehicleTruth.state``: driving."""
STOPPED = 1
"""``VehicleTruth.state``: standing in a traffic lane first at a stop line."""
QUEUED = 2
"""``VehicleTruth.state``: standing in a traffic lane behind another standing vehicle."""
PARKED = 3
"""``VehicleTruth.state``: standing in a parking row at the kerb."""
STATE_NAMES: tuple[str, ...] = ("moving", "stopped", "queued", "parked")
"""Names of the ``VehicleTruth.state`` codes."""
GHOST_OWNER = -2
"""``RoadFrame.owner`` of a mirror ghost (a vehicle seen via a wall): no vehicle's return."""

PATH_NAMES: tuple[str, ...] = ("direct", "ground_bistatic", "ground_double", "underbody", "wall_double",
                               "wall_bistatic")
"""Names of the :attr:`RoadFrame.path` codes: the direct return; out direct and back via the
ground (or the reverse); out and back via the ground; an under-body return (via the ground both
ways); out and back via a wall (the mirror ghost); out direct and back via a wall (or the reverse).
See :mod:`radarpc.sim.multipath`."""

_PARKING_SLOT_M = 6.0              # kerb length per parking place
_CROSSWALK_M = 3.0                 # stop line to the cross street's edge
_RAIL_TOP_M = 1.0                  # guard rails reflect scatterers up to this height


@dataclass(frozen=True)
class RoadSceneConfig:
    """Parameters of a kind of procedural road scene (ranges are ``(low, high)`` of uniform draws).

    The presets :data:`radarpc.sim.scenes.CITY`, ``COUNTRYSIDE`` and ``HIGHWAY`` are instances;
    the defaults here are a generic two-way road with moving traffic only.
    """

    name: str = "road"                                 # the scene kind, written per frame
    frame_period_s: float = 0.1                        # time between frames
    radar_height_m: float = 0.8                        # radar above the ground
    lane_width_m: float = 3.5
    lanes_same: tuple[int, int] = (1, 3)               # lanes in the ego direction (inclusive)
    lanes_opposite: tuple[int, int] = (0, 2)           # oncoming lanes (inclusive)
    median_m: float = 0.0                              # gap between the two carriageways
    median_rail: bool = False                          # a guard rail in the middle of the median
    straight_prob: float = 0.4                         # probability of a straight road
    curvature_1pm: tuple[float, float] = (-1 / 150, 1 / 150)  # else uniform curvature (1/m, left +)
    ego_speed_mps: tuple[float, float] = (0.0, 20.0)   # ego speed at t = 0
    ego_accel_mps2: tuple[float, float] = (-0.6, 0.6)  # constant ego acceleration
    lane_speed_mps: tuple[float, float] = (4.0, 25.0)  # speed of the traffic of a lane
    traffic_per_km: tuple[float, float] = (5.0, 25.0)  # moving vehicles per km and lane (per sequence)
    min_gap_m: float = 10.0                            # least free gap between moving vehicles
    truck_fraction: float = 0.15                       # probability that a vehicle is a truck
    car_size_m: tuple[tuple[float, float], ...] = ((3.9, 4.9), (1.7, 1.95), (1.4, 1.65))  # L, W, H
    truck_size_m: tuple[tuple[float, float], ...] = ((7.5, 12.0), (2.4, 2.55), (3.0, 3.8))
    parking_prob: float = 0.0                          # per road side: a parking row along the kerb
    parking_row_m: tuple[float, float] = (20.0, 60.0)  # length of a parking row
    parking_occupancy: tuple[float, float] = (0.5, 0.9)  # share of its places taken
    parking_lane_width_m: float = 2.2
    intersection_prob: float = 0.0                     # a cross street (the road is then straight)
    intersection_ahead_m: tuple[float, float] = (15.0, 60.0)  # ego to the cross street's edge (green)
    red_prob: float = 0.5                              # the main road waits at the intersection
    queue_vehicles: tuple[int, int] = (0, 3)           # standing vehicles per approach lane
    cross_speed_mps: tuple[float, float] = (5.0, 12.0)  # cross traffic (red for the main road)
    cross_traffic_per_km: tuple[float, float] = (10.0, 40.0)  # per cross-street lane
    turn_prob: float = 0.0                             # green: a vehicle turns right ahead
    guard_rail_prob: float = 0.7                       # per road side
    guard_rail_spacing_m: float = 2.0
    pole_spacing_m: tuple[float, float] = (20.0, 40.0)
    building_prob: float = 0.6                         # per road side
    building_setback_m: tuple[float, float] = (6.0, 14.0)
    trees_per_100m: float = 0.0                        # per road side
    tree_setback_m: tuple[float, float] = (2.0, 12.0)
    field_clutter_per_100m: float = 0.0                # diffuse field / vegetation points per side
    field_depth_m: tuple[float, float] = (3.0, 40.0)   # their distance beyond the road edge
    clutter_per_100m: float = 40.0                     # weak road-surface scatterers
    pedestrians: tuple[int, int] = (0, 4)
    cyclists: tuple[int, int] = (0, 2)
    occlusion_loss_db: float = 15.0                    # attenuation of a scatterer hidden by a vehicle
    ground_reflection_db: float = -6.0                 # power loss of one bounce off the road
    rail_reflection_db: float = -4.0                   # ... off a guard rail
    facade_reflection_db: float = -8.0                 # ... off a facade
    ghost_min_rcs_m2: float = 1.0                      # vehicle scatterers this strong get wall ghosts
    underbody_rcs_m2: tuple[float, float] = (0.5, 2.0)  # under-body points, seen via the ground only
    min_range_m: float = 1.0                           # closer scatterers are dropped

    def __post_init__(self) -> None:
        if not self.name or not self.name.replace("-", "").replace("_", "").isalnum():
            raise ValueError(f"name must be a non-empty word (letters, digits, - or _), got {self.name!r}")
        if not self.frame_period_s > 0:
            raise ValueError(f"frame_period_s must be > 0, got {self.frame_period_s}")
        if not self.lane_width_m > 0:
            raise ValueError(f"lane_width_m must be > 0, got {self.lane_width_m}")
        if self.lanes_same[0] < 1 or self.lanes_same[1] < self.lanes_same[0]:
            raise ValueError(f"lanes_same must be (low >= 1, high >= low), got {self.lanes_same}")
        if self.lanes_opposite[0] < 0 or self.lanes_opposite[1] < self.lanes_opposite[0]:
            raise ValueError(f"lanes_opposite must be (low >= 0, high >= low), got {self.lanes_opposite}")
        if self.queue_vehicles[0] < 0 or self.queue_vehicles[1] < self.queue_vehicles[0]:
            raise ValueError(f"queue_vehicles must be (low >= 0, high >= low), got {self.queue_vehicles}")
        for name in ("truck_fraction", "guard_rail_prob", "building_prob", "straight_prob", "parking_prob",
                     "intersection_prob", "red_prob", "turn_prob"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {p}")
        for name in ("traffic_per_km", "cross_traffic_per_km", "parking_occupancy", "lane_speed_mps",
                     "ego_speed_mps", "cross_speed_mps"):
            lo, hi = getattr(self, name)
            if not 0.0 <= lo <= hi:
                raise ValueError(f"{name} must be (low >= 0, high >= low), got {getattr(self, name)}")
        if not 0.0 <= self.parking_occupancy[1] <= 1.0:
            raise ValueError(f"parking_occupancy must lie in [0, 1], got {self.parking_occupancy}")
        for name in ("min_gap_m", "median_m", "trees_per_100m", "field_clutter_per_100m", "clutter_per_100m"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("ground_reflection_db", "rail_reflection_db", "facade_reflection_db"):
            if not getattr(self, name) <= 0:
                raise ValueError(f"{name} must be <= 0 dB (a loss), got {getattr(self, name)}")
        if max(abs(k) for k in self.curvature_1pm) > 1 / 50:
            raise ValueError(f"curvature_1pm={self.curvature_1pm} must stay within +-1/50 per metre")


def road_to_world(kappa: float, s: np.ndarray, l: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World ``(..., 2)`` positions and road headings ``(...)`` of road coordinates ``(s, l)``.

    Numerically stable for ``kappa -> 0``: ``sin(k s) / k = s sinc(k s / pi)`` and
    ``(1 - cos(k s)) / k = (k s^2 / 2) sinc(k s / 2 pi)^2``.
    """
    s, l = np.broadcast_arrays(np.asarray(s, float), np.asarray(l, float))
    th = kappa * s
    a = s * np.sinc(th / np.pi)
    b = 0.5 * kappa * s * s * np.sinc(th / (2 * np.pi)) ** 2
    return np.stack([a - l * np.sin(th), b + l * np.cos(th)], -1), th


@dataclass(frozen=True)
class RoadGeometry:
    """The road of one frame as the radar sees it.

    Attributes
    ----------
    curvature_1pm : float
        Curvature of the centre line (1/m, left positive; 0 = straight).
    radar_xy : (float, float)
        World position of the radar.
    radar_heading_rad : float
        World heading of the radar x axis.
    bounds_m : (float, float)
        Lateral offsets ``(right, left)`` of the drivable surface's edges from the centre line.
    crossing_m : (float, float) or None
        A cross street of a straight road: world ``x`` of its centre line and its half width.
    median_m : (float, float) or None
        Lateral offsets ``(right, left)`` of a non-drivable median strip between the carriageways.
    """

    curvature_1pm: float
    radar_xy: tuple[float, float]
    radar_heading_rad: float
    bounds_m: tuple[float, float]
    crossing_m: tuple[float, float] | None = None
    median_m: tuple[float, float] | None = None

    def to_world(self, xy: np.ndarray) -> np.ndarray:
        """Radar-frame ground points ``(..., 2)`` to world coordinates."""
        c, s = math.cos(self.radar_heading_rad), math.sin(self.radar_heading_rad)
        xy = np.asarray(xy, float)
        return np.stack([c * xy[..., 0] - s * xy[..., 1] + self.radar_xy[0],
                         s * xy[..., 0] + c * xy[..., 1] + self.radar_xy[1]], -1)

    def lateral_m(self, xy: np.ndarray) -> np.ndarray:
        """Lateral offset ``l`` from the centre line of radar-frame ground points ``(..., 2)``."""
        w = self.to_world(xy)
        k = self.curvature_1pm
        if k == 0.0:
            return w[..., 1]
        return 1.0 / k - math.copysign(1.0, k) * np.hypot(w[..., 0], w[..., 1] - 1.0 / k)

    def on_road(self, xy: np.ndarray) -> np.ndarray:
        """Boolean: the radar-frame ground points lie on the drivable surface."""
        lat = self.lateral_m(xy)
        out = (lat >= self.bounds_m[0]) & (lat <= self.bounds_m[1])
        if self.median_m is not None:
            out &= (lat <= self.median_m[0]) | (lat >= self.median_m[1])
        if self.crossing_m is not None:
            out |= np.abs(self.to_world(xy)[..., 0] - self.crossing_m[0]) <= self.crossing_m[1]
        return out


@dataclass
class VehicleTruth:
    """Ground truth of the vehicles of one frame, in the radar frame (``V`` vehicles, numpy).

    Attributes
    ----------
    ids : int64 ``(V,)``           vehicle index in the sequence (stable over frames)
    kind : int64 ``(V,)``          :data:`CAR` or :data:`TRUCK`
    center_xyz : float64 ``(V, 3)`` centre of the footprint on the ground, radar frame
    size_lwh : float64 ``(V, 3)``  length (along heading), width, height
    yaw_rad : float64 ``(V,)``     heading in the radar frame, 0 = radar +x, left positive
    velocity_xy : float64 ``(V, 2)`` ground velocity over the ground, in radar-frame axes
    rel_velocity_xy : float64 ``(V, 2)`` velocity relative to the radar, in radar-frame axes
    visible_fraction : float64 ``(V,)`` share of its radar-facing scatterers not hidden by others
    state : int64 ``(V,)``         :data:`MOVING`, :data:`STOPPED`, :data:`QUEUED` or
        :data:`PARKED`; when not given, MOVING above 0.1 m/s ground speed, else STOPPED
    """

    ids: np.ndarray
    kind: np.ndarray
    center_xyz: np.ndarray
    size_lwh: np.ndarray
    yaw_rad: np.ndarray
    velocity_xy: np.ndarray
    rel_velocity_xy: np.ndarray
    visible_fraction: np.ndarray
    state: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.state is None:
            speed = np.hypot(self.velocity_xy[:, 0], self.velocity_xy[:, 1])
            self.state = np.where(speed > 0.1, MOVING, STOPPED).astype(np.int64)

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def ground_speed_mps(self) -> np.ndarray:
        """Speed over the ground ``(V,)``."""
        return np.hypot(self.velocity_xy[:, 0], self.velocity_xy[:, 1])

    def corners_xy(self) -> np.ndarray:
        """Footprint corners ``(V, 4, 2)`` in the radar frame (rear-right, front-right, front-left,
        rear-left)."""
        hl, hw = self.size_lwh[:, 0] / 2, self.size_lwh[:, 1] / 2
        local = np.stack([np.stack([-hl, -hw], -1), np.stack([hl, -hw], -1),
                          np.stack([hl, hw], -1), np.stack([-hl, hw], -1)], 1)     # (V, 4, 2)
        c, s = np.cos(self.yaw_rad)[:, None], np.sin(self.yaw_rad)[:, None]
        x = c * local[..., 0] - s * local[..., 1] + self.center_xyz[:, None, 0]
        y = s * local[..., 0] + c * local[..., 1] + self.center_xyz[:, None, 1]
        return np.stack([x, y], -1)


@dataclass
class RoadFrame:
    """One frame of a road scene.

    Attributes
    ----------
    time_s : float
    scatterers : Scatterers
        float64 on the CPU, radar frame, already culled to the field of view and attenuated by
        occlusion; multipath included.
    owner : Tensor int64 ``(N,)``
        Vehicle id of each scatterer (index into the sequence's vehicles), ``-1`` for static
        clutter and people, :data:`GHOST_OWNER` for mirror ghosts.
    vehicles : VehicleTruth
        Every vehicle of the sequence at this time (labels select those in the field of view).
    road : RoadGeometry
        The road surface, for the freespace mask.
    ego_speed_mps : float
    radar_height_m : float
    scene : str
        The scene kind (:attr:`RoadSceneConfig.name`).
    path : Tensor int64 ``(N,)`` or None
        The propagation path of each scatterer, an index into :data:`PATH_NAMES`.
    """

    time_s: float
    scatterers: Scatterers
    owner: torch.Tensor
    vehicles: VehicleTruth
    road: RoadGeometry
    ego_speed_mps: float
    radar_height_m: float
    scene: str = "road"
    path: torch.Tensor | None = None


@dataclass
class _Body:
    """Scatterers rigidly attached to moving bodies (vehicles, people), body frame."""

    owner: np.ndarray          # (K,) body index
    local: np.ndarray          # (K, 3) position in the body frame (x forward, y left, z up)
    normal: np.ndarray         # (K, 2) outward normal in the body xy plane; (0, 0) = always visible
    rcs: np.ndarray            # (K,)
    # periodic motion: displacement a * (cos(phase(t)), 0, sin(phase(t))) in the body x-z plane with
    # phase(t) = phase0 - omega * t (wheel rim: a = radius, omega = speed / radius), or a swing
    # a * sin(omega t + phase0) along x (legs: kind 2); kind 0 = rigid.
    kind: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    amp: np.ndarray = field(default_factory=lambda: np.zeros(0))
    omega: np.ndarray = field(default_factory=lambda: np.zeros(0))
    phase0: np.ndarray = field(default_factory=lambda: np.zeros(0))
    under: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # seen via the ground only

    @classmethod
    def of_one(cls, local, normal, rcs, kind, amp, omega, phase0, under=None) -> "_Body":
        """The scatterers of a single body (owner 0) from per-scatterer sequences."""
        local = np.asarray(local, float).reshape(-1, 3)
        n = local.shape[0]
        return cls(owner=np.zeros(n, np.int64), local=local, normal=np.asarray(normal, float).reshape(n, 2),
                   rcs=np.asarray(rcs, float).reshape(n), kind=np.asarray(kind, np.int64).reshape(n),
                   amp=np.asarray(amp, float).reshape(n), omega=np.asarray(omega, float).reshape(n),
                   phase0=np.asarray(phase0, float).reshape(n),
                   under=np.zeros(n, bool) if under is None else np.asarray(under, bool).reshape(n))

    @classmethod
    def stack(cls, bodies: "list[_Body]") -> "_Body":
        """Concatenate bodies; body ``i`` of the list becomes owner ``i``."""
        if not bodies:
            return cls.of_one(np.zeros((0, 3)), np.zeros((0, 2)), [], [], [], [], [])
        owner = np.concatenate([np.full(len(b.rcs), i, np.int64) for i, b in enumerate(bodies)])
        return cls(owner=owner,
                   local=np.concatenate([b.local for b in bodies]),
                   normal=np.concatenate([b.normal for b in bodies]),
                   rcs=np.concatenate([b.rcs for b in bodies]),
                   kind=np.concatenate([b.kind for b in bodies]),
                   amp=np.concatenate([b.amp for b in bodies]),
                   omega=np.concatenate([b.omega for b in bodies]),
                   phase0=np.concatenate([b.phase0 for b in bodies]),
                   under=np.concatenate([b.under for b in bodies]))


@dataclass(frozen=True)
class _VehicleSpawn:
    """A vehicle at t = 0: in road coordinates (lane traffic, standing vehicles) or on a track.

    A track (crossing and turning traffic, straight roads only) starts at world ``track_xy``
    with heading ``yaw``, runs straight for ``track_straight_m``, then along an arc of curvature
    ``track_kappa`` for ``track_arc_m``, then straight on.
    """

    s0: float                              # arc length of the footprint centre, m
    l: float                               # lateral offset, m (left positive)
    yaw: float                             # 0 = along the road, pi = oncoming (track: world heading)
    speed: float                           # m/s along its heading
    size: tuple[float, float, float]       # length, width, height, m
    kind: int                              # CAR or TRUCK
    state: int = MOVING
    track_xy: tuple[float, float] | None = None
    track_straight_m: float = math.inf
    track_kappa: float = 0.0
    track_arc_m: float = 0.0


@dataclass(frozen=True)
class _PersonSpawn:
    """A pedestrian or cyclist on a sidewalk at t = 0."""

    s0: float                              # arc length, m
    l: float                               # lateral offset, m
    vs: float                              # speed along the road, m/s (signed)


@dataclass(frozen=True)
class _Wall:
    """A reflecting wall along the road at lateral offset ``l``, present around samples ``s``."""

    l: float
    s: np.ndarray                          # sorted arc lengths where the wall exists
    reach_m: float                         # the wall covers s within this of a sample
    loss_db: float
    max_height_m: float                    # reflects scatterers up to this height

    def covers(self, s: np.ndarray) -> np.ndarray:
        i = np.clip(np.searchsorted(self.s, s), 1, max(len(self.s) - 1, 1))
        if len(self.s) == 0:
            return np.zeros(np.shape(s), bool)
        d = np.minimum(np.abs(s - self.s[i - 1]), np.abs(s - self.s[np.minimum(i, len(self.s) - 1)]))
        return d <= self.reach_m


def _vehicle_template(rng: np.random.Generator, length: float, width: float, height: float,
                      truck: bool, speed: float, under_rcs: tuple[float, float]) -> _Body:
    """Scatterers of one vehicle in its body frame (origin: footprint centre on the ground)."""
    hl, hw = length / 2, width / 2
    pts, nrm, rcs, kind, amp, omg, ph, und = [], [], [], [], [], [], [], []

    def add(p, n, s, k=0, a=0.0, w=0.0, f=0.0, u=False):
        pts.append(p); nrm.append(n); rcs.append(s); kind.append(k); amp.append(a); omg.append(w); ph.append(f)
        und.append(u)

    bumper_z = 0.5 if not truck else 0.9
    for sign, nx in ((-1.0, -1.0), (1.0, 1.0)):                         # rear, front faces
        for y in np.linspace(-0.7 * hw, 0.7 * hw, 3):
            add((sign * hl, y, bumper_z), (nx, 0.0), rng.uniform(0.5, 2.5) * (3 if truck else 1))
        for y in (-0.5 * hw, 0.5 * hw):                                  # lights / plate / cab
            add((sign * hl, y, min(1.0, 0.7 * height)), (nx, 0.0), rng.uniform(0.3, 1.2) * (2 if truck else 1))
    n_side = max(2, int(length / 1.2))
    for sy in (-1.0, 1.0):                                               # sides
        for x in np.linspace(-0.8 * hl, 0.8 * hl, n_side):
            add((x, sy * hw, rng.uniform(0.4, 0.8 * height)), (0.0, sy), rng.uniform(0.1, 0.8))
    for sx in (-1.0, 1.0):                                               # corners (strong)
        for sy in (-1.0, 1.0):
            add((sx * hl, sy * hw, bumper_z), (sx / math.sqrt(2), sy / math.sqrt(2)),
                rng.uniform(2.0, 6.0) * (2 if truck else 1))
    radius = 0.33 if not truck else 0.5
    axle = hl - (0.8 if not truck else 1.3)
    omega = abs(speed) / radius
    spin = 1.0 if speed >= 0 else -1.0                                   # rolling direction
    for ax in (-axle, axle):                                             # wheels: hub + 3 rim points
        for sy in (-1.0, 1.0):
            add((ax, sy * hw, radius), (0.0, sy), rng.uniform(0.1, 0.3))
            ph0 = rng.uniform(0, 2 * math.pi)
            for k in range(3):
                add((ax, sy * hw, radius), (0.0, sy), rng.uniform(0.05, 0.15),
                    1, radius, spin * omega, ph0 + 2 * math.pi * k / 3)
    # under-body: axles / differential / exhaust at chassis height, hidden from the direct view by
    # the bumpers, lit through the gap between the body and the road (via the ground)
    for x in ((-axle, axle) if not truck else (-axle, 0.0, axle)):
        add((x, rng.uniform(-0.3, 0.3) * hw, 0.3 if not truck else 0.5), (0.0, 0.0),
            rng.uniform(*under_rcs) * (2 if truck else 1), u=True)
    return _Body.of_one(pts, nrm, rcs, kind, amp, omg, ph, und)


def _person_template(rng: np.random.Generator, cyclist: bool) -> _Body:
    """A pedestrian (torso, two swinging legs, arm) or a cyclist (rider, bike, pedalling legs)."""
    if cyclist:
        pts = [(0.0, 0.0, 1.3), (0.0, 0.0, 0.6), (0.5, 0.0, 0.35), (-0.5, 0.0, 0.35), (0.0, 0.1, 0.5), (0.0, -0.1, 0.5)]
        rcs = [0.6, 1.0, 0.2, 0.2, 0.1, 0.1]
        kind = [0, 0, 0, 0, 2, 2]
        amp = [0, 0, 0, 0, 0.15, 0.15]
        f = rng.uniform(1.0, 1.5)
    else:
        pts = [(0.0, 0.0, 1.2), (0.0, 0.1, 0.45), (0.0, -0.1, 0.45), (0.0, 0.25, 1.0)]
        rcs = [0.4, 0.12, 0.12, 0.05]
        kind = [0, 2, 2, 2]
        amp = [0, 0.3, 0.3, 0.2]
        f = rng.uniform(0.8, 1.1)
    n = len(pts)
    ph0 = rng.uniform(0, 2 * math.pi)
    phase = [ph0 + (math.pi if (k % 2) else 0.0) for k in range(n)]     # legs in antiphase
    return _Body.of_one(pts, np.zeros((n, 2)), np.asarray(rcs, float) * rng.uniform(0.7, 1.3),
                        kind, amp, np.full(n, 2 * math.pi * f), phase)


def _track_pose(xy0: np.ndarray, th0: np.ndarray, straight: np.ndarray, kappa: np.ndarray,
                arc: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World position ``(T, 2)`` and heading ``(T,)`` after travelling ``u`` along tracks
    (straight, then an arc of curvature ``kappa`` and length ``arc``, then straight)."""
    u1 = np.minimum(u, straight)                                         # may be < 0 (before t = 0)
    u2 = np.clip(u - straight, 0.0, arc)
    u3 = np.maximum(u - straight - arc, 0.0)
    d0 = np.stack([np.cos(th0), np.sin(th0)], -1)
    p = xy0 + u1[:, None] * d0
    a = u2 * np.sinc(kappa * u2 / np.pi)                                 # arc chord, heading frame
    b = 0.5 * kappa * u2 * u2 * np.sinc(kappa * u2 / (2 * np.pi)) ** 2
    p = p + a[:, None] * d0 + b[:, None] * np.stack([-d0[:, 1], d0[:, 0]], -1)
    th = th0 + kappa * u2
    return p + u3[:, None] * np.stack([np.cos(th), np.sin(th)], -1), th


class RoadScene:
    """One procedural road sequence, deterministic from ``(seed, sequence)``.

    Parameters
    ----------
    config : RoadSceneConfig
    seed, sequence : int
        The scene is drawn from ``numpy.random.default_rng([seed, sequence])``.
    n_frames : int
        Frames the sequence lasts (objects are generated to fill the view for that long).
    max_range_m : float
        Radar instrumented range; scatterers beyond ``max_range_m - margin_m`` are dropped so that
        no energy wraps around the range FFT.
    margin_m : float
        See ``max_range_m`` (default 1 m).

    Examples
    --------
    >>> scene = RoadScene(RoadSceneConfig(), seed=0, sequence=0, n_frames=10, max_range_m=103.0)
    >>> fr = scene.frame(0.3)
    >>> fr.scatterers.range_m.shape[0] > 0
    True
    """

    def __init__(self, config: RoadSceneConfig, seed: int, sequence: int, n_frames: int,
                 max_range_m: float, *, margin_m: float = 1.0) -> None:
        if int(n_frames) < 1:
            raise ValueError(f"n_frames must be >= 1, got {n_frames}")
        if not max_range_m > margin_m + config.min_range_m:
            raise ValueError(f"max_range_m={max_range_m} must exceed margin_m + min_range_m")
        if int(seed) < 0 or int(sequence) < 0:
            raise ValueError(f"seed and sequence must be >= 0, got seed={seed}, sequence={sequence}")
        self.config = config
        self.seed, self.sequence, self.n_frames = int(seed), int(sequence), int(n_frames)
        self.max_range_m = float(max_range_m)
        self.margin_m = float(margin_m)
        rng = np.random.default_rng([self.seed, self.sequence])
        c = config
        duration = self.n_frames * c.frame_period_s
        w = c.lane_width_m

        # ---- road, intersection and ego ---------------------------------------------------------
        self.n_same = int(rng.integers(c.lanes_same[0], c.lanes_same[1] + 1))
        self.n_opp = int(rng.integers(c.lanes_opposite[0], c.lanes_opposite[1] + 1))
        crossing = bool(rng.random() < c.intersection_prob)
        straight = crossing or bool(rng.random() < c.straight_prob)
        self.kappa = 0.0 if straight else float(rng.uniform(*c.curvature_1pm))
        median = c.median_m if self.n_opp else 0.0
        self.median_strip_m = (0.0, median) if median > 0 else None
        carriage = (-self.n_same * w, median + self.n_opp * w + (0.0 if self.n_opp else 0.5))
        parking = (bool(rng.random() < c.parking_prob), bool(rng.random() < c.parking_prob))
        pw = c.parking_lane_width_m
        self.road_right = carriage[0] - (pw if parking[0] else 0.0)     # lateral offsets of the edges
        self.road_left = carriage[1] + (pw if parking[1] else 0.0)
        ego_lane = int(rng.integers(0, self.n_same))
        self.ego_l = -(ego_lane + 0.5) * w
        red = crossing and bool(rng.random() < c.red_prob)
        turn = crossing and not red and bool(rng.random() < c.turn_prob)
        turn_speed = float(rng.uniform(5.0, 9.0))
        self.ego_v0 = float(rng.uniform(*c.ego_speed_mps))
        a = float(rng.uniform(*c.ego_accel_mps2))
        if red:                                            # waiting at the light
            self.ego_v0, a = 0.0, 0.0
        elif turn and ego_lane == self.n_same - 1:         # behind the turning vehicle: slower
            self.ego_v0, a = min(self.ego_v0, float(rng.uniform(0.0, turn_speed - 1.0))), min(a, 0.0)
        if self.ego_v0 + a * duration < 0:                 # never drive backwards
            a = -self.ego_v0 / duration
        self.ego_a = a
        ego_s_end = self.ego_v0 * duration + 0.5 * a * duration ** 2
        s_lo, s_hi = -40.0, ego_s_end + self.max_range_m + 40.0
        density = float(rng.uniform(*c.traffic_per_km))

        road_veh: list[_VehicleSpawn] = []
        road_bodies: list[_Body] = []
        trk_veh: list[_VehicleSpawn] = []
        trk_bodies: list[_Body] = []

        def size(allow_truck: bool = True) -> tuple[tuple[float, float, float], int]:
            truck = allow_truck and bool(rng.random() < c.truck_fraction)
            sz = c.truck_size_m if truck else c.car_size_m
            return tuple(float(rng.uniform(*r)) for r in sz), TRUCK if truck else CAR

        def add(v: _VehicleSpawn) -> None:
            body = _vehicle_template(rng, *v.size, v.kind == TRUCK, v.speed, c.underbody_rcs_m2)
            (trk_veh if v.track_xy is not None else road_veh).append(v)
            (trk_bodies if v.track_xy is not None else road_bodies).append(body)

        def flow(lo: float, hi: float, per_km: float) -> list[tuple[float, tuple, int]]:
            """Rear positions, sizes and kinds of a Poisson stream of vehicles on ``[lo, hi)``."""
            out, x = [], lo + (float(rng.exponential(1000.0 / per_km)) if per_km > 0 else math.inf)
            while x < hi:
                sz, kind = size()
                out.append((x, sz, kind))
                x += sz[0] + c.min_gap_m + float(rng.exponential(1000.0 / per_km))
            return out

        def queue(front: float, direction: float, n: int, l: float, yaw: float) -> None:
            """``n`` standing vehicles, the first with its front at ``front``, the others behind it
            (``direction``: +1 if the queue faces +s)."""
            for k in range(n):
                sz, kind = size()
                add(_VehicleSpawn(s0=front - direction * sz[0] / 2, l=l + float(rng.uniform(-0.2, 0.2)),
                                  yaw=yaw, speed=0.0, size=sz, kind=kind, state=STOPPED if k == 0 else QUEUED))
                front -= direction * (sz[0] + float(rng.uniform(1.5, 3.5)))

        # where the intersection is; in red the ego lane's queue sets the stop line
        s_x = math.inf
        if crossing:
            if red:
                n_q = int(rng.integers(c.queue_vehicles[0], c.queue_vehicles[1] + 1))
                front = float(rng.uniform(2.0, 4.0))                       # ego front (radar) at s = 0
                sizes = [size() for _ in range(n_q)]
                for k, (sz, kind) in enumerate(sizes):
                    add(_VehicleSpawn(s0=front + sz[0] / 2, l=self.ego_l + float(rng.uniform(-0.2, 0.2)),
                                      yaw=0.0, speed=0.0, size=sz, kind=kind,
                                      state=STOPPED if k == n_q - 1 else QUEUED))
                    front += sz[0] + (float(rng.uniform(1.5, 3.5)) if k < n_q - 1 else 0.0)
                near = front + float(rng.uniform(0.3, 1.5)) + _CROSSWALK_M
            else:
                near = float(rng.uniform(max(c.intersection_ahead_m[0], 25.0 if turn else 0.0),
                                         max(c.intersection_ahead_m[1], 25.0 if turn else 0.0)))
            s_x = near + w                                                  # one lane each way
        stop_near, stop_far = s_x - w - _CROSSWALK_M, s_x + w + _CROSSWALK_M

        # ---- lane traffic -------------------------------------------------------------------------
        lanes = [(-(k + 0.5) * w, 0.0) for k in range(self.n_same)] + \
                [(median + (k + 0.5) * w, math.pi) for k in range(self.n_opp)]
        turner = None
        if turn:                                           # the rightmost lane's turning vehicle
            radius = float(rng.uniform(5.0, 9.0))
            x_a = s_x - w / 2 - radius                     # the arc starts here, ends heading -y
            l_t = -(self.n_same - 0.5) * w
            sz, kind = size(allow_truck=False)
            s_t = x_a - float(rng.uniform(0.0, 0.8 * turn_speed * duration))
            if self.n_same - 1 == ego_lane:
                s_t = min(max(s_t, 10.0 + sz[0] / 2), x_a)
            turner = (s_t, sz[0])
            add(_VehicleSpawn(s0=s_t, l=l_t, yaw=0.0, speed=turn_speed, size=sz, kind=kind,
                              track_xy=(s_t, l_t), track_straight_m=x_a - s_t, track_kappa=-1.0 / radius,
                              track_arc_m=0.5 * math.pi * radius))
        for k_lane, (y_lane, yaw) in enumerate(lanes):
            same = yaw == 0.0
            is_ego_lane = abs(y_lane - self.ego_l) < 1e-9
            if red:
                if same and not is_ego_lane:
                    queue(stop_near - float(rng.uniform(0.3, 1.5)), 1.0, int(rng.integers(c.queue_vehicles[0], c.queue_vehicles[1] + 1)), y_lane, 0.0)
                elif not same:
                    queue(stop_far + float(rng.uniform(0.3, 1.5)), -1.0, int(rng.integers(c.queue_vehicles[0], c.queue_vehicles[1] + 1)), y_lane, math.pi)
            if turn and k_lane == self.n_same - 1:
                speed = turn_speed
            elif is_ego_lane:
                speed = self.ego_v0 + max(a, 0.0) * duration + float(rng.uniform(0.5, 3.0))
            else:
                speed = float(rng.uniform(*c.lane_speed_mps))
            signed = speed if same else -speed
            # cover the view over the whole sequence: shift the spawn window by the relative motion
            rel = signed - self.ego_v0
            span_lo = s_lo - max(0.0, rel * duration)
            span_hi = s_hi - min(0.0, rel * duration)
            if is_ego_lane:
                span_lo = 10.0                                 # ahead of the ego, pulling away
            if red:                                            # moving only away from the crossing
                span_lo, span_hi = (max(span_lo, stop_far + 5.0), span_hi) if same else (span_lo, stop_near - 5.0)
            for rear, sz, kind in flow(span_lo, span_hi, density):
                s0 = rear + sz[0] / 2
                if turner is not None and k_lane == self.n_same - 1 and \
                        abs(s0 - turner[0]) < (sz[0] + turner[1]) / 2 + c.min_gap_m:
                    continue
                add(_VehicleSpawn(s0=s0, l=y_lane + float(rng.uniform(-0.25, 0.25)), yaw=yaw, speed=speed,
                                  size=sz, kind=kind))

        # ---- cross street -------------------------------------------------------------------------
        if crossing:
            reach = self.max_range_m
            for direction, x_lane in ((1.0, s_x + w / 2), (-1.0, s_x - w / 2)):   # heading +y / -y
                th = direction * math.pi / 2
                if red:                                        # cross traffic passes
                    v = float(rng.uniform(*c.cross_speed_mps))
                    for rear, sz, kind in flow(-reach - v * duration, reach,
                                               float(rng.uniform(*c.cross_traffic_per_km))):
                        y0 = direction * (rear + sz[0] / 2)
                        add(_VehicleSpawn(s0=x_lane, l=y0, yaw=th, speed=v, size=sz, kind=kind,
                                          track_xy=(x_lane, y0)))
                else:                                          # waiting at their red light
                    edge = self.road_right if direction > 0 else self.road_left
                    front = edge - direction * (_CROSSWALK_M + float(rng.uniform(0.3, 1.5)))
                    for k in range(int(rng.integers(c.queue_vehicles[0], c.queue_vehicles[1] + 1))):
                        sz, kind = size()
                        y0 = front - direction * sz[0] / 2
                        add(_VehicleSpawn(s0=x_lane, l=y0, yaw=th, speed=0.0, size=sz, kind=kind,
                                          state=STOPPED if k == 0 else QUEUED, track_xy=(x_lane, y0)))
                        front -= direction * (sz[0] + float(rng.uniform(1.5, 3.5)))
            self.crossing_m: tuple[float, float] | None = (s_x, w)
        else:
            self.crossing_m = None

        # ---- parking rows ---------------------------------------------------------------------------
        occupancy = float(rng.uniform(*c.parking_occupancy))
        for side, present in ((-1.0, parking[0]), (1.0, parking[1])):
            if not present:
                continue
            length = float(rng.uniform(*c.parking_row_m))
            start = float(rng.uniform(s_lo, max(s_lo, s_hi - length)))
            l_p = (carriage[0] - pw / 2) if side < 0 else (carriage[1] + pw / 2)
            yaw = math.pi if (side > 0 and self.n_opp) else 0.0
            for slot in np.arange(start, start + length - _PARKING_SLOT_M + 1e-9, _PARKING_SLOT_M):
                taken = bool(rng.random() < occupancy)
                sz, kind = size(allow_truck=False)
                if taken and abs(slot + _PARKING_SLOT_M / 2 - s_x) > w + _CROSSWALK_M + 8.0:
                    add(_VehicleSpawn(s0=float(slot) + _PARKING_SLOT_M / 2, l=l_p + side * float(rng.uniform(-0.1, 0.2)),
                                      yaw=yaw, speed=0.0, size=sz, kind=kind, state=PARKED))

        veh = road_veh + trk_veh
        self.n_road = len(road_veh)
        self.n_vehicles = len(veh)
        self.veh_s0 = np.asarray([v.s0 for v in road_veh], float)            # (V_road,)
        self.veh_l = np.asarray([v.l for v in road_veh], float)
        self.veh_yaw = np.asarray([v.yaw for v in veh], float)              # (V,)
        self.veh_speed = np.asarray([v.speed for v in veh], float)
        self.veh_size = np.asarray([v.size for v in veh], float).reshape(-1, 3)  # (V, 3)
        self.veh_kind = np.asarray([v.kind for v in veh], np.int64)
        self.veh_state = np.asarray([v.state for v in veh], np.int64)
        self.trk_xy0 = np.asarray([v.track_xy for v in trk_veh], float).reshape(-1, 2)   # (V_track, 2)
        self.trk_straight = np.asarray([v.track_straight_m for v in trk_veh], float)
        self.trk_kappa = np.asarray([v.track_kappa for v in trk_veh], float)
        self.trk_arc = np.asarray([v.track_arc_m for v in trk_veh], float)

        # ---- people (sidewalks) ---------------------------------------------------------------
        ppl: list[_PersonSpawn] = []
        bodies = road_bodies + trk_bodies
        n_ped = int(rng.integers(c.pedestrians[0], c.pedestrians[1] + 1))
        n_cyc = int(rng.integers(c.cyclists[0], c.cyclists[1] + 1))
        for k in range(n_ped + n_cyc):
            cyc = k >= n_ped
            side = 1.0 if rng.random() < 0.5 else -1.0
            edge = self.road_left if side > 0 else self.road_right
            lat = edge + side * float(rng.uniform(2.0, 4.5))
            s_at = float(rng.uniform(5.0, s_hi - 40.0))
            sp = float(rng.uniform(3.5, 7.0) if cyc else rng.uniform(0.8, 1.8))
            ppl.append(_PersonSpawn(s0=s_at, l=lat, vs=sp if rng.random() < 0.5 else -sp))
            bodies.append(_person_template(rng, cyc))
        self.ppl_s0 = np.asarray([p.s0 for p in ppl], float)
        self.ppl_l = np.asarray([p.l for p in ppl], float)
        self.ppl_vs = np.asarray([p.vs for p in ppl], float)
        self._body = _Body.stack(bodies)

        # ---- static world ---------------------------------------------------------------------
        self._walls: list[_Wall] = []
        self._static_xyz, self._static_rcs = self._static_world(rng, s_lo, s_hi, median, s_x)

    # ---- construction helpers -------------------------------------------------------------------
    def _static_world(self, rng: np.random.Generator, s_lo: float, s_hi: float, median: float,
                      s_x: float) -> tuple[np.ndarray, np.ndarray]:
        c = self.config
        xyz, rcs = [], []
        gap = c.lane_width_m + 2.0                          # no kerb-side objects across a cross street

        def add(s, l, z, r):
            s, l, z, r = np.broadcast_arrays(np.asarray(s, float), np.asarray(l, float), np.asarray(z, float),
                                             np.asarray(r, float))
            keep = np.abs(s - s_x) > gap
            xyz.append(np.stack([s[keep], l[keep], z[keep]], 1))
            rcs.append(r[keep])

        def rail(l):
            xs = np.arange(s_lo, s_hi, c.guard_rail_spacing_m) + rng.uniform(0, c.guard_rail_spacing_m)
            r = rng.uniform(0.1, 0.5, xs.size)
            r[::2] *= 4.0                                                  # posts every other point
            add(xs, l, 0.6, r)
            self._walls.append(_Wall(l=float(l), s=xs[np.abs(xs - s_x) > gap], reach_m=c.guard_rail_spacing_m,
                                     loss_db=c.rail_reflection_db, max_height_m=_RAIL_TOP_M))

        span = s_hi - s_lo
        for side in (-1.0, 1.0):
            edge = self.road_left if side > 0 else self.road_right
            if rng.random() < c.guard_rail_prob:                           # guard rail + posts
                rail(edge + side * 1.0)
            xs = np.arange(s_lo + rng.uniform(0, 20), s_hi, rng.uniform(*c.pole_spacing_m))   # poles
            add(xs, edge + side * rng.uniform(1.8, 3.0), 1.0, rng.uniform(2.0, 6.0, xs.size))
            if rng.random() < c.building_prob:                             # facades with gaps
                setback = rng.uniform(*c.building_setback_m)
                xs = np.arange(s_lo, s_hi, 1.5)
                keep = np.sin(xs / rng.uniform(8, 20) + rng.uniform(0, 6)) > -0.4
                xs = xs[keep]
                add(xs, edge + side * (setback + rng.uniform(-0.3, 0.3, xs.size)), rng.uniform(0.5, 3.0, xs.size),
                    rng.lognormal(np.log(1.0), 1.0, xs.size))
                self._walls.append(_Wall(l=float(edge + side * setback), s=xs[np.abs(xs - s_x) > gap],
                                         reach_m=1.0, loss_db=c.facade_reflection_db, max_height_m=math.inf))
            n_tree = rng.poisson(c.trees_per_100m * span / 100.0)         # trees: trunk + canopy
            ts = rng.uniform(s_lo, s_hi, n_tree)
            tl = edge + side * rng.uniform(*c.tree_setback_m, n_tree)
            add(ts, tl, 1.0, rng.lognormal(np.log(0.8), 0.6, n_tree))
            add(ts + rng.uniform(-1.5, 1.5, n_tree), tl + rng.uniform(-1.5, 1.5, n_tree), rng.uniform(2.5, 5.0, n_tree),
                rng.uniform(0.05, 0.4, n_tree))
            n_fld = rng.poisson(c.field_clutter_per_100m * span / 100.0)   # fields: weak, diffuse
            add(rng.uniform(s_lo, s_hi, n_fld), edge + side * rng.uniform(*c.field_depth_m, n_fld),
                rng.uniform(0.0, 0.8, n_fld), rng.lognormal(np.log(0.05), 1.0, n_fld))
            # curb: weak, dense
            xs = np.arange(s_lo, s_hi, 3.0) + rng.uniform(0, 3.0)
            add(xs, edge + side * 0.3, 0.1, rng.uniform(0.01, 0.05, xs.size))
        if c.median_rail and median > 0:
            rail(median / 2)
        n_cl = rng.poisson(c.clutter_per_100m * span / 100.0)              # road surface
        xyz.append(np.stack([rng.uniform(s_lo, s_hi, n_cl), rng.uniform(self.road_right, self.road_left, n_cl),
                             np.zeros(n_cl)], 1))
        rcs.append(rng.lognormal(np.log(0.02), 1.0, n_cl))
        sl = np.concatenate(xyz)                                                 # (s, l, z)
        world, _ = road_to_world(self.kappa, sl[:, 0], sl[:, 1])
        return np.concatenate([world, sl[:, 2:]], 1), np.concatenate(rcs)

    # ---- time evolution --------------------------------------------------------------------------
    def _along_road(self, s: np.ndarray, l: np.ndarray, s_dot: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World position ``(..., 2)``, road heading and world velocity ``(..., 2)`` of points
        moving along the road at ``ds/dt = s_dot`` with fixed lateral offset ``l``."""
        pos, th = road_to_world(self.kappa, s, l)
        speed = np.asarray(s_dot, float) * (1.0 - self.kappa * np.asarray(l, float))
        return pos, th, np.stack([speed * np.cos(th), speed * np.sin(th)], -1)

    def ego_state(self, t: float) -> tuple[np.ndarray, float, np.ndarray, float]:
        """Radar pose at time ``t``: world position ``(3,)``, heading (rad), world velocity
        ``(2,)`` and speed over the ground."""
        s = self.ego_v0 * t + 0.5 * self.ego_a * t * t
        pos, th, vel = self._along_road(np.array(s), np.array(self.ego_l), np.array(self.ego_v0 + self.ego_a * t))
        return (np.array([pos[0], pos[1], self.config.radar_height_m]), float(th), vel,
                float(np.hypot(vel[0], vel[1])))

    def _body_poses(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World ground position ``(B, 2)``, yaw ``(B,)`` and velocity ``(B, 2)`` of every body."""
        nr = self.n_road
        sign = np.concatenate([np.where(np.cos(self.veh_yaw[:nr]) >= 0, 1.0, -1.0),
                               np.where(self.ppl_vs >= 0, 1.0, -1.0)])
        s_dot = np.concatenate([sign[:nr] * self.veh_speed[:nr], self.ppl_vs])
        s = np.concatenate([self.veh_s0, self.ppl_s0]) + s_dot * t
        l = np.concatenate([self.veh_l, self.ppl_l])
        pos, th, vel = self._along_road(s, l, s_dot)
        yaw = th + np.where(sign > 0, 0.0, math.pi)
        trk_speed = self.veh_speed[nr:]
        tpos, tyaw = _track_pose(self.trk_xy0, self.veh_yaw[nr:], self.trk_straight, self.trk_kappa,
                                 self.trk_arc, trk_speed * t)
        tvel = trk_speed[:, None] * np.stack([np.cos(tyaw), np.sin(tyaw)], -1)
        def order(a, b):                                                   # road, track, people
            return np.concatenate([a[:nr], b, a[nr:]])

        return order(pos.reshape(-1, 2), tpos), order(yaw, tyaw), order(vel.reshape(-1, 2), tvel)

    def _vehicle_road_coords(self, t: float, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Arc length and lateral offset ``(V,)`` of the vehicles at ``t`` (world positions ``pos``)."""
        nr = self.n_road
        s = self.veh_s0 + np.where(np.cos(self.veh_yaw[:nr]) >= 0, 1.0, -1.0) * self.veh_speed[:nr] * t
        # track vehicles exist on straight roads only, where (s, l) = (x, y)
        return (np.concatenate([s, pos[nr:self.n_vehicles, 0]]),
                np.concatenate([self.veh_l, pos[nr:self.n_vehicles, 1]]))

    def frame_time(self, index: int) -> float:
        """Time of frame ``index``: ``index * frame_period_s``."""
        return int(index) * self.config.frame_period_s

    def frame(self, t: float) -> RoadFrame:
        """Scatterers, vehicle ground truth and road geometry at time ``t`` (seconds)."""
        if not math.isfinite(t):
            raise ValueError(f"frame time must be finite, got {t}")
        c = self.config
        h = c.radar_height_m
        radar, heading, v_radar_xy, v_ego = self.ego_state(t)
        v_radar = np.array([v_radar_xy[0], v_radar_xy[1], 0.0])
        ch, sh = math.cos(heading), math.sin(heading)

        def radar_axes(v):  # world vectors (N, 2 or 3) -> radar axes (rotation by -heading)
            out = v.copy()
            out[:, 0] = ch * v[:, 0] + sh * v[:, 1]
            out[:, 1] = -sh * v[:, 0] + ch * v[:, 1]
            return out

        def aspect(p, n):  # world points and outward normals (N, 2) -> seen?, RCS factor
            to_radar = radar[None, :2] - p[:, :2]
            cos_inc = (n * to_radar).sum(1) / np.linalg.norm(to_radar, axis=1).clip(1e-6)
            has_normal = np.abs(n).sum(1) > 0
            return ~has_normal | (cos_inc > 0.05), np.where(has_normal, np.clip(cos_inc, 0.0, 1.0) ** 0.5, 1.0)

        pos, yaw, vel = self._body_poses(t)
        b = self._body
        cy, sy = np.cos(yaw[b.owner]), np.sin(yaw[b.owner])

        # periodic motion in the body frame (wheel rims rotate, legs swing)
        local = b.local.copy()
        lvel = np.zeros_like(local)
        rim = b.kind == 1
        ph = b.phase0[rim] - b.omega[rim] * t
        local[rim, 0] += b.amp[rim] * np.cos(ph)
        local[rim, 2] += b.amp[rim] * np.sin(ph)
        lvel[rim, 0] = b.amp[rim] * b.omega[rim] * np.sin(ph)
        lvel[rim, 2] = -b.amp[rim] * b.omega[rim] * np.cos(ph)
        leg = b.kind == 2
        ph = b.omega[leg] * t + b.phase0[leg]
        local[leg, 0] += b.amp[leg] * np.sin(ph)
        lvel[leg, 0] = b.amp[leg] * b.omega[leg] * np.cos(ph)

        def rot(v):  # body -> world (yaw about z)
            return np.stack([cy * v[:, 0] - sy * v[:, 1], sy * v[:, 0] + cy * v[:, 1], v[:, 2]], 1)

        dyn_xyz = rot(local) + np.concatenate([pos[b.owner], np.zeros((len(b.owner), 1))], 1)
        dyn_vel = rot(lvel) + np.concatenate([vel[b.owner], np.zeros((len(b.owner), 1))], 1)
        n_world = rot(np.concatenate([b.normal, np.zeros((len(b.owner), 1))], 1))[:, :2]
        facing, fac = aspect(dyn_xyz, n_world)
        dyn_rcs = b.rcs * fac
        dyn_owner = np.where(b.owner < self.n_vehicles, b.owner, -1)
        direct = facing & ~b.under

        # ---- mirror ghosts of vehicles off walls (world frame, then radar axes) ---------------------
        g_xyz, g_vel, g_rcs, g_src, m_a, m_b, m_src, m_rcs = [], [], [], [], [], [], [], []
        strong = np.flatnonzero((dyn_owner >= 0) & ~b.under & (b.rcs >= c.ghost_min_rcs_m2))
        if strong.size and self._walls:
            s_v, l_v = self._vehicle_road_coords(t, pos)
            src = dyn_owner[strong]
            s_e = float(self.ego_v0 * t + 0.5 * self.ego_a * t * t)
            for wall in self._walls:
                same_side = np.sign(l_v[src] - wall.l) == np.sign(self.ego_l - wall.l)
                ok = same_side & (dyn_xyz[strong, 2] <= wall.max_height_m)
                if not ok.any():
                    continue
                k = strong[ok]
                q, th = road_to_world(self.kappa, s_v[src[ok]], wall.l)          # tangent line at the vehicle
                d = np.stack([np.cos(th), np.sin(th)], -1)
                gx, gv = mirror_through_line(dyn_xyz[k], dyn_vel[k], q, d)
                gn, _ = mirror_through_line(np.concatenate([n_world[k], np.zeros((k.size, 1))], 1),
                                            np.zeros((k.size, 3)), np.zeros(2), d)
                # specular point: where the line radar -> ghost crosses the wall line
                nn = np.stack([-d[:, 1], d[:, 0]], 1)
                dr = ((radar[None, :2] - q) * nn).sum(1)
                dg = ((gx[:, :2] - q) * nn).sum(1)
                spec = radar[None, :2] + (gx[:, :2] - radar[None, :2]) * (dr / (dr - dg))[:, None]
                s_spec = s_v[src[ok]] + ((spec - q) * d).sum(1)
                seen, fac_g = aspect(gx, gn[:, :2])
                keep = wall.covers(s_spec) & seen & (s_spec > s_e)
                rho2 = 10.0 ** (wall.loss_db / 10.0)                             # |Gamma|^2
                g_xyz.append(gx[keep]); g_vel.append(gv[keep]); g_src.append(dyn_owner[k][keep])
                g_rcs.append(b.rcs[k][keep] * fac_g[keep] * rho2 ** 2)           # out and back via the wall
                both = keep & facing[k]                                          # one leg direct, one via the wall
                m_a.append(np.concatenate([dyn_xyz[k][both], dyn_vel[k][both]], 1))
                m_b.append(np.concatenate([gx[both], gv[both]], 1))
                m_src.append(dyn_owner[k][both])
                m_rcs.append(b.rcs[k][both] * np.sqrt(fac[k][both] * fac_g[both]) * 4.0 * rho2)

        def cat(parts, *shape):
            return np.concatenate(parts) if parts else np.zeros((0, *shape))

        def rel(p, v):  # world points and velocities -> radar frame, relative to the radar
            return radar_axes(p - radar[None, :]), radar_axes(v - v_radar[None, :])

        # groups of paths: (r, az, el, v_r), rcs, owner, line-of-sight point for occlusion, the
        # vehicle that does not occlude it (its own), direct path of a vehicle?
        groups = []

        def group(f, rcs, owner, los, own, kind):
            groups.append((f, rcs, owner, los, own, np.full(len(rcs), PATH_NAMES.index(kind), np.int64)))

        s_xyz, s_vel = rel(self._static_xyz, np.zeros_like(self._static_xyz))
        group(path_fields(s_xyz, s_vel), self._static_rcs, np.full(len(self._static_rcs), -1, np.int64),
              s_xyz[:, :2], np.full(len(self._static_rcs), -1, np.int64), "direct")
        d_xyz, d_vel = rel(dyn_xyz[direct], dyn_vel[direct])
        d_rcs, d_own = dyn_rcs[direct], dyn_owner[direct]
        group(path_fields(d_xyz, d_vel), d_rcs, d_own, d_xyz[:, :2], d_own, "direct")
        # ground bounce of the bodies' direct scatterers; under-body returns via the ground only
        gamma2 = 10.0 ** (c.ground_reflection_db / 10.0)                          # |Gamma|^2
        img, vimg = ground_image(d_xyz, d_vel, h)
        group(bistatic_fields(d_xyz, d_vel, img, vimg), d_rcs * 4.0 * gamma2, d_own, d_xyz[:, :2], d_own,
              "ground_bistatic")
        group(path_fields(img, vimg), d_rcs * gamma2 ** 2, d_own, d_xyz[:, :2], d_own, "ground_double")
        u_xyz, u_vel = rel(dyn_xyz[b.under], dyn_vel[b.under])
        u_img, u_vimg = ground_image(u_xyz, u_vel, h)
        u_own = dyn_owner[b.under]
        group(path_fields(u_img, u_vimg), dyn_rcs[b.under] * gamma2 ** 2, u_own, u_xyz[:, :2], u_own, "underbody")
        # wall ghosts: no vehicle's return
        gh_xyz, gh_vel = rel(cat(g_xyz, 3), cat(g_vel, 3))
        gh_src = cat(g_src).astype(np.int64)
        group(path_fields(gh_xyz, gh_vel), cat(g_rcs), np.full(len(gh_src), GHOST_OWNER, np.int64),
              gh_xyz[:, :2], gh_src, "wall_double")
        ma, mb = cat(m_a, 6), cat(m_b, 6)
        ma_xyz, ma_vel = rel(ma[:, :3], ma[:, 3:])
        mb_xyz, mb_vel = rel(mb[:, :3], mb[:, 3:])
        m_own = cat(m_src).astype(np.int64)
        group(bistatic_fields(ma_xyz, ma_vel, mb_xyz, mb_vel), cat(m_rcs),
              np.full(len(m_own), GHOST_OWNER, np.int64), mb_xyz[:, :2], m_own, "wall_bistatic")

        r, az, el, vr = (np.concatenate([g[0][i] for g in groups]) for i in range(4))
        rcs, owner, los, own, path = (np.concatenate([g[i] for g in groups]) for i in range(1, 6))

        # vehicles in the radar frame
        nv = self.n_vehicles
        vpos = radar_axes(pos[:nv] - radar[None, :2])
        centre = np.concatenate([vpos, np.full((nv, 1), -h)], 1)
        truth_vel = radar_axes(vel[:nv])
        truth_yaw = np.angle(np.exp(1j * (yaw[:nv] - heading)))                 # wrapped to (-pi, pi]

        # field of view: ahead, within range
        keep = (np.abs(az) < 90.0) & (r >= c.min_range_m) & (r < self.max_range_m - self.margin_m)
        r, az, el, vr, rcs, owner, los, own, path = (x[keep] for x in (r, az, el, vr, rcs, owner, los, own, path))

        # occlusion by other vehicles' footprints
        hidden = self._hidden(los, own, centre[:, :2], truth_yaw, self.veh_size)
        rcs = rcs * np.where(hidden, 10 ** (-c.occlusion_loss_db / 10), 1.0)
        visible_fraction = np.ones(nv)
        if nv:
            mine = (path == 0) & (owner >= 0)
            tot = np.bincount(owner[mine], minlength=nv)
            vis = np.bincount(owner[mine & ~hidden], minlength=nv)
            visible_fraction = np.where(tot > 0, vis / np.maximum(tot, 1), 0.0)

        truth = VehicleTruth(
            ids=np.arange(nv, dtype=np.int64), kind=self.veh_kind.copy(),
            center_xyz=centre, size_lwh=self.veh_size.copy(), yaw_rad=truth_yaw,
            velocity_xy=truth_vel, rel_velocity_xy=truth_vel - radar_axes(v_radar[None, :2]),
            visible_fraction=visible_fraction, state=self.veh_state.copy())
        t64 = lambda x: torch.from_numpy(np.ascontiguousarray(x, dtype=np.float64))
        sc = Scatterers(range_m=t64(r), azimuth_deg=t64(az), elevation_deg=t64(el), velocity_mps=t64(vr),
                        rcs_m2=t64(rcs))
        return RoadFrame(time_s=float(t), scatterers=sc, owner=torch.from_numpy(owner), vehicles=truth,
                         road=RoadGeometry(curvature_1pm=self.kappa, radar_xy=(float(radar[0]), float(radar[1])),
                                           radar_heading_rad=float(heading),
                                           bounds_m=(float(self.road_right), float(self.road_left)),
                                           crossing_m=self.crossing_m, median_m=self.median_strip_m),
                         ego_speed_mps=float(v_ego), radar_height_m=h, scene=c.name, path=torch.from_numpy(path))

    @staticmethod
    def _hidden(p: np.ndarray, owner: np.ndarray, centres: np.ndarray, yaw: np.ndarray,
                size: np.ndarray) -> np.ndarray:
        """``(N,)`` True where the segment radar -> ``p`` crosses another vehicle's footprint
        (``owner``: the vehicle each point belongs to, which does not hide it; -1 for none)."""
        n, v = p.shape[0], centres.shape[0]
        if n == 0 or v == 0:
            return np.zeros(n, bool)
        t_in, t_out = footprint_crossings(p, centres, yaw, size)              # (N, V), in units of |p|
        cross = (t_in < t_out) & (t_out > 0) & (t_in < 0.98)                  # enters before reaching p
        cross &= owner[:, None] != np.arange(v)[None, :]
        return cross.any(axis=1)


def footprint_crossings(d: np.ndarray, centres: np.ndarray, yaw: np.ndarray, size: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Where the rays ``u * d`` (``u >= 0``) from the radar enter and leave vehicle footprints.

    Slab method in each box frame, vectorised over rays and boxes.

    Parameters
    ----------
    d : ndarray ``(A, 2)``
        Ray directions in the radar xy plane (any length: ``u`` is in units of it).
    centres : ndarray ``(V, 2)``
        Footprint centres; ``yaw`` ``(V,)`` headings; ``size`` ``(V, >=2)`` length and width.

    Returns
    -------
    (t_in, t_out) : ndarray ``(A, V)`` each
        The ray meets box ``v`` iff ``t_in < t_out`` and ``t_out > 0``; ``+-inf`` when parallel.
    """
    c, s = np.cos(yaw), np.sin(yaw)                                           # (V,)
    ox = -(c * centres[:, 0] + s * centres[:, 1])                             # radar in box frames
    oy = -(-s * centres[:, 0] + c * centres[:, 1])
    dx = c[None, :] * d[:, None, 0] + s[None, :] * d[:, None, 1]              # (A, V)
    dy = -s[None, :] * d[:, None, 0] + c[None, :] * d[:, None, 1]

    def slab(o, dd, h):
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-h[None, :] - o[None, :]) / dd
            t2 = (h[None, :] - o[None, :]) / dd
        inside = np.abs(o)[None, :] <= h[None, :]
        lo = np.where(dd == 0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
        hi = np.where(dd == 0, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
        return lo, hi

    lx, hx = slab(ox, dx, size[:, 0] / 2)
    ly, hy = slab(oy, dy, size[:, 1] / 2)
    return np.maximum(lx, ly), np.minimum(hx, hy)
