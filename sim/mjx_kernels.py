"""MJX backend of the physics kernels: one compiled kernel for many (object, support) pairs.

Same signatures and protocols as :mod:`sim.kernels` (the CPU reference); this module adds
``*_many`` variants that take a list of scenes and a per-pose scene index, which is what
dataset generation needs.

Heterogeneous batches (the template). Compiling once per pair would dominate dataset
generation, so every pair is written into a *template* model whose structure (the static
part of ``mjx.Model``: geom types, contact pairs, body tree, mesh-convex array shapes) is
shared by many pairs:

- geoms are laid out in typed slots: the wall (a box; parked far away for free-standing
  supports), support capsules, boxes and meshes, then the object's capsules, boxes and
  meshes. Slot counts are rounded up (:func:`template_for`) so pairs of similar complexity
  land on the same template. Unused slots hold a tiny massless geom parked 1 km away: they
  still run their narrow phase (cost) but never touch anything (no effect);
- explicit contact pairs: every object slot x every support/wall slot; no floor collision
  (falling is detected from the object's lowest hull point, see :mod:`sim.scene`);
- each convex mesh's MJX convex data (vertices, polygon faces, edges) is padded to one
  layout by repeating the last entry (what MJX itself does for polygon faces): duplicate
  vertices, faces and edges change no support function and no separating-axis result;
- per pair, every traced model field (geom sizes/poses, body inertia, mesh-convex arrays,
  friction...) differs and is stacked along a leading pair axis; each simulated world
  gathers its pair's row, so one jitted, vmapped function serves all pairs of a template.
  Static fields are taken from the first pair; the ones that matter are checked equal.

Stability runs as *continuous batching*: a fixed number of lanes (worlds) advances one
0.1 s check segment per call; a world whose label is final (fallen, diverged, settled) is
replaced by the next queued pose at the start of the next call, so the GPU never simulates
finished worlds. A diverged world (NaN, blow-up) is labelled DIVERGED and reset; worlds are
independent under vmap, so it never touches the others.

Compilations are counted in :data:`COMPILES` (incremented while JAX traces a function,
which happens exactly once per compilation).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from sim import geometry, kernels
from sim.geometry import Box, Capsule, ConvexMesh
from sim.kernels import (
    DIVERGED,
    FALLEN,
    PENETRATING,
    STABLE,
    ContactConfig,
    ContactResult,
    StabilityConfig,
    StabilityResult,
    TakeoffConfig,
    TakeoffResult,
)
from sim.scene import Scene, _fmt, _geom_xml, wall_geom_xml

COMPILES: collections.Counter = collections.Counter()  # function name -> compilations
FAR = 1000.0  # m; unused template slots are parked this far away
OBJECT_BODY = 1  # the template's object body id (world is 0)


@dataclasses.dataclass(frozen=True)
class MJXSettings:
    """Knobs of the MJX backend that do not change the protocol."""

    lanes: int = 256  # worlds simulated at once; the benchmark uses the largest that fits
    iterations: int | None = None  # Newton cap; None keeps the scene's PhysicsConfig
    ls_iterations: int | None = None
    chunk: int = 256  # poses per call of the penetration probe / take-off
    impl: str = "jax"  # "jax": padded templates (below); "warp": MuJoCo Warp union model
    contacts_per_world: int = 48  # warp: contact pool = lanes x this (naconmax)


@dataclasses.dataclass(frozen=True)
class Template:
    """Slot counts of a template model and the padded mesh-convex layout."""

    support: tuple[int, int, int]  # capsules, boxes, meshes
    obj: tuple[int, int, int]
    mesh_layout: tuple[int, int, int, int]  # vertices, faces, polygon width, edges


def _round_up(n: int, steps: Sequence[int]) -> int:
    for s in steps:
        if n <= s:
            return s
    return int(np.ceil(n / steps[-1]) * steps[-1])


_CAPSULE_STEPS = (0, 2, 4, 8, 12, 16, 24, 32)
_BOX_STEPS = (0, 1, 2, 4)
_MESH_STEPS = (0, 1, 2, 4, 8, 16)


def _counts(parts) -> tuple[int, int, int]:
    return (
        sum(isinstance(p, Capsule) for p in parts),
        sum(isinstance(p, Box) for p in parts),
        sum(isinstance(p, ConvexMesh) for p in parts),
    )


def _bucket(counts: tuple[int, int, int]) -> tuple[int, int, int]:
    c, b, m = counts
    return _round_up(c, _CAPSULE_STEPS), _round_up(b, _BOX_STEPS), _round_up(m, _MESH_STEPS)


def template_for(scene: Scene) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    """Rounded-up (support, object) slot counts of a pair: pairs with equal counts share a
    compiled kernel."""
    return _bucket(_counts(scene.support.parts)), _bucket(_counts(scene.obj.parts))


# ----------------------------------------------------------------------------- template


def _dummy(kind: str, z: float):
    if kind == "capsule":
        return Capsule(np.array([0, 0, z]), np.array([0, 0, z + 0.002]), 0.001)
    if kind == "box":
        return Box(np.array([0, 0, z]), np.eye(3), np.full(3, 0.001))
    tet = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0, 0, 0.01]]) + [0, 0, z]
    return ConvexMesh(tet)


def _slotted(parts, counts, z) -> tuple[list, list[int]]:
    """Parts in typed slot order padded with parked dummies; source index (-1: dummy)."""
    out, src = [], []
    for kind, cls, n in zip(("capsule", "box", "mesh"), (Capsule, Box, ConvexMesh), counts):
        idx = [i for i, p in enumerate(parts) if isinstance(p, cls)]
        if len(idx) > n:
            raise ValueError(f"{len(idx)} {kind} parts do not fit a template of {n}")
        out += [parts[i] for i in idx] + [_dummy(kind, z) for _ in range(n - len(idx))]
        src += idx + [-1] * (n - len(idx))
    return out, src


def template_xml(scene: Scene, support_counts, object_counts, settings: MJXSettings) -> str:
    """The pair written into the typed slots of a template (see module docstring)."""
    physics = scene.physics
    obj, support = scene.obj, scene.support
    s_parts, s_src = _slotted(support.parts, support_counts, -FAR)
    o_parts, o_src = _slotted(obj.parts, object_counts, FAR)
    volumes = geometry.parts_volume(obj.parts)
    masses = physics.object_mass * volumes / volumes.sum()
    meshes, mesh_ref = {}, {}

    def lines(parts, src, prefix, group, mass):
        out = []
        for i, (part, j) in enumerate(zip(parts, src)):
            name = f"{prefix}{i}"
            if isinstance(part, ConvexMesh):
                mesh_ref[name] = f"{name}_mesh"
                meshes[f"{name}_mesh"] = np.asarray(part.vertices, float)
            extra = ""
            if mass:
                extra = f'mass="{masses[j]:.7g}"' if j >= 0 else 'mass="0"'
            out.append(_geom_xml(part, name, group, extra, mesh_ref))
        return out

    sup = lines(s_parts, s_src, "slot_s", 2, False)
    ob = lines(o_parts, o_src, "slot_o", 1, True)
    if support.wall_y is not None:
        wall = wall_geom_xml(support.wall_y, physics)  # the CPU scene's wall block
    else:
        wall = f'<geom name="wall" type="box" pos="0 0 {-2 * FAR}" size="0.01 0.01 0.01"/>'
    pairs = [
        f'<pair geom1="slot_o{i}" geom2="{t}"/>'
        for i in range(len(o_parts))
        for t in [f"slot_s{k}" for k in range(len(s_parts))] + ["wall"]
    ]
    assets = "\n".join(f'<mesh name="{n}" vertex="{_fmt(v)}"/>' for n, v in meshes.items())
    it = settings.iterations or physics.iterations
    ls = settings.ls_iterations or physics.ls_iterations
    return (
        f"""<mujoco model="template">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{physics.timestep}" integrator="implicitfast" solver="Newton" cone="elliptic"
          iterations="{it}" ls_iterations="{ls}" gravity="0 0 {physics.gravity}"/>
  <default>
    <geom contype="0" conaffinity="0" condim="4" solref="{physics.contact_timeconst} 1" friction="{physics.friction} 0.005 0.0001"/>
  </default>
  <asset>
{assets}
  </asset>
  <worldbody>
    {wall}
    {chr(10).join(sup)}
    <body name="object" pos="0 0 {FAR}">
      <freejoint/>
      {chr(10).join(ob)}
    </body>
  </worldbody>
  <contact>
    {chr(10).join(pairs)}
  </contact>
