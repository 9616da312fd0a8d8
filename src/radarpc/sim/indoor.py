"""Seeded indoor and outdoor scenes for the ColoRadar-format simulator, and ray casting.

A :class:`Scene` is ray-castable geometry -- yaw-oriented boxes (walls, floors, furniture,
doors, building fronts, bushes) and vertical cylinders (pillars, poles, trunks, bins, people) --
each with a :class:`Material`, plus walking people (moving cylinders) and a smooth trajectory of
the sensor rig (handheld: sway and bob; wheeled: smooth) that gives the ground-truth poses.

Scene kinds (:data:`SCENE_KINDS`): ``hallway`` (L-shaped corridor with doors, one turn),
``lab`` (room with benches, cabinets, chairs), ``classroom`` (rows of desks, whiteboard),
``large_room`` (hall with pillars and furniture), ``outdoor`` (ground, building fronts, vegetation
clutter, poles). All randomness comes from ``numpy.random.default_rng(seed)``.

World frame: z up, floor at ``z = 0``. Rig (``base``) poses are world <- base transforms; the rig's
direction of travel is its base **+y** axis, because ColoRadar's radars look along base +y
(``base_to_single_chip`` is a +90 deg yaw).

Ray casting (:func:`ray_cast`) is vectorized in torch over rays x primitives (chunked over rays)
and runs on the device of the given tensors.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from radarpc.sensors.coloradar import Transform, matrix_to_quaternion, quaternion_to_matrix

__all__ = [
    "SCENE_KINDS",
    "Material",
    "MATERIALS",
    "Person",
    "Trajectory",
    "Scene",
    "Geometry",
    "RayHits",
    "make_scene",
    "ray_cast",
    "yaw_quaternion",
]

SCENE_KINDS = ("hallway", "lab", "classroom", "large_room", "outdoor")


@dataclass(frozen=True)
class Material:
    """Surface reflectivity for radar and LiDAR."""

    name: str
    radar_diffuse: float      # diffuse radar cross-section per unit area (m^2/m^2) at normal incidence
    radar_specular: float     # peak specular gain at normal incidence (relative to diffuse term)
    specular_width_deg: float # width of the specular lobe
    lidar_reflectivity: float # LiDAR reflectivity in [0, 1]


MATERIALS: tuple[Material, ...] = (
    Material("concrete", 0.02, 3.0, 6.0, 0.45),     # 0 walls, floors
    Material("drywall", 0.01, 2.0, 6.0, 0.70),      # 1 partition walls, ceilings
    Material("wood", 0.02, 2.0, 8.0, 0.50),         # 2 doors, desks
    Material("metal", 0.05, 60.0, 3.0, 0.30),       # 3 cabinets, poles, whiteboards, frames
    Material("glass", 0.005, 20.0, 2.0, 0.08),      # 4 windows
    Material("fabric", 0.005, 0.5, 15.0, 0.35),     # 5 chairs
    Material("foliage", 0.03, 0.0, 30.0, 0.25),     # 6 bushes, canopies
    Material("human", 0.05, 4.0, 15.0, 0.40),       # 7 people
    Material("ground", 0.01, 1.0, 5.0, 0.20),       # 8 outdoor ground
)
_M = {m.name: i for i, m in enumerate(MATERIALS)}


@dataclass(frozen=True)
class Person:
    """A walking person: a vertical cylinder moving back and forth between two points."""

    start: tuple[float, float]
    end: tuple[float, float]
    speed: float              # m/s
    phase: float              # initial fraction of the round trip, in [0, 1)
    radius: float = 0.22
    height: float = 1.75

    def state(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Position ``(2,)`` and velocity ``(2,)`` at time ``t`` (s)."""
        a, b = np.asarray(self.start), np.asarray(self.end)
        length = float(np.linalg.norm(b - a))
        if length < 1e-6 or self.speed <= 0:
            return a.copy(), np.zeros(2)
        period = 2 * length / self.speed
        s = ((t / period + self.phase) % 1.0) * 2 * length
        u = (b - a) / length
        if s <= length:
            return a + u * s, u * self.speed
        return b - u * (s - length), -u * self.speed


