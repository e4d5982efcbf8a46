"""MJX's Warp implementation of the batched physics kernels (``MJXSettings(impl="warp")``):
MuJoCo Warp's CUDA kernels (also on Warp's CPU device) behind the same protocols as
:mod:`sim.mjx_kernels`, which dispatches here.

One *union* model serves every pair of a batch, so one compiled program serves them all:

- geoms: the wall slot, support capsule/box slots (as many as the largest support has),
  every pair's support meshes, then on the one free body the object capsule/box slots
  and every pair's object meshes. A world activates its pair's geoms through per-world
  model fields (MuJoCo Warp's batched model fields: geom_pos/quat/size/aabb/rbound,
  body inertia); all other geoms are parked 1 km away (support below, object above the
  body frame), where the broad phase drops them.
- collisions by contype/conaffinity (object x support/wall only), MuJoCo Warp's own
  broad phase and narrow phase (GJK/EPA for meshes), no explicit pairs.
- per-world mesh ids are not supported by MJX, hence the union of meshes rather than
  mesh slots; primitive slots take their size per world.
- the support's geoms hang on a mocap body that never moves, not on the world body:
  MuJoCo Warp computes the poses of geoms welded to the world once (make_data), so
  per-world geom_pos of those would be ignored.
- contacts live in one pool of ``lanes x contacts_per_world`` entries tagged with their
  world, so the protocol's contact checks are segment reductions over the pool.
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

from sim import kernels
from sim.geometry import Box, Capsule
from sim.kernels import DIVERGED, FALLEN, STABLE, StabilityResult, TakeoffResult
from sim.mjx_kernels import (
    COMPILES,
    FAR,
    MJXSettings,
    _chunks,
    _counts,
    _drain,
    _dummy,
    _lane_state,
    _overlap,
    _pad_rows,
    _padded,
    _sequential,
    _set_pose,
    _world_hull,
)
from sim.scene import Scene, _fmt, _geom_xml, wall_box

W_SUPPORT_BODY, W_OBJECT_BODY = 1, 2  # body ids of the union model

_PER_WORLD = (
    "geom_pos",
    "geom_quat",
    "geom_size",
    "geom_aabb",
    "geom_rbound",
    "geom_friction",
    "body_mass",
    "body_inertia",
    "body_ipos",
    "body_iquat",
    "body_invweight0",
    "body_subtreemass",
    "dof_invweight0",
)


@dataclasses.dataclass
class WarpBatch:
    """Union model of a list of pairs and their per-pair model fields (warp impl)."""

    mj: mujoco.MjModel
    model: mjx.Model  # impl="warp", unbatched
    fields: dict  # name -> [P, ...] per-pair values of _PER_WORLD
    aux: dict  # hull [P, K, 3], floor_z [P], bounds [P, 2, 3], ground [P, ngeom]
    scenes: list
    naconmax_per_world: int
    njmax: int


def union_xml(scenes: Sequence[Scene], settings: MJXSettings):
    """MJCF of the union model and, per pair, {union geom name: scene geom name}."""
    physics = scenes[0].physics
    s_caps = max(_counts(s.support.parts)[0] for s in scenes)
    s_box = max(_counts(s.support.parts)[1] for s in scenes)
    o_caps = max(_counts(s.obj.parts)[0] for s in scenes)
    o_box = max(_counts(s.obj.parts)[1] for s in scenes)
    sup, obj, assets = [], [], []
    maps = [{} for _ in scenes]
    sup_attr = 'contype="0" conaffinity="1"'
    obj_attr = 'contype="1" conaffinity="0"'
    for k in range(s_caps):
        sup.append(_geom_xml(_dummy("capsule", 0.0), f"s_cap{k}", 2, sup_attr, {}))
    for k in range(s_box):
        sup.append(_geom_xml(_dummy("box", 0.0), f"s_box{k}", 2, sup_attr, {}))
    for k in range(o_caps):
        obj.append(_geom_xml(_dummy("capsule", 0.0), f"o_cap{k}", 1, obj_attr, {}))
    for k in range(o_box):
        obj.append(_geom_xml(_dummy("box", 0.0), f"o_box{k}", 1, obj_attr, {}))
    # Mesh geoms are shared by every pair with the same convex part (same vertices): a
    # group of dataset shards holds few distinct objects (pairs are ordered by object), and
    # every world carries every union geom through the broad phase, so one geom per pair
    # made a group of 128 cap pairs 1,905 mesh geoms instead of ~160 (docs/dataset.md).
    mesh_names: dict[tuple[str, bytes, int], str] = {}
    for p, scene in enumerate(scenes):
        for prefix, parts, out, attr, uprefix in (
            ("support_", scene.support.parts, sup, sup_attr, "s"),
            ("object_", scene.obj.parts, obj, obj_attr, "o"),
        ):
            nc = nb = 0
            seen: collections.Counter = collections.Counter()  # same part twice in one pair
            for i, part in enumerate(parts):
                if isinstance(part, Capsule):
                    maps[p][f"{uprefix}_cap{nc}"] = f"{prefix}{i}"
                    nc += 1
                elif isinstance(part, Box):
                    maps[p][f"{uprefix}_box{nb}"] = f"{prefix}{i}"
                    nb += 1
                else:
                    vertices = np.ascontiguousarray(part.vertices, dtype=np.float64)
                    raw = vertices.tobytes()
                    key = (uprefix, raw, seen[raw])
                    seen[raw] += 1
                    if key not in mesh_names:
                        name = f"{uprefix}_mesh{len(mesh_names)}"
                        mesh_names[key] = name
                        assets.append(f'<mesh name="{name}_m" vertex="{_fmt(vertices)}"/>')
                        out.append(_geom_xml(part, name, 2, attr, {name: f"{name}_m"}))
                    maps[p][mesh_names[key]] = f"{prefix}{i}"
        if scene.support.wall_y is not None:
            maps[p]["wall"] = "wall"
    it = settings.iterations or physics.iterations
    ls = settings.ls_iterations or physics.ls_iterations
    xml = f"""<mujoco model="union">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{physics.timestep}" integrator="implicitfast" solver="Newton" cone="elliptic"
          iterations="{it}" ls_iterations="{ls}" gravity="0 0 {physics.gravity}"/>
  <default>
    <geom condim="4" solref="{physics.contact_timeconst} 1" friction="{physics.friction} 0.005 0.0001"/>
  </default>
  <asset>
{chr(10).join(assets)}
  </asset>
  <worldbody>
    <body name="support" mocap="true">
      <geom name="wall" type="box" size="{_fmt(wall_box(0.0, physics)[1])}" {sup_attr}/>
      {chr(10).join(sup)}
    </body>
    <body name="object" pos="0 0 {FAR}">
      <freejoint/>
      {chr(10).join(obj)}
    </body>
  </worldbody>
