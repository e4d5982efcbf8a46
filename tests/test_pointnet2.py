"""PointNet++ sampling/grouping vs plain numpy oracles (exact), and module shapes/dtypes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from omnihang_jax import pointnet2
from omnihang_jax.pointnet2 import (
    PointNet2Encoder,
    PointNet2Segmentation,
    ball_query,
    farthest_point_sample,
    group_points,
    three_nn_interpolate,
)

# ---------------------------------------------------------------------------------------------
# Numpy oracles, written as the original CUDA kernels loop (one centroid / one point at a time).


def _sqdist_np(a, b):
    d = (a - b).astype(np.float32)
    return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


def fps_numpy(points, num_samples):
    """points [N, 3] float32 -> [S] int: start at 0, then argmax of the min distance."""
    n = points.shape[0]
    idx = np.zeros(num_samples, np.int32)
    min_d2 = np.full(n, 1e10, np.float32)
    last = 0
    for i in range(1, num_samples):
        min_d2 = np.minimum(min_d2, _sqdist_np(points, points[last]))
        last = int(np.argmax(min_d2))
        idx[i] = last
    return idx


def ball_query_numpy(points, centroids, radius, nsample):
    """Original kernel: scan k in order, fill all slots with the first hit, then overwrite."""
    out = np.zeros((centroids.shape[0], nsample), np.int32)
    r2 = np.float32(radius**2)
    for j, c in enumerate(centroids):
        d2 = _sqdist_np(points, c)
        cnt = 0
        for k in range(points.shape[0]):
            if cnt == nsample:
                break
            if d2[k] < r2:
                if cnt == 0:
                    out[j, :] = k
                out[j, cnt] = k
                cnt += 1
        if cnt == 0:
            out[j, :] = int(np.argmin(d2))
    return out


def group_numpy(points, features, centroids, idx):
    rel = points[idx] - centroids[:, None, :]
    return np.concatenate([rel, features[idx]], -1)


@pytest.fixture(scope="module")
def clouds():
    rng = np.random.default_rng(0)
    return rng.uniform(-0.05, 0.05, size=(3, 200, 3)).astype(np.float32)


@pytest.mark.parametrize("num_samples", [1, 17, 64])
def test_fps_matches_numpy(clouds, num_samples):
    got = np.asarray(jax.jit(farthest_point_sample, static_argnums=1)(clouds, num_samples))
    assert got.dtype == np.int32 and got.shape == (3, num_samples)
    for b in range(3):
        np.testing.assert_array_equal(got[b], fps_numpy(clouds[b], num_samples))
        assert len(set(got[b].tolist())) == num_samples  # no repeats on distinct points


@pytest.mark.parametrize("unroll", [3, 8, 64])
def test_fps_unrolled_gives_the_same_indices(clouds, unroll):
    # FPS_UNROLL: steps per loop iteration change the loop, not the
    # indices, also when the step count is no multiple of it
    want = [fps_numpy(clouds[b], 17) for b in range(3)]
    fps = jax.jit(farthest_point_sample, static_argnums=(1, 2))
    np.testing.assert_array_equal(np.asarray(fps(clouds, 17, unroll)), np.stack(want))


@pytest.mark.parametrize("method", ["cumsum", "count", "top_k"])
@pytest.mark.parametrize("radius,nsample", [(0.01, 8), (0.03, 16), (0.2, 32), (1e-4, 4)])
def test_ball_query_matches_numpy(clouds, radius, nsample, method):
    # Centroids: FPS points (always have a hit) plus off-cloud points (may have none -> nearest).
    rng = np.random.default_rng(1)
    centroids = np.concatenate(
        [clouds[:, ::7], rng.uniform(-0.06, 0.06, (3, 10, 3)).astype(np.float32)], axis=1
    )
    got = np.asarray(ball_query(clouds, centroids, radius, nsample, method=method))
    assert got.dtype == np.int32 and got.shape == (3, centroids.shape[1], nsample)
    for b in range(3):
        np.testing.assert_array_equal(
            got[b], ball_query_numpy(clouds[b], centroids[b], radius, nsample)
        )


@pytest.mark.parametrize("method", ["cumsum", "count", "top_k"])
def test_ball_query_nsample_larger_than_cloud(method):
    pts = np.random.default_rng(2).uniform(size=(1, 5, 3)).astype(np.float32)
    got = np.asarray(ball_query(pts, pts[:, :2], 10.0, 8, method=method))
    np.testing.assert_array_equal(got[0], ball_query_numpy(pts[0], pts[0, :2], 10.0, 8))
    np.testing.assert_array_equal(got[0, 0], [0, 1, 2, 3, 4, 0, 0, 0])


def test_fps_unroll_is_eight_on_a_gpu_one_elsewhere_unless_forced(monkeypatch):
    monkeypatch.setattr(pointnet2, "FPS_UNROLL", None)
    assert pointnet2.fps_unroll() == (1 if jax.default_backend() == "cpu" else 8)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert pointnet2.fps_unroll() == pointnet2.FPS_UNROLL_GPU == 8
    monkeypatch.setattr(pointnet2, "FPS_UNROLL", 3)
    assert pointnet2.fps_unroll() == 3


def test_ball_query_default_method_is_read_when_traced(clouds, monkeypatch):
    centroids = clouds[:, ::9]
    want = np.asarray(ball_query(clouds, centroids, 0.03, 8, method="cumsum"))
    for method in ("count", "top_k"):
        monkeypatch.setattr(pointnet2, "BALL_QUERY_METHOD", method)
        np.testing.assert_array_equal(np.asarray(ball_query(clouds, centroids, 0.03, 8)), want)
    monkeypatch.setattr(pointnet2, "BALL_QUERY_METHOD", "sort")
    with pytest.raises(ValueError, match="ball-query method 'sort'"):
        ball_query(clouds, centroids, 0.03, 8)


@pytest.mark.parametrize("reductions", [True, False])
def test_first_argmin_and_argmax_are_argmin_and_argmax(monkeypatch, reductions):
    """Both ways (two plain reductions on the CPU, jnp.argmin elsewhere) give argmin's and
    argmax's indices, the first of tied values included, along any axis."""
    monkeypatch.setattr(pointnet2, "_by_min_reductions", lambda: reductions)
    rng = np.random.default_rng(0)
    x = rng.integers(0, 5, size=(4, 7, 9)).astype(np.float32)  # many ties
    x[0, 0] = 2.0  # a whole row tied
    for axis in (0, 1, -1):
        got_min = np.asarray(jax.jit(pointnet2.first_argmin, static_argnums=1)(x, axis))
        got_max = np.asarray(jax.jit(pointnet2.first_argmax, static_argnums=1)(x, axis))
        np.testing.assert_array_equal(got_min, np.argmin(x, axis=axis))
        np.testing.assert_array_equal(got_max, np.argmax(x, axis=axis))
        assert got_min.dtype == np.int32 and got_max.dtype == np.int32


