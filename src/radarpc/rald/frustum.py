"""Frustum occupancy in sensor polar coordinates (RaLD, Eqs. 6-8): voxelize, look up, sample queries.

A frustum cell :math:`\\mathcal{F}_{i,j,k}` is the set of points whose range, azimuth and
elevation fall in ``[r_i, r_{i+1}) x [theta_j, theta_{j+1}) x [phi_k, phi_{k+1})``; it is occupied
(:math:`O_{i,j,k} = 1`) if at least one LiDAR point falls inside it, and a query point takes the
occupancy of the cell that contains it.

One frustum: the sensor's field of view (:class:`radarpc.sensors.coloradar.RadarFOV`, the same
object :func:`radarpc.data.coloradar.frustum_mask` crops the LiDAR ground truth to) is the
frustum, and a :class:`FrustumGrid` is its discretisation into cells of a given size
(:meth:`FrustumGrid.from_fov`).  :data:`RALD_GRID` discretises :data:`AWR1843_FOV` (range
0..15.863 m, azimuth -90..90 deg, elevation -20..20 deg) with RaLD's cells (:data:`RALD_CELL`:
0.05 m, 0.25 deg, 0.5 deg): ``ceil(15.863 / 0.05) = 318`` range cells to 15.9 m, i.e.
318 x 720 x 80 cells.  RaLD's public configuration (``pc_range`` / ``voxel_size``) stops at
15.8 m (316 range cells); radarpc's grid spans the FOV instead so that there is one frustum:
otherwise the LiDAR points between 15.8 m and 15.863 m would be ground truth that the grid cannot
represent.  Cells past the FOV's range (15.863..15.9 m) simply stay empty.

Conventions (the same as :mod:`radarpc.sensors.radial`):

* Cartesian radar frame: x forward, y left, z up, metres.
* Polar coordinates ``(r, a, e)``: range ``r = |p|`` in metres, azimuth ``a = atan2(y, x)`` in
  degrees with **left positive**, elevation ``e = atan2(z, hypot(x, y))`` in degrees, up positive;
  ``p = r (cos e cos a, cos e sin a, sin e)``.  (RaLD's public code negates the azimuth, i.e.
  right positive; radarpc keeps the left-positive convention of the rest of the package.)
* Normalized coordinates: each polar axis mapped affinely to [-1, 1] over the grid's span,
  ``u = (p - (lo + hi) / 2) / ((hi - lo) / 2)`` (RaLD's anisotropic normalization).
* Cells are stored sparsely as sorted unique linear indices ``(i * n_az + j) * n_el + k`` (int64);
  the dense ``(n_r, n_az, n_el)`` grid (18 M cells for :data:`RALD_GRID`) is never allocated unless
  :meth:`OccupancyGrid.dense` is called.

Everything is torch and device-agnostic: outputs live on the device of the inputs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Sequence

import torch

from radarpc.sensors.coloradar import AWR1843_FOV, RadarFOV

__all__ = [
    "FrustumGrid",
    "OccupancyGrid",
    "RALD_CELL",
    "RALD_GRID",
    "cartesian_to_polar",
    "polar_to_cartesian",
    "normalize",
    "denormalize",
    "in_frustum",
    "cell_indices",
    "voxelize",
    "voxelize_batch",
    "occupancy",
    "sample_queries",
    "sample_queries_batch",
    "occupancy_to_polar",
    "occupancy_to_points",
]

Coords = Literal["cartesian", "polar", "normalized"]
_COORDS = ("cartesian", "polar", "normalized")

# Jitter is drawn in [_EDGE, 1 - _EDGE] of a cell so that float32 rounding of a normalized
# query can never move it across a cell edge (0.1 % of a cell is ~12,000 float32 ulps).
_EDGE = 1e-3


@dataclass(frozen=True)
class FrustumGrid:
    """A regular grid in (range, azimuth, elevation): the frustum cells of RaLD.

    The number of cells per axis is ``round((hi - lo) / cell)``; the span must be a whole
    number of cells.  Build the grid of a sensor with :meth:`from_fov`.
    """

    range_m: tuple[float, float]               # [r_min, r_max] in metres
    azimuth_deg: tuple[float, float]           # [theta_min, theta_max], left positive
    elevation_deg: tuple[float, float]         # [phi_min, phi_max], up positive
    cell: tuple[float, float, float]           # cell size: metres, degrees, degrees

    def __post_init__(self) -> None:
        names = ("range_m", "azimuth_deg", "elevation_deg")
        if len(self.cell) != 3:
            raise ValueError(f"FrustumGrid.cell must have 3 entries (range, azimuth, elevation), got {self.cell}")
        for ax, (name, c) in enumerate(zip(names, self.cell)):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
                raise ValueError(f"FrustumGrid.{name}={getattr(self, name)} must be finite with max > min")
            if not (math.isfinite(c) and c > 0):
                raise ValueError(f"FrustumGrid.cell[{ax}]={c} must be positive")
            n = (hi - lo) / c
            if abs(n - round(n)) > 1e-6 * max(1.0, n):
                raise ValueError(f"FrustumGrid.{name} span {hi - lo} is not a whole number of cells of {c}")
        if self.range_m[0] < 0:
            raise ValueError(f"FrustumGrid.range_m={self.range_m} must start at 0 or above")
        if self.azimuth_deg[0] < -180 or self.azimuth_deg[1] > 180:
            raise ValueError(f"FrustumGrid.azimuth_deg={self.azimuth_deg} must lie in [-180, 180]")
        if self.elevation_deg[0] < -90 or self.elevation_deg[1] > 90:
            raise ValueError(f"FrustumGrid.elevation_deg={self.elevation_deg} must lie in [-90, 90]")

    @classmethod
    def from_fov(cls, fov: RadarFOV, cell: tuple[float, float, float]) -> "FrustumGrid":
        """The grid of ``cell``-sized cells that covers the field of view ``fov``.

        Each polar axis starts at the FOV's lower bound and takes ``n = ceil((hi - lo) / cell)``
        cells, so the grid spans the whole FOV; where the FOV's span is not a whole number of cells
        the last cell reaches past it (AWR1843's 15.863 m at 0.05 m: 318 cells, to 15.9 m) and the
        cells beyond the FOV stay empty, as the ground truth is cropped to the FOV.

        Parameters
        ----------
        fov : RadarFOV
            Range, azimuth and elevation intervals of the sensor (the LiDAR crop).
        cell : tuple of 3 floats
            Cell size in range (m), azimuth (deg) and elevation (deg).
        """
        if len(cell) != 3 or not all(math.isfinite(c) and c > 0 for c in cell):
            raise ValueError(f"cell must be 3 positive sizes (range, azimuth, elevation), got {cell}")
        edges = []
        for (lo, hi), c in zip(((fov.min_range_m, fov.max_range_m), fov.azimuth_deg, fov.elevation_deg), cell):
            q = (hi - lo) / c
            n = math.ceil(q - 1e-6 * max(1.0, q))   # a whole-number span up to rounding keeps its n
            edges.append((lo, lo + n * c))
        return cls(*edges, cell=tuple(cell))

    @property
    def lo(self) -> tuple[float, float, float]:
        """Lower edges ``(r_min, theta_min, phi_min)``."""
        return (self.range_m[0], self.azimuth_deg[0], self.elevation_deg[0])

    @property
    def hi(self) -> tuple[float, float, float]:
        """Upper edges ``(r_max, theta_max, phi_max)``."""
        return (self.range_m[1], self.azimuth_deg[1], self.elevation_deg[1])

    @property
    def shape(self) -> tuple[int, int, int]:
        """Cells per axis ``(n_r, n_az, n_el)``; ``(318, 720, 80)`` for :data:`RALD_GRID`."""
        return tuple(int(round((h - l) / c)) for l, h, c in zip(self.lo, self.hi, self.cell))

    @property
    def n_cells(self) -> int:
        n_r, n_az, n_el = self.shape
        return n_r * n_az * n_el

    def _tensors(self, device, dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        lo = torch.tensor(self.lo, device=device, dtype=dtype)
        hi = torch.tensor(self.hi, device=device, dtype=dtype)
        cell = torch.tensor(self.cell, device=device, dtype=dtype)
        return lo, hi, cell


RALD_CELL = (0.05, 0.25, 0.5)
"""RaLD's frustum cell: 0.05 m in range, 0.25 deg in azimuth, 0.5 deg in elevation."""

RALD_GRID = FrustumGrid.from_fov(AWR1843_FOV, RALD_CELL)
"""RaLD's occupancy grid over the AWR1843 field of view: 318 x 720 x 80 cells, range 0..15.9 m."""


@dataclass
class OccupancyGrid:
    """Sparse frustum occupancy of one point cloud.

    Attributes
    ----------
    grid : FrustumGrid
        The cell layout.
    cells : torch.Tensor, int64, ``(M,)``
        Sorted unique linear indices ``(i * n_az + j) * n_el + k`` of the occupied cells.
    n_points : int
        Points of the input cloud that fell inside the frustum.
    n_outside : int
        Points of the input cloud outside the frustum (dropped).
    """

    grid: FrustumGrid
    cells: torch.Tensor
    n_points: int = 0
    n_outside: int = 0

    def __post_init__(self) -> None:
        c = self.cells
        if c.dtype != torch.int64 or c.ndim != 1:
            raise ValueError(f"OccupancyGrid.cells must be a 1-D int64 tensor, got {c.dtype} "
                             f"of shape {tuple(c.shape)}")
        if c.numel() and (int(c[0]) < 0 or int(c[-1]) >= self.grid.n_cells or bool((c[1:] <= c[:-1]).any())):
            raise ValueError(f"OccupancyGrid.cells must be sorted unique indices in [0, {self.grid.n_cells})")

    @property
    def n_occupied(self) -> int:
        return int(self.cells.numel())

    @property
    def device(self) -> torch.device:
        return self.cells.device

    def dense(self) -> torch.Tensor:
        """The dense boolean grid ``(n_r, n_az, n_el)`` (18 M cells for :data:`RALD_GRID`; only when asked)."""
        out = torch.zeros(self.grid.n_cells, dtype=torch.bool, device=self.cells.device)
        out[self.cells] = True
        return out.view(self.grid.shape)

    def ijk(self) -> torch.Tensor:
        """Integer cell indices ``(M, 3)`` = (range, azimuth, elevation) of the occupied cells."""
        return _unravel(self.grid, self.cells)


# ---- coordinates ------------------------------------------------------------------------------

def _points(x, name: str = "points") -> torch.Tensor:
    t = torch.as_tensor(x)
    if t.is_complex():
        raise ValueError(f"{name} must be real, got complex dtype {t.dtype}")
    if t.ndim < 1 or t.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got {tuple(t.shape)}")
    if not t.is_floating_point():
        t = t.to(torch.float32)
    if t.numel() and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or infinite values")
    return t


def cartesian_to_polar(xyz) -> torch.Tensor:
    """Cartesian ``(x, y, z)`` -> polar ``(r [m], azimuth [deg], elevation [deg])``.

    Parameters
    ----------
    xyz : array-like or torch.Tensor, ``(..., 3)``
        Points in the radar frame (x forward, y left, z up).

    Returns
    -------
    torch.Tensor, ``(..., 3)``
        ``r = |p|``, ``a = atan2(y, x)`` (left positive), ``e = atan2(z, hypot(x, y))``;
        the origin maps to ``(0, 0, 0)``.
    """
    p = _points(xyz, "xyz")
    x, y, z = p.unbind(-1)
    rho = torch.hypot(x, y)
    r = torch.hypot(rho, z)
    az = torch.rad2deg(torch.atan2(y, x))
    el = torch.rad2deg(torch.atan2(z, rho))
    return torch.stack((r, az, el), dim=-1)


def polar_to_cartesian(rae) -> torch.Tensor:
    """Polar ``(r [m], azimuth [deg], elevation [deg])`` -> Cartesian ``(x, y, z)``.

    ``p = r (cos e cos a, cos e sin a, sin e)``, the inverse of :func:`cartesian_to_polar`.
    """
    p = _points(rae, "rae")
    r, az, el = p.unbind(-1)
    a, e = torch.deg2rad(az), torch.deg2rad(el)
    ce = torch.cos(e)
    return torch.stack((r * ce * torch.cos(a), r * ce * torch.sin(a), r * torch.sin(e)), dim=-1)


def normalize(grid: FrustumGrid, rae) -> torch.Tensor:
    """Polar -> normalized: ``u = (p - (lo + hi) / 2) / ((hi - lo) / 2)`` per axis, so the grid is [-1, 1]^3."""
    p = _points(rae, "rae")
    lo, hi, _ = grid._tensors(p.device, p.dtype)
    return (p - 0.5 * (lo + hi)) / (0.5 * (hi - lo))


def denormalize(grid: FrustumGrid, u) -> torch.Tensor:
    """Normalized -> polar: ``p = u (hi - lo) / 2 + (lo + hi) / 2`` per axis."""
    q = _points(u, "normalized points")
    lo, hi, _ = grid._tensors(q.device, q.dtype)
    return q * (0.5 * (hi - lo)) + 0.5 * (lo + hi)


def _to_polar(grid: FrustumGrid, points, coords: str) -> torch.Tensor:
    if coords not in _COORDS:
        raise ValueError(f"coords must be one of {_COORDS}, got {coords!r}")
    if coords == "cartesian":
        return cartesian_to_polar(points)
    if coords == "normalized":
        return denormalize(grid, points)
    return _points(points, "rae")


def in_frustum(grid: FrustumGrid, points, *, coords: Coords = "cartesian") -> torch.Tensor:
    """Boolean mask ``(...,)``: the point lies in the closed box ``[lo, hi]`` of every polar axis."""
    p = _to_polar(grid, points, coords)
    lo, hi, _ = grid._tensors(p.device, p.dtype)
    return ((p >= lo) & (p <= hi)).all(dim=-1)


def cell_indices(grid: FrustumGrid, points, *, coords: Coords = "cartesian") -> tuple[torch.Tensor, torch.Tensor]:
    """Linear cell index of each point and whether it lies inside the frustum.

    Parameters
    ----------
    grid : FrustumGrid
    points : array-like or torch.Tensor, ``(..., 3)``
        Points in ``coords`` coordinates.
    coords : {"cartesian", "polar", "normalized"}

    Returns
    -------
    index : torch.Tensor, int64, ``(...,)``
        ``(i * n_az + j) * n_el + k`` with ``i = floor((r - r_min) / dr)`` etc.; a point exactly on
        the upper edge belongs to the last cell.  Meaningless where ``inside`` is False.
    inside : torch.Tensor, bool, ``(...,)``
    """
    p = _to_polar(grid, points, coords)
    lo, hi, cell = grid._tensors(p.device, p.dtype)
    inside = ((p >= lo) & (p <= hi)).all(dim=-1)
    n = torch.tensor(grid.shape, device=p.device)
    ijk = torch.floor((p - lo) / cell).to(torch.int64)
    ijk = torch.minimum(ijk.clamp_min(0), n - 1)
    return _ravel(grid, ijk), inside


def _ravel(grid: FrustumGrid, ijk: torch.Tensor) -> torch.Tensor:
    _, n_az, n_el = grid.shape
    return (ijk[..., 0] * n_az + ijk[..., 1]) * n_el + ijk[..., 2]


def _unravel(grid: FrustumGrid, lin: torch.Tensor) -> torch.Tensor:
    _, n_az, n_el = grid.shape
    k = lin % n_el
    j = (lin // n_el) % n_az
    i = lin // (n_el * n_az)
    return torch.stack((i, j, k), dim=-1)


# ---- occupancy --------------------------------------------------------------------------------

def voxelize(grid: FrustumGrid, points, *, coords: Coords = "cartesian") -> OccupancyGrid:
    """Occupancy of a point cloud: the sorted unique cells holding at least one point (Eq. 7).

    Parameters
    ----------
    grid : FrustumGrid
    points : array-like or torch.Tensor, ``(N, 3)``
        One LiDAR cloud (N may be 0); points outside the frustum are dropped and counted.
    coords : {"cartesian", "polar", "normalized"}
        Coordinates of ``points``.

    Returns
    -------
    OccupancyGrid
        On the device of ``points``; memory O(N), the dense grid is never built.
    """
    p = _points(points, "points")
    if p.ndim != 2:
        raise ValueError(f"points must have shape (N, 3), got {tuple(p.shape)}")
    lin, inside = cell_indices(grid, p, coords=coords)
    cells = torch.unique(lin[inside], sorted=True)   # (M,)
    n_in = int(inside.sum())
    return OccupancyGrid(grid=grid, cells=cells, n_points=n_in, n_outside=int(p.shape[0]) - n_in)


def voxelize_batch(grid: FrustumGrid, points, offset, *, coords: Coords = "cartesian") -> list[OccupancyGrid]:
    """:func:`voxelize` for a batch of clouds concatenated Pointcept-style.

    Parameters
    ----------
    grid : FrustumGrid
    points : array-like or torch.Tensor, ``(sum N_b, 3)``
        The clouds one after the other (e.g. from :func:`radarpc.data.coloradar.collate_coloradar`).
    offset : array-like or torch.Tensor, int, ``(B,)``
        Cumulative end index of each cloud (``offset[-1] == len(points)``).
    coords : {"cartesian", "polar", "normalized"}

    Returns
    -------
    list of OccupancyGrid
        One per cloud, on the device of ``points``; one ``unique`` over the whole batch.
    """
    p = _points(points, "points")
    if p.ndim != 2:
        raise ValueError(f"points must have shape (N, 3), got {tuple(p.shape)}")
    off = torch.as_tensor(offset, device=p.device)
    if off.ndim != 1 or off.numel() == 0 or off.is_floating_point():
        raise ValueError(f"offset must be a non-empty 1-D integer tensor, got {tuple(off.shape)} {off.dtype}")
    off = off.to(torch.int64)
    if bool((off[1:] < off[:-1]).any()) or int(off[0]) < 0 or int(off[-1]) != p.shape[0]:
        raise ValueError(f"offset must be non-decreasing cumulative sizes ending at len(points)={p.shape[0]}, "
                         f"got {off.tolist()}")
    batch = torch.bucketize(torch.arange(p.shape[0], device=p.device), off, right=True)   # (N,) cloud of each point
    lin, inside = cell_indices(grid, p, coords=coords)
    keyed = torch.unique(batch[inside] * grid.n_cells + lin[inside], sorted=True)            # (M_total,)
    which = keyed // grid.n_cells
    bounds = torch.searchsorted(which, torch.arange(off.numel() + 1, device=p.device))
    n_in = torch.bincount(batch[inside], minlength=off.numel())
    sizes = torch.diff(off, prepend=off.new_zeros(1))
    return [OccupancyGrid(grid, keyed[bounds[b]:bounds[b + 1]] - b * grid.n_cells, int(n_in[b]),
                          int(sizes[b] - n_in[b])) for b in range(off.numel())]


def _lookup(sorted_cells: torch.Tensor, lin: torch.Tensor) -> torch.Tensor:
    # Membership of each linear index in the sorted set: one binary search per query.
    if sorted_cells.numel() == 0:
        return torch.zeros(lin.shape, dtype=torch.bool, device=lin.device)
    pos = torch.searchsorted(sorted_cells, lin.reshape(-1)).clamp_max(sorted_cells.numel() - 1)
    return (sorted_cells[pos] == lin.reshape(-1)).view(lin.shape)


def occupancy(occ: OccupancyGrid, queries, *, coords: Coords = "normalized") -> torch.Tensor:
    """Occupancy ``O(q)`` of arbitrary query points (Eq. 8): True where the containing cell is occupied.

    Parameters
    ----------
    occ : OccupancyGrid
    queries : array-like or torch.Tensor, ``(..., 3)``
        Query points in ``coords`` coordinates (default: normalized, as the decoder sees them).
    coords : {"normalized", "polar", "cartesian"}

    Returns
    -------
    torch.Tensor, bool, ``(...,)``
        False for queries outside the frustum.
    """
    q = _points(queries, "queries").to(occ.cells.device)
    lin, inside = cell_indices(occ.grid, q, coords=coords)
    return _lookup(occ.cells, lin) & inside


def sample_queries(
    occ: OccupancyGrid,
    n: int = 10_000,
    positive_ratio: float = 0.0625,
    *,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    shuffle: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Training queries for the occupancy decoder: positives in occupied cells, negatives in empty ones.

    ``n_pos = floor(n * positive_ratio)`` queries (exactly; 625 of 10,000 by default, RaLD's 6.25 %)
    are drawn by choosing occupied cells uniformly with replacement; the other ``n - n_pos`` by
    choosing cells uniformly among the empty ones (vectorized rejection sampling on random cells).
    Each query is jittered uniformly within its cell (the central 99.8 %, see ``_EDGE``) and
    returned normalized to [-1, 1].  Positives come first, then negatives (as in RaLD), unless
    ``shuffle``.

    Parameters
    ----------
    occ : OccupancyGrid
    n : int
        Total number of queries.
    positive_ratio : float
        Fraction of positives, in [0, 1].
    generator : torch.Generator, optional
        On the device of ``occ.cells``; makes the draw reproducible.
    dtype : torch.dtype
        Floating dtype of the returned queries.
    shuffle : bool
        Randomly permute queries and labels together.

    Returns
    -------
    queries : torch.Tensor, ``(n, 3)``
        Normalized polar coordinates.
    labels : torch.Tensor, bool, ``(n,)``
        True for the ``n_pos`` positives.

    Raises
    ------
    ValueError
        Bad ``n`` or ``positive_ratio``; positives requested from an empty occupancy (an empty
        LiDAR scan); negatives requested from a fully occupied grid.
    """
    if int(n) != n or n < 1:
        raise ValueError(f"n must be a positive integer, got {n}")
    if not (0.0 <= positive_ratio <= 1.0):
        raise ValueError(f"positive_ratio must lie in [0, 1], got {positive_ratio}")
    n = int(n)
    n_pos = int(math.floor(n * positive_ratio + 1e-9))
    n_neg = n - n_pos
    grid, dev = occ.grid, occ.cells.device
    m = occ.n_occupied
    if n_pos and m == 0:
        raise ValueError("cannot sample positive queries: the occupancy grid is empty (empty LiDAR scan "
                         "or no point inside the frustum)")
    if n_neg and m >= grid.n_cells:
        raise ValueError("cannot sample negative queries: every cell of the grid is occupied")

    pos = occ.cells[torch.randint(0, max(m, 1), (n_pos,), device=dev, generator=generator)]   # (n_pos,)
    neg = _sample_empty(occ, n_neg, generator)                                                 # (n_neg,)
    lin = torch.cat((pos, neg))                                                                # (n,)

    lo, _, cell = grid._tensors(dev, torch.float64)
    u = torch.rand((n, 3), device=dev, generator=generator, dtype=torch.float64)
    u = _EDGE + (1.0 - 2.0 * _EDGE) * u
    rae = lo + (_unravel(grid, lin).to(torch.float64) + u) * cell      # (n, 3) polar
    queries = normalize(grid, rae).to(dtype)
    labels = torch.zeros(n, dtype=torch.bool, device=dev)
    labels[:n_pos] = True
    if shuffle:
        perm = torch.randperm(n, device=dev, generator=generator)
        queries, labels = queries[perm], labels[perm]
    return queries, labels


def _sample_empty(occ: OccupancyGrid, k: int, generator: torch.Generator | None) -> torch.Tensor:
    dev = occ.cells.device
    total = occ.grid.n_cells
    if k == 0:
        return torch.zeros(0, dtype=torch.int64, device=dev)
    empty_frac = 1.0 - occ.n_occupied / total
    out: list[torch.Tensor] = []
    have = 0
    while have < k:   # ends: each round keeps a draw with probability empty_frac > 0
        need = k - have
        draw = int(math.ceil(need / empty_frac * 1.2)) + 16
        cand = torch.randint(0, total, (draw,), device=dev, generator=generator)
        cand = cand[~_lookup(occ.cells, cand)][:need]
        out.append(cand)
        have += int(cand.numel())
    return torch.cat(out)


def sample_queries_batch(
    occs: Sequence[OccupancyGrid],
    n: int = 10_000,
    positive_ratio: float = 0.0625,
    *,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    shuffle: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`sample_queries` for a batch of frames: queries ``(B, n, 3)`` and labels ``(B, n)``."""
    if len(occs) == 0:
        raise ValueError("sample_queries_batch needs at least one OccupancyGrid")
    qs, ls = zip(*(sample_queries(o, n, positive_ratio, generator=generator, dtype=dtype, shuffle=shuffle)
                        for o in occs))
    return torch.stack(qs), torch.stack(ls)


def occupancy_to_polar(occ: OccupancyGrid, *, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Polar centres ``(M, 3)`` of the occupied cells, ``lo + (ijk + 1/2) * cell``."""
    lo, _, cell = occ.grid._tensors(occ.cells.device, torch.float64)
    rae = lo + (occ.ijk().to(torch.float64) + 0.5) * cell
    return rae.to(dtype)


def occupancy_to_points(occ: OccupancyGrid, *, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Cartesian points ``(M, 3)`` at the centres of the occupied cells (the decoded point cloud)."""
    return polar_to_cartesian(occupancy_to_polar(occ, dtype=torch.float64)).to(dtype)
