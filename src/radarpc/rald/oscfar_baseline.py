"""OS-CFAR baseline of RaLD: radar cube -> 3-D ordered-statistic CFAR -> point cloud.

The classical baseline of the RaLD tables ("OS-CFAR", Richards 2005): detect cells of the
(range, azimuth, elevation) intensity cube whose power exceeds ``tau`` times an ordered-statistic
noise estimate of their training ring, and place one point per detected cell.

Pipeline for one frame (``cube_db``: intensity in dB, ``(n_r, n_az, n_el)``):

1. optional bilinear upsampling of the two angle axes to ``angle_bins`` (RaLD upsamples the
   single-chip cube's 8 x 2 angle bins for its model; here it lets CFAR place points between the
   coarse angle bins), the bin angles interpolated the same way;
2. linear power ``P = 10 ** (cube_db / 10)``;
3. 3-D OS-CFAR (:func:`radarpc.dsp.cfar.os_cfar`, full odd ``window`` / ``guard`` side lengths
   per axis, ``rank`` a quantile or k-th smallest) and detection ``P / noise > 10 ** (tau_db / 10)``;
   cells closer than ``min_range_m`` are ignored (TX leakage / DC);
4. if fewer than ``min_points`` cells pass, the ``min_points`` highest-SNR cells are kept, so that
   every frame yields a non-empty cloud and Chamfer distance is always defined;
5. each detected cell becomes a point at its bin centre (range, azimuth, elevation) mapped to
   Cartesian (x forward, y left, z up); with ``refine`` the range and azimuth are refined by a
   parabola through the dB values of the cell and its two neighbours (offset clipped to half a bin)
   where the cell is a local maximum along that axis; azimuth and elevation are clipped to the
   frustum (``clip_angles_deg``), since FFT angle bins may lie outside it.

Elevation (``elevation_deg``, default 0). The AWR1843's virtual array has two elevation rows one
unit apart, and RaLD's 2-point elevation FFT has bins at spatial frequencies -1/2 and 0, i.e.
about -79 deg and 0 deg. A target at elevation ``el`` puts ``|a -+ b e^{j phi}|^2`` into them
(``phi = 2 pi d sin el``, ``a``, ``b`` the two rows' azimuth spectra), which is the same for ``+el``
and ``-el``: the sign of the elevation is not observable, and the -79 deg bin is the difference
channel, not a direction. Placing points at the bin centres (``elevation_deg=None``) therefore put
every bin-0 detection at -79 deg, clipped to the frustum's -20 deg floor (37 % of the points on
simulated data, inflating CD). By default each detected (range, azimuth) cell -- a detection in
either elevation bin -- becomes one point at ``elevation_deg = 0``, the radar's horizontal plane
and the centre of the +-20 deg frustum; ``elevation_deg=None`` keeps the bin centres for cubes
whose elevation axis is resolved (e.g. a cascade heatmap).

The parameters are tuned on the validation split by an exhaustive grid search minimizing the mean
Chamfer distance to the cropped LiDAR (:func:`tune_oscfar`); the chosen configuration is saved as
YAML (:func:`save_config`) next to the predictions.
"""
from __future__ import annotations

import itertools
import math
import os
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
import yaml

from radarpc.dsp.cfar import os_cfar
from radarpc.eval.pointsets import ChamferTarget
from radarpc.io import DataFileError, atomic_write
from radarpc.rald.frustum import polar_to_cartesian

__all__ = [
    "CubeAxes",
    "OSCFARConfig",
    "TuningGrid",
    "TuningResult",
    "upsample_angles",
    "detect_cells",
    "detections_to_points",
    "detect_points",
    "tune_oscfar",
    "save_config",
    "load_config",
]


