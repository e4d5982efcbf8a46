"""The hanging dataset engine: per (object, support) pair, stable poses that can be taken off,
near-miss negatives, collision-labelled poses, one camera view per body, contact annotations.

A dataset folder holds ``recipe.json`` (the config, library config, versions: everything
needed to rebuild), ``shards/shard_NNNNN.npz`` (the labels of ``shard_size`` consecutive
pairs) and ``dataset_card.json`` / ``.md``; the format is described in :mod:`sim.dataset_io`.
Heavy arrays (partial clouds, contact maps, contact pairs) are derived from the labels by
:func:`derive_pair` (deterministic ray casting on the CPU) and cached by the caller.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import hashlib
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from sim import annotate, atomic, camera, dataset_io, kernels, proposals
from sim import workers as workers_mod
from sim.assets.base import Asset
from sim.library import Library, LibraryConfig, build_library, check_split
from sim.scene import Scene, build_scene

# Version of the physics behind the labels. Shards of another version are never mixed in:
# 1 = take-off with a changed object mass but stale constraint weights (objects could pass
# through closed supports at masses other than 0.5 kg); 2 = kernels.with_material runs
# mj_setConst; 3 = the wall is a solid 0.5 m block (sim.scene PhysicsConfig.wall_thickness),
# not a 2 cm slab a strap could pass through (the paper dataset was relabelled pair by pair
# with experiments.relabel).
LABELS_VERSION = 3


@dataclasses.dataclass(frozen=True)
class DatasetConfig:
    library: LibraryConfig = LibraryConfig()
    max_objects_per_category: int | None = None  # None: all of the library's objects
    max_supports_per_family: int | None = None
    max_pairs: int | None = None  # a seeded random subset of the pairs (for measurements)
    max_candidates: int = 10_000  # original: up to 10,000 candidates per pair
    batch: int = 512  # candidates per kernel call
    max_stable: int = 50  # original: at most 50 stable poses per pair
    max_negatives: int = 50  # original: at most 50 near misses per pair
    negative_candidates: int = 200  # perturbed stable poses tried as near misses
    negative_shift: tuple[float, float] = (0.01, 0.04)  # m, perturbation of a stable pose
    negative_turn: float = 0.3  # rad, largest perturbation angle
    negative_gap: float = 0.01  # m; original: mesh distance in (0, 1 cm] at the start
    negative_time: float = 0.5  # s; original 50 steps of 1/100 s
    negative_moved: float = 0.3  # m; original: a near miss falls or moves more than 0.3 m
    hang_fraction: float = 0.75  # share of candidates from hang-feature threading (rest uniform)
    n_collision: int = 1000  # original: 1000 random poses per pair for collision labels
    collision_free_within: float = 0.02  # m; farther poses are dropped (original 2 cm)
    collision_expand: float = 1.5  # support box grown by object extent / 1.5 (original)
    n_views: int = 4  # candidate views per body; the one seeing most contact mass is kept
    camera: camera.CameraConfig = camera.CameraConfig()
    mass_range: tuple[float, float] = (0.3, 0.8)  # kg, take-off test (original)
    friction_range: tuple[float, float] = (0.1, 0.5)  # take-off test (original)
    shard_size: int = 16  # pairs per shard file
    seed: int = 0
    stability: kernels.StabilityConfig = kernels.StabilityConfig()
    takeoff: kernels.TakeoffConfig = kernels.TakeoffConfig()


PRESETS = {
    # a few minutes on 2 CPU cores: two objects per category (one held out, one for
    # training) x one support per family
    "demo": DatasetConfig(
        max_objects_per_category=2,
        max_supports_per_family=1,
        max_candidates=256,
        batch=256,
        max_stable=10,
        max_negatives=10,
        negative_candidates=40,
        n_collision=100,
        n_views=3,
        camera=camera.CameraConfig(width=320, height=240, n_points=2048),
        shard_size=8,
    ),
    # seconds on a CPU, for tests and smoke runs: 2 categories x 2 families, 4 pairs
    "tiny": DatasetConfig(
        library=LibraryConfig(
            n_objects=22,
            n_supports=10,
            object_categories=("mug", "wrench"),
            support_families=("single_rod_hook", "towel_bar"),
        ),
        max_objects_per_category=1,
        max_supports_per_family=1,
        max_candidates=128,
        batch=128,
        max_stable=4,
        max_negatives=4,
        negative_candidates=40,
        n_collision=40,
        n_views=2,
        camera=camera.CameraConfig(width=120, height=90, n_points=256),
        shard_size=2,
    ),
    # the paper's scale: 340 objects x 72 supports; 32-pair shards keep the per-file
    # overhead of npz small (labels ~1.2 kB per pair) while losing little when killed
    # max_candidates 2048 instead of the original's 10,000: the original sampled uniformly
    # (0.8% stable); 75% of these candidates are hang-threaded (57.5% stable on average),
    # and pairs that reach the cap are the ones where neither sampler finds hangs, which
    # took 95% of the rollout time at 10,000 (docs/dataset.md, "Candidate budget").
    "paper": DatasetConfig(shard_size=32, max_candidates=2048),
}


# ----------------------------------------------------------------------------- pairs


def pair_list(library: Library, config: DatasetConfig) -> list[tuple[str, str, str]]:
    """Deterministic (object, support, split) list. A pair is "test" if its object or its
    support is held out, "train" if both are training assets."""

    def pick(table: dict[str, Asset], limit: int | None, test_first: bool) -> list[str]:
        by_group: dict[str, list[str]] = {}
        for name in sorted(table):
            by_group.setdefault(table[name].category, []).append(name)
        chosen = []
        for g, names in enumerate(by_group.values()):
            if limit is None:
                chosen += names
            else:  # subsets keep both splits: every other group starts from its test assets
                train = [n for n in names if library.split_of(n) == "train"]
                test = [n for n in names if library.split_of(n) == "test"]
                first, second = (test, train) if (g % 2 and test_first) else (train, test)
                mix = (
                    [x for pair in zip(first, second) for x in pair]
                    + first[len(second) :]
                    + second[len(first) :]
                )
                chosen += mix[:limit]
        return sorted(chosen)

    objs = pick(library.objects, config.max_objects_per_category, test_first=True)
    sups = pick(library.supports, config.max_supports_per_family, test_first=False)
    pairs = []
    for o in objs:
        for s in sups:
            split = "train" if library.split_of(o) == library.split_of(s) == "train" else "test"
            pairs.append((o, s, split))
    if config.max_pairs is not None and config.max_pairs < len(pairs):
        keep = np.random.default_rng([config.seed, 7]).choice(
            len(pairs), config.max_pairs, replace=False
        )
        pairs = [pairs[i] for i in sorted(keep)]
    return pairs


def pair_seed(base: int, obj: str, sup: str) -> int:
    return int.from_bytes(hashlib.sha256(f"{base}/{obj}/{sup}".encode()).digest()[:8], "little")


def collision_poses(obj: Asset, support: Asset, seed: int, config: DatasetConfig) -> np.ndarray:
    """The pair's collision-label candidates [n_collision, 7], regenerated from its seed."""
    rng = np.random.default_rng([seed, 2])
    grow = obj.extents.max() / config.collision_expand  # original: box grown by extent / 1.5
    cfg = proposals.ProposalConfig(uniform_margin=grow, uniform_up=0.0)
    return proposals.uniform_poses(obj, support, config.n_collision, rng, cfg)


