"""Relabel the pairs of a generated dataset whose labels change with the current physics.

Labels version 3 (``sim.dataset.LABELS_VERSION``) made the scene's wall a solid 0.5 m block
(``sim.scene.PhysicsConfig.wall_thickness``) instead of a 2 cm slab that a strap could pass
through (docs/judges.md). Only labels that involve something behind the wall
plane can change, and which those are is decided from the stored labels by geometry alone
(:func:`wall_changes`). Pairs with a changed stable pose are regenerated whole with
``sim.dataset.generate_pair`` under the new scene; pairs whose stable poses stay get their
near misses and collision labels recomputed from them (what ``generate_pair`` computes
from the same stable poses). Both are spliced back into their shards, every other
record's arrays kept exactly as they were.

    # 1. which pairs change (a few CPU-minutes; writes WORK/pairs.json)
    python -m experiments.relabel find --data datasets/paper --work out/relabel_v3
    # 2. regenerate them (resumable: one file per finished pair in WORK/records/)
    nice -n 5 python -m experiments.relabel run --data datasets/paper --work out/relabel_v3 --workers 2
    # 3. splice them into DATA/shards, set recipe.json's labels_version, log the run in
    #    DATA/runs.jsonl, drop stale DATA/derived files, rewrite the dataset card
    python -m experiments.relabel merge --data datasets/paper --work out/relabel_v3

    # 4. (optional) regenerate a seeded sample of unflagged and of label-recomputed pairs
    #    whole and compare with the merged records (WORK/verify.json)
    nice -n 5 python -m experiments.relabel verify --data datasets/paper --work out/relabel_v3 --sample 24

A killed ``run`` loses at most the pairs in progress; run it again to resume. ``merge``
refuses to write a dataset with some listed pairs not regenerated yet.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from experiments import _cli

STABLE_DEPTH = 1e-3  # m: a stable pose reaching deeper behind the wall plane went through it


def wall_changes(record: dict, obj, support, config) -> dict:
    """Which of one stored record's labels the solid wall changes (counts; all 0: none).

    - ``stable``: stored stable poses reaching more than :data:`STABLE_DEPTH` behind the
      wall plane (a resting pose in front of the wall reads up to a few 0.1 mm behind it:
      soft contacts and 0.1 mm quantisation; a deeper one passed through the slab and, in
      the solid wall, starts PENETRATING);
    - ``negative``: kept near misses (regenerated from the pair seed and the stored stable
      poses) that reach behind the plane at all: the solid wall makes them penetrate at the
      start, so they cannot be near misses (the slab let them start "not touching");
    - ``collision``: collision-label poses reaching behind the plane that are stored as not
      colliding (the solid wall collides with everything behind its plane; a stored
      colliding pose stays colliding, the block contains the slab).

    Contacts in front of the wall are unchanged (same front face). What this does not see
    is a trajectory that left the wall plane and came back (a candidate that fell through
    the slab and would now be caught by the wall); see docs/dataset.md.
    """
    from sim import dataset, judges

    out = {"stable": 0, "negative": 0, "collision": 0}
    if support.wall_y is None:
        return out
    seed = int(record["pair_seed"])
    stable = np.asarray(record["stable_poses"], float).reshape(-1, 7)
    if len(stable):
        out["stable"] = int(
            (judges.behind_wall_depth(obj, stable, support.wall_y) > STABLE_DEPTH).sum()
        )
        kept = np.asarray(record["negative_kept"], bool)
        if kept.any():
            cand = dataset.negative_candidates(stable, seed, config)[kept]
            out["negative"] = int((judges.behind_wall_depth(obj, cand, support.wall_y) > 0).sum())
    free = ~np.asarray(record["collision_label"], bool)
    if free.any():
        poses = dataset.collision_poses(obj, support, seed, config)[free]
        out["collision"] = int((judges.behind_wall_depth(obj, poses, support.wall_y) > 0).sum())
    return out


def _load(data: str):
    from omnihang_jax import dataset_bridge
    from sim.library import build_library

    recipe = dataset_bridge.read_recipe(data)
    config = dataset_bridge.dataset_config_from_recipe(recipe)
    return recipe, config, build_library(config.library, progress=False)


def find(data: str, work: str, progress: bool = True, full: bool = False) -> dict:
    """Check every stored record (:func:`wall_changes`); write WORK/pairs.json. ``full``:
    list every flagged pair for whole regeneration (none only recomputed)."""
    from sim import dataset

    recipe, config, library = _load(data)
    records = dataset.load_records(data)
    t0 = time.time()
    changed, totals = [], {"stable": 0, "negative": 0, "collision": 0}
    per_reason = {k: 0 for k in totals}
    for r in tqdm(records, desc="records", disable=not progress, smoothing=0.05):
        obj_name, sup_name, _ = recipe["pairs"][int(r["pair_index"])]
        c = wall_changes(r, library.objects[obj_name], library.supports[sup_name], config)
        if any(c.values()):
            changed.append({"pair_index": int(r["pair_index"]), **c})
            for k, v in c.items():
                totals[k] += v
                per_reason[k] += v > 0
    result = {
        "labels_version_from": recipe.get("labels_version", 1),
        "records_checked": len(records),
        # regenerated whole (sim.dataset.generate_pair): a stable pose changes, and with it
        # which candidates fill the 50-pose cap, the take-off test and the near misses
        "pairs": sorted(p["pair_index"] for p in changed if p["stable"] or full),
        # stable poses unchanged: near misses and collision labels recomputed from them
        # exactly as generate_pair computes them (sim.dataset.near_misses, collision_labels)
        "label_pairs": sorted(p["pair_index"] for p in changed if not (p["stable"] or full)),
        "pairs_by_reason": per_reason,
        "labels_changed": totals,
        "stable_depth_m": STABLE_DEPTH,
        "seconds": round(time.time() - t0, 1),
        "detail": sorted(changed, key=lambda p: p["pair_index"]),
    }
    Path(work).mkdir(parents=True, exist_ok=True)
    from sim import atomic

    atomic.write_text(Path(work) / "pairs.json", json.dumps(result, indent=1) + "\n")
    return result


# ----------------------------------------------------------------------------- regenerate

_WORKER: dict = {}


def _worker_init(data: str) -> None:
    from sim import kernels

    kernels.DEFAULT_NTHREAD = 1  # one process per core, as sim.dataset's workers
    recipe, config, library = _load(data)
    _WORKER.update(recipe=recipe, config=config, library=library)


def _record_path(work: str | Path, index: int) -> Path:
    return Path(work) / "records" / f"pair_{index:06d}.npz"


def _collision_behind(scene, seed: int, config, kept: np.ndarray, label: np.ndarray):
    """The pair's collision labels with every pose that reaches behind the wall plane and
    was stored as not colliding relabelled by ``sim.dataset.collision_labels``' rule under
    ``scene`` (contact queries are per pose, so this equals the full recomputation on those
    poses). Poses in front of the wall see the same front face as before, and a pose that
    collided with the slab collides with the block that contains it: both keep their
    stored labels."""
    from sim import dataset, judges, kernels

    kept, label = np.array(kept, bool), np.array(label, bool)
    poses = dataset.collision_poses(scene.obj, scene.support, seed, config)
    depth = judges.behind_wall_depth(scene.obj, poses, scene.support.wall_y)
    behind = np.flatnonzero((depth > 0) & ~label)
    if len(behind):
        con = kernels.contact_query(
            scene,
            poses[behind],
            kernels.ContactConfig(distance_cutoff=config.collision_free_within + 1e-3),
        )
        colliding = con.penetration > 0
        free = (~colliding) & (con.distance <= config.collision_free_within)
        kept[behind], label[behind] = colliding | free, colliding
    return kept, label


def _regenerate(job: tuple[int, str, str, str]) -> tuple[int, dict]:
    """``kind`` "full": ``generate_pair`` under the current scene; "labels": the stored
    record with its near misses and collision labels recomputed under the current scene
    (what ``generate_pair`` computes from the same stable poses). Writes a one-pair shard."""
    from sim import atomic, dataset, dataset_io
    from sim.scene import build_scene

    index, work, kind, data, redo_negatives = job
    w = _WORKER
    dataset.STAGE_SECONDS.clear()
    config = w["config"]
    obj_name, sup_name, _ = w["recipe"]["pairs"][index]
    obj, sup = w["library"].objects[obj_name], w["library"].supports[sup_name]
    seed = dataset.pair_seed(config.seed, obj_name, sup_name)
    ids = (w["recipe"]["objects"].index(obj_name), w["recipe"]["supports"].index(sup_name), seed)
    if kind == "full":
        rec = dataset.generate_pair(obj, sup, seed, config, "cpu")
        one = dataset_io.pack_shard([rec], [index], [ids])
    else:
        path = Path(data) / "shards" / f"shard_{index // config.shard_size:05d}.npz"
        with np.load(path) as z:
            shard = {f: z[f] for f in z.files}
        (i,) = np.flatnonzero(shard["pair_index"] == index)
        part = _slices(shard, int(i))
        if int(part["pair_seed"][0]) != seed:
            raise AssertionError(f"pair {index}: stored seed differs from the recipe's")
        stable = dataset_io.unpack(shard)[int(i)]["stable_poses"].astype(float)
        scene = build_scene(obj, sup)
        if redo_negatives:  # a kept near miss starts in the wall: the cap may admit others
            with dataset._timed("negatives"):
                part["negative_kept"] = dataset.near_misses(scene, stable, seed, config, "cpu")
        with dataset._timed("collision_labels"):
            part["collision_kept"], part["collision_label"] = _collision_behind(
                scene, seed, config, part["collision_kept"], part["collision_label"]
            )
        one = _from_slices([part], shard)
    atomic.savez(_record_path(work, index), **one)
    return index, dict(dataset.STAGE_SECONDS)


def run(data: str, work: str, workers: int = 2, progress: bool = True) -> dict:
    """Regenerate every pair of WORK/pairs.json not yet in WORK/records (resumable)."""
    from sim import dataset_io
    from sim import workers as workers_mod

    found = json.loads((Path(work) / "pairs.json").read_text())
    kinds = {i: "full" for i in found["pairs"]} | {i: "labels" for i in found["label_pairs"]}
    listed = found["pairs"] + found["label_pairs"]
    todo = [i for i in listed if not _record_path(work, i).exists()]
    (Path(work) / "records").mkdir(parents=True, exist_ok=True)
    t0, done, stages = time.time(), 0, {}
    bar = tqdm(total=len(listed), initial=len(listed) - len(todo), desc="pairs", unit="pair",
               disable=not progress, smoothing=0.05)  # fmt: skip
    negatives = {p["pair_index"] for p in found["detail"] if p["negative"]}
    jobs = [(i, os.fspath(work), kinds[i], os.fspath(data), i in negatives) for i in todo]
    interrupted = True
    try:
        if workers <= 1:
            _worker_init(data)
            results = map(_regenerate, jobs)
            for _, sec in results:
                done += 1
                bar.update(1)
                for k, v in sec.items():
                    stages[k] = stages.get(k, 0.0) + v
        elif jobs:
            with workers_mod.spawn_pool(workers, _worker_init, (data,)) as pool:
                for _, sec in pool.imap_unordered(_regenerate, jobs):
                    done += 1
                    bar.update(1)
                    for k, v in sec.items():
                        stages[k] = stages.get(k, 0.0) + v
        interrupted = False
    finally:
        bar.close()
        if done:
            log = {
                "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "pairs": done,
                "seconds": round(time.time() - t0, 2),
                "workers": workers,
                "device": dataset_io.device_name(),
                "stage_seconds": {k: round(v, 2) for k, v in sorted(stages.items())},
                "interrupted": interrupted,
            }
            with open(Path(work) / "runs.jsonl", "a") as f:
                f.write(json.dumps(log) + "\n")
    left = sum(not _record_path(work, i).exists() for i in listed)
    return {"listed": len(listed), "done_this_run": done, "left": left,
            "seconds": round(time.time() - t0, 1)}  # fmt: skip


# ----------------------------------------------------------------------------- merge

_PER_PAIR = ("pair_index", "object_id", "support_id", "pair_seed", "mass", "friction",
             "object_eye", "support_eye", "n_candidates", "n_penetrating", "n_fallen",
             "n_stable_raw", "n_takeoff_rejected")  # fmt: skip
_RAGGED = {"stable": ("stable_position", "stable_quaternion")}
_BITS = {"negative": ("negative_kept",), "collision": ("collision_kept", "collision_label")}


def _slices(shard: dict, i: int) -> dict:
    """Pair ``i`` of a loaded shard as raw arrays (int16 poses, bool label bits)."""
    out = {k: shard[k][i : i + 1] for k in _PER_PAIR}
    a, b = shard["stable_offsets"][i], shard["stable_offsets"][i + 1]
    for k in _RAGGED["stable"]:
        out[k] = shard[k][a:b]
    for g, fields in _BITS.items():
        off = shard[f"{g}_offsets"]
        for f in fields:
            bits = np.unpackbits(shard[f], count=int(off[-1])).astype(bool)
            out[f] = bits[off[i] : off[i + 1]]
    return out


def splice(shard: dict, replacements: dict[int, dict]) -> dict:
    """A shard's arrays with the pairs of ``replacements`` (pair_index -> a one-pair shard,
    as ``sim.dataset_io.pack_shard`` writes it) swapped in; every other pair's stored values, in
    the same order and dtypes, untouched (poses are not requantised)."""
    parts = []
    for i in range(len(shard["pair_index"])):
        idx = int(shard["pair_index"][i])
        parts.append(_slices(replacements[idx], 0) if idx in replacements else _slices(shard, i))
    return _from_slices(parts, shard)


def _from_slices(parts: list[dict], shard: dict) -> dict:
    """A shard's arrays (the layout and dtypes of ``shard``) from per-pair raw slices."""
    out: dict[str, np.ndarray] = {}
    for k in _PER_PAIR:
        out[k] = np.concatenate([p[k] for p in parts]).astype(shard[k].dtype)
    lengths = [len(p["stable_position"]) for p in parts]
    out["stable_offsets"] = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    for k in _RAGGED["stable"]:
        out[k] = np.concatenate([p[k] for p in parts]).astype(shard[k].dtype)
    for g, fields in _BITS.items():
        lengths = [len(p[fields[0]]) for p in parts]
        out[f"{g}_offsets"] = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
        for f in fields:
            out[f] = np.packbits(np.concatenate([p[f] for p in parts]))
    if set(out) != set(shard):
        raise AssertionError(f"shard fields differ: {sorted(set(out) ^ set(shard))}")
    return out


