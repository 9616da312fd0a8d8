"""The classical reference detector: CFAR points -> ego-motion-compensated Doppler gating -> BEV
clustering -> one detection per cluster, in the learned models' :class:`Detections` format so
that the same metrics score it.

1. **Ego speed from the points.** A static scatterer seen from a radar moving forward at ``v``
   has radial velocity ``v_r = -v cos(az) cos(el)`` (receding positive). Most CFAR points of a
   road scene are static, so the ego speed is the ``v`` that explains the most points: a grid
   search maximises the number of points with ``|wrap(v_r + v cos az cos el)| < static_tol_mps``
   (``wrap`` into the unambiguous interval ``[-v_max, v_max)``, since the measured velocity is
   aliased), then a least-squares fit over those inliers refines it. Moving vehicles and clutter
   are outliers of a consensus count, so they do not bias it.
2. **Doppler gating.** A point is moving when its ego-compensated radial velocity
   ``u = wrap(v_r + v cos az cos el)`` exceeds ``moving_threshold_mps`` in magnitude.
3. **BEV clustering.** Moving points closer than ``cluster_eps_m`` in ``(x, y)`` whose
   compensated velocities differ by less than ``cluster_max_dv_mps`` are linked; connected
   components of at least ``min_points`` points are clusters (DBSCAN with ``min_samples = 1``
   and a minimum cluster size).
4. **One detection per cluster**, at the SNR-weighted mean range and azimuth of its points.
   RADIal's reference point is the middle of the vehicle's visible (nearest) face, which holds
   the strongest returns; the weighting keeps the weaker side returns from dragging the point
   along the vehicle (the nearest point instead is biased short by range sidelobes: on 9
   simulated radial-s frames it gave F1 0.11 / 0.05 at 5 % / 44 % density against 0.14 / 0.22
   weighted). The score ``n / (n + score_half_points)`` grows with the cluster's point count
   ``n`` (0.5 at ``score_half_points``) so the confidence sweep 0.1..0.9 ranks clusters by
   support.

Static vehicles are invisible to step 2 by design: the row shows what Doppler alone gives.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from radarpc.boxes import Detections
from radarpc.points import PointCloudBatch
from radarpc.sensors.radial import RADIAL

__all__ = ["ClassicalConfig", "wrap_velocity", "estimate_ego_speed", "detect_frame", "classical_detect"]


@dataclass(frozen=True)
class ClassicalConfig:
    """Settings of the classical detector (defaults: the RADIal sensor).

    Attributes
    ----------
    max_velocity_mps : float
        Unambiguous radial velocity ``v_max``: measured velocities lie in ``[-v_max, v_max)``.
    ego_speed_range_mps : (float, float)
        Interval searched for the forward ego speed.
    ego_grid_step_mps : float
        Grid step of the search (the least-squares refinement then goes below it).
    static_tol_mps : float
        Residual of a static point (inlier) in the ego fit: a few Doppler bins of quantisation
        and the elevation error.
    moving_threshold_mps : float
        Compensated radial speed above which a point is moving.
    cluster_eps_m : float
        Link distance in the ``(x, y)`` plane.
    cluster_max_dv_mps : float
        Largest compensated-velocity difference of linked points.
    min_points : int
        Smallest cluster.
    score_half_points : float
        Cluster size that scores 0.5.
    """

    max_velocity_mps: float = RADIAL.max_velocity_mps
    ego_speed_range_mps: tuple[float, float] = (0.0, 40.0)
    ego_grid_step_mps: float = 0.05
    static_tol_mps: float = 0.5
    moving_threshold_mps: float = 1.0
    cluster_eps_m: float = 2.0
    cluster_max_dv_mps: float = 2.0
    min_points: int = 2
    score_half_points: float = 4.0

    def __post_init__(self) -> None:
        lo, hi = self.ego_speed_range_mps
        checks = {
            "max_velocity_mps": self.max_velocity_mps > 0,
            "ego_speed_range_mps": lo <= hi,
            "ego_grid_step_mps": self.ego_grid_step_mps > 0,
            "static_tol_mps": self.static_tol_mps > 0,
            "moving_threshold_mps": self.moving_threshold_mps >= 0,
            "cluster_eps_m": self.cluster_eps_m > 0,
            "cluster_max_dv_mps": self.cluster_max_dv_mps > 0,
            "min_points": self.min_points >= 1,
            "score_half_points": self.score_half_points > 0,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"ClassicalConfig: invalid {', '.join(f'{k}={getattr(self, k)!r}' for k in bad)} "
                             "(positive values, and a (low, high) speed interval)")


def wrap_velocity(v: np.ndarray, v_max: float) -> np.ndarray:
    """``v`` folded into ``[-v_max, v_max)`` (the radar's unambiguous interval)."""
    return np.mod(v + v_max, 2 * v_max) - v_max


def estimate_ego_speed(velocity_mps: np.ndarray, azimuth_deg: np.ndarray, elevation_deg: np.ndarray,
                       cfg: ClassicalConfig = ClassicalConfig()) -> tuple[float, np.ndarray]:
    """Forward ego speed from the radial velocities of mostly static points.

    Returns
    -------
    speed : float
        ``v`` maximising the static consensus, refined by least squares over its inliers
        (NaN for an empty cloud).
    static : bool ``(N,)``
        Inliers: ``|wrap(v_r + v cos az cos el)| < static_tol_mps``.
    """
    vr = np.asarray(velocity_mps, np.float64)
    c = np.cos(np.deg2rad(np.asarray(azimuth_deg, np.float64))) * np.cos(np.deg2rad(np.asarray(elevation_deg, np.float64)))
    if vr.size == 0:
        return float("nan"), np.zeros(0, bool)
    lo, hi = cfg.ego_speed_range_mps
    grid = np.arange(lo, hi + 0.5 * cfg.ego_grid_step_mps, cfg.ego_grid_step_mps)       # (G,)
    votes = np.empty(grid.size, np.int64)
    for s in range(0, grid.size, 256):                     # (256, N) chunks bound the memory
        g = grid[s:s + 256, None]
        votes[s:s + 256] = (np.abs(wrap_velocity(vr[None] + g * c[None], cfg.max_velocity_mps))
                            < cfg.static_tol_mps).sum(1)
    v = float(grid[int(np.argmax(votes))])                 # first maximum: the slowest consensus
    for _ in range(2):
        u = wrap_velocity(vr + v * c, cfg.max_velocity_mps)
        static = np.abs(u) < cfg.static_tol_mps
        if not static.any() or not np.any(c[static]):
            break
        # unaliased measurement of each inlier: -v c + u; least squares of vr' = -v c
        vr_un = u[static] - v * c[static]
        v = float(-np.dot(c[static], vr_un) / np.dot(c[static], c[static]))
    u = wrap_velocity(vr + v * c, cfg.max_velocity_mps)
    return v, np.abs(u) < cfg.static_tol_mps


def detect_frame(range_m: np.ndarray, azimuth_deg: np.ndarray, elevation_deg: np.ndarray,
                 velocity_mps: np.ndarray, x: np.ndarray, y: np.ndarray, snr: np.ndarray,
                 cfg: ClassicalConfig = ClassicalConfig()) -> tuple[np.ndarray, float]:
    """Detections of one frame's points (1-D arrays of equal length).

    Returns
    -------
    rows : float64 ``(K, 3)`` ``(score, range_m, azimuth_deg)``, one per cluster
    ego_speed : float, the estimated forward speed (m/s)
    """
    v_ego, _ = estimate_ego_speed(velocity_mps, azimuth_deg, elevation_deg, cfg)
    if not np.isfinite(v_ego):
        return np.zeros((0, 3)), v_ego
    c = np.cos(np.deg2rad(azimuth_deg)) * np.cos(np.deg2rad(elevation_deg))
    u = wrap_velocity(np.asarray(velocity_mps, np.float64) + v_ego * c, cfg.max_velocity_mps)
    moving = np.flatnonzero(np.abs(u) > cfg.moving_threshold_mps)
    if moving.size < cfg.min_points:
        return np.zeros((0, 3)), v_ego
    xy = np.stack([x[moving], y[moving]], 1).astype(np.float64)
    pairs = cKDTree(xy).query_pairs(cfg.cluster_eps_m, output_type="ndarray")             # (E, 2)
    um = u[moving]
    pairs = pairs[np.abs(um[pairs[:, 0]] - um[pairs[:, 1]]) < cfg.cluster_max_dv_mps]
    n = moving.size
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    rows = []
    r, a = np.asarray(range_m, np.float64)[moving], np.asarray(azimuth_deg, np.float64)[moving]
    w = np.maximum(np.asarray(snr, np.float64)[moving], 0) + 1e-12
    for k in np.unique(comp):
        m = comp == k
        cnt = int(m.sum())
        if cnt < cfg.min_points:
            continue
        rows.append((cnt / (cnt + cfg.score_half_points), np.average(r[m], weights=w[m]),
                     np.average(a[m], weights=w[m])))
    return (np.asarray(rows, np.float64) if rows else np.zeros((0, 3))), v_ego


def classical_detect(points: PointCloudBatch, cfg: ClassicalConfig = ClassicalConfig()) -> Detections:
    """:func:`detect_frame` on every frame of an offset-batched cloud (computed on the CPU);
    the result is on the points' device."""
    frames = []
    for b in range(len(points)):
        p = points.frame(b)
        f = {k: getattr(p, k).detach().cpu().numpy() for k in
             ("range_m", "azimuth_deg", "elevation_deg", "velocity_mps", "x", "y", "snr")}
        rows, _ = detect_frame(cfg=cfg, **f)
        frames.append(torch.from_numpy(rows).float())
    return Detections.from_frames(frames).to(points.offset.device)
