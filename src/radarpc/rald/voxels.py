"""Occupancy partitioning as a choice: RaLD's frustum cells or Cartesian voxels (the seed's Tables 1,
4, 5 and 7 compare them), behind one set of functions.

A :class:`CartesianGrid` is a regular grid of voxels in the radar frame's ``(x, y, z)`` (metres);
the seed's voxel baseline uses 0.05 m voxels. It has the cell layout of a
:class:`~radarpc.rald.frustum.FrustumGrid` (``lo``, ``hi``, ``cell``, ``shape``, ``n_cells``, linear
index ``(i * n_y + j) * n_z + k``), so :func:`~radarpc.rald.frustum.voxelize`,
:func:`~radarpc.rald.frustum.occupancy` and :func:`~radarpc.rald.frustum.sample_queries` work on
it unchanged with the grid's own coordinates in place of polar ones. The functions here take care
of that: every function takes Cartesian LiDAR points and either kind of grid.

* :func:`partition_grid` builds the grid a partitioning names over a sensor's field of view;
* :func:`grid_coords` maps Cartesian points to the grid's own coordinates (polar for a frustum,
  unchanged for voxels), :func:`model_coords` further to the normalised ``[-1, 1]^3`` the
  autoencoder reads (:mod:`radarpc.models.vecset`), and :func:`cartesian_points` back;
* :func:`voxelize_points` is the occupancy of a Cartesian cloud; queries and labels then come from
  :func:`~radarpc.rald.frustum.sample_queries`, already normalised; :func:`cell_centres` gives the
  occupied cells' centres in metres.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch

from radarpc.rald.frustum import (RALD_CELL, FrustumGrid, OccupancyGrid, _points, cartesian_to_polar, denormalize,
                                  normalize, polar_to_cartesian, voxelize)
from radarpc.sensors.coloradar import AWR1843_FOV, RadarFOV

__all__ = [
    "PARTITIONS",
    "RALD_VOXEL",
    "CartesianGrid",
    "partition_grid",
    "grid_coords",
    "model_coords",
    "cartesian_points",
    "voxelize_points",
    "cell_centres",
]

Partition = Literal["frustum", "cartesian"]
PARTITIONS: tuple[str, ...] = ("frustum", "cartesian")
"""Occupancy partitionings: RaLD's frustum cells, Cartesian voxels."""

RALD_VOXEL = (0.05, 0.05, 0.05)
"""The seed's Cartesian voxel, metres (its voxel-based autoencoders)."""