@dataclass(frozen=True)
class Trajectory:
    """Smooth rig path: waypoints (2-D, m) followed at constant speed, with handheld sway.

    ``pose(t)`` is the world <- base transform; base +y points along the path.
    """

    waypoints: tuple[tuple[float, float], ...]
    speed: float = 1.0            # m/s along the path
    height: float = 1.0           # sensor height above the floor (m)
    handheld: bool = True         # handheld: lateral sway, vertical bob, small pitch/roll
    sway_seed: int = 0
    t0: float = 0.0               # time of the first waypoint (s)

    def _densify(self) -> tuple[np.ndarray, np.ndarray]:
        # Chaikin corner cutting -> smooth polyline; cumulative arclength
        p = np.asarray(self.waypoints, dtype=np.float64)
        for _ in range(4):
            q = 0.75 * p[:-1] + 0.25 * p[1:]
            r = 0.25 * p[:-1] + 0.75 * p[1:]
            p = np.concatenate([p[:1], np.stack([q, r], 1).reshape(-1, 2), p[-1:]])
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        return p, s

    @property
    def length(self) -> float:
        return float(self._densify()[1][-1])

    @property
    def duration(self) -> float:
        return self.length / self.speed

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """``(position (3,), quaternion (4,) qx qy qz qw)`` of the base at time ``t``."""
        p, s = self._densify()
        d = np.clip((t - self.t0) * self.speed, 0.0, s[-1])
        i = int(np.clip(np.searchsorted(s, d, side="right") - 1, 0, len(s) - 2))
        w = (d - s[i]) / max(s[i + 1] - s[i], 1e-9)
        xy = p[i] * (1 - w) + p[i + 1] * w
        # heading from a centred difference over +-0.3 m of path (smooth yaw)
        def at(dd):
            dd = np.clip(dd, 0.0, s[-1])
            j = int(np.clip(np.searchsorted(s, dd, side="right") - 1, 0, len(s) - 2))
            ww = (dd - s[j]) / max(s[j + 1] - s[j], 1e-9)
            return p[j] * (1 - ww) + p[j + 1] * ww
        tan = at(d + 0.3) - at(d - 0.3)
        heading = math.atan2(tan[1], tan[0])
        z, roll, pitch = self.height, 0.0, 0.0
        if self.handheld:
            rng = np.random.default_rng(self.sway_seed)
            f = rng.uniform(0.7, 1.1, 3)
            ph = rng.uniform(0, 2 * np.pi, 3)
            tt = t - self.t0
            lat = 0.04 * math.sin(2 * np.pi * f[0] * 0.5 * tt + ph[0])
            xy = xy + lat * np.array([-math.sin(heading), math.cos(heading)])
            z += 0.02 * math.sin(2 * np.pi * f[1] * 1.8 * tt + ph[1])
            roll = math.radians(1.5) * math.sin(2 * np.pi * f[2] * 0.5 * tt + ph[2])
            pitch = math.radians(1.0) * math.sin(2 * np.pi * f[1] * 1.8 * tt + ph[1])
        # base +y along the heading: yaw = heading - 90 deg; then small roll/pitch about base axes
        yaw = heading - math.pi / 2
        rz = quaternion_to_matrix(yaw_quaternion(yaw))
        cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
        ry = np.array([[cr, 0, sr], [0, 1, 0], [-sr, 0, cr]])       # roll about base y (travel axis)
        rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])       # pitch about base x
        r = rz @ rx @ ry
        return np.array([xy[0], xy[1], z]), matrix_to_quaternion(r)

    def transform(self, t: float) -> Transform:
        pos, q = self.pose(t)
        return Transform(tuple(float(v) for v in pos), tuple(float(v) for v in q))

    def velocity(self, t: float, dt: float = 0.02) -> np.ndarray:
        """World velocity ``(3,)`` of the base origin (central difference)."""
        return (self.pose(t + dt)[0] - self.pose(t - dt)[0]) / (2 * dt)


def yaw_quaternion(yaw: float) -> np.ndarray:
    """Quaternion ``(qx, qy, qz, qw)`` of a rotation by ``yaw`` rad about +z."""
    return np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])


@dataclass
class Geometry:
    """Torch tensors of a scene at one time, ready for :func:`ray_cast`."""

    box_center: torch.Tensor      # (B, 3)
    box_half: torch.Tensor        # (B, 3) half extents in the box frame
    box_yaw: torch.Tensor         # (B,)
    box_material: torch.Tensor    # (B,) long
    cyl_center: torch.Tensor      # (C, 2) xy of the axis
    cyl_radius: torch.Tensor      # (C,)
    cyl_z: torch.Tensor           # (C, 2) z range
    cyl_material: torch.Tensor    # (C,) long
    cyl_velocity: torch.Tensor    # (C, 3) world velocity (people); 0 for static

    @property
    def device(self) -> torch.device:
        return self.box_center.device


@dataclass
class RayHits:
    """Result of :func:`ray_cast` for ``M`` rays."""

    hit: torch.Tensor        # (M,) bool
    t: torch.Tensor          # (M,) distance along the unit ray (inf where no hit)
    point: torch.Tensor      # (M, 3)
    normal: torch.Tensor     # (M, 3) unit outward normal (zeros where no hit)
    material: torch.Tensor   # (M,) long (-1 where no hit)
    velocity: torch.Tensor   # (M, 3) world velocity of the hit surface


