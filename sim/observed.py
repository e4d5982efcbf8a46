"""Stability on the OBSERVED geometry: the partial clouds as spheres, simulated by the kernels.

The evaluation simulates the true meshes; the pipeline sees only two partial clouds. This
module builds a MuJoCo scene from those clouds alone, so a candidate pose can be dropped in
physics before it is answered (``first_staying``; ``experiments.observed_check`` reads it on an
evaluation's records, ``omnihang_jax.hang`` runs it on clouds-only inputs):

- every observed surface point ``p`` with outward normal ``n`` becomes a sphere of radius
  ``r`` centred at ``p - r n`` (the sphere's outer side touches the observed surface);
- only the points where the two clouds can meet are kept: support points within ``crop`` of
  the posed object cloud and object points within ``crop`` of the support cloud, thinned to
  one per ``voxel`` cube (a hanging object moves millimetres; one that slides farther falls);
- the object's mass (``PhysicsConfig.object_mass``) and inertia come from ALL its observed
  points, thinned to one per voxel (the visible surface, area-weighted), through an explicit
  ``<inertial>``; the collision spheres carry no mass of their own;
- the floor is the support's floor plane and the wall its wall (an observer sees both);
  support points within ``ground_band`` of the floor form a separate static body whose
  contact counts as ground, like a stand's base in :mod:`sim.scene`.

The result is a :class:`sim.scene.Scene`, so :func:`sim.kernels.stability` runs it with the
dataset's protocol by default (``StabilityConfig``: penetration > 1 mm at the start fails, 2 s,
the same settle checks). A point the view hid is not there: an object resting on the hidden side
of a hook falls through it here. What depends only on the clouds (their checks, the support's
search tree, the object's mass) is prepared once per pair (:func:`prepare`), the crop per pose.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import NamedTuple

import mujoco
import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from sim.scene import (
    ENV_GROUP,
    OBJECT_GROUP,
    SUPPORT_GROUP,
    PhysicsConfig,
    Scene,
    _fmt,
    wall_geom_xml,
)

_log = logging.getLogger(__name__)

# The answer check's reach: the first of the rule's best ANSWER_TOP candidates that stays on the
# observed clouds. 60 is the default pipeline's whole pool (three views x 2K, K = 10); chosen on
# the validation records over 2-60 (first of 60: 87.93 over three keys, first of 8: 87.23). Most
# pairs stop at the first or second candidate; the ~13 % where none of the best 10 stays try all.
ANSWER_TOP = 60


@dataclasses.dataclass(frozen=True)
class ObservedConfig:
    # m, sphere radius: 4 mm chosen on the validation records over 1.5-5 mm (docs/stage3.md);
    # larger spheres close the gaps between observed points
    radius: float = 0.004
    voxel: float = 0.002  # m, one collision sphere per cube of this side
    crop: float = 0.03  # m, keep points within this of the other posed cloud
    max_spheres: int = 2000  # per body, after thinning (a uniform subsample beyond it)
    ground_band: float = 0.02  # m, support points this close to the floor count as ground
    memory_mb: int = 64  # MuJoCo arena: a deep overlap of two sphere clouds makes ~10k contacts
    physics: PhysicsConfig = PhysicsConfig()


def unknown_environment(support_points) -> tuple[float, None]:
    """(floor_z, wall_y) for a clouds-only input, where neither is known: no wall, and the floor
    1 m below the support cloud's lowest point, so a fall is the object leaving the support."""
    return float(np.nanmin(np.asarray(support_points, float)[:, 2])) - 1.0, None


