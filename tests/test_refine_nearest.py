"""The nearest-point grid of ICP (dope_hope.refine.nearest): its answers against scipy's exact
cKDTree, nothing answered beyond reach or outside the grid, one grid per model kept."""
from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from dope_hope.io.meshes import sample_surface_points
from dope_hope.refine.nearest import NearestPointGrid, nearest_point_grid

POINTS = sample_surface_points(trimesh.creation.box(extents=[0.065, 0.15, 0.045]), 2000, oversample=10)


def test_the_grid_answers_within_half_a_cell_of_the_exact_nearest():
    grid = NearestPointGrid.build(POINTS, reach_m=0.03)
    rng = np.random.default_rng(0)
    x = POINTS[rng.integers(0, len(POINTS), 5000)] + rng.normal(0.0, 0.01, (5000, 3))
    exact, _ = cKDTree(POINTS).query(x)
    idx = grid.nearest(x)
    found = exact < 0.03 - grid.cell_m  # well within reach: every one answered
    assert np.all(idx[found] >= 0)
    answered = np.linalg.norm(x[found] - POINTS[idx[found]], axis=1)
    # the cell centre's nearest point is at most a cell's diagonal farther than the exact one
    assert np.all(answered <= exact[found] + grid.cell_m * np.sqrt(3) + 1e-12)
    assert np.median(answered - exact[found]) < 0.5 * grid.cell_m
    # a (B, n, 3) batch answers as its rows do
    assert np.array_equal(grid.nearest(x.reshape(10, 500, 3)).ravel(), idx)


def test_nothing_is_answered_beyond_reach_or_outside_the_grid():
    grid = NearestPointGrid.build(POINTS, reach_m=0.02)
    far = np.array([[0.0, 0.0, 0.5], [-3.0, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.0425 + 0.02 + 0.004]])
    assert np.all(grid.nearest(far) == -1)
    # the box's centre is 2.25 cm from its nearest face: beyond 2 cm of reach
    assert grid.nearest(np.zeros((1, 3)))[0] == -1
    assert NearestPointGrid.build(POINTS, reach_m=0.03).nearest(np.zeros((1, 3)))[0] >= 0


def test_a_large_model_gets_larger_cells_and_each_model_one_grid():
    grid = NearestPointGrid.build(POINTS * 10.0, reach_m=0.03, max_cells=100_000)
    assert grid.cell_m > 0.002 and np.prod(grid.shape) <= 1.2 * 100_000  # (+1 cell a side)
    assert nearest_point_grid(POINTS, 0.03) is nearest_point_grid(POINTS.copy(), 0.03)
    assert nearest_point_grid(POINTS, 0.03) is not nearest_point_grid(POINTS, 0.02)
