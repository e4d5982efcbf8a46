"""How to hang, evaluated: plan held-out pairs with a named planner config and judge every
returned path on the full meshes.

Per held-out pair (a seeded random sample, round robin over the object categories) the goal
is the pair's first stable pose (the paper's protocol) and the start is the planner's start
pose in front of the support (``planner.start_pose``). The planner of the config
(:func:`omnihang_jax.paths.make_planner`, never falling back to the meshes) plans on the
pair's observed clouds, rendered from the dataset's cameras as every other part of the
project sees them. A returned path is checked every 2 mm (the planner's metric) on the full
meshes; it is collision-free when no state penetrates deeper than 1 mm.

Precision = collision-free paths / paths returned, recall = collision-free paths / pairs,
F1 their harmonic mean; pooled over pairs and seeds (and per object category). Each OMPL seed
plans every pair once, in processes of its own (OMPL takes one seed per process).

Writes ``OUT/pairs.jsonl`` (one record per pair and seed, appended as they finish;
a second run skips the pairs and seeds already there) and ``OUT/config.json`` (the planner
config: a run with another config refuses that folder).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from omnihang_jax.paths import Clouds, PlannerConfig

__all__ = [
    "PairSpec",
    "held_out_pairs",
    "evaluate_pair",
    "prf",
    "summarise",
    "read_records",
    "evaluate_paths",
]

RECORDS = "pairs.jsonl"
FRAMES = ("library", "any")


class PairSpec(NamedTuple):
    """One pair of the dataset to plan: what a worker needs to rebuild it (picklable)."""

    pair_index: int
    object_name: str
    support_name: str
    category: str  # the object's category
    seed: int  # the pair's seed (its cameras' depth noise)
    object_eye: tuple  # the dataset's camera positions
    support_eye: tuple
    goal: tuple  # [7] the first stable pose

    @property
    def name(self) -> str:
        from omnihang_jax import dataset_bridge

        return Path(
            dataset_bridge.pair_file_name(self.pair_index, self.object_name, self.support_name)
        ).stem


def held_out_pairs(data: str | os.PathLike, n: int, split: str = "test") -> list[PairSpec]:
    """The first ``n`` pairs of ``split`` with a stable pose and a kept collision pose, in a
    seeded random order (seed 0) within each object category, round robin over the
    categories: the pairs (and order) of
    ``collision_data.derive_collision_pairs(..., shuffle_seed=0)``."""
    from omnihang_jax import dataset_bridge
    from sim import dataset

    if split not in ("test", "train"):
        raise ValueError(f"split must be 'test' or 'train', got {split!r}")
    recipe = dataset_bridge.read_recipe(data)
    pairs = recipe["pairs"]
    jobs = []
    for record in dataset.load_records(data):
        index = int(record["pair_index"])
        if pairs[index][2] != split or len(record["stable_poses"]) == 0:
            continue
        if not np.asarray(record["collision_kept"]).any():
            continue
        jobs.append((record, ""))
    order = np.random.default_rng(0).permutation(len(jobs))
    jobs = dataset_bridge.interleave_by_category([jobs[i] for i in order], pairs)[:n]
    out = []
    for record, _ in jobs:
        index = int(record["pair_index"])
        obj, sup, _ = pairs[index]
        out.append(PairSpec(
            index, obj, sup, obj.rsplit("_", 1)[0], int(record["pair_seed"]),
            tuple(float(x) for x in record["object_eye"]),
            tuple(float(x) for x in record["support_eye"]),
            tuple(float(x) for x in np.asarray(record["stable_poses"][0], float)),
        ))  # fmt: skip
    return out


_WORKER: dict = {}


def _library(data: str):
    """The dataset's asset library and camera settings, once per process."""
    if _WORKER.get("data") != data:
        from omnihang_jax import dataset_bridge
        from sim.library import build_library

        config = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(data))
        _WORKER.update(data=data, library=build_library(config.library, progress=False),
                       camera=config.camera)  # fmt: skip
    return _WORKER["library"], _WORKER["camera"]


def pair_scene(data: str, spec: PairSpec):
    """(scene, object Clouds, support Clouds) of a pair: the observed clouds as the dataset's
    cameras see them (the first two draws of the pair's generator, as derived pair files
    hold them)."""
    from sim import camera
    from sim.scene import build_scene

    library, cam = _library(data)
    scene = build_scene(library.objects[spec.object_name], library.supports[spec.support_name])
    rng = np.random.default_rng([spec.seed, 5])
    oc = camera.partial_cloud(scene, "object", np.asarray(spec.object_eye), rng, cam)
    sc = camera.partial_cloud(scene, "support", np.asarray(spec.support_eye), rng, cam)
    return scene, _clouds(oc), _clouds(sc)


