"""The scene's wall is solid (labels version 3): a strap can no longer pass
through it, while everything in front of it is as before; and the relabel tool finds and
splices exactly the changed pairs."""

from __future__ import annotations

import numpy as np
import pytest

from sim import dataset, dataset_io, judges, kernels
from sim.assets import objects, supports  # noqa: F401  (register the generators)
from sim.assets.base import build_object, build_support
from sim.scene import PhysicsConfig, build_scene, wall_box

# bag_0029 x two_rod_hook_0004 of the paper dataset (pair 2152): two of its stored
# version-2 stable poses. BEHIND: the strap went through the 2 cm slab and the bag hung
# 11.7 cm behind the wall plane; FRONT: an ordinary hang on the hook.
BAG_SEED, HOOK_SEED = 568245083, 3806430513
BEHIND = np.array([0.0289, 0.0406, 0.0344, 0.8387476, 0.536398, 0.0789216, -0.0505086])
FRONT = np.array([-0.0031, 0.0063, -0.171, 0.0006104, -0.0018616, -0.0076296, 0.9999689])


@pytest.fixture(scope="module")
def bag_scene():
    return build_scene(build_object("bag", BAG_SEED), build_support("two_rod_hook", HOOK_SEED))


def test_wall_is_a_block_behind_the_same_front_face(bag_scene):
    m, w = bag_scene.model, bag_scene.wall_geom
    wall_y = bag_scene.support.wall_y
    assert w >= 0
    # front face on the wall plane, 0.5 m deep, 2 m x 2 m
    assert m.geom_pos[w][1] + m.geom_size[w][1] == pytest.approx(wall_y, abs=1e-6)
    assert 2 * m.geom_size[w][1] == pytest.approx(PhysicsConfig().wall_thickness)
    pos, half = wall_box(wall_y)
    np.testing.assert_allclose(m.geom_pos[w], pos, atol=1e-6)
    np.testing.assert_allclose(m.geom_size[w], half, atol=1e-6)
    # the 2 cm slab of labels versions 1-2 is the thin_wall variant (same front face)
    thin = judges.mujoco_variant(bag_scene, **judges.MUJOCO_VARIANTS["thin_wall"]).model
    assert thin.geom_pos[w][1] + thin.geom_size[w][1] == pytest.approx(wall_y, abs=1e-6)
    assert 2 * thin.geom_size[w][1] == pytest.approx(0.02)


def test_strap_through_the_wall_no_longer_hangs_a_known_hang_still_does(bag_scene):
    """Physics with physics: in the old 2 cm slab both stored poses are stable (the strap
    passes through it); in the solid wall the pose behind the wall starts deep inside it
    (PENETRATING: generation rejects it), the ordinary hang is stable as before."""
    poses = np.stack([BEHIND, FRONT])
    depth = judges.behind_wall_depth(bag_scene.obj, poses, bag_scene.support.wall_y)
    assert depth[0] > 0.1 and depth[1] == 0.0
    cfg = dataset.DatasetConfig().stability
    thin = judges.mujoco_variant(bag_scene, thick_wall=0.02)
    old = kernels.stability(thin, poses, cfg)
    assert old.stable.tolist() == [True, True]
    new = kernels.stability(bag_scene, poses, cfg)
    assert new.status.tolist() == [kernels.PENETRATING, kernels.STABLE]
    assert new.initial_penetration[0] > 0.05  # the strap is centimetres inside the wall
    # the contact query (near misses, collision labels) sees the same
    con = kernels.contact_query(bag_scene, poses)
    assert con.penetration[0] > 0.05 and con.penetration[1] < 1e-3


def test_mjx_template_has_the_scenes_wall(bag_scene):
    mjx_kernels = pytest.importorskip("sim.mjx_kernels")
    import mujoco

    counts = (16, 8, 16)
    xml = mjx_kernels.template_xml(bag_scene, counts, counts, mjx_kernels.MJXSettings())[0]
    m = mujoco.MjModel.from_xml_string(xml)
    w = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "wall")
    np.testing.assert_allclose(m.geom_pos[w], bag_scene.model.geom_pos[bag_scene.wall_geom])
    np.testing.assert_allclose(m.geom_size[w], bag_scene.model.geom_size[bag_scene.wall_geom])


