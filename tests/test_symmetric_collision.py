"""The symmetric observed-cloud test (``GeometricConfig.symmetric``): support points behind the
observed object surface. A thin support plate inside a closed sphere cloud is caught by the
symmetric side while the one-sided test (object points behind the support) misses it; far
away is free; batched == one pose at a time; ``symmetric=False`` is the one-sided test."""

from __future__ import annotations

from dataclasses import replace

import jax
import numpy as np

from omnihang_jax import collision

SPHERE_RADIUS = 0.01  # m: the object, a closed sphere cloud centred on its frame's origin


def _sphere(rng, n=2000, radius=SPHERE_RADIUS):
    """Points on a sphere (spacing ~0.8 mm) with outward normals, object frame."""
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return (radius * normals).astype(np.float32), normals.astype(np.float32)


def _plate(rng, n=300, half=0.003, thick=0.001):
    """A 6 x 6 mm plate, 1 mm thick, both faces observed (top +z, bottom -z), support frame:
    small enough to lie inside the sphere, so no sphere point is behind either face."""
    xy = rng.uniform(-half, half, (2 * n, 2))
    z = np.repeat([0.5 * thick, -0.5 * thick], n)[:, None]
    normals = np.repeat([[0, 0, 1.0], [0, 0, -1.0]], n, axis=0)
    return np.concatenate([xy, z], 1).astype(np.float32), normals.astype(np.float32)


def _setup(seed=0):
    rng = np.random.default_rng(seed)
    obj, obj_normals = _sphere(rng)
    plate, plate_normals = _plate(rng)
    grids = collision.GeometricGrids(
        collision.support_grid(plate, plate_normals, max_voxels=200_000),
        collision.support_grid(obj, obj_normals, max_voxels=200_000),
    )
    return rng, obj, grids


def _pose(xyz, axis=(0, 0, 1), angle=0.0):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    q = [np.cos(angle / 2), *(np.sin(angle / 2) * axis)]
    return np.array([*xyz, *q], np.float32)


def _random_poses(rng, n, spread):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([rng.uniform(-spread, spread, (n, 3)), q], 1).astype(np.float32)


GEO = collision.GeometricConfig(object_points=2000, symmetric=True)


def test_inverse_transform_points_undoes_transform_points():
    rng = np.random.default_rng(1)
    poses = _random_poses(rng, 6, 0.1)
    pts = rng.normal(0, 0.05, (40, 3)).astype(np.float32)
    back = collision.inverse_transform_points(poses, collision.transform_points(poses, pts))
    np.testing.assert_allclose(np.asarray(back), np.broadcast_to(pts, back.shape), atol=1e-6)


def test_plate_inside_the_sphere_is_caught_by_the_symmetric_side_only():
    _, obj, grids = _setup()
    # the sphere centred on the plate, as is and turned and moved (the plate's points go into
    # the object frame through the inverse pose)
    poses = np.stack([_pose((0, 0, 0)), _pose((0.002, -0.001, 0.001), (1, 2, 3), 0.7)])
    one_sided = np.asarray(
        collision.penetration_count(obj, grids.support, poses, GEO.depth, GEO.radius)
    )
    sym = np.asarray(
        collision.support_penetration_count(
            grids.object, grids.support.points, poses, GEO.sym_depth, GEO.sym_radius
        )
    )
    assert np.all(one_sided == 0)  # no sphere point behind the plate's observed faces
    assert np.all(sym > 100)  # most of the plate's 600 points inside the sphere
    plain = jax.jit(collision.geometric_collides(replace(GEO, symmetric=False)))
    both = jax.jit(collision.geometric_collides(GEO))
    np.testing.assert_array_equal(np.asarray(plain(grids, obj, None, poses)), [False, False])
    np.testing.assert_array_equal(np.asarray(both(grids, obj, None, poses)), [True, True])


def test_far_pose_is_free_and_batched_equals_one_pose_at_a_time():
    rng, obj, grids = _setup(2)
    far = np.stack([_pose((0.2, 0, 0)), _pose((0, 0.05, 0.03), (0, 1, 0), 1.0)])
    both = jax.jit(collision.geometric_collides(GEO))
    np.testing.assert_array_equal(np.asarray(both(grids, obj, None, far)), [False, False])
    # poses from inside to grazing to clear: both answers occur
    many = np.concatenate([far, _random_poses(rng, 14, 0.012)])
    batched = np.asarray(both(grids, obj, None, many))
    assert batched.any() and not batched.all()
    single = [bool(both(grids, obj, None, p[None])[0]) for p in many]
    np.testing.assert_array_equal(batched, single)
    # the hybrid: with an NCE that never collides it is the symmetric test, batched too
    cfg = collision.NCE_PRESETS["tiny"]
    params = collision.make_nce(cfg).init(jax.random.key(0))
    oc = obj[: cfg.object_points]
    sc = np.asarray(grids.support.points)[: cfg.support_points]
    hybrid_params = collision.NCEGeometricParams(
        params, jax.numpy.asarray(obj), grids.support, grids.object
    )
    hybrid = jax.jit(collision.nce_geometric_collides(replace(cfg, threshold=1.1), GEO))
    got = np.asarray(hybrid(hybrid_params, oc, sc, many))
    np.testing.assert_array_equal(got, batched)
    single = [bool(hybrid(hybrid_params, oc, sc, p[None])[0]) for p in many]
    np.testing.assert_array_equal(got, single)