@dataclass(frozen=True)
class CubeAxes:
    """Bin centres of a radar cube: range in metres, azimuth and elevation in degrees.

    Azimuth is left positive and elevation up positive (the radarpc radar frame); each axis must be
    strictly monotonic (either direction: FFT angle bins are often stored descending).
    """

    range_m: tuple[float, ...]        # (n_r,)
    azimuth_deg: tuple[float, ...]    # (n_az,)
    elevation_deg: tuple[float, ...]  # (n_el,)

    def __post_init__(self) -> None:
        for name in ("range_m", "azimuth_deg", "elevation_deg"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.ndim != 1 or v.size < 1 or not np.isfinite(v).all():
                raise ValueError(f"CubeAxes.{name} must be a non-empty 1-D finite sequence, got {v.shape}")
            d = np.diff(v)
            if v.size > 1 and not ((d > 0).all() or (d < 0).all()):
                raise ValueError(f"CubeAxes.{name} must be strictly monotonic")
            object.__setattr__(self, name, tuple(float(x) for x in v))

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self.range_m), len(self.azimuth_deg), len(self.elevation_deg))

    @classmethod
    def from_radians(cls, range_m, azimuth_rad, elevation_rad) -> "CubeAxes":
        """From bin tables with angles in radians (e.g. :class:`radarpc.data.coloradar.RadarCube`)."""
        def vec(v):
            return np.asarray(v.detach().cpu() if hasattr(v, "detach") else v, dtype=np.float64)
        return cls(tuple(vec(range_m)), tuple(np.rad2deg(vec(azimuth_rad))), tuple(np.rad2deg(vec(elevation_rad))))


@dataclass(frozen=True)
class OSCFARConfig:
    """Parameters of the OS-CFAR baseline (saved as YAML beside its predictions)."""

    window: tuple[int, int, int] = (9, 3, 3)     # full odd training-window side per axis (range, az, el)
    guard: tuple[int, int, int] = (3, 1, 1)      # full odd guard-window side per axis, < window
    rank: float = 0.75                           # OS rank: quantile in (0, 1) of the training cells
    tau_db: float = 8.0                          # threshold on the CFAR SNR, dB
    angle_bins: tuple[int, int] | None = None    # upsample (azimuth, elevation) bins before CFAR; None = off
    min_range_m: float = 0.3                     # cells closer than this are never detections
    min_points: int = 1                          # keep at least this many highest-SNR cells per frame
    refine: bool = True                          # parabolic sub-bin refinement in range and azimuth
    clip_angles_deg: tuple[float, float] | None = (90.0, 20.0)  # |azimuth|, |elevation| of points clipped to these
    elevation_deg: float | None = 0.0            # every point at this elevation (cells merged over elevation); None = bin centres

    def __post_init__(self) -> None:
        for name in ("window", "guard"):
            v = tuple(int(x) for x in getattr(self, name))
            if len(v) != 3 or any(x < 1 or x % 2 == 0 for x in v):
                raise ValueError(f"OSCFARConfig.{name}={getattr(self, name)} must be 3 positive odd ints")
            object.__setattr__(self, name, v)
        if any(g >= w for g, w in zip(self.guard, self.window)):
            raise ValueError(f"OSCFARConfig.guard={self.guard} must be smaller than window={self.window} on every axis")
        if not 0.0 < float(self.rank) < 1.0:
            raise ValueError(f"OSCFARConfig.rank={self.rank} must be a quantile in (0, 1)")
        if not math.isfinite(self.tau_db):
            raise ValueError(f"OSCFARConfig.tau_db={self.tau_db} must be finite")
        if self.angle_bins is not None:
            ab = tuple(int(x) for x in self.angle_bins)
            if len(ab) != 2 or min(ab) < 1:
                raise ValueError(f"OSCFARConfig.angle_bins={self.angle_bins} must be two positive ints or None")
            object.__setattr__(self, "angle_bins", ab)
        if self.min_range_m < 0 or not math.isfinite(self.min_range_m):
            raise ValueError(f"OSCFARConfig.min_range_m={self.min_range_m} must be >= 0")
        if self.clip_angles_deg is not None:
            ca = tuple(float(x) for x in self.clip_angles_deg)
            if len(ca) != 2 or not all(0 < x <= 180 for x in ca):
                raise ValueError(f"OSCFARConfig.clip_angles_deg={self.clip_angles_deg} must be two angles in (0, 180] or None")
            object.__setattr__(self, "clip_angles_deg", ca)
        if int(self.min_points) < 1:
            raise ValueError(f"OSCFARConfig.min_points={self.min_points} must be >= 1")
        if self.elevation_deg is not None and not (math.isfinite(self.elevation_deg) and -90 <= self.elevation_deg <= 90):
            raise ValueError(f"OSCFARConfig.elevation_deg={self.elevation_deg} must be in [-90, 90] or None")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["window"], d["guard"] = list(self.window), list(self.guard)
        d["angle_bins"] = None if self.angle_bins is None else list(self.angle_bins)
        d["clip_angles_deg"] = None if self.clip_angles_deg is None else list(self.clip_angles_deg)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "OSCFARConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown OS-CFAR config keys {sorted(unknown)}; expected {sorted(known)}")
        kw = dict(d)
        for k in ("window", "guard", "angle_bins", "clip_angles_deg"):
            if kw.get(k) is not None:
                kw[k] = tuple(kw[k])
        return cls(**kw)