@dataclass
class Scene:
    """Static boxes and cylinders, walking people, a rig trajectory and a multipath plane."""

    kind: str
    seed: int
    boxes: np.ndarray                 # (B, 8): cx cy cz hx hy hz yaw material
    cylinders: np.ndarray             # (C, 6): cx cy r z0 z1 material
    people: tuple[Person, ...]
    trajectory: Trajectory
    mirror_planes: tuple[tuple[tuple[float, float, float], float], ...] = field(default_factory=tuple)
    # each mirror plane (n, c): points with n.p = c; used for multipath ghosts

    def geometry(self, t: float, device: torch.device | str | None = None,
                 dtype: torch.dtype = torch.float32) -> Geometry:
        """Geometry at time ``t``: static primitives plus people at their positions."""
        cyl = [self.cylinders]
        vel = [np.zeros((len(self.cylinders), 3))]
        for p in self.people:
            pos, v = p.state(t)
            cyl.append(np.array([[pos[0], pos[1], p.radius, 0.0, p.height, _M["human"]]]))
            vel.append(np.array([[v[0], v[1], 0.0]]))
        c = np.concatenate(cyl, 0) if cyl else np.zeros((0, 6))
        v = np.concatenate(vel, 0)
        b = self.boxes
        f = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)  # noqa: E731
        lng = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.long, device=device)  # noqa: E731
        return Geometry(f(b[:, 0:3]), f(b[:, 3:6]), f(b[:, 6]), lng(b[:, 7].astype(np.int64)),
                        f(c[:, 0:2]), f(c[:, 2]), f(c[:, 3:5]), lng(c[:, 5].astype(np.int64)), f(v))


# ------------------------------------------------------------------------------------------------
# ray casting
# ------------------------------------------------------------------------------------------------
def _slab_t(o, d, center, half, c, s, eps: float) -> torch.Tensor:
    # Entry distance of rays o + t d into yaw-oriented boxes (slab test in each box frame, axis by
    # axis), inf where missed. Arguments broadcast: o, d, center, half (..., 3); c, s = cos, sin of
    # the yaw (...). Used on (M, 1) x (1, B) grids and on gathered (P,) ray-box pairs alike.
    rx = o[..., 0] - center[..., 0]
    ry = o[..., 1] - center[..., 1]
    rz = o[..., 2] - center[..., 2]
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    loc = ((c * rx + s * ry, c * dx + s * dy), (c * ry - s * rx, c * dy - s * dx), (rz, dz))
    tmin = tmax = None
    for k, (ol, dl) in enumerate(loc):
        inv = 1.0 / torch.where(dl.abs() < 1e-12, 1e-12, dl)
        h = half[..., k]
        t1 = (-h - ol) * inv
        t2 = (h - ol) * inv
        lo, hi = torch.minimum(t1, t2), torch.maximum(t1, t2)
        tmin = lo if tmin is None else torch.maximum(tmin, lo)
        tmax = hi if tmax is None else torch.minimum(tmax, hi)
    hit = (tmax >= tmin) & (tmin > eps)
    return torch.where(hit, tmin, float("inf"))


def _cyl_t(o, d, center, radius, z01, eps: float) -> torch.Tensor:
    # Entry distance of rays into vertical cylinders (side surface), inf where missed; arguments
    # broadcast like _slab_t: center (..., 2), radius (...), z01 (..., 2).
    ox = o[..., 0] - center[..., 0]
    oy = o[..., 1] - center[..., 1]
    dx, dy = d[..., 0], d[..., 1]
    a = (dx * dx + dy * dy).clamp_min(1e-12)
    b = 2 * (ox * dx + oy * dy)
    cc = ox * ox + oy * oy - radius ** 2
    disc = b * b - 4 * a * cc
    sq = disc.clamp_min(0).sqrt()
    t = (-b - sq) / (2 * a)
    z = o[..., 2] + t * d[..., 2]
    ok = (disc >= 0) & (t > eps) & (z >= z01[..., 0]) & (z <= z01[..., 1])
    return torch.where(ok, t, float("inf"))


def _cast_boxes(o, d, g: Geometry, eps: float) -> torch.Tensor:
    # o: (M, 3) or (1, 3), d: (M, 3) -> (M, B)
    c, s = torch.cos(g.box_yaw), torch.sin(g.box_yaw)                       # (B,)
    return _slab_t(o[:, None, :], d[:, None, :], g.box_center[None], g.box_half[None], c[None], s[None], eps)


def _box_normal(p: torch.Tensor, g: Geometry, j: torch.Tensor) -> torch.Tensor:
    # outward normal of box j at surface point p: the face whose slab the point lies on
    c, s = torch.cos(g.box_yaw[j]), torch.sin(g.box_yaw[j])
    r = p - g.box_center[j]
    loc = torch.stack([c * r[:, 0] + s * r[:, 1], -s * r[:, 0] + c * r[:, 1], r[:, 2]], -1)
    q = loc / g.box_half[j]
    ax = q.abs().argmax(1)
    nl = torch.zeros_like(loc)
    nl.scatter_(1, ax[:, None], torch.sign(q.gather(1, ax[:, None])))
    return torch.stack([c * nl[:, 0] - s * nl[:, 1], s * nl[:, 0] + c * nl[:, 1], nl[:, 2]], -1)


