"""Held-out hanging success of the where-to-hang answer, end to end (docs/evaluation.md).

One run of :func:`omnihang_jax.where.load_where` per batch of pairs gives every answer the
figures need; each is simulated on the pair's TRUE meshes with the evaluation protocol
(``omnihang_jax.evaluate.protocol_stability``: 1 s from rest, > 3 mm initial penetration
fails). Success is "stable"; a figure is the mean over object categories of the per-category
success.

The answers of a pair (:data:`ANSWERS`):

* ``stage1_network``: the network's first Stage-1 proposal as predicted (the paper's reading);
* ``stage1``: the least penetrating of the K proposals, released ``stage1.ANSWER_LIFT`` up;
* ``stage1_2``: the least penetrating of the K Stage-2 poses, released ``stage2.ANSWER_LIFT`` up;
* ``stage1_3``: the rule's best candidate refined from a Stage-1 proposal (configs that refine
  from Stage 1 only);
* ``all_stages_unchecked``: the rule's best candidate;
* ``all_stages``: the answer after the observed-cloud check (= unchecked when the check is off).

The check and the simulations run in worker processes (each holding the asset library) while
the networks run the next batch. Records are one JSON line per pair, appended as pairs finish:
a killed run resumes where it stopped.
"""

from __future__ import annotations

import functools
import json
import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from omnihang_jax import where as where_mod
from omnihang_jax.hang_inputs import _estimate_normals
from omnihang_jax.refine import label_job, library_pool

__all__ = ["ANSWERS", "evaluate_where", "pair_files", "read_records", "summarise"]

ANSWERS = (
    "stage1_network",
    "stage1",
    "stage1_2",
    "stage1_3",
    "all_stages_unchecked",
    "all_stages",
)
VALIDATION_FRACTION = 0.1  # the trainers' validation objects (data.validation_objects)
FRAMES = ("library", "any")
CLOUD_KEYS = ("object_points", "object_normals", "support_points", "support_normals")
ANY_FRAME_SHIFT = 0.1  # m: the object's origin anywhere in a 20-cm cube (any frame)
NOISE_SEED = 20261208  # the degraded clouds' draws: fold in the seed and the pair


def any_frame(seed: int, pair_index: int, free_standing: bool) -> dict:
    """The any-frame protocol's turn of one pair, the same for every config: the object in a
    uniform random SO(3) frame shifted up to ``ANY_FRAME_SHIFT`` per axis; a free-standing
    support turned about z by a uniform angle (wall-mounted ones keep their wall at -y)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng([20261207, int(seed), int(pair_index)])
    q = rng.normal(size=4)
    yaw = float(rng.uniform(-np.pi, np.pi))
    return dict(
        object_rotation=Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix(),  # q as wxyz: uniform
        object_shift=rng.uniform(-ANY_FRAME_SHIFT, ANY_FRAME_SHIFT, 3),
        support_yaw=yaw if free_standing else 0.0,
    )


@functools.cache
def pair_eyes(dataset_dir: str) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """{pair index: (object camera, support camera)} of a dataset: where each pair's clouds
    were seen from (object frame / support frame), the rays that depth noise runs along."""
    from sim import dataset

    return {int(r["pair_index"]): (np.asarray(r["object_eye"], float),
                                   np.asarray(r["support_eye"], float))
            for r in dataset.load_records(dataset_dir)}  # fmt: skip


def degrade_clouds(clouds: dict, eyes: tuple, depth_noise: float, dropout: float,
                   rng: np.random.Generator) -> dict:  # fmt: skip
    """The pair's clouds as a worse sensor gives them: Gaussian noise of ``depth_noise`` m
    (standard deviation) along each point's camera ray, the normals then re-estimated from
    the noisy points (``hang_inputs._estimate_normals``, the estimate the ``hang`` command makes
    for clouds without normals, turned towards the camera); a random ``dropout`` share of the points lost, the rest resampled to
    the same count. Applied in the frames the clouds were seen in, before any turn."""
    out = {}
    for part, eye in zip(("object", "support"), eyes, strict=True):
        pts = np.asarray(clouds[f"{part}_points"], np.float64)
        nrm = np.asarray(clouds[f"{part}_normals"], np.float64)
        n = len(pts)
        if dropout > 0:
            keep = rng.permutation(n)[: max(1, int(round(n * (1 - dropout))))]
            idx = keep[rng.integers(0, len(keep), n)]
            idx[: len(keep)] = keep  # every kept point once, the rest drawn again
            pts, nrm = pts[idx], nrm[idx]
        if depth_noise > 0:
            ray = pts - eye
            ray /= np.linalg.norm(ray, axis=1, keepdims=True)
            pts = pts + rng.normal(scale=depth_noise, size=(n, 1)) * ray
            nrm = _estimate_normals(pts, eye)
        out[f"{part}_points"] = pts.astype(np.float32)
        out[f"{part}_normals"] = nrm.astype(np.float32)
    return out


def _yaw_matrix(a: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("z", a).as_matrix()


def turn_clouds(clouds: dict, turn: dict) -> dict:
    """The pair's clouds as handed over in the turned frames."""
    r, s, rz = turn["object_rotation"], turn["object_shift"], _yaw_matrix(turn["support_yaw"])
    f32 = np.float32
    return dict(
        object_points=(np.asarray(clouds["object_points"]) @ r.T + s).astype(f32),
        object_normals=(np.asarray(clouds["object_normals"]) @ r.T).astype(f32),
        support_points=(np.asarray(clouds["support_points"]) @ rz.T).astype(f32),
        support_normals=(np.asarray(clouds["support_normals"]) @ rz.T).astype(f32),
    )


