"""Where RaLD's guided queries start: a frame's "CFAR" points, RaLD's intensity peaks or radarpc's OS-CFAR.

RaLD's generation decodes queries around points of the radar frame
(:func:`radarpc.rald.generate.cfar_guided_queries`). The public RoyAPTX4869/RaLD code makes those
"helper points" in ``dataset_preprocessor/cache_test_cfar.py`` (``RA2DDetectorTensor``,
``weighted_allocation``, ``cube_idx2coord``); it is a top-``n`` intensity picker, not a CFAR
test. :func:`peak_points` does the same on radarpc's cube:

1. the single-chip cube with finer angle FFTs (official ``radarcube_high_res``: 128 range x 32
   azimuth x 16 elevation bins; :func:`radarpc.dsp.tdm.radar_cube` with ``n_azimuth=32``,
   ``n_elevation=16``), its intensity in dB;
2. trilinear upsampling (``align_corners=False``) to ``upsample`` (official 256 x 256 x 128);
3. the ``n`` picks (official ``cfar_num_point`` 800,000) shared between the range slices in
   proportion to each slice's summed intensity ``w_r`` (:func:`weighted_allocation`:
   ``floor(n w_r / sum w)``, the rest to the largest slice);
4. in each range slice, its share of cells of highest intensity (:func:`peak_cells`); the points
   listed range slice by range slice, by decreasing intensity within one;
5. each cell's (range, azimuth, elevation), then Cartesian metres. The generation keeps those in
   its grid (the official code crops them to the field of view) and takes the first ones when
   there are more than it needs.

Step 5 reads the positions from the cube's own bin axes, sampled where the upsampling samples
the intensity: output index ``i`` of an axis of ``n_in`` bins upsampled to ``n_out`` sits at input
position ``(i + 1/2) n_in / n_out - 1/2``, clamped to ``[0, n_in - 1]``; range is interpolated
linearly, an angle linearly in its sine (the FFT's bins are uniform in spatial frequency). The
official code instead gives the upsampled range bin ``i`` the range ``(i + 1) r_max / n_out`` and
an angle the arcsine of an evenly spaced spatial frequency over the upsampled bins; radarpc keeps
its cube's axes, the ones its LiDAR and OS-CFAR points are placed on. Where one slice's share
exceeds its cells the share is cut to the slice (the official code stops with an assertion).

``source="os-cfar"`` takes radarpc's OS-CFAR baseline points
(:func:`radarpc.rald.oscfar_baseline.detect_points` on RaLD's 128 x 8 x 2 cube) instead, and
``"none"`` no point (random queries only).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from radarpc.dsp.tdm import RadarCube, radar_cube
from radarpc.rald.frustum import polar_to_cartesian
from radarpc.rald.oscfar_baseline import CubeAxes, OSCFARConfig, detect_points
from radarpc.sensors.coloradar import ColoRadarChipConfig

__all__ = [
    "GUIDE_SOURCES",
    "GuideConfig",
    "weighted_allocation",
    "peak_cells",
    "peak_points",
    "guide_points",
]

GUIDE_SOURCES: tuple[str, ...] = ("peaks", "os-cfar", "none")
"""Where the guided queries start: RaLD's intensity peaks, radarpc's OS-CFAR baseline, nowhere."""


@dataclass(frozen=True)
class GuideConfig:
    """A frame's guide points (defaults: the official helper points)."""

    source: str = "peaks"                                   # one of GUIDE_SOURCES
    n_points: int = 800_000                                 # peaks: cells picked per frame (cfar_num_point)
    angle_bins: tuple[int, int] = (32, 16)                  # peaks: azimuth, elevation FFT sizes of the cube
    upsample: tuple[int, int, int] = (256, 256, 128)        # peaks: (range, azimuth, elevation) bins picked from
    oscfar: OSCFARConfig = field(default_factory=OSCFARConfig)   # os-cfar: the baseline's parameters

    def __post_init__(self) -> None:
        if self.source not in GUIDE_SOURCES:
            raise ValueError(f"GuideConfig.source must be one of {list(GUIDE_SOURCES)}, got {self.source!r}")
        if isinstance(self.n_points, bool) or int(self.n_points) != self.n_points or self.n_points < 1:
            raise ValueError(f"GuideConfig.n_points must be an integer >= 1, got {self.n_points!r}")
        object.__setattr__(self, "n_points", int(self.n_points))
        for k, n in (("angle_bins", 2), ("upsample", 3)):
            v = tuple(getattr(self, k))
            if len(v) != n or any(isinstance(x, bool) or int(x) != x or x < 1 for x in v):
                raise ValueError(f"GuideConfig.{k} must be {n} integers >= 1, got {getattr(self, k)!r}")
            object.__setattr__(self, k, tuple(int(x) for x in v))
        if not isinstance(self.oscfar, OSCFARConfig):
            raise ValueError(f"GuideConfig.oscfar must be an OSCFARConfig, got {type(self.oscfar).__name__}")


