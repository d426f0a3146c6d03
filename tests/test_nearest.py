"""SampleIndex (polargs_plugin.nearest) gives cKDTree's nearest-neighbour distances, bit for bit,
on the cases that make a tree search hard: queries deep inside a sampled sphere (near its
centre every sample is almost equally far), far away, on the samples, exact ties on a grid,
repeated and collinear points."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from polargs_plugin.nearest import SampleIndex, morton_order


def unit_sphere_samples(n: int, seed: int) -> np.ndarray:
    x = np.random.default_rng(seed).normal(size=(n, 3))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def check_same_as_ckdtree(points: np.ndarray, queries: np.ndarray, **kw) -> np.ndarray:
    distance, index = SampleIndex.build(points, **kw).query(queries)
    expected = cKDTree(points).query(queries)[0]
    np.testing.assert_array_equal(distance, expected)  # the same floats, not just close
    np.testing.assert_array_equal(np.linalg.norm(queries - points[index], axis=1), distance)
    return distance


@pytest.mark.parametrize("leaf_size", [pytest.param(1, marks=pytest.mark.slow), 4, 32])
def test_sphere_samples_queried_from_inside_outside_and_on_them(leaf_size):
    points = unit_sphere_samples(20_000, 0)
    rng = np.random.default_rng(1)
    queries = np.concatenate([
        unit_sphere_samples(2000, 2) * rng.uniform(0.0, 0.99, (2000, 1)),  # inside, down to the centre
        unit_sphere_samples(1000, 3) * rng.uniform(1.01, 5.0, (1000, 1)),  # outside, far away
        points[:500],  # on the samples: distance 0
        np.zeros((1, 3)),  # the centre itself
    ])
    distance = check_same_as_ckdtree(points, queries, leaf_size=leaf_size)
    assert (distance[3000:3500] == 0).all()


def test_ties_repeats_and_degenerate_point_sets():
    grid = np.stack(np.meshgrid(np.arange(6.0), np.arange(5.0), [0.0], indexing="ij"), -1).reshape(-1, 3)
    centres = grid[:-1] + np.array([0.5, 0.5, 0.0])  # equidistant from 4 grid points
    check_same_as_ckdtree(grid, np.concatenate([centres, centres + [0, 0, 2.0]]))
    repeated = np.repeat(np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.5]]), 100, axis=0)
    check_same_as_ckdtree(repeated, np.random.default_rng(4).normal(size=(50, 3)), leaf_size=8)
    line = np.linspace([0, 0, 0], [1, 2, 3], 500)
    check_same_as_ckdtree(line, np.random.default_rng(5).normal(size=(200, 3)))
    check_same_as_ckdtree(np.array([[0.3, -1.0, 2.0]]), np.random.default_rng(6).normal(size=(20, 3)))


def test_query_order_and_threads_do_not_change_the_result():
    points = unit_sphere_samples(5000, 7)
    queries = np.random.default_rng(8).normal(size=(3000, 3)) * 0.6
    index = SampleIndex.build(points)
    one, _ = index.query(queries, threads=1)
    two, _ = index.query(queries, threads=2)
    np.testing.assert_array_equal(one, two)
    flip = index.query(queries[::-1])[0][::-1]
    np.testing.assert_array_equal(one, flip)
    order = morton_order(queries)
    assert sorted(order) == list(range(len(queries)))


def test_errors():
    with pytest.raises(ValueError, match="N >= 1"):
        SampleIndex.build(np.zeros((0, 3)))
    with pytest.raises(ValueError, match="finite"):
        SampleIndex.build(np.array([[0.0, np.nan, 0.0]]))
    index = SampleIndex.build(np.zeros((1, 3)))
    with pytest.raises(ValueError, match="finite"):
        index.query(np.array([[np.inf, 0.0, 0.0]]))
    assert index.query(np.zeros((0, 3)))[0].shape == (0,)