def voxel_thin(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of one point per occupied ``voxel`` cube (the first in input order)."""
    points = np.asarray(points, float)
    if len(points) == 0:
        return np.zeros(0, int)
    cells = np.floor(points / voxel).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return np.sort(first)


def _check_cloud(name: str, points, normals) -> tuple[np.ndarray, np.ndarray]:
    points, normals = np.asarray(points, float), np.asarray(normals, float)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(
            f"{name}: points {points.shape} and normals {normals.shape} must be [N, 3]"
        )
    ok = np.isfinite(points).all(1) & np.isfinite(normals).all(1)
    if not ok.any():
        raise ValueError(f"{name}: no finite point")
    points, normals = points[ok], normals[ok]
    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    return points, normals / np.maximum(norm, 1e-9)


def _cap(idx: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    if len(idx) <= n:
        return idx
    return np.sort(np.random.default_rng(seed).choice(idx, n, replace=False))


def _inertia(points: np.ndarray, mass: float) -> tuple[np.ndarray, np.ndarray]:
    """(centre of mass [3], full inertia [6]: xx yy zz xy xz yz) of ``mass`` spread evenly
    over ``points``, with a floor so a flat patch still has a valid tensor."""
    com = points.mean(0)
    d = points - com
    cov = d.T @ d / len(points)
    inertia = mass * (np.trace(cov) * np.eye(3) - cov)
    inertia += np.eye(3) * mass * 1e-6  # (1 mm)^2 x m: keeps the tensor positive definite
    return com, np.array([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1],
                          inertia[0, 2], inertia[1, 2]])  # fmt: skip


class Prepared(NamedTuple):
    """What :func:`observed_scene` needs of a pair's clouds, whatever the pose."""

    op: np.ndarray  # [N, 3] finite object points (object frame) and unit normals
    on: np.ndarray
    sp: np.ndarray  # [M, 3] finite support points (support frame) and unit normals
    sn: np.ndarray
    support_tree: cKDTree
    whole: np.ndarray  # the object points thinned to one per voxel: mass and bounding hull
    com: np.ndarray
    inertia: np.ndarray


def prepare(clouds: dict, config: ObservedConfig = ObservedConfig()) -> Prepared:
    """Check a pair's clouds (``object_points``/``object_normals`` in the object frame,
    ``support_*`` in the support frame) and compute what does not depend on the pose. Raises
    ``ValueError`` on malformed clouds."""
    op, on = _check_cloud("object cloud", clouds["object_points"], clouds["object_normals"])
    sp, sn = _check_cloud("support cloud", clouds["support_points"], clouds["support_normals"])
    whole = op[voxel_thin(op, config.voxel)]
    com, inertia = _inertia(whole, config.physics.object_mass)
    return Prepared(op, on, sp, sn, cKDTree(sp), whole, com, inertia)


def observed_scene(
    object_points,
    object_normals,
    support_points,
    support_normals,
    pose,
    floor_z: float,
    wall_y: float | None,
    config: ObservedConfig = ObservedConfig(),
) -> Scene:
    """A scene of the observed clouds (object frame / support frame), cropped around ``pose``
    [7] (object frame -> support frame, wxyz). Raises ``ValueError`` on malformed clouds."""
    clouds = dict(object_points=object_points, object_normals=object_normals,
                  support_points=support_points, support_normals=support_normals)  # fmt: skip
    return _scene(prepare(clouds, config), pose, floor_z, wall_y, config)


def _scene(
    prep: Prepared, pose, floor_z: float, wall_y: float | None, config: ObservedConfig
) -> Scene:
    op, on, sp, sn = prep.op, prep.on, prep.sp, prep.sn
    pose = np.asarray(pose, float)
    if pose.shape != (7,) or not np.isfinite(pose).all():
        raise ValueError(f"pose must be 7 finite numbers, got {pose}")
    r, phys = config.radius, config.physics
    rot = Rotation.from_quat(np.roll(pose[3:] / np.linalg.norm(pose[3:]), -1)).as_matrix()
    posed = op @ rot.T + pose[:3]
    near_s = cKDTree(posed).query(sp, k=1, distance_upper_bound=config.crop)[0] < np.inf
    near_o = prep.support_tree.query(posed, k=1, distance_upper_bound=config.crop)[0] < np.inf
    s_idx = np.flatnonzero(near_s)
    s_idx = _cap(s_idx[voxel_thin(sp[s_idx], config.voxel)], config.max_spheres)
    o_idx = np.flatnonzero(near_o)
    o_idx = _cap(o_idx[voxel_thin(op[o_idx], config.voxel)], config.max_spheres)
    whole, com, inertia = prep.whole, prep.com, prep.inertia
    s_centres, o_centres = sp[s_idx] - r * sn[s_idx], op[o_idx] - r * on[o_idx]
    ground = s_centres[:, 2] < floor_z + config.ground_band
    sphere = f'type="sphere" size="{r:.7g}"'

    def spheres(centres, group, tag):
        return "\n      ".join(
            f'<geom name="{tag}{i}" {sphere} pos="{_fmt(c)}" group="{group}" mass="0"/>'
            for i, c in enumerate(centres)
        )

    env = [
        f'<geom name="floor" type="plane" pos="0 0 {floor_z:.7g}" size="0 0 1" group="{ENV_GROUP}"/>'
    ]
    if wall_y is not None:
        env.append(wall_geom_xml(wall_y, phys, f'group="{ENV_GROUP}"'))
    sensors = ['<contact name="ground_0" geom1="floor" body2="object" num="1" data="found"/>']
    if ground.any():
        sensors.append(
            '<contact name="ground_1" body1="support_base" body2="object" num="1" data="found"/>'
        )
    sensors.append(
        '<contact name="support_touch" body1="object" subtree2="world" num="1" '
        'data="found dist" reduce="mindist"/>'
    )
    base = (
        f'<body name="support_base">\n      {spheres(s_centres[ground], SUPPORT_GROUP, "base_")}\n    </body>'
        if ground.any()
        else ""
    )
    # An object with no sphere near the support still needs a body that can fall.
    o_geoms = (
        spheres(o_centres, OBJECT_GROUP, "object_")
        if len(o_centres)
        else (f'<geom name="object_0" {sphere} pos="{_fmt(com)}" group="{OBJECT_GROUP}" mass="0"/>')
    )
    xml = f"""<mujoco model="observed">
  <compiler angle="radian" autolimits="true" inertiafromgeom="false"/>
  <size memory="{config.memory_mb}M"/>
  <option timestep="{phys.timestep}" integrator="implicitfast" solver="Newton" cone="elliptic"
          iterations="{phys.iterations}" ls_iterations="{phys.ls_iterations}"
          gravity="0 0 {phys.gravity}"/>
  <default>
    <geom condim="4" solref="{phys.contact_timeconst} 1" friction="{phys.friction} 0.005 0.0001"/>
  </default>
  <worldbody>
    {chr(10).join("    " + e for e in env).strip()}
    <body name="support">
      {spheres(s_centres[~ground], SUPPORT_GROUP, "support_")}
    </body>
    {base}
    <body name="object" pos="0 0 50">
      <freejoint name="object"/>
      <inertial pos="{_fmt(com)}" mass="{phys.object_mass:.7g}" fullinertia="{_fmt(inertia)}"/>
      {o_geoms}
    </body>
  </worldbody>
  <sensor>
    {chr(10).join("    " + s for s in sensors).strip()}
  </sensor>
</mujoco>
"""
    model = mujoco.MjModel.from_xml_string(xml)
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")
    support_geoms = np.flatnonzero(model.geom_bodyid != body)
    n_ground = len(sensors) - 1
    return Scene(
        obj=None,
        support=None,
        physics=phys,
        xml=xml,
        model=model,
        object_body=body,
        object_geoms=np.flatnonzero(model.geom_bodyid == body),
        support_geoms=support_geoms,
        ground_geoms=np.zeros(0, int),
        wall_geom=-1
        if wall_y is None
        else mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "wall"),
        object_hull_points=whole,
        support_bounds=np.stack([sp.min(0), sp.max(0)]),
        ground_sensors=np.asarray(model.sensor_adr[:n_ground]),
        support_sensor=int(model.sensor_adr[n_ground]),
    )


