"""The nearest model point of any point near a model, looked up on a voxel grid.

ICP (:mod:`dope_hope.refine.icp`) pairs every scene point with its nearest model point a few
hundred times per detection (ten starts, fourteen iterations, up to 3,000 points): some 140,000
nearest-neighbour queries. ``scipy.spatial.cKDTree`` answers each exactly in about 1.5-2.5 us on
a 2,000-point model (AMD EPYC, AVX2): 0.1 s a detection, as much as the network's pass on a
whole frame. A grid answers in a few tens of nanoseconds: built once per model, each cell holds
the model point nearest its centre (``cKDTree``, once), and a query takes the answer of its
cell. Hand-written because none of the project's libraries keeps such a grid (Open3D's
``VoxelGrid`` holds occupancy, not nearest points, and is not a dependency).

The answer is the nearest point of the cell's centre, not of the query itself: a point at most
half a cell's diagonal (``cell_m * sqrt(3) / 2``, 1.7 mm at 2 mm cells) from the exact nearest
one's distance, in practice a neighbour on the same surface patch, whose plane (ICP's
point-to-plane residual) is the same. The caller still measures the true distance to the point
returned and drops pairs beyond its threshold.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

#: Cell side of a grid, metres, where the cell budget allows it.
DEFAULT_CELL_M = 0.002
#: Most cells of one grid (int32 each: 8 MB); a larger model gets larger cells.
MAX_CELLS = 2_000_000
#: Grids kept (:func:`nearest_point_grid`): one per model surface of a run, a few objects.
CACHE_SIZE = 16


@dataclass(frozen=True)
class NearestPointGrid:
    """A model's nearest points on a voxel grid (module docstring).

    origin: (3,) metres, the centre of cell (0, 0, 0), model frame. cell_m: cell side, metres.
    shape: (nx, ny, nz) cells. index: (nx + 2, ny + 2, nz + 2) int32, the model point nearest
    each cell's centre, -1 where none lies within ``reach_m`` (plus half a cell's diagonal) of
    it, and on a border of one cell all round (where a query outside the grid lands).
    reach_m: how far from the model a query is answered, metres.
    """

    origin: np.ndarray
    cell_m: float
    shape: tuple[int, int, int]
    index: np.ndarray
    reach_m: float

    @classmethod
    def build(cls, points: np.ndarray, reach_m: float, cell_m: float = DEFAULT_CELL_M,
              max_cells: int = MAX_CELLS) -> NearestPointGrid:
        """The grid of (N, 3) model ``points`` (metres) over their bounding box widened by
        ``reach_m``; ``cell_m`` grown where the box would need more than ``max_cells``."""
        P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not len(P):
            raise ValueError("no model points")
        lo, hi = P.min(axis=0) - reach_m, P.max(axis=0) + reach_m
        cell_m = max(float(cell_m), float(np.prod(hi - lo) / max_cells) ** (1.0 / 3.0))
        shape = tuple(int(n) for n in np.ceil((hi - lo) / cell_m).astype(np.int64) + 1)
        axes = [lo[i] + cell_m * np.arange(shape[i]) for i in range(3)]
        centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        _, idx = cKDTree(P).query(centres, distance_upper_bound=reach_m + cell_m * np.sqrt(3) / 2)
        index = np.where(idx < len(P), idx, -1).astype(np.int32).reshape(shape)
        return cls(origin=lo, cell_m=cell_m, shape=shape, index=np.pad(index, 1, constant_values=-1),
                   reach_m=float(reach_m))

    def nearest(self, x: np.ndarray) -> np.ndarray:
        """(..., 3) model-frame points, metres -> (...) int32: the model point of each one's
        cell, -1 outside the grid or where no model point is within reach."""
        # cell c of the padded index holds grid cell c - 1: a point's is floor(q + 1.5), q its
        # offset from the origin in cells; one outside lands on the border (-1) by the clip
        q = (np.asarray(x, dtype=np.float64) - (self.origin - 1.5 * self.cell_m)) / self.cell_m
        np.clip(q, 0.0, np.asarray(self.index.shape) - 1.0, out=q)
        ijk = q.astype(np.intp)
        ny, nz = self.index.shape[1:]
        return self.index.ravel()[(ijk[..., 0] * ny + ijk[..., 1]) * nz + ijk[..., 2]]


class ExactNearest:
    """The exact nearest model point (``scipy.spatial.cKDTree``) behind the grid's interface:
    ``icp_refine.nearest: exact``, the baseline the grid is measured against
    (``bench/postprocess.py --only-icp``)."""

    def __init__(self, points: np.ndarray, reach_m: float):
        self.tree, self.reach_m = cKDTree(np.asarray(points, dtype=np.float64).reshape(-1, 3)), float(reach_m)

    def nearest(self, x: np.ndarray) -> np.ndarray:
        """(..., 3) model-frame points, metres -> (...) int64: the nearest model point, -1 where
        none lies within ``reach_m``."""
        x = np.asarray(x, dtype=np.float64)
        _, idx = self.tree.query(x.reshape(-1, 3), distance_upper_bound=self.reach_m)
        return np.where(idx < self.tree.n, idx, -1).reshape(x.shape[:-1])


#: What ICP looks its model points up in: the grid, or the exact tree (its baseline).
NearestLookup = NearestPointGrid | ExactNearest

def nearest_point_grid(points: np.ndarray, reach_m: float) -> NearestPointGrid:
    """The :class:`NearestPointGrid` of (N, 3) model ``points`` (metres) answering within
    ``reach_m``: built on first use, then kept (:data:`CACHE_SIZE` grids, by the points' bytes:
    every detection of one object shares its model's grid)."""
    return _grid_of(np.ascontiguousarray(points, dtype=np.float64).tobytes(), float(reach_m))


@functools.lru_cache(maxsize=CACHE_SIZE)
def _grid_of(points: bytes, reach_m: float) -> NearestPointGrid:
    """:func:`nearest_point_grid` of the float64 (N, 3) points in ``points``."""
    return NearestPointGrid.build(np.frombuffer(points).reshape(-1, 3), reach_m)