def _cast_cylinders(o, d, g: Geometry, eps: float):
    # o: (M, 3) or (1, 3), d: (M, 3) -> (M, C)
    return _cyl_t(o[:, None, :], d[:, None, :], g.cyl_center[None], g.cyl_radius[None], g.cyl_z[None], eps)


def _subset(g: Geometry, bi: torch.Tensor, ci: torch.Tensor) -> Geometry:
    return Geometry(g.box_center[bi], g.box_half[bi], g.box_yaw[bi], g.box_material[bi],
                    g.cyl_center[ci], g.cyl_radius[ci], g.cyl_z[ci], g.cyl_material[ci], g.cyl_velocity[ci])


def _cast_chunk(oc, dc, g: Geometry, eps: float):
    m = dc.shape[0]
    best_t = torch.full((m,), float("inf"), dtype=dc.dtype, device=dc.device)
    best_n = torch.zeros((m, 3), dtype=dc.dtype, device=dc.device)
    best_m = torch.full((m,), -1, dtype=torch.long, device=dc.device)
    best_v = torch.zeros((m, 3), dtype=dc.dtype, device=dc.device)
    if g.box_center.shape[0]:
        tmin, j = _cast_boxes(oc, dc, g, eps).min(1)                         # (m,)
        nw = _box_normal(oc + tmin.clamp_max(1e9)[:, None] * dc, g, j)
        upd = tmin < best_t
        best_t = torch.where(upd, tmin, best_t)
        best_n = torch.where(upd[:, None], nw, best_n)
        best_m = torch.where(upd, g.box_material[j], best_m)
    if g.cyl_center.shape[0]:
        tc = _cast_cylinders(oc, dc, g, eps)
        tmin, j = tc.min(1)
        p = oc + tmin.clamp_max(1e9)[:, None] * dc
        nxy = (p[:, :2] - g.cyl_center[j]) / g.cyl_radius[j][:, None]
        nw = torch.cat([nxy, torch.zeros_like(nxy[:, :1])], 1)
        upd = tmin < best_t
        best_t = torch.where(upd, tmin, best_t)
        best_n = torch.where(upd[:, None], nw, best_n)
        best_m = torch.where(upd, g.cyl_material[j], best_m)
        best_v = torch.where(upd[:, None], g.cyl_velocity[j], best_v)
    return best_t, best_n, best_m, best_v