def _clouds(cloud) -> Clouds:
    return Clouds(np.asarray(cloud.points, np.float32), np.asarray(cloud.normals, np.float32))


def turned_object(obj: Clouds, goal: np.ndarray, turn: dict) -> tuple[Clouds, np.ndarray]:
    """The object cloud and the goal [7] with the object handed over in the turned frame of
    ``turn`` (``where_eval.any_frame``; the support stays): points ``R p + s``; the goal the
    same placement of that frame (``where_eval.poses_to_library`` undoes it)."""
    from scipy.spatial.transform import Rotation

    r, shift = turn["object_rotation"], turn["object_shift"]
    rot = Rotation.from_quat(np.asarray(goal, float)[[4, 5, 6, 3]]).as_matrix() @ r.T
    t = np.asarray(goal[:3], float) - rot @ shift
    q = Rotation.from_matrix(rot).as_quat()[[3, 0, 1, 2]]
    cloud = Clouds((obj.points @ r.T + shift).astype(np.float32),
                   (obj.normals @ r.T).astype(np.float32))  # fmt: skip
    return cloud, np.concatenate([t, q])


def _plan_any_frame(planner: Callable, scene, obj: Clouds, sup: Clouds, spec: PairSpec,
                    seed: int):  # fmt: skip
    """The any-frame protocol: the planner gets the object cloud and the goal in a random frame
    of the object (``where_eval.any_frame`` of the OMPL seed and the pair) and no meshes (it
    cannot know the library's frame); the path it returns is mapped back and checked densely
    on the meshes."""
    from omnihang_jax import planner as planner_mod
    from omnihang_jax import where_eval

    turn = dict(where_eval.any_frame(seed, spec.pair_index, False), support_yaw=0.0)
    cloud, goal = turned_object(obj, np.asarray(spec.goal, float), turn)
    free_standing = where_eval.free_standing(spec.support_name.rsplit("_", 1)[0])
    plan = planner(None, cloud, sup, goal, free_standing=free_standing, mesh_fallback=False)
    info = dict(plan.info)
    if len(plan.poses):
        poses = where_eval.poses_to_library(plan.poses, turn)
        free, deepest, n = planner_mod.dense_check(
            planner_mod.MeshChecker(scene, planner.limits.penetration_tolerance), poses,
            planner.limits.dense_resolution, planner_mod.object_radius(scene),
        )  # fmt: skip
        info.update(dense_check_collision_free=free, deepest_penetration_m=deepest,
                    dense_states=n)  # fmt: skip
        plan = plan._replace(poses=poses, info=info)
    return plan


def evaluate_pair(planner: Callable, data: str, spec: PairSpec, seed: int,
                  frame: str = "library") -> dict:  # fmt: skip
    """Plan one pair with ``planner`` (a :class:`omnihang_jax.paths.Planner`) and judge the
    path on the meshes; the pair's record. ``frame``: "library" (the clouds as the dataset
    renders them, the meshes' geometry for the start and bounds) or "any"
    (:func:`_plan_any_frame`)."""
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
    t0 = time.perf_counter()
    scene, obj, sup = pair_scene(data, spec)
    goal = np.asarray(spec.goal, float)
    if frame == "any":
        plan = _plan_any_frame(planner, scene, obj, sup, spec, seed)
    else:
        plan = planner(scene, obj, sup, goal, mesh_fallback=False)
    info = plan.info
    returned = len(plan.poses) > 0
    row = dict(
        pair=spec.name, pair_index=spec.pair_index, object=spec.object_name,
        support=spec.support_name, category=spec.category, seed=int(seed),
        goal=[round(x, 6) for x in spec.goal], status=info.get("status"),
        planning_s=round(float(info.get("planning_s", 0.0)), 3),
        states_checked=int(info.get("states_checked", 0)), returned=returned,
        collision_free=bool(returned and info["dense_check_collision_free"]), frame=frame,
    )  # fmt: skip
    if returned:
        row |= dict(deepest_m=round(float(info["deepest_penetration_m"]), 5),
                    waypoints=int(info["waypoints"]))  # fmt: skip
    first = info.get("replanned_after")
    if first is not None:
        row |= dict(replanned=True, planning_s=round(row["planning_s"] + first["planning_s"], 3))
    ending = info.get("approach")
    if ending is not None:
        row["approach"] = dict(used=bool(ending.get("used")),
                               route=bool((ending.get("route") or {}).get("used")))  # fmt: skip
    if "cleared" in info:
        row["cleared_moves"] = int(info["cleared"]["moves"])
    row["wall_s"] = round(time.perf_counter() - t0, 3)
    return row


