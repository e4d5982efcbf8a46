"""PyBullet, the second judge: its world is MuJoCo's (geometry, mass, inertia, friction), and
it judges hangs the same way (a hang stays, a pose beside the hook falls)."""

from __future__ import annotations

import dataclasses
import os

import mujoco
import numpy as np
import pytest

pb = pytest.importorskip("pybullet")

from scipy.spatial.transform import Rotation  # noqa: E402

from sim import judges, kernels, proposals, pybullet_ref  # noqa: E402
from sim.assets import objects, supports  # noqa: E402, F401
from sim.assets.base import build_object, build_support  # noqa: E402
from sim.geometry import Box, ConvexMesh  # noqa: E402
from sim.scene import build_scene  # noqa: E402


@pytest.fixture(scope="module")
def hang():
    """A mug hanging on a single-rod hook: MuJoCo's stable settled poses (found here, not
    hard-coded) and the scene."""
    scene = build_scene(build_object("mug", 7), build_support("single_rod_hook", 3))
    cand = proposals.hang_poses(scene.obj, scene.support, 16, np.random.default_rng(0))
    res = kernels.stability(scene, cand, nthread=1)
    assert res.stable.sum() >= 2, "the test pair should hang in MuJoCo"
    return scene, res.settled_pose[res.stable][:2]


def test_known_hang_stays_and_pose_beside_the_hook_falls(hang):
    scene, poses = hang
    beside = poses.copy()
    beside[:, 0] += 0.08  # 8 cm along the wall: nothing under the object
    both = np.concatenate([poses, beside])
    bullet = pybullet_ref.stability(scene, both)
    assert bullet.status.tolist() == [kernels.STABLE] * 2 + [kernels.FALLEN] * 2
    # it comes to rest within a few millimetres of MuJoCo's rest pose
    assert np.abs(bullet.settled_pose[:2, :3] - poses[:, :3]).max() < 3e-3
    mj = kernels.stability(scene, both, nthread=1)
    assert (mj.stable == bullet.stable).all()


def test_judge_both_is_the_conjunction(hang):
    scene, poses = hang
    beside = poses[:1] + np.array([0.08, 0, 0, 0, 0, 0, 0])
    out = judges.judge_stability(scene, np.concatenate([poses[:1], beside]), judge="both")
    assert set(out.by_judge) == {"mujoco", "pybullet"}
    assert out.stable.tolist() == [True, False]
    assert out.status[1] == kernels.FALLEN
    with pytest.raises(ValueError, match="judge must be one of"):
        judges.judge_stability(scene, poses, judge="bullet")


@pytest.mark.parametrize("category,family", [("racquet", "towel_bar"), ("cap", "mug_tree")])
def test_world_geometry_inertia_and_frames_are_mujocos(category, family):
    """All parts load (a racquet has > 16, PyBullet's shape-array limit), distances to the
    support, wall and stand equal MuJoCo's within the 1 mm rounding of eroded hull edges,
    and mass, principal inertia and the pose round trip are MuJoCo's."""
    scene = build_scene(build_object(category, 11), build_support(family, 5))
    model, data = scene.model, mujoco.MjData(scene.model)
    world = pybullet_ref.PairWorld(scene)
    try:
        c = world.client
        assert len(pb.getCollisionShapeData(world.body, -1, physicsClientId=c)) == len(
            scene.obj.parts
        )
        info = pb.getDynamicsInfo(world.body, -1, physicsClientId=c)
        assert info[0] == pytest.approx(model.body_mass[scene.object_body])
        np.testing.assert_allclose(info[2], model.body_inertia[scene.object_body], rtol=1e-6)
        env = [g for g in range(model.ngeom) if g not in scene.object_geoms and g != 0]
        lo, hi = scene.support.bounds()
        rng = np.random.default_rng(0)
        errors = []
        for t in range(80):
            pose = np.concatenate(
                [rng.uniform(lo - 0.03, hi + 0.03), np.roll(Rotation.random(rng=t).as_quat(), 1)]
            )
            if scene.support.wall_y is not None:
                pose[1] = max(pose[1], scene.support.wall_y + 0.12)
            data.qpos[:7] = pose
            mujoco.mj_forward(model, data)
            d_mj = min(
                mujoco.mj_geomDistance(model, data, int(a), int(b), 0.03, None)
                for a in scene.object_geoms
                for b in env
            )
            world.set_pose(pose)
            np.testing.assert_allclose(world.pose()[:3], pose[:3], atol=1e-9)
            d_pb = min(
                [
                    p[8]
                    for body in [world.support, *world.ground[1:]]
                    for p in pb.getClosestPoints(world.body, body, 0.03, physicsClientId=c)
                ],
                default=0.03,
            )
            if min(d_mj, d_pb) > -0.002:  # deep overlaps have no unique depth
                errors.append(abs(d_mj - d_pb))
        assert len(errors) >= 5
        assert max(errors) < 1e-3 and np.median(errors) < 5e-4
    finally:
        world.close()