def merge(data: str, work: str, progress: bool = True) -> dict:
    """Splice WORK/records into DATA/shards; set recipe.json's labels_version to the code's,
    log the relabel in DATA/runs.jsonl and recipe.json, remove the relabelled pairs' stale
    derived files (DATA/derived), rewrite the dataset card."""
    from sim import atomic, dataset

    found = json.loads((Path(work) / "pairs.json").read_text())
    listed = sorted(found["pairs"] + found["label_pairs"])
    missing = [i for i in listed if not _record_path(work, i).exists()]
    if missing:
        raise ValueError(
            f"{len(missing)} of {len(listed)} listed pairs are not regenerated yet "
            f"(first: {missing[:5]}): run `python -m experiments.relabel run` first"
        )
    recipe_path = Path(data) / "recipe.json"
    recipe = json.loads(recipe_path.read_text())
    size = recipe["config"]["shard_size"]
    by_shard: dict[int, dict[int, dict]] = {}
    for i in listed:
        with np.load(_record_path(work, i)) as z:
            by_shard.setdefault(i // size, {})[i] = {k: z[k] for k in z.files}
    t0 = time.time()
    for k, repl in tqdm(sorted(by_shard.items()), desc="shards", disable=not progress):
        path = Path(data) / "shards" / f"shard_{k:05d}.npz"
        with np.load(path) as z:
            shard = {f: z[f] for f in z.files}
        if not set(repl) <= set(int(x) for x in shard["pair_index"]):
            raise ValueError(f"{path} does not hold pairs {sorted(repl)}")
        atomic.savez(path, **splice(shard, repl))
    # stale derived files (git-ignored caches) of the relabelled pairs
    removed = 0
    derived = Path(data) / "derived"
    for i in listed:
        for f in derived.glob(f"*/{i:05d}_*.npz"):
            f.unlink()
            removed += 1
    runs = [json.loads(x) for x in (Path(work) / "runs.jsonl").read_text().splitlines() if x]
    secs = sum(r["seconds"] for r in runs)
    stage: dict[str, float] = {}
    for r in runs:
        for key, v in r["stage_seconds"].items():
            stage[key] = round(stage.get(key, 0.0) + v, 2)
    entry = {
        "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "pairs": len(listed),
        "seconds": round(secs, 2),
        "pairs_per_min": round(60 * len(listed) / max(secs, 1e-9), 2),
        "workers": runs[-1]["workers"],
        "part": [0, 1],
        "backend": "cpu",
        "device": runs[-1]["device"],
        "stage_seconds": stage,
        "interrupted": False,
        "shards": sorted(by_shard),
        "relabel": {
            "labels_version": dataset.LABELS_VERSION,
            "from_version": found["labels_version_from"],
            "pairs_regenerated": found["pairs"],
            "pairs_labels_recomputed": found["label_pairs"],
            "why": "solid wall (sim.scene.PhysicsConfig.wall_thickness); experiments.relabel",
            "pairs_by_reason": found["pairs_by_reason"],
            "labels_changed": found["labels_changed"],
        },
    }
    with open(Path(data) / "runs.jsonl", "a") as f:
        f.write(json.dumps(entry) + "\n")
    history = recipe.setdefault("relabels", [])
    history.append({"date": entry["date"], "labels_version": dataset.LABELS_VERSION,
                    "from_version": found["labels_version_from"], "pairs": len(listed),
                    "shards": sorted(by_shard)})  # fmt: skip
    recipe["labels_version"] = dataset.LABELS_VERSION
    atomic.write_text(recipe_path, json.dumps(recipe, indent=1))
    return {"pairs": len(listed), "shards_rewritten": len(by_shard),
            "derived_files_removed": removed, "seconds": round(time.time() - t0, 1)}  # fmt: skip


def _compare(a: dict, b: dict) -> list[str]:
    """Fields in which two unpacked records differ (stable poses compared as stored)."""
    diff = []
    for k in ("stable_poses", "negative_kept", "collision_kept", "collision_label",
              "object_eye", "support_eye", "n_candidates", "n_stable_raw",
              "n_takeoff_rejected", "n_penetrating", "n_fallen"):  # fmt: skip
        x, y = np.asarray(a[k]), np.asarray(b[k])
        if x.shape != y.shape or not np.array_equal(x, y):
            diff.append(k)
    return diff


def _verify_one(job: tuple[int, float]) -> tuple[int, float, dict]:
    """Regenerate pair ``index`` whole with the wall ``thickness`` (m); the unpacked record."""
    from sim import dataset, dataset_io
    from sim.scene import PhysicsConfig, build_scene

    index, thickness = job
    w = _WORKER
    config = w["config"]
    obj_name, sup_name, _ = w["recipe"]["pairs"][index]
    obj, sup = w["library"].objects[obj_name], w["library"].supports[sup_name]
    seed = dataset.pair_seed(config.seed, obj_name, sup_name)
    physics = PhysicsConfig(wall_thickness=thickness)
    saved = dataset.build_scene
    dataset.build_scene = lambda o, s: build_scene(o, s, physics)
    try:
        rec = dataset.generate_pair(obj, sup, seed, config, "cpu")
    finally:
        dataset.build_scene = saved
    ids = (w["recipe"]["objects"].index(obj_name), w["recipe"]["supports"].index(sup_name), seed)
    return index, thickness, dataset_io.unpack(dataset_io.pack_shard([rec], [index], [ids]))[0]


def verify(data: str, work: str, n: int = 24, seed: int = 0, workers: int = 2,
           progress: bool = True) -> dict:  # fmt: skip
    """Regenerate whole, under the current (solid) wall, a seeded sample of ``n`` wall-mounted
    pairs the check did not flag and ``n`` pairs whose near misses / collision labels were
    recomputed, and compare with the dataset's records (after ``merge``). A pair that differs
    is regenerated once more with the old 2 cm slab, to tell the wall from anything else
    (another machine's floating point). Writes WORK/verify.json."""
    from sim import dataset
    from sim import workers as workers_mod

    recipe, config, library = _load(data)
    found = json.loads((Path(work) / "pairs.json").read_text())
    flagged = set(found["pairs"]) | set(found["label_pairs"])
    wall_pairs = [
        i for i, (o, s, _) in enumerate(recipe["pairs"])
        if library.supports[s].wall_y is not None and i not in flagged
    ]  # fmt: skip
    rng = np.random.default_rng(seed)
    groups = {
        "unflagged": sorted(rng.choice(wall_pairs, n, replace=False).tolist()),
        "labels_recomputed": sorted(rng.choice(found["label_pairs"], n, replace=False).tolist()),
    }
    stored = {int(r["pair_index"]): r for r in dataset.load_records(data)}
    t0 = time.time()
    results: dict[tuple[int, float], dict] = {}
    jobs = [(i, config_thickness()) for g in groups.values() for i in g]
    with workers_mod.spawn_pool(workers, _worker_init, (data,)) as pool:
        for i, t, rec in tqdm(pool.imap_unordered(_verify_one, jobs), total=len(jobs),
                              desc="pairs", disable=not progress):  # fmt: skip
            results[(i, t)] = rec
        differ = [i for (i, _t), rec in list(results.items()) if _compare(rec, stored[i])]
        again = [(i, 0.02) for i in differ]
        for i, t, rec in tqdm(pool.imap_unordered(_verify_one, again), total=len(again),
                              desc="old wall", disable=not progress):  # fmt: skip
            results[(i, t)] = rec
    out = {"seconds": round(time.time() - t0, 1), "sample_seed": seed, "groups": {}}
    for name, idx in groups.items():
        rows = []
        for i in idx:
            d = _compare(results[(i, config_thickness())], stored[i])
            row = {"pair_index": i, "differs_in": d}
            if d:
                row["old_wall_differs_in"] = _compare(results[(i, 0.02)], stored[i])
            rows.append(row)
        out["groups"][name] = {
            "pairs": len(rows),
            "identical": sum(not r["differs_in"] for r in rows),
            "labels_identical": sum(
                not set(r["differs_in"]) - {"n_penetrating", "n_fallen"} for r in rows
            ),
            "rows": rows,
        }
    from sim import atomic

    atomic.write_text(Path(work) / "verify.json", json.dumps(out, indent=1) + "\n")
    return out


def config_thickness() -> float:
    from sim.scene import PhysicsConfig

    return PhysicsConfig().wall_thickness


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("step", choices=["find", "run", "merge", "verify"])
    parser.add_argument("--data", required=True, help="generated dataset (recipe.json + shards/)")
    parser.add_argument("--work", required=True, help="work folder (pairs.json, records/)")
    parser.add_argument("--workers", type=int, default=2, help="processes for `run`")
    parser.add_argument(
        "--full",
        action="store_true",
        help="`find`: regenerate every flagged pair whole (instead of recomputing near misses "
        "and collision labels where the stable poses stay)",
    )
    parser.add_argument("--sample", type=int, default=24, help="`verify`: pairs per group")
    parser.add_argument("--seed", type=int, default=0, help="`verify`: sample seed")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    progress = not args.no_progress
    try:
        if args.step == "find":
            res = find(args.data, args.work, progress, args.full)
            res = {k: v for k, v in res.items() if k not in ("detail", "pairs")} | {
                "pairs": len(res["pairs"])
            }
        elif args.step == "run":
            res = run(args.data, args.work, args.workers, progress)
        elif args.step == "merge":
            res = merge(args.data, args.work, progress)
        else:
            res = verify(args.data, args.work, args.sample, args.seed, args.workers, progress)
            res = {g: {k: v for k, v in d.items() if k != "rows"} for g, d in res["groups"].items()}
    except KeyboardInterrupt:
        print("interrupted: finished pairs are kept; run again to resume", file=sys.stderr)
        raise SystemExit(130) from None
    print(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    _cli.run(main)