# ---- detection ----------------------------------------------------------------------------------

def _check_cube(cube_db, axes: CubeAxes | None = None) -> torch.Tensor:
    x = torch.as_tensor(cube_db)
    if x.is_complex():
        raise ValueError(f"radar cube must be real intensity in dB, got complex dtype {x.dtype}")
    if x.ndim not in (3, 4):
        raise ValueError(f"radar cube must be (n_r, n_az, n_el) or (B, n_r, n_az, n_el), got {tuple(x.shape)}")
    if not x.is_floating_point():
        x = x.to(torch.float32)
    if not bool(torch.isfinite(x).all()):
        raise ValueError("radar cube contains NaN or infinite values")
    if axes is not None and tuple(x.shape[-3:]) != axes.shape:
        raise ValueError(f"radar cube shape {tuple(x.shape[-3:])} does not match its axes {axes.shape}")
    return x


def _interp_axis(values: Sequence[float], n_out: int) -> tuple[float, ...]:
    # Bin positions of an align_corners=True linear resampling: linspace over the old indices.
    v = np.asarray(values, dtype=np.float64)
    if n_out == v.size:
        return tuple(v)
    pos = np.linspace(0.0, v.size - 1, n_out) if v.size > 1 else np.zeros(n_out)
    return tuple(np.interp(pos, np.arange(v.size), v))


def upsample_angles(cube_db, axes: CubeAxes, angle_bins: tuple[int, int]) -> tuple[torch.Tensor, CubeAxes]:
    """Bilinear (``align_corners=True``) upsampling of the azimuth and elevation axes of a dB cube.

    Returns the cube ``(..., n_r, angle_bins[0], angle_bins[1])`` and its interpolated axes.
    """
    x = _check_cube(cube_db, axes)
    n_az, n_el = (int(a) for a in angle_bins)
    lead = x.shape[:-3]
    flat = x.reshape(-1, *x.shape[-3:])                     # (B, R, A, E)
    up = F.interpolate(flat, size=(n_az, n_el), mode="bilinear", align_corners=True)   # (B, R, A', E')
    new_axes = CubeAxes(axes.range_m, _interp_axis(axes.azimuth_deg, n_az), _interp_axis(axes.elevation_deg, n_el))
    return up.reshape(*lead, *up.shape[-3:]), new_axes


def detect_cells(cube_db, axes: CubeAxes, cfg: OSCFARConfig) -> tuple[torch.Tensor, torch.Tensor, CubeAxes]:
    """Run the CFAR on a cube (batched) and return the detection mask.

    Parameters
    ----------
    cube_db : torch.Tensor or ndarray, ``(n_r, n_az, n_el)`` or ``(B, n_r, n_az, n_el)``
        Intensity in dB.
    axes : CubeAxes
        Bin centres of ``cube_db``.
    cfg : OSCFARConfig

    Returns
    -------
    mask : torch.Tensor, bool, shape of the (possibly upsampled) cube
        Detections, including the ``min_points`` fallback.
    cube_db : torch.Tensor
        The (possibly upsampled) dB cube the mask refers to.
    axes : CubeAxes
        Its axes.
    """
    x = _check_cube(cube_db, axes)
    if cfg.angle_bins is not None:
        x, axes = upsample_angles(x, axes, cfg.angle_bins)
    snr = os_cfar(torch.pow(10.0, x / 10.0), cfg.window, cfg.guard, float(cfg.rank)).snr
    mask = _threshold(snr, axes, cfg, x.device)
    return mask, x, axes