# ----------------------------------------------------------------------------- one pair


# Seconds spent per stage of generate_pair in this process (the dataset card's "time per
# stage"); process workers send theirs back with each shard.
STAGE_SECONDS: collections.Counter = collections.Counter()


class _timed:
    def __init__(self, stage: str):
        self.stage = stage

    def __enter__(self):
        self.t0 = time.perf_counter()

    def __exit__(self, *exc):
        STAGE_SECONDS[self.stage] += time.perf_counter() - self.t0


def generate_pair(
    obj: Asset, support: Asset, seed: int, config: DatasetConfig, backend: str = "cpu"
) -> dict:
    """Labels of one pair (see the module docstring for the fields)."""
    rng = np.random.default_rng([seed, 1])
    with _timed("scene"):
        scene = build_scene(obj, support)
    stable = []
    counts = dict(n_candidates=0, n_penetrating=0, n_fallen=0, n_stable_raw=0)
    while counts["n_candidates"] < config.max_candidates and len(stable) < 2 * config.max_stable:
        n = min(config.batch, config.max_candidates - counts["n_candidates"])
        with _timed("proposals"):
            cand = draw_candidates(obj, support, rng, n, config)
        with _timed("stability"):
            res = kernels.stability(scene, cand, config.stability, backend=backend)
        counts["n_candidates"] += n
        counts["n_penetrating"] += int((res.status == kernels.PENETRATING).sum())
        counts["n_fallen"] += int((res.status == kernels.FALLEN).sum())
        counts["n_stable_raw"] += int(res.stable.sum())
        stable.extend(res.settled_pose[res.stable])
    stable_arr = np.asarray(stable, dtype=float).reshape(-1, 7)[: 2 * config.max_stable]
    mass = float(rng.uniform(*config.mass_range))
    friction = float(rng.uniform(*config.friction_range))
    removable = np.zeros(len(stable_arr), dtype=bool)
    if len(stable_arr):
        take_cfg = dataclasses.replace(config.takeoff, mass=mass, friction=friction)
        with _timed("takeoff"):
            removable = kernels.takeoff(scene, stable_arr, take_cfg, backend=backend).removable
    kept = stable_arr[removable][: config.max_stable]
    # the stored (quantised) poses are what everything downstream sees, negatives included
    kept = dataset_io.dequantise_poses(*dataset_io.quantise_poses(kept)).astype(float)
    with _timed("negatives"):
        negative_kept = near_misses(scene, kept, seed, config, backend)
    with _timed("collision_labels"):
        collision_kept, colliding = collision_labels(scene, obj, support, seed, config)
    # eyes: the view of each body that sees the most contact-map mass at the stable poses
    with _timed("views"):
        obj_eye, sup_eye = choose_views(scene, kept, seed, config)
    return dict(
        **counts,
        n_takeoff_rejected=int((~removable).sum()),
        mass=mass,
        friction=friction,
        stable_poses=kept.astype(np.float32),
        negative_kept=negative_kept,
        collision_kept=collision_kept,
        collision_label=colliding,
        object_eye=obj_eye.astype(np.float32),
        support_eye=sup_eye.astype(np.float32),
    )


