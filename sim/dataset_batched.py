"""Shard-level batched dataset generation: the physics of every pair of a shard in one call.

:func:`sim.dataset.generate_pair` labels one pair at a time, one kernel call per batch of
candidates of that pair. On a GPU, MJX's MuJoCo Warp impl is fast only when many pairs
share a call (one union model, :func:`sim.mjx_warp.build_warp_batch`), so
:func:`shard_records_batched` runs the pairs of a shard *together*, in the same steps as
``generate_pair`` and with the same random streams:

1. rounds of candidates: every pair still short of ``2 * max_stable`` stable poses and
   under ``max_candidates`` draws its next batch exactly as ``generate_pair`` does (its own
   ``default_rng([seed, 1])``), and one stability call labels the batches of all of them;
2. per pair, mass and friction from the same rng after its candidate loop; one take-off
   call for the stable poses of all pairs, each with its pair's material;
3. near misses: candidates and the contact query per pair on the CPU, the short rollouts
   of the close candidates of all pairs in one stability call (``negative_time``);
4. collision labels and camera views per pair on the CPU, as ``generate_pair``.

:func:`generate_groups` runs several shards per device model and moves step 4 to a process
pool, so that the CPU stage of one group overlaps the GPU physics of the next (the
generator's ``--backend mjx --shards-per-call N --workers W``).

The records have exactly the keys of ``generate_pair``'s and go through
:func:`sim.dataset_io.pack_shard` unchanged. With ``settings=None`` the physics runs on the CPU
reference pair by pair, over exactly the poses ``generate_pair`` would give it in the same
order, so the records equal ``_shard_records(..., backend="cpu")`` bit for bit (tested);
with the Warp impl labels differ only where the engines do.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from sim import dataset, dataset_io, kernels
from sim.assets.base import Asset
from sim.dataset import DatasetConfig
from sim.library import Library
from sim.mjx_kernels import MJXSettings
from sim.scene import Scene, build_scene

# the benchmark's setting on one H100 (docs/benchmarks.md): 8192 worlds at once
DEFAULT_SETTINGS = MJXSettings(impl="warp", lanes=8192, chunk=4096)


# ----------------------------------------------------------------------------- physics


def _stability(
    scenes: Sequence[Scene],
    pair: np.ndarray,
    poses: np.ndarray,
    config: kernels.StabilityConfig,
    settings: MJXSettings | None,
) -> kernels.StabilityResult:
    """Stability of ``poses`` [B, 7], pose i on ``scenes[pair[i]]``: one
    :func:`sim.mjx_kernels.stability_many` call, or (``settings=None``) one CPU
    :func:`sim.kernels.stability` call per pair over that pair's poses in order."""
    pair = np.asarray(pair, np.int32)
    if settings is not None:
        from sim import mjx_kernels

        return mjx_kernels.stability_many(scenes, pair, poses, config, settings)
    n = len(poses)
    out = kernels.StabilityResult(
        np.zeros(n, bool), np.zeros(n, np.int8), np.zeros((n, 7)), np.zeros(n), np.zeros(n)
    )
    for p in np.unique(pair):
        rows = np.flatnonzero(pair == p)
        res = kernels.stability(scenes[p], poses[rows], config)
        for dst, src in zip(out, res):
            dst[rows] = src
    return out


def _removable(
    scenes: Sequence[Scene],
    pair: np.ndarray,
    poses: np.ndarray,
    config: kernels.TakeoffConfig,
    mass: np.ndarray,
    friction: np.ndarray,
    settings: MJXSettings | None,
) -> np.ndarray:
    """[B] take-off of ``poses`` [B, 7] on ``scenes[pair[i]]`` with per-pair ``mass`` [P]
    and ``friction`` [P] (generate_pair: ``kernels.takeoff`` with the pair's material).
    Warp: one ``takeoff_many`` call with per-pair materials; the JAX impl: one call per
    pair (its stacked model takes one material); None: the CPU reference per pair."""
    pair = np.asarray(pair, np.int32)
    out = np.zeros(len(poses), bool)
    if settings is not None and settings.impl == "warp":
        from sim import mjx_kernels

        res = mjx_kernels.takeoff_many(
            scenes, pair, poses, config, settings, materials=(mass, friction)
        )
        return res.removable
    for p in np.unique(pair):
        rows = np.flatnonzero(pair == p)
        cfg = dataclasses.replace(config, mass=float(mass[p]), friction=float(friction[p]))
        if settings is None:
            out[rows] = kernels.takeoff(scenes[p], poses[rows], cfg).removable
        else:
            from sim import mjx_kernels

            sub = np.full(len(rows), p, np.int32)
            out[rows] = mjx_kernels.takeoff_many(scenes, sub, poses[rows], cfg, settings).removable
    return out


