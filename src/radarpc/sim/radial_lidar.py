"""RADIal's laser scanner seen from a simulated road frame: ``laser_PCL`` point clouds by ray casting.

The scanner (RADIal's sensor table: 16 layers, 10 deg vertical and 133 deg horizontal field of
view, 0.6 deg between layers, 0.125-0.25 deg horizontal steps, 150 m range) is
:data:`RADIAL_LASER`. Its frame is the one of ``labels.csv``'s ``laser_X/Y/Z_m`` columns: the
radar's axes with the origin at :data:`radarpc.sim.radial_labels.LIDAR_OFFSET_M` in the radar
frame, so the labelled reference point of a vehicle lies on (or next to) the vehicle's points.

The scene it sees is the one the camera draws (:mod:`radarpc.sim.radial_camera`): the vehicles'
3-D boxes, the ground plane, and every static reflector standing above the ground as a post
(a vertical cylinder of radius :data:`POST_RADIUS_M` up to 0.3 m above the reflector). All of
them are vertical prisms on the ground, so :func:`laser_scan` solves each azimuth column in the
horizontal plane (the road's :func:`radarpc.sim.road.footprint_crossings` for the boxes, a
circle for the posts) and then each layer in closed form; the ground is a plane. (A general 3-D
caster, :func:`radarpc.sim.indoor.ray_cast`, took seconds a frame on the thousand posts of a
road frame.)

Points are ``(N, 8)`` float32 in :data:`radarpc.data.radial_format.LASER_PCL_COLUMNS` order; the
intensity is the surface's LiDAR reflectivity (:data:`radarpc.sim.indoor.MATERIALS`) times the
cosine of the incidence angle. No range noise: a frame's points are a pure function of its scene.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from radarpc.sim.indoor import MATERIALS
from radarpc.sim.radial_camera import scatterer_xyz
from radarpc.sim.radial_labels import LIDAR_OFFSET_M
from radarpc.sim.road import RoadFrame, footprint_crossings

__all__ = ["LaserConfig", "RADIAL_LASER", "POST_RADIUS_M", "laser_directions", "laser_scan"]

POST_RADIUS_M: float = 0.1
"""Radius of the posts that stand for static reflectors above the ground."""
_MATERIAL = {m.name: i for i, m in enumerate(MATERIALS)}


@dataclass(frozen=True)
class LaserConfig:
    """A multi-layer laser scanner: layers evenly spaced in elevation, columns in azimuth."""

    n_layers: int = 16                    # RADIal: 16-layer scanner
    layer_pitch_deg: float = 0.6          # elevation between layers (16 x 0.6 = 9.6 ~ 10 deg FOV)
    azimuth_fov_deg: float = 133.0        # horizontal field of view, centred on x
    azimuth_step_deg: float = 0.25        # coarsest of the 0.125-0.25 deg steps
    max_range_m: float = 150.0

    def __post_init__(self) -> None:
        if self.n_layers < 1:
            raise ValueError(f"n_layers must be >= 1, got {self.n_layers}")
        for name in ("layer_pitch_deg", "azimuth_step_deg", "max_range_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0 < self.azimuth_fov_deg < 360:
            raise ValueError(f"azimuth_fov_deg must be in (0, 360), got {self.azimuth_fov_deg}")


RADIAL_LASER = LaserConfig()
"""RADIal's scanner (sensor table of the RADIal README)."""