def poses_to_library(poses, turn: dict) -> np.ndarray:
    """Poses [..., 7] of the turned object in the turned support frame -> the same placements
    as poses of the library-frame object in the library-frame support (what the true meshes
    are simulated with): R = Rz^T R' R_o, t = Rz^T (R' s_o + t')."""
    from scipy.spatial.transform import Rotation

    poses = np.asarray(poses, np.float64)
    flat = poses.reshape(-1, 7)
    r_o, s_o = turn["object_rotation"], turn["object_shift"]
    rz_t = _yaw_matrix(turn["support_yaw"]).T
    rot = Rotation.from_quat(flat[:, [4, 5, 6, 3]]).as_matrix()  # wxyz -> scipy's xyzw
    t = np.einsum("ij,nj->ni", rz_t, np.einsum("nij,j->ni", rot, s_o) + flat[:, :3])
    xyzw = Rotation.from_matrix(rz_t[None] @ rot @ r_o[None]).as_quat()
    out = np.concatenate([t, xyzw[:, [3, 0, 1, 2]]], axis=1)
    return out.reshape(poses.shape)


@functools.cache
def free_standing(family: str) -> bool:
    """Whether the support family stands on the floor (no wall): turned about z in any frame."""
    from sim.assets import supports  # noqa: F401  (registers the families)
    from sim.assets.base import SUPPORT_FAMILIES

    if family not in SUPPORT_FAMILIES:
        raise ValueError(f"unknown support family {family!r}: one of {sorted(SUPPORT_FAMILIES)}")
    return not SUPPORT_FAMILIES[family](np.random.default_rng(0)).wall


# The figures of record's sample: the first 1,794 held-out pairs of :func:`pair_files`'s
# category-balanced order (156-157 a category; the full held-out split has 6,345 pairs).
RECORD_PAIRS = 1794


def pair_files(data: str | os.PathLike, split: str, pairs: int | None = None) -> list[Path]:
    """The derived pair files of ``split``: "test" (held-out objects and supports),
    "validation" (the training split's validation objects, never trained on) or "train" (the
    training split less those). ``pairs``: at most this many, taken round robin over the object
    categories (a balanced prefix)."""
    from omnihang_jax import data as data_mod
    from omnihang_jax import dataset_bridge

    if split not in ("test", "validation", "train"):
        raise ValueError(f"split must be 'test', 'validation' or 'train', got {split!r}")
    _, derived = dataset_bridge.resolve_dataset_dir(data)
    files = dataset_bridge.derived_files(derived, "test" if split == "test" else "train")
    if split != "test":
        names = [data_mod.object_name_of(os.fspath(f)) for f in files]
        fit, val = data_mod.split_by_object(names, VALIDATION_FRACTION)
        files = [files[i] for i in (val if split == "validation" else fit)]
    by_cat: dict[str, list[Path]] = {}
    for f in files:
        obj = f.name.split("__")[0].split("_", 1)[1]
        by_cat.setdefault(obj.rsplit("_", 1)[0], []).append(f)
    groups = list(by_cat.values())
    order = [g[i] for i in range(max(map(len, groups), default=0)) for g in groups if i < len(g)]
    return order if pairs is None else order[:pairs]