def prf(rows: list[dict]) -> dict:
    """Precision / recall / F1 (%) of records: free paths over returned ones, over all."""
    returned = sum(bool(r["returned"]) for r in rows)
    free = sum(bool(r["collision_free"]) for r in rows)
    precision = free / returned if returned else 0.0
    recall = free / len(rows) if rows else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return dict(records=len(rows), returned=returned, collision_free=free,
                precision=round(100 * precision, 1), recall=round(100 * recall, 1),
                f1=round(100 * f1, 1))  # fmt: skip


def summarise(rows: list[dict]) -> dict:
    """The figures of a run's records: pooled over pairs and seeds, per seed, per object
    category and their mean; planning times and time-outs."""
    if not rows:
        raise ValueError("no records to summarise")
    from omnihang_jax import planner

    seeds = sorted({int(r["seed"]) for r in rows})
    out = prf(rows)
    out |= dict(pairs=len({r["pair"] for r in rows}), seeds=seeds)
    per_seed = {s: prf([r for r in rows if int(r["seed"]) == s]) for s in seeds}
    out["per_seed"] = {str(s): {k: v[k] for k in ("precision", "recall", "f1")}
                       for s, v in per_seed.items()}  # fmt: skip
    if len(seeds) > 1:
        f1 = np.array([v["f1"] for v in per_seed.values()])
        out["f1_sd_over_seeds"] = round(float(f1.std(ddof=1)), 1)
    cats = sorted({r["category"] for r in rows})
    per_cat = {c: prf([r for r in rows if r["category"] == c]) for c in cats}
    out["per_category"] = {c: {k: v[k] for k in ("precision", "recall", "f1")}
                           for c, v in per_cat.items()}  # fmt: skip
    out["mean_over_categories"] = {
        k: round(float(np.mean([v[k] for v in per_cat.values()])), 1)
        for k in ("precision", "recall", "f1")
    }
    times = np.array([r["planning_s"] for r in rows], float)
    out |= dict(
        median_planning_s=round(float(np.median(times)), 3),
        p90_planning_s=round(float(np.quantile(times, 0.9)), 3),
        timeouts=sum(planner.timed_out(str(r["status"])) for r in rows),
    )
    return out


def read_records(path: str | os.PathLike) -> list[dict]:
    """A run's records; the last record of a (pair, seed) counts. A damaged last line (a run
    killed mid-write) is left out."""
    latest = {}
    path = Path(path)
    if not path.exists():
        return []
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        latest[(row["pair"], int(row["seed"]))] = row
    return list(latest.values())


def _worker_init(config: PlannerConfig, seed: int) -> None:
    from omnihang_jax import paths

    _WORKER["planner"] = paths.make_planner(config, seed=seed)


def _worker_plan(job: tuple[str, PairSpec, int, str]) -> dict:
    data, spec, seed, frame = job
    return evaluate_pair(_WORKER["planner"], data, spec, seed, frame)


@contextlib.contextmanager
def _cpu_workers(on: bool):
    """JAX on the CPU in the spawned workers (many processes do not share one GPU)."""
    saved = os.environ.get("JAX_PLATFORMS")
    if on:
        os.environ["JAX_PLATFORMS"] = "cpu"
    try:
        yield
    finally:
        if saved is None:
            os.environ.pop("JAX_PLATFORMS", None)
        else:
            os.environ["JAX_PLATFORMS"] = saved


def _check_config(path: Path, config: PlannerConfig) -> None:
    """The records' config file ``path`` is written once; a later run must plan with the same
    config."""
    path.parent.mkdir(parents=True, exist_ok=True)
    settings = dataclasses.asdict(config)
    if path.exists():
        before = json.loads(path.read_text())
        if before != json.loads(json.dumps(settings)):
            diff = sorted(k for k in settings if before.get(k) != settings[k])
            raise ValueError(f"{path.parent} holds records of another planner config (differs "
                             f"in {diff}): give other records")  # fmt: skip
    else:
        path.write_text(json.dumps(settings, indent=1))