def release(scenes: Sequence[Scene], settings: MJXSettings | None) -> None:
    """Forget the device-side model built for ``scenes`` (and its Warp lane data): the
    MJX kernels cache one per list of scenes, which a run over many shards would otherwise
    keep alive, one per shard. Both caches are dropped together: the lane-data cache is
    keyed by the batch's ``id``, which may be reused once the batch is freed."""
    if settings is None:
        return
    from sim import mjx_kernels, mjx_warp

    key = (tuple(id(s) for s in scenes), settings)
    mjx_kernels._BATCHES.pop(key, None)
    entry = mjx_warp._WARP_BATCHES.pop(key, None)
    if entry is not None:
        for k in [k for k in mjx_warp._WARP_DATA if k[0] == id(entry[0])]:
            del mjx_warp._WARP_DATA[k]


# ----------------------------------------------------------------------------- a shard


class ShardRun(NamedTuple):
    records: list[dict]  # one generate_pair-like record per pair of the chunk
    chunk: list[int]  # pair indices
    ids: list[tuple[int, int, int]]  # (object id, support id, pair seed) per pair
    candidate_status: list[np.ndarray]  # per pair [n_candidates] int8 stability status
    kernel_calls: dict  # name -> physics calls made for the whole shard


def label_pairs_batched(
    objs: Sequence[Asset],
    supports: Sequence[Asset],
    seeds: Sequence[int],
    config: DatasetConfig,
    settings: MJXSettings | None = DEFAULT_SETTINGS,
) -> tuple[list[dict], list[np.ndarray], dict]:
    """``[generate_pair(objs[p], supports[p], seeds[p], config) for p]`` with the physics of
    all pairs batched: returns (records, per-pair candidate statuses [n_candidates], calls).

    ``settings``: MJX settings (``impl="warp"`` is the one that batches pairs of any shape
    into one model); None runs the CPU reference per pair (equal to ``generate_pair``).
    The device model of the pairs is built on the first call and released at the end.
    """
    scenes = [build_scene(o, s) for o, s in zip(objs, supports)]
    try:
        return _label(scenes, objs, supports, seeds, config, settings)
    finally:
        release(scenes, settings)


def _label(scenes, objs, supports, seeds, config, settings):
    """Body of :func:`label_pairs_batched`, steps 1-4 of the module docstring."""
    physics, kept, status, calls = label_physics(scenes, objs, supports, seeds, config, settings)
    records = [
        dict(**ph, **cpu_stage(scenes[p], objs[p], supports[p], seeds[p], kept[p], config))
        for p, ph in enumerate(physics)
    ]
    return records, status, calls


