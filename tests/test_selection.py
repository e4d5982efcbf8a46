"""omnihang_jax.selection: the observed-cloud inside counts and the answer rules."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from omnihang_jax import selection

IDENTITY = [1.0, 0.0, 0.0, 0.0]


def plane_support(size=0.04, step=0.002):
    """A flat observed support: points on z = 0, outward normal +z."""
    xs = np.arange(-size, size + 1e-9, step)
    pts = np.stack(np.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    points = np.concatenate([pts, np.zeros((len(pts), 1))], 1).astype(np.float32)
    normals = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (len(points), 1))
    return points, normals


def small_object():
    rng = np.random.default_rng(0)
    return rng.uniform(-0.005, 0.005, (64, 3)).astype(np.float32)


def test_inside_counts_follow_the_observed_surface():
    sup, nrm = plane_support()
    obj = small_object()
    poses = np.array([
        [0.0, 0.0, 0.05] + IDENTITY,  # 5 cm above: nothing inside
        [0.0, 0.0, -0.02] + IDENTITY,  # 2 cm below: every point inside
        [0.0, 0.0, 0.0] + IDENTITY,  # straddling: the points below -1 mm
        [0.2, 0.0, -0.02] + IDENTITY,  # below the plane's level but far beside it
    ], np.float32)  # fmt: skip
    counts = np.asarray(selection.inside_counts(obj, sup, nrm, poses, 0.001, 0.003))
    assert counts[0] == 0
    assert counts[1] == len(obj)
    assert counts[2] == int(np.sum(obj[:, 2] < -0.001))
    assert counts[3] == 0  # beside the observed surface: not inside


def test_inside_counts_jit_and_deeper_thresholds_never_count_more():
    sup, nrm = plane_support()
    obj = small_object()
    poses = np.array([[0.0, 0.0, z] + IDENTITY for z in (-0.004, -0.001, 0.0, 0.003)], np.float32)
    jitted = jax.jit(selection.inside_counts, static_argnums=(4, 5))
    for radius in (0.002, 0.005):
        rows = []
        for depth in (0.0005, 0.001, 0.002, 0.003):
            eager = np.asarray(selection.inside_counts(obj, sup, nrm, poses, depth, radius))
            np.testing.assert_array_equal(np.asarray(jitted(obj, sup, nrm, poses, depth, radius)),
                                          eager)  # fmt: skip
            rows.append(eager)
        assert np.all(np.diff(np.stack(rows), axis=0) <= 0)


def test_rules():
    v = jnp.array([0.9, 0.8, 0.3, 0.1])
    counts = jnp.array([12, 0, 0, 3])
    assert int(selection.select(v, counts, selection.SelectConfig())) == 0
    clear = selection.SelectConfig("value_clear", max_points=0)
    assert int(selection.select(v, counts, clear)) == 1
    assert (
        int(selection.select(v, counts, selection.SelectConfig("value_clear", max_points=20))) == 0
    )
    # every candidate inside: the fewest inside points, ties by V
    assert int(selection.select(v, jnp.array([5, 4, 4, 9]), clear)) == 1
    # batched over leading axes
    both = selection.select(jnp.stack([v, v]), jnp.stack([counts, jnp.zeros(4, int)]), clear)
    np.testing.assert_array_equal(np.asarray(both), [1, 0])


def test_config_is_checked():
    with pytest.raises(ValueError, match="rule"):
        selection.SelectConfig("best")
    with pytest.raises(ValueError, match="radius"):
        selection.SelectConfig("value_clear", radius=0.0)
