"""PyBullet version of the stability protocol (the original paper's engine), for benchmarks.

Settings from the original code: time step 1/100 s with 40 sub-steps, 40 solver
iterations, gravity -9.81, lateral friction 0.5 (PyBullet's default). The pair is built
from the same convex parts as the MuJoCo scene: capsules -> GEOM_CAPSULE, boxes ->
GEOM_BOX, convex meshes -> GEOM_MESH (a triangulated hull OBJ file per part, see
:func:`_write_hull_obj`). The
protocol is :mod:`sim.kernels`' (1 mm penetration reject, 2 s in 0.1 s checks, ground
contact / box separation = fallen, divergence, early rest), so labels per second compare
engines under one protocol. One core, one world at a time: how the original ran.
"""

from __future__ import annotations

import os
import tempfile

import numpy as np
import pybullet as pb
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.transform import Rotation

from sim import geometry, kernels
from sim.assets.base import Asset
from sim.geometry import Box, Capsule, ConvexMesh
from sim.kernels import DIVERGED, FALLEN, PENETRATING, STABLE, StabilityConfig, StabilityResult
from sim.scene import Scene

TIME_STEP = 1.0 / 100.0  # original
SUB_STEPS = 40  # original
SOLVER_ITERATIONS = 40  # original


def _xyzw(rot: np.ndarray) -> list[float]:
    return Rotation.from_matrix(rot).as_quat().tolist()


def _write_hull_obj(fname: str, vertices) -> None:
    """Write the convex hull of ``vertices`` as a triangulated OBJ file.

    PyBullet reads OBJ meshes through their faces: a file of bare ``v`` lines loads as an
    empty mesh ("issue extracting mesh from COLLADA/STL file"), which either drops the part
    silently from the compound or fails the whole ``createCollisionShapeArray``. The hull's
    vertices (duplicates and interior points removed) and triangles are written instead.
    """
    pts = np.unique(np.round(np.asarray(vertices, float), 9), axis=0)
    try:
        hull = ConvexHull(pts)
    except QhullError:  # flat or degenerate: joggle (exact enough for collision)
        hull = ConvexHull(pts, qhull_options="QJ")
    used = np.unique(hull.simplices)
    remap = np.full(len(pts), -1)
    remap[used] = np.arange(len(used))
    centre = pts[used].mean(0)
    with open(fname, "w") as f:
        f.writelines(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in pts[used])
        for tri in hull.simplices:
            a, b, c = pts[tri]
            if np.dot(np.cross(b - a, c - a), a - centre) < 0:  # outward winding
                tri = tri[[0, 2, 1]]
            f.write("f {} {} {}\n".format(*(remap[tri] + 1)))


def _shape_args(parts, offset: np.ndarray, tmp: str, tag: str) -> dict:
    """Arguments of ``createCollisionShapeArray`` for ``parts`` shifted by ``-offset``."""
    args = {k: [] for k in ("shapeTypes", "radii", "halfExtents", "lengths", "fileNames")}
    args.update(collisionFramePositions=[], collisionFrameOrientations=[], meshScales=[])
    for i, part in enumerate(parts):
        radius, half, length, fname = 0.0, [0.0] * 3, 0.0, ""
        if isinstance(part, Capsule):
            axis = part.p1 - part.p0
            length = float(np.linalg.norm(axis))
            z = axis / max(length, 1e-12)
            rot = Rotation.align_vectors([z], [[0, 0, 1.0]])[0].as_matrix()
            kind, radius, pos = pb.GEOM_CAPSULE, float(part.radius), 0.5 * (part.p0 + part.p1)
        elif isinstance(part, Box):
            kind, half, pos, rot = (
                pb.GEOM_BOX,
                list(map(float, part.half_size)),
                part.center,
                part.rotation,
            )
        elif isinstance(part, ConvexMesh):
            fname = os.path.join(tmp, f"{tag}{i}.obj")
            _write_hull_obj(fname, part.vertices)
            kind, pos, rot = pb.GEOM_MESH, np.zeros(3), np.eye(3)
        else:
            raise TypeError(type(part))
        args["shapeTypes"].append(kind)
        args["radii"].append(radius)
        args["halfExtents"].append(half)
        args["lengths"].append(length)
        args["fileNames"].append(fname)
        args["meshScales"].append([1, 1, 1])
        args["collisionFramePositions"].append((np.asarray(pos) - offset).tolist())
        args["collisionFrameOrientations"].append(_xyzw(rot))
    return args