def _status(
    prep: Prepared,
    pose: np.ndarray,
    floor_z: float,
    wall_y: float | None,
    config: ObservedConfig,
    stability,
    nthread: int,
) -> int:
    """The status of one checked pose [7] on prepared clouds; an arena overflow is DIVERGED."""
    from sim import kernels

    scene = _scene(prep, pose, floor_z, wall_y, config)
    try:
        return int(kernels.stability(scene, pose[None], stability, nthread=nthread).status[0])
    except mujoco.FatalError as err:  # arena overflow: the clouds overlap deeply
        _log.warning("observed check of a pose failed in MuJoCo (%s); labelled diverged",
                     str(err).splitlines()[0])  # fmt: skip
        return kernels.DIVERGED


def observed_stability(clouds: dict, poses, floor_z: float, wall_y: float | None,
                       config: ObservedConfig = ObservedConfig(), stability=None,
                       nthread: int = 1):  # fmt: skip
    """[P] status (``sim.kernels`` codes) of each pose [P, 7] on the observed clouds
    (``object_points``/``object_normals`` in the object frame, ``support_*`` in the support
    frame): one cropped scene per pose, ``stability`` (default: the dataset's protocol) on each."""
    from sim import kernels

    stability = stability or kernels.StabilityConfig()
    poses = kernels.check_poses(poses)
    prep = prepare(clouds, config)
    return np.array([_status(prep, q, floor_z, wall_y, config, stability, nthread)
                     for q in poses], np.int8)  # fmt: skip


def first_staying(clouds: dict, poses, floor_z: float, wall_y: float | None, top: int = ANSWER_TOP,
                  config: ObservedConfig = ObservedConfig(), stability=None,
                  nthread: int = 1) -> tuple[int, np.ndarray]:  # fmt: skip
    """The answer check: ``poses`` [C, 7] in ranking order (best first) are dropped on the
    observed clouds one at a time; -> (index of the first of the best ``top`` that stays, or
    0 when none does; [C] int8 statuses, -2 where not simulated). The same answer as
    simulating all ``top`` and taking the first that stays, at the cost of the ones tried."""
    from sim import kernels

    stability = stability or kernels.StabilityConfig()
    poses = kernels.check_poses(poses)
    prep = prepare(clouds, config)
    status = np.full(len(poses), -2, np.int8)
    for i in range(min(top, len(poses))):
        status[i] = _status(prep, poses[i], floor_z, wall_y, config, stability, nthread)
        if status[i] == kernels.STABLE:
            return i, status
    return 0, status
