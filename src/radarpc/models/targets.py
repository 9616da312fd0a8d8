"""RADIal's range-azimuth detection targets: encoding labels into the 128 x 224 map, and decoding it
back into detections with a confidence threshold and greedy NMS.

The map (RADIal ``FFTRadNet/dataset/encoder.py``; facts, not code, carried over):

* Rows are range cells of ``c_r = 4 x 0.201171875 = 0.8046875 m`` (row ``i`` starts at
  ``i c_r``); columns are azimuth cells of ``c_a = 0.8 deg``, column ``j`` starting at
  ``(j - 112) c_a`` (224 columns, -89.6 .. +89.6 deg, left positive).
* A vehicle at ``(R, A)`` lies in cell ``(i0, j0) = (floor(R / c_r), floor(A / c_a) + 112)``.
  Channel 0 (probability) is 1 on the ``3 x 3`` patch of cells around it; every patch cell
  ``(i, j)`` regresses the vehicle's offset from its own lower corner,

      t_r = (R - i c_r - mu_r) / sigma_r,        t_a = (A - (j - 112) c_a - mu_a) / sigma_a,

  so any patch cell decodes to the same point: ``R = i c_r + sigma_r t_r + mu_r`` (likewise ``A``).
* ``mu``, ``sigma`` are RADIal's ``reg_mean`` / ``reg_std``. They are (up to the data's noise)
  the moments of the raw offset over a 3 x 3 patch with a uniform in-cell position:
  ``mu = c / 2`` and ``sigma^2 = c^2 / 12 + (2/3) c^2`` (the patch adds ``-c, 0, +c`` with equal
  weight), i.e. ``sigma = 0.8660 c`` = 0.6969 m and 0.6928 deg, against RADIal's 0.6969 and
  0.6943; the defaults are RADIal's numbers so that the official weights decode unchanged.

Where radarpc departs from the official encoder (each only where the official code misbehaves):
patch cells outside the map are dropped at every edge (the official code paints nothing for a
vehicle in the last azimuth column and wraps negative row indices for ``R < c_r``); labels
whose own cell is outside the map are skipped; where the patches of two vehicles overlap, a
cell regresses the vehicle whose point is nearer to the cell's centre (in cell units), not the
label that happens to come last.

Decoding keeps the cells with probability ``>= threshold`` (RADIal: 0.05), turns each into a
point, and runs greedy non-maximum suppression on RADIal's fixed boxes
(:func:`radarpc.boxes.ra_to_box_xy`): a detection is dropped when its box IoU with a higher-scoring
kept one is ``>= nms_iou`` (0.05). The result is a :class:`radarpc.boxes.Detections`: detections of
``B`` frames concatenated with a cumulative ``offset``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.spatial import cKDTree

from radarpc.boxes import BOX_LENGTH_M, BOX_WIDTH_M, Detections, ra_to_box_xy

__all__ = [
    "RANGE_CELL_M",
    "AZIMUTH_CELL_DEG",
    "RADIAL_REG_MEAN",
    "RADIAL_REG_STD",
    "TargetConfig",
    "encode_targets",
    "encode_batch",
    "decode_detections",
    "nms",
]

RANGE_CELL_M = 4 * 0.201171875
"""Range cell of the detection map: 4 RD range bins of RADIal (0.8046875 m)."""
AZIMUTH_CELL_DEG = 4 * 0.2
"""Azimuth cell of the detection map: 4 columns of RADIal's 0.2-degree RA grid (0.8 deg)."""
RADIAL_REG_MEAN = (0.4048094369863972, 0.3997392847799934)
"""RADIal's ``reg_mean`` (range m, azimuth deg) of the regression offsets."""
RADIAL_REG_STD = (0.6968599580482511, 0.6942950877813826)
"""RADIal's ``reg_std`` (range m, azimuth deg) of the regression offsets."""