def label_physics(scenes, objs, supports, seeds, config, settings):
    """Steps 1-3 of the module docstring for the pairs of ``scenes``: (per pair the record
    fields from the physics, per pair the kept poses (float64, what step 4 needs), per pair
    the candidate statuses, kernel-call counts)."""
    n_pairs = len(objs)
    rngs = [np.random.default_rng([seed, 1]) for seed in seeds]
    stable: list[list[np.ndarray]] = [[] for _ in range(n_pairs)]
    statuses: list[list[np.ndarray]] = [[] for _ in range(n_pairs)]
    counts = [dict(n_candidates=0, n_penetrating=0, n_fallen=0, n_stable_raw=0) for _ in objs]
    calls = dict(stability=0, takeoff=0, near_miss=0)

    # 1. rounds: generate_pair's candidate loop, all pairs still looping in one call
    while True:
        batch, owner = [], []
        for p in range(n_pairs):
            c = counts[p]
            if c["n_candidates"] < config.max_candidates and len(stable[p]) < 2 * config.max_stable:
                n = min(config.batch, config.max_candidates - c["n_candidates"])
                batch.append(dataset.draw_candidates(objs[p], supports[p], rngs[p], n, config))
                owner.append(np.full(n, p, np.int32))
        if not batch:
            break
        pair = np.concatenate(owner)
        with dataset._timed("stability"):
            res = _stability(scenes, pair, np.concatenate(batch), config.stability, settings)
        calls["stability"] += 1
        for p in np.unique(pair):
            rows = pair == p
            st = res.status[rows]
            c = counts[p]
            c["n_candidates"] += int(rows.sum())
            c["n_penetrating"] += int((st == kernels.PENETRATING).sum())
            c["n_fallen"] += int((st == kernels.FALLEN).sum())
            c["n_stable_raw"] += int(res.stable[rows].sum())
            stable[p].extend(res.settled_pose[rows][res.stable[rows]])
            statuses[p].append(st)

    # 2. material after the loop (same rng), then one take-off call for every pair
    stable_arr = [
        np.asarray(s, dtype=float).reshape(-1, 7)[: 2 * config.max_stable] for s in stable
    ]
    drawn = [(r.uniform(*config.mass_range), r.uniform(*config.friction_range)) for r in rngs]
    mass, friction = (np.array([float(d[j]) for d in drawn]) for j in (0, 1))
    removable = [np.zeros(len(s), dtype=bool) for s in stable_arr]
    take_pair = np.concatenate([np.full(len(s), p, np.int32) for p, s in enumerate(stable_arr)])
    if len(take_pair):
        with dataset._timed("takeoff"):
            rem = _removable(
                scenes,
                take_pair,
                np.concatenate(stable_arr),
                config.takeoff,
                mass,
                friction,
                settings,
            )
        calls["takeoff"] += 1
        removable = [rem[take_pair == p] for p in range(n_pairs)]
    kept = [
        dataset_io.dequantise_poses(*dataset_io.quantise_poses(s[r][: config.max_stable])).astype(
            float
        )
        for s, r in zip(stable_arr, removable)
    ]

    # 3. near misses: CPU contact queries per pair, one short rollout call for all pairs
    t_neg = time.perf_counter()
    close = [
        dataset.near_miss_close(sc, k, seed, config) for sc, k, seed in zip(scenes, kept, seeds)
    ]
    roll_pair = np.concatenate([np.full(len(i), p, np.int32) for p, (_, i) in enumerate(close)])
    negative_kept = [np.zeros(len(c), dtype=bool) for c, _ in close]
    if len(roll_pair):
        cfg = dataclasses.replace(config.stability, duration=config.negative_time)
        poses = np.concatenate([c[i] for c, i in close])
        res = _stability(scenes, roll_pair, poses, cfg, settings)
        calls["near_miss"] += 1
        for p, (c, i) in enumerate(close):
            rows = roll_pair == p
            negative_kept[p] = dataset.near_miss_kept(
                c, i, res.status[rows], res.settled_pose[rows], config
            )
    dataset.STAGE_SECONDS["negatives"] += time.perf_counter() - t_neg

    physics = _physics_records(counts, removable, mass, friction, kept, negative_kept)
    status = [np.concatenate(s) if s else np.zeros(0, np.int8) for s in statuses]
    return physics, kept, status, calls


def _physics_records(counts, removable, mass, friction, kept, negative_kept) -> list[dict]:
    """Per pair, the record fields that come from the physics (steps 1-3), in record order."""
    return [
        dict(
            **counts[p],
            n_takeoff_rejected=int((~removable[p]).sum()),
            mass=float(mass[p]),
            friction=float(friction[p]),
            stable_poses=kept[p].astype(np.float32),
            negative_kept=negative_kept[p],
        )
        for p in range(len(counts))
    ]


def cpu_stage(
    scene: Scene, obj: Asset, support: Asset, seed: int, kept: np.ndarray, config: DatasetConfig
) -> dict:
    """Step 4 for one pair on the CPU: collision labels and the camera views, exactly as
    ``generate_pair`` computes them (``kept``: the pair's kept stable poses, float64)."""
    with dataset._timed("collision_labels"):
        col_kept, col_label = dataset.collision_labels(scene, obj, support, seed, config)
    with dataset._timed("views"):
        obj_eye, sup_eye = dataset.choose_views(scene, kept, seed, config)
    return dict(
        collision_kept=col_kept,
        collision_label=col_label,
        object_eye=obj_eye.astype(np.float32),
        support_eye=sup_eye.astype(np.float32),
    )


def shard_run_batched(
    library: Library,
    config: DatasetConfig,
    pairs,
    rec: dict,
    k: int,
    settings: MJXSettings | None = DEFAULT_SETTINGS,
) -> ShardRun:
    """:func:`shard_records_batched` plus per-candidate statuses and kernel-call counts."""
    chunk, ids, objs, sups, seeds = dataset.shard_inputs(library, config, pairs, rec, k)
    records, status, calls = label_pairs_batched(objs, sups, seeds, config, settings)
    return ShardRun(records, chunk, ids, status, calls)


