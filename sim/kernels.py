"""Physics kernels over a batch of object poses: contact query, stability, take-off.

One signature per kernel, ``kernel(scene, poses, config, backend=...) -> Result``: the scene
(host-side MjModel + ids, :mod:`sim.scene`), poses ``[B, 7]`` (position in metres, quaternion
``w, x, y, z``; the object frame in the support frame), a frozen config and a backend name.
``backend="cpu"`` runs MuJoCo C through the multithreaded ``mujoco.rollout`` and is the
reference; ``backend="mjx"`` (``sim.mjx_kernels``) implements the same signature on JAX.

Protocols (see docs/kernels.md for the reasons behind each threshold):

Stability (original: PyBullet, 200 steps of 1/100 s):
  1. reject a pose at once if any contact of the object penetrates deeper than 1 mm;
  2. simulate up to 2 s with gravity from rest, checking every 0.1 s;
  3. FALLEN if the object touches the ground (floor plane or a stand's base) at any step, or
     its bounding box stops overlapping the support's (it left the item);
     DIVERGED if the state is non-finite, flies beyond 5 m or moves faster than 50 m/s;
     settled early (STABLE) once linear speed < 1 cm/s and angular < 0.1 rad/s at two
     consecutive checks while touching the support; STABLE if still hanging at 2 s.
Take-off (original: 20 N for 40 steps of 1/100 s, boxes checked every 10 steps, 20 free steps):
  push with a constant 20 N along each of the 11 original directions for 0.4 s (boxes
  checked every 0.1 s), then 0.2 s free; removable if the object's bounding box separates
  from the support's at any check, for any direction.
"""

from __future__ import annotations

import collections
import copy
import dataclasses
import logging
import os
import threading
from typing import NamedTuple

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout
from scipy.spatial.transform import Rotation

from sim.scene import Scene

STABLE, FALLEN, PENETRATING, DIVERGED = 0, 1, 2, 3
STATUS_NAMES = ("stable", "fallen", "penetrating", "diverged")

# The original take-off directions, normalised; no straight-down direction.
TAKEOFF_DIRECTIONS = np.array(
    [
        (-1, -1, 1),
        (-1, 1, 1),
        (1, 0, 1),
        (0, 1, 1),
        (0, -1, 1),
        (-1, 0, 1),
        (0, 1, 0),
        (-1, 0, 0),
        (0, 0, 1),
        (0, -1, 0),
        (1, 0, 0),
    ],
    dtype=float,
)
TAKEOFF_DIRECTIONS /= np.linalg.norm(TAKEOFF_DIRECTIONS, axis=1, keepdims=True)


@dataclasses.dataclass(frozen=True)
class StabilityConfig:
    max_penetration: float = 0.001  # m; original drops candidates penetrating > 1 mm
    duration: float = 2.0  # s; original 200 steps x 1/100 s
    check_every: float = 0.1  # s between checks (early termination granularity)
    settle_speed: float = 0.01  # m/s; below this (and settle_spin) the object is at rest
    settle_spin: float = 0.1  # rad/s
    settle_checks: int = 2  # consecutive resting checks before stopping early
    escape_radius: float = 5.0  # m; original "flies away" threshold
    max_speed: float = 50.0  # m/s; faster means the integration blew up
    box_margin: float = 0.005  # m; bounding boxes closer than this still "overlap"


@dataclasses.dataclass(frozen=True)
class TakeoffConfig:
    force: float = 20.0  # N, original
    push_time: float = 0.4  # s, original 40 steps x 1/100 s
    free_time: float = 0.2  # s, original 20 free steps
    check_every: float = 0.1  # s, original every 10 steps
    frame: str = "support"  # "support" or "object": frame of the 11 directions (docs/kernels.md)
    mass: float | None = None  # kg; None keeps the scene's; datasets sample U(0.3, 0.8)
    friction: float | None = None  # None keeps the scene's; datasets sample U(0.1, 0.5)