@dataclass(frozen=True)
class TargetConfig:
    """The range-azimuth target map and its regression statistics (RADIal's by default).

    Attributes
    ----------
    n_range, n_azimuth : int
        Map rows (range cells) and columns (azimuth cells); column ``n_azimuth // 2`` starts at 0 deg.
    range_cell_m, azimuth_cell_deg : float
        Cell size.
    patch : int
        Odd side of the square patch of positive cells around a vehicle's cell.
    reg_mean, reg_std : tuple of float
        ``(range m, azimuth deg)`` statistics that normalise the offsets.
    """

    n_range: int = 128
    n_azimuth: int = 224
    range_cell_m: float = RANGE_CELL_M
    azimuth_cell_deg: float = AZIMUTH_CELL_DEG
    patch: int = 3
    reg_mean: tuple[float, float] = RADIAL_REG_MEAN
    reg_std: tuple[float, float] = RADIAL_REG_STD

    def __post_init__(self) -> None:
        if self.n_range < 1 or self.n_azimuth < 2 or self.n_azimuth % 2:
            raise ValueError(f"TargetConfig: n_range must be >= 1 and n_azimuth even and >= 2, got "
                             f"{self.n_range} x {self.n_azimuth}")
        if not (self.range_cell_m > 0 and self.azimuth_cell_deg > 0):
            raise ValueError(f"TargetConfig: cell sizes must be > 0, got {self.range_cell_m} m x "
                             f"{self.azimuth_cell_deg} deg")
        if self.patch < 1 or self.patch % 2 == 0:
            raise ValueError(f"TargetConfig: patch must be an odd number >= 1, got {self.patch}")
        if len(self.reg_mean) != 2 or len(self.reg_std) != 2 or min(self.reg_std) <= 0:
            raise ValueError(f"TargetConfig: reg_mean and reg_std must be (range, azimuth) pairs with std > 0, "
                             f"got {self.reg_mean}, {self.reg_std}")

    @property
    def shape(self) -> tuple[int, int, int]:
        """Target map shape ``(3, n_range, n_azimuth)``: probability, range offset, azimuth offset."""
        return (3, self.n_range, self.n_azimuth)


# ---------------------------------------------------------------------------------------------
# encoding
# ---------------------------------------------------------------------------------------------

def encode_targets(labels: torch.Tensor, cfg: TargetConfig = TargetConfig()) -> torch.Tensor:
    """The target map of one frame.

    Parameters
    ----------
    labels : float ``(n, >= 2)``
        Label rows whose columns 0 and 1 are range (m) and azimuth (deg), e.g. the readers'
        :data:`~radarpc.data.radial_format.LABEL_TENSOR_COLUMNS` rows.
    cfg : TargetConfig

    Returns
    -------
    float32 ``(3, n_range, n_azimuth)`` on ``labels.device``: probability (0 or 1), normalised
    range offset, normalised azimuth offset (0 outside the patches).
    """
    lab = torch.as_tensor(labels)
    if lab.ndim != 2 or lab.shape[1] < 2:
        raise ValueError(f"labels must be (n, >= 2) with range_m, azimuth_deg in columns 0 and 1, got shape "
                         f"{tuple(lab.shape)}")
    ra = lab[:, :2].detach().to("cpu", torch.float64).numpy()                 # (n, 2)
    out = np.zeros(cfg.shape, dtype=np.float64)
    half_a = cfg.n_azimuth // 2
    s = cfg.patch // 2
    best = np.full((cfg.n_range, cfg.n_azimuth), np.inf)                     # distance of the owner
    for r, a in ra:
        if not (np.isfinite(r) and np.isfinite(a)):
            continue
        i0 = math.floor(r / cfg.range_cell_m)
        j0 = math.floor(a / cfg.azimuth_cell_deg) + half_a
        if not (0 <= i0 < cfg.n_range and 0 <= j0 < cfg.n_azimuth):
            continue                                                          # outside the map
        i = np.arange(max(i0 - s, 0), min(i0 + s + 1, cfg.n_range))[:, None]   # (p, 1)
        j = np.arange(max(j0 - s, 0), min(j0 + s + 1, cfg.n_azimuth))[None, :]  # (1, q)
        off_r = r - i * cfg.range_cell_m                                      # (p, 1) raw offsets
        off_a = a - (j - half_a) * cfg.azimuth_cell_deg                       # (1, q)
        # distance (cells) from the point to each cell's centre: nearer vehicles own shared cells
        dist = np.hypot(off_r / cfg.range_cell_m - 0.5, off_a / cfg.azimuth_cell_deg - 0.5)  # (p, q)
        own = dist < best[i, j]
        best[i, j] = np.where(own, dist, best[i, j])
        ii, jj = np.broadcast_arrays(i, j)
        ii, jj = ii[own], jj[own]
        out[0, ii, jj] = 1.0
        out[1, ii, jj] = np.broadcast_to((off_r - cfg.reg_mean[0]) / cfg.reg_std[0], own.shape)[own]
        out[2, ii, jj] = np.broadcast_to((off_a - cfg.reg_mean[1]) / cfg.reg_std[1], own.shape)[own]
    return torch.from_numpy(out.astype(np.float32)).to(lab.device)


def encode_batch(labels: torch.Tensor, label_offset: torch.Tensor,
                 cfg: TargetConfig = TargetConfig()) -> torch.Tensor:
    """Target maps ``(B, 3, n_range, n_azimuth)`` of offset-batched labels (frame ``b`` holds rows
    ``label_offset[b-1]:label_offset[b]``, as :class:`~radarpc.data.point_dataset.PointFrameBatch`)."""
    ends = [int(e) for e in label_offset]
    starts = [0] + ends[:-1]
    if not ends:
        return torch.zeros((0, *cfg.shape), device=labels.device)
    return torch.stack([encode_targets(labels[a:b], cfg) for a, b in zip(starts, ends)])