def _threshold(snr: torch.Tensor, axes: CubeAxes, cfg: OSCFARConfig, device) -> torch.Tensor:
    near = torch.tensor(axes.range_m, device=device) < cfg.min_range_m          # (n_r,)
    snr = snr.masked_fill(near[:, None, None], 0.0)
    mask = snr > 10.0 ** (cfg.tau_db / 10.0)
    # Fallback: at least min_points cells per frame, the ones of highest SNR.
    flat_snr = snr.reshape(-1, math.prod(snr.shape[-3:]))                      # (B, cells)
    flat = mask.reshape(flat_snr.shape).clone()
    k = min(int(cfg.min_points), flat_snr.shape[1])
    short = flat.sum(1) < k
    if bool(short.any()):
        top = flat_snr[short].topk(k, dim=1).indices
        rows = flat[short]
        rows.scatter_(1, top, True)
        flat[short] = rows
    return flat.view(mask.shape)


def _parabolic(db: torch.Tensor, idx: torch.Tensor, axis: int) -> torch.Tensor:
    """Sub-bin offset in [-0.5, 0.5] of the parabola through (i-1, i, i+1) along ``axis``; 0 if not a peak."""
    n = db.shape[axis]
    if n < 3:
        return torch.zeros(idx.shape[0], dtype=db.dtype, device=db.device)
    i = idx[:, axis]
    ok = (i > 0) & (i < n - 1)
    lo, hi = idx.clone(), idx.clone()
    lo[:, axis] = (i - 1).clamp(0, n - 1)
    hi[:, axis] = (i + 1).clamp(0, n - 1)
    y0 = db[tuple(lo.T)]
    y1 = db[tuple(idx.T)]
    y2 = db[tuple(hi.T)]
    den = y0 - 2.0 * y1 + y2
    ok = ok & (y1 >= y0) & (y1 >= y2) & (den < 0)
    off = torch.where(ok, 0.5 * (y0 - y2) / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(den))
    return off.clamp(-0.5, 0.5)


def _axis_value(values: Sequence[float], frac_idx: torch.Tensor) -> torch.Tensor:
    # Linear interpolation of the bin-centre table at fractional indices (linear extrapolation by
    # half a bin at the ends).
    v = torch.tensor(values, dtype=torch.float64, device=frac_idx.device)
    if v.numel() == 1:
        return v.expand(frac_idx.shape).clone()
    i0 = frac_idx.floor().long().clamp(0, v.numel() - 2)
    t = frac_idx - i0
    return v[i0] + t * (v[i0 + 1] - v[i0])