def weighted_allocation(weights, total: int) -> torch.Tensor:
    """``total`` split in proportion to non-negative ``weights`` ``(R,)``: ``floor(total w_r / sum w)``,
    the remainder added to the first largest weight; an even split (the first ``total mod R``
    getting one more) when every weight is 0. Sums to ``total``; int64."""
    w = torch.as_tensor(weights, dtype=torch.float64).reshape(-1)
    if w.numel() == 0 or bool((w < 0).any()) or not bool(torch.isfinite(w).all()):
        raise ValueError("weights must be a non-empty vector of finite values >= 0")
    n = w.numel()
    s = float(w.sum())
    if s == 0.0:
        alloc = torch.full((n,), total // n, dtype=torch.int64)
        alloc[: total % n] += 1
        return alloc
    alloc = torch.floor(w / s * total).to(torch.int64)
    alloc[int(torch.argmax(w))] += int(total) - int(alloc.sum())
    return alloc


def peak_cells(intensity: torch.Tensor, n: int) -> torch.Tensor:
    """The ``n`` picked cells of an intensity cube ``(R, A, E)`` (see the module docstring, steps 3-4).

    Returns
    -------
    torch.Tensor, int64, ``(N, 3)``
        ``(range, azimuth, elevation)`` indices, range slice by range slice (ascending), by
        decreasing intensity within one (ties in index order); ``N = n`` unless a slice's share
        exceeds its ``A E`` cells.
    """
    x = torch.as_tensor(intensity)
    if x.ndim != 3:
        raise ValueError(f"intensity must be (R, A, E), got shape {tuple(x.shape)}")
    r, a, e = x.shape
    if not 1 <= int(n) <= x.numel():
        raise ValueError(f"n must be in [1, {x.numel()}] (the cube's cells), got {n}")
    flat = x.reshape(r, a * e).to(torch.float64)                                       # (R, A E)
    share = weighted_allocation(flat.sum(1).clamp_min(0), int(n)).clamp_max(a * e)     # (R,)
    order = torch.sort(flat, dim=1, descending=True, stable=True).indices              # (R, A E)
    take = torch.arange(a * e)[None, :] < share[:, None]                               # (R, A E)
    rows = torch.arange(r)[:, None].expand(r, a * e)[take]                             # (N,)
    cols = order[take]                                                                 # (N,)
    return torch.stack((rows, cols // e, cols % e), dim=-1)


def _sample_axis(values, n_out: int, *, sine: bool) -> torch.Tensor:
    """Bin positions of an axis of ``len(values)`` bins after ``align_corners=False`` resampling to
    ``n_out`` (linear in the value, or in its sine for an angle in radians)."""
    v = torch.as_tensor(np.asarray(values, dtype=np.float64))
    v = torch.sin(v) if sine else v
    n_in = v.numel()
    pos = ((torch.arange(n_out, dtype=torch.float64) + 0.5) * n_in / n_out - 0.5).clamp(0, n_in - 1)
    lo = pos.floor().to(torch.int64)
    hi = (lo + 1).clamp_max(n_in - 1)
    out = v[lo] + (pos - lo) * (v[hi] - v[lo])
    return torch.asin(out.clamp(-1, 1)) if sine else out


def peak_points(intensity_db, axes: CubeAxes, n: int = 800_000,
                upsample: tuple[int, int, int] = (256, 256, 128)) -> torch.Tensor:
    """RaLD's helper points of one cube: the ``n`` picked cells, Cartesian (module docstring).

    Parameters
    ----------
    intensity_db : torch.Tensor or ndarray, ``(R, A, E)``
        The cube's intensity in dB (official: 128 x 32 x 16).
    axes : CubeAxes
        Its bin centres (range m, azimuth and elevation deg).
    n : int
        Cells picked (official 800,000).
    upsample : (int, int, int)
        The grid they are picked from (official 256 x 256 x 128).

    Returns
    -------
    torch.Tensor, ``(N, 3)`` float32, CPU
        Cartesian metres, radar frame; in the order of :func:`peak_cells`.
    """
    x = torch.as_tensor(intensity_db, dtype=torch.float32).cpu()
    if x.ndim != 3 or tuple(x.shape) != axes.shape:
        raise ValueError(f"intensity must be (R, A, E) matching its axes {axes.shape}, got shape {tuple(x.shape)}")
    up = F.interpolate(x[None, None], size=tuple(int(s) for s in upsample), mode="trilinear",
                       align_corners=False)[0, 0]                                      # (R', A', E')
    ijk = peak_cells(up, n)                                                             # (N, 3)
    r = _sample_axis(axes.range_m, up.shape[0], sine=False)
    az = _sample_axis(np.radians(axes.azimuth_deg), up.shape[1], sine=True)
    el = _sample_axis(np.radians(axes.elevation_deg), up.shape[2], sine=True)
    rae = torch.stack((r[ijk[:, 0]], torch.rad2deg(az[ijk[:, 1]]), torch.rad2deg(el[ijk[:, 2]])), dim=-1)
    return polar_to_cartesian(rae).to(torch.float32)


def guide_points(cfg: GuideConfig, adc, chip: ColoRadarChipConfig, cube: RadarCube | None = None) -> np.ndarray:
    """A frame's guide points, ``(P, 3)`` float32 Cartesian metres (radar frame).

    Parameters
    ----------
    cfg : GuideConfig
    adc : complex array or tensor
        The frame's single-chip ADC samples ``(tx, rx, chirps, samples)`` (for ``"peaks"``).
    chip : ColoRadarChipConfig
        The single chip's configuration.
    cube : RadarCube, optional
        RaLD's 128 x 8 x 2 cube of the frame (for ``"os-cfar"``; computed from ``adc`` when None).
    """
    if cfg.source == "none":
        return np.zeros((0, 3), np.float32)
    if cfg.source == "peaks":
        hr = radar_cube(adc, chip, n_azimuth=cfg.angle_bins[0], n_elevation=cfg.angle_bins[1])
        axes = CubeAxes.from_radians(hr.range_m, hr.azimuth_rad, hr.elevation_rad)
        return peak_points(hr.intensity_db, axes, cfg.n_points, cfg.upsample).numpy()
    cube = radar_cube(adc, chip) if cube is None else cube
    axes = CubeAxes.from_radians(cube.range_m, cube.azimuth_rad, cube.elevation_rad)
    return detect_points(cube.intensity_db, axes, cfg.oscfar).cpu().numpy().astype(np.float32)