def shard_records_batched(
    library: Library,
    config: DatasetConfig,
    pairs,
    rec: dict,
    k: int,
    settings: MJXSettings | None = DEFAULT_SETTINGS,
) -> tuple[list[dict], list[int], list[tuple[int, int, int]]]:
    """Drop-in for :func:`sim.dataset._shard_records`: (records, chunk, ids) of shard ``k``,
    the physics of all its pairs batched (module docstring). ``settings=None``: the CPU
    reference, identical to ``_shard_records(..., backend="cpu")``."""
    run = shard_run_batched(library, config, pairs, rec, k, settings)
    return run.records, run.chunk, run.ids


# ----------------------------------------------------------------------------- many shards


def _cpu_stage_job(job: tuple) -> tuple[dict, dict]:
    """Pool side of :func:`generate_groups`: step 4 of one pair in a worker process set up
    by ``sim.dataset._worker_init`` (which holds the asset library); returns (fields, stage
    seconds of this job)."""
    obj_name, sup_name, seed, kept, config = job
    lib = dataset._WORKER["library"]
    dataset.STAGE_SECONDS.clear()
    obj, sup = lib.objects[obj_name], lib.supports[sup_name]
    with dataset._timed("scene"):
        scene = build_scene(obj, sup)
    out = cpu_stage(scene, obj, sup, seed, kept, config)
    return out, dict(dataset.STAGE_SECONDS)


def generate_groups(
    library: Library,
    config: DatasetConfig,
    pairs,
    rec: dict,
    groups: Sequence[Sequence[int]],
    save: Callable[[int, list[dict], list[int], list[tuple[int, int, int]]], None],
    settings: MJXSettings | None = DEFAULT_SETTINGS,
    pool=None,
    deadline: float | None = None,
    stage_seconds: dict | None = None,
) -> int:
    """Label the shards of each group (a list of shard indices) with one device model per
    group, and ``save(k, records, chunk, ids)`` every shard; returns the shards saved.

    With a ``pool`` (``multiprocessing`` pool whose workers ran ``sim.dataset._worker_init``)
    step 4 (collision labels, views) of group g runs in the pool while this process labels
    group g+1 on the GPU; without one it runs here. Records equal
    :func:`shard_records_batched`'s shard by shard (same physics calls per group: the rounds
    of a group batch all its pairs; with ``settings=None`` bit-equal to the CPU path, tested).
    ``deadline``: start no group after this time (groups under way are finished).
    ``stage_seconds``: a Counter that receives the time per stage (pool seconds included).
    """
    saved = 0
    pending = None

    def finish(item) -> None:
        nonlocal saved
        shards, physics, fields = item
        if pool is not None:
            got = fields.get()
            fields = [f for f, _ in got]
            if stage_seconds is not None:
                for _, sec in got:
                    stage_seconds.update(sec)
        p = 0
        for k, chunk, ids in shards:
            records = [dict(**physics[p + j], **fields[p + j]) for j in range(len(chunk))]
            p += len(chunk)
            save(k, records, chunk, ids)
            saved += 1

    for group in groups:
        if deadline is not None and time.time() > deadline:
            break
        dataset.STAGE_SECONDS.clear()
        shards, objs, sups, seeds = [], [], [], []
        for k in group:
            chunk, ids, o, s, sd = dataset.shard_inputs(library, config, pairs, rec, k)
            shards.append((k, chunk, ids))
            objs += o
            sups += s
            seeds += sd
        with dataset._timed("scene"):
            scenes = [build_scene(o, s) for o, s in zip(objs, sups)]
        try:
            physics, kept, _, _ = label_physics(scenes, objs, sups, seeds, config, settings)
        finally:
            release(scenes, settings)
        if pool is not None:
            jobs = [
                (o.name, s.name, sd, kp, config) for o, s, sd, kp in zip(objs, sups, seeds, kept)
            ]
            fields = pool.map_async(_cpu_stage_job, jobs, chunksize=1)
        else:
            fields = [
                cpu_stage(sc, o, s, sd, kp, config)
                for sc, o, s, sd, kp in zip(scenes, objs, sups, seeds, kept)
            ]
        if stage_seconds is not None:  # this process's seconds for the group, counted once
            stage_seconds.update(dataset.STAGE_SECONDS)
            dataset.STAGE_SECONDS.clear()
        if pending is not None:
            finish(pending)  # the previous group's CPU stage ran while this group's physics did
        pending = (shards, physics, fields)
    if pending is not None:
        finish(pending)
    return saved
