"""Re-judge the answers of an ``eval_stage3`` run in MuJoCo and PyBullet (the second judge).

    nice -n 5 python -m experiments.judge_stage3 \\
        --pairs results/hanging_success_stage3.pairs.jsonl.gz --per-category 40 --workers 2 \\
        --items out/judge_stage3/items.jsonl --keep-previous labels_v2_thin_wall \\
        --out results/hanging_success_stage3_judges.json

For each pair the chosen pose of every stage (Stage 1, 1+2, 1+3, all stages) is simulated
under the evaluation protocol by ``sim.judges.judge_stability`` (MuJoCo, and PyBullet
``MATCHED``, contact manifolds flushed between poses; stable under "both" = stable in each) in the
current scene (``sim.scene.build_scene``: the solid wall of labels version 3; PyBullet's
``MATCHED`` world copies that scene's wall box, docs/judges.md); success per judge = mean
over categories. The stored verdict of the evaluation run (MuJoCo, in the scene of its
day) of the same pairs is reported beside them (``stored``).

PyBullet runs ~2 poses/s per core, hence a balanced subset: ``--per-category N`` pairs of
each category, spread over its pairs (bit-reversed order, so smaller subsets are prefixes of
larger ones), judged round-robin over the categories. With
``--items`` every judged pair is appended to a JSONL file as it finishes and a rerun skips
the pairs already there, so a run can be stopped (Ctrl-C) and resumed or summarised
(``--summarize-only``); the summary uses the largest balanced prefix of the judged pairs
(the same number per category, in the round-robin order).
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from experiments import _cli
from omnihang_jax import dataset_bridge, refine
from omnihang_jax.eval_pipeline import STAGES

_W: dict = {}
JUDGES = ("mujoco", "pybullet")


def _init(dataset_dir: str) -> None:
    recipe = dataset_bridge.read_recipe(dataset_dir)
    _W["config"] = dataset_bridge.dataset_config_from_recipe(recipe).library
    _W["assets"] = {}


def _asset(kind: str, name: str):
    """The dataset library's asset ``name`` ("<category>_<index>"), built alone the way
    ``sim.library.build_library`` builds it (the whole library takes ~5 s of CPU)."""
    from sim.assets.base import build_object, build_support
    from sim.library import asset_seed

    key = (kind, name)
    if key not in _W["assets"]:
        config = _W["config"]
        category, index = name.rsplit("_", 1)
        counts = config.objects_per_category() if kind == "object" else config.supports_per_family()
        if category not in counts or not index.isdigit() or int(index) >= counts[category]:
            raise ValueError(f"{kind} {name!r} is not in the dataset's library")
        build = build_object if kind == "object" else build_support
        _W["assets"][key] = build(
            category, asset_seed(config.seed, kind, category, int(index)), int(index)
        )
    return _W["assets"][key]


def _judge(job):
    """``job`` = (pair_index, object, support, poses [S, 7]) -> per-judge stable / status.

    Both engines judge the poses as one batch: MuJoCo starts every pose from fresh
    ``MjData``, PyBullet flushes the previous pose's contact manifolds
    (``pybullet_ref.stability``; before that fix a per-pose world was needed here, see
    docs/judges.md)."""
    from omnihang_jax.evaluate import protocol_stability
    from sim import judges
    from sim.kernels import STATUS_NAMES
    from sim.scene import build_scene

    pair_index, obj, sup, poses = job
    scene = build_scene(_asset("object", obj), _asset("support", sup))
    poses = np.asarray(poses)
    config = protocol_stability()
    mj = judges.judge_stability(scene, poses, config, judge="mujoco")
    pb = judges.judge_stability(scene, poses, config, judge="pybullet")
    return {
        "pair_index": pair_index,
        "mujoco": [bool(x) for x in mj.stable],
        "mujoco_status": [STATUS_NAMES[int(x)] for x in mj.status],
        "pybullet": [bool(x) for x in pb.stable],
        "pybullet_status": [STATUS_NAMES[int(x)] for x in pb.status],
    }


def _open(path):
    return gzip.open(path, "rt") if str(path).endswith(".gz") else open(path)


def spread_order(n: int) -> list[int]:
    """0..n-1 in bit-reversed (van der Corput) order: every prefix is spread evenly over the
    range (0, n/2, n/4, 3n/4, ...)."""
    bits = max(1, (n - 1).bit_length())
    rev = [int(format(i, f"0{bits}b")[::-1], 2) for i in range(1 << bits)]
    return [i for i in rev if i < n]


def select(records: list[dict], per_category: int) -> list[dict]:
    """The first ``per_category`` records of each category in :func:`spread_order` (so the
    subsets of different sizes nest and each is spread over the category's pairs), in
    round-robin order over the categories (sorted), so any prefix is nearly balanced."""
    by_cat: dict[str, list] = {}
    for r in records:
        by_cat.setdefault(r["category"], []).append(r)
    lists = [
        [by_cat[c][i] for i in spread_order(len(by_cat[c]))[:per_category]] for c in sorted(by_cat)
    ]
    return [ls[k] for k in range(max(map(len, lists), default=0)) for ls in lists if k < len(ls)]


def balanced_prefix(chosen: list[dict], done: dict[int, dict]) -> list[dict]:
    """The first ``k`` chosen records of every category (all of a category that has fewer),
    ``k`` the largest number such that all of those are judged; every chosen record when all
    are judged."""
    by_cat: dict[str, list] = {}
    for r in chosen:
        by_cat.setdefault(r["category"], []).append(r)
    k = min(
        (
            next((i for i, r in enumerate(rs) if r["pair_index"] not in done), None)
            for rs in by_cat.values()
        ),
        key=lambda i: float("inf") if i is None else i,
        default=None,
    )
    return [r for rs in by_cat.values() for r in (rs if k is None else rs[:k])]


def summarize(chosen: list[dict], done: dict[int, dict]) -> dict:
    """Success per stage under each judge, both and the stored verdict; agreement."""
    used = balanced_prefix(chosen, done)
    out: dict = {"pairs": len(used)}
    if not used:
        return out
    counts: dict[str, int] = {}
    for r in used:
        counts[r["category"]] = counts.get(r["category"], 0) + 1
    out["pairs_per_category"] = counts
    verdicts = {
        "stored": [[bool(r[s]["success"]) for s in STAGES] for r in used],
        "mujoco": [done[r["pair_index"]]["mujoco"] for r in used],
        "pybullet": [done[r["pair_index"]]["pybullet"] for r in used],
    }
    verdicts["both"] = [
        [a and b for a, b in zip(m, p, strict=True)]
        for m, p in zip(verdicts["mujoco"], verdicts["pybullet"], strict=True)
    ]
    for judge in ("mujoco", "pybullet", "both", "stored"):
        out[judge] = {}
        for i, stage in enumerate(STAGES):
            cats: dict[str, list] = {}
            for r, v in zip(used, verdicts[judge], strict=True):
                cats.setdefault(r["category"], []).append(bool(v[i]))
            out[judge][stage] = {
                "mean": float(100 * np.mean([np.mean(x) for x in cats.values()])),
                "successes": int(sum(map(sum, cats.values()))),
                "per_category": {c: float(100 * np.mean(x)) for c, x in sorted(cats.items())},
            }

    def agree(a: str, b: str) -> dict:
        per = {
            stage: float(
                np.mean([x[i] == y[i] for x, y in zip(verdicts[a], verdicts[b], strict=True)])
            )
            for i, stage in enumerate(STAGES)
        }
        return {"all": float(np.mean(list(per.values())))} | per

    out["agreement"] = agree("mujoco", "pybullet")["all"]
    out["agreement_by_stage"] = agree("mujoco", "pybullet")
    out["mujoco_vs_stored"] = agree("mujoco", "stored")
    out["disagreements"] = [
        {
            "pair_index": r["pair_index"],
            "object": r["object"],
            "support": r["support"],
            "category": r["category"],
            "family": r.get("family"),
            "stage": stage,
            "stored": verdicts["stored"][j][i],
            "mujoco": done[r["pair_index"]]["mujoco_status"][i],
            "pybullet": done[r["pair_index"]]["pybullet_status"][i],
        }
        for j, r in enumerate(used)
        for i, stage in enumerate(STAGES)
        if verdicts["mujoco"][j][i] != verdicts["pybullet"][j][i]
        or verdicts["mujoco"][j][i] != verdicts["stored"][j][i]
    ]
    return out


def _read_items(path) -> dict[int, dict]:
    done: dict[int, dict] = {}
    if path and Path(path).exists():
        with open(path) as f:
            for line in f:
                if line.strip():
                    try:
                        item = json.loads(line)
                    except json.JSONDecodeError:  # a line cut by a kill: judged again
                        continue
                    done[int(item["pair_index"])] = item
    return done


def compact(out: dict, path: str) -> dict:
    """The figures of a summary for a results file's ``judges`` key."""
    return {
        "note": "every stage's chosen pose re-judged by MuJoCo and PyBullet (MATCHED, contact "
        "manifolds flushed between poses) in the scene of labels version "
        f"{out['scene']['labels_version']} (solid wall, {out['scene']['wall_thickness_m']} m); "
        "success = mean over categories (%); 'stored' = the evaluation run's own MuJoCo "
        "verdict of the same pairs; agreement = share of (pair, stage) verdicts on which "
        "MuJoCo and PyBullet agree",
        "pairs": out["pairs"],
        "pairs_per_category": out["pairs_per_category"],
        "scene": out["scene"],
        **{
            judge: {stage: out[judge][stage]["mean"] for stage in STAGES}
            for judge in ("mujoco", "pybullet", "both", "stored")
        },
        "agreement": out["agreement"],
        "agreement_by_stage": out["agreement_by_stage"],
        "mujoco_vs_stored": out["mujoco_vs_stored"],
        "source": out["source"],
        "file": path,
        "command": out["command"],
    }


def _write_into(results: str, path: str, out: dict, keep_previous: str | None) -> None:
    data = json.loads(Path(results).read_text())
    entry = compact(out, path)
    prev = data.get("judges")
    if keep_previous and prev:
        entry[keep_previous] = prev.get(keep_previous, prev)
    data["judges"] = entry
    refine.write_json(results, data)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--pairs", required=True, help="per-pair JSONL(.gz) of eval_stage3")
    parser.add_argument("--data", default="datasets/paper")
    parser.add_argument("--per-category", type=int, default=20)
    parser.add_argument("--workers", type=int, default=0)
    parser.add_argument("--items", help="JSONL of per-pair verdicts (appended; resumes)")
    parser.add_argument(
        "--summarize-only", action="store_true", help="judge nothing: summarise --items"
    )
    parser.add_argument(
        "--keep-previous",
        metavar="KEY",
        help="keep the existing --out file's figures under KEY of the new one",
    )
    parser.add_argument("--out", required=True)
    parser.add_argument(
        "--into",
        metavar="RESULTS_JSON",
        help="also write a compact entry under the key 'judges' of this results file "
        "(e.g. results/hanging_success.json; its other keys are kept)",
    )
    args = parser.parse_args(argv)
    if args.per_category < 1:
        raise ValueError(f"--per-category must be >= 1, got {args.per_category}")
    if args.summarize_only and not args.items:
        raise ValueError("--summarize-only needs --items")
    try:
        with _open(args.pairs) as f:
            records = [json.loads(x) for x in f if x.strip()]
    except (OSError, json.JSONDecodeError) as err:
        print(f"judge_stage3: error: cannot read {args.pairs}: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    chosen = select(records, args.per_category)
    done = _read_items(args.items)
    todo = [r for r in chosen if r["pair_index"] not in done]
    jobs = [
        (r["pair_index"], r["object"], r["support"], [r[s]["pose"] for s in STAGES]) for r in todo
    ]
    t0 = time.time()
    if jobs and not args.summarize_only:
        if args.items:
            os.makedirs(os.path.dirname(os.path.abspath(args.items)), exist_ok=True)
        sink = open(args.items, "a") if args.items else None  # noqa: SIM115
        try:
            dataset_dir = dataset_bridge.resolve_dataset_dir(args.data)[0]
            if args.workers > 0:
                from sim.workers import spawn_pool

                with spawn_pool(args.workers, _init, (str(dataset_dir),)) as pool:
                    results = pool.imap_unordered(_judge, jobs)
                    for n, item in enumerate(results, 1):
                        done[item["pair_index"]] = item
                        if sink:
                            sink.write(json.dumps(item) + "\n")
                            sink.flush()
                        print(f"judge_stage3: {n}/{len(jobs)} pairs", file=sys.stderr)
            else:
                _init(str(dataset_dir))
                for job in jobs:
                    item = _judge(job)
                    done[item["pair_index"]] = item
                    if sink:
                        sink.write(json.dumps(item) + "\n")
                        sink.flush()
        finally:
            if sink:
                sink.close()
    from sim.dataset import LABELS_VERSION
    from sim.scene import PhysicsConfig

    out = {
        "what": "the chosen pose of every stage re-judged under the evaluation protocol by "
        "MuJoCo (sim.scene) and PyBullet MATCHED (the same scene's wall box); success = mean "
        "over categories; 'stored' = the evaluation run's own MuJoCo verdict of the same pairs",
        "scene": {
            "labels_version": LABELS_VERSION,
            "wall_thickness_m": PhysicsConfig().wall_thickness,
        },
        "per_category_requested": args.per_category,
        "source": args.pairs,
        "judged_now": 0 if args.summarize_only else len(jobs),  # the rest came from --items
        "judge_s": round(time.time() - t0, 1),
    } | summarize(chosen, done)
    out["command"] = "python -m experiments.judge_stage3 " + " ".join(
        sys.argv[1:] if argv is None else argv
    )
    if args.keep_previous and Path(args.out).exists():
        prev = json.loads(Path(args.out).read_text())
        if args.keep_previous in prev:  # already kept by an earlier run: carry it over
            out[args.keep_previous] = prev[args.keep_previous]
        else:
            out[args.keep_previous] = prev
    refine.write_json(args.out, out)
    if args.into and out["pairs"]:
        _write_into(args.into, args.out, out, args.keep_previous)
    if out["pairs"]:
        summary = {j: {s: round(out[j][s]["mean"], 1) for s in STAGES} for j in out if j in
                   ("mujoco", "pybullet", "both", "stored")}  # fmt: skip
        print(json.dumps(summary | {"pairs": out["pairs"], "agreement": out["agreement"]}))
    return out


if __name__ == "__main__":
    _cli.run(main)