def test_grouping_matches_numpy(clouds):
    rng = np.random.default_rng(3)
    features = rng.normal(size=(3, 200, 5)).astype(np.float32)
    centre_idx = np.asarray(farthest_point_sample(clouds, 16))
    centroids = np.take_along_axis(clouds, centre_idx[..., None], 1)
    idx = np.asarray(ball_query(clouds, centroids, 0.03, 8))
    got = np.asarray(group_points(clouds, features, centroids, idx))
    assert got.shape == (3, 16, 8, 8) and got.dtype == np.float32
    for b in range(3):
        np.testing.assert_array_equal(
            got[b], group_numpy(clouds[b], features[b], centroids[b], idx[b])
        )


def test_three_nn_interpolate_matches_numpy(clouds):
    rng = np.random.default_rng(4)
    sparse = clouds[:, :20]
    feats = rng.normal(size=(3, 20, 4)).astype(np.float32)
    got = np.asarray(three_nn_interpolate(clouds, sparse, feats))
    for b in range(3):
        d2 = ((clouds[b, :, None] - sparse[b, None]) ** 2).sum(-1)
        nn3 = np.argsort(d2, 1)[:, :3]
        w = 1 / np.maximum(np.take_along_axis(d2, nn3, 1), 1e-10)
        w /= w.sum(1, keepdims=True)
        want = (w[..., None] * feats[b][nn3]).sum(1)
        np.testing.assert_allclose(got[b], want, rtol=1e-4, atol=1e-5)


def test_presets_match_facts():
    levels = [(lv.npoint, lv.radius, lv.nsample, lv.mlp) for lv in pointnet2.ORIGINAL.sa_levels]
    assert levels == [
        (512, 0.01, 32, (32, 32, 64)),
        (128, 0.02, 32, (64, 64, 128)),
        (64, 0.04, 32, (128, 128, 256)),
        (16, 0.08, 32, (256, 256, 512)),
        (1, 0.20, 16, (512, 512, 1024)),
    ]
    assert pointnet2.ORIGINAL.num_points == 4096
    assert pointnet2.ORIGINAL.global_feature_dim == 1024
    assert pointnet2.ORIGINAL.point_feature_dim == 64


def test_encoder_and_segmentation_shapes():
    cfg = pointnet2.TINY
    pts = jax.random.uniform(jax.random.key(0), (2, 128, 3), maxval=0.1)
    flags = jnp.ones((2, 128, 1))
    enc = PointNet2Encoder(cfg)
    params = jax.jit(enc.init)(jax.random.key(1), pts)
    global_feature, levels = jax.jit(enc.apply)(params, pts)
    assert global_feature.shape == (2, cfg.global_feature_dim)
    assert global_feature.dtype == jnp.float32
    assert [lv[0].shape[1] for lv in levels] == [128, 32, 8, 1]

    seg = PointNet2Segmentation(cfg)
    sparams = jax.jit(seg.init)(jax.random.key(2), pts, flags)
    point_features, g = jax.jit(seg.apply)(sparams, pts, flags)
    assert point_features.shape == (2, 128, cfg.point_feature_dim)
    assert bool(jnp.all(jnp.isfinite(point_features)))
    # vmap over an extra axis works (no Python-side shape logic on traced values).
    many = jnp.stack([pts, pts + 0.01])
    out = jax.jit(jax.vmap(lambda p: enc.apply(params, p)[0]))(many)
    assert out.shape == (2, 2, cfg.global_feature_dim)


def test_original_level_is_translation_invariant_but_group_all_is_not():
    """Ball-query levels see relative xyz only; group-all sees absolute xyz (documented)."""
    pts = jax.random.uniform(jax.random.key(0), (1, 128, 3), maxval=0.1)
    cfg = pointnet2.PointNet2Config(
        sa_levels=pointnet2.TINY.sa_levels[:2], fp_mlps=((8,), (8,)), num_points=128
    )
    enc = PointNet2Encoder(cfg)
    params = jax.jit(enc.init)(jax.random.key(1), pts)
    a, _ = jax.jit(enc.apply)(params, pts)
    b, _ = jax.jit(enc.apply)(params, pts + 0.5)
    np.testing.assert_allclose(a, b, atol=1e-4)
