"""Partial point clouds from one virtual depth camera, by ray casting (``mujoco.mj_multiRay``).

No OpenGL is needed, so this runs headless on any CPU. Each pixel's ray returns the first
surface hit, its distance and the surface normal; segmentation comes from geom groups
(object 1, support 2, wall and floor 3): the object's cloud is cast with only group 1
visible, the support's with only group 2, so each is exactly what the camera sees of that
body (self-occlusion included, the other body not occluding; the original rendered each
body alone in the same way).

Camera (original: 640x480, 60 degree field of view, near 0.02, far 4, on a sphere around
the body looking at its origin; supports only from the side away from the wall): here the
sphere's radius is chosen so the body's bounding sphere fits the field of view
(``radius / sin(fov / 2) * margin``). The original's "1.2 x object scale" presumes its own
scale unit; ours is explicit and never clips the body.

Frames: the object's cloud is in the object frame (the object is placed at the identity
pose for the render), the support's in the support (world) frame.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import mujoco
import numpy as np

from sim.scene import ENV_GROUP, OBJECT_GROUP, PARK_HEIGHT, SUPPORT_GROUP, Scene


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    width: int = 640  # pixels (original)
    height: int = 480
    fovy_deg: float = 60.0  # vertical field of view (original 60 degrees)
    near: float = 0.02  # m (original)
    far: float = 4.0  # m (original)
    fit_margin: float = 1.1  # camera distance = bounding radius / sin(fov/2) * margin
    n_points: int = 4096  # points per cloud after resampling (original 4096)
    depth_noise: float = 0.0  # m, std of Gaussian noise along each ray (0: none)


class PointCloud(NamedTuple):
    points: np.ndarray  # [N, 3] float32 metres
    normals: np.ndarray  # [N, 3] float32 unit outward normals
    eye: np.ndarray  # [3] camera position, same frame as the points
    n_visible: int  # pixels that hit the body before resampling


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[3, 3] camera frame (columns: right, down, forward) looking from ``eye`` at ``target``."""
    fwd = np.asarray(target, float) - np.asarray(eye, float)
    fwd /= np.linalg.norm(fwd)
    up = np.asarray(up, float)
    if abs(np.dot(fwd, up)) > 0.99:
        up = np.array([0.0, 1.0, 0.0])
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    return np.stack([right, down, fwd], axis=1)


@functools.lru_cache(maxsize=8)
def _pixel_rays(height: int, width: int, fovy_deg: float) -> np.ndarray:
    """[H * W, 3] unit ray directions in the camera frame (read-only, cached per intrinsics:
    this was ~80% of the time of a 640x480 render when computed per call)."""
    f = 0.5 * height / np.tan(np.deg2rad(fovy_deg) / 2)
    u = (np.arange(width) + 0.5 - width / 2) / f
    v = (np.arange(height) + 0.5 - height / 2) / f
    uu, vv = np.meshgrid(u, v)
    local = np.stack([uu, vv, np.ones_like(uu)], axis=-1).reshape(-1, 3)
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    local.setflags(write=False)
    return local


def camera_rays(eye, target, config: CameraConfig) -> np.ndarray:
    """[H * W, 3] unit ray directions in row-major pixel order (pinhole camera)."""
    local = _pixel_rays(config.height, config.width, float(config.fovy_deg))
    return local @ look_at(eye, target).T


def camera_distance(radius: float, config: CameraConfig) -> float:
    half = np.deg2rad(config.fovy_deg) / 2 * min(1.0, config.width / config.height)
    return radius / np.sin(half) * config.fit_margin


def sample_eye(
    rng: np.random.Generator, center, radius: float, config: CameraConfig, front_only: bool = False
):
    """A camera position on the sphere around ``center``; ``front_only``: the +y side (away
    from a wall at low y) and not from below the support."""
    while True:
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        if not front_only or (d[1] > 0.2 and d[2] > -0.3):
            break
    return np.asarray(center, float) + camera_distance(radius, config) * d


def cast(model, data, eye, dirs, groups: tuple[int, ...], static: bool, cutoff: float):
    """Cast rays [R, 3] from ``eye``; returns geom ids [R], distances [R] (-1 miss), normals [R, 3]."""
    n = len(dirs)
    geomgroup = np.zeros(6, dtype=np.uint8)
    geomgroup[list(groups)] = 1
    geomid = np.zeros(n, dtype=np.int32)
    dist = np.zeros(n)
    normal = np.zeros(3 * n)
    mujoco.mj_multiRay(
        model,
        data,
        np.asarray(eye, float),
        np.ascontiguousarray(dirs, dtype=float).ravel(),
        geomgroup,
        int(static),
        -1,
        geomid,
        dist,
        normal,
        n,
        cutoff,
    )
    return geomid, dist, normal.reshape(n, 3)