def _incline(config: pybullet_ref.BulletConfig, degrees: float) -> tuple[float, float]:
    """A 10 cm hull cube resting on a static box tilted by ``degrees``, with the judge's
    materials and hulls: (distance (m) it slides in 1 s, its initial contact distance (m))."""
    erosion = pybullet_ref.BULLET_HULL_MARGIN if config.hulls == "exact" else 0.0
    c = pb.connect(pb.DIRECT)
    try:
        pb.setGravity(0, 0, -9.81, physicsClientId=c)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=config.time_step,
            numSubSteps=config.sub_steps,
            numSolverIterations=config.solver_iterations,
            physicsClientId=c,
        )
        tilt = Rotation.from_euler("x", degrees, degrees=True)
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            ramp = pb.loadURDF(
                pybullet_ref.write_urdf(
                    f"{tmp}/ramp.urdf", [Box(np.zeros(3), np.eye(3), np.array([1, 1, 0.05]))]
                ),
                tilt.apply([0, 0, -0.05]).tolist(),
                tilt.as_quat().tolist(),
                useFixedBase=True,
                physicsClientId=c,
            )
            cube = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
            body = pb.loadURDF(
                pybullet_ref.write_urdf(
                    f"{tmp}/cube.urdf",
                    [ConvexMesh(0.05 * cube)],
                    0.5,
                    (1e-3,) * 3,
                    tag="cube",
                    hull_erosion=erosion,
                ),
                tilt.apply([0, 0, 0.05]).tolist(),
                tilt.as_quat().tolist(),
                physicsClientId=c,
            )
        pybullet_ref.set_materials(c, body, [ramp], config)
        pb.performCollisionDetection(physicsClientId=c)
        depth = min(p[8] for p in pb.getContactPoints(body, ramp, physicsClientId=c))
        start = np.array(pb.getBasePositionAndOrientation(body, physicsClientId=c)[0])
        for _ in range(100):
            pb.stepSimulation(physicsClientId=c)
        end = np.array(pb.getBasePositionAndOrientation(body, physicsClientId=c)[0])
        return float(np.linalg.norm(end - start)), depth
    finally:
        pb.disconnect(c)


def test_friction_is_the_combined_coefficient_and_hulls_are_exact():
    """Bullet multiplies the two bodies' frictions: the original's 0.5 x 0.5 = 0.25 slides
    on a 20 degree incline (tan = 0.36), and its 1 mm hull margin starts a resting cube 1 mm
    deep; the matched set-up starts it touching and holds it (0.5 x 1.0) and, like Coulomb
    friction 0.5, lets it slide at 30 degrees (tan = 0.58) or with friction 0.3."""
    matched, original = pybullet_ref.MATCHED, pybullet_ref.ORIGINAL
    slide, depth = _incline(original, 20)
    assert slide > 0.1 and depth == pytest.approx(-0.001, abs=1e-5)
    slide, depth = _incline(matched, 20)
    assert slide < 1e-3 and abs(depth) < 1e-6
    assert _incline(matched, 30)[0] > 0.1
    assert _incline(dataclasses.replace(matched, friction=0.3), 20)[0] > 0.1


def test_erode_hull_moves_faces_inwards():
    cube = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * 0.05
    eroded = pybullet_ref.erode_hull(cube, 0.001)
    np.testing.assert_allclose(np.abs(eroded), 0.049, atol=1e-9)
    plate = cube * np.array([1, 1, 0.01])  # 1 mm thick: eroded by 90 % of its 0.5 mm inradius
    thin = pybullet_ref.erode_hull(plate, 0.001)
    np.testing.assert_allclose(np.abs(thin[:, 2]).max(), 0.0005 * 0.1, atol=1e-9)