</mujoco>
""",
        s_src,
        o_src,
    )


def _pad_rows(x: np.ndarray, n: int) -> np.ndarray:
    if len(x) > n:
        raise ValueError(f"mesh convex data of {len(x)} rows exceeds the layout's {n}")
    return np.concatenate([x, np.repeat(x[-1:], n - len(x), axis=0)]) if len(x) < n else x


def _pad_convex(c, layout) -> mjx._src.types.ConvexMesh:  # noqa: SLF001
    nv, nf, npoly, ne = layout
    face = np.asarray(c.face)  # [F, P, 3] polygon vertices, edge-padded by MJX
    face = np.concatenate([face, np.repeat(face[:, -1:], npoly - face.shape[1], axis=1)], axis=1)
    return c.replace(
        vert=jnp.asarray(_pad_rows(np.asarray(c.vert), nv)),
        face=jnp.asarray(_pad_rows(face, nf)),
        face_normal=jnp.asarray(_pad_rows(np.asarray(c.face_normal), nf)),
        edge=jnp.asarray(_pad_rows(np.asarray(c.edge), ne)),
        edge_face_normal=jnp.asarray(_pad_rows(np.asarray(c.edge_face_normal), ne)),
    )


def _layout_of(convex) -> tuple[int, int, int, int]:
    return (
        len(convex.vert),
        len(convex.face),
        convex.face.shape[1],
        len(convex.edge),
    )


_STATIC_CHECK = (
    "geom_type",
    "geom_dataid",
    "pair_geom1",
    "pair_geom2",
    "pair_dim",
    "body_parentid",
)


@dataclasses.dataclass
class Batch:
    """Device-side stack of template models for a list of pairs (one template)."""

    template: Template
    models: mjx.Model  # every traced leaf [P, ...]
    aux: dict  # per-pair arrays [P, ...] for the protocol checks
    data0: mjx.Data  # one world at rest (the same for every pair of the template)
    scenes: list


def _round8(n: int) -> int:
    return int(np.ceil(n / 8) * 8)


def build_batch(scenes: Sequence[Scene], settings: MJXSettings = MJXSettings()) -> Batch:
    """Write every pair into the template of the largest slot counts among ``scenes``."""
    counts = [template_for(s) for s in scenes]
    s_counts = tuple(max(c[0][k] for c in counts) for k in range(3))
    o_counts = tuple(max(c[1][k] for c in counts) for k in range(3))
    built = []
    for scene in scenes:
        xml, s_src, o_src = template_xml(scene, s_counts, o_counts, settings)
        mj = mujoco.MjModel.from_xml_string(xml)
        built.append((mj, mjx.put_model(mj), s_src, o_src))
    convex = [c for _, m, _, _ in built for c in m._impl.mesh_convex if c is not None]
    layout = (32, 8, 8, 8)
    if convex:
        lay = np.max([_layout_of(c) for c in convex], axis=0)
        layout = (max(32, int(lay[0])), _round8(lay[1]), int(lay[2]), _round8(lay[3]))
    template = Template(s_counts, o_counts, layout)
    models, aux = [], collections.defaultdict(list)
    ref = built[0][0]
    kmax = max(len(s.object_hull_points) for s in scenes)
    for scene, (mj, m, s_src, o_src) in zip(scenes, built):
        for f in _STATIC_CHECK:
            if not np.array_equal(getattr(mj, f), getattr(ref, f)):
                raise AssertionError(f"template field {f} differs between pairs")
        padded = tuple(None if c is None else _pad_convex(c, layout) for c in m._impl.mesh_convex)
        models.append(m.replace(_impl=m._impl.replace(mesh_convex=padded)))
        nw = 1  # wall slot first
        valid = np.zeros(mj.ngeom, bool)
        ground = np.zeros(mj.ngeom, bool)
        has_wall = scene.support.wall_y is not None
        valid[0] = has_wall
        for k, j in enumerate(s_src):
            valid[nw + k] = j >= 0
            ground[nw + k] = j >= 0 and j in tuple(scene.support.ground_parts)
        for k, j in enumerate(o_src):
            valid[nw + len(s_src) + k] = j >= 0
        hull = np.asarray(scene.object_hull_points, float)
        aux["hull"].append(_pad_rows(hull, kmax))
        aux["floor_z"].append(float(scene.support.floor_z))
        aux["bounds"].append(np.asarray(scene.support_bounds, float))
        aux["valid"].append(valid)
        aux["ground"].append(ground)
    leaves0, treedef = jax.tree.flatten(models[0])
    all_leaves = [jax.tree.leaves(m) for m in models]
    for leaves in all_leaves:
        if len(leaves) != len(leaves0) or any(
            np.shape(a) != np.shape(b) for a, b in zip(leaves, leaves0)
        ):
            raise AssertionError("pairs of one template must have equal traced shapes")
    stacked = jax.tree.unflatten(treedef, [jnp.stack(xs) for xs in zip(*all_leaves, strict=True)])
    aux = {k: jnp.asarray(np.stack(v)) for k, v in aux.items()}
    data0 = mjx.make_data(models[0])
    return Batch(template, stacked, aux, data0, list(scenes))


def with_material(batch: Batch, mass: float | None, friction: float | None) -> mjx.Model:
    """The stacked models with the object's mass and every contact's friction replaced."""
    m = batch.models
    if mass is not None:
        factor = mass / m.body_mass[:, OBJECT_BODY]
        m = m.replace(
            body_mass=m.body_mass.at[:, OBJECT_BODY].set(mass),
            body_inertia=m.body_inertia.at[:, OBJECT_BODY].multiply(factor[:, None]),
            # as mj_setConst after a mass change (kernels.with_material): the free object's
            # inverse weights scale by 1 / factor; its 6 dofs are the model's only dofs
            body_invweight0=m.body_invweight0.at[:, OBJECT_BODY].divide(factor[:, None]),
            dof_invweight0=m.dof_invweight0 / factor[:, None],
        )
    if friction is not None:
        m = m.replace(pair_friction=m.pair_friction.at[:, :, 0:2].set(friction))
    return m


# ----------------------------------------------------------------------------- device side


def _row(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def _rotmat(q):
    w, x, y, z = q
    return jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _world_hull(aux, qpos):
    q = qpos[3:7] / jnp.maximum(jnp.linalg.norm(qpos[3:7]), 1e-9)
    return aux["hull"] @ _rotmat(q).T + qpos[:3]


def _overlap(aux, qpos, margin):
    pts = _world_hull(aux, qpos)
    lo, hi = aux["bounds"][0] - margin, aux["bounds"][1] + margin
    return jnp.all((pts.min(0) <= hi) & (pts.max(0) >= lo))


def _contact_dist(aux, d):
    """[ncon] contact distances of real geoms (inf for parked slots)."""
    con = d._impl.contact
    ok = aux["valid"][con.geom[:, 0]] & aux["valid"][con.geom[:, 1]]
    return jnp.where(ok, con.dist, jnp.inf), con


def _ground_now(aux, d):
    dist, con = _contact_dist(aux, d)
    on_base = aux["ground"][con.geom[:, 0]] | aux["ground"][con.geom[:, 1]]
    base = jnp.any(on_base & (dist < 0))
    floor = _world_hull(aux, d.qpos).min(0)[2] < aux["floor_z"]
    return base | floor


def _set_pose(data0, qpos):
    return data0.replace(qpos=data0.qpos.at[:7].set(qpos))


def _probe_one(m, aux, data0, qpos):
    d = _set_pose(data0, qpos)
    d = mjx.kinematics(m, d)
    d = mjx.collision(m, d)
    dist, con = _contact_dist(aux, d)
    floor = _world_hull(aux, qpos).min(0)[2] - aux["floor_z"]
    return dist, con.pos, con.frame.reshape(-1, 9)[:, :3], con.geom, floor


@functools.partial(jax.jit, static_argnames=())
def _probe(models, aux, data0, pair, qpos):
    COMPILES["probe"] += 1
    return jax.vmap(lambda p, q: _probe_one(_row(models, p), _row(aux, p), data0, q))(pair, qpos)


@functools.partial(jax.jit, static_argnames=("seg", "cfg"), donate_argnums=(3,))
def _advance(models, aux, data0, lanes, refill, new_qpos, new_pair, seg, cfg):
    """Refill finished lanes, then simulate one check segment of every lane.

    lanes: dict of d [L] mjx.Data, pair [L], rest [L], nseg [L]. Returns the new lanes and
    per-lane status (-1 still running), final qpos [L, 7] and segments simulated [L].
    """
    COMPILES["advance"] += 1

    def one(d, pair, rest, nseg, refill, q_new, p_new):
        d = jax.tree.map(lambda a, b: jnp.where(refill, a, b), _set_pose(data0, q_new), d)
        pair = jnp.where(refill, p_new, pair)
        rest = jnp.where(refill, 0, rest)
        nseg = jnp.where(refill, 0, nseg)
        m, ax = _row(models, pair), _row(aux, pair)

        def step(carry, _):
            d, ground, finite = carry
            d = mjx.step(m, d)
            ok = jnp.all(jnp.isfinite(d.qpos)) & jnp.all(jnp.isfinite(d.qvel))
            return (d, ground | (_ground_now(ax, d) & ok), finite & ok), None

        (d, ground, finite), _ = jax.lax.scan(step, (d, False, True), None, length=seg)
        qpos, qvel = d.qpos[:7], d.qvel[:6]
        safe = jnp.where(finite, qpos, jnp.array([0, 0, 0, 1.0, 0, 0, 0]))
        pos_ok = finite & (jnp.linalg.norm(safe[:3]) < cfg.escape_radius)
        speed = jnp.where(finite, jnp.linalg.norm(qvel[:3]), jnp.inf)
        spin = jnp.where(finite, jnp.linalg.norm(qvel[3:]), jnp.inf)
        diverged = ~pos_ok | (speed > cfg.max_speed)
        overlap = _overlap(ax, safe, cfg.box_margin)
        dist, _ = _contact_dist(ax, d)
        touching = jnp.any(dist < 0)
        resting = (speed < cfg.settle_speed) & (spin < cfg.settle_spin) & touching
        rest = jnp.where(resting, rest + 1, 0)
        nseg = nseg + 1
        status = jnp.full((), -1, jnp.int8)
        status = jnp.where(rest >= cfg.settle_checks, jnp.int8(STABLE), status)
        status = jnp.where(ground | ~overlap, jnp.int8(FALLEN), status)
        status = jnp.where(diverged, jnp.int8(DIVERGED), status)
        nmax = max(1, round(cfg.duration / cfg.check_every))
        status = jnp.where((status < 0) & (nseg >= nmax), jnp.int8(STABLE), status)
        # a diverged world is reset to its pose so its NaNs never reach a later step
        d = jax.tree.map(lambda a, b: jnp.where(diverged, a, b), _set_pose(data0, safe), d)
        return (d, pair, rest, nseg), status, safe, nseg

    (d, pair, rest, nseg), status, qpos, nseg = jax.vmap(one)(
        lanes["d"], lanes["pair"], lanes["rest"], lanes["nseg"], refill, new_qpos, new_pair
    )
    return {"d": d, "pair": pair, "rest": rest, "nseg": nseg}, status, qpos, nseg


@functools.partial(jax.jit, static_argnames=("push", "free", "every"))
def _takeoff_run(models, aux, data0, pair, qpos, force, push, free, every):
    """[N] pulls: removed if the object's box separates from the support's at any check."""
    COMPILES["takeoff"] += 1

    def one(p, q, f):
        m, ax = _row(models, p), _row(aux, p)
        d = _set_pose(data0, q)

        def step(carry, t):
            d, removed = carry
            xfrc = d.xfrc_applied.at[OBJECT_BODY, :3].set(jnp.where(t < push, f, 0.0))
            d = mjx.step(m, d.replace(xfrc_applied=xfrc))
            check = (t + 1) % every == 0
            check = check | (t == push + free - 1)
            q = d.qpos[:7]
            ok = jnp.all(jnp.isfinite(q)) & (jnp.linalg.norm(jnp.nan_to_num(q[:3])) < 1e3)
            sep = ~ok | ~_overlap(ax, jnp.where(ok, q, jnp.array([0, 0, 1e3, 1.0, 0, 0, 0])), 0.0)
            return (d, removed | (check & sep)), None

        (_, removed), _ = jax.lax.scan(step, (d, False), jnp.arange(push + free))
        return removed

    return jax.vmap(one)(pair, qpos, force)


# ----------------------------------------------------------------------------- host side

_BATCHES: dict = {}


def _batch_for(scenes: Sequence[Scene], settings: MJXSettings) -> Batch:
    key = (tuple(id(s) for s in scenes), settings)
    if key not in _BATCHES:
        _BATCHES[key] = (build_batch(scenes, settings), list(scenes))  # keep scenes alive
    return _BATCHES[key][0]


def _chunks(n: int, size: int):
    for s in range(0, n, size):
        yield np.arange(s, min(s + size, n))


def _padded(idx, size, *arrays):
    """Arrays indexed by idx, padded to ``size`` rows by repeating the first row."""
    fill = np.concatenate([idx, np.full(size - len(idx), idx[0])])
    return [a[fill] for a in arrays]


def probe_many(batch: Batch, pair: np.ndarray, poses: np.ndarray, chunk: int):
    """Host arrays of the probe for every pose: dist [B, C], pos, normal, geom, floor [B]."""
    outs = []
    for idx in _chunks(len(poses), chunk):
        p, q = _padded(idx, chunk, pair, poses)
        res = _probe(batch.models, batch.aux, batch.data0, jnp.asarray(p), jnp.asarray(q))
        outs.append([np.asarray(r)[: len(idx)] for r in res])
    return [np.concatenate(x) for x in zip(*outs)]


def _lane_state(data, nl: int) -> dict:
    """Per-lane state of continuous batching: the worlds' data, their pair index, resting
    checks in a row and segments simulated."""
    # separate buffers: the advance step donates its lane state
    return {k: jnp.zeros(nl, jnp.int32) for k in ("pair", "rest", "nseg")} | {"d": data}


def _drain(poses, pair, depth, config, dt, nl, lanes, advance, park) -> StabilityResult:
    """Host side of continuous batching, shared by both impls: ``nl`` lanes advance one
    check segment per ``advance(lanes, refill, new_qpos, new_pair)`` call; a lane whose label
    is final is refilled with the next queued pose (``park`` pose when the queue is empty)."""
    seg = max(1, round(config.check_every / dt))
    n = len(poses)
    status = np.full(n, -1, np.int8)
    final = poses.copy()
    sim_time = np.zeros(n)
    status[depth > config.max_penetration] = PENETRATING
    queue = list(np.flatnonzero(status < 0)[::-1])
    owner = np.full(nl, -1)  # pose index simulated in each lane
    while queue or (owner >= 0).any():
        refill = np.zeros(nl, bool)
        new_q = np.tile(park, (nl, 1))
        new_p = np.zeros(nl, np.int32)
        for lane in np.flatnonzero(owner < 0):
            if not queue:
                break
            i = queue.pop()
            owner[lane], refill[lane] = i, True
            new_q[lane], new_p[lane] = poses[i], pair[i]
        lanes, st, qpos, nseg = advance(lanes, refill, new_q, new_p, seg)
        st, qpos, nseg = np.asarray(st), np.asarray(qpos), np.asarray(nseg)
        done = (owner >= 0) & (st >= 0)
        rows = owner[done]
        status[rows] = st[done]
        final[rows] = np.where((st[done] == DIVERGED)[:, None], poses[rows], qpos[done])
        sim_time[rows] = nseg[done] * seg * dt
        owner[done] = -1
    final[:, 3:] /= np.linalg.norm(final[:, 3:], axis=1, keepdims=True)
    return StabilityResult(status == STABLE, status, final, depth, sim_time)


def stability_many(
    scenes: Sequence[Scene],
    pair: np.ndarray,
    poses: np.ndarray,
    config: StabilityConfig = StabilityConfig(),
    settings: MJXSettings = MJXSettings(),
    batch: Batch | None = None,
) -> StabilityResult:
    """Stability labels of ``poses`` [B, 7], pose i on ``scenes[pair[i]]`` (one template).

    ``batch`` (optional) is a prebuilt :func:`build_batch` of ``scenes``.
    """
    poses = kernels.check_poses(poses)
    pair = np.asarray(pair, dtype=np.int32)
    if settings.impl == "warp":
        from sim import mjx_warp

        return mjx_warp.stability_warp(scenes, pair, poses, config, settings, batch)
    batch = batch or _batch_for(scenes, settings)
    dist, *_, floor = probe_many(batch, pair, poses, settings.chunk)
    depth = np.maximum(np.maximum(-dist.min(1), -floor), 0.0)
    depth[~np.isfinite(depth)] = 0.0
    nl = settings.lanes
    lanes = _lane_state(jax.tree.map(lambda x: jnp.stack([x] * nl), batch.data0), nl)

    def advance(lanes, refill, new_q, new_p, seg):
        return _advance(
            batch.models,
            batch.aux,
            batch.data0,
            lanes,
            jnp.asarray(refill),
            jnp.asarray(new_q),
            jnp.asarray(new_p),
            seg,
            config,
        )

    park = np.array([0, 0, FAR, 1.0, 0, 0, 0])
    return _drain(poses, pair, depth, config, scenes[0].physics.timestep, nl, lanes, advance, park)


def stability(
    scene: Scene,
    poses: np.ndarray,
    config: StabilityConfig = StabilityConfig(),
    settings: MJXSettings = MJXSettings(),
) -> StabilityResult:
    """MJX version of :func:`sim.kernels.stability` for one pair."""
    poses = kernels.check_poses(poses)
    return stability_many([scene], np.zeros(len(poses), np.int32), poses, config, settings)


def _sequential(removed: np.ndarray) -> TakeoffResult:
    """The reference's sequential semantics from all 11 directions simulated at once.

    The device pushes every pose along all 11 directions in parallel (one pass); the CPU
    reference tries them in the original order and does not push a pose freed by one
    direction along the later ones, so only the first removing direction stays True.
    ``removable`` and ``direction`` are unchanged by this; ``removed`` then matches.
    """
    removed = np.asarray(removed, bool)
    first = np.where(removed.any(1), removed.argmax(1), -1)
    seq = np.zeros_like(removed)
    rows = np.flatnonzero(first >= 0)
    seq[rows, first[rows]] = True
    return TakeoffResult(seq.any(1), first, seq)


def takeoff_many(
    scenes: Sequence[Scene],
    pair: np.ndarray,
    poses: np.ndarray,
    config: TakeoffConfig = TakeoffConfig(),
    settings: MJXSettings = MJXSettings(),
    materials: tuple[np.ndarray, np.ndarray] | None = None,
) -> TakeoffResult:
    """Take-off of ``poses`` [B, 7], pose i on ``scenes[pair[i]]`` (one template).

    ``materials`` (warp impl only): per-pair ``(mass [P], friction [P])``, P = len(scenes),
    replacing ``config.mass`` / ``config.friction`` pair by pair (as
    :func:`sim.kernels.with_material` does for one pair); None keeps the config's.
    """
    poses = kernels.check_poses(poses)
    pair = np.asarray(pair, dtype=np.int32)
    if settings.impl == "warp":
        from sim import mjx_warp

        return mjx_warp.takeoff_warp(scenes, pair, poses, config, settings, materials)
    if materials is not None:
        raise NotImplementedError("per-pair materials need impl='warp'")
    batch = _batch_for(scenes, settings)
    models = with_material(batch, config.mass, config.friction)
    dt = scenes[0].physics.timestep
    push, free = round(config.push_time / dt), round(config.free_time / dt)
    every = max(1, round(config.check_every / dt))
    forces = kernels.takeoff_forces(poses, config).reshape(-1, 3)
    rep_pose = np.repeat(poses, 11, axis=0)
    rep_pair = np.repeat(pair, 11)
    removed = np.zeros(len(rep_pose), bool)
    for idx in _chunks(len(rep_pose), settings.chunk):
        p, q, f = _padded(idx, settings.chunk, rep_pair, rep_pose, forces)
        out = _takeoff_run(
            models, batch.aux, batch.data0, jnp.asarray(p), jnp.asarray(q), jnp.asarray(f),
            push, free, every,
        )  # fmt: skip
        removed[idx] = np.asarray(out)[: len(idx)]
    return _sequential(removed.reshape(len(poses), 11))


def takeoff(
    scene: Scene,
    poses: np.ndarray,
    config: TakeoffConfig = TakeoffConfig(),
    settings: MJXSettings = MJXSettings(),
) -> TakeoffResult:
    """MJX version of :func:`sim.kernels.takeoff` for one pair."""
    poses = kernels.check_poses(poses)
    return takeoff_many([scene], np.zeros(len(poses), np.int32), poses, config, settings)


def contact_query(
    scene: Scene,
    poses: np.ndarray,
    config: ContactConfig = ContactConfig(),
    settings: MJXSettings = MJXSettings(chunk=64),
) -> ContactResult:
    """MJX version of :func:`sim.kernels.contact_query`.

    ``distance`` is the smallest distance MJX's narrow phase reports over object-support
    pairs; MJX reports exact distances for primitive pairs and separating-axis distances
    for convex meshes (a lower bound when the closest features are edges), clipped at the
    cutoff.
    """
    poses = kernels.check_poses(poses)
    batch = _batch_for([scene], settings)
    pair = np.zeros(len(poses), np.int32)
    dist, pos, normal, geom, _ = probe_many(batch, pair, poses, settings.chunk)
    b, c = len(poses), config.max_contacts
    obj_first = geom[:, :, 0] > geom[:, :, 1]  # object slots come after support slots
    # MJX normals point from geom[0] to geom[1]; make them point support -> object
    sign = np.where(obj_first, -1.0, 1.0)
    pen = np.zeros(b)
    out_d = np.full(b, config.distance_cutoff)
    opts, spts, nrm = (np.zeros((b, c, 3)) for _ in range(3))
    mask = np.zeros((b, c), bool)
    for i in range(b):
        real = np.isfinite(dist[i])
        if real.any():
            out_d[i] = min(config.distance_cutoff, dist[i][real].min())
        rows = np.flatnonzero(real & (dist[i] < 0))
        rows = rows[np.argsort(dist[i][rows])][:c]
        for j, r in enumerate(rows):
            n = normal[i, r] * sign[i, r]  # support -> object
            # (object - support) . n = dist: the points straddle the midpoint along n
            opts[i, j] = pos[i, r] + 0.5 * dist[i, r] * n
            spts[i, j] = pos[i, r] - 0.5 * dist[i, r] * n
            nrm[i, j], mask[i, j] = n, True
        if len(rows):
            pen[i] = max(0.0, -dist[i, rows[0]])
    return ContactResult(pen, out_d, opts, spts, nrm, mask)