def judge_pair(job: dict) -> dict:
    """Worker: the observed-cloud check of one pair, then its answers simulated on the true
    meshes. ``job``: object, support, clouds, ranked [C, 7], answers {name: [7]}, check (reach)."""
    from omnihang_jax.refine import worker_library
    from sim import kernels, observed

    lib = worker_library()
    support = lib.supports[job["support"]]
    turn = job.get("turn")
    pick, tried, note = 0, 0, None
    if job["check"] > 0:
        try:  # floor and wall stay where they are: a turn about z keeps both
            pick, status = observed.first_staying(
                job["clouds"], job["ranked"], support.floor_z, support.wall_y, job["check"]
            )
            tried = int((status != -2).sum())
        except ValueError as err:  # a malformed cloud: the check is skipped, said in the record
            note = f"check skipped: {err}"
    answers = dict(job["answers"])
    answers["all_stages"] = job["ranked"][pick]
    names = list(answers)
    poses = np.stack([np.asarray(answers[n], np.float64) for n in names])
    if turn is not None:  # the answers of the turned clouds, as placements of the true meshes
        poses = poses_to_library(poses, turn)
    status, _ = label_job((job["object"], job["support"], poses))
    return dict(
        check_pick=int(pick), check_tried=tried, check_note=note,
        status={n: kernels.STATUS_NAMES[int(s)] for n, s in zip(names, status, strict=True)},
        poses={n: np.round(p, 6).tolist() for n, p in zip(names, poses, strict=True)},
    )  # fmt: skip


def read_records(path: str | os.PathLike) -> list[dict]:
    """The per-pair records of a run (a torn last line, from a kill, is dropped)."""
    rows = []
    if Path(path).exists():
        for line in Path(path).read_text().splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return rows


def evaluate_where(
    config: where_mod.WhereConfig,
    files: Sequence[str | os.PathLike],
    records_path: str | os.PathLike,
    seed: int = 0,
    batch: int = 8,
    workers: int = 0,
    progress: bool = True,
    dataset_dir: str | os.PathLike | None = None,
    frame: str = "library",
    depth_noise: float = 0.0,
    dropout: float = 0.0,
) -> list[dict]:
    """Run the answer on every pair file not yet in ``records_path`` and append its record;
    returns all records of the file (earlier ones included). ``workers`` > 0: that many
    processes check and simulate while the networks run; 0: in this process. ``frame``:
    "library" (the clouds as derived) or "any" (:func:`any_frame`: each pair's clouds turned
    before the answer, its answers turned back before the simulation). ``depth_noise`` (m)
    and ``dropout`` (share of points): the clouds degraded first (:func:`degrade_clouds`,
    seeded by the seed and the pair); one records file holds one setting."""
    from tqdm.auto import tqdm

    from omnihang_jax import dataset_bridge, stage3

    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
    files = [Path(f) for f in files]
    if not files:
        return read_records(records_path)
    if dataset_dir is None:
        dataset_dir, _ = dataset_bridge.resolve_dataset_dir(files[0].parent.parent)
    records_path = Path(records_path)
    records_path.parent.mkdir(parents=True, exist_ok=True)
    earlier = read_records(records_path)
    other = {r.get("frame", "library") for r in earlier} - {frame}
    if other:
        raise ValueError(f"{records_path} holds records in the {sorted(other)} frame, not "
                         f"{frame!r}: give another --records file")  # fmt: skip
    if not (0 <= depth_noise < 0.05 and 0 <= dropout < 1):
        raise ValueError(f"depth noise must be in [0, 50 mm) and dropout in [0, 1), got "
                         f"{depth_noise} m and {dropout}")  # fmt: skip
    sensor = dict(depth_noise_m=float(depth_noise), dropout=float(dropout))
    mixed = {(r.get("depth_noise_m", 0.0), r.get("dropout", 0.0)) for r in earlier}
    mixed -= {(sensor["depth_noise_m"], sensor["dropout"])}
    if mixed:
        raise ValueError(f"{records_path} holds records of other clouds (depth noise m, "
                         f"dropout: {sorted(mixed)}): give another --records file")  # fmt: skip
    done = {int(r["pair_index"]) for r in earlier if r.get("seed") == seed}
    todo = [f for f in files if _pair_index(f) not in done]
    if not todo:
        return read_records(records_path)
    where = where_mod.load_where(config)
    starts = config.pipeline.starts
    pool = library_pool(dataset_dir, workers)
    pending: list = []
    bar = tqdm(total=len(todo), desc=f"where ({len(done)} done)", disable=not progress)

    def drain(all_: bool) -> None:
        with records_path.open("a") as out:
            while pending and (all_ or not pool or pending[0][1].done()):
                meta, result = pending.pop(0)
                row = {**meta, **(result.result() if pool else result)}
                row["success"] = {n: s == "stable" for n, s in row["status"].items()}
                out.write(json.dumps(row) + "\n")
                out.flush()
                bar.update(1)

    try:
        for i in range(0, len(todo), batch):
            chunk = todo[i : i + batch]
            loaded, pairs, turns = [], [], []
            for f in chunk:
                sample, meta = dataset_bridge.load_pair_file(f)
                pair = {k: np.asarray(getattr(sample, k)) for k in CLOUD_KEYS}
                if depth_noise > 0 or dropout > 0:
                    eyes = pair_eyes(os.fspath(dataset_dir))[int(meta["pair_index"])]
                    rng = np.random.default_rng([NOISE_SEED, int(seed), int(meta["pair_index"])])
                    pair = degrade_clouds(pair, eyes, depth_noise, dropout, rng)
                turn = None
                if frame == "any":
                    turn = any_frame(
                        seed, meta["pair_index"], free_standing(meta["support_family"])
                    )
                    pair = turn_clouds(pair, turn)
                loaded.append(meta)
                pairs.append(pair)
                turns.append(turn)
            padded = pairs + [pairs[0]] * (batch - len(chunk))  # one compiled shape
            clouds = stage3.PairClouds(
                *(np.stack([p[k] for p in padded]).astype(np.float32) for k in CLOUD_KEYS)
            )
            ids = [m["pair_index"] for m in loaded] + [loaded[0]["pair_index"]] * (
                batch - len(chunk)
            )
            out = where.answer(clouds, ids, seed)
            for b, (meta, pair, turn) in enumerate(zip(loaded, pairs, turns, strict=True)):
                answers = {
                    "stage1_network": out.stage1[b, 0],
                    "stage1": where_mod.stage1_answer(
                        pair["object_points"], pair["support_points"], pair["support_normals"],
                        out.stage1[b],
                    ),
                    "stage1_2": where_mod.stage1_2_answer(
                        pair["object_points"], pair["support_points"], pair["support_normals"],
                        out.stage2[b],
                    ),
                }  # fmt: skip
                if "stage1" in starts:
                    answers["stage1_3"] = out.ranked[b][out.start[b] == "stage1"][0]
                answers["all_stages_unchecked"] = out.ranked[b, 0]
                job = dict(object=meta["object_name"], support=meta["support_name"], clouds=pair,
                           ranked=out.ranked[b], answers=answers, check=config.check,
                           turn=turn)  # fmt: skip
                info = dict(
                    pair_index=int(meta["pair_index"]), seed=int(seed), frame=frame, **sensor,
                    object=str(meta["object_name"]), support=str(meta["support_name"]),
                    category=str(meta["object_category"]), family=str(meta["support_family"]),
                )  # fmt: skip
                pending.append((info, pool.submit(judge_pair, job) if pool else judge_pair(job)))
            drain(all_=False)
        drain(all_=True)
    finally:
        bar.close()
        if pool is not None:
            pool.__exit__(None, None, None)
    return read_records(records_path)


