"""PyBullet, the original paper's engine, as a second judge of :mod:`sim.kernels`' protocols.

One world per pair (:class:`PairWorld`): the supporting item (static, with its wall slab
and the floor plane; a stand's base parts count as ground), and the object as one rigid
body built from the project's own convex parts (capsules -> ``GEOM_CAPSULE``, boxes ->
``GEOM_BOX``, hulls -> ``GEOM_MESH`` of a triangulated hull OBJ) or, optionally, from a
V-HACD decomposition of the watertight mesh (``shapes="vhacd"``, as the original did).
Mass, centre of mass and principal inertia are MuJoCo's (``scene.model``): the shapes
are placed in the body's principal inertial frame, so Bullet's base frame *is* that frame.

Settings (:class:`BulletConfig`) and why; every figure behind them is in docs/judges.md:

- ``time_step = 1/100 s``, ``sub_steps = 40``, ``solver_iterations = 40``: the original's
  ``setPhysicsEngineParameter`` (0.25 ms effective step).
- ``friction = 0.5`` is the *combined* (effective) Coulomb coefficient of an
  object-support contact, the one MuJoCo uses (MuJoCo combines a pair by maximum, so 0.5
  on every geom gives 0.5). Bullet multiplies the two bodies' lateral frictions: the
  original left both at PyBullet's default 0.5, an effective **0.25** (measured here: a
  box slides down a 15 degree incline, tan = 0.27, with 0.5/0.5 but not with 0.5/1.0).
  ``friction_combine="matched"`` gives the object ``friction`` and the environment 1.0, so
  the product is ``friction``; ``"original"`` gives both ``friction`` (product 0.25).
- ``hulls = "exact"``: Bullet grows every convex hull by its collision margin (PyBullet's
  URDF hulls: 1 mm; boxes and capsules keep theirs inside the shape), so a pose resting in
  MuJoCo starts 1 mm (hull on rod) to 2 mm (hull on hull) deep, above the 1 mm rejection
  threshold. ``changeDynamics(collisionMargin=...)`` does not reach the children of a
  compound, so instead each hull is written eroded by the margin (its faces moved 1 mm
  inwards): hull + margin is then the part again, exact on faces and rounded by 1 mm at
  edges and corners. Hulls thinner than 2 mm (137 of the library's 1,953) are eroded by
  90 % of their inradius and stay up to 1 mm too large. ``"inflated"`` keeps Bullet's.
- ``spinning_friction = 0.005 m``: MuJoCo's torsional coefficient (``condim 4``). Bullet
  combines it as ``spin_a * lateral_b + lateral_a * spin_b``, so with the environment's
  lateral 1.0 and spin 0 the combined torsional coefficient is the object's value.
- ``damping = 0``: PyBullet damps a base's velocities by 0.04 per second by default;
  MuJoCo's scene has none. ``None`` keeps Bullet's.
- ``inertia = "mujoco"``: MuJoCo's principal moments; ``"bullet"`` keeps the inertia that
  PyBullet computes for a compound (the box inertia of its bounding box).
- ``touch_distance = 1 mm``: Bullet keeps contact points in its manifolds up to 2 cm
  apart; a body "touches" another (ground contact, resting on the support) only through
  a point closer than this.

:data:`ORIGINAL` reproduces the original set-up (Bullet's margins, product friction 0.25,
no spinning friction, default damping and compound inertia); :data:`MATCHED` (the default)
is the same physical model as the MuJoCo scene. The protocol is :mod:`sim.kernels`' (1 mm
penetration reject, 2 s in 0.1 s checks, ground contact / box separation = fallen,
divergence, early rest), one world and one pose at a time on one core.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import os
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pybullet as pb
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError
from scipy.spatial.transform import Rotation

from sim import kernels
from sim.assets.base import Asset
from sim.geometry import Box, Capsule, ConvexMesh
from sim.kernels import DIVERGED, FALLEN, PENETRATING, STABLE, StabilityConfig, StabilityResult
from sim.scene import Scene

TIME_STEP = 1.0 / 100.0  # original
SUB_STEPS = 40  # original
SOLVER_ITERATIONS = 40  # original
BULLET_HULL_MARGIN = 0.001  # m, PyBullet's collision margin of a URDF mesh hull (measured)


@dataclasses.dataclass(frozen=True)
class BulletConfig:
    time_step: float = TIME_STEP  # s, original
    sub_steps: int = SUB_STEPS  # original
    solver_iterations: int = SOLVER_ITERATIONS  # original
    friction: float = 0.5  # combined Coulomb coefficient of a contact (MuJoCo's 0.5)
    friction_combine: str = "matched"  # "matched": object f, environment 1; "original": both f
    spinning_friction: float = 0.005  # m, combined torsional coefficient (MuJoCo condim 4)
    hulls: str = "exact"  # "exact": hulls eroded by Bullet's margin; "inflated": Bullet's default
    damping: float | None = 0.0  # 1/s linear and angular; None keeps PyBullet's 0.04
    inertia: str = "mujoco"  # "mujoco": MuJoCo's principal inertia; "bullet": Bullet's own
    shapes: str = "parts"  # "parts": the project's convex parts; "vhacd": V-HACD of the mesh
    touch_distance: float = 0.001  # m, a contact point closer than this is a touch
    # keep only the first N object parts: 16 reproduces the previous reference, whose
    # createCollisionShapeArray silently dropped every part after the 16th (docs/judges.md)
    max_parts: int | None = None


MATCHED = BulletConfig()
ORIGINAL = BulletConfig(
    friction_combine="original",
    spinning_friction=0.0,
    hulls="inflated",
    damping=None,
    inertia="bullet",
)


# the previous reference (before this judge): original settings and the 16-part cap
LEGACY = dataclasses.replace(ORIGINAL, max_parts=16)


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


def erode_hull(vertices, depth: float, max_error: float = 0.001) -> np.ndarray:
    """[K, 3] vertices of the convex hull of ``vertices`` with every face moved inwards by
    the largest of ``depth`` x (1, 3/4, 1/2, 1/4, 0) (m) that keeps every original vertex
    within ``depth + max_error`` of the eroded hull (bounded by its nearest eroded vertex):
    Bullet adds ``depth`` back as a sphere, so faces are exact and no point of the part
    is more than ``max_error`` outside the result. A sharp tip retracts by
    ``d / sin(half angle)`` when its faces move by ``d``: a knife's blade tip would lose
    centimetres at the full depth, so such hulls are eroded less (and stay up to
    ``depth - d`` too large). Never more than 90 % of the inradius (thin plates)."""
    pts = np.unique(np.round(np.asarray(vertices, float), 12), axis=0)
    try:
        hull = ConvexHull(pts)
    except QhullError:  # flat: nothing to erode
        return pts
    a, b = hull.equations[:, :3], hull.equations[:, 3]
    norm = np.linalg.norm(a, axis=1)
    # Chebyshev centre: the deepest interior point, max r with a x + r |a| <= -b
    bounds = [(None, None)] * 3 + [(0, None)]
    lp = linprog([0, 0, 0, -1], A_ub=np.c_[a, norm], b_ub=-b, bounds=bounds)
    if not lp.success or lp.x[3] <= 0:
        return pts
    centre, inradius = lp.x[:3], lp.x[3]
    for k in (1.0, 0.75, 0.5, 0.25):
        d = min(k * depth, 0.9 * inradius)
        cut = HalfspaceIntersection(np.c_[a, b + d * norm], centre)
        eroded = np.unique(np.round(cut.intersections, 12), axis=0)
        gap = np.linalg.norm(pts[:, None] - eroded[None], axis=-1).min(1).max()
        if gap - d <= max_error:
            return eroded
    return pts


def _fmt(v) -> str:
    return " ".join(f"{float(x):.9g}" for x in np.ravel(v))


def write_urdf(
    path: str,
    parts,
    mass: float = 0.0,
    inertia=(0.0, 0.0, 0.0),
    origin: np.ndarray | None = None,
    frame: np.ndarray | None = None,
    tag: str = "part",
    hull_erosion: float = 0.0,
) -> str:
    """Write ``parts`` as a one-link URDF (one ``<collision>`` per part) with the parts
    expressed in the frame (``origin`` [3], rotation ``frame`` [3, 3]) of their current
    coordinates (a point ``x`` becomes ``frame.T @ (x - origin)``); hull meshes go beside it
    as triangulated OBJ files, eroded by ``hull_erosion`` (m, see :func:`erode_hull`). The
    link's inertial frame is its own frame: ``mass`` (kg) and principal moments
    ``inertia`` [3] (kg m^2) there.

    Why URDF and not ``createCollisionShapeArray``: PyBullet's shape arrays hold at most
    16 children (``MAX_COMPOUND_COLLISION_SHAPES``) and silently drop the rest, so a
    30-part racquet kept 16 of its parts (found comparing contact distances with MuJoCo);
    the URDF importer builds compounds of any size, as the original's URDFs did.
    """
    origin = np.zeros(3) if origin is None else np.asarray(origin, float)
    frame = np.eye(3) if frame is None else np.asarray(frame, float)

    def local(x):
        return (np.asarray(x, float) - origin) @ frame

    folder = os.path.dirname(path)
    rows = []
    for i, part in enumerate(parts):
        if isinstance(part, Capsule):
            p0, p1 = local(part.p0), local(part.p1)
            axis = p1 - p0
            length = float(np.linalg.norm(axis))
            z = axis / max(length, 1e-12)
            rot = Rotation.align_vectors([z], [[0, 0, 1.0]])[0]
            pos, geom = (
                0.5 * (p0 + p1),
                f'<capsule radius="{part.radius:.9g}" length="{length:.9g}"/>',
            )
        elif isinstance(part, Box):
            rot = Rotation.from_matrix(frame.T @ part.rotation)
            pos, geom = local(part.center), f'<box size="{_fmt(2 * np.asarray(part.half_size))}"/>'
        elif isinstance(part, ConvexMesh):
            name = f"{tag}{i}.obj"
            verts = local(part.vertices)
            if hull_erosion > 0:
                verts = erode_hull(verts, hull_erosion)
            _write_hull_obj(os.path.join(folder, name), verts)
            rot, pos, geom = Rotation.identity(), np.zeros(3), f'<mesh filename="{name}"/>'
        else:
            raise TypeError(type(part))
        with warnings.catch_warnings():  # gimbal lock: still the same rotation
            warnings.simplefilter("ignore", UserWarning)
            rpy = rot.as_euler("xyz")  # URDF rpy: fixed-axis roll, pitch, yaw
        rows.append(
            f'  <collision><origin xyz="{_fmt(pos)}" rpy="{_fmt(rpy)}"/>'
            f"<geometry>{geom}</geometry></collision>"
        )
    ixx, iyy, izz = map(float, inertia)
    text = (
        f'<?xml version="1.0"?>\n<robot name="{tag}">\n<link name="base">\n'
        f'  <inertial><origin xyz="0 0 0" rpy="0 0 0"/><mass value="{mass:.9g}"/>'
        f'<inertia ixx="{ixx:.9g}" ixy="0" ixz="0" iyy="{iyy:.9g}" iyz="0" izz="{izz:.9g}"/>'
        "</inertial>\n" + "\n".join(rows) + "\n</link>\n</robot>\n"
    )
    with open(path, "w") as f:
        f.write(text)
    return path


# ----------------------------------------------------------------------------- V-HACD


def vhacd_cache_dir() -> Path:
    """``$OMNIHANG_CACHE/vhacd`` if that variable is set, else ``~/.cache/omnihang_jax/vhacd``."""
    root = os.environ.get("OMNIHANG_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "omnihang_jax") / "vhacd"


def vhacd_parts(asset: Asset, resolution: int = 100_000, cache_dir=None) -> list[ConvexMesh]:
    """The watertight mesh of ``asset`` decomposed by PyBullet's V-HACD (the original's
    decomposition), as convex parts in the asset's frame; cached on disk by mesh and
    settings (one OBJ per asset, V-HACD's own output)."""
    mesh = asset.mesh
    h = hashlib.sha256(b"vhacd-1")
    h.update(np.ascontiguousarray(mesh.vertices, np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, np.int64).tobytes())
    h.update(str(resolution).encode())
    directory = Path(cache_dir) if cache_dir is not None else vhacd_cache_dir()
    out = directory / f"{h.hexdigest()}.obj"
    if not out.exists():
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory() as tmp:
            src = os.path.join(tmp, "in.obj")
            mesh.export(src)
            dst = os.path.join(tmp, "out.obj")
            with _quiet_stdout():  # V-HACD prints its progress bars from C
                pb.vhacd(src, dst, os.path.join(tmp, "log.txt"), resolution=resolution)
            if not os.path.exists(dst):
                raise RuntimeError(f"V-HACD wrote no output for {asset.name}")
            shutil.move(dst, out)  # the temporary folder may be on another file system
    return _read_obj_groups(out)


@contextlib.contextmanager
def _quiet_stdout():
    """Silence file descriptor 1 (C-level prints) for the duration."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _read_obj_groups(path: Path) -> list[ConvexMesh]:
    """Convex parts of a multi-object OBJ (``o`` starts a part, vertices indexed globally)."""
    verts: list[list[float]] = []
    groups: list[set[int]] = []
    for line in Path(path).read_text().splitlines():
        if line.startswith("o ") or (line.startswith("f ") and not groups):
            groups.append(set())
        if line.startswith("v "):
            verts.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            groups[-1].update(int(tok.split("/")[0]) - 1 for tok in line.split()[1:])
    v = np.asarray(verts)
    parts = [ConvexMesh(v[sorted(g)]) for g in groups if len(g) >= 4]
    if not parts:
        raise ValueError(f"no convex parts in {path}")
    return parts


# ----------------------------------------------------------------------------- the world


def set_materials(client: int, body: int, env: list[int], config: BulletConfig) -> None:
    """Friction and damping of the object ``body`` and its static ``env`` bodies (module
    docstring): the combined Coulomb coefficient is ``config.friction`` (Bullet multiplies
    the two lateral frictions) and the combined torsional one ``spinning_friction``."""
    f_env = 1.0 if config.friction_combine == "matched" else config.friction
    pb.changeDynamics(
        body,
        -1,
        lateralFriction=config.friction,
        spinningFriction=config.spinning_friction,
        physicsClientId=client,
    )
    for e in env:
        pb.changeDynamics(
            e, -1, lateralFriction=f_env, spinningFriction=0.0, physicsClientId=client
        )
    if config.damping is not None:
        pb.changeDynamics(
            body,
            -1,
            linearDamping=config.damping,
            angularDamping=config.damping,
            physicsClientId=client,
        )


class PairWorld:
    """One PyBullet world holding a pair: support (+ wall, floor, stand base) and the object.

    ``body`` is the object; ``support`` the supporting item with its wall; ``ground`` the
    floor plane and a stand's base. Poses in and out are the object frame in the support
    frame (``[7]``, quaternion wxyz), as everywhere in the project.
    """

    def __init__(self, scene: Scene, config: BulletConfig = MATCHED, mass: float | None = None):
        if config.friction_combine not in ("matched", "original"):
            raise ValueError(
                f"friction_combine must be 'matched' or 'original', got {config.friction_combine!r}"
            )
        if config.inertia not in ("mujoco", "bullet"):
            raise ValueError(f"inertia must be 'mujoco' or 'bullet', got {config.inertia!r}")
        if config.hulls not in ("exact", "inflated"):
            raise ValueError(f"hulls must be 'exact' or 'inflated', got {config.hulls!r}")
        if config.shapes not in ("parts", "vhacd"):
            raise ValueError(f"shapes must be 'parts' or 'vhacd', got {config.shapes!r}")
        self.scene, self.config = scene, config
        obj, support = scene.obj, scene.support
        self.client = pb.connect(pb.DIRECT)
        c = self.client
        pb.setGravity(0, 0, scene.physics.gravity, physicsClientId=c)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=config.time_step,
            numSubSteps=config.sub_steps,
            numSolverIterations=config.solver_iterations,
            physicsClientId=c,
        )
        self._tmp = tempfile.TemporaryDirectory()
        self._erosion = BULLET_HULL_MARGIN if config.hulls == "exact" else 0.0
        ground = set(support.ground_parts)
        hold = [p for i, p in enumerate(support.parts) if i not in ground]
        base = [p for i, p in enumerate(support.parts) if i in ground]
        if scene.wall_geom >= 0:  # the wall box exactly as the MuJoCo model has it
            w = scene.wall_geom
            hold.append(
                Box(
                    np.array(scene.model.geom_pos[w], float),
                    np.eye(3),
                    np.array(scene.model.geom_size[w], float),
                )
            )
        self.support = self._static(hold, "s")
        floor = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=c)
        self.ground = [
            pb.createMultiBody(0, floor, basePosition=[0, 0, support.floor_z], physicsClientId=c)
        ]
        if base:
            self.ground.append(self._static(base, "g"))

        # The object in MuJoCo's principal inertial frame (body_ipos, body_iquat).
        model, b = scene.model, scene.object_body
        self.com = np.array(model.body_ipos[b], float)
        self.inertial_rot = Rotation.from_quat(np.roll(model.body_iquat[b], -1))
        parts = vhacd_parts(obj) if config.shapes == "vhacd" else obj.parts
        parts = parts[: config.max_parts]
        m = float(model.body_mass[b]) if mass is None else mass
        inertia = np.array(model.body_inertia[b], float) * (m / float(model.body_mass[b]))
        urdf = write_urdf(
            os.path.join(self._tmp.name, "object.urdf"),
            parts,
            m,
            inertia,
            self.com,
            self.inertial_rot.as_matrix(),
            "object",
            self._erosion,
        )
        flags = pb.URDF_USE_INERTIA_FROM_FILE if config.inertia == "mujoco" else 0
        self.body = pb.loadURDF(urdf, [0, 0, 50], flags=flags, physicsClientId=c)
        n_shapes = len(pb.getCollisionShapeData(self.body, -1, physicsClientId=c))
        if n_shapes != len(parts):
            raise RuntimeError(
                f"PyBullet loaded {n_shapes} of the {len(parts)} parts of {obj.name}"
            )
        set_materials(c, self.body, [self.support, *self.ground], config)

    def _static(self, parts, tag) -> int:
        path = os.path.join(self._tmp.name, f"{tag}.urdf")
        urdf = write_urdf(path, parts, tag=tag, hull_erosion=self._erosion)
        body = pb.loadURDF(urdf, useFixedBase=True, physicsClientId=self.client)
        n_shapes = len(pb.getCollisionShapeData(body, -1, physicsClientId=self.client))
        if n_shapes != len(parts):
            raise RuntimeError(f"PyBullet loaded {n_shapes} of the {len(parts)} support parts")
        return body

    def set_pose(self, pose: np.ndarray) -> None:
        """Place the object at ``pose`` [7] (object frame in the support frame) at rest."""
        rot = Rotation.from_quat(np.roll(pose[3:], -1))
        pos = pose[:3] + rot.apply(self.com)
        quat = (rot * self.inertial_rot).as_quat()
        pb.resetBasePositionAndOrientation(
            self.body, pos.tolist(), quat.tolist(), physicsClientId=self.client
        )
        pb.resetBaseVelocity(self.body, [0, 0, 0], [0, 0, 0], physicsClientId=self.client)

    def pose(self) -> np.ndarray:
        """[7] the object's pose (object frame in the support frame, quaternion wxyz)."""
        pos, quat = pb.getBasePositionAndOrientation(self.body, physicsClientId=self.client)
        rot = Rotation.from_quat(quat) * self.inertial_rot.inv()
        q = rot.as_quat()
        return np.concatenate([np.asarray(pos) - rot.apply(self.com), np.roll(q, 1)])

    def park(self) -> None:
        """Move the object 1 km up and run collision detection: Bullet drops the contact
        manifolds of pairs whose boxes no longer overlap. ``set_pose`` alone keeps them, and
        the next pose's penetration check read the previous pose's points (a hanging pose
        judged after penetrating ones read 28 mm deep; docs/judges.md)."""
        pb.resetBasePositionAndOrientation(
            self.body, [0.0, 0.0, 1000.0], [0.0, 0.0, 0.0, 1.0], physicsClientId=self.client
        )
        pb.performCollisionDetection(physicsClientId=self.client)

    def contacts(self, other: int):
        return pb.getContactPoints(self.body, other, physicsClientId=self.client)

    def touching(self, other: int) -> bool:
        tol = self.config.touch_distance
        return any(p[8] < tol for p in self.contacts(other))

    def close(self) -> None:
        pb.disconnect(self.client)
        self._tmp.cleanup()


def stability(
    scene: Scene,
    poses: np.ndarray,
    config: StabilityConfig = StabilityConfig(),
    bullet: BulletConfig = MATCHED,
    world: PairWorld | None = None,
) -> StabilityResult:
    """:func:`sim.kernels.stability`'s protocol in PyBullet, one pose after the other.

    ``world`` reuses an open :class:`PairWorld` of this scene (its config wins over
    ``bullet``); otherwise one is built and closed here.
    """
    poses = kernels.check_poses(poses)
    own = world is None
    world = PairWorld(scene, bullet) if own else world
    n = len(poses)
    status = np.full(n, -1, np.int8)
    final, depth, sim_time = poses.copy(), np.zeros(n), np.zeros(n)
    step = world.config.time_step
    every = max(1, round(config.check_every / step))
    nseg = max(1, round(config.duration / (every * step)))
    c = world.client
    env = [world.support, *world.ground]
    try:
        for i, pose in enumerate(poses):
            world.park()  # flush the previous pose's contact manifolds
            world.set_pose(pose)
            pb.performCollisionDetection(physicsClientId=c)
            dists = [p[8] for b in env for p in world.contacts(b)]
            depth[i] = max(0.0, -min(dists, default=0.0))
            if depth[i] > config.max_penetration:
                status[i] = PENETRATING
                continue
            rest = 0
            for k in range(nseg):
                ground = False
                for _ in range(every):
                    pb.stepSimulation(physicsClientId=c)
                    ground |= any(world.touching(g) for g in world.ground)
                q = world.pose()
                lin, ang = pb.getBaseVelocity(world.body, physicsClientId=c)
                speed, spin = np.linalg.norm(lin), np.linalg.norm(ang)
                sim_time[i] = (k + 1) * every * step
                if (
                    not np.isfinite(q).all()
                    or np.linalg.norm(q[:3]) > config.escape_radius
                    or speed > config.max_speed
                ):
                    status[i] = DIVERGED
                    break
                final[i] = q
                box = kernels.object_boxes(scene, q[None])
                if (
                    ground
                    or not kernels.boxes_overlap(box, scene.support_bounds, config.box_margin)[0]
                ):
                    status[i] = FALLEN
                    break
                resting = (
                    speed < config.settle_speed
                    and spin < config.settle_spin
                    and world.touching(world.support)
                )
                rest = rest + 1 if resting else 0
                if rest >= config.settle_checks:
                    status[i] = STABLE
                    break
            if status[i] < 0:
                status[i] = STABLE
    finally:
        if own:
            world.close()
    final[:, 3:] /= np.linalg.norm(final[:, 3:], axis=1, keepdims=True)
    return StabilityResult(status == STABLE, status, final, depth, sim_time)