def draw_candidates(
    obj: Asset, support: Asset, rng: np.random.Generator, n: int, config: DatasetConfig
) -> np.ndarray:
    """[n, 7] the next batch of candidates of a pair, drawn from its rng exactly as one
    iteration of ``generate_pair``'s loop draws them: ``round(n * hang_fraction)``
    hang-threaded poses (when both assets have hang features), then uniform ones."""
    has_features = bool(obj.features) and bool(support.features)
    n_hang = int(round(n * config.hang_fraction)) if has_features else 0
    return np.concatenate(
        [
            proposals.hang_poses(obj, support, n_hang, rng) if n_hang else np.zeros((0, 7)),
            proposals.uniform_poses(obj, support, n - n_hang, rng),
        ]
    )


def near_miss_close(
    scene: Scene, stable_poses: np.ndarray, seed: int, config: DatasetConfig
) -> tuple[np.ndarray, np.ndarray]:
    """First half of :func:`near_misses` (CPU): the pair's
    :func:`~sim.dataset.negative_candidates` [N, 7] and the indices [M] of those that start
    within ``negative_gap`` of the support without touching it (to be rolled out)."""
    cand = negative_candidates(stable_poses, seed, config)
    if len(cand) == 0:
        return cand, np.zeros(0, np.int64)
    con = kernels.contact_query(
        scene, cand, kernels.ContactConfig(distance_cutoff=config.negative_gap + 1e-3)
    )
    close = (con.penetration == 0) & (con.distance > 0) & (con.distance <= config.negative_gap)
    return cand, np.flatnonzero(close)