def render_depth(scene: Scene, which: str, eye, target, config: CameraConfig, pose=None):
    """Depth image of one body: (dist [H, W] with -1 for misses, normals [H, W, 3], dirs)."""
    model = scene.model
    data = mujoco.MjData(model)
    if which == "object":
        data.qpos[:7] = [0, 0, 0, 1, 0, 0, 0] if pose is None else pose
        groups, static = (OBJECT_GROUP,), False
    elif which == "support":
        data.qpos[:7] = [0, 0, PARK_HEIGHT, 1, 0, 0, 0]
        groups, static = (SUPPORT_GROUP,), True
    elif which == "scene":
        data.qpos[:7] = [0, 0, PARK_HEIGHT, 1, 0, 0, 0] if pose is None else pose
        groups, static = (OBJECT_GROUP, SUPPORT_GROUP, ENV_GROUP), True
    else:
        raise ValueError(f"which must be 'object', 'support' or 'scene', got {which!r}")
    mujoco.mj_kinematics(model, data)
    dirs = camera_rays(eye, target, config)
    geomid, dist, normal = cast(model, data, eye, dirs, groups, static, config.far)
    dist = np.where((geomid >= 0) & (dist >= config.near) & (dist <= config.far), dist, -1.0)
    shape = (config.height, config.width)
    return (
        dist.reshape(shape),
        normal.reshape(*shape, 3),
        dirs.reshape(*shape, 3),
        geomid.reshape(shape),
    )


def partial_cloud(
    scene: Scene, which: str, eye, rng: np.random.Generator, config: CameraConfig = CameraConfig()
) -> PointCloud:
    """The partial cloud of ``which`` ("object" in its own frame, "support" in the world
    frame) seen from ``eye``, resampled to ``config.n_points`` points with normals.

    Raises ``ValueError`` if the camera sees nothing of the body.
    """
    target = np.zeros(3)
    dist, normal, dirs, _ = render_depth(scene, which, eye, target, config)
    hit = dist.ravel() > 0
    n_visible = int(hit.sum())
    if n_visible == 0:
        raise ValueError(
            f"camera at {np.round(eye, 3).tolist()} sees nothing of the {which} of {scene.model.names[:40]!r}"
        )
    d = dist.ravel()[hit]
    if config.depth_noise > 0:
        d = d + rng.normal(scale=config.depth_noise, size=d.shape)
    pts = np.asarray(eye) + d[:, None] * dirs.reshape(-1, 3)[hit]
    nrm = normal.reshape(-1, 3)[hit]
    idx = rng.choice(n_visible, config.n_points, replace=n_visible < config.n_points)
    return PointCloud(
        pts[idx].astype(np.float32), nrm[idx].astype(np.float32), np.asarray(eye, float), n_visible
    )


def default_eyes(scene: Scene, rng: np.random.Generator, config: CameraConfig = CameraConfig()):
    """One camera position for the object (any side) and one for the support (front side)."""
    obj_eye = sample_eye(rng, np.zeros(3), np.linalg.norm(scene.obj.extents) / 2, config)
    sup_eye = sample_eye(
        rng,
        np.zeros(3),
        np.linalg.norm(scene.support.extents) / 2,
        config,
        front_only=scene.support.wall_y is not None,
    )
    return obj_eye, sup_eye


def sphere_directions(n: int) -> np.ndarray:
    """[n, 3] unit vectors spread evenly on the sphere (Fibonacci lattice), deterministic."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (1.0 + 5**0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def surface_cloud(
    scene: Scene,
    which: str,
    rng: np.random.Generator,
    config: CameraConfig = CameraConfig(),
    n_dirs: int = 42,
    n_points: int = 2048,
    voxel: float = 0.002,
) -> np.ndarray:
    """The body's whole visible-from-outside surface as ``n_points`` points (the frame of
    :func:`partial_cloud`): the union of its clouds from ``n_dirs`` cameras spread over the
    whole sphere (behind a support's wall too: the wall is never drawn), thinned to one point
    per ``voxel`` cell (so overlapping views do not weigh more), then sampled. The target of
    shape completion (``omnihang_jax.completion``)."""
    ext = scene.obj.extents if which == "object" else scene.support.extents
    radius = camera_distance(float(np.linalg.norm(ext)) / 2, config)
    pts = []
    for d in sphere_directions(n_dirs):
        dist, _, dirs, _ = render_depth(scene, which, radius * d, np.zeros(3), config)
        hit = dist.ravel() > 0
        pts.append(radius * d + dist.ravel()[hit, None] * dirs.reshape(-1, 3)[hit])
    pts = np.concatenate(pts)
    if len(pts) == 0:
        raise ValueError(f"no camera sees the {which} of {scene.model.names[:40]!r}")
    _, keep = np.unique(np.floor(pts / voxel).astype(np.int64), axis=0, return_index=True)
    pts = pts[keep]
    idx = rng.choice(len(pts), n_points, replace=len(pts) < n_points)
    return pts[idx].astype(np.float32)
