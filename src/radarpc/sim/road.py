"""Seeded procedural road scenes for the RADIal-like radar: point scatterers that move in time.

A scene is a multi-lane road whose centre line is a circular arc of constant curvature
``kappa`` (straight when 0) starting at the world origin along ``+x`` (world frame: y left, z up,
ground at ``z = 0``). Everything on the road is placed in road coordinates ``(s, l)``: arc length
along the centre line and lateral offset (left positive), with world position

.. math::

    x = \frac{\sin \kappa s}{\kappa} - l \sin \kappa s, \qquad
    y = \frac{1 - \cos \kappa s}{\kappa} + l \cos \kappa s

and road heading ``kappa s``. The ego vehicle drives along one of its lanes (``ds/dt`` changing
linearly in time); the radar sits at its front at height ``radar_height_m``, looking along the
lane's heading, with the axes of :mod:`radarpc.sensors.radial` (x forward, y left, z up).

Content (all generated once per sequence from ``numpy.random.default_rng([seed, sequence])``):

* vehicles (cars, trucks) in every lane at constant speed (one speed per lane, so they never
  collide; ego-lane traffic is ahead and faster than the ego), each an extended set of
  scatterers: rear and front faces, sides, four strong corners, and wheels whose rim points
  rotate, so that the wheels spread in Doppler (micro-Doppler, rim speed 0 .. 2 v);
* guard rails (points every ``guard_rail_spacing_m`` and stronger posts), lamp poles, building
  facades behind a sidewalk, weak road-surface clutter, pedestrians (swinging legs) and cyclists;
* occlusion: a scatterer whose line of sight crosses another vehicle's footprint is attenuated by
  ``occlusion_loss_db`` (radar sees partly under and around cars); faces pointing away from the
  radar are not seen.

Radial velocities are those of the motion relative to the radar (``<p, v_obj - v_radar> / |p|``),
so static clutter has ``-v_ego cos(az) cos(el)``. Frames at ``t = i * frame_period_s`` are
consistent in time: world velocities are the time derivatives of world positions
(``ds/dt (1 - kappa l)`` along the road heading).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

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
]

CAR = 0
"""``VehicleTruth.kind`` of a car."""
TRUCK = 1
"""``VehicleTruth.kind`` of a truck."""


@dataclass(frozen=True)
class RoadSceneConfig:
    """Parameters of the procedural road scenes (ranges are ``(low, high)`` of uniform draws)."""

    frame_period_s: float = 0.1                        # time between frames
    radar_height_m: float = 0.8                        # radar above the ground
    lane_width_m: float = 3.5
    lanes_same: tuple[int, int] = (1, 3)               # lanes in the ego direction (inclusive)
    lanes_opposite: tuple[int, int] = (0, 2)           # oncoming lanes (inclusive)
    straight_prob: float = 0.4                         # probability of a straight road
    curvature_1pm: tuple[float, float] = (-1 / 150, 1 / 150)  # else uniform curvature (1/m, left +)
    ego_speed_mps: tuple[float, float] = (0.0, 20.0)   # ego speed at t = 0
    ego_accel_mps2: tuple[float, float] = (-0.6, 0.6)  # constant ego acceleration
    lane_speed_mps: tuple[float, float] = (4.0, 25.0)  # speed of the traffic of a lane
    vehicle_gap_m: tuple[float, float] = (12.0, 90.0)  # free gap between consecutive vehicles
    truck_fraction: float = 0.15                       # probability that a vehicle is a truck
    car_size_m: tuple[tuple[float, float], ...] = ((3.9, 4.9), (1.7, 1.95), (1.4, 1.65))  # L, W, H
    truck_size_m: tuple[tuple[float, float], ...] = ((7.5, 12.0), (2.4, 2.55), (3.0, 3.8))
    guard_rail_prob: float = 0.7                       # per road side
    guard_rail_spacing_m: float = 2.0
    pole_spacing_m: tuple[float, float] = (20.0, 40.0)
    building_prob: float = 0.6                         # per road side
    building_setback_m: tuple[float, float] = (6.0, 14.0)
    clutter_per_100m: float = 40.0                     # weak road-surface scatterers
    pedestrians: tuple[int, int] = (0, 4)
    cyclists: tuple[int, int] = (0, 2)
    occlusion_loss_db: float = 15.0                    # attenuation of a scatterer hidden by a vehicle
    min_range_m: float = 1.0                           # closer scatterers are dropped

    def __post_init__(self) -> None:
        if not self.frame_period_s > 0:
            raise ValueError(f"frame_period_s must be > 0, got {self.frame_period_s}")
        if not self.lane_width_m > 0:
            raise ValueError(f"lane_width_m must be > 0, got {self.lane_width_m}")
        if self.lanes_same[0] < 1 or self.lanes_same[1] < self.lanes_same[0]:
            raise ValueError(f"lanes_same must be (low >= 1, high >= low), got {self.lanes_same}")
        if self.lanes_opposite[0] < 0 or self.lanes_opposite[1] < self.lanes_opposite[0]:
            raise ValueError(f"lanes_opposite must be (low >= 0, high >= low), got {self.lanes_opposite}")
        for name in ("truck_fraction", "guard_rail_prob", "building_prob", "straight_prob"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {p}")
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
    """

    curvature_1pm: float
    radar_xy: tuple[float, float]
    radar_heading_rad: float
    bounds_m: tuple[float, float]

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
        return (lat >= self.bounds_m[0]) & (lat <= self.bounds_m[1])


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
    """

    ids: np.ndarray
    kind: np.ndarray
    center_xyz: np.ndarray
    size_lwh: np.ndarray
    yaw_rad: np.ndarray
    velocity_xy: np.ndarray
    rel_velocity_xy: np.ndarray
    visible_fraction: np.ndarray

    def __len__(self) -> int:
        return int(self.ids.shape[0])

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
        occlusion.
    owner : Tensor int64 ``(N,)``
        Vehicle id of each scatterer (index into the sequence's vehicles), ``-1`` for anything else.
    vehicles : VehicleTruth
        Every vehicle of the sequence at this time (labels select those in the field of view).
    road : RoadGeometry
        The road surface, for the freespace mask.
    ego_speed_mps : float
    radar_height_m : float
    """

    time_s: float
    scatterers: Scatterers
    owner: torch.Tensor
    vehicles: VehicleTruth
    road: RoadGeometry
    ego_speed_mps: float
    radar_height_m: float


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

    @classmethod
    def of_one(cls, local, normal, rcs, kind, amp, omega, phase0) -> "_Body":
        """The scatterers of a single body (owner 0) from per-scatterer sequences."""
        local = np.asarray(local, float).reshape(-1, 3)
        n = local.shape[0]
        return cls(owner=np.zeros(n, np.int64), local=local, normal=np.asarray(normal, float).reshape(n, 2),
                   rcs=np.asarray(rcs, float).reshape(n), kind=np.asarray(kind, np.int64).reshape(n),
                   amp=np.asarray(amp, float).reshape(n), omega=np.asarray(omega, float).reshape(n),
                   phase0=np.asarray(phase0, float).reshape(n))

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
                   phase0=np.concatenate([b.phase0 for b in bodies]))