def test_bad_settings_fail_clearly(hang):
    scene, _ = hang
    for field, value in (("friction_combine", "max"), ("inertia", "x"), ("hulls", "y")):
        with pytest.raises(ValueError, match=field):
            pybullet_ref.PairWorld(
                scene, dataclasses.replace(pybullet_ref.MATCHED, **{field: value})
            )


def test_erode_hull_keeps_sharp_tips():
    """A knife-like wedge (6 degree tip): eroding its faces by 1 mm would pull the tip back
    about 1 cm, so it is eroded less and no vertex ends more than 1 mm outside."""
    wedge = np.array(
        [[0, -0.005, -0.01], [0, 0.005, -0.01], [0, -0.005, 0.01], [0, 0.005, 0.01]]
        + [[0.1, 0, -0.01], [0.1, 0, 0.01]]
    )
    for depth in (0.001,):
        eroded = pybullet_ref.erode_hull(wedge, depth)
        gap = np.linalg.norm(wedge[:, None] - eroded[None], axis=-1).min(1)
        assert eroded[:, 0].max() > 0.1 - 0.02  # the tip stays near x = 0.1
        assert (gap <= depth + 0.001 + 1e-9).all()


# Pair 4846 of the paper dataset's held-out split (clothes_hanger_0005 on mug_tree_0010): the
# answers of Stage 1, Stage 1+2, Stage 1+3 and all stages of a held-out evaluation.
PAIR_4846_POSES = [
    [0.010519614443182945, -0.007246396038681269, 0.03812822327017784,
     0.9076762795448303, 0.008303013630211353, -0.13426917791366577, 0.3975256681442261],
    [0.01873163878917694, -0.0032222222071141005, 0.03739733248949051,
     0.9076762795448303, 0.008303013630211353, -0.13426917791366577, 0.3975256681442261],
    [-0.022411059588193893, 0.001722145825624466, 0.051291219890117645,
     0.7530350685119629, -0.12466730922460556, -0.022271446883678436, -0.6456781029701233],
    [-0.03358829393982887, 0.01557794027030468, 0.03941619396209717,
     0.7130275368690491, -0.12208858877420425, -0.05679059773683548, -0.6880850791931152],
]  # fmt: skip


def _library_asset(config, kind: str, name: str):
    """The dataset library's asset ``name`` ("<category>_<index>"), built alone the way
    ``sim.library.build_library`` builds it."""
    from sim.library import asset_seed

    category, index = name.rsplit("_", 1)
    build = build_object if kind == "object" else build_support
    return build(category, asset_seed(config.seed, kind, category, int(index)), int(index))


@pytest.mark.skipif(
    not os.path.exists("datasets/paper/recipe.json"), reason="paper dataset not present"
)
def test_poses_judged_in_one_world_do_not_see_the_previous_poses_contacts():
    """Bullet keeps contact manifolds across ``set_pose``: a clothes hanger's hanging pose
    judged after three penetrating poses of the same pair read 28 mm deep in one shared
    world (0 mm alone). ``stability`` must give each pose the verdict it gets alone."""
    from omnihang_jax import dataset_bridge
    from omnihang_jax.evaluate import protocol_stability

    recipe = dataset_bridge.read_recipe("datasets/paper")
    library = dataset_bridge.dataset_config_from_recipe(recipe).library
    scene = build_scene(
        _library_asset(library, "object", "clothes_hanger_0005"),
        _library_asset(library, "support", "mug_tree_0010"),
    )
    poses = np.array(PAIR_4846_POSES, np.float64)
    config = protocol_stability()
    shared = pybullet_ref.stability(scene, poses, config)
    alone = [pybullet_ref.stability(scene, poses[i : i + 1], config) for i in range(4)]
    assert [int(a.status[0]) for a in alone] == [kernels.PENETRATING] * 3 + [kernels.STABLE]
    assert shared.status.tolist() == [int(a.status[0]) for a in alone]
    np.testing.assert_allclose(
        shared.initial_penetration, [a.initial_penetration[0] for a in alone], atol=1e-4
    )