def ray_cast(geometry: Geometry, origins: torch.Tensor, directions: torch.Tensor, *,
             max_range: float = float("inf"), chunk: int = 4096, eps: float = 1e-4) -> RayHits:
    """First intersection of rays with the scene.

    With a shared origin (``origins`` of shape ``(3,)``) rays are processed in azimuth-sorted
    chunks and each chunk is tested only against primitives whose bounding sphere overlaps the
    chunk's azimuth wedge and starts within ``max_range`` (exact culling, large speed-up for wide
    scenes); origin-only terms of the slab test are then computed once per primitive.

    Parameters
    ----------
    geometry : Geometry
        From :meth:`Scene.geometry`.
    origins : torch.Tensor
        ``(M, 3)`` or ``(3,)`` (shared origin), world frame.
    directions : torch.Tensor
        ``(M, 3)`` unit vectors.
    max_range : float
        Hits farther than this are discarded.
    chunk : int
        Rays per batch (memory ~ ``chunk * (B + C) * 3`` floats).

    Returns
    -------
    RayHits
    """
    d = torch.as_tensor(directions)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions must be (M, 3), got {tuple(d.shape)}")
    o = torch.as_tensor(origins, dtype=d.dtype, device=d.device)
    shared = o.ndim == 1
    if shared and o.shape != (3,):
        raise ValueError(f"a shared origin must have shape (3,), got {tuple(o.shape)}")
    if not shared and o.shape != d.shape:
        raise ValueError(f"origins {tuple(o.shape)} must be (3,) or match directions {tuple(d.shape)}")
    if not (torch.isfinite(d).all() and torch.isfinite(o).all()):
        raise ValueError("ray origins/directions contain NaN or infinite values")
    g = geometry
    m, dev = d.shape[0], d.device
    t_all = torch.full((m,), float("inf"), dtype=d.dtype, device=dev)
    n_all = torch.zeros((m, 3), dtype=d.dtype, device=dev)
    mat_all = torch.full((m,), -1, dtype=torch.long, device=dev)
    vel_all = torch.zeros((m, 3), dtype=d.dtype, device=dev)
    if shared:
        order = torch.argsort(torch.atan2(d[:, 1], d[:, 0]))
        # bounding spheres of primitives as seen from the origin: centre azimuth, half-angle
        bc = torch.cat([g.box_center, torch.cat([g.cyl_center, g.cyl_z.mean(1, keepdim=True)], 1)], 0)
        br = torch.cat([g.box_half.norm(dim=1),
                        (g.cyl_radius ** 2 + (0.5 * (g.cyl_z[:, 1] - g.cyl_z[:, 0])) ** 2).sqrt()], 0)
        rel = bc - o
        dist_xy = rel[:, :2].norm(dim=1)
        p_az = torch.atan2(rel[:, 1], rel[:, 0])
        always = dist_xy <= br + 1e-3                         # origin above/below/inside: any azimuth
        p_half = torch.asin((br / dist_xy.clamp_min(1e-6)).clamp(max=1.0))
        # a primitive whose bounding sphere lies beyond max_range cannot give a kept hit
        in_range = rel.norm(dim=1) - br <= max_range + 1e-3
        nbox = g.box_center.shape[0]
    else:
        order = torch.arange(m, device=dev)
    for s in range(0, m, chunk):
        idx = order[s:s + chunk]
        dc = d[idx]
        oc = o[None] if shared else o[idx]                      # (1, 3) broadcasts over the chunk
        gg = g
        if shared:
            az = torch.atan2(dc[:, 1], dc[:, 0])
            a0, a1 = az.min(), az.max()
            mid, half = 0.5 * (a0 + a1), 0.5 * (a1 - a0)
            diff = torch.remainder(p_az - mid + math.pi, 2 * math.pi) - math.pi
            keep = (always | (diff.abs() <= half + p_half + 1e-4)) & in_range
            gg = _subset(g, torch.nonzero(keep[:nbox])[:, 0], torch.nonzero(keep[nbox:])[:, 0])
        bt, bn, bm, bv = _cast_chunk(oc, dc, gg, eps)
        t_all[idx], n_all[idx], mat_all[idx], vel_all[idx] = bt, bn, bm, bv
    hit = torch.isfinite(t_all) & (t_all <= max_range)
    t_all = torch.where(hit, t_all, torch.full_like(t_all, float("inf")))
    point = torch.where(hit[:, None], o + t_all.clamp_max(1e9)[:, None] * d, torch.zeros_like(d))
    n_all = torch.where(hit[:, None], n_all, torch.zeros_like(n_all))
    mat_all = torch.where(hit, mat_all, torch.full_like(mat_all, -1))
    return RayHits(hit, t_all, point, n_all, mat_all, vel_all * hit[:, None])


# ------------------------------------------------------------------------------------------------
# scene builders
# ------------------------------------------------------------------------------------------------
class _Builder:
    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.boxes: list[list[float]] = []
        self.cyls: list[list[float]] = []

    def box(self, lo, hi, material: str, yaw: float = 0.0) -> None:
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        c, h = (lo + hi) / 2, np.abs(hi - lo) / 2
        self.boxes.append([*c, *np.maximum(h, 0.005), yaw, _M[material]])

    def obox(self, center, half, yaw: float, material: str) -> None:
        self.boxes.append([*center, *half, yaw, _M[material]])

    def cyl(self, x, y, r, z0, z1, material: str) -> None:
        self.cyls.append([x, y, r, z0, z1, _M[material]])

    def table(self, x, y, w, d, h, yaw, material="wood") -> None:
        self.obox((x, y, h - 0.02), (w / 2, d / 2, 0.02), yaw, material)
        c, s = math.cos(yaw), math.sin(yaw)
        for sx in (-1, 1):
            for sy in (-1, 1):
                lx, ly = sx * (w / 2 - 0.05), sy * (d / 2 - 0.05)
                self.obox((x + c * lx - s * ly, y + s * lx + c * ly, (h - 0.04) / 2), (0.025, 0.025, (h - 0.04) / 2),
                          yaw, "metal")

    def room(self, x0, y0, x1, y1, height, wall="concrete", ceiling=True, th=0.15) -> None:
        self.box((x0 - th, y0 - th, -0.1), (x1 + th, y1 + th, 0.0), "concrete")            # floor
        if ceiling:
            self.box((x0 - th, y0 - th, height), (x1 + th, y1 + th, height + 0.1), "drywall")
        self.box((x0 - th, y0 - th, 0), (x1 + th, y0, height), wall)
        self.box((x0 - th, y1, 0), (x1 + th, y1 + th, height), wall)
        self.box((x0 - th, y0, 0), (x0, y1, height), wall)
        self.box((x1, y0, 0), (x1 + th, y1, height), wall)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        b = np.asarray(self.boxes, dtype=np.float64).reshape(-1, 8)
        c = np.asarray(self.cyls, dtype=np.float64).reshape(-1, 6)
        return b, c