def laser_directions(cfg: LaserConfig = RADIAL_LASER) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit ray directions ``(L * A, 3)``, their elevations and azimuths (radians), layer-major.

    Layer ``k`` (0 = bottom) is at elevation ``(k - (L - 1) / 2) * pitch``; azimuths run from
    ``-fov / 2`` to ``+fov / 2`` in ``azimuth_step_deg`` steps (left positive).
    """
    el = np.deg2rad((np.arange(cfg.n_layers) - (cfg.n_layers - 1) / 2) * cfg.layer_pitch_deg)
    n_az = int(math.floor(cfg.azimuth_fov_deg / cfg.azimuth_step_deg + 1e-9)) + 1
    az = np.deg2rad(-cfg.azimuth_fov_deg / 2 + np.arange(n_az) * cfg.azimuth_step_deg)
    e, a = np.meshgrid(el, az, indexing="ij")                                  # (L, A)
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)
    return d.reshape(-1, 3), e.reshape(-1), a.reshape(-1)


def _prisms(frame: RoadFrame, reach_m: float):
    """Vertical prisms of the scene in the LiDAR frame: vehicles (boxes) and posts (cylinders).

    Returns ``(box_xy, box_yaw, box_size, box_z, post_xy, post_z)``: footprint centres ``(B, 2)``,
    yaws, ``(B, 2)`` length and width, ``(B, 2)`` bottom and top heights; ``(C, 2)`` and
    ``(C, 2)`` for the posts.
    """
    off = np.asarray(LIDAR_OFFSET_M, dtype=np.float64)
    ground = -frame.radar_height_m - off[2]
    veh = frame.vehicles
    centre = veh.center_xyz - off
    near = np.hypot(centre[:, 0], centre[:, 1]) < reach_m + np.hypot(veh.size_lwh[:, 0], veh.size_lwh[:, 1])
    box_z = np.stack([centre[:, 2], centre[:, 2] + veh.size_lwh[:, 2]], 1)
    xyz = scatterer_xyz(frame)
    posts = (frame.owner.numpy() == -1) & (xyz[:, 2] + frame.radar_height_m > 0.3)   # not ghosts (-2)
    p = xyz[posts] - off
    post_z = np.stack([np.full(len(p), ground), p[:, 2] + 0.3], 1)
    return (centre[near, :2], veh.yaw_rad[near], veh.size_lwh[near, :2], box_z[near], p[:, :2], post_z)


def laser_scan(frame: RoadFrame, cfg: LaserConfig = RADIAL_LASER) -> np.ndarray:
    """The laser points of a road frame, float32 ``(N, 8)`` (module docstring).

    Every primitive is a vertical prism standing on the ground, so each azimuth column is solved
    in the horizontal plane first (where its ray enters and leaves each footprint, at horizontal
    distances ``rho_in < rho_out``), then per layer: a ray of elevation ``e`` is at height
    ``rho tan e``; it hits a prism's side at ``rho_in`` if that height lies within the prism,
    else its top (going down) or bottom (going up) if it crosses that plane before ``rho_out``.
    The 3-D distance is ``rho / cos e``. Rows are layer-major (layer 0 first, azimuth increasing);
    rays without a hit within ``cfg.max_range_m`` give no row.
    """
    d, el, az = laser_directions(cfg)
    n_l, n_a = cfg.n_layers, d.shape[0] // cfg.n_layers
    az_col = az[:n_a]
    u = np.stack([np.cos(az_col), np.sin(az_col)], 1)                         # (A, 2) unit
    tan_e = np.tan(el[::n_a])                                                  # (L,)
    box_xy, box_yaw, box_lw, box_z, post_xy, post_z = _prisms(frame, cfg.max_range_m)
    refl = {m.name: m.lidar_reflectivity for m in MATERIALS}

    # horizontal crossings, columns x prisms
    t_in, t_out = footprint_crossings(u, box_xy, box_yaw, box_lw)              # (A, B)
    b = u @ post_xy.T                                                          # (A, C)
    disc = b * b - ((post_xy ** 2).sum(1) - POST_RADIUS_M ** 2)[None, :]
    sq = np.sqrt(np.maximum(disc, 0.0))
    c_in, c_out = np.where(disc >= 0, b - sq, np.inf), np.where(disc >= 0, b + sq, -np.inf)
    rho_in = np.concatenate([t_in, c_in], 1)                                   # (A, P)
    rho_out = np.concatenate([t_out, c_out], 1)
    zr = np.concatenate([box_z, post_z], 0)                                    # (P, 2)
    col, prim = np.nonzero((rho_in < rho_out) & (rho_out > 0) & (rho_in < cfg.max_range_m))
    r0, r1 = np.maximum(rho_in[col, prim], 0.0), rho_out[col, prim]           # (K,)
    z0, z1 = zr[prim, 0], zr[prim, 1]

    # per layer: side, top or bottom
    te = tan_e[:, None]                                                        # (L, 1)
    h_in = r0[None] * te                                                       # (L, K)
    with np.errstate(divide="ignore", invalid="ignore"):
        side = (h_in >= z0) & (h_in <= z1)
        rho_top = np.where(te < 0, z1 / te, np.inf)
        rho_bot = np.where(te > 0, z0 / te, np.inf)
    top = ~side & (h_in > z1) & (rho_top <= r1)
    bot = ~side & (h_in < z0) & (rho_bot <= r1)
    rho = np.where(side, r0, np.where(top, rho_top, np.where(bot, rho_bot, np.inf)))
    ray = np.arange(n_l)[:, None] * n_a + col[None, :]                         # (L, K) ray index
    best = np.full(n_l * n_a, np.inf)
    np.minimum.at(best, ray.ravel(), rho.ravel())
    # which pair gave the best hit (for the normal): the first pair reaching the minimum
    win = np.full(n_l * n_a, -1, dtype=np.int64)
    is_best = np.isfinite(rho) & (rho == best[ray])
    flat = np.flatnonzero(is_best.ravel())
    win[ray.ravel()[flat[::-1]]] = flat[::-1]                                  # first writer wins

    # the ground plane, below the scanner
    ground = -frame.radar_height_m - LIDAR_OFFSET_M[2]
    cos_e = np.cos(el)
    with np.errstate(divide="ignore"):
        rho_g = np.where(d[:, 2] < 0, ground / np.tan(el), np.inf)
    on_ground = rho_g < best
    rho_all = np.where(on_ground, rho_g, best)
    t = rho_all / cos_e
    keep = np.isfinite(t) & (t <= cfg.max_range_m)

    # normals and reflectivities of the hits
    normal = np.zeros((d.shape[0], 3))
    r_hit = np.zeros(d.shape[0])
    normal[on_ground] = (0.0, 0.0, 1.0)
    r_hit[on_ground] = refl["ground"]
    obj = (win >= 0) & ~on_ground
    k = win[obj] % len(col)                                                    # pair index
    lay = win[obj] // len(col)
    p_hit = rho_all[obj, None] * u[col[k]]                                     # (H, 2)
    n_box = len(box_xy)
    is_box = prim[k] < n_box
    n_h = np.zeros((len(k), 3))
    flat_top = top[lay, k] | bot[lay, k]
    n_h[flat_top, 2] = np.where(top[lay, k], 1.0, -1.0)[flat_top]
    # box sides: the face whose slab the point lies on (in the box frame)
    sb = ~flat_top & is_box
    j = prim[k][sb]
    cy, sy = np.cos(box_yaw[j]), np.sin(box_yaw[j])
    rel = p_hit[sb] - box_xy[j]
    loc = np.stack([cy * rel[:, 0] + sy * rel[:, 1], -sy * rel[:, 0] + cy * rel[:, 1]], 1) / (box_lw[j] / 2)
    along = np.abs(loc[:, 0]) >= np.abs(loc[:, 1])
    nl = np.where(along[:, None], np.stack([np.sign(loc[:, 0]), 0 * loc[:, 0]], 1),
                  np.stack([0 * loc[:, 1], np.sign(loc[:, 1])], 1))
    n_h[sb, 0] = cy * nl[:, 0] - sy * nl[:, 1]
    n_h[sb, 1] = sy * nl[:, 0] + cy * nl[:, 1]
    sc = ~flat_top & ~is_box
    n_h[sc, :2] = (p_hit[sc] - post_xy[prim[k][sc] - n_box]) / POST_RADIUS_M
    normal[obj] = n_h
    r_hit[obj] = np.where(is_box, refl["metal"], refl["concrete"])

    layer = np.repeat(np.arange(n_l), n_a)
    pts = t[keep, None] * d[keep]
    intensity = r_hit[keep] * np.abs((normal[keep] * d[keep]).sum(1))
    out = np.concatenate([pts, intensity[:, None], t[keep, None], el[keep, None], az[keep, None],
                          layer[keep, None]], 1)
    return out.astype(np.float32)