class PairWorld:
    """One PyBullet world holding a pair: support (+ stand base and floor) and the object."""

    def __init__(self, scene: Scene, friction: float = 0.5, mass: float | None = None):
        self.scene = scene
        obj, support = scene.obj, scene.support
        self.client = pb.connect(pb.DIRECT)
        c = self.client
        pb.setGravity(0, 0, scene.physics.gravity, physicsClientId=c)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=TIME_STEP,
            numSubSteps=SUB_STEPS,
            numSolverIterations=SOLVER_ITERATIONS,
            physicsClientId=c,
        )
        self._tmp = tempfile.TemporaryDirectory()
        ground = set(support.ground_parts)
        hold = [p for i, p in enumerate(support.parts) if i not in ground]
        base = [p for i, p in enumerate(support.parts) if i in ground]
        if support.wall_y is not None:
            h = scene.physics.wall_half_size
            hold.append(
                Box(np.array([0, support.wall_y - 0.01, 0]), np.eye(3), np.array([h, 0.01, h]))
            )
        self.support = self._static(hold, "s")
        floor = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=c)
        self.ground = [
            pb.createMultiBody(0, floor, basePosition=[0, 0, support.floor_z], physicsClientId=c)
        ]
        if base:
            self.ground.append(self._static(base, "g"))
        vol = geometry.parts_volume(obj.parts)
        centres = np.array([p.support_points().mean(0) for p in obj.parts])
        self.com = (vol[:, None] * centres).sum(0) / vol.sum()
        shape = pb.createCollisionShapeArray(
            **_shape_args(obj.parts, self.com, self._tmp.name, "o"), physicsClientId=c
        )
        m = scene.physics.object_mass if mass is None else mass
        self.body = pb.createMultiBody(m, shape, basePosition=[0, 0, 50], physicsClientId=c)
        for b in [self.body, self.support, *self.ground]:
            pb.changeDynamics(b, -1, lateralFriction=friction, physicsClientId=c)

    def _static(self, parts, tag) -> int:
        c = self.client
        try:
            args = _shape_args(parts, np.zeros(3), self._tmp.name, tag)
            shape = pb.createCollisionShapeArray(**args, physicsClientId=c)
        except pb.error:  # some single-mesh arrays fail: give the mesh its vertices directly
            if len(parts) != 1 or not isinstance(parts[0], ConvexMesh):
                raise
            verts = np.asarray(parts[0].vertices, float).tolist()
            shape = pb.createCollisionShape(pb.GEOM_MESH, vertices=verts, physicsClientId=c)
        return pb.createMultiBody(0, shape, physicsClientId=c)

    def set_pose(self, pose: np.ndarray) -> None:
        rot = Rotation.from_quat(np.roll(pose[3:], -1))
        pos = pose[:3] + rot.apply(self.com)
        pb.resetBasePositionAndOrientation(
            self.body, pos.tolist(), rot.as_quat().tolist(), physicsClientId=self.client
        )
        pb.resetBaseVelocity(self.body, [0, 0, 0], [0, 0, 0], physicsClientId=self.client)

    def pose(self) -> np.ndarray:
        pos, quat = pb.getBasePositionAndOrientation(self.body, physicsClientId=self.client)
        rot = Rotation.from_quat(quat)
        return np.concatenate([np.asarray(pos) - rot.apply(self.com), np.roll(quat, 1)])

    def contacts(self, other: int):
        return pb.getContactPoints(self.body, other, physicsClientId=self.client)

    def close(self) -> None:
        pb.disconnect(self.client)
        self._tmp.cleanup()


def stability(scene: Scene, poses: np.ndarray, config: StabilityConfig = StabilityConfig()):
    """:func:`sim.kernels.stability`'s protocol in PyBullet, one pose after the other."""
    poses = kernels.check_poses(poses)
    world = PairWorld(scene)
    n = len(poses)
    status = np.full(n, -1, np.int8)
    final, depth, sim_time = poses.copy(), np.zeros(n), np.zeros(n)
    every = max(1, round(config.check_every / TIME_STEP))
    nseg = max(1, round(config.duration / (every * TIME_STEP)))
    c = world.client
    for i, pose in enumerate(poses):
        world.set_pose(pose)
        pb.performCollisionDetection(physicsClientId=c)
        dists = [p[8] for b in [world.support, *world.ground] for p in world.contacts(b)]
        depth[i] = max(0.0, -min(dists, default=0.0))
        if depth[i] > config.max_penetration:
            status[i] = PENETRATING
            continue
        rest = 0
        for k in range(nseg):
            ground = False
            for _ in range(every):
                pb.stepSimulation(physicsClientId=c)
                ground |= any(len(world.contacts(g)) > 0 for g in world.ground)
            q = world.pose()
            lin, ang = pb.getBaseVelocity(world.body, physicsClientId=c)
            speed, spin = np.linalg.norm(lin), np.linalg.norm(ang)
            sim_time[i] = (k + 1) * every * TIME_STEP
            if (
                not np.isfinite(q).all()
                or np.linalg.norm(q[:3]) > config.escape_radius
                or speed > config.max_speed
            ):
                status[i] = DIVERGED
                break
            final[i] = q
            box = kernels.object_boxes(scene, q[None])
            if ground or not kernels.boxes_overlap(box, scene.support_bounds, config.box_margin)[0]:
                status[i] = FALLEN
                break
            touching = len(world.contacts(world.support)) > 0
            resting = speed < config.settle_speed and spin < config.settle_spin and touching
            rest = rest + 1 if resting else 0
            if rest >= config.settle_checks:
                status[i] = STABLE
                break
        if status[i] < 0:
            status[i] = STABLE
    world.close()
    return StabilityResult(status == STABLE, status, final, depth, sim_time)


def describe(asset: Asset) -> str:
    return f"{asset.name} ({len(asset.parts)} parts)"