def _one_sided_reference(config):
    """The test as it was before the symmetric option (eleventh session), verbatim."""

    def collides(params, object_cloud, support_cloud, poses):
        count = collision.penetration_count(
            object_cloud, params, poses, config.depth, config.radius
        )
        return count > config.min_points

    return collides


def test_symmetric_false_is_bit_identical_to_the_one_sided_test():
    rng = np.random.default_rng(3)
    obj, obj_normals = _sphere(rng, 500, 0.02)
    # a 6 x 6 cm patch at z = 0 (normals +z): the sphere sinks into it at some poses
    patch = np.concatenate([rng.uniform(-0.03, 0.03, (3000, 2)), np.zeros((3000, 1))], 1)
    patch = patch.astype(np.float32)
    normals = np.tile([0, 0, 1.0], (3000, 1)).astype(np.float32)
    grid = collision.support_grid(patch, normals, max_voxels=200_000)
    grids = collision.GeometricGrids(
        grid, collision.support_grid(obj, obj_normals, max_voxels=200_000)
    )
    poses = _random_poses(rng, 32, 0.025)
    geo = collision.GeometricConfig(depth=0.002, radius=0.004, min_points=2, object_points=500)
    assert not geo.symmetric  # the default
    want = np.asarray(jax.jit(_one_sided_reference(geo))(grid, obj, None, poses))
    assert want.any() and not want.all()
    test = jax.jit(collision.geometric_collides(geo))
    np.testing.assert_array_equal(np.asarray(test(grid, obj, None, poses)), want)
    np.testing.assert_array_equal(np.asarray(test(grids, obj, None, poses)), want)
    # the hybrid with an NCE that never collides: the object grid is ignored when off
    cfg = collision.NCE_PRESETS["tiny"]
    params = collision.make_nce(cfg).init(jax.random.key(0))
    hybrid = jax.jit(collision.nce_geometric_collides(replace(cfg, threshold=1.1), geo))
    oc, sc = obj[: cfg.object_points], patch[: cfg.support_points]
    for object_grid in (None, grids.object):
        hp = collision.NCEGeometricParams(params, jax.numpy.asarray(obj), grid, object_grid)
        np.testing.assert_array_equal(np.asarray(hybrid(hp, oc, sc, poses)), want)
    # and switching the symmetric side on can only add colliding calls
    on = jax.jit(collision.geometric_collides(replace(geo, symmetric=True)))
    assert np.all(np.asarray(on(grids, obj, None, poses)) >= want)


def _open_cap(rng, n=2000, radius=SPHERE_RADIUS):
    """The sphere's top cap only (z > 0.6 r, normals within 53 degrees of +z), outward
    normals: a one-sided (open) surface, as a thin part seen from one side; no two of its
    normals face each other, nothing observed behind it."""
    pts, normals = _sphere(rng, 5 * n, radius)
    up = pts[:, 2] > 0.6 * radius
    return pts[up], normals[up]


def test_solid_only_ignores_support_behind_a_one_sided_surface():
    rng = np.random.default_rng(4)
    closed, closed_normals = _sphere(rng)
    cap, cap_normals = _open_cap(rng)
    # a closed sphere: (nearly) every point has its back face observed; an open cap: none
    assert collision.solid_backed(closed, closed_normals, 0.03, 0.004).mean() > 0.95
    assert not collision.solid_backed(cap, cap_normals, 0.03, 0.004).any()
    geo = replace(GEO, sym_solid_only=True)
    # support points 3 mm under the cap's top (inside the sphere, behind the cap's surface)
    support = rng.uniform(-0.002, 0.002, (200, 3)).astype(np.float32)
    support[:, 2] += 0.007
    poses = np.stack([_pose((0, 0, 0)), _pose((0.0005, 0, 0), (0, 0, 1), 0.3)])

    def count(obj, normals, config):
        grid = collision.object_grid(obj, normals, config)
        return np.asarray(
            collision.support_penetration_count(
                grid, support, poses, config.sym_depth, config.sym_radius
            )
        )

    assert np.all(count(cap, cap_normals, GEO) > 100)  # counted by the plain symmetric side
    assert np.all(count(cap, cap_normals, geo) == 0)  # not behind a one-sided surface
    assert np.all(count(closed, closed_normals, geo) > 100)  # still inside the closed object
    # off by default: the object table is the plain support_grid's, bit for bit
    plain = collision.support_grid(closed, closed_normals, max_voxels=200_000)
    same = collision.object_grid(closed, closed_normals, replace(GEO, max_voxels=200_000))
    for a, b in zip(plain, same):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