@dataclass(frozen=True)
class _VehicleSpawn:
    """A vehicle placed on the road at t = 0 (road coordinates)."""

    s0: float                              # arc length of the footprint centre, m
    l: float                               # lateral offset, m (left positive)
    yaw: float                             # 0 = along the road, pi = oncoming
    speed: float                           # m/s along its heading
    size: tuple[float, float, float]       # length, width, height, m
    kind: int                              # CAR or TRUCK


@dataclass(frozen=True)
class _PersonSpawn:
    """A pedestrian or cyclist on a sidewalk at t = 0."""

    s0: float                              # arc length, m
    l: float                               # lateral offset, m
    vs: float                              # speed along the road, m/s (signed)


def _vehicle_template(rng: np.random.Generator, length: float, width: float, height: float,
                      truck: bool, speed: float) -> _Body:
    """Scatterers of one vehicle in its body frame (origin: footprint centre on the ground)."""
    hl, hw = length / 2, width / 2
    pts, nrm, rcs, kind, amp, omg, ph = [], [], [], [], [], [], []

    def add(p, n, s, k=0, a=0.0, w=0.0, f=0.0):
        pts.append(p); nrm.append(n); rcs.append(s); kind.append(k); amp.append(a); omg.append(w); ph.append(f)

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
    return _Body.of_one(pts, nrm, rcs, kind, amp, omg, ph)


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

        # ---- road and ego --------------------------------------------------------------------
        self.n_same = int(rng.integers(c.lanes_same[0], c.lanes_same[1] + 1))
        self.n_opp = int(rng.integers(c.lanes_opposite[0], c.lanes_opposite[1] + 1))
        self.kappa = 0.0 if rng.random() < c.straight_prob else float(rng.uniform(*c.curvature_1pm))
        w = c.lane_width_m
        self.road_right = -self.n_same * w                  # lateral offsets l of the road edges
        self.road_left = self.n_opp * w + (0.0 if self.n_opp else 0.5)
        ego_lane = int(rng.integers(0, self.n_same))
        self.ego_l = -(ego_lane + 0.5) * w
        self.ego_v0 = float(rng.uniform(*c.ego_speed_mps))
        a = float(rng.uniform(*c.ego_accel_mps2))
        if self.ego_v0 + a * duration < 0:                 # never drive backwards
            a = -self.ego_v0 / duration
        self.ego_a = a
        ego_s_end = self.ego_v0 * duration + 0.5 * a * duration ** 2
        s_lo, s_hi = -40.0, ego_s_end + self.max_range_m + 40.0

        # ---- vehicles -----------------------------------------------------------------------
        veh: list[_VehicleSpawn] = []
        bodies: list[_Body] = []
        lanes = [(-(k + 0.5) * w, 0.0) for k in range(self.n_same)] + \
                [((k + 0.5) * w, math.pi) for k in range(self.n_opp)]
        for y_lane, yaw in lanes:
            is_ego_lane = abs(y_lane - self.ego_l) < 1e-9
            if is_ego_lane:
                speed = self.ego_v0 + max(a, 0.0) * duration + float(rng.uniform(1.0, 6.0))
                lo = 10.0                                    # ahead of the ego, pulling away
            else:
                speed = float(rng.uniform(*c.lane_speed_mps))
                lo = s_lo
            signed = speed if yaw == 0.0 else -speed
            # cover the view over the whole sequence: shift the spawn window by the relative motion
            rel = signed - self.ego_v0
            span_lo = lo if is_ego_lane else s_lo - max(0.0, rel * duration)
            span_hi = s_hi - min(0.0, rel * duration)
            x = span_lo + float(rng.uniform(0.0, c.vehicle_gap_m[1]))
            while x < span_hi:
                truck = bool(rng.random() < c.truck_fraction)
                sz = c.truck_size_m if truck else c.car_size_m
                length, width, height = (float(rng.uniform(*r)) for r in sz)
                veh.append(_VehicleSpawn(s0=x + length / 2, l=y_lane + float(rng.uniform(-0.25, 0.25)),
                                         yaw=yaw, speed=speed, size=(length, width, height),
                                         kind=TRUCK if truck else CAR))
                bodies.append(_vehicle_template(rng, length, width, height, truck, speed))
                x += length + float(rng.uniform(*c.vehicle_gap_m))
        self.n_vehicles = len(veh)
        self.veh_s0 = np.asarray([v.s0 for v in veh], float)                 # (V,)
        self.veh_l = np.asarray([v.l for v in veh], float)
        self.veh_yaw = np.asarray([v.yaw for v in veh], float)
        self.veh_speed = np.asarray([v.speed for v in veh], float)
        self.veh_size = np.asarray([v.size for v in veh], float).reshape(-1, 3)  # (V, 3)
        self.veh_kind = np.asarray([v.kind for v in veh], np.int64)

        # ---- people (sidewalks) ---------------------------------------------------------------
        ppl: list[_PersonSpawn] = []
        n_ped = int(rng.integers(c.pedestrians[0], c.pedestrians[1] + 1))
        n_cyc = int(rng.integers(c.cyclists[0], c.cyclists[1] + 1))
        for k in range(n_ped + n_cyc):
            cyc = k >= n_ped
            side = 1.0 if rng.random() < 0.5 else -1.0
            edge = self.road_left if side > 0 else self.road_right
            lat = edge + side * float(rng.uniform(2.0, 4.5))          # draw order kept: l, s0, speed, sign
            s_at = float(rng.uniform(5.0, s_hi - 40.0))
            sp = float(rng.uniform(3.5, 7.0) if cyc else rng.uniform(0.8, 1.8))
            ppl.append(_PersonSpawn(s0=s_at, l=lat, vs=sp if rng.random() < 0.5 else -sp))
            bodies.append(_person_template(rng, cyc))
        self.ppl_s0 = np.asarray([p.s0 for p in ppl], float)
        self.ppl_l = np.asarray([p.l for p in ppl], float)
        self.ppl_vs = np.asarray([p.vs for p in ppl], float)
        self._body = _Body.stack(bodies)

        # ---- static world ---------------------------------------------------------------------
        self._static_xyz, self._static_rcs = self._static_world(rng, s_lo, s_hi)

    # ---- construction helpers -------------------------------------------------------------------
    def _static_world(self, rng: np.random.Generator, s_lo: float, s_hi: float
                      ) -> tuple[np.ndarray, np.ndarray]:
        c = self.config
        xyz, rcs = [], []
        for side in (-1.0, 1.0):
            edge = self.road_left if side > 0 else self.road_right
            if rng.random() < c.guard_rail_prob:                           # guard rail + posts
                xs = np.arange(s_lo, s_hi, c.guard_rail_spacing_m) + rng.uniform(0, c.guard_rail_spacing_m)
                y = edge + side * 1.0
                xyz.append(np.stack([xs, np.full_like(xs, y), np.full_like(xs, 0.6)], 1))
                r = rng.uniform(0.1, 0.5, xs.size)
                r[::2] *= 4.0                                              # posts every other point
                rcs.append(r)
            xs = np.arange(s_lo + rng.uniform(0, 20), s_hi, rng.uniform(*c.pole_spacing_m))   # poles
            y = edge + side * rng.uniform(1.8, 3.0)
            xyz.append(np.stack([xs, np.full_like(xs, y), np.full_like(xs, 1.0)], 1))
            rcs.append(rng.uniform(2.0, 6.0, xs.size))
            if rng.random() < c.building_prob:                             # facades with gaps
                setback = rng.uniform(*c.building_setback_m)
                xs = np.arange(s_lo, s_hi, 1.5)
                keep = np.sin(xs / rng.uniform(8, 20) + rng.uniform(0, 6)) > -0.4
                xs = xs[keep]
                y = edge + side * (setback + rng.uniform(-0.3, 0.3, xs.size))
                z = rng.uniform(0.5, 3.0, xs.size)
                xyz.append(np.stack([xs, y, z], 1))
                rcs.append(rng.lognormal(np.log(1.0), 1.0, xs.size))
            # curb: weak, dense
            xs = np.arange(s_lo, s_hi, 3.0) + rng.uniform(0, 3.0)
            xyz.append(np.stack([xs, np.full_like(xs, edge + side * 0.3), np.full_like(xs, 0.1)], 1))
            rcs.append(rng.uniform(0.01, 0.05, xs.size))
        n_cl = rng.poisson(c.clutter_per_100m * (s_hi - s_lo) / 100.0)          # road surface
        xs = rng.uniform(s_lo, s_hi, n_cl)
        ys = rng.uniform(self.road_right, self.road_left, n_cl)
        xyz.append(np.stack([xs, ys, np.zeros(n_cl)], 1))
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
        s_dot = np.concatenate([np.where(np.cos(self.veh_yaw) >= 0, 1.0, -1.0) * self.veh_speed, self.ppl_vs])
        s = np.concatenate([self.veh_s0, self.ppl_s0]) + s_dot * t
        l = np.concatenate([self.veh_l, self.ppl_l])
        pos, th, vel = self._along_road(s, l, s_dot)
        yaw = th + np.where(s_dot >= 0, 0.0, math.pi)
        return pos.reshape(-1, 2), yaw, vel.reshape(-1, 2)

    def frame_time(self, index: int) -> float:
        """Time of frame ``index``: ``index * frame_period_s``."""
        return int(index) * self.config.frame_period_s

    def frame(self, t: float) -> RoadFrame:
        """Scatterers, vehicle ground truth and road geometry at time ``t`` (seconds)."""
        if not math.isfinite(t):
            raise ValueError(f"frame time must be finite, got {t}")
        c = self.config
        radar, heading, v_radar_xy, v_ego = self.ego_state(t)
        v_radar = np.array([v_radar_xy[0], v_radar_xy[1], 0.0])
        ch, sh = math.cos(heading), math.sin(heading)

        def radar_axes(v):  # world vectors (N, 2 or 3) -> radar axes (rotation by -heading)
            out = v.copy()
            out[:, 0] = ch * v[:, 0] + sh * v[:, 1]
            out[:, 1] = -sh * v[:, 0] + ch * v[:, 1]
            return out

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
        to_radar = radar[None, :2] - dyn_xyz[:, :2]
        dist = np.linalg.norm(to_radar, axis=1).clip(1e-6)
        cos_inc = (n_world * to_radar).sum(1) / dist
        has_normal = np.abs(b.normal).sum(1) > 0
        facing = ~has_normal | (cos_inc > 0.05)
        dyn_rcs = b.rcs * np.where(has_normal, np.clip(cos_inc, 0.0, 1.0) ** 0.5, 1.0)
        dyn_owner = np.where(b.owner < self.n_vehicles, b.owner, -1)

        xyz = radar_axes(np.concatenate([self._static_xyz, dyn_xyz[facing]]) - radar[None, :])
        velo = radar_axes(np.concatenate([np.zeros_like(self._static_xyz), dyn_vel[facing]]) - v_radar[None, :])
        rcs = np.concatenate([self._static_rcs, dyn_rcs[facing]])
        owner = np.concatenate([np.full(len(self._static_rcs), -1, np.int64), dyn_owner[facing]])

        # vehicles in the radar frame
        vpos = radar_axes(pos[: self.n_vehicles] - radar[None, :2])
        centre = np.concatenate([vpos, np.full((self.n_vehicles, 1), -c.radar_height_m)], 1)
        truth_vel = radar_axes(vel[: self.n_vehicles])
        truth_yaw = np.angle(np.exp(1j * (yaw[: self.n_vehicles] - heading)))        # wrapped to (-pi, pi]

        # field of view: ahead, within range
        rng_ = np.linalg.norm(xyz, axis=1)
        keep = (xyz[:, 0] > 0.0) & (rng_ >= c.min_range_m) & (rng_ < self.max_range_m - self.margin_m)
        xyz, velo, rcs, owner = xyz[keep], velo[keep], rcs[keep], owner[keep]

        # occlusion by other vehicles' footprints
        hidden = self._hidden(xyz[:, :2], owner, centre[:, :2], truth_yaw, self.veh_size)
        rcs = rcs * np.where(hidden, 10 ** (-c.occlusion_loss_db / 10), 1.0)
        visible_fraction = np.ones(self.n_vehicles)
        if self.n_vehicles:
            tot = np.bincount(owner[owner >= 0], minlength=self.n_vehicles)
            vis = np.bincount(owner[(owner >= 0) & ~hidden], minlength=self.n_vehicles)
            visible_fraction = np.where(tot > 0, vis / np.maximum(tot, 1), 0.0)

        truth = VehicleTruth(
            ids=np.arange(self.n_vehicles, dtype=np.int64), kind=self.veh_kind.copy(),
            center_xyz=centre, size_lwh=self.veh_size.copy(), yaw_rad=truth_yaw,
            velocity_xy=truth_vel, rel_velocity_xy=truth_vel - radar_axes(v_radar[None, :2]),
            visible_fraction=visible_fraction)
        sc = Scatterers.from_xyz(torch.from_numpy(xyz), torch.from_numpy(velo), torch.from_numpy(rcs))
        return RoadFrame(time_s=float(t), scatterers=sc, owner=torch.from_numpy(owner), vehicles=truth,
                         road=RoadGeometry(curvature_1pm=self.kappa, radar_xy=(float(radar[0]), float(radar[1])),
                                           radar_heading_rad=float(heading),
                                           bounds_m=(float(self.road_right), float(self.road_left))),
                         ego_speed_mps=float(v_ego), radar_height_m=c.radar_height_m)

    @staticmethod
    def _hidden(p: np.ndarray, owner: np.ndarray, centres: np.ndarray, yaw: np.ndarray,
                size: np.ndarray) -> np.ndarray:
        """``(N,)`` True where the segment radar -> ``p`` crosses another vehicle's footprint."""
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