</mujoco>
"""
    return xml, maps


def build_warp_batch(scenes: Sequence[Scene], settings: MJXSettings = MJXSettings()) -> WarpBatch:
    """The union model of ``scenes`` and each pair's per-world model fields."""
    xml, maps = union_xml(scenes, settings)
    mj = mujoco.MjModel.from_xml_string(xml)
    model = mjx.put_model(mj, impl="warp")
    base = {k: np.asarray(getattr(model, k)) for k in _PER_WORLD}
    on_object = mj.geom_bodyid == W_OBJECT_BODY
    fields = collections.defaultdict(list)
    aux = collections.defaultdict(list)
    kmax = max(len(s.object_hull_points) for s in scenes)
    for scene, gmap in zip(scenes, maps):
        sm = scene.model
        f = {k: v.copy() for k, v in base.items()}
        f["geom_pos"][:, 2] += np.where(on_object, FAR, -FAR)  # park everything
        ground = np.zeros(mj.ngeom, bool)
        ground_names = {f"support_{k}" for k in scene.support.ground_parts}
        for g in range(mj.ngeom):
            uname = mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_GEOM, g)
            if uname not in gmap:
                continue
            s = mujoco.mj_name2id(sm, mujoco.mjtObj.mjOBJ_GEOM, gmap[uname])
            f["geom_pos"][g] = sm.geom_pos[s]
            f["geom_quat"][g] = sm.geom_quat[s]
            f["geom_size"][g] = sm.geom_size[s]
            f["geom_aabb"][g] = sm.geom_aabb[s].reshape(2, 3)
            f["geom_rbound"][g] = sm.geom_rbound[s]
            f["geom_friction"][g] = sm.geom_friction[s]
            ground[g] = gmap[uname] in ground_names
        for k in ("body_mass", "body_inertia", "body_ipos", "body_iquat", "body_invweight0"):
            f[k][W_OBJECT_BODY] = getattr(sm, k)[scene.object_body]
        f["body_subtreemass"][W_OBJECT_BODY] = sm.body_subtreemass[scene.object_body]
        f["dof_invweight0"][:] = sm.dof_invweight0[:6]
        for k, v in f.items():
            fields[k].append(v)
        aux["hull"].append(_pad_rows(np.asarray(scene.object_hull_points, float), kmax))
        aux["floor_z"].append(float(scene.support.floor_z))
        aux["bounds"].append(np.asarray(scene.support_bounds, float))
        aux["ground"].append(ground)
    fields = {k: jnp.asarray(np.stack(v), dtype=base[k].dtype) for k, v in fields.items()}
    aux = {
        k: jnp.asarray(np.stack(v), dtype=bool if k == "ground" else jnp.float32)
        for k, v in aux.items()
    }
    nc = settings.contacts_per_world
    return WarpBatch(mj, model, fields, aux, list(scenes), nc, 4 * nc)