def evaluate_paths(
    config: PlannerConfig,
    out_dir: str | os.PathLike | None = None,
    data: str | os.PathLike = "datasets/paper",
    split: str = "test",
    pairs: int = 80,
    seeds: Iterable[int] = (1,),
    workers: int = 1,
    progress: Callable[[int, int], None] | bool = True,
    cpu_workers: bool = True,
    records_path: str | os.PathLike | None = None,
    frame: str = "library",
) -> dict:
    """Plan ``pairs`` pairs of ``split`` with ``config`` under each OMPL seed of ``seeds``
    (module docstring) and return the summary (:func:`summarise`: ``precision``, ``recall``,
    ``f1`` in %, ``pairs``, ``seeds``, ...). ``workers`` > 1: that many spawned processes per
    seed, single-threaded, JAX on the CPU unless ``cpu_workers`` is False; 1: this process
    when OMPL here is unseeded or has the seed, else one worker. ``progress``: True (a tqdm
    bar), False, or ``progress(done, total)``. Records: ``out_dir/pairs.jsonl`` beside
    ``out_dir/config.json``, or ``records_path`` beside ``<its stem>.config.json``; resumed.
    ``frame``: "library" or "any" (:func:`evaluate_pair`); one records file holds one frame."""
    from omnihang_jax import paths, planner

    seeds = [int(s) for s in seeds]
    if not seeds or any(s < 1 for s in seeds):
        raise ValueError(f"OMPL seeds must be >= 1, got {seeds}")
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
    if frame == "any" and config.checker == "mesh":
        raise ValueError("the mesh checker plans on the meshes in the library's frame: "
                         "--frame any takes a planner that reads the clouds")  # fmt: skip
    if pairs < 1 or workers < 1:
        raise ValueError(f"pairs and workers must be >= 1, got {pairs}, {workers}")
    config = dataclasses.replace(config, mesh_fallback=False)  # judged on the meshes
    why = paths.missing(config)
    if why is not None:
        raise FileNotFoundError(why)
    if (out_dir is None) == (records_path is None):
        raise ValueError("give one of out_dir and records_path")
    if records_path is None:
        records, config_path = Path(out_dir) / RECORDS, Path(out_dir) / "config.json"
    else:
        records = Path(records_path)
        config_path = records.with_name(records.name.split(".")[0] + ".config.json")
    earlier = read_records(records)
    other = {r.get("frame", "library") for r in earlier} - {frame}
    if other:
        raise ValueError(f"{records} holds records in the {sorted(other)} frame, not "
                         f"{frame!r}: give other records")  # fmt: skip
    _check_config(config_path, config)
    specs = held_out_pairs(data, pairs, split)
    names = {s.name for s in specs}
    done = {(r["pair"], int(r["seed"])) for r in earlier}
    todo = {s: [p for p in specs if (p.name, s) not in done] for s in seeds}
    total = sum(map(len, todo.values()))
    bar = None
    if progress is True:
        from tqdm.auto import tqdm

        bar = tqdm(total=total, desc=f"plan {config.checker}", unit="pair")
    count = [0]

    def keep(row: dict) -> None:
        with open(records, "a") as f:  # one line a record, written as it comes
            f.write(json.dumps(row) + "\n")
        count[0] += 1
        if bar is not None:
            bar.update(1)
        elif callable(progress):
            progress(count[0], total)

    t0 = time.time()
    data = os.fspath(data)
    try:
        for seed in seeds:
            jobs = [(data, spec, seed, frame) for spec in todo[seed]]
            if not jobs:
                continue
            here = workers == 1 and planner._SEEDED in ([], [seed])
            if here:
                plan = paths.make_planner(config, seed=seed)
                for job in jobs:
                    keep(evaluate_pair(plan, *job))
                continue
            from sim.workers import spawn_pool

            with (
                _cpu_workers(cpu_workers),
                spawn_pool(min(workers, len(jobs)), _worker_init, (config, seed)) as pool,
            ):
                for row in pool.imap_unordered(_worker_plan, jobs):
                    keep(row)
    finally:
        if bar is not None:
            bar.close()
    rows = [r for r in read_records(records) if r["pair"] in names and int(r["seed"]) in seeds]
    summary = summarise(rows)
    summary["settings"] = dict(
        config=dataclasses.asdict(config), data=data, split=split, frame=frame, pairs_asked=pairs,
        workers=workers, records=os.fspath(records), wall_s_this_run=round(time.time() - t0, 1),
    )  # fmt: skip
    return summary