def _people(rng, n, region, speed=(0.8, 1.5)) -> tuple[Person, ...]:
    (x0, y0, x1, y1) = region
    out = []
    for _ in range(n):
        a = (rng.uniform(x0, x1), rng.uniform(y0, y1))
        b = (rng.uniform(x0, x1), rng.uniform(y0, y1))
        out.append(Person(a, b, float(rng.uniform(*speed)), float(rng.uniform()),
                          radius=float(rng.uniform(0.18, 0.25)), height=float(rng.uniform(1.6, 1.9))))
    return tuple(out)


def _hallway(rng, rr) -> tuple[_Builder, Trajectory, tuple[Person, ...], tuple]:
    b = _Builder(rng)
    w = float(rng.uniform(1.8, 2.6))
    l1, l2, h = float(rng.uniform(14, 22)), float(rng.uniform(8, 14)), float(rng.uniform(2.6, 3.2))
    th = 0.15
    # floor/ceiling over the L bounding box (ray casting only sees the inside)
    b.box((-th, -w / 2 - th, -0.1), (l1 + th, w / 2 + l2 + th, 0.0), "concrete")
    b.box((-th, -w / 2 - th, h), (l1 + th, w / 2 + l2 + th, h + 0.1), "drywall")
    b.box((-th, -w / 2 - th, 0), (l1 + th, -w / 2, h), "drywall")                  # right wall, seg 1
    b.box((-th, w / 2, 0), (l1 - w, w / 2 + th, h), "drywall")                     # left wall, seg 1
    b.box((-th, -w / 2, 0), (0, w / 2, h), "concrete")                             # start wall
    b.box((l1, -w / 2, 0), (l1 + th, w / 2 + l2, h), "concrete")                   # end wall / seg 2 right
    b.box((l1 - w - th, w / 2, 0), (l1 - w, w / 2 + l2, h), "drywall")             # seg 2 left
    b.box((l1 - w - th, w / 2 + l2, 0), (l1 + th, w / 2 + l2 + th, h), "concrete")  # seg 2 end
    # doors: recessed wooden panels with metal frames along both walls of segment 1
    x = float(rng.uniform(1.5, 3.0))
    while x < l1 - w - 1.5:
        side = rng.choice([-1, 1])
        yw = side * w / 2
        b.box((x, yw - 0.03, 0), (x + 0.9, yw + 0.03, 2.1), "wood")
        b.box((x - 0.05, yw - 0.06, 0), (x, yw + 0.06, 2.15), "metal")
        b.box((x + 0.9, yw - 0.06, 0), (x + 0.95, yw + 0.06, 2.15), "metal")
        x += float(rng.uniform(2.5, 5.0))
    y = w / 2 + float(rng.uniform(1.0, 2.5))
    while y < w / 2 + l2 - 1.0:
        xw = l1 - w if rng.uniform() < 0.5 else l1
        b.box((xw - 0.03, y, 0), (xw + 0.03, y + 0.9, 2.1), "wood")
        y += float(rng.uniform(2.5, 4.5))
    # clutter: bins, radiators, a fire extinguisher cabinet, ceiling lights
    for _ in range(int(rng.integers(2, 5))):
        xx = float(rng.uniform(1, l1 - w - 1))
        side = rng.choice([-1, 1])
        b.cyl(xx, side * (w / 2 - 0.25), 0.2, 0, 0.8, "metal")
    for _ in range(int(rng.integers(2, 4))):
        xx = float(rng.uniform(1, l1 - w - 2))
        b.box((xx, -w / 2, 0.1), (xx + 1.0, -w / 2 + 0.1, 0.7), "metal")
    for xx in np.arange(1.0, l1, 2.5):
        b.box((xx, -0.3, h - 0.05), (xx + 0.6, 0.3, h), "metal")
    wps = ((0.6, float(rr.uniform(-0.3, 0.3))), (l1 - w / 2 + float(rr.uniform(-0.2, 0.2)), 0.0),
           (l1 - w / 2, w / 2 + l2 - 0.8))
    traj = Trajectory(wps if rr.uniform() < 0.5 else wps[::-1], speed=float(rr.uniform(0.9, 1.3)),
                      height=float(rr.uniform(0.9, 1.2)), handheld=True, sway_seed=int(rr.integers(1 << 30)))
    people = _people(rr, int(rr.integers(1, 3)), (1.0, -w / 2 + 0.4, l1 - w - 0.5, w / 2 - 0.4))
    mirrors = (((0.0, 0.0, 1.0), 0.0), ((0.0, 1.0, 0.0), -w / 2))
    return b, traj, people, mirrors