_WARP_DATA: dict = {}


def _warp_data0(batch: WarpBatch, lanes: int) -> mjx.Data:
    key = (id(batch), lanes)
    if key not in _WARP_DATA:
        _WARP_DATA[key] = mjx.make_data(
            batch.mj, impl="warp", naconmax=lanes * batch.naconmax_per_world, njmax=batch.njmax
        )
    return _WARP_DATA[key]


def _w_models(model, fields):
    return model.replace(**fields)


def _w_segment_any(flag, worldid, lanes):
    return jnp.zeros(lanes, bool).at[worldid].max(flag)


def _w_contacts(d, lanes):
    """Pool view: (valid [C], worldid [C], dist [C], geom [C, 2])."""
    impl = d._impl
    n = impl.contact__dist.shape[0]
    valid = jnp.arange(n) < jnp.reshape(impl.nacon, (-1,))[0]
    wid = jnp.clip(impl.contact__worldid, 0, lanes - 1)
    return valid, wid, impl.contact__dist, impl.contact__geom


def _w_posed(data0, qpos):
    """[L] worlds at rest at ``qpos`` [L, 7] (Data batched along the lanes)."""
    return jax.vmap(lambda q: _set_pose(data0, q))(qpos)


@functools.partial(jax.jit, static_argnames=())
def _w_probe(model, fields, aux, data0, pair, qpos):
    """Deepest initial penetration [L] of each world: object-support contacts and floor."""
    COMPILES["warp_probe"] += 1
    lanes = qpos.shape[0]
    f = jax.tree.map(lambda x: x[pair], fields)
    d = _w_posed(data0, qpos)
    d = jax.vmap(lambda f, d: mjx.forward(_w_models(model, f), d))(f, d)
    valid, wid, dist, _ = _w_contacts(d, lanes)
    dmin = jnp.full(lanes, jnp.inf).at[wid].min(jnp.where(valid, dist, jnp.inf))
    ax = jax.tree.map(lambda x: x[pair], aux)
    floor = jax.vmap(lambda a, q: _world_hull(a, q).min(0)[2] - a["floor_z"])(ax, qpos)
    return jnp.maximum(jnp.maximum(-dmin, -floor), 0.0)