@dataclass(frozen=True)
class CartesianGrid:
    """A regular voxel grid in ``(x, y, z)``, metres; each span a whole number of cells."""

    x_m: tuple[float, float]
    y_m: tuple[float, float]
    z_m: tuple[float, float]
    cell: tuple[float, float, float]

    def __post_init__(self) -> None:
        if len(self.cell) != 3:
            raise ValueError(f"CartesianGrid.cell must have 3 entries (x, y, z), got {self.cell}")
        for name, c in zip(("x_m", "y_m", "z_m"), self.cell):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
                raise ValueError(f"CartesianGrid.{name}={getattr(self, name)} must be finite with max > min")
            if not (math.isfinite(c) and c > 0):
                raise ValueError(f"CartesianGrid.cell={self.cell} must be positive")
            n = (hi - lo) / c
            if abs(n - round(n)) > 1e-6 * max(1.0, n):
                raise ValueError(f"CartesianGrid.{name} span {hi - lo} is not a whole number of cells of {c}")

    @classmethod
    def covering(cls, fov: RadarFOV, cell: tuple[float, float, float] = RALD_VOXEL) -> "CartesianGrid":
        """The smallest grid of ``cell``-sized voxels, aligned to the origin, that holds the field of view.

        The box's bounds are the extremes of ``r (cos e cos a, cos e sin a, sin e)`` over the FOV: each
        coordinate is a product of functions of one variable, so its extremes are at the ends of
        each interval or at an interior extremum of the cosine / sine (0, +-90, 180 deg).
        """
        if len(cell) != 3 or not all(math.isfinite(c) and c > 0 for c in cell):
            raise ValueError(f"cell must be 3 positive sizes (x, y, z), got {cell}")

        def angles(lo: float, hi: float) -> list[float]:
            return [lo, hi] + [a for a in (-180.0, -90.0, 0.0, 90.0, 180.0) if lo < a < hi]

        az = torch.deg2rad(torch.tensor(angles(*fov.azimuth_deg), dtype=torch.float64))
        el = torch.deg2rad(torch.tensor(angles(*fov.elevation_deg), dtype=torch.float64))
        r = torch.tensor([fov.min_range_m, fov.max_range_m], dtype=torch.float64)
        r, a, e = (t.reshape(-1) for t in torch.meshgrid(r, az, el, indexing="ij"))
        xyz = torch.stack((r * e.cos() * a.cos(), r * e.cos() * a.sin(), r * e.sin()), dim=-1)   # (K, 3)
        edges = []
        for lo, hi, c in zip(xyz.min(0).values.tolist(), xyz.max(0).values.tolist(), cell):
            n_lo, n_hi = math.floor(lo / c + 1e-9), math.ceil(hi / c - 1e-9)
            edges.append((n_lo * c, max(n_hi, n_lo + 1) * c))
        return cls(*edges, cell=tuple(float(c) for c in cell))

    @property
    def lo(self) -> tuple[float, float, float]:
        """Lower edges ``(x, y, z)``."""
        return (self.x_m[0], self.y_m[0], self.z_m[0])

    @property
    def hi(self) -> tuple[float, float, float]:
        """Upper edges ``(x, y, z)``."""
        return (self.x_m[1], self.y_m[1], self.z_m[1])

    @property
    def shape(self) -> tuple[int, int, int]:
        """Voxels per axis ``(n_x, n_y, n_z)``."""
        return tuple(int(round((h - l) / c)) for l, h, c in zip(self.lo, self.hi, self.cell))

    @property
    def n_cells(self) -> int:
        n_x, n_y, n_z = self.shape
        return n_x * n_y * n_z

    def _tensors(self, device, dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return tuple(torch.tensor(v, device=device, dtype=dtype) for v in (self.lo, self.hi, self.cell))


def partition_grid(partition: Partition, fov: RadarFOV = AWR1843_FOV,
                   cell: tuple[float, float, float] | None = None) -> FrustumGrid | CartesianGrid:
    """The occupancy grid of ``partition`` over ``fov``.

    Parameters
    ----------
    partition : {"frustum", "cartesian"}
    fov : RadarFOV
        The field of view the LiDAR truth is cropped to.
    cell : tuple of 3 floats, optional
        Cell size: (m, deg, deg) for frustum cells (default RaLD's 0.05 m, 0.25 deg, 0.5 deg), metres
        for voxels (default 0.05 m).
    """
    if partition == "frustum":
        return FrustumGrid.from_fov(fov, RALD_CELL if cell is None else cell)
    if partition == "cartesian":
        return CartesianGrid.covering(fov, RALD_VOXEL if cell is None else cell)
    raise ValueError(f"partition must be one of {list(PARTITIONS)}, got {partition!r}")


def _grid(grid) -> None:
    if not isinstance(grid, (FrustumGrid, CartesianGrid)):
        raise ValueError(f"grid must be a FrustumGrid or a CartesianGrid, got {type(grid).__name__}")


def grid_coords(grid: FrustumGrid | CartesianGrid, xyz) -> torch.Tensor:
    """Cartesian points ``(..., 3)`` in the grid's own coordinates: polar ``(r, a, e)`` for a frustum
    grid, ``(x, y, z)`` unchanged for voxels."""
    _grid(grid)
    return cartesian_to_polar(xyz) if isinstance(grid, FrustumGrid) else _points(xyz, "xyz")


def model_coords(grid: FrustumGrid | CartesianGrid, xyz) -> torch.Tensor:
    """Cartesian points ``(..., 3)`` as the autoencoder reads them: the grid's coordinates mapped
    affinely to ``[-1, 1]`` per axis over the grid's span (RaLD's anisotropic normalisation)."""
    return normalize(grid, grid_coords(grid, xyz))


def cartesian_points(grid: FrustumGrid | CartesianGrid, u) -> torch.Tensor:
    """Normalised coordinates ``(..., 3)`` (queries, decoded points) back to Cartesian metres."""
    _grid(grid)
    p = denormalize(grid, u)
    return polar_to_cartesian(p) if isinstance(grid, FrustumGrid) else p


def voxelize_points(grid: FrustumGrid | CartesianGrid, xyz) -> OccupancyGrid:
    """Occupancy of a Cartesian cloud ``(N, 3)`` on either kind of grid (cells holding a point);
    points outside the grid are dropped and counted."""
    return voxelize(grid, grid_coords(grid, xyz), coords="polar")   # "polar": the grid's own coordinates


def cell_centres(occ: OccupancyGrid, *, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Cartesian centres ``(M, 3)`` of the occupied cells of either kind of grid (a decoded cloud)."""
    grid = occ.grid
    _grid(grid)
    lo, _, cell = grid._tensors(occ.cells.device, torch.float64)
    centres = lo + (occ.ijk().to(torch.float64) + 0.5) * cell                   # (M, 3) in the grid's coordinates
    return (polar_to_cartesian(centres) if isinstance(grid, FrustumGrid) else centres).to(dtype)