def detections_to_points(mask: torch.Tensor, cube_db: torch.Tensor, axes: CubeAxes, *, refine: bool = True,
                    clip_angles_deg: tuple[float, float] | None = None,
                    elevation_deg: float | None = None) -> torch.Tensor:
    """Detected cells of one frame -> Cartesian points ``(N, 3)`` (float32) in the radar frame.

    Parameters
    ----------
    mask : torch.Tensor, bool, ``(n_r, n_az, n_el)``
    cube_db : torch.Tensor, ``(n_r, n_az, n_el)``
        The dB cube the mask refers to (used by the refinement).
    axes : CubeAxes
    refine : bool
        Parabolic sub-bin refinement in range and azimuth.
    clip_angles_deg : (float, float), optional
        Clip ``|azimuth|`` and ``|elevation|`` of the points to these (the radar frustum): FFT
        angle bins can lie outside the field of view (the AWR1843's 2-bin elevation FFT has bins
        at about -80 and 0 deg).
    elevation_deg : float, optional
        If given, the elevation axis is collapsed first: a (range, azimuth) cell detected in any
        elevation bin gives one point at this elevation, refined on the maximum over elevation
        of the dB cube (see the module docstring for why this is the default of the baseline).
    """
    if mask.ndim != 3 or tuple(mask.shape) != tuple(cube_db.shape) or tuple(mask.shape) != axes.shape:
        raise ValueError(f"mask {tuple(mask.shape)}, cube {tuple(cube_db.shape)} and axes {axes.shape} "
                         "must all be one (n_r, n_az, n_el) frame")
    if elevation_deg is not None:
        mask = mask.any(-1, keepdim=True)                                   # (n_r, n_az, 1)
        cube_db = cube_db.amax(-1, keepdim=True)                            # (n_r, n_az, 1)
        axes = CubeAxes(axes.range_m, axes.azimuth_deg, (float(elevation_deg),))
    idx = mask.nonzero()                                                    # (N, 3)
    frac = idx.to(torch.float64)
    if refine and idx.shape[0]:
        db = cube_db.to(torch.float64)
        frac[:, 0] += _parabolic(db, idx, 0)
        frac[:, 1] += _parabolic(db, idx, 1)
    rae = torch.stack([_axis_value(axes.range_m, frac[:, 0]),
                       _axis_value(axes.azimuth_deg, frac[:, 1]),
                       _axis_value(axes.elevation_deg, frac[:, 2])], dim=-1)   # (N, 3) polar
    if clip_angles_deg is not None:
        a, e = clip_angles_deg
        rae[:, 1].clamp_(-a, a)
        rae[:, 2].clamp_(-e, e)
    return polar_to_cartesian(rae).to(torch.float32)


def detect_points(cube_db, axes: CubeAxes, cfg: OSCFARConfig = OSCFARConfig()) -> list[torch.Tensor] | torch.Tensor:
    """OS-CFAR point cloud of a cube ``(n_r, n_az, n_el)`` -> ``(N, 3)``, or of a batch -> list of ``(N_b, 3)``.

    Points are Cartesian (x forward, y left, z up), metres, float32, on the cube's device; every
    frame has at least ``cfg.min_points`` points.
    """
    mask, x, ax = detect_cells(cube_db, axes, cfg)
    if mask.ndim == 3:
        return detections_to_points(mask, x, ax, refine=cfg.refine, clip_angles_deg=cfg.clip_angles_deg,
                               elevation_deg=cfg.elevation_deg)
    return [detections_to_points(m, c, ax, refine=cfg.refine, clip_angles_deg=cfg.clip_angles_deg,
                            elevation_deg=cfg.elevation_deg) for m, c in zip(mask, x)]


# ---- tuning -------------------------------------------------------------------------------------

@dataclass(frozen=True)
class TuningGrid:
    """Candidate values searched exhaustively by :func:`tune_oscfar` (invalid window/guard pairs skipped)."""

    windows: tuple[tuple[int, int, int], ...] = ((9, 3, 3), (13, 5, 3), (17, 7, 3))
    guards: tuple[tuple[int, int, int], ...] = ((3, 1, 1), (5, 3, 1))
    ranks: tuple[float, ...] = (0.5, 0.75, 0.9)
    taus_db: tuple[float, ...] = (3.0, 5.0, 8.0, 11.0, 14.0, 18.0)
    angle_bins: tuple[tuple[int, int] | None, ...] = (None, (32, 8))
    base: OSCFARConfig = field(default_factory=OSCFARConfig)   # min_range_m, min_points, refine

    def candidates(self) -> list[OSCFARConfig]:
        out = []
        for ab, w, g, r, t in itertools.product(self.angle_bins, self.windows, self.guards, self.ranks, self.taus_db):
            if all(gi < wi for gi, wi in zip(g, w)):
                out.append(replace(self.base, window=w, guard=g, rank=r, tau_db=t, angle_bins=ab))
        if not out:
            raise ValueError("TuningGrid has no valid (window, guard) pair: every guard must be smaller than its window")
        return out


