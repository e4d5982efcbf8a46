"""MJX kernels against the CPU reference (MuJoCo C), on one tiny pair and a few poses.

Compiling MJX on a 2-core CPU is slow (tens of seconds per function), so the fast tests
share one pair, short durations and one template; the multi-pair agreement check is slow.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim import geometry, kernels
from sim.assets.base import Asset, HangLoop
from tests.test_kernels import middle_pose, support_of

jax = pytest.importorskip("jax")
mjx_kernels = pytest.importorskip("sim.mjx_kernels")
mjx_warp = pytest.importorskip("sim.mjx_warp")

# one worker for the module: its tests share one compiled template
pytestmark = pytest.mark.xdist_group("mjx")
SHORT = kernels.StabilityConfig(duration=0.3)
BRIEF = kernels.StabilityConfig(duration=0.2)  # the diverged-world test: two checks are enough
SETTINGS = mjx_kernels.MJXSettings(lanes=4, chunk=4)


def small_ring(radius=0.03, tube=0.004, n=6) -> Asset:
    """A closed loop of ``n`` capsules (fewer than test_kernels' ring: faster to compile)."""
    parts = geometry.ring([0, 0, 0], [0, 0, 1], radius, tube, n)
    free = radius * np.cos(np.pi / n) - tube
    loop = HangLoop(np.zeros(3), np.array([0, 0, 1.0]), free)
    return Asset("ring6", "object", "others", 0, parts, [loop], {})


@pytest.fixture(scope="module")
def pair():
    from sim.scene import build_scene

    ring = small_ring()
    hook = support_of("single_rod_hook", style="angled")
    scene = build_scene(ring, hook)
    pose = middle_pose(ring, hook)
    beside = pose.copy()
    beside[0] += 0.1  # nothing holds it
    sunk = pose.copy()
    sunk[2] -= 0.006  # 6 mm into the rod
    return scene, np.stack([pose, beside, sunk])


def test_stability_labels_match_cpu(pair):
    scene, poses = pair
    ref = kernels.stability(scene, poses, SHORT)
    got = kernels.stability(scene, poses, SHORT, backend="mjx", settings=SETTINGS)
    assert (
        got.status.tolist()
        == ref.status.tolist()
        == [
            kernels.STABLE,
            kernels.FALLEN,
            kernels.PENETRATING,
        ]
    )
    np.testing.assert_allclose(got.initial_penetration, ref.initial_penetration, atol=2e-4)
    np.testing.assert_allclose(got.sim_time, ref.sim_time)
    # still on the rod near the reference: on the angled rod the ring slides during the
    # short check, at a rate that differs between the solvers (measured ~1 cm in 0.3 s)
    assert np.linalg.norm(got.settled_pose[0, :3] - ref.settled_pose[0, :3]) < 0.02


@pytest.mark.slow  # a compile-count guard; the labels test above covers correctness
def test_compiled_once_and_reused(pair):
    scene, poses = pair
    kernels.stability(
        scene, poses, SHORT, backend="mjx", settings=SETTINGS
    )  # compiled here or earlier
    before = dict(mjx_kernels.COMPILES)
    kernels.stability(scene, poses[::-1], SHORT, backend="mjx", settings=SETTINGS)
    assert dict(mjx_kernels.COMPILES) == before


@pytest.mark.slow  # a second MJX batch shape: ~2 min of compiling on 2 cores
def test_diverged_world_does_not_poison_batch(pair):
    """A world whose state is NaN is labelled diverged; its neighbours are unaffected."""
    scene, poses = pair
    batch = mjx_kernels._batch_for([scene], SETTINGS)
    # a pair whose object has a NaN mass: its world diverges at the first step
    two = jax.tree.map(lambda x: jax.numpy.concatenate([x] * 2), batch.models)
    two = two.replace(body_mass=two.body_mass.at[1, mjx_kernels.OBJECT_BODY].set(np.nan))
    aux = jax.tree.map(lambda x: jax.numpy.concatenate([x] * 2), batch.aux)
    bad = mjx_kernels.Batch(batch.template, two, aux, batch.data0, [scene, scene])
    res = mjx_kernels.stability_many(
        [scene, scene], np.array([0, 1, 1, 0]), poses[[0, 0, 1, 1]], BRIEF, SETTINGS, batch=bad
    )
    assert res.status[0] == kernels.STABLE
    assert res.status[1] == kernels.DIVERGED and res.status[2] == kernels.DIVERGED
    assert res.status[3] == kernels.FALLEN
    assert np.isfinite(res.settled_pose).all()


def test_contact_query_reports_penetration(pair):
    scene, poses = pair
    ref = kernels.contact_query(scene, poses[[2]])
    got = kernels.contact_query(scene, poses[[2]], backend="mjx")
    assert got.penetration[0] == pytest.approx(ref.penetration[0], abs=5e-4)
    valid = got.mask[0]
    assert valid.any()
    gap = np.einsum(
        "ij,ij->i",
        got.object_points[0, valid] - got.support_points[0, valid],
        got.normals[0, valid],
    )
    assert np.all(gap < 1e-6)


@pytest.mark.slow
def test_takeoff_matches_cpu(pair):
    scene, poses = pair
    cfg = kernels.TakeoffConfig(push_time=0.2, free_time=0.1)
    ref = kernels.takeoff(scene, poses[:1], cfg)
    got = kernels.takeoff(scene, poses[:1], cfg, backend="mjx", settings=SETTINGS)
    assert (got.removed == ref.removed).mean() >= 10 / 11


@pytest.mark.slow
def test_small_agreement_over_pairs(tmp_path):
    """The benchmark's agreement check, tiny: a few pairs of several categories."""
    from experiments import bench_sim

    res = bench_sim.main(
        [
            "--out", str(tmp_path), "--pairs", "3", "--poses", "8", "--repeat", "1",
            "--lanes", "16", "--pybullet-poses", "0", "--no-takeoff",
        ]
    )  # fmt: skip
    assert res["agreement"] >= 0.9, res["disagreements"]


def test_warp_union_matches_cpu(pair):
    """MJX's Warp impl (union model, per-world fields; Warp's CPU device here) agrees with
    the reference on the three poses, and a second call reuses the compiled kernels."""
    pytest.importorskip("warp")
    scene, poses = pair
    settings = mjx_kernels.MJXSettings(lanes=4, chunk=4, impl="warp")
    ref = kernels.stability(scene, poses, SHORT)
    got = kernels.stability(scene, poses, SHORT, backend="mjx", settings=settings)
    assert got.status.tolist() == ref.status.tolist()
    np.testing.assert_allclose(got.initial_penetration, ref.initial_penetration, atol=2e-4)
    np.testing.assert_allclose(got.sim_time, ref.sim_time)
    assert np.linalg.norm(got.settled_pose[0, :3] - ref.settled_pose[0, :3]) < 0.005
    before = {k: v for k, v in mjx_kernels.COMPILES.items() if k.startswith("warp")}
    again = kernels.stability(scene, poses[::-1], SHORT, backend="mjx", settings=settings)
    assert again.status.tolist() == ref.status.tolist()[::-1]
    assert {k: v for k, v in mjx_kernels.COMPILES.items() if k.startswith("warp")} == before


def test_sequential_takeoff_semantics():
    """All 11 directions run at once on the device; only the first removing one is kept,
    as in the reference (a freed pose is not pushed along later directions)."""
    removed = np.zeros((3, 11), bool)
    removed[0, [1, 3, 6, 8]] = True
    removed[2, 10] = True
    res = mjx_kernels._sequential(removed)
    assert res.removable.tolist() == [True, False, True]
    assert res.direction.tolist() == [1, -1, 10]
    assert res.removed.sum(1).tolist() == [1, 0, 1]
    assert res.removed[0, 1] and res.removed[2, 10]


def _cpu_every_direction(scene, poses, cfg):
    """[B, 11] reference outcome of each direction on its own (no sequential skipping)."""
    from unittest import mock

    out = np.zeros((len(poses), 11), bool)
    forces = kernels.takeoff_forces
    for k in range(11):
        only_k = lambda p, c, k=k: np.repeat(forces(p, c)[:, k : k + 1], 11, axis=1)  # noqa: E731
        with mock.patch.object(kernels, "takeoff_forces", only_k):
            out[:, k] = kernels.takeoff(scene, poses, cfg).removed[:, 0]
    return out


def test_warp_takeoff_matches_cpu(pair):
    """Take-off under the Warp impl: the labels (removable, first direction, sequential
    ``removed``) equal the reference's, with the scene's and with sampled material; and
    each direction on its own (world-frame force at the object's COM) agrees with the
    reference run along that direction alone."""
    pytest.importorskip("warp")
    scene, poses = pair
    settings = mjx_kernels.MJXSettings(lanes=22, chunk=22, impl="warp")
    two = np.stack([poses[0], poses[0] + [0.002, 0, 0.001, 0, 0, 0, 0]])
    for cfg in (
        kernels.TakeoffConfig(push_time=0.2, free_time=0.1),
        kernels.TakeoffConfig(push_time=0.2, free_time=0.1, mass=0.3, friction=0.1),
    ):
        ref = kernels.takeoff(scene, two, cfg)
        got = kernels.takeoff(scene, two, cfg, backend="mjx", settings=settings)
        assert got.removable.tolist() == ref.removable.tolist()
        assert got.direction.tolist() == ref.direction.tolist()
        assert (got.removed == ref.removed).all()
        every = _cpu_every_direction(scene, two, cfg)
        pair0 = np.zeros(len(two), np.int32)
        dev = mjx_warp.takeoff_warp_removed([scene], pair0, two, cfg, settings)
        assert (dev == every).mean() >= 21 / 22


@pytest.mark.parametrize("category", ["wrench", "knife", "cap"])
def test_pybullet_reference_loads_every_mesh_part(category):
    """PyBullet (the benchmark's third engine) builds meshy objects whole: convex parts
    are written as triangulated hulls, so none is dropped and no shape array fails
    (wrench/knife seed 1000 used to fail with 'createCollisionShapeArray failed')."""
    pb = pytest.importorskip("pybullet")
    from sim import pybullet_ref
    from sim.assets import objects, supports  # noqa: F401
    from sim.assets.base import build_object, build_support
    from sim.scene import build_scene

    scene = build_scene(build_object(category, 1000), build_support("two_rod_hook", 2000))
    world = pybullet_ref.PairWorld(scene)
    try:
        pose = np.array([0.3, 0.2, 0.5, 1, 0, 0, 0.0])
        world.set_pose(pose)
        shapes = pb.getCollisionShapeData(world.body, -1, physicsClientId=world.client)
        assert len(shapes) == len(scene.obj.parts)  # every part, beyond PyBullet's 16 too
        lo, hi = np.array(pb.getAABB(world.body, physicsClientId=world.client))
        box = kernels.object_boxes(scene, pose[None])[0]
        # PyBullet's AABB (the union of its children's rotated local boxes, not tight)
        # holds the whole object, to the 1 mm of hull erosion (docs/judges.md); distances
        # to MuJoCo's geometry: tests/test_pybullet_ref.py
        assert (lo <= box[0] + 1e-3).all() and (hi >= box[1] - 1e-3).all()
    finally:
        world.close()


def test_warp_union_shares_mesh_geoms_between_pairs():
    """Pairs with the same convex parts share the union's mesh geoms (a group of shards has
    few distinct objects, and every world carries every geom through the broad phase); a
    part repeated inside one pair still gets a geom of its own."""
    import mujoco

    from sim.scene import build_scene

    cube = geometry.hull(
        np.array([[x, y, z] for x in (0, 0.02) for y in (0, 0.02) for z in (0, 0.02)])
    )
    twin = geometry.hull(cube.vertices + [0.0, 0.0, 0.0])  # same vertices, another part
    block = Asset("blocks", "object", "others", 0, [cube, twin], [], {})
    other = Asset("block", "object", "others", 1, [geometry.hull(cube.vertices * 1.5)], [], {})
    hook = support_of("single_rod_hook", style="angled")
    scenes = [build_scene(block, hook), build_scene(block, hook), build_scene(other, hook)]
    xml, maps = mjx_warp.union_xml(scenes, mjx_kernels.MJXSettings(impl="warp"))
    mj = mujoco.MjModel.from_xml_string(xml)
    names = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_GEOM, g) for g in range(mj.ngeom)]
    object_meshes = [n for n in names if n.startswith("o_mesh")]
    assert len(object_meshes) == 3  # cube and twin (one pair needs both), the larger block
    assert maps[0] == maps[1]
    mine = {u for u in maps[0] if u.startswith("o_mesh")}
    assert len(mine) == 2 and sorted(maps[0][u] for u in mine) == ["object_0", "object_1"]
    assert {u for u in maps[2] if u.startswith("o_mesh")}.isdisjoint(mine)