def near_miss_kept(
    cand: np.ndarray,
    idx: np.ndarray,
    status: np.ndarray,
    settled: np.ndarray,
    config: DatasetConfig,
) -> np.ndarray:
    """Second half of :func:`near_misses`: [N] bool, the close candidates
    ``cand[idx]`` whose short rollout (``status`` [M], ``settled`` poses [M, 7]) fell,
    diverged or moved more than ``negative_moved``; at most ``max_negatives`` marked."""
    kept = np.zeros(len(cand), dtype=bool)
    if len(idx) == 0:
        return kept
    moved = np.linalg.norm(settled[:, :3] - cand[idx, :3], axis=1)
    miss = (
        (status == kernels.FALLEN) | (status == kernels.DIVERGED) | (moved > config.negative_moved)
    )
    kept[idx[miss][: config.max_negatives]] = True
    return kept


def collision_labels(
    scene: Scene, obj: Asset, support: Asset, seed: int, config: DatasetConfig
) -> tuple[np.ndarray, np.ndarray]:
    """(collision_kept [n_collision], collision_label [n_collision]) of the pair's
    :func:`~sim.dataset.collision_poses`, as ``generate_pair`` computes them (CPU): colliding
    poses, plus free ones within ``collision_free_within`` of the support."""
    col_poses = collision_poses(obj, support, seed, config)
    con = kernels.contact_query(
        scene, col_poses, kernels.ContactConfig(distance_cutoff=config.collision_free_within + 1e-3)
    )
    colliding = con.penetration > 0
    free = (~colliding) & (con.distance <= config.collision_free_within)
    return colliding | free, colliding


def negative_candidates(stable_poses: np.ndarray, seed: int, config: DatasetConfig) -> np.ndarray:
    """[negative_candidates, 7] perturbed copies of the (stored) stable poses, regenerated from
    the pair seed: a random stable pose, shifted 1-4 cm in a random direction and turned by
    up to 0.3 rad about a random axis. Empty if there are no stable poses."""
    from scipy.spatial.transform import Rotation

    if len(stable_poses) == 0:
        return np.zeros((0, 7))
    rng = np.random.default_rng([seed, 6])
    n = config.negative_candidates
    base = np.asarray(stable_poses, float)[rng.integers(len(stable_poses), size=n)]
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    shift = direction * rng.uniform(*config.negative_shift, size=(n, 1))
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    turn = Rotation.from_rotvec(axis * rng.uniform(0, config.negative_turn, size=(n, 1)))
    quat = (turn * Rotation.from_quat(np.roll(base[:, 3:], -1, axis=1))).as_quat()
    return np.concatenate([base[:, :3] + shift, np.roll(quat, 1, axis=1)], axis=1)


def near_misses(
    scene, stable_poses: np.ndarray, seed: int, config: DatasetConfig, backend: str = "cpu"
) -> np.ndarray:
    """[negative_candidates] bool: which :func:`negative_candidates` are near misses (original:
    start within 1 cm of the support without touching it, then fall or move > 0.3 m within
    0.5 s); at most ``max_negatives`` are marked."""
    cand, idx = near_miss_close(scene, stable_poses, seed, config)
    if len(idx) == 0:
        return np.zeros(len(cand), dtype=bool)
    cfg = dataclasses.replace(config.stability, duration=config.negative_time)
    res = kernels.stability(scene, cand[idx], cfg, backend=backend)
    return near_miss_kept(cand, idx, res.status, res.settled_pose, config)


def choose_views(scene, stable_poses: np.ndarray, seed: int, config: DatasetConfig):
    """Among ``n_views`` random views per body, the one whose cloud carries the most contact
    map mass at the first stable pose (original: the view covering the most contact mass)."""
    obj_eyes, sup_eyes = rank_views(scene, stable_poses, seed, config)
    return obj_eyes[0], sup_eyes[0]


def candidate_views(scene, seed: int, config: DatasetConfig) -> tuple[list, list]:
    """The pair's ``n_views`` candidate camera positions per body (object eyes, support
    eyes), in sampling order (the generator's draws: ``rank_views`` orders the same ones)."""
    rng = np.random.default_rng([seed, 3])
    eyes = [camera.default_eyes(scene, rng, config.camera) for _ in range(max(1, config.n_views))]
    return [e[0] for e in eyes], [e[1] for e in eyes]


