"""The collision estimators' pair files: clouds, collision labels, near-contact and far poses.

``derive_collision_pairs`` derives what the estimators (and the approach networks) train on,
per pair of the dataset (resumable, cached in ``DATA/derived/collision/<split>/``): the
partial clouds with normals (the same arrays as ``experiments.derive_dataset``, reused when
present: same ray casts, same seed), the pair's collision poses regenerated from its seed
(``sim.dataset.collision_poses``) with their labels, its stable poses and the near-contact
poses labelled by the planner's own ground truth (``meshes.MeshChecker``).
"""

from __future__ import annotations

import dataclasses
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from omnihang_jax import collision, dataset_bridge
from omnihang_jax.meshes import start_pose

DERIVED = os.path.join(dataset_bridge.DERIVED_DIRNAME, "collision")  # ignored by git
VAL_EVERY = 20  # training pairs with pair_index % VAL_EVERY == 0: the NCE's validation pairs
NEAR_TOLERANCE = 1e-3  # m: the planner's penetration tolerance (meshes.MeshChecker)


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
# Version 2 adds the transit poses; versions 1 and 2 draw the same
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

    Measured: 10 of the hybrid's 15 colliding paths collide more than 4.5 cm
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
    starts in, and calls it colliding (measured)."""
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


# ----------------------------------------------------------------------------------------------
# Loading pair files for training and evaluation


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
    far_poses: np.ndarray | None = None  # [F, 7] far free poses, stable poses, near poses
    far_labels: np.ndarray | None = None  # [F] bool (True = colliding; near poses only)
    far_near: np.ndarray | None = None  # [F] bool: the row is a near-contact pose
    # near-contact poses of the pairs (near_contact_poses), labelled by the planner's ground
    # truth (penetration > NEAR_TOLERANCE on the full meshes)
    near_pair: np.ndarray | None = None  # [K] int32
    near_poses: np.ndarray | None = None  # [K, 7]
    near_kind: np.ndarray | None = None  # [K] int8 (NEAR_STABLE ... NEAR_TRANSIT)
    near_labels: np.ndarray | None = None  # [K] bool


def _geometry_of(f: dict, meta: dict, cache: dict) -> dict:
    """The pair's geometry from its file, or (files derived before it was stored) rebuilt
    from the library."""
    if "object_half_diagonal" in f:
        return {k: f[k] for k in ("object_half_diagonal", "support_bounds", "wall_y")}
    if "library" not in cache:
        from sim.library import LibraryConfig, build_library

        cache["library"] = build_library(LibraryConfig(), progress=False)
    lib = cache["library"]
    return pair_geometry(lib.objects[meta["object_name"]], lib.supports[meta["support_name"]])


def load_collision_data(
    files: list[Path],
    far_per_pair: int = 0,
    seed: int = 0,
    recipe_library=None,
    training: bool = False,
    planner_labels: bool = False,
) -> CollisionData:
    """Clouds and labels of the pair files. The near-contact poses are always loaded
    (``near_*``, for the metrics) when the files have them.

    ``far_per_pair``: far free poses per pair (:func:`far_free_poses`) as extra training rows;
    ``training``: the pair's stable poses as free rows and its moved near-contact poses
    (jitter, approach, lift: not the stable nor the transit ones) with their mesh labels
    (``far_near``).

    ``planner_labels``: the dataset's labelled poses are labelled by the planner's ground
    truth instead (deepest mesh penetration ``collision_penetration`` > NEAR_TOLERANCE, where
    the file has it): the dataset calls any touch colliding, the planner and its evaluation
    allow 1 mm, and the stable poses (free rows) rest in contact, so without this the NCE is
    taught both sides of the same millimetre."""
    if not files:
        raise ValueError("no pair files to load")
    rng = np.random.default_rng(seed)
    cache: dict = {} if recipe_library is None else {"library": recipe_library}
    far: dict[str, list] = {k: [] for k in ("pair", "poses", "labels", "near")}

    def add_far(i, poses_, labels_, near_=False):
        far["pair"].append(np.full(len(poses_), i, np.int32))
        far["poses"].append(np.asarray(poses_, np.float32))
        far["labels"].append(np.asarray(labels_, bool))
        far["near"].append(np.full(len(poses_), near_, bool))

    near: dict[str, list] = {"pair": [], "poses": [], "kind": [], "labels": []}
    keys = ("object_points", "object_normals", "support_points", "support_normals")
    clouds: dict[str, list] = {k: [] for k in keys}
    pair, poses, labels, meta = [], [], [], []

    def read(path):  # zlib releases the GIL: threads read ~4x faster than one loop
        with np.load(path) as f:
            return {k: f[k] for k in f.files}

    with ThreadPoolExecutor(8) as pool:
        contents = pool.map(read, files)
    for i, f in enumerate(contents):
        for k in keys:
            clouds[k].append(f[k])
        poses.append(f["collision_poses"])
        if planner_labels and "collision_penetration" in f:
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
        if training:
            stable = f["stable_poses"].astype(np.float32)
            add_far(i, stable, np.zeros(len(stable), bool))
        if "near_poses" in f:
            kind = f["near_kind"]
            label = f["near_penetration"] > NEAR_TOLERANCE
            near["pair"].append(np.full(len(kind), i, np.int32))
            near["poses"].append(f["near_poses"].astype(np.float32))
            near["kind"].append(kind)
            near["labels"].append(label)
            if training:
                moved = (kind != NEAR_STABLE) & (kind != NEAR_TRANSIT)
                add_far(i, f["near_poses"][moved], label[moved], True)
    return CollisionData(
        *(np.stack(clouds[k]) for k in keys),
        pair=np.concatenate(pair),
        poses=np.concatenate(poses).astype(np.float32),
        labels=np.concatenate(labels),
        meta=meta,
        **{f"far_{k}": np.concatenate(v) if v else None for k, v in far.items()},
        **{f"near_{k}": np.concatenate(v) if v else None for k, v in near.items()},
    )