@dataclasses.dataclass(frozen=True)
class ContactConfig:
    max_contacts: int = 32  # contacts kept per pose (deepest first)
    distance_cutoff: float = 0.02  # m; distances beyond this are reported as the cutoff


class StabilityResult(NamedTuple):
    stable: np.ndarray  # [B] bool
    status: np.ndarray  # [B] int8, one of STABLE, FALLEN, PENETRATING, DIVERGED
    settled_pose: np.ndarray  # [B, 7] final pose (initial pose where rejected/diverged)
    initial_penetration: np.ndarray  # [B] m, >= 0, deepest initial penetration
    sim_time: np.ndarray  # [B] s simulated before the label was final


class TakeoffResult(NamedTuple):
    removable: np.ndarray  # [B] bool
    direction: np.ndarray  # [B] int, first direction index that removed it, -1 if none
    removed: np.ndarray  # [B, 11] bool: removed by this direction (later ones not tried)


class ContactResult(NamedTuple):
    penetration: np.ndarray  # [B] m, deepest penetration (>= 0)
    distance: np.ndarray  # [B] m, signed object-support distance, clipped at the cutoff
    object_points: np.ndarray  # [B, C, 3] world frame, on the object's surface
    support_points: np.ndarray  # [B, C, 3] world frame, on the support (or wall) surface
    normals: np.ndarray  # [B, C, 3] unit, from the support towards the object
    mask: np.ndarray  # [B, C] bool, valid contacts


# ----------------------------------------------------------------------------- helpers


def check_poses(poses: np.ndarray) -> np.ndarray:
    """Validate ``poses`` [B, 7]; return a float64 copy with unit quaternions."""
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 2 or poses.shape[1] != 7:
        raise ValueError(f"poses must be [B, 7] (position, quaternion wxyz), got {poses.shape}")
    bad = ~np.isfinite(poses).all(axis=1)
    if bad.any():
        raise ValueError(f"poses contain NaN/inf at rows {np.flatnonzero(bad)[:10].tolist()}")
    norms = np.linalg.norm(poses[:, 3:], axis=1)
    if (norms < 1e-6).any():
        raise ValueError(f"zero quaternion at rows {np.flatnonzero(norms < 1e-6)[:10].tolist()}")
    poses = poses.copy()
    poses[:, 3:] /= norms[:, None]
    return poses


def _rotations(poses: np.ndarray) -> np.ndarray:
    return Rotation.from_quat(np.roll(poses[:, 3:7], -1, axis=1)).as_matrix()


def object_boxes(scene: Scene, poses: np.ndarray) -> np.ndarray:
    """[B, 2, 3] world AABBs (min, max) of the object at ``poses`` [B, 7]."""
    pts = np.einsum("bij,kj->bki", _rotations(poses), scene.object_hull_points) + poses[:, None, :3]
    return np.stack([pts.min(1), pts.max(1)], axis=1)