def _pair_index(path: Path) -> int:
    return int(path.name.split("_", 1)[0])


def summarise(records: Sequence[dict]) -> dict:
    """Per answer: ``mean`` (over object categories, %), ``per_category``, ``pairs``; with
    several seeds also ``per_seed`` and ``std_over_seeds``."""
    seeds = sorted({int(r["seed"]) for r in records})
    out = {}
    for name in ANSWERS:
        rows = [r for r in records if name in r["success"]]
        if not rows:
            continue
        per_seed = {s: _category_mean([r for r in rows if r["seed"] == s], name) for s in seeds}
        per_seed = {s: v for s, v in per_seed.items() if v is not None}
        cats = sorted({r["category"] for r in rows})
        per_cat = {c: round(100 * float(np.mean([r["success"][name] for r in rows
                                                  if r["category"] == c])), 2)
                   for c in cats}  # fmt: skip
        entry = dict(
            mean=round(float(np.mean([v["mean"] for v in per_seed.values()])), 2),
            per_category=per_cat,
            pairs=len({r["pair_index"] for r in rows}),
        )
        if len(per_seed) > 1:
            entry["per_seed"] = {str(s): round(v["mean"], 2) for s, v in per_seed.items()}
            entry["std_over_seeds"] = round(
                float(np.std([v["mean"] for v in per_seed.values()])), 2
            )
        out[name] = entry
    return out


def _category_mean(rows: Sequence[dict], name: str) -> dict | None:
    if not rows:
        return None
    cats = sorted({r["category"] for r in rows})
    means = [np.mean([r["success"][name] for r in rows if r["category"] == c]) for c in cats]
    return dict(mean=100 * float(np.mean(means)))


def timing_note(t0: float, pairs: int) -> dict:
    """Wall seconds and pairs per second of a run since ``t0``."""
    dt = time.time() - t0
    return dict(wall_s=round(dt, 1), pairs_per_s=round(pairs / dt, 3) if dt > 0 else None)