@functools.partial(jax.jit, static_argnames=("seg", "cfg"))
def _w_advance(model, fields, aux, data0, lanes, refill, new_qpos, new_pair, seg, cfg):
    """Warp version of :func:`_advance`: refill finished lanes, simulate one segment."""
    COMPILES["warp_advance"] += 1
    nl = refill.shape[0]
    fresh = _w_posed(data0, new_qpos)
    d = jax.vmap(lambda d, r, f: d.where(r, f))(lanes["d"], refill, fresh)
    pair = jnp.where(refill, new_pair, lanes["pair"])
    rest = jnp.where(refill, 0, lanes["rest"])
    nseg = jnp.where(refill, 0, lanes["nseg"])
    f = jax.tree.map(lambda x: x[pair], fields)
    ax = jax.tree.map(lambda x: x[pair], aux)

    def step(carry, _):
        d, ground, finite = carry
        d = jax.vmap(lambda f, d: mjx.step(_w_models(model, f), d))(f, d)
        ok = jnp.all(jnp.isfinite(d.qpos), 1) & jnp.all(jnp.isfinite(d.qvel), 1)
        valid, wid, dist, geom = _w_contacts(d, nl)
        g = ax["ground"]
        on_base = g[wid, geom[:, 0]] | g[wid, geom[:, 1]]
        base = _w_segment_any(valid & on_base & (dist < 0), wid, nl)
        floor = jax.vmap(lambda a, q: _world_hull(a, q).min(0)[2] < a["floor_z"])(ax, d.qpos)
        return (d, ground | ((base | floor) & ok), finite & ok), None

    init = (d, jnp.zeros(nl, bool), jnp.ones(nl, bool))
    (d, ground, finite), _ = jax.lax.scan(step, init, None, length=seg)
    qpos, qvel = d.qpos[:, :7], d.qvel[:, :6]
    safe = jnp.where(finite[:, None], qpos, jnp.array([0, 0, 0, 1.0, 0, 0, 0]))
    pos_ok = finite & (jnp.linalg.norm(safe[:, :3], axis=1) < cfg.escape_radius)
    speed = jnp.where(finite, jnp.linalg.norm(qvel[:, :3], axis=1), jnp.inf)
    spin = jnp.where(finite, jnp.linalg.norm(qvel[:, 3:], axis=1), jnp.inf)
    diverged = ~pos_ok | (speed > cfg.max_speed)
    overlap = jax.vmap(lambda a, q: _overlap(a, q, cfg.box_margin))(ax, safe)
    valid, wid, dist, _ = _w_contacts(d, nl)
    touching = _w_segment_any(valid & (dist < 0), wid, nl)
    resting = (speed < cfg.settle_speed) & (spin < cfg.settle_spin) & touching
    rest = jnp.where(resting, rest + 1, 0)
    nseg = nseg + 1
    status = jnp.full(nl, -1, jnp.int8)
    status = jnp.where(rest >= cfg.settle_checks, jnp.int8(STABLE), status)
    status = jnp.where(ground | ~overlap, jnp.int8(FALLEN), status)
    status = jnp.where(diverged, jnp.int8(DIVERGED), status)
    nmax = max(1, round(cfg.duration / cfg.check_every))
    status = jnp.where((status < 0) & (nseg >= nmax), jnp.int8(STABLE), status)
    # a diverged world restarts at rest at a safe pose: its NaNs never reach a later step
    reset = _w_posed(data0, safe)
    d = jax.vmap(lambda d, r, f: d.where(r, f))(d, diverged, reset)
    return {"d": d, "pair": pair, "rest": rest, "nseg": nseg}, status, safe, nseg


_WARP_BATCHES: dict = {}


def warp_batch_for(scenes: Sequence[Scene], settings: MJXSettings) -> WarpBatch:
    key = (tuple(id(s) for s in scenes), settings)
    if key not in _WARP_BATCHES:
        _WARP_BATCHES[key] = (build_warp_batch(scenes, settings), list(scenes))
    return _WARP_BATCHES[key][0]


def stability_warp(scenes, pair, poses, config, settings, batch=None) -> StabilityResult:
    batch = batch or warp_batch_for(scenes, settings)
    nl = settings.lanes
    data0 = _warp_data0(batch, nl)
    n = len(poses)
    depth = np.zeros(n)
    for idx in _chunks(n, nl):
        p, q = _padded(idx, nl, pair, poses)
        out = _w_probe(batch.model, batch.fields, batch.aux, data0, jnp.asarray(p), jnp.asarray(q))
        depth[idx] = np.asarray(out)[: len(idx)]
    depth[~np.isfinite(depth)] = 0.0
    park = np.array([0, 0, FAR, 1.0, 0, 0, 0])
    lanes = _lane_state(_w_posed(data0, jnp.asarray(np.tile(park, (nl, 1)), jnp.float32)), nl)

    def advance(lanes, refill, new_q, new_p, seg):
        return _w_advance(
            batch.model,
            batch.fields,
            batch.aux,
            data0,
            lanes,
            jnp.asarray(refill),
            jnp.asarray(new_q, jnp.float32),
            jnp.asarray(new_p),
            seg,
            config,
        )

    return _drain(poses, pair, depth, config, scenes[0].physics.timestep, nl, lanes, advance, park)