def boxes_overlap(boxes: np.ndarray, bounds: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """[B] bool: each AABB [B, 2, 3] overlaps ``bounds`` [2, 3] grown by ``margin``."""
    lo, hi = bounds[0] - margin, bounds[1] + margin
    return np.all((boxes[:, 0] <= hi) & (boxes[:, 1] >= lo), axis=1)


_STATE_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS

# MuJoCo prints a warning (and writes MUJOCO_LOG.TXT) whenever a world blows up and is
# reset. The kernels label such worlds DIVERGED themselves, so the warnings are counted
# here instead of flooding progress bars; ``MUJOCO_WARNINGS`` maps message -> count.
MUJOCO_WARNINGS: collections.Counter = collections.Counter()
_WARNING_LOCK = threading.Lock()
_log = logging.getLogger(__name__)


def _count_warning(message: str) -> None:
    key = message.split("Time =")[0].strip()
    with _WARNING_LOCK:
        MUJOCO_WARNINGS[key] += 1
    _log.debug("MuJoCo: %s", message)


def _install_warning_counter() -> None:
    if mujoco.get_mju_user_warning() is not _count_warning:
        mujoco.set_mju_user_warning(_count_warning)


# Threads per CPU rollout when the caller names none; None means one per available core.
# Process-parallel callers (dataset workers) set it to 1.
DEFAULT_NTHREAD: int | None = None


def _nthread(nthread: int | None) -> int:
    return (
        nthread
        or DEFAULT_NTHREAD
        or max(
            1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        )
    )


def _initial_states(scene: Scene, poses: np.ndarray) -> np.ndarray:
    """[B, nstate] full-physics states at rest at ``poses``."""
    model = scene.model
    data = mujoco.MjData(model)
    template = np.zeros(scene.nstate)
    mujoco.mj_getState(model, data, template, _STATE_SPEC)
    states = np.tile(template, (len(poses), 1))
    states[:, 1 : 1 + 7] = poses  # [time, qpos(7), qvel(6), ...]
    states[:, 8:14] = 0.0
    return states


def _run(model, states, nstep, nthread, control=None, control_spec=0):
    _install_warning_counter()
    n = _nthread(nthread)
    datas = [mujoco.MjData(model) for _ in range(min(n, len(states)))]
    with mj_rollout.Rollout(nthread=len(datas)) as pool:
        return pool.rollout(model, datas, states, control, control_spec=control_spec, nstep=nstep)


# ----------------------------------------------------------------------------- stability


def stability(
    scene: Scene,
    poses: np.ndarray,
    config: StabilityConfig = StabilityConfig(),
    backend: str = "cpu",
    **kw,
) -> StabilityResult:
    """Label each pose stable / fallen / penetrating / diverged (see module docstring)."""
    if backend == "mjx":
        from sim import mjx_kernels

        return mjx_kernels.stability(scene, poses, config, **kw)
    if backend != "cpu":
        raise ValueError(f"unknown backend {backend!r}; use 'cpu' or 'mjx'")
    return _stability_cpu(scene, poses, config, **kw)


def _stability_cpu(
    scene: Scene, poses, config: StabilityConfig, nthread: int | None = None
) -> StabilityResult:
    poses = check_poses(poses)
    model = scene.model
    n = len(poses)
    dt = model.opt.timestep
    status = np.full(n, -1, dtype=np.int8)
    final = poses.copy()
    sim_time = np.zeros(n)
    states = _initial_states(scene, poses)
    adr = scene.support_sensor

    # 1. initial penetration: sensors of the first step see the initial configuration.
    _, sens = _run(model, states, 1, nthread)
    found = sens[:, 0, adr] > 0
    depth = np.where(found, np.maximum(-sens[:, 0, adr + 1], 0.0), 0.0)
    status[depth > config.max_penetration] = PENETRATING

    # 2. simulate in segments, terminating worlds as soon as their label is final.
    seg = max(1, round(config.check_every / dt))
    nseg = max(1, round(config.duration / (seg * dt)))
    rest_count = np.zeros(n, dtype=int)
    active = np.flatnonzero(status < 0)
    for k in range(nseg):
        if len(active) == 0:
            break
        st, sens = _run(model, states[active], seg, nthread)
        last = st[:, -1]
        states[active] = last
        sim_time[active] = (k + 1) * seg * dt
        qpos, qvel = last[:, 1:8], last[:, 8:14]
        finite = np.isfinite(last).all(axis=1)
        pos_ok = finite & (
            np.linalg.norm(np.nan_to_num(qpos[:, :3], nan=1e9), axis=1) < config.escape_radius
        )
        speed = np.linalg.norm(np.nan_to_num(qvel[:, :3], nan=1e9), axis=1)
        spin = np.linalg.norm(np.nan_to_num(qvel[:, 3:], nan=1e9), axis=1)
        diverged = ~pos_ok | (speed > config.max_speed) | ~np.isfinite(sens).all(axis=(1, 2))
        ground = (sens[:, :, scene.ground_sensors] > 0).any(axis=(1, 2))
        safe_q = np.where(diverged[:, None], poses[active], qpos)
        overlap = boxes_overlap(
            object_boxes(scene, check_poses(safe_q)), scene.support_bounds, config.box_margin
        )
        touching = sens[:, -1, adr] > 0
        resting = (speed < config.settle_speed) & (spin < config.settle_spin) & touching
        rest_count[active] = np.where(resting, rest_count[active] + 1, 0)
        new = np.full(len(active), -1, dtype=np.int8)
        new[ground | ~overlap] = FALLEN
        new[diverged] = DIVERGED
        new[(new < 0) & (rest_count[active] >= config.settle_checks)] = STABLE
        done = new >= 0
        status[active[done]] = new[done]
        final[active] = np.where(diverged[:, None], poses[active], qpos)
        active = active[~done]
    status[active] = STABLE  # still hanging at the end of the check
    final[:, 3:] /= np.linalg.norm(final[:, 3:], axis=1, keepdims=True)
    return StabilityResult(status == STABLE, status, final, depth, sim_time)


# ----------------------------------------------------------------------------- take-off


def with_material(scene: Scene, mass: float | None, friction: float | None) -> mujoco.MjModel:
    """A copy of the scene model with the object's mass and every geom's friction replaced."""
    model = copy.copy(scene.model)
    if mass is not None:
        body = scene.object_body
        factor = mass / model.body_mass[body]
        model.body_mass[body] = mass
        model.body_inertia[body] *= factor
    if friction is not None:
        model.geom_friction[:, 0] = friction
    if mass is not None:
        # Constraint softness is scaled by each body's inverse weight (body_invweight0, set
        # by mj_setConst from the masses at compile time). Without recomputing it, a heavier
        # or lighter object keeps the 0.5 kg softness: contacts sank 15 mm and a pulled ring
        # passed through a closed towel bar (found by comparing with MuJoCo Warp).
        mujoco.mj_setConst(model, mujoco.MjData(model))
    return model


def takeoff(
    scene: Scene,
    poses: np.ndarray,
    config: TakeoffConfig = TakeoffConfig(),
    backend: str = "cpu",
    **kw,
) -> TakeoffResult:
    """Can the object be taken off from each pose by a constant pull (module docstring)?"""
    if backend == "mjx":
        from sim import mjx_kernels

        return mjx_kernels.takeoff(scene, poses, config, **kw)
    if backend != "cpu":
        raise ValueError(f"unknown backend {backend!r}; use 'cpu' or 'mjx'")
    return _takeoff_cpu(scene, poses, config, **kw)


def takeoff_forces(poses: np.ndarray, config: TakeoffConfig) -> np.ndarray:
    """[B, 11, 3] world-frame pull forces (N) for each pose and direction."""
    dirs = np.broadcast_to(TAKEOFF_DIRECTIONS, (len(poses), 11, 3))
    if config.frame == "object":
        dirs = np.einsum("bij,bkj->bki", _rotations(poses), dirs)
    elif config.frame != "support":
        raise ValueError(f"takeoff frame must be 'support' or 'object', got {config.frame!r}")
    return config.force * dirs


def _takeoff_cpu(
    scene: Scene, poses, config: TakeoffConfig, nthread: int | None = None, chunk: int = 512
):
    """Directions are tried in the original order; a pose removed by one direction is not
    pushed along the later ones (its remaining ``removed`` entries stay False)."""
    poses = check_poses(poses)
    model = with_material(scene, config.mass, config.friction)
    dt = model.opt.timestep
    push, free = round(config.push_time / dt), round(config.free_time / dt)
    every = max(1, round(config.check_every / dt))
    checks = np.arange(every - 1, push + free, every)
    if checks[-1] != push + free - 1:
        checks = np.append(checks, push + free - 1)
    forces = takeoff_forces(poses, config)
    removed = np.zeros((len(poses), 11), dtype=bool)
    spec = mujoco.mjtState.mjSTATE_XFRC_APPLIED
    body = scene.object_body
    for k in range(11):
        todo = np.flatnonzero(~removed.any(axis=1))
        for start in range(0, len(todo), chunk):
            idx = todo[start : start + chunk]
            states = _initial_states(scene, poses[idx])
            control = np.zeros((len(idx), push + free, model.nbody * 6))
            control[:, :push, 6 * body : 6 * body + 3] = forces[idx, k][:, None, :]
            st, _ = _run(model, states, push + free, nthread, control, spec)
            q = st[:, checks, 1:8].reshape(-1, 7)
            finite = np.isfinite(q).all(axis=1) & (
                np.linalg.norm(np.nan_to_num(q[:, :3]), axis=1) < 1e3
            )
            q = np.where(
                finite[:, None], q, np.array([0, 0, 1e3, 1, 0, 0, 0.0])
            )  # diverged: far away
            sep = ~boxes_overlap(object_boxes(scene, check_poses(q)), scene.support_bounds)
            removed[idx, k] = sep.reshape(len(idx), len(checks)).any(axis=1)
    first = np.where(removed.any(1), removed.argmax(1), -1)
    return TakeoffResult(removed.any(1), first, removed)


# ----------------------------------------------------------------------------- contact query


def contact_query(
    scene: Scene, poses: np.ndarray, config: ContactConfig = ContactConfig(), backend: str = "cpu"
) -> ContactResult:
    """Deepest penetration, object-support distance and contact points at each pose."""
    if backend == "mjx":
        from sim import mjx_kernels

        return mjx_kernels.contact_query(scene, poses, config)
    if backend != "cpu":
        raise ValueError(f"unknown backend {backend!r}; use 'cpu' or 'mjx'")
    poses = check_poses(poses)
    model = scene.model
    data = mujoco.MjData(model)
    b, c = len(poses), config.max_contacts
    pen = np.zeros(b)
    dist = np.full(b, config.distance_cutoff)
    opts = np.zeros((b, c, 3))
    spts = np.zeros((b, c, 3))
    nrm = np.zeros((b, c, 3))
    mask = np.zeros((b, c), dtype=bool)
    obj = set(scene.object_geoms.tolist())
    others = [*scene.support_geoms.tolist()] + ([scene.wall_geom] if scene.wall_geom >= 0 else [])
    for i, pose in enumerate(poses):
        data.qpos[:7] = pose
        data.qvel[:] = 0
        mujoco.mj_forward(model, data)
        rows = []
        for con in data.contact[: data.ncon]:
            g1, g2 = int(con.geom1), int(con.geom2)
            if (g1 in obj) == (g2 in obj):
                continue
            n = np.array(con.frame[:3])  # from geom1 towards geom2
            p1 = con.pos - 0.5 * con.dist * n
            p2 = con.pos + 0.5 * con.dist * n
            if g1 in obj:  # normal must point from the support towards the object
                rows.append((con.dist, p1, p2, -n))
            else:
                rows.append((con.dist, p2, p1, n))
        rows.sort(key=lambda r: r[0])
        for j, (_d, po, ps, nn) in enumerate(rows[:c]):
            opts[i, j], spts[i, j], nrm[i, j], mask[i, j] = po, ps, nn, True
        if rows:
            pen[i] = max(0.0, -rows[0][0])
        if rows and rows[0][0] < 0:  # penetrating: the signed distance is the deepest contact
            dist[i] = rows[0][0]
            continue
        best = config.distance_cutoff
        for go in scene.object_geoms:
            for gs in others:
                best = min(
                    best,
                    mujoco.mj_geomDistance(
                        model, data, int(go), int(gs), config.distance_cutoff, None
                    ),
                )
        dist[i] = best
    return ContactResult(pen, dist, opts, spts, nrm, mask)