def _furnished_room(rng, rr, kind: str):
    b = _Builder(rng)
    if kind == "lab":
        lx, ly, h = rng.uniform(8, 11), rng.uniform(6, 8), rng.uniform(2.8, 3.2)
    elif kind == "classroom":
        lx, ly, h = rng.uniform(9, 12), rng.uniform(7, 9), rng.uniform(2.8, 3.2)
    else:  # large_room
        lx, ly, h = rng.uniform(18, 24), rng.uniform(12, 16), rng.uniform(3.5, 5.0)
    lx, ly, h = float(lx), float(ly), float(h)
    b.room(0, 0, lx, ly, h, wall="concrete" if kind == "large_room" else "drywall")
    margin = 1.6   # free band along the walls for the trajectory
    if kind == "lab":
        # benches in the middle, cabinets along the walls, chairs
        for i in range(int(rng.integers(2, 4))):
            y = margin + 0.8 + i * (ly - 2 * margin - 0.8) / 3
            b.table(lx / 2, y, float(rng.uniform(3, lx - 2 * margin - 1.5)), 0.9, 0.9, 0.0)
            for _ in range(int(rng.integers(1, 4))):
                b.box((lx / 2 + rng.uniform(-1.5, 1.5), y - 0.3, 0.9),
                      (lx / 2 + rng.uniform(-1.5, 1.5) + 0.4, y + 0.2, 0.9 + rng.uniform(0.2, 0.6)), "metal")
        for x in np.arange(0.5, lx - 1.0, float(rng.uniform(1.2, 2.0))):
            if rng.uniform() < 0.6:
                b.box((x, ly - 0.6, 0), (x + 0.9, ly, float(rng.uniform(1.0, 2.0))), "metal")
        for _ in range(int(rng.integers(4, 8))):
            b.obox((float(rng.uniform(margin, lx - margin)), float(rng.uniform(margin, ly - margin)), 0.25),
                   (0.22, 0.22, 0.25), float(rng.uniform(0, np.pi)), "fabric")
    elif kind == "classroom":
        b.box((lx * 0.25, -0.01, 0.9), (lx * 0.75, 0.03, 2.1), "metal")  # whiteboard on the front wall
        rows, cols = int(rng.integers(3, 5)), int(rng.integers(3, 5))
        for r in range(rows):
            for c in range(cols):
                x = margin + 0.6 + c * (lx - 2 * margin - 1.2) / max(cols - 1, 1)
                y = margin + 1.0 + r * (ly - 2 * margin - 1.5) / max(rows - 1, 1)
                b.table(x, y, 1.2, 0.6, 0.75, 0.0)
                b.obox((x, y + 0.5, 0.23), (0.2, 0.2, 0.23), 0.0, "fabric")
        for y in np.arange(1.0, ly - 1.0, 1.5):   # windows on one side wall
            b.box((lx - 0.02, y, 1.0), (lx, y + 1.0, 2.2), "glass")
    else:
        # pillars on a grid, a few furniture groups
        nx, ny = int(rng.integers(3, 5)), int(rng.integers(2, 4))
        square = rng.uniform() < 0.5
        for i in range(nx):
            for j in range(ny):
                x = lx * (i + 1) / (nx + 1)
                y = ly * (j + 1) / (ny + 1)
                if square:
                    b.box((x - 0.25, y - 0.25, 0), (x + 0.25, y + 0.25, h), "concrete")
                else:
                    b.cyl(x, y, 0.3, 0, h, "concrete")
        for _ in range(int(rng.integers(3, 7))):
            x, y = float(rng.uniform(margin, lx - margin)), float(rng.uniform(margin, ly - margin))
            b.table(x, y, float(rng.uniform(1.0, 2.0)), float(rng.uniform(0.6, 1.0)), 0.75, float(rng.uniform(0, np.pi)))
    inset = margin * float(rr.uniform(0.5, 0.7))
    loop = ((inset, inset), (lx - inset, inset), (lx - inset, ly - inset), (inset, ly - inset), (inset, inset + 1.0))
    k = int(rr.integers(0, 4))
    loop = loop[k:-1] + loop[:k] + (loop[k],)
    if rr.uniform() < 0.5:
        loop = loop[::-1]
    traj = Trajectory(loop, speed=float(rr.uniform(0.8, 1.2)), height=float(rr.uniform(0.9, 1.3)),
                      handheld=kind != "large_room", sway_seed=int(rr.integers(1 << 30)))
    people = _people(rr, int(rr.integers(1, 4)), (1.0, 1.0, lx - 1.0, ly - 1.0))
    mirrors = (((0.0, 0.0, 1.0), 0.0), ((1.0, 0.0, 0.0), 0.0))
    return b, traj, people, mirrors