@functools.partial(jax.jit, static_argnames=("push", "free", "every"))
def _w_takeoff(model, fields, aux, data0, pair, qpos, force, push, free, every):
    """[L] pulls (warp): removed if the object's box separates from the support's."""
    COMPILES["warp_takeoff"] += 1
    f = jax.tree.map(lambda x: x[pair], fields)
    ax = jax.tree.map(lambda x: x[pair], aux)
    d = _w_posed(data0, qpos)

    def step(carry, t):
        d, removed = carry
        push_f = jnp.where(t < push, force, 0.0)
        xfrc = d.xfrc_applied.at[:, W_OBJECT_BODY, :3].set(push_f)
        d = jax.vmap(lambda f, d: mjx.step(_w_models(model, f), d))(f, d.replace(xfrc_applied=xfrc))
        check = ((t + 1) % every == 0) | (t == push + free - 1)
        q = d.qpos[:, :7]
        ok = jnp.all(jnp.isfinite(q), 1) & (jnp.linalg.norm(jnp.nan_to_num(q[:, :3]), axis=1) < 1e3)
        far = jnp.array([0, 0, 1e3, 1.0, 0, 0, 0])
        sep = ~ok | ~jax.vmap(lambda a, q: _overlap(a, q, 0.0))(ax, jnp.where(ok[:, None], q, far))
        return (d, removed | (check & sep)), None

    init = (d, jnp.zeros(qpos.shape[0], bool))
    (_, removed), _ = jax.lax.scan(step, init, jnp.arange(push + free))
    return removed


def takeoff_warp(scenes, pair, poses, config, settings, materials=None) -> TakeoffResult:
    return _sequential(takeoff_warp_removed(scenes, pair, poses, config, settings, materials))


def warp_material(fields: dict, mass, friction) -> dict:
    """Per-pair fields with the object's mass (inertia scaled along) and every geom's
    sliding friction replaced, as :func:`sim.kernels.with_material` does for one pair.
    ``mass`` / ``friction``: None (keep), a scalar, or one value per pair [P]."""
    fields = dict(fields)
    n = fields["body_mass"].shape[0]
    if friction is not None:
        fr = jnp.broadcast_to(jnp.asarray(friction, fields["geom_friction"].dtype), (n,))
        fields["geom_friction"] = fields["geom_friction"].at[:, :, 0].set(fr[:, None])
    if mass is not None:
        ms = jnp.broadcast_to(jnp.asarray(mass, fields["body_mass"].dtype), (n,))
        factor = ms / fields["body_mass"][:, W_OBJECT_BODY]
        fields["body_mass"] = fields["body_mass"].at[:, W_OBJECT_BODY].set(ms)
        fields["body_subtreemass"] = fields["body_subtreemass"].at[:, W_OBJECT_BODY].set(ms)
        fields["body_inertia"] = (
            fields["body_inertia"].at[:, W_OBJECT_BODY].multiply(factor[:, None])
        )
        # what mj_setConst gives (kernels.with_material): mass and inertia scale together, so
        # every inverse weight of the free body scales by 1 / factor (checked to 1e-12)
        fields["body_invweight0"] = (
            fields["body_invweight0"].at[:, W_OBJECT_BODY].divide(factor[:, None])
        )
        fields["dof_invweight0"] = fields["dof_invweight0"] / factor[:, None]
    return fields


def takeoff_warp_removed(scenes, pair, poses, config, settings, materials=None) -> np.ndarray:
    """[B, 11] outcome of every direction on its own (all pushed in parallel).

    ``materials``: None (``config.mass`` / ``config.friction`` for every pair) or per-pair
    ``(mass [P], friction [P])`` arrays, P = len(scenes)."""
    batch = warp_batch_for(scenes, settings)
    mass, friction = config.mass, config.friction
    if materials is not None:
        mass, friction = (np.asarray(x, float).reshape(-1) for x in materials)
        if len(mass) != len(scenes) or len(friction) != len(scenes):
            raise ValueError(
                f"materials need one mass and one friction per scene ({len(scenes)}), "
                f"got {len(mass)} and {len(friction)}"
            )
    fields = warp_material(batch.fields, mass, friction)
    nl = settings.lanes
    data0 = _warp_data0(batch, nl)
    dt = scenes[0].physics.timestep
    push, free = round(config.push_time / dt), round(config.free_time / dt)
    every = max(1, round(config.check_every / dt))
    forces = kernels.takeoff_forces(poses, config).reshape(-1, 3)
    rep_pose = np.repeat(poses, 11, axis=0)
    rep_pair = np.repeat(pair, 11)
    removed = np.zeros(len(rep_pose), bool)
    for idx in _chunks(len(rep_pose), nl):
        p, q, fo = _padded(idx, nl, rep_pair, rep_pose, forces)
        out = _w_takeoff(
            batch.model, fields, batch.aux, data0, jnp.asarray(p),
            jnp.asarray(q, jnp.float32), jnp.asarray(fo, jnp.float32), push, free, every,
        )  # fmt: skip
        removed[idx] = np.asarray(out)[: len(idx)]
    return removed.reshape(len(poses), 11)
