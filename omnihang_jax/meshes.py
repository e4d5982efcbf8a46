"""Ground truth on the full meshes (MuJoCo, host) and the planner's scene geometry: its start
pose, bounds and metric. Apart from ``omnihang_jax.planner`` (which needs OMPL) so that
training can label poses the way the planner judges them on a machine without OMPL;
``collision`` and ``planner`` re-export them.
"""

from __future__ import annotations

import numpy as np


class MeshChecker:
    """Full-mesh collision through MuJoCo: colliding when any object geom penetrates a
    support (or wall) geom deeper than ``tolerance``. Host CPU, one state at a time."""

    def __init__(self, scene, tolerance: float = 1e-3):
        self.scene = scene
        self.model = scene.model
        import mujoco

        self._mujoco = mujoco
        self.data = mujoco.MjData(self.model)
        self.tolerance = tolerance
        self.object_geoms = set(int(g) for g in scene.object_geoms)
        others = list(scene.support_geoms) + ([scene.wall_geom] if scene.wall_geom >= 0 else [])
        self.other_geoms = set(int(g) for g in others)

    def deepest_contacts(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """[B, 7] -> (depth [B] of the deepest object-support penetration in metres, 0 if none;
        its contact point [B, 3] in the support frame, NaN where there is none)."""
        poses = np.asarray(poses, float).reshape(-1, 7)
        depth = np.zeros(len(poses))
        point = np.full((len(poses), 3), np.nan)
        m, d = self.model, self.data
        for i, pose in enumerate(poses):
            d.qpos[:7] = pose
            self._mujoco.mj_kinematics(m, d)
            self._mujoco.mj_collision(m, d)
            for j in range(d.ncon):
                con = d.contact[j]
                g1, g2 = int(con.geom1), int(con.geom2)
                if (g1 in self.object_geoms and g2 in self.other_geoms) or (
                    g2 in self.object_geoms and g1 in self.other_geoms
                ):
                    if -float(con.dist) > depth[i]:
                        depth[i], point[i] = -float(con.dist), con.pos
        return depth, point

    def clearance(self, poses: np.ndarray, cap: float = 0.05) -> np.ndarray:
        """[B, 7] -> [B] the smallest signed distance (m, at most ``cap``; negative when they
        overlap) between any object part and any support (or wall) part, by
        ``mujoco.mj_geomDistance``: how far off the support a pose is."""
        poses = np.asarray(poses, float).reshape(-1, 7)
        out = np.full(len(poses), cap)
        m, d = self.model, self.data
        for i, pose in enumerate(poses):
            d.qpos[:7] = pose
            self._mujoco.mj_kinematics(m, d)
            for a in self.object_geoms:
                for b in self.other_geoms:
                    out[i] = min(out[i], float(self._mujoco.mj_geomDistance(m, d, a, b, cap, None)))
        return out

    def penetration(self, poses: np.ndarray) -> np.ndarray:
        """[B, 7] -> [B] deepest object-support penetration in metres (0 if none)."""
        return self.deepest_contacts(poses)[0]

    def __call__(self, poses: np.ndarray) -> np.ndarray:
        return self.penetration(poses) > self.tolerance


def posed_points(poses: np.ndarray, points: np.ndarray) -> np.ndarray:
    """NumPy twin of ``collision.transform_points`` for host-side checkers: poses [B, 7]
    (xyz + wxyz), points [N, 3] (object frame) -> [B, N, 3] (support frame). The planner calls
    its checkers ~1,000 times a plan with varying batch sizes: eager JAX ops or a jit per size
    would cost more than the arithmetic."""
    poses = np.asarray(poses, float).reshape(-1, 7)
    q = poses[:, 3:] / np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
    w, x, y, z = q.T
    rot = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)  # fmt: skip
    return np.einsum("bij,nj->bni", rot, np.asarray(points, float)) + poses[:, None, :3]


def cloud_gap(object_points, support, poses: np.ndarray, upper: float = np.inf) -> np.ndarray:
    """[K] the smallest distance (m) between the object cloud [N, 3] (object frame) moved by
    each pose [K, 7] and the support cloud (support frame): ``support`` is its points [M, 3]
    or a ``scipy.spatial.cKDTree`` of them (build it once for many calls). Distances of
    ``upper`` or more come back as inf (a much faster search). Host NumPy: the quantity
    ``planner.ClearanceFarFromGoal`` thresholds and the transit poses of
    ``experiments.train_collision`` are kept by."""
    from scipy.spatial import cKDTree

    poses = np.asarray(poses, float).reshape(-1, 7)
    if len(poses) == 0:
        return np.zeros(0)
    tree = support if isinstance(support, cKDTree) else cKDTree(np.asarray(support, float))
    moved = posed_points(poses, object_points)  # [K, N, 3]
    d, _ = tree.query(moved.reshape(-1, 3), k=1, distance_upper_bound=upper)
    return d.reshape(len(poses), -1).min(axis=1)


def object_radius(scene) -> float:
    """Half the object's largest extent (m): the rotation weight of the planner's metric."""
    return 0.5 * float(np.max(scene.obj.extents))


def default_bounds(scene) -> tuple[np.ndarray, np.ndarray]:
    """The support's box grown by the object's largest extent on every side, and on +y up
    to half an extent beyond :func:`start_pose`."""
    grow = float(np.max(scene.obj.extents))
    lo, hi = np.asarray(scene.support_bounds, float)
    lo, hi = lo - grow, hi + grow
    hi[1] += 1.0 * grow
    return lo, hi


def start_pose(scene, goal: np.ndarray) -> np.ndarray:
    """In front of the support (+y), clear of its box by the object's largest extent (the
    centre 1.5 extents beyond it), at the goal's x and height, in the goal's orientation."""
    size = float(np.max(scene.obj.extents))
    hi = np.asarray(scene.support_bounds, float)[1]
    return np.array([goal[0], hi[1] + 1.5 * size, goal[2], *goal[3:]], float)