def _outdoor(rng, rr):
    b = _Builder(rng)
    length = float(rng.uniform(40, 60))
    b.box((-10, -20, -0.1), (length + 10, 25, 0.0), "ground")
    # building fronts along y = yb, with window recesses and entrances
    yb = float(rng.uniform(6, 9))
    x = -5.0
    while x < length + 5:
        wlen = float(rng.uniform(8, 20))
        height = float(rng.uniform(6, 15))
        depth_shift = float(rng.uniform(-1.0, 1.0))
        b.box((x, yb + depth_shift, 0), (x + wlen, yb + depth_shift + 8, height), "concrete")
        for wx in np.arange(x + 1.0, x + wlen - 1.5, 2.5):
            for wz in (1.0, 4.0):
                if wz + 1.5 < height:
                    b.box((wx, yb + depth_shift - 0.05, wz), (wx + 1.4, yb + depth_shift, wz + 1.5), "glass")
        x += wlen + float(rng.uniform(0, 3))
    # poles (street lights, signs) along the path
    for px in np.arange(float(rng.uniform(2, 6)), length, float(rng.uniform(8, 14))):
        b.cyl(float(px), float(rng.uniform(3.0, 4.0)), 0.08, 0, float(rng.uniform(3.5, 6.0)), "metal")
    # vegetation: trees (trunk + canopy of small boxes) and bushes (clusters) on the other side
    for tx in np.arange(float(rng.uniform(1, 5)), length, float(rng.uniform(5, 9))):
        ty = float(rng.uniform(-7, -4))
        b.cyl(float(tx), ty, 0.15, 0, 2.5, "wood")
        for _ in range(12):
            c = (tx + rng.normal(0, 0.9), ty + rng.normal(0, 0.9), 3.2 + rng.normal(0, 0.5))
            b.obox(c, tuple(rng.uniform(0.2, 0.5, 3)), float(rng.uniform(0, np.pi)), "foliage")
    for _ in range(int(rng.integers(6, 12))):
        cx, cy = float(rng.uniform(0, length)), float(rng.uniform(-4.0, -2.5))
        for _ in range(6):
            b.obox((cx + rng.normal(0, 0.4), cy + rng.normal(0, 0.3), float(rng.uniform(0.2, 0.7))),
                   tuple(rng.uniform(0.15, 0.4, 3)), float(rng.uniform(0, np.pi)), "foliage")
    # a few parked cars / benches
    for _ in range(int(rng.integers(1, 4))):
        cx = float(rng.uniform(5, length - 5))
        b.obox((cx, float(rng.uniform(-12, -9)), 0.75), (2.2, 0.9, 0.75), float(rng.normal(0, 0.1)), "metal")
    wp = [(0.0, float(rr.uniform(-1.0, 1.0)))]
    for xx in np.arange(6.0, length, 6.0):
        wp.append((float(xx), float(rr.uniform(-1.0, 1.0))))
    traj = Trajectory(tuple(wp) if rr.uniform() < 0.5 else tuple(wp[::-1]), speed=float(rr.uniform(1.0, 1.6)),
                      height=float(rr.uniform(1.0, 1.3)), handheld=rr.uniform() < 0.5,
                      sway_seed=int(rr.integers(1 << 30)))
    people = _people(rr, int(rr.integers(1, 4)), (0.0, -2.0, length, 4.0), speed=(1.0, 1.8))
    mirrors = (((0.0, 0.0, 1.0), 0.0),)
    return b, traj, people, mirrors


def make_scene(kind: str, seed: int, run: int = 0) -> Scene:
    """Build a seeded scene of ``kind`` (one of :data:`SCENE_KINDS`).

    Every run is its own seeded instance of the scene kind: the environment layout (walls,
    furniture, vegetation) is drawn from a generator seeded by ``(seed, kind, run, 1)`` and the rig
    trajectory and the people from one seeded by ``(seed, kind, run, 2)``. Different runs of a kind
    are therefore different places, so a split by run (:func:`radarpc.data.coloradar.split_runs`)
    holds out whole layouts (held-out scenes); the same ``(seed, kind, run)`` always gives the same
    scene.

    Examples
    --------
    >>> s = make_scene("hallway", 0)
    >>> s.trajectory.duration > 5
    True
    """
    if kind not in SCENE_KINDS:
        raise ValueError(f"unknown scene kind {kind!r}; expected one of {SCENE_KINDS}")
    if int(run) < 0:
        raise ValueError(f"run must be >= 0, got {run}")
    key = [int(seed), SCENE_KINDS.index(kind), int(run)]
    rng = np.random.default_rng(key + [1])            # layout of this run's instance of the kind
    rr = np.random.default_rng(key + [2])              # rig path and people
    if kind == "hallway":
        b, traj, people, mirrors = _hallway(rng, rr)
    elif kind == "outdoor":
        b, traj, people, mirrors = _outdoor(rng, rr)
    else:
        b, traj, people, mirrors = _furnished_room(rng, rr, kind)
    boxes, cyls = b.arrays()
    return Scene(kind, int(seed), boxes, cyls, people, traj, mirrors)