# ---------------------------------------------------------------------------------------------
# NMS
# ---------------------------------------------------------------------------------------------

def nms(score: torch.Tensor, xy: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Greedy NMS: indices of the kept detections, by decreasing score.

    Visiting detections by decreasing score (ties in input order), a detection is kept unless its
    box IoU with an already kept one is ``>= iou_threshold`` (RADIal drops ``IoU >= 0.05``).

    The fixed boxes overlap only when ``|dx| < W`` and ``|dy| < L``, so the overlapping pairs are
    found with a KD-tree (Chebyshev distance on ``(x / W, y / L)``) and the greedy scan walks that
    sparse graph: time and memory grow with the number of overlapping pairs, not ``K^2``, which
    keeps an untrained model's ~28k candidate cells per frame cheap. Computed on the CPU; the
    indices are returned on ``score.device``.

    Raises
    ------
    ValueError
        ``iou_threshold <= 0`` (every pair would suppress, overlapping or not).
    """
    if not iou_threshold > 0:
        raise ValueError(f"nms: iou_threshold must be > 0, got {iou_threshold}")
    s = score.detach().to("cpu", torch.float64).numpy()
    p = xy.detach().to("cpu", torch.float64).numpy().reshape(-1, 2)
    order = np.argsort(-s, kind="stable")
    pairs = cKDTree(p / [BOX_WIDTH_M, BOX_LENGTH_M]).query_pairs(1.0, p=np.inf, output_type="ndarray")  # (E, 2)
    if len(pairs):
        d = np.abs(p[pairs[:, 0]] - p[pairs[:, 1]])
        inter = np.clip(BOX_WIDTH_M - d[:, 0], 0, None) * np.clip(BOX_LENGTH_M - d[:, 1], 0, None)
        pairs = pairs[inter / (2 * BOX_WIDTH_M * BOX_LENGTH_M - inter) >= iou_threshold]
    n = s.size
    graph = coo_matrix((np.ones(2 * len(pairs), bool), (np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]])),
                       shape=(n, n)).tocsr()
    suppressed = np.zeros(n, bool)
    keep = []
    for i in order.tolist():
        if not suppressed[i]:
            keep.append(i)
            suppressed[graph.indices[graph.indptr[i]:graph.indptr[i + 1]]] = True
    return torch.tensor(keep, dtype=torch.int64, device=score.device)


# ---------------------------------------------------------------------------------------------
# decoding
# ---------------------------------------------------------------------------------------------

def decode_detections(maps: torch.Tensor, cfg: TargetConfig = TargetConfig(), threshold: float = 0.05,
                      nms_iou: float | None = 0.05) -> Detections:
    """Detections from predicted (or target) maps, as RADIal decodes them.

    Parameters
    ----------
    maps : float ``(B, 3, n_range, n_azimuth)``
        Channel 0 a probability (the heads apply the sigmoid), channels 1 and 2 the normalised
        range and azimuth offsets.
    cfg : TargetConfig
    threshold : float
        Cells with probability ``>= threshold`` become candidates (RADIal: 0.05).
    nms_iou : float or None
        Greedy NMS IoU (:func:`nms`; RADIal: 0.05). ``None`` keeps every candidate.

    Returns
    -------
    Detections on ``maps.device``, float32, sorted by decreasing score within each frame.
    """
    if maps.ndim != 4 or tuple(maps.shape[1:]) != cfg.shape:
        raise ValueError(f"maps must be (B, {', '.join(map(str, cfg.shape))}), got shape {tuple(maps.shape)}")
    m = maps.detach().float()
    b, i, j = torch.nonzero(m[:, 0] >= threshold, as_tuple=True)               # candidate cells
    score = m[b, 0, i, j]
    rng = i * cfg.range_cell_m + m[b, 1, i, j] * cfg.reg_std[0] + cfg.reg_mean[0]
    az = (j - cfg.n_azimuth // 2) * cfg.azimuth_cell_deg + m[b, 2, i, j] * cfg.reg_std[1] + cfg.reg_mean[1]
    counts = torch.bincount(b, minlength=maps.shape[0])
    if nms_iou is not None:
        xy = ra_to_box_xy(rng, az)
        kept, counts_k = [], []
        start = 0
        for n in counts.tolist():       # nonzero is row-major: frame b's candidates are contiguous
            k = nms(score[start:start + n], xy[start:start + n], nms_iou) + start
            kept.append(k)
            counts_k.append(k.numel())
            start += n
        idx = torch.cat(kept) if kept else b.new_zeros(0)
        counts = torch.tensor(counts_k, dtype=torch.int64, device=maps.device)
    else:
        # sort by decreasing score within each frame (frame-major, then score)
        key = torch.sort(score, descending=True, stable=True).indices
        idx = key[torch.sort(b[key], stable=True).indices]
    return Detections(score[idx], rng[idx], az[idx], torch.cumsum(counts, 0))