def rank_views(scene, stable_poses: np.ndarray, seed: int, config: DatasetConfig):
    """The ``n_views`` candidate views of each body (object eyes, support eyes), each list
    ordered by the contact-map mass its cloud sees at the first stable pose, most first (ties
    keep the sampling order; without stable poses or contacts: the sampling order). The first
    of each is ``choose_views``' answer; the others are the extra views ``derive_pair(view=k)``
    renders."""
    cam = config.camera
    obj_eyes, sup_eyes = candidate_views(scene, seed, config)
    eyes = list(zip(obj_eyes, sup_eyes))
    if len(stable_poses) == 0 or len(eyes) == 1:
        return obj_eyes, sup_eyes
    pose = stable_poses[0].astype(float)
    con = kernels.contact_query(scene, pose[None])
    m = con.mask[0]
    if not m.any():
        return obj_eyes, sup_eyes
    co, cs = annotate.contact_points(con.object_points[0, m], con.support_points[0, m], pose)
    o_mass, s_mass = [], []
    for i, (oe, se) in enumerate(eyes):
        crng = np.random.default_rng([seed, 4, i])
        oc = camera.partial_cloud(scene, "object", oe, crng, cam)
        sc = camera.partial_cloud(scene, "support", se, crng, cam)
        # mass seen: how close the visible cloud comes to the contacts, as soft-map mass
        o_mass.append(_visible_contact_mass(oc.points, co.astype(np.float32)))
        s_mass.append(_visible_contact_mass(sc.points, cs.astype(np.float32)))
    o_order = np.argsort(-np.asarray(o_mass), kind="stable")
    s_order = np.argsort(-np.asarray(s_mass), kind="stable")
    return [obj_eyes[i] for i in o_order], [sup_eyes[i] for i in s_order]


def _other_views(ranked: list, chosen: np.ndarray) -> list[np.ndarray]:
    """``ranked`` eyes without the one equal to ``chosen`` (the first, if none is)."""
    same = [i for i, e in enumerate(ranked) if np.allclose(e, chosen, atol=1e-5)]
    drop = same[0] if same else 0
    return [np.asarray(e, float) for i, e in enumerate(ranked) if i != drop]


def _visible_contact_mass(points: np.ndarray, contacts: np.ndarray, scale: float = 0.01) -> float:
    if len(contacts) == 0:
        return 0.0
    d = np.linalg.norm(points[:, None, :] - contacts[None, :, :], axis=-1).min(0)
    return float(np.exp(-d / scale).sum())


def derive_pair(
    obj: Asset,
    support: Asset,
    record: dict,
    config: DatasetConfig,
    contacts: bool = True,
    view: int = 0,
) -> dict:
    """Heavy arrays of one pair from its labels: clouds with normals (object frame / world
    frame) and, per stable pose, soft contact maps and contact pairs. Deterministic.

    contacts=False skips the contact query and annotation (about half the time): the maps
    are zeros and the contact-pair lists empty; the clouds are the same as with contacts
    (what Stage 1, V and the NCE read).

    view=0: the record's views (the candidate views seeing the most contact mass); view=k: the
    k-th of the other candidate views of each body in sampling order (``candidate_views``;
    1 <= k < ``n_views``): a different view of the same pair for training, drawn like the
    held-out views' candidates but not chosen for its contact coverage."""
    scene = build_scene(obj, support)
    seed = int(record["pair_seed"])
    rng = np.random.default_rng([seed, 5] if view == 0 else [seed, 5, view])
    obj_eye = np.asarray(record["object_eye"], float)
    sup_eye = np.asarray(record["support_eye"], float)
    if view:
        if not 0 < view < max(1, config.n_views):
            raise ValueError(f"view must be in [0, {config.n_views}), got {view}")
        # the other candidates in sampling order (ranking them by contact mass, like the
        # record's choice, would render all n_views of them: ~4x the cost of this derive)
        obj_eyes, sup_eyes = candidate_views(scene, seed, config)
        obj_eye = _other_views(obj_eyes, obj_eye)[view - 1]
        sup_eye = _other_views(sup_eyes, sup_eye)[view - 1]
    oc = camera.partial_cloud(scene, "object", obj_eye, rng, config.camera)
    sc = camera.partial_cloud(scene, "support", sup_eye, rng, config.camera)
    poses = np.asarray(record["stable_poses"], float)
    n, m = len(oc.points), len(sc.points)
    obj_maps = np.zeros((len(poses), n), np.float32)
    sup_maps = np.zeros((len(poses), m), np.float32)
    pairs = []
    if not contacts:
        pairs = [np.zeros((0, 2), np.int32) for _ in range(len(poses))]
    elif len(poses):
        con = kernels.contact_query(scene, poses)
        cfg = annotate.AnnotationConfig()
        graphs = (
            annotate.CloudGraph(oc.points, oc.normals, cfg),
            annotate.CloudGraph(sc.points, sc.normals, cfg),
        )
        for i in range(len(poses)):
            k = con.mask[i]
            ann = annotate.annotate(
                con.object_points[i, k], con.support_points[i, k], poses[i], oc, sc, cfg, graphs
            )
            obj_maps[i], sup_maps[i] = ann.object_map, ann.support_map
            pairs.append(ann.pairs)
    return dict(
        object_points=oc.points,
        object_normals=oc.normals,
        support_points=sc.points,
        support_normals=sc.normals,
        object_contact_maps=obj_maps,
        support_contact_maps=sup_maps,
        contact_pairs=pairs,
    )