def _one_pair_shard(index: int, n_stable: int, rng) -> dict:
    rec = dict(
        n_candidates=10, n_penetrating=1, n_fallen=2, n_stable_raw=n_stable,
        n_takeoff_rejected=0, mass=0.5, friction=0.3,
        stable_poses=np.concatenate(
            [rng.normal(0, 0.05, (n_stable, 3)), np.tile([1.0, 0, 0, 0], (n_stable, 1))], 1
        ),
        negative_kept=rng.random(7) < 0.5, collision_kept=rng.random(9) < 0.5,
        collision_label=rng.random(9) < 0.5,
        object_eye=rng.normal(size=3), support_eye=rng.normal(size=3),
    )  # fmt: skip
    return rec


def test_splice_replaces_only_the_listed_pairs():
    from experiments import relabel

    rng = np.random.default_rng(0)
    recs = [_one_pair_shard(i, n, rng) for i, n in enumerate([3, 0, 5, 2])]
    ids = [(i, i + 1, 1000 + i) for i in range(4)]
    shard = dataset_io.pack_shard(recs, [8, 9, 10, 11], ids)
    new = _one_pair_shard(9, 4, rng)
    repl = {9: dataset_io.pack_shard([new], [9], [ids[1]])}
    out = relabel.splice(shard, repl)
    assert set(out) == set(shard) and all(out[k].dtype == shard[k].dtype for k in shard)
    before, after = dataset_io.unpack(shard), dataset_io.unpack(out)
    for i in (0, 2, 3):  # untouched pairs: identical stored values
        for k in before[i]:
            np.testing.assert_array_equal(before[i][k], after[i][k])
    np.testing.assert_array_equal(after[1]["negative_kept"], new["negative_kept"])
    np.testing.assert_array_equal(after[1]["collision_label"], new["collision_label"])
    assert len(after[1]["stable_poses"]) == 4 and int(after[1]["n_stable_raw"]) == 4
    # raw quantised poses of untouched pairs are copied, not requantised
    a, b = shard["stable_offsets"][2], shard["stable_offsets"][3]
    c, d = out["stable_offsets"][2], out["stable_offsets"][3]
    np.testing.assert_array_equal(shard["stable_quaternion"][a:b], out["stable_quaternion"][c:d])


def test_wall_changes_flags_labels_behind_the_wall(bag_scene):
    """A stored record with the BEHIND pose is flagged (stable), one with only FRONT is not;
    a stored non-colliding label on a pose behind the plane is flagged (collision)."""
    from experiments import relabel

    obj, sup = bag_scene.obj, bag_scene.support
    config = dataset.DatasetConfig()
    seed = 7
    base = dict(
        pair_seed=np.uint64(seed),
        negative_kept=np.zeros(config.negative_candidates, bool),
    )
    poses = dataset.collision_poses(obj, sup, seed, config)
    behind = judges.behind_wall_depth(obj, poses, sup.wall_y) > 0
    assert behind.any() and not behind.all()
    colliding = behind.copy()  # the solid wall's labels: nothing to change
    front = dict(base, stable_poses=FRONT[None], collision_label=colliding)
    assert relabel.wall_changes(front, obj, sup, config) == {
        "stable": 0, "negative": 0, "collision": 0
    }  # fmt: skip
    both = dict(base, stable_poses=np.stack([FRONT, BEHIND]), collision_label=np.zeros_like(behind))
    c = relabel.wall_changes(both, obj, sup, config)
    assert c["stable"] == 1 and c["collision"] == int(behind.sum())


def test_collision_relabel_marks_poses_behind_the_wall_colliding(bag_scene):
    """``relabel._collision_behind``: a stored "free" label on a pose that reaches behind the
    wall plane becomes colliding (and kept) under the solid wall; poses in front keep their
    stored labels; it agrees with the generator's own rule on those poses."""
    from experiments import relabel

    config = dataset.DatasetConfig(n_collision=200)
    seed = 3
    obj, sup = bag_scene.obj, bag_scene.support
    poses = dataset.collision_poses(obj, sup, seed, config)
    behind = judges.behind_wall_depth(obj, poses, sup.wall_y) > 0
    assert 0 < behind.sum() < len(poses)
    stored = np.zeros(len(poses), bool)
    kept, label = relabel._collision_behind(bag_scene, seed, config, stored, stored)
    assert label[behind].all() and kept[behind].all()
    assert not label[~behind].any() and not kept[~behind].any()
    full_kept, full_label = dataset.collision_labels(bag_scene, obj, sup, seed, config)
    np.testing.assert_array_equal(label[behind], full_label[behind])
    np.testing.assert_array_equal(kept[behind], full_kept[behind])
