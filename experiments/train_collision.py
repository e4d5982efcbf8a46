"""Train the collision estimators (NCE and the HCE normal net) on the dataset's collision labels.

    python -m experiments.train_collision --data datasets/paper --out runs/collision \\
        --preset fast --train-pairs 200 --test-pairs 60 --time-budget nce=600,normals=120

1. Derives what the estimators need for the chosen pairs (resumable, cached in
   ``DATA/derived/collision/<split>/``): the partial clouds with normals (the same arrays as
   ``experiments.derive_dataset``, which are reused when present: same ray casts, same seed),
   the pair's collision poses regenerated from its seed (``sim.dataset.collision_poses``) with
   their labels (kept poses only: colliding, or free within 2 cm), and its stable poses.
   Training pairs come from the training split, evaluation pairs from the held-out split
   (a pair is held out when its object or its support is): no held-out pair is trained on.
2. Trains the NCE with cross entropy (random point subsets each step) and the HCE normal net
   with the paper's ``-sum(n_hat . n)`` on object and support clouds, each under a time budget.
3. Chooses the HCE thresholds (predicted and true normals) on training labels (best balanced
   accuracy), then reports accuracy / precision / recall (positive = colliding) of all three
   estimators on held-out labels, with the clouds subsampled exactly as the planner does.

Writes ``OUT/nce/`` and ``OUT/hce_normals/`` (``config.json`` + ``params.msgpack``),
``OUT/hce_true_normals.json`` (its threshold) and ``OUT/metrics.json``; prints the metrics.
``--resume`` starts from the weights already in OUT.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from omnihang_jax import collision, dataset_bridge
from omnihang_jax.collision import start_pose

T_IMPORT = time.time()  # the phases' clock (train_collision's start)
DERIVED = os.path.join(dataset_bridge.DERIVED_DIRNAME, "collision")  # ignored by git
SUBSET_SEED_OBJECT, SUBSET_SEED_SUPPORT = 0, 1  # the planner's fixed cloud subsets


# ----------------------------------------------------------------------------------------------
# Data: clouds + collision labels per pair


_WORKER: dict = {}


def _worker_init(recipe: dict, data_dir: str) -> None:
    from sim.library import build_library

    config = dataset_bridge.dataset_config_from_recipe(recipe)
    _WORKER.update(
        config=config,
        library=build_library(config.library, progress=False),
        pairs=recipe["pairs"],
        data_dir=data_dir,
    )


def _derive_one(job: tuple[dict, str]) -> str:
    """Derive one pair file, or add the near-contact labels to a file derived before them."""
    from sim import atomic, camera, dataset
    from sim.scene import build_scene

    record, path = job
    w = _WORKER
    index = int(record["pair_index"])
    obj_name, sup_name, split = w["pairs"][index]
    obj, sup = w["library"].objects[obj_name], w["library"].supports[sup_name]
    seed = int(record["pair_seed"])
    if os.path.exists(path):  # derived before the near-contact labels: add them only
        with np.load(path) as f:
            fields = {k: f[k] for k in f.files}
        fields |= near_contact_labels(
            build_scene(obj, sup), fields["stable_poses"], fields["collision_poses"], seed,
            clouds=fields,
        )  # fmt: skip
        atomic.savez(path, **fields)
        return path
    full = Path(w["data_dir"], dataset_bridge.DERIVED_DIRNAME, split)
    full = full / dataset_bridge.pair_file_name(index, obj_name, sup_name)
    scene = build_scene(obj, sup)
    if full.exists():  # derive_dataset's file: the same clouds
        with np.load(full) as f:
            clouds = {k: f[k] for k in ("object_points", "object_normals")}
            clouds |= {k: f[k] for k in ("support_points", "support_normals")}
    else:  # the first two draws of derive_pair's generator (sim.dataset.derive_pair)
        rng = np.random.default_rng([seed, 5])
        cam = w["config"].camera
        oc = camera.partial_cloud(
            scene, "object", np.asarray(record["object_eye"], float), rng, cam
        )
        sc = camera.partial_cloud(
            scene, "support", np.asarray(record["support_eye"], float), rng, cam
        )
        clouds = dict(
            object_points=oc.points,
            object_normals=oc.normals,
            support_points=sc.points,
            support_normals=sc.normals,
        )
    kept = np.asarray(record["collision_kept"], bool)
    poses = dataset.collision_poses(obj, sup, seed, w["config"])[kept]
    stable = np.asarray(record["stable_poses"], np.float32)
    atomic.savez(
        path,
        **{k: np.asarray(v, np.float32) for k, v in clouds.items()},
        collision_poses=poses.astype(np.float32),
        collision_labels=np.asarray(record["collision_label"], bool)[kept],
        stable_poses=stable,
        **pair_geometry(obj, sup),
        **near_contact_labels(scene, stable, poses, seed, clouds=clouds),
        pair_index=np.int64(index),
        object_name=np.str_(obj_name),
        support_name=np.str_(sup_name),
        object_category=np.str_(obj.category),
        support_family=np.str_(sup.category),
        split=np.str_(split),
    )
    return path


# Near-contact poses (see near_contact_poses), labelled by the planner's own ground truth.
# Version 2 (twenty-third session) adds the transit poses; versions 1 and 2 draw the same
# stable / jitter / approach / lift poses (the transit ones come last from the same stream).
NEAR_VERSION = 2
NEAR_STABLE, NEAR_JITTER, NEAR_APPROACH, NEAR_LIFT, NEAR_TRANSIT = 0, 1, 2, 3, 4
NEAR_COUNTS = {NEAR_JITTER: 160, NEAR_APPROACH: 60, NEAR_LIFT: 40}  # per pair (+ stable poses)
TRANSIT_COUNT = 96  # per pair, when the observed clouds are given (near_contact_poses)
TRANSIT_GAP = 0.03  # m: a transit pose's observed clouds come at least this close
TRANSIT_DEEP = 0.01  # m: colliding transit poses deeper than this are not kept
TRANSIT_POINTS = 256  # object points of the gap test (evenly strided)
NEAR_KINDS = {"jitter": NEAR_JITTER, "approach": NEAR_APPROACH, "lift": NEAR_LIFT,
              "transit": NEAR_TRANSIT}  # fmt: skip


def observed_gap(object_points, support, poses: np.ndarray, upper: float = np.inf):
    """[K] float32 ``collision.cloud_gap`` with ``TRANSIT_POINTS`` evenly strided object points:
    how close the observed clouds come at each pose [K, 7] (``support``: the support cloud or
    a cKDTree of it)."""
    obj = np.asarray(object_points, float)
    obj = obj[np.linspace(0, len(obj) - 1, min(TRANSIT_POINTS, len(obj))).astype(int)]
    return collision.cloud_gap(obj, support, poses, upper).astype(np.float32)


def transit_poses(scene, stable: np.ndarray, clouds, rng: np.random.Generator, n: int, mesh=None):
    """``n`` poses [n, 7] of the kind RRT-Connect's edges pass by the support on the way in,
    at the boundary between free and colliding:

    - positions uniform in the planner's bounds (``collision.default_bounds``), orientations
      half uniform and half a stable pose's turned by up to pi about a random axis (the trees
      grow from the start, in the goal's orientation, through uniformly sampled rotations);
    - kept only where the observed clouds come within ``TRANSIT_GAP`` (:func:`observed_gap`):
      the open space is free by geometry and covered by the far poses;
    - labelled on the full meshes (``mesh``, a ``collision.MeshChecker``), and the colliding
      ones deeper than ``TRANSIT_DEEP`` dropped: half of the ``n`` are free, half collide by
      at most 1 cm (the other side fills a short one).

    Measured (docs/paths.md): 10 of the hybrid's 15 colliding paths collide more than 4.5 cm
    from the goal, 1.5-7 mm deep, where the observed clouds are still 1-25 mm apart; among
    uniform transit poses 60-90 % collide, most of them centimetres deep, which the contact
    NCE already calls colliding (recall 0.97): the shallow ones are where it errs (0.86).
    Fewer than ``n`` when the rejection runs out of rounds."""
    from scipy.spatial.transform import Rotation

    from omnihang_jax.collision import default_bounds

    mesh = collision.MeshChecker(scene) if mesh is None else mesh
    lo, hi = default_bounds(scene)
    # a cheap first cut: the object cloud's bounding sphere (about its origin) must come
    # within TRANSIT_GAP of the support cloud's box
    from scipy.spatial import cKDTree

    reach = float(np.linalg.norm(clouds["object_points"], axis=1).max()) + TRANSIT_GAP
    box_lo, box_hi = clouds["support_points"].min(0), clouds["support_points"].max(0)
    tree = cKDTree(np.asarray(clouds["support_points"], float))  # once for all rounds
    free, shallow = [], []
    for _ in range(12):
        m = 16 * n
        goal = stable[rng.integers(len(stable), size=m)]
        pos = rng.uniform(lo, hi, (m, 3))
        axis = rng.normal(size=(m, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        turn = Rotation.from_rotvec(axis * rng.uniform(0.0, np.pi, m)[:, None])
        quat = (turn * Rotation.from_quat(goal[:, [4, 5, 6, 3]])).as_quat()[:, [3, 0, 1, 2]]
        uniform = rng.normal(size=(m, 4))
        uniform /= np.linalg.norm(uniform, axis=1, keepdims=True)
        quat = np.where((rng.random(m) < 0.5)[:, None], uniform, quat)
        quat *= np.where(quat[:, :1] < 0, -1.0, 1.0)  # w >= 0, as the other kinds
        poses = np.concatenate([pos, quat], axis=1)
        poses = poses[np.linalg.norm(pos - np.clip(pos, box_lo, box_hi), axis=1) < reach]
        gap = observed_gap(clouds["object_points"], tree, poses, TRANSIT_GAP)
        poses = poses[gap < TRANSIT_GAP]
        pen = mesh.penetration(poses)
        free.append(poses[pen <= mesh.tolerance])
        shallow.append(poses[(pen > mesh.tolerance) & (pen <= TRANSIT_DEEP)])
        if min(sum(map(len, free)), sum(map(len, shallow))) >= n // 2:
            break
    free, shallow = np.concatenate(free), np.concatenate(shallow)
    n_shallow = min(len(shallow), max(n // 2, n - len(free)))
    return np.concatenate([free[: n - n_shallow], shallow[:n_shallow]])


def near_contact_poses(scene, stable: np.ndarray, rng: np.random.Generator, clouds=None, mesh=None):
    """Poses around the pair's hanging poses, where the planner's last edges run: (poses
    [K, 7], kind [K] int8).

    - ``NEAR_STABLE``: the stable poses themselves (resting on the support, MuJoCo puts them
      0.03-0.06 mm inside: free by the planner's 1 mm tolerance);
    - ``NEAR_JITTER``: a random stable pose moved 0.5-30 mm (log-uniform) in a random
      direction and, for half of them, turned by up to 0.1 rad about a random axis: poses a
      few millimetres into the support (hard negatives) and small clearances next to it;
    - ``NEAR_APPROACH``: on the straight line from the planner's start pose
      (``collision.start_pose``, in front of the support) to a stable pose, t^2-distributed
      towards the goal: far free poses along the approach, and where the straight approach
      runs into the support;
    - ``NEAR_LIFT``: a stable pose raised 0.5-20 mm (log-uniform): the clearance above it;
    - ``NEAR_TRANSIT`` (only with ``clouds``, the pair's observed ``object_points`` /
      ``support_points``): :func:`transit_poses`, where the planner's paths pass the support.
    """
    from scipy.spatial.transform import Rotation

    stable = np.asarray(stable, float).reshape(-1, 7)
    if len(stable) == 0:
        return np.zeros((0, 7), np.float32), np.zeros(0, np.int8)

    def base(n):
        return stable[rng.integers(len(stable), size=n)]

    def log_uniform(lo, hi, n):
        return np.exp(rng.uniform(np.log(lo), np.log(hi), n))

    def unit(n):
        v = rng.normal(size=(n, 3))
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    n = NEAR_COUNTS[NEAR_JITTER]
    jitter = base(n)
    jitter[:, :3] += unit(n) * log_uniform(5e-4, 0.03, n)[:, None]
    angle = rng.uniform(0.0, 0.1, n) * (rng.random(n) < 0.5)
    turn = Rotation.from_rotvec(unit(n) * angle[:, None])
    quat = (turn * Rotation.from_quat(jitter[:, [4, 5, 6, 3]])).as_quat()
    jitter[:, 3:] = quat[:, [3, 0, 1, 2]]

    n = NEAR_COUNTS[NEAR_APPROACH]
    goal = base(n)
    start = np.stack([start_pose(scene, g) for g in goal])
    t = rng.random(n)[:, None] ** 2
    approach = goal.copy()
    approach[:, :3] += t * (start[:, :3] - goal[:, :3])

    n = NEAR_COUNTS[NEAR_LIFT]
    lift = base(n)
    lift[:, 2] += log_uniform(5e-4, 0.02, n)

    parts = [stable, jitter, approach, lift]
    kinds = [NEAR_STABLE, NEAR_JITTER, NEAR_APPROACH, NEAR_LIFT]
    if clouds is not None and TRANSIT_COUNT:
        parts.append(transit_poses(scene, stable, clouds, rng, TRANSIT_COUNT, mesh))
        kinds.append(NEAR_TRANSIT)
    poses = np.concatenate(parts)
    counts = [len(p) for p in parts]
    return poses.astype(np.float32), np.repeat(np.array(kinds, np.int8), counts)


def near_contact_labels(scene, stable, dataset_poses, seed: int, clouds=None) -> dict:
    """The fields a pair file gets for planner-facing training: ``near_poses`` /
    ``near_kind`` (:func:`near_contact_poses`, seeded by the pair; the transit poses only
    with ``clouds``), ``near_penetration`` (deepest object-support penetration on the full
    meshes, m: the planner's ground truth, ``collision.MeshChecker``; colliding above 1 mm),
    ``near_gap`` (:func:`observed_gap`, m; NaN without ``clouds``) and ``collision_penetration``
    (the same for the dataset's labelled poses, whose own labels call any penetration
    colliding)."""
    mesh = collision.MeshChecker(scene)
    poses, kind = near_contact_poses(scene, stable, np.random.default_rng([seed, 13]), clouds, mesh)
    if clouds is None:
        gap = np.full(len(poses), np.nan, np.float32)
    else:
        gap = observed_gap(clouds["object_points"], clouds["support_points"], poses)
    return dict(
        near_poses=poses,
        near_kind=kind,
        near_penetration=mesh.penetration(poses).astype(np.float32),
        near_gap=gap,
        collision_penetration=mesh.penetration(dataset_poses).astype(np.float32),
        near_version=np.int64(NEAR_VERSION),
    )


def pair_geometry(obj, sup) -> dict:
    """What far-pose labelling needs: the object's half diagonal (m), the support's box
    [2, 3] and its wall plane y (NaN when free-standing)."""
    return dict(
        object_half_diagonal=np.float32(0.5 * np.linalg.norm(obj.extents)),
        support_bounds=np.asarray(sup.bounds(), np.float32),
        wall_y=np.float32(np.nan if sup.wall_y is None else sup.wall_y),
    )


FAR_MARGIN = 0.02  # m: far poses clear the support's box (and wall) by this much at least


def far_free_poses(
    rng: np.random.Generator, half_diagonal: float, support_bounds, wall_y: float, n: int
) -> np.ndarray:
    """``n`` poses [n, 7] that cannot collide, by geometry alone: the object's bounding
    sphere (radius = half diagonal of its box) clears the support's box by ``FAR_MARGIN``
    (and lies in front of the wall). Positions uniform in the support's box grown by 1.25
    object diagonals + the margin (most of them inside the planner's bounds, which grow the
    box by the largest extent), rotations uniform.

    Why: the dataset keeps free poses only within 2 cm of the support (the original's
    protocol), so a network trained on those alone has never seen the open space a planner
    starts in, and calls it colliding (measured: docs/paths.md)."""
    lo, hi = np.asarray(support_bounds, float)
    grow = 2.5 * half_diagonal + FAR_MARGIN
    out = []
    while sum(len(x) for x in out) < n:
        pos = rng.uniform(lo - grow, hi + grow, (4 * n, 3))
        gap = np.linalg.norm(pos - np.clip(pos, lo, hi), axis=1)
        ok = gap > half_diagonal + FAR_MARGIN
        if np.isfinite(wall_y):
            ok &= pos[:, 1] - half_diagonal > wall_y + FAR_MARGIN
        out.append(pos[ok])
    pos = np.concatenate(out)[:n]
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([pos, q], axis=1).astype(np.float32)


def derive_collision_pairs(
    data_dir: str | os.PathLike,
    limits: dict[str, int],
    workers: int = 1,
    progress: bool = True,
    out_dir: str | os.PathLike | None = None,
    existing_only: bool = False,
    shuffle_seed: int | None = None,
    only=None,
    derive_only=None,
) -> dict[str, list[Path]]:
    """Per split in ``limits`` ("test" / "train" -> n): its first n pairs with stable poses
    (round robin over object categories), derived to ``DATA/derived/collision/<split>/`` if
    not there yet (resumable; the splits in the order given, in one worker pool). Returns the
    files per split; ``existing_only``: derive nothing, return those already there;
    ``shuffle_seed``: pairs in a seeded random order within each category (by default the
    pair order, which takes each category's first object with every support in turn);
    ``only(pair_index) -> bool``: only those pairs; ``derive_only(pair_index) -> bool``: of the
    chosen pairs, derive only those (the chosen list is the same; the others are returned as
    they are, whether there or not)."""
    from sim import dataset

    for split in limits:
        if split not in ("train", "test"):
            raise ValueError(f"split must be 'train' or 'test', got {split!r}")
    data_dir = Path(data_dir)
    recipe = dataset_bridge.read_recipe(data_dir)
    out = Path(out_dir) if out_dir else data_dir / DERIVED
    pairs = recipe["pairs"]
    jobs: dict[str, list] = {split: [] for split in limits}
    for record in dataset.load_records(data_dir):
        index = int(record["pair_index"])
        obj_name, sup_name, split = pairs[index]
        if split not in jobs or len(record["stable_poses"]) == 0:
            continue
        if only is not None and not only(index):
            continue
        if not np.asarray(record["collision_kept"]).any():
            continue
        path = out / split / dataset_bridge.pair_file_name(index, obj_name, sup_name)
        jobs[split].append((record, os.fspath(path)))
    files = {}
    todo = []
    for split, n in limits.items():
        if shuffle_seed is not None:
            order = np.random.default_rng(shuffle_seed).permutation(len(jobs[split]))
            jobs[split] = [jobs[split][i] for i in order]
        chosen = dataset_bridge.interleave_by_category(jobs[split], pairs)[:n]
        files[split] = [Path(j[1]) for j in chosen]
        todo += [j for j in chosen if not is_complete(j[1])
                 and (derive_only is None or derive_only(int(j[0]["pair_index"])))]  # fmt: skip
    if existing_only:
        return {split: [p for p in paths if is_complete(p)] for split, paths in files.items()}
    bar = tqdm(total=len(todo), desc="derive", unit="pair", disable=not progress)
    if todo and workers <= 1:
        _worker_init(recipe, os.fspath(data_dir))
        for job in todo:
            _derive_one(job)
            bar.update(1)
    elif todo:
        from sim.workers import spawn_pool

        with spawn_pool(workers, _worker_init, (recipe, os.fspath(data_dir))) as pool:
            for _ in pool.imap_unordered(_derive_one, todo, chunksize=1):
                bar.update(1)
    bar.close()
    return files


def is_complete(path) -> bool:
    """The pair file exists and has the current near-contact labels."""
    if not os.path.exists(path):
        return False
    try:
        with np.load(path) as f:
            return "near_version" in f.files and int(f["near_version"]) >= NEAR_VERSION
    except (OSError, ValueError, EOFError):  # a damaged file: derive it again
        os.remove(path)
        return False


class _Fields(dict):
    """A pair file's arrays, read into memory (``.files`` like an open ``np.load``)."""

    @property
    def files(self):
        return list(self)


@dataclasses.dataclass
class CollisionData:
    """Clouds of P pairs and their L labelled poses (host numpy)."""

    object_points: np.ndarray  # [P, N, 3] object frame
    object_normals: np.ndarray  # [P, N, 3]
    support_points: np.ndarray  # [P, M, 3] support frame
    support_normals: np.ndarray  # [P, M, 3]
    pair: np.ndarray  # [L] int32 index into the P pairs
    poses: np.ndarray  # [L, 7]
    labels: np.ndarray  # [L] bool, True = colliding
    meta: list[dict]  # per pair: names, category, family, split, pair_index
    far_pair: np.ndarray | None = None  # [F] int32: extra training poses:
    far_poses: np.ndarray | None = None  # [F, 7] far_free_poses, stable poses, near poses
    far_labels: np.ndarray | None = None  # [F] bool (True = colliding; near poses only)
    far_near: np.ndarray | None = None  # [F] bool: the row is a near-contact pose (--near-share)
    far_transit: np.ndarray | None = None  # [F] bool: ... and a transit pose (--transit-share)
    far_mined: np.ndarray | None = None  # [F] bool: a state the planner's checker judged (--mined)
    # near-contact poses of the pairs (near_contact_poses; files derived with them), labelled
    # by the planner's ground truth (penetration > NEAR_TOLERANCE on the full meshes)
    near_pair: np.ndarray | None = None  # [K] int32
    near_poses: np.ndarray | None = None  # [K, 7]
    near_kind: np.ndarray | None = None  # [K] int8 (NEAR_STABLE ... NEAR_TRANSIT)
    near_labels: np.ndarray | None = None  # [K] bool
    near_gap: np.ndarray | None = None  # [K] observed clouds' gap (m; observed_gap), NaN: unknown


def _geometry_of(f, meta: dict, cache: dict) -> dict:
    """The pair's geometry from its file, or (files derived before it was stored) rebuilt
    from the library."""
    if "object_half_diagonal" in f.files:
        return {k: f[k] for k in ("object_half_diagonal", "support_bounds", "wall_y")}
    if "library" not in cache:
        from sim.assets.base import build_object, build_support  # noqa: F401
        from sim.library import LibraryConfig, build_library

        cache["library"] = build_library(LibraryConfig(), progress=False)
    lib = cache["library"]
    return pair_geometry(lib.objects[meta["object_name"]], lib.supports[meta["support_name"]])


NEAR_TOLERANCE = 1e-3  # m: the planner's penetration tolerance (planner.PlannerConfig)


def load_collision_data(
    files: list[Path],
    far_per_pair: int = 0,
    seed: int = 0,
    recipe_library=None,
    stable_free: bool = False,
    near_train: bool = False,
    planner_labels: bool = False,
    transit_train: bool = True,
    mined_dir: str | os.PathLike | None = None,
) -> CollisionData:
    """Clouds and labels of the pair files; ``far_per_pair`` far free poses per pair
    (:func:`far_free_poses`), with ``stable_free`` the pair's stable poses as free labels and
    with ``near_train`` its near-contact poses (not the stable ones) with their mesh labels,
    for training (see ``main``'s ``--stable-free`` / ``--near``). The near-contact poses are
    always loaded (``near_*``, for the metrics) when the files have them; ``transit_train``
    False keeps the transit poses (``NEAR_TRANSIT``) out of training (a control run).

    ``planner_labels``: the dataset's labelled poses are labelled by the planner's ground
    truth instead (deepest mesh penetration ``collision_penetration`` > NEAR_TOLERANCE, where
    the file has it): the dataset calls any touch colliding, the planner and its evaluation
    allow 1 mm, and the stable poses (free labels) rest in contact, so without this the NCE
    is taught both sides of the same millimetre.

    ``mined_dir`` (twenty-ninth session): a folder of ``eval_paths --mine`` files; a pair with
    one gets its mined states as training rows (``far_mined``; labels: mesh penetration >
    NEAR_TOLERANCE, the planner's ground truth), drawn with ``train_nce``'s ``mined_share``."""
    if not files:
        raise ValueError("no pair files to load")
    if mined_dir is not None and not Path(mined_dir).is_dir():
        raise FileNotFoundError(f"--mined {mined_dir}: no such folder")
    rng = np.random.default_rng(seed)
    cache: dict = {} if recipe_library is None else {"library": recipe_library}
    far: dict[str, list] = {k: [] for k in ("pair", "poses", "labels", "near", "transit", "mined")}

    def add_far(i, poses_, labels_, near_=False, transit_=None, mined_=False):
        n = len(poses_)
        far["pair"].append(np.full(n, i, np.int32))
        far["poses"].append(np.asarray(poses_, np.float32))
        far["labels"].append(np.asarray(labels_, bool))
        far["near"].append(np.full(n, near_, bool))
        far["transit"].append(np.zeros(n, bool) if transit_ is None else transit_)
        far["mined"].append(np.full(n, mined_, bool))

    near: dict[str, list] = {"pair": [], "poses": [], "kind": [], "labels": [], "gap": []}
    keys = ("object_points", "object_normals", "support_points", "support_normals")
    clouds: dict[str, list] = {k: [] for k in keys}
    pair, poses, labels, meta = [], [], [], []

    def read(path):  # zlib releases the GIL: threads read ~4x faster than one loop
        with np.load(path) as f:
            return _Fields({k: f[k] for k in f.files})

    with ThreadPoolExecutor(8) as pool:
        contents = pool.map(read, files)
    for i, f in enumerate(contents):
        for k in keys:
            clouds[k].append(f[k])
        poses.append(f["collision_poses"])
        if planner_labels and "collision_penetration" in f.files:
            labels.append(f["collision_penetration"] > NEAR_TOLERANCE)
        else:
            labels.append(f["collision_labels"])
        pair.append(np.full(len(f["collision_labels"]), i, np.int32))
        meta.append({k: f[k].item() for k in dataset_bridge.META_KEYS})
        if far_per_pair:
            g = _geometry_of(f, meta[-1], cache)
            free = far_free_poses(
                rng,
                float(g["object_half_diagonal"]),
                g["support_bounds"],
                float(g["wall_y"]),
                far_per_pair,
            )
            add_far(i, free, np.zeros(far_per_pair, bool))
        if stable_free:
            stable = f["stable_poses"].astype(np.float32)
            add_far(i, stable, np.zeros(len(stable), bool))
        if "near_poses" in f.files:
            kind = f["near_kind"]
            label = f["near_penetration"] > NEAR_TOLERANCE
            near["pair"].append(np.full(len(kind), i, np.int32))
            near["poses"].append(f["near_poses"].astype(np.float32))
            near["kind"].append(kind)
            near["labels"].append(label)
            gap = f["near_gap"] if "near_gap" in f.files else np.full(len(kind), np.nan)
            near["gap"].append(gap.astype(np.float32))
            if near_train:
                moved = kind != NEAR_STABLE
                if not transit_train:
                    moved &= kind != NEAR_TRANSIT
                add_far(i, f["near_poses"][moved], label[moved], True, kind[moved] == NEAR_TRANSIT)
        mined = None if mined_dir is None else Path(mined_dir) / f"{Path(files[i]).stem}.npz"
        if mined is not None and mined.exists():
            with np.load(mined) as m:
                if int(m["pair_index"]) != int(meta[-1]["pair_index"]):
                    raise ValueError(f"{mined}: pair {int(m['pair_index'])}, not {meta[-1]}")
                add_far(i, m["poses"], m["penetration"] > NEAR_TOLERANCE, mined_=True)
    return CollisionData(
        *(np.stack(clouds[k]) for k in keys),
        pair=np.concatenate(pair),
        poses=np.concatenate(poses).astype(np.float32),
        labels=np.concatenate(labels),
        meta=meta,
        **{f"far_{k}": np.concatenate(v) if v else None for k, v in far.items()},
        **{f"near_{k}": np.concatenate(v) if v else None for k, v in near.items()},
    )


def complete_collision_data(
    data: CollisionData,
    completion_folder: str | os.PathLike,
    eyes: dict[int, tuple] | None,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = False,
) -> CollisionData:
    """``data`` with each pair's clouds replaced by completed ones (twenty-eighth session: the
    input of a completion-aware NCE, ``NCEConfig.input_clouds = "completed"``):
    ``completion.completed_cloud`` of the observed cloud and the shape-completion networks'
    prediction, carved with the pair's cameras (``eyes``: pair_index -> (object eye, support
    eye), the dataset's records) so that only the hidden side is added; the planner builds the
    same clouds (``eval_paths``). Normals of the predicted points are unknown (zero): the HCE's
    normal net must not train on these clouds. ``cache_dir``: one small file per pair
    (``<pair_index>.npz``), reused by a resumed call."""
    from omnihang_jax import completion

    cache = Path(cache_dir) if cache_dir is not None else None
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
    index = [int(m["pair_index"]) for m in data.meta]
    obj, sup = data.object_points.copy(), data.support_points.copy()
    obj_n, sup_n = data.object_normals.copy(), data.support_normals.copy()
    todo = []
    for i, p in enumerate(index):
        path = cache / f"{p:05d}.npz" if cache is not None else None
        if path is not None and path.exists():
            with np.load(path) as f:
                obj[i], sup[i] = f["object_points"], f["support_points"]
        else:
            todo.append(i)
    if todo:
        if eyes is not None:
            missing = [index[i] for i in todo if index[i] not in eyes]
            if missing:
                raise ValueError(f"no camera (dataset record) for pairs {missing[:5]}")
        nets = completion.load_nets(completion_folder)
        bar = tqdm(total=len(todo), desc="completion", disable=not progress)
        for start in range(0, len(todo), 1024):
            part = todo[start : start + 1024]
            pred = completion.predict_points_many(
                nets, data.object_points[part], data.support_points[part],
                None if eyes is None else [eyes[index[i]] for i in part],
            )  # fmt: skip
            for i, (po, ps) in zip(part, pred):
                obj[i] = completion.completed_cloud(data.object_points[i], po)
                sup[i] = completion.completed_cloud(data.support_points[i], ps)
                if cache is not None:
                    np.savez(cache / f"{index[i]:05d}.npz", object_points=obj[i],
                             support_points=sup[i])  # fmt: skip
            bar.update(len(part))
        bar.close()
    # the observed rows keep their normals; the predicted points have none
    keep = completion.completed_observed_rows(data.object_points.shape[1])
    for normals in (obj_n, sup_n):
        normals[:, : len(keep)] = normals[:, keep]
        normals[:, len(keep) :] = 0.0
    return dataclasses.replace(
        data, object_points=obj, support_points=sup, object_normals=obj_n, support_normals=sup_n
    )


def record_eyes(data_dir: str | os.PathLike, pair_indices) -> dict[int, tuple]:
    """pair_index -> (object eye [3] in the object frame, support eye [3]) of the dataset's
    records (the cameras of the partial clouds)."""
    from sim import dataset

    want = {int(p) for p in pair_indices}
    return {
        int(r["pair_index"]): (np.asarray(r["object_eye"]), np.asarray(r["support_eye"]))
        for r in dataset.load_records(data_dir)
        if int(r["pair_index"]) in want
    }


# ----------------------------------------------------------------------------------------------
# Training


def _sample_points(key, clouds, n):
    """clouds [B, K, 3] -> [B, n, 3] random rows (with replacement) of each cloud."""
    idx = jax.random.randint(key, (clouds.shape[0], n), 0, clouds.shape[1])
    return jnp.take_along_axis(clouds, idx[..., None], axis=1)


def train_nce(
    data: CollisionData,
    config: collision.NCEConfig,
    steps: int,
    time_budget: float,
    batch: int = 64,
    learning_rate: float = 1e-3,
    seed: int = 0,
    params=None,
    progress: bool = True,
    stop_at: float | None = None,
    near_share: float = 0.0,
    schedule: str = "constant",
    transit_share: float = 0.0,
    mined_share: float = 0.0,
    val: CollisionData | None = None,
    val_every: int = 0,
    val_labels: int = 8192,
) -> tuple[dict, dict]:
    """Cross entropy on (pair, pose, label) triples. Returns (params, log). ``stop_at``: a
    unix time training stops at, whatever the budget (initialisation and compilation
    included).

    ``near_share``: this fraction of every batch is drawn from the near-contact training poses
    (``CollisionData.far_near``; the rest uniformly from all rows), so that the millimetres
    around the goals, where the planner's last edges run, get more of the training;
    ``transit_share``: this fraction more from the transit poses alone (``far_transit``);
    ``mined_share``: this fraction more from the planner's mined states (``far_mined``).
    ``schedule``: "constant" (the paper's Adam at ``learning_rate``) or "cosine" (a linear
    warm-up over the first 3 % of the time budget, then cosine decay to 5 % of the rate at
    its end: the budget, not a step count, is what a device call fixes).
    ``val`` (pairs never trained on) with ``val_every`` > 0: every ``val_every`` steps the
    loss and accuracy on a fixed set of at most ``val_labels`` of their labelled poses (half
    near-contact poses, planner labels; half dataset poses), with the planner's fixed cloud
    subsets, go to ``log["val_history"]``."""
    nets = collision.make_nce(config)
    key = jax.random.key(seed)
    key, init_key = jax.random.split(key)
    params = nets.init(init_key) if params is None else params
    opt = optax.inject_hyperparams(optax.adam)(learning_rate=learning_rate)
    opt_state = opt.init(params)
    obj_clouds = jnp.asarray(data.object_points)
    sup_clouds = jnp.asarray(data.support_points)
    pair, poses, labels = data.pair, data.poses, data.labels
    near_rows = transit_rows = mined_rows = np.zeros(0, np.int64)
    if data.far_poses is not None:  # far / stable (free) and near-contact poses
        if data.far_near is not None:
            near_rows = len(pair) + np.flatnonzero(data.far_near)
        if data.far_transit is not None:
            transit_rows = len(pair) + np.flatnonzero(data.far_transit)
        if data.far_mined is not None:
            mined_rows = len(pair) + np.flatnonzero(data.far_mined)
        pair = np.concatenate([pair, data.far_pair])
        poses = np.concatenate([poses, data.far_poses])
        labels = np.concatenate([labels, data.far_labels])
    n_near = int(round(near_share * batch)) if len(near_rows) else 0
    if near_share > 0 and not n_near:
        print("warning: --near-share without near-contact training poses: uniform batches")
    near_rows = jnp.asarray(near_rows if n_near else np.zeros(1, np.int64))
    n_transit = int(round(transit_share * batch)) if len(transit_rows) else 0
    if transit_share > 0 and not n_transit:
        print("warning: --transit-share without transit training poses: none drawn")
    n_mined = int(round(mined_share * batch)) if len(mined_rows) else 0
    if mined_share > 0 and not n_mined:
        print("warning: --mined-share without mined training states: none drawn")
    if n_near + n_transit + n_mined > batch:
        raise ValueError(
            f"near + transit + mined shares > 1 ({n_near} + {n_transit} + {n_mined} > {batch})"
        )
    transit_rows = jnp.asarray(transit_rows if n_transit else np.zeros(1, np.int64))
    mined_rows = jnp.asarray(mined_rows if n_mined else np.zeros(1, np.int64))
    pair, poses = jnp.asarray(pair), jnp.asarray(poses)
    labels = jnp.asarray(labels, jnp.float32)

    @jax.jit
    def step(params, opt_state, key):
        k_pick, k_near, k_obj, k_sup = jax.random.split(key, 4)
        k_transit = jax.random.fold_in(k_near, 1)  # the earlier draws stay as they were
        k_mined = jax.random.fold_in(k_near, 2)
        n_uniform = batch - n_near - n_transit - n_mined
        pick = jax.random.randint(k_pick, (n_uniform,), 0, labels.shape[0])
        if n_near:
            near = near_rows[jax.random.randint(k_near, (n_near,), 0, near_rows.shape[0])]
            pick = jnp.concatenate([pick, near])
        if n_transit:
            draw = jax.random.randint(k_transit, (n_transit,), 0, transit_rows.shape[0])
            pick = jnp.concatenate([pick, transit_rows[draw]])
        if n_mined:
            draw = jax.random.randint(k_mined, (n_mined,), 0, mined_rows.shape[0])
            pick = jnp.concatenate([pick, mined_rows[draw]])
        p = pair[pick]
        obj = _sample_points(k_obj, obj_clouds[p], config.object_input)
        sup = _sample_points(k_sup, sup_clouds[p], config.support_input)

        def loss_fn(params):
            logits = nets.apply(params, obj, sup, poses[pick])
            loss = optax.sigmoid_binary_cross_entropy(logits, labels[pick]).mean()
            return loss, jnp.mean((logits > 0) == (labels[pick] > 0.5))

        (loss, acc), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, acc

    lr_at = None
    if schedule == "cosine":
        lr_at = functools.partial(warmup_cosine, peak=learning_rate)
    elif schedule != "constant":
        raise ValueError(f"schedule must be 'constant' or 'cosine', got {schedule!r}")
    evaluate = None
    if val is not None and val_every > 0:
        evaluate = _validation_fn(nets, config, val, val_labels, seed)
    params, log = _loop(
        step, params, opt_state, key, steps, time_budget, batch, "nce", progress, stop_at,
        lr_at=lr_at, evaluate=evaluate, eval_every=val_every,
    )  # fmt: skip
    log |= dict(
        near_share=n_near / batch,
        transit_share=n_transit / batch,
        mined_share=n_mined / batch,
        mined_rows=int(len(mined_rows)) if n_mined else 0,
        schedule=schedule,
        peak_lr=learning_rate,
    )
    return params, log


def warmup_cosine(frac: float, peak: float, warmup: float = 0.03, final: float = 0.05) -> float:
    """The learning rate at ``frac`` (0..1) of a run: linear warm-up from 10 % of ``peak``
    over the first ``warmup`` of it, then cosine decay to ``final`` x ``peak`` at its end."""
    frac = min(max(frac, 0.0), 1.0)
    if frac < warmup:
        return peak * (0.1 + 0.9 * frac / warmup)
    t = (frac - warmup) / (1.0 - warmup)
    return peak * (final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * t)))


def validation_rows(val: CollisionData, max_labels: int, seed: int = 0):
    """A fixed validation set: (pair [V], poses [V, 7], labels [V] bool, near [V] bool,
    transit [V] bool), at most ``max_labels`` rows, half near-contact poses (planner labels)
    where the files have them, the rest dataset poses; files of near version 2 add up to
    ``max_labels / 4`` transit poses (not counted in ``near``, so that the near rows are
    drawn as before)."""
    rng = np.random.default_rng([seed, 7])
    kinds = np.zeros(0, np.int8) if val.near_kind is None else val.near_kind
    pool = np.flatnonzero(kinds != NEAR_TRANSIT)
    n_near = min(len(pool), max_labels // 2)
    near = np.sort(pool[rng.choice(len(pool), n_near, False)]) if n_near else np.zeros(0, int)
    n_data = min(len(val.labels), max_labels - n_near)
    rows = np.sort(rng.choice(len(val.labels), n_data, False))
    transit_pool = np.flatnonzero(kinds == NEAR_TRANSIT)
    n_transit = min(len(transit_pool), max_labels // 4)
    transit = np.sort(rng.choice(transit_pool, n_transit, False)) if n_transit else near[:0]
    extra = np.concatenate([near, transit]).astype(int)
    has = val.near_poses is not None
    pair = np.concatenate([val.pair[rows], val.near_pair[extra] if has else []])
    poses = np.concatenate([val.poses[rows], val.near_poses[extra] if has else np.zeros((0, 7))])
    labels = np.concatenate([val.labels[rows], val.near_labels[extra] if has else []])
    is_near = np.concatenate(
        [np.zeros(n_data, bool), np.ones(n_near, bool), np.zeros(n_transit, bool)]
    )
    is_transit = np.concatenate([np.zeros(n_data + n_near, bool), np.ones(n_transit, bool)])
    return pair.astype(np.int32), poses.astype(np.float32), labels.astype(bool), is_near, is_transit


def _validation_fn(nets, config, val: CollisionData, max_labels: int, seed: int):
    """evaluate(params) -> dict of the validation loss / accuracy (all rows and near-contact
    rows) on :func:`validation_rows`, with the planner's fixed cloud subsets."""
    pair, poses, labels, is_near, is_transit = validation_rows(val, max_labels, seed)
    obj, sup = zip(
        *(
            planner_clouds(o, s, config.object_input, config.support_input)
            for o, s in zip(val.object_points, val.support_points)
        )
    )
    obj, sup = jnp.asarray(np.stack(obj)), jnp.asarray(np.stack(sup))
    chunk = 1024
    pad = (-len(pair)) % chunk
    pair_p = jnp.asarray(np.concatenate([pair, np.repeat(pair[:1], pad)]))
    poses_p = jnp.asarray(np.concatenate([poses, np.repeat(poses[:1], pad, 0)]))

    @jax.jit
    def logits_of(params, p, x):
        return nets.apply(params, obj[p], sup[p], x)

    y = labels.astype(np.float32)

    def evaluate(params) -> dict:
        logits = np.concatenate(
            [
                np.asarray(logits_of(params, pair_p[a : a + chunk], poses_p[a : a + chunk]))
                for a in range(0, len(pair_p), chunk)
            ]
        )[: len(pair)]
        loss = np.asarray(optax.sigmoid_binary_cross_entropy(logits, y))
        right = (logits > 0) == labels
        out = dict(val_loss=float(loss.mean()), val_accuracy=float(right.mean()))
        if is_near.any():
            out |= dict(
                val_near_loss=float(loss[is_near].mean()),
                val_near_accuracy=float(right[is_near].mean()),
            )
        if is_transit.any():
            out |= dict(
                val_transit_loss=float(loss[is_transit].mean()),
                val_transit_accuracy=float(right[is_transit].mean()),
            )
        return out

    return evaluate


def train_normals(
    data: CollisionData,
    config: collision.NormalNetConfig,
    steps: int,
    time_budget: float,
    batch: int = 16,
    learning_rate: float = 1e-3,
    seed: int = 1,
    params=None,
    progress: bool = True,
    stop_at: float | None = None,
) -> tuple[dict, dict]:
    """The paper's normal loss on object and support clouds alike. Returns (params, log)."""
    nets = collision.make_normal_net(config)
    key = jax.random.key(seed)
    key, init_key = jax.random.split(key)
    params = nets.init(init_key) if params is None else params
    opt = optax.adam(learning_rate)
    opt_state = opt.init(params)
    points = jnp.asarray(np.concatenate([data.object_points, data.support_points]))
    normals = jnp.asarray(np.concatenate([data.object_normals, data.support_normals]))

    @jax.jit
    def step(params, opt_state, key):
        k_pick, k_pts = jax.random.split(key)
        pick = jax.random.randint(k_pick, (batch,), 0, points.shape[0])
        idx = jax.random.randint(k_pts, (batch, config.points), 0, points.shape[1])
        pts = jnp.take_along_axis(points[pick], idx[..., None], axis=1)
        nrm = jnp.take_along_axis(normals[pick], idx[..., None], axis=1)

        def loss_fn(params):
            pred = nets.apply(params, pts)
            return collision.normal_loss(pred, nrm), jnp.mean(jnp.sum(pred * nrm, -1))

        (loss, cos), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, cos

    return _loop(
        step, params, opt_state, key, steps, time_budget, batch, "normals", progress, stop_at
    )


def _loop(
    step, params, opt_state, key, steps, time_budget, batch, name, progress, stop_at=None,
    lr_at=None, evaluate=None, eval_every=0,
):  # fmt: skip
    """Run ``step`` until ``steps`` or the time budget. ``lr_at(frac)``: the learning rate at
    this fraction of the budget (an ``optax.inject_hyperparams`` state); ``evaluate(params)``
    every ``eval_every`` steps (and at the end) -> a dict logged in ``val_history``."""
    t_compile = time.perf_counter()
    key, k = jax.random.split(key)

    def set_lr(frac):
        if lr_at is not None:
            opt_state.hyperparams["learning_rate"] = jnp.asarray(lr_at(frac), jnp.float32)

    set_lr(0.0)
    params, opt_state, loss, metric = step(params, opt_state, k)
    jax.block_until_ready(loss)
    compile_s = time.perf_counter() - t_compile
    t0 = time.perf_counter()
    history, val_history = [], []
    done = 1
    bar = tqdm(total=steps, desc=f"train {name}", disable=not progress)
    bar.update(1)
    losses, metrics = [], []
    if stop_at is not None:  # the budget, or less if the wall clock says so
        time_budget = min(time_budget, stop_at - time.time())

    def validate():
        if evaluate is not None:
            t = time.perf_counter()
            row = dict(step=done, seconds=round(t - t0, 1), **evaluate(params))
            val_history.append(row)
            print(f"{name} validation at step {done}: " + json.dumps(row), flush=True)
            return time.perf_counter() - t  # not counted against the training budget
        return 0.0

    paused = validate()
    while (
        done < steps
        and time.perf_counter() - t0 - paused < time_budget
        and (stop_at is None or time.time() < stop_at)
    ):
        set_lr((time.perf_counter() - t0 - paused) / max(time_budget, 1e-9))
        key, k = jax.random.split(key)
        params, opt_state, loss, metric = step(params, opt_state, k)
        losses.append(loss)
        metrics.append(metric)
        done += 1
        bar.update(1)
        if done % 50 == 0:
            mean_loss = float(jnp.mean(jnp.stack(losses)))
            mean_metric = float(jnp.mean(jnp.stack(metrics)))
            history.append((done, mean_loss, mean_metric))
            bar.set_postfix(loss=f"{mean_loss:.3f}", metric=f"{mean_metric:.3f}")
            losses, metrics = [], []
        if eval_every and done % eval_every == 0:
            paused += validate()
    jax.block_until_ready(params)
    if evaluate is not None and (not val_history or val_history[-1]["step"] != done):
        paused += validate()
    bar.close()
    seconds = time.perf_counter() - t0 - paused
    log = dict(
        steps=done,
        batch=batch,
        train_s=round(seconds, 1),
        compile_s=round(compile_s, 1),
        samples_per_s=round((done - 1) * batch / max(seconds, 1e-9), 1),
        history=history,
    )
    if evaluate is not None:
        log["val_history"] = val_history
    return params, log


def write_curves(out: Path, log: dict) -> None:
    """Append this call's NCE log to ``OUT/nce_history.jsonl`` (one line per training call:
    a resumed job keeps every call's curve) and draw all calls, steps counted on, into
    ``OUT/nce_curves.png``: training loss and, where measured, validation loss (all rows,
    near-contact rows and transit rows)."""
    with open(out / "nce_history.jsonl", "a") as f:
        f.write(json.dumps(log) + "\n")
    calls = [json.loads(line) for line in open(out / "nce_history.jsonl") if line.strip()]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    offset, transit_drawn = 0, False
    for i, call in enumerate(calls):
        hist = np.asarray(call.get("history") or np.zeros((0, 3)), float).reshape(-1, 3)
        ax.plot(offset + hist[:, 0], hist[:, 1], "C0", lw=1, label="train" if i == 0 else None)
        val = call.get("val_history") or []
        if val:
            steps = offset + np.array([r["step"] for r in val])
            ax.plot(steps, [r["val_loss"] for r in val], "C1o-", ms=3,
                    label="validation" if i == 0 else None)  # fmt: skip
            if "val_near_loss" in val[0]:
                ax.plot(steps, [r["val_near_loss"] for r in val], "C2s--", ms=3,
                        label="validation, near contact" if i == 0 else None)  # fmt: skip
            if "val_transit_loss" in val[0]:
                ax.plot(steps, [r["val_transit_loss"] for r in val], "C3^:", ms=3,
                        label=None if transit_drawn else "validation, transit")  # fmt: skip
                transit_drawn = True
        if i:
            ax.axvline(offset, color="0.7", lw=0.8)
        offset += int(call.get("steps", 0))
    ax.set_xlabel("NCE step (calls joined; grey: a resumed call)")
    ax.set_ylabel("cross entropy")
    ax.set_yscale("log")
    ax.legend()
    ax.set_title("NCE training")
    fig.tight_layout()
    fig.savefig(out / "nce_curves.png", dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------------------------
# Evaluation on labels


def planner_clouds(object_points, support_points, n_object: int, n_support: int):
    """The fixed cloud subsets every estimator sees at planning time."""
    return (
        collision.subsample_cloud(object_points, n_object, SUBSET_SEED_OBJECT),
        collision.subsample_cloud(support_points, n_support, SUBSET_SEED_SUPPORT),
    )


def score_poses(data: CollisionData, pair, poses, score_fn, n_object, n_support) -> np.ndarray:
    """Scores [L] of ``poses`` [L, 7] of pairs ``pair`` [L], pair by pair, with the planner's
    cloud subsets. score_fn(pair_index, object_cloud, support_cloud, poses) -> [B]."""
    scores = np.zeros(len(pair))
    for p in np.unique(pair):
        rows = np.flatnonzero(pair == p)
        oc, sc = planner_clouds(data.object_points[p], data.support_points[p], n_object, n_support)
        for a in range(0, len(rows), 512):  # chunks padded to 512: one compilation
            r = rows[a : a + 512]
            chunk = poses[r]
            padded = np.concatenate([chunk, np.repeat(chunk[:1], 512 - len(r), 0)])
            scores[r] = np.asarray(score_fn(p, oc, sc, padded))[: len(r)]
    return scores


def estimator_scores(
    data: CollisionData, score_fn, n_object, n_support, max_labels=None, seed=0, max_pairs=None
):
    """Scores of (a random subset of at most ``max_labels``) labelled poses, pair by pair (of
    the first ``max_pairs`` pairs only: one call per pair and chunk, so thousands of pairs
    cost minutes). score_fn(pair_index, object_cloud, support_cloud, poses) -> [B].
    Returns (scores, labels)."""
    chosen = np.arange(len(data.labels))
    if max_pairs is not None:
        chosen = chosen[data.pair < max_pairs]
    if max_labels is not None and max_labels < len(chosen):
        chosen = np.sort(np.random.default_rng(seed).choice(len(chosen), max_labels, False))
    scores = score_poses(data, data.pair[chosen], data.poses[chosen], score_fn, n_object, n_support)
    return scores, data.labels[chosen]


def near_metrics(scores: np.ndarray, data: CollisionData, threshold: float) -> dict:
    """What the planner needs near the goal, from the scores of ``data.near_poses``:
    ``goal_pass`` = fraction of stable poses called free (a hanging pose that is called
    colliding cannot be reached), and accuracy / precision / recall (positive = colliding
    deeper than 1 mm on the full meshes) of the moved near-contact poses, all of them and per
    kind (jitter: a few mm into or next to the support; approach: the straight line from the
    start; lift: above the hanging pose; transit: where the planner's paths pass the support,
    files of NEAR_VERSION 2). ``near`` leaves the transit poses out (the same rows as before
    version 2); ``transit_apart``: the transit poses whose observed clouds are more than
    ``APART`` apart, where a test on the clouds alone sees no contact."""
    called = scores > threshold
    stable = data.near_kind == NEAR_STABLE
    moved = ~stable & (data.near_kind != NEAR_TRANSIT)
    out = dict(
        threshold=float(threshold),
        goal_pass=float(np.mean(~called[stable])) if stable.any() else float("nan"),
        stable_poses=int(stable.sum()),
        near=collision.binary_metrics(called[moved], data.near_labels[moved]),
    )
    for name, kind in NEAR_KINDS.items():
        rows = data.near_kind == kind
        out[name] = collision.binary_metrics(called[rows], data.near_labels[rows])
    if data.near_gap is not None:
        rows = (data.near_kind == NEAR_TRANSIT) & (data.near_gap > APART)
        out["transit_apart"] = collision.binary_metrics(called[rows], data.near_labels[rows])
    return out


APART = 0.003  # m: observed clouds farther apart than this (near_metrics' transit_apart)


def goal_pass_threshold(
    scores: np.ndarray, data: CollisionData, target: float, lowest=0.5, highest=0.95
) -> float:
    """The lowest probability threshold in [lowest, highest] (steps of 0.01) at which at
    least ``target`` of the stable poses are called free (``highest`` if none): stable goals
    pass while as many near-contact collisions as possible stay detected."""
    stable = scores[data.near_kind == NEAR_STABLE]
    for t in np.arange(lowest, highest + 1e-9, 0.01):
        if np.mean(stable <= t) >= target:
            return round(float(t), 2)
    return float(highest)


def nce_score_fn(config, params):
    prob = jax.jit(collision.nce_probability(config))
    return lambda p, oc, sc, poses: prob(params, oc, sc, poses)


def hce_score_fn(config, params):
    """Predicted-normal heuristic: the normal net sees the planner's support subset."""
    normals_fn = jax.jit(
        lambda prm, pts: collision.make_normal_net(config).apply(prm, pts[None])[0]
    )
    score = jax.jit(collision.heuristic_score)
    cache = {}

    def fn(p, oc, sc, poses):
        if p not in cache:
            cache[p] = normals_fn(params, sc)
        return score(oc, sc, cache[p], poses)

    return fn


def true_normals_score_fn(data: CollisionData, n_support):
    score = jax.jit(collision.heuristic_score)

    def fn(p, oc, sc, poses):
        normals = collision.subsample_cloud(data.support_normals[p], n_support, SUBSET_SEED_SUPPORT)
        return score(oc, sc, normals, poses)

    return fn


# ----------------------------------------------------------------------------------------------


def evaluate_only(
    out: Path,
    test: CollisionData,
    eval_labels: int,
    val: CollisionData | None = None,
    goal_pass: float = 0.95,
) -> dict:
    """Held-out metrics of the NCE already in ``out`` (``--eval-only``); with validation
    pairs ``val``, first its threshold (:func:`goal_pass_threshold`), written into its
    config."""
    cfg, params, meta = collision.load_estimator(out / "nce")
    fn = nce_score_fn(cfg, params)
    n_obj, n_sup = cfg.object_input, cfg.support_input
    result = {}
    if val is not None and val.near_poses is not None:
        s = score_poses(val, val.near_pair, val.near_poses, fn, n_obj, n_sup)
        threshold = goal_pass_threshold(s, val, goal_pass)
        cfg = dataclasses.replace(cfg, threshold=threshold)
        result["validation"] = dict(
            pairs=len(val.meta), chosen=near_metrics(s, val, threshold),
            at_05=near_metrics(s, val, 0.5),
        )  # fmt: skip
    s, y = estimator_scores(test, fn, n_obj, n_sup, eval_labels)
    result |= dict(test_pairs=len(test.meta), threshold=cfg.threshold)
    for t in sorted({cfg.threshold, 0.5}):
        result[f"labels_at_{t:g}"] = collision.binary_metrics(s > t, y)
    if test.near_poses is not None:
        s = score_poses(test, test.near_pair, test.near_poses, fn, n_obj, n_sup)
        for t in sorted({cfg.threshold, 0.5, 0.7, 0.9}):
            result[f"near_at_{t:g}"] = near_metrics(s, test, t)
    with open(out / "metrics_eval.json", "w") as f:
        json.dump(result, f, indent=2)
    if "validation" in result:  # the chosen threshold goes into the NCE's config
        extra = {k: v for k, v in meta.items() if k not in ("kind", "config")}
        collision.save_estimator(out / "nce", cfg, params, **extra, eval_only=result)
    print(json.dumps(_brief(result)))
    return result


def _completer(args, progress: bool):
    """CollisionData -> CollisionData: with ``--completion`` the completed clouds
    (:func:`complete_collision_data`, cached beside the pair files), else unchanged."""
    if not args.completion:
        return lambda data: data
    cache = Path(args.derived_dir or os.path.join(args.data, DERIVED))
    cache = cache / f"completed_{Path(args.completion).name}"

    def completed(data: CollisionData) -> CollisionData:
        t0 = time.time()
        eyes = record_eyes(args.data, [m["pair_index"] for m in data.meta])
        out = complete_collision_data(data, args.completion, eyes, cache, progress)
        print(f"completed clouds of {len(data.meta)} pairs in {time.time() - t0:.0f} s", flush=True)
        return out

    return completed


def _brief(result: dict) -> dict:
    """The headline numbers of evaluate_only's result."""
    out = {"threshold": result["threshold"]}
    for k, v in result.items():
        if k.startswith("labels_at_"):
            out[k] = {x: round(v[x], 3) for x in ("accuracy", "precision", "recall")}
        elif k.startswith("near_at_"):
            out[k] = dict(
                goal_pass=round(v["goal_pass"], 3),
                near_recall=round(v["near"]["recall"], 3),
                near_precision=round(v["near"]["precision"], 3),
                free_precision=round(v["near"]["free_precision"], 3),
                jitter_recall=round(v["jitter"]["recall"], 3),
                jitter_specificity=round(v["jitter"]["specificity"], 3),
                lift_specificity=round(v["lift"]["specificity"], 3),
                approach_specificity=round(v["approach"]["specificity"], 3),
                transit_recall=round(v["transit"]["recall"], 3),
                transit_free_precision=round(v["transit"]["free_precision"], 3),
            )
            if "transit_apart" in v:
                out[k]["transit_apart_recall"] = round(v["transit_apart"]["recall"], 3)
    return out


def _budgets(text: str) -> dict[str, float]:
    out = {"nce": 300.0, "normals": 60.0}
    for item in filter(None, text.split(",")):
        name, _, value = item.partition("=")
        if name not in out:
            raise ValueError(f"--time-budget: unknown part {name!r} (nce, normals)")
        out[name] = float(value)
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", default="datasets/paper", help="dataset (recipe.json + shards/)")
    parser.add_argument("--out", required=True, help="output folder for the weights")
    parser.add_argument("--preset", default="fast", choices=sorted(collision.NCE_PRESETS))
    parser.add_argument("--normal-preset", default=None, help="default: --preset")
    parser.add_argument(
        "--support-crop-from",
        type=int,
        default=0,
        help="NCE: given this many support points, keep the preset's number nearest to the "
        "posed object (collision.NCEConfig.support_crop_from; 0: off)",
    )
    parser.add_argument("--train-pairs", type=int, default=200)
    parser.add_argument("--test-pairs", type=int, default=60)
    parser.add_argument("--steps", type=int, default=1_000_000, help="cap on steps per network")
    parser.add_argument(
        "--time-budget",
        default="nce=300,normals=60",
        help="seconds per network (normals=0: no normal net, no HCE metrics)",
    )
    parser.add_argument("--batch", type=int, default=64, help="NCE batch (poses)")
    parser.add_argument("--normal-batch", type=int, default=16, help="normal-net batch (clouds)")
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam lr (the cosine's peak)")
    parser.add_argument(
        "--lr-schedule",
        choices=["constant", "cosine"],
        default="constant",
        help="NCE: constant, or warm-up + cosine decay over its time budget (train_nce)",
    )
    parser.add_argument(
        "--near-share",
        type=float,
        default=0.0,
        help="NCE: fraction of each batch drawn from the near-contact training poses (--near 1)",
    )
    parser.add_argument(
        "--transit-share",
        type=float,
        default=0.0,
        help="NCE: fraction of each batch drawn from the transit poses alone (on top of "
        "--near-share; files of near version 2, --transit 1)",
    )
    parser.add_argument(
        "--mined", default=None, metavar="DIR",
        help="NCE: the planner's own states on training pairs, labelled by the meshes "
        "(eval_paths --split train --mine DIR), as training rows of the pairs they belong to",
    )  # fmt: skip
    parser.add_argument(
        "--mined-share", type=float, default=0.0,
        help="NCE: fraction of each batch drawn from the --mined states alone",
    )  # fmt: skip
    parser.add_argument(
        "--planner-labels",
        type=int,
        default=0,
        help="1: the dataset's poses labelled by the planner's ground truth (mesh penetration "
        "> 1 mm, as the evaluation) instead of any touch; training pairs only",
    )
    parser.add_argument(
        "--val-curve-every",
        type=int,
        default=0,
        help="NCE: validation loss on the validation pairs every N steps (0: off)",
    )
    parser.add_argument(
        "--stable-free",
        type=int,
        default=1,
        help="1: the training pairs' stable poses are free labels too (hanging poses rest on "
        "the support, < 1 mm deep: free by the planner's ground truth); 0: off",
    )
    parser.add_argument(
        "--far-per-pair",
        type=int,
        default=100,
        help="far free poses per training pair (0: the dataset's labels only)",
    )
    parser.add_argument(
        "--near",
        type=int,
        default=1,
        help="1: train on the pairs' near-contact poses with their mesh labels too "
        "(near_contact_poses: hard negatives a few mm into the support, clearances, the "
        "approach); 0: off (they are still scored on held-out pairs)",
    )
    parser.add_argument(
        "--transit",
        type=int,
        default=1,
        help="with --near 1: 1 trains on the transit poses too (NEAR_TRANSIT, files of near "
        "version 2: where the planner's paths pass the support); 0: a control without them "
        "(still scored on held-out pairs)",
    )
    parser.add_argument(
        "--val-every",
        type=int,
        default=20,
        help="training-split pairs with pair_index %% N == 0 are not trained on: the NCE "
        "threshold is chosen on them (0: none, threshold 0.5)",
    )
    parser.add_argument(
        "--goal-pass",
        type=float,
        default=0.95,
        help="NCE threshold: the lowest in [0.5, 0.95] that calls this fraction of the "
        "validation pairs' stable poses free (0: keep 0.5)",
    )
    parser.add_argument("--eval-labels", type=int, default=20000, help="held-out labels scored")
    parser.add_argument("--threshold-labels", type=int, default=20000, help="training labels")
    parser.add_argument(
        "--threshold-pairs", type=int, default=400, help="HCE thresholds: of these first pairs"
    )
    parser.add_argument(
        "--derived-dir", default=None, help="pair files (default: DATA/derived/collision)"
    )
    parser.add_argument("--workers", type=int, default=1, help="derive processes (0 = all cores)")
    parser.add_argument("--resume", action="store_true", help="start from the weights in OUT")
    parser.add_argument("--derive-only", action="store_true", help="derive the pairs, then stop")
    parser.add_argument(
        "--existing-only", action="store_true", help="use only pairs already derived"
    )
    parser.add_argument(
        "--eval-only",
        action="store_true",
        help="score the NCE in OUT on the held-out pairs (labels, goal pass, near contact) "
        "at its threshold and at 0.5; writes OUT/metrics_eval.json",
    )
    parser.add_argument(
        "--eval-val-pairs",
        type=int,
        default=0,
        help="--eval-only: also choose the NCE threshold (--goal-pass) on this many validation "
        "pairs (pair_index %% --val-every == 0, never trained on), derived if needed",
    )
    parser.add_argument(
        "--deadline",
        type=float,
        default=0.0,
        help="unix time by which everything must be written: the NCE trains for what is left "
        "after loading, compilation and the reserves (0: --time-budget only)",
    )
    parser.add_argument(
        "--post-reserve-s", type=float, default=60.0, help="--deadline: after the NCE trains"
    )
    parser.add_argument(
        "--compile-reserve-s", type=float, default=45.0, help="--deadline: per compilation"
    )
    parser.add_argument(
        "--completion",
        default=None,
        metavar="FOLDER",
        help="train on completed clouds (twenty-eighth session): half observed, half the "
        "shape-completion networks' carved prediction (FOLDER/object, FOLDER/support; "
        "completion.completed_cloud); the NCE's config records input_clouds=completed so that "
        "the planner builds the same clouds. Needs --time-budget normals=0",
    )
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    progress = not args.no_progress
    budgets = _budgets(args.time_budget)
    train_normal_net = budgets["normals"] > 0
    if args.completion and train_normal_net:
        parser.error("--completion: the predicted points have no normals; pass --time-budget "
                     "...,normals=0")  # fmt: skip
    if args.completion and not (Path(args.completion) / "object" / "config.json").exists():
        parser.error(f"--completion {args.completion}: no object/config.json there")
    phases: list = []

    def phase(name: str) -> None:  # wall-clock log of the phases (stdout, flushed)
        seconds = round(time.time() - T_IMPORT, 1)
        phases.append((name, seconds))
        print(f"[{seconds} s since start] {name}", flush=True)

    workers = args.workers or len(os.sched_getaffinity(0))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    nce_cfg = collision.NCE_PRESETS[args.preset]
    if args.support_crop_from:
        nce_cfg = dataclasses.replace(nce_cfg, support_crop_from=args.support_crop_from)
    normal_name = args.normal_preset or args.preset
    if normal_name not in collision.NORMAL_PRESETS:
        raise SystemExit(f"--normal-preset must be one of {sorted(collision.NORMAL_PRESETS)}")
    normal_cfg = collision.NORMAL_PRESETS[normal_name]

    t0 = time.time()
    files = derive_collision_pairs(
        args.data,
        {"test": args.test_pairs, "train": args.train_pairs},  # held-out first: a cut-short
        workers,  # derive still has them all
        progress,
        out_dir=args.derived_dir,
        existing_only=args.existing_only,
    )
    train_files, test_files = files["train"], files["test"]
    val_files = []
    if args.val_every > 0:
        val_files = [f for f in train_files if int(f.stem.split("_")[0]) % args.val_every == 0]
        train_files = [f for f in train_files if f not in set(val_files)]
    derive_s = time.time() - t0
    if args.derive_only:
        print(
            f"derived: {len(train_files)} train, {len(test_files)} test pairs in {derive_s:.0f} s"
        )
        return {"train_files": len(train_files), "test_files": len(test_files)}
    completed = _completer(args, progress)
    if args.eval_only:
        val = None
        if args.val_every > 0 and args.eval_val_pairs > 0:
            val_files = derive_collision_pairs(
                args.data, {"train": args.eval_val_pairs}, workers, progress,
                out_dir=args.derived_dir, only=lambda i: i % args.val_every == 0,
            )["train"]  # fmt: skip
            val = completed(load_collision_data(val_files))
        return evaluate_only(
            out, completed(load_collision_data(test_files)), args.eval_labels, val, args.goal_pass
        )
    train = load_collision_data(
        train_files,
        far_per_pair=args.far_per_pair,
        stable_free=bool(args.stable_free),
        near_train=bool(args.near),
        planner_labels=bool(args.planner_labels),
        transit_train=bool(args.transit),
        mined_dir=args.mined,
    )
    if args.mined:
        n_mined = 0 if train.far_mined is None else int(train.far_mined.sum())
        n_pairs = 0 if train.far_mined is None else len(np.unique(train.far_pair[train.far_mined]))
        print(f"mined: {n_mined} states of {n_pairs} training pairs from {args.mined}")
        if args.mined_share > 0 and not n_mined:
            raise SystemExit(
                f"--mined {args.mined}: none of its files is a training pair loaded here "
                "(derive those pairs first)"
            )
    test = load_collision_data(test_files)
    # the validation curve measures the training objective: the same labels as training
    # (the threshold and the metrics below read the near-contact poses, labelled either way)
    val = (
        load_collision_data(val_files, planner_labels=bool(args.planner_labels))
        if val_files
        else None
    )
    train, test = completed(train), completed(test)
    val = completed(val) if val is not None else None
    held_out = {m["pair_index"] for m in test.meta}
    if val is not None:
        held_out |= {m["pair_index"] for m in val.meta}
    if held_out & {m["pair_index"] for m in train.meta} or any(
        m["split"] != "train" for m in train.meta
    ):
        raise RuntimeError("a held-out (or validation) pair reached the training set")
    print(
        f"pairs: {len(train.meta)} train ({len(train.labels)} labels, "
        f"{train.labels.mean():.1%} colliding), {len(test.meta)} held out "
        f"({len(test.labels)} labels), {len(val_files)} validation pairs; "
        f"{0 if train.far_labels is None else len(train.far_labels)} extra training poses "
        f"({args.far_per_pair} far free per pair, stable free {args.stable_free}, near "
        f"{args.near}); "
        f"derived in {derive_s:.0f} s; device {jax.devices()[0]}"
    )

    phase("loaded")
    nce_params = normal_params = None
    if args.resume and (out / "nce" / "config.json").exists():
        nce_cfg, nce_params, _ = collision.load_estimator(out / "nce")
    if args.completion:  # also a fine-tune of an NCE trained on observed clouds
        nce_cfg = dataclasses.replace(nce_cfg, input_clouds="completed")
    elif nce_cfg.input_clouds != "observed":
        raise SystemExit(f"the NCE in {out} was trained on {nce_cfg.input_clouds} clouds: "
                         "pass --completion")  # fmt: skip
    if args.resume and (out / "hce_normals" / "config.json").exists():
        normal_cfg, normal_params, _ = collision.load_estimator(out / "hce_normals")

    # the NCE's training time: what --deadline leaves after loading (measured), compilation
    # and what must follow (NCE threshold + held-out metrics, then the normal net and HCEs)
    nce_budget = budgets["nce"]
    if args.deadline:
        after = args.post_reserve_s + (budgets["normals"] if train_normal_net else 0.0)
        nce_budget = min(nce_budget, args.deadline - time.time() - args.compile_reserve_s - after)
        if nce_budget < 1:
            raise SystemExit(
                f"--deadline leaves no time to train the NCE ({nce_budget:.0f} s after loading; "
                f"reserves: compile {args.compile_reserve_s:.0f} s, after {after:.0f} s)"
            )
        print(
            f"NCE time budget {nce_budget:.0f} s (deadline in {args.deadline - time.time():.0f} s)"
        )
    nce_params, nce_log = train_nce(
        train, nce_cfg, args.steps, nce_budget, args.batch, args.lr, params=nce_params,
        progress=progress,
        stop_at=args.deadline - after if args.deadline else None,
        near_share=args.near_share, schedule=args.lr_schedule,
        transit_share=args.transit_share, mined_share=args.mined_share,
        val=val if args.val_curve_every > 0 else None, val_every=args.val_curve_every,
    )  # fmt: skip
    collision.save_estimator(out / "nce", nce_cfg, nce_params, train=nce_log, evaluated=False)
    write_curves(out, nce_log)
    phase(f"NCE trained ({nce_log['steps']} steps, compiled in {nce_log['compile_s']} s)")

    # the NCE threshold: stable goals of validation pairs pass (near_metrics, --goal-pass)
    n_obj, n_sup = nce_cfg.object_input, nce_cfg.support_input
    nce_fn = nce_score_fn(nce_cfg, nce_params)
    validation = {}
    if val is not None and args.goal_pass > 0 and val.near_poses is not None:
        s = score_poses(val, val.near_pair, val.near_poses, nce_fn, n_obj, n_sup)
        threshold = goal_pass_threshold(s, val, args.goal_pass)
        validation = {
            "at_0.5": near_metrics(s, val, 0.5),
            "chosen": near_metrics(s, val, threshold),
        }
        nce_cfg = dataclasses.replace(nce_cfg, threshold=threshold)
    metrics = {}
    s, y = estimator_scores(test, nce_fn, n_obj, n_sup, args.eval_labels)
    metrics["nce"] = collision.binary_metrics(s > nce_cfg.threshold, y)
    metrics["nce_at_0.5"] = collision.binary_metrics(s > 0.5, y)
    near_held_out = {}
    if test.near_poses is not None:
        s = score_poses(test, test.near_pair, test.near_poses, nce_fn, n_obj, n_sup)
        near_held_out = {
            "nce": near_metrics(s, test, nce_cfg.threshold),
            "nce_at_0.5": near_metrics(s, test, 0.5),
        }
    summary = dict(
        device=str(jax.devices()[0]),
        train_pairs=len(train.meta),
        train_labels=int(len(train.labels)),
        test_pairs=len(test.meta),
        test_labels=int(len(test.labels)),
        derive_s=round(derive_s, 1),
        far_free_per_pair=args.far_per_pair,
        stable_poses_free=bool(args.stable_free),
        nce=nce_log,
        nce_threshold=nce_cfg.threshold,
        near_training=bool(args.near),
        transit_training=bool(args.near and args.transit),
        transit_share=args.transit_share,
        mined=args.mined,
        mined_share=args.mined_share,
        near_share=args.near_share,
        planner_labels=bool(args.planner_labels),
        lr=args.lr,
        lr_schedule=args.lr_schedule,
        validation_pairs=len(val_files),
        validation=validation,
        held_out=metrics,
        held_out_near=near_held_out,
        phases=phases,
    )
    extra = dict(train_pairs=len(train.meta), held_out=metrics, held_out_near=near_held_out)
    collision.save_estimator(out / "nce", nce_cfg, nce_params, train=nce_log, **extra)
    with open(out / "metrics.json", "w") as f:  # written again below with the HCEs
        json.dump(summary, f, indent=2)
    phase("NCE threshold and held-out metrics")

    if train_normal_net:
        normal_budget = budgets["normals"]
        if args.deadline:  # what is left after compiling it and the HCE metrics
            normal_budget = min(
                normal_budget,
                args.deadline - time.time() - args.compile_reserve_s - args.post_reserve_s / 2,
            )
        if normal_budget < 1:
            print(f"skipped the normal net and the HCEs: {normal_budget:.0f} s left for them")
            train_normal_net = False
    if train_normal_net:
        normal_params, normal_log = train_normals(
            train, normal_cfg, args.steps, normal_budget, args.normal_batch, args.lr,
            params=normal_params, progress=progress,
            stop_at=args.deadline - args.post_reserve_s / 2 if args.deadline else None,
        )  # fmt: skip
        collision.save_estimator(
            out / "hce_normals", normal_cfg, normal_params, train=normal_log, evaluated=False
        )
        phase(f"normal net trained ({normal_log['steps']} steps)")
        # HCE thresholds on training labels, metrics on held-out labels
        h_obj, h_sup = nce_cfg.object_points, normal_cfg.points
        hce_train, y_train = estimator_scores(
            train, hce_score_fn(normal_cfg, normal_params), h_obj, h_sup,
            args.threshold_labels, max_pairs=args.threshold_pairs,
        )  # fmt: skip
        hce_threshold = collision.balanced_threshold(hce_train, y_train)
        true_train, y_true_train = estimator_scores(
            train, true_normals_score_fn(train, h_sup), h_obj, h_sup, args.threshold_labels,
            max_pairs=args.threshold_pairs,
        )  # fmt: skip
        true_threshold = collision.balanced_threshold(true_train, y_true_train)
        normal_cfg = dataclasses.replace(normal_cfg, threshold=hce_threshold)
        s, y = estimator_scores(
            test, hce_score_fn(normal_cfg, normal_params), h_obj, h_sup, args.eval_labels
        )
        metrics["hce"] = collision.binary_metrics(s > hce_threshold, y)
        s, y = estimator_scores(
            test, true_normals_score_fn(test, h_sup), h_obj, h_sup, args.eval_labels
        )
        metrics["hce_true_normals"] = collision.binary_metrics(s > true_threshold, y)
        summary |= dict(
            normals=normal_log, hce_threshold=hce_threshold,
            hce_true_normals_threshold=true_threshold,
        )  # fmt: skip
        collision.save_estimator(
            out / "hce_normals", normal_cfg, normal_params, train=normal_log, **extra
        )
        with open(out / "hce_true_normals.json", "w") as f:
            json.dump(dict(threshold=true_threshold, points=h_sup, held_out=metrics), f, indent=2)
        phase("HCE thresholds and held-out metrics")
    with open(out / "metrics.json", "w") as f:
        json.dump(summary, f, indent=2)
    for name, m in metrics.items():
        print(
            f"held-out {name}: accuracy {m['accuracy']:.3f} precision {m['precision']:.3f} "
            f"recall {m['recall']:.3f} balanced {m['balanced_accuracy']:.3f} (n={m['n']})"
        )
    for name, m in near_held_out.items():
        print(
            f"held-out near {name} (threshold {m['threshold']:.2f}): goal pass "
            f"{m['goal_pass']:.3f} of {m['stable_poses']} stable poses; near-contact accuracy "
            f"{m['near']['accuracy']:.3f} precision {m['near']['precision']:.3f} recall "
            f"{m['near']['recall']:.3f} free precision {m['near']['free_precision']:.3f} "
            f"(n={m['near']['n']}); jitter P/R {m['jitter']['precision']:.3f}/"
            f"{m['jitter']['recall']:.3f}"
        )
    return summary


if __name__ == "__main__":
    main()