# ----------------------------------------------------------------------------- shards


def recipe(config: DatasetConfig, library: Library, pairs, preset: str) -> dict:
    import mujoco

    return {
        "format": dataset_io.FORMAT,
        "labels_version": LABELS_VERSION,
        "preset": preset,
        "config": dataset_io.config_json(config),
        "objects": sorted(library.objects),
        "supports": sorted(library.supports),
        "pairs": [list(p) for p in pairs],
        "versions": {
            "mujoco": mujoco.__version__,
            "numpy": np.__version__,
            "python": platform.python_version(),
        },
    }


def shard_inputs(library: Library, config: DatasetConfig, pairs, rec: dict, k: int):
    """Shard ``k``'s (chunk = pair indices, ids = (object id, support id, seed) per pair,
    objects, supports, seeds)."""
    obj_index = {n: i for i, n in enumerate(rec["objects"])}
    sup_index = {n: i for i, n in enumerate(rec["supports"])}
    chunk = list(range(k * config.shard_size, min((k + 1) * config.shard_size, len(pairs))))
    names = [tuple(pairs[i][:2]) for i in chunk]
    seeds = [pair_seed(config.seed, o, s) for o, s in names]
    ids = [(obj_index[o], sup_index[s], seed) for (o, s), seed in zip(names, seeds)]
    objs = [library.objects[o] for o, _ in names]
    sups = [library.supports[s] for _, s in names]
    return chunk, ids, objs, sups, seeds


def _shard_records(library: Library, config: DatasetConfig, pairs, rec, k: int, backend: str):
    chunk, ids, objs, sups, seeds = shard_inputs(library, config, pairs, rec, k)
    records = [generate_pair(o, s, seed, config, backend) for o, s, seed in zip(objs, sups, seeds)]
    return records, chunk, ids


_WORKER: dict = {}


def _worker_init(config: DatasetConfig, rec: dict, backend: str) -> None:
    kernels.DEFAULT_NTHREAD = 1  # one process per core; rollouts stay single-threaded
    library = build_library(config.library, progress=False)
    pairs = [tuple(p) for p in rec["pairs"]]
    _WORKER.update(library=library, config=config, pairs=pairs, rec=rec, backend=backend)


def _worker_shard(job: tuple[int, str, float | None]) -> tuple[int, int, dict]:
    k, path, deadline = job
    if deadline is not None and time.time() > deadline:
        return k, 0, {}  # too late to start a shard: left for the next run
    STAGE_SECONDS.clear()
    w = _WORKER
    records, chunk, ids = _shard_records(
        w["library"], w["config"], w["pairs"], w["rec"], k, w["backend"]
    )
    atomic.savez(path, **dataset_io.pack_shard(records, chunk, ids))
    return k, len(chunk), dict(STAGE_SECONDS)