@dataclass
class TuningResult:
    """Outcome of the grid search: the best configuration and the mean Chamfer of every candidate."""

    best: OSCFARConfig
    best_chamfer: float
    n_frames: int
    table: list[tuple[OSCFARConfig, float, float]]   # (config, mean CD in m, mean points per frame)


def tune_oscfar(
    frames: Iterable[tuple[object, object]],
    axes: CubeAxes,
    grid: TuningGrid = TuningGrid(),
    *,
    progress: bool = False,
) -> TuningResult:
    """Grid search of the OS-CFAR parameters minimizing the mean Chamfer distance to the LiDAR.

    The CFAR statistic is computed once per (angle_bins, window, guard, rank) and frame; every
    threshold is then a cheap comparison.

    Parameters
    ----------
    frames : iterable of (cube_db, lidar_xyz)
        Validation frames: dB cube ``(n_r, n_az, n_el)`` and cropped LiDAR ``(M, 3)`` in the radar
        frame (consumed once and kept in memory: pass a moderate number of frames).
    axes : CubeAxes
    grid : TuningGrid
    progress : bool
        tqdm bar over the CFAR settings.

    Returns
    -------
    TuningResult
        Ties are broken by the order of :meth:`TuningGrid.candidates`.
    """
    data = []
    for i, (cube, lidar) in enumerate(frames):
        if len(lidar) == 0:
            raise ValueError(f"validation frame {i}: the LiDAR cloud is empty; Chamfer distance needs points")
        data.append((_check_cube(cube, axes), ChamferTarget(lidar)))   # LiDAR KD-tree built once
    if not data:
        raise ValueError("tune_oscfar needs at least one validation frame")
    cands = grid.candidates()
    groups: dict[tuple, list[OSCFARConfig]] = {}
    for c in cands:
        groups.setdefault((c.angle_bins, c.window, c.guard, c.rank), []).append(c)
    it = groups.items()
    if progress:
        from tqdm import tqdm
        it = tqdm(list(it), desc="OS-CFAR tuning", unit="setting")
    scores: dict[OSCFARConfig, tuple[float, float]] = {}
    for (ab, w, g, r), group in it:
        sums = np.zeros((len(group), 2))
        for cube, target in data:
            x, ax = (upsample_angles(cube, axes, ab) if ab is not None else (cube, axes))
            snr = os_cfar(torch.pow(10.0, x / 10.0), w, g, float(r)).snr
            for j, c in enumerate(group):
                pts = detections_to_points(_threshold(snr, ax, c, x.device), x, ax, refine=c.refine,
                                      clip_angles_deg=c.clip_angles_deg, elevation_deg=c.elevation_deg)
                sums[j, 0] += target(pts)
                sums[j, 1] += pts.shape[0]
        for j, c in enumerate(group):
            scores[c] = (sums[j, 0] / len(data), sums[j, 1] / len(data))
    table = [(c, *scores[c]) for c in cands]
    best = min(table, key=lambda row: row[1])
    return TuningResult(best=best[0], best_chamfer=float(best[1]), n_frames=len(data), table=table)


# ---- config files -------------------------------------------------------------------------------

def save_config(path: str | os.PathLike, cfg: OSCFARConfig, **provenance) -> None:
    """Write ``cfg`` (and JSON-like provenance under ``provenance:``) as YAML, atomically."""
    doc = {"oscfar": cfg.to_dict()}
    if provenance:
        doc["provenance"] = provenance
    with atomic_write(Path(path), "w") as f:
        yaml.safe_dump(doc, f, sort_keys=False)


def load_config(path: str | os.PathLike) -> OSCFARConfig:
    """Read a configuration written by :func:`save_config` (safe YAML)."""
    path = Path(path)
    if not path.is_file():
        raise DataFileError(path, "OS-CFAR config file is missing")
    try:
        doc = yaml.safe_load(path.read_text())
        return OSCFARConfig.from_dict(doc["oscfar"])
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as e:
        raise DataFileError(path, f"expected a YAML mapping with an 'oscfar' section of OS-CFAR parameters ({e})") from e