def generate(
    config: DatasetConfig,
    out_dir: str | os.PathLike,
    preset: str = "custom",
    backend: str = "cpu",
    progress: bool = True,
    workers: int = 1,
    part: tuple[int, int] = (0, 1),
    stop_after_s: float | None = None,
    shards_per_call: int = 1,
    mjx_settings=None,
    max_shards: int | None = None,
) -> dict:
    """Generate (or resume) the dataset into ``out_dir``; returns the dataset card.

    ``workers`` > 1 runs shards in that many processes (one single-threaded rollout each)
    with the CPU backend; with ``backend="mjx"`` the physics stays in this process (MuJoCo
    Warp, ``shards_per_call`` shards in one device model; ``mjx_settings``: an
    ``MJXSettings``, default ``sim.dataset_batched.DEFAULT_SETTINGS``) and ``workers``
    processes compute the per-pair CPU stage of one group while the GPU labels the next. ``part = (i, n)`` makes this job do only the shards ``k`` with
    ``k % n == i``, so several machines can share one dataset: copy their ``shards/`` into
    one directory and run once more (nothing left to do) to write the card.
    ``stop_after_s``: start no shard after this many seconds (shards already started are
    finished), so a job on a time limit ends with whole shards instead of killed ones.
    ``max_shards``: do at most this many of the shards left (bounded chunks of work, e.g.
    one device model per process with ``backend="mjx"``).
    """
    out = Path(out_dir)
    (out / "shards").mkdir(parents=True, exist_ok=True)
    i_part, n_part = part
    if not (n_part >= 1 and 0 <= i_part < n_part):
        raise ValueError(f"part must be (i, n) with 0 <= i < n, got {part}")
    if shards_per_call < 1:
        raise ValueError(f"shards_per_call must be >= 1, got {shards_per_call}")
    library = build_library(config.library, progress=progress)
    check_split(library)
    pairs = pair_list(library, config)
    rec = recipe(config, library, pairs, preset)
    recipe_path = out / "recipe.json"
    if recipe_path.exists():
        old = json.loads(recipe_path.read_text())
        if old.get("labels_version", 1) != LABELS_VERSION:
            raise ValueError(
                f"{recipe_path} holds labels of version {old.get('labels_version', 1)} "
                f"(this code makes version {LABELS_VERSION}: see sim.dataset.LABELS_VERSION); "
                "regenerate into a new --out"
            )
        diff = dataset_io.config_differences(
            dataset_io.upgrade_config_json(old["config"]), rec["config"]
        )
        if diff or old["pairs"] != rec["pairs"]:
            what = f"config fields {diff}" if diff else "pair list"
            raise ValueError(
                f"{recipe_path} was written for another config ({what} differ); "
                "use a new --out or delete it"
            )
    else:
        atomic.write_text(recipe_path, json.dumps(rec, indent=1))
    n_shards = (len(pairs) + config.shard_size - 1) // config.shard_size
    mine = [k for k in range(n_shards) if k % n_part == i_part]
    todo = [k for k in mine if not (out / "shards" / f"shard_{k:05d}.npz").exists()]
    if max_shards is not None:
        if max_shards < 0:
            raise ValueError(f"max_shards must be >= 0, got {max_shards}")
        todo = todo[:max_shards]
    t0 = time.time()
    done_pairs = 0
    written: list[int] = []  # shards this run wrote (provenance in runs.jsonl)
    total = sum(min(config.shard_size, len(pairs) - k * config.shard_size) for k in mine)
    bar = tqdm(total=total, desc="pairs", unit="pair", disable=not progress, smoothing=0.1)
    bar.update(
        total - sum(min(config.shard_size, len(pairs) - k * config.shard_size) for k in todo)
    )

    def advance(n: int) -> None:
        nonlocal done_pairs
        done_pairs += n
        bar.update(n)
        bar.set_postfix(pairs_per_min=f"{60 * done_pairs / max(time.time() - t0, 1e-9):.1f}")

    deadline = None if stop_after_s is None else time.time() + stop_after_s
    STAGE_SECONDS.clear()
    stage_seconds: collections.Counter = collections.Counter()
    if backend == "mjx":  # every pair of a group of shards in one MuJoCo Warp call per round
        try:
            import warp  # noqa: F401
        except ImportError as e:
            raise ValueError(
                "--backend mjx generates with MuJoCo Warp: install warp-lang "
                "(pip install -e '.[gpu]'); or use --backend cpu"
            ) from e

    def save(k: int, records, chunk, ids) -> None:
        atomic.savez(
            out / "shards" / f"shard_{k:05d}.npz", **dataset_io.pack_shard(records, chunk, ids)
        )
        written.append(k)
        advance(len(chunk))

    interrupted = True
    try:
        if backend == "mjx":
            from sim import dataset_batched

            groups = [todo[i : i + shards_per_call] for i in range(0, len(todo), shards_per_call)]
            settings = mjx_settings or dataset_batched.DEFAULT_SETTINGS
            pool_cm = (  # the per-pair CPU stage of one group runs while the GPU does the next
                workers_mod.spawn_pool(workers, _worker_init, (config, rec, "cpu"))
                if workers > 1
                else contextlib.nullcontext()
            )
            with pool_cm as pool:
                dataset_batched.generate_groups(
                    library,
                    config,
                    pairs,
                    rec,
                    groups,
                    save,
                    settings,
                    pool,
                    deadline,
                    stage_seconds,
                )
        elif workers <= 1:
            for k in todo:
                if deadline is not None and time.time() > deadline:
                    break
                save(k, *_shard_records(library, config, pairs, rec, k, backend))
        elif todo:
            jobs = [(k, str(out / "shards" / f"shard_{k:05d}.npz"), deadline) for k in todo]
            with workers_mod.spawn_pool(workers, _worker_init, (config, rec, backend)) as pool:
                for k, n, seconds in pool.imap_unordered(_worker_shard, jobs):
                    stage_seconds.update(seconds)
                    if n:
                        written.append(k)
                    advance(n)
        interrupted = False
    finally:
        bar.close()
        # a worker may have written its shard just before a kill reached the parent: every
        # shard of this run's list that exists now was written by this run
        for k in todo:
            if k not in written and (out / "shards" / f"shard_{k:05d}.npz").exists():
                written.append(k)
                done_pairs += min(config.shard_size, len(pairs) - k * config.shard_size)
        stage_seconds.update(STAGE_SECONDS)
        timings = {
            "generate_s": time.time() - t0,
            "workers": workers,
            "part": list(part),
            # summed over worker processes (CPU-seconds when workers > 1)
            "stage_seconds": {k: round(v, 2) for k, v in sorted(stage_seconds.items())},
        }
        if done_pairs:  # every run that did work is logged, so throughput survives resumes
            run = {
                "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "pairs": done_pairs,
                "seconds": round(timings["generate_s"], 2),
                "pairs_per_min": round(60 * done_pairs / max(timings["generate_s"], 1e-9), 2),
                "workers": workers,
                "part": list(part),
                "backend": backend,
                "device": dataset_io.device_name(),
                "stage_seconds": timings["stage_seconds"],
                "interrupted": interrupted,  # killed (Ctrl-C / SIGTERM): shards so far count
                "shards": sorted(written),  # which labels this backend/device made
            }
            if backend == "mjx":
                run["shards_per_call"] = shards_per_call
            with open(out / "runs.jsonl", "a") as f:
                f.write(json.dumps(run) + "\n")
    records, runs = load_records(out), load_runs(out)
    return dataset_io.dataset_card(
        out, library, pairs, rec, timings, backend, done_pairs, records, runs
    )


def load_runs(out_dir: str | os.PathLike) -> list[dict]:
    """The generation runs logged in ``DIR/runs.jsonl`` (one JSON object per line)."""
    path = Path(out_dir) / "runs.jsonl"
    if not path.exists():
        return []
    runs = []
    for line in path.read_text().splitlines():
        try:
            runs.append(json.loads(line))
        except json.JSONDecodeError:  # a run killed while appending: skip the torn line
            continue
    return runs


def load_records(out_dir: str | os.PathLike) -> list[dict]:
    """Every pair's labels in the dataset folder ``out_dir`` (:func:`sim.dataset_io.unpack`)."""
    out = Path(out_dir)
    recs = []
    for path in sorted((out / "shards").glob("shard_*.npz")):
        with np.load(path) as z:
            recs.extend(dataset_io.unpack({k: z[k] for k in z.files}))
    return recs
