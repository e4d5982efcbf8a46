"""Release height: the answer of a stage let go a few millimetres above the predicted pose.

    python -m experiments.release_lift --records /tmp/val_where.pairs.jsonl --data datasets/paper \\
        --stages stage1 --lifts 0,0.0025,0.005,0.0075,0.01,0.015 --out results/release_lift_val.json

Most failed answers start a few millimetres inside the support (the protocol fails a pose whose
initial penetration exceeds 3 mm), while a pose a little above a hook drops onto it and settles.
This re-simulates the chosen pose of each ``--stages`` stage of every pair of an evaluation
run's records (``eval_where`` or ``eval_stage3`` per-pair JSONL, optionally gzipped) moved
``lift`` metres up (+z of the support frame, against gravity; rotation kept), for every lift of
``--lifts``, under the evaluation protocol (``evaluate.protocol_stability``, MuJoCo on the CPU,
one batched call per pair). Lift 0 is re-simulated too: the baseline of the same run (a record
judged on the GPU may differ on a few pairs; ``stored_agreement`` counts them). Success = mean
over categories, as everywhere. The lift is chosen on the records of validation-object pairs
(``--split train``) and applied once to held-out records (``--split test``).

Every judged pair is appended to ``--items`` (default: OUT with suffix .items.jsonl) as it
finishes; a rerun skips the pairs already there, so a stopped run resumes.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from experiments import _cli
from experiments.summarise_heldout import read_rows
from omnihang_jax import dataset_bridge, evaluate


def parse_lifts(text: str) -> list[float]:
    try:
        lifts = [float(x) for x in text.split(",") if x.strip()]
    except ValueError as e:
        raise ValueError(f"--lifts: {text!r} is not a comma-separated list of metres") from e
    if not lifts or any(not np.isfinite(v) or v < 0 or v > 0.1 for v in lifts):
        raise ValueError(f"--lifts: {text!r}: give lifts between 0 and 0.1 m")
    return sorted(set(lifts) | {0.0})


def judge_pair(scene, record: dict, stages, lifts, stability) -> dict:
    """One batched stability call for every (stage, lift) of a record -> {stage: {lift: status}}."""
    from sim import judges, kernels

    keys, poses = [], []
    for stage in stages:
        pose = np.asarray(record[stage]["pose"], np.float64)
        for lift in lifts:
            keys.append((stage, lift))
            poses.append(evaluate.lift_poses(pose.reshape(7), lift))
    poses = np.stack(poses)
    finite = np.isfinite(poses).all(1) & (np.linalg.norm(poses[:, 3:], axis=1) > 1e-6)
    status = np.full(len(poses), kernels.DIVERGED, np.int8)
    if finite.any():
        status[finite] = judges.judge_stability(scene, poses[finite], stability).status
    out: dict = {s: {} for s in stages}
    for (stage, lift), st in zip(keys, status):
        out[stage][f"{lift:g}"] = kernels.STATUS_NAMES[st]
    return out


def summarize(items: list[dict], stages, lifts) -> dict:
    """{stage: {lift: summarize_success + statuses}, stored_agreement}."""
    out = {}
    for stage in stages:
        per = {}
        for lift in lifts:
            key = f"{lift:g}"
            rows = [
                {
                    "category": it["category"],
                    stage: {"success": it["status"][stage][key] == "stable"},
                }
                for it in items
            ]
            s = evaluate.summarize_success(rows, stage)
            statuses: dict[str, int] = {}
            for it in items:
                name = it["status"][stage][key]
                statuses[name] = statuses.get(name, 0) + 1
            s["statuses"] = statuses
            per[key] = s
        agree = sum(it["status"][stage]["0"] == it["stored"][stage] for it in items)
        out[stage] = {
            "by_lift": per,
            "stored_mean": evaluate.summarize_success(
                [{"category": it["category"], stage: {"success": it["stored"][stage] == "stable"}}
                 for it in items],
                stage,
            )["mean"],
            "stored_agreement": {"pairs": len(items), "same_status_at_lift_0": agree},
        }  # fmt: skip
    return out


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--records", required=True, help="per-pair JSONL(.gz) of eval_where / eval_stage3"
    )
    p.add_argument("--data", required=True, help="the generated dataset (for the assets)")
    p.add_argument(
        "--stages", default="stage1", help="comma-separated record stages, e.g. stage1,all_stages"
    )
    p.add_argument(
        "--lifts", default="0,0.0025,0.005,0.0075,0.01,0.015", help="metres (0 is always added)"
    )
    p.add_argument("--out", required=True, help="results JSON")
    p.add_argument(
        "--items", default=None, help="per-pair JSONL, appended as pairs finish (resume)"
    )
    p.add_argument("--limit", type=int, default=None, help="first N records only (smoke runs)")
    p.add_argument("--label", default="", help="free text stored in the results")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)

    from sim.library import build_library
    from sim.scene import build_scene

    stages = [s for s in args.stages.split(",") if s]
    lifts = parse_lifts(args.lifts)
    records = read_rows(args.records)[: args.limit]
    for r in records:
        for s in stages:
            if s not in r or "pose" not in r[s]:
                raise ValueError(f"{args.records}: pair {r.get('pair_index')} has no {s!r} pose")
    items_path = Path(args.items or Path(args.out).with_suffix(".items.jsonl"))
    done: dict[int, dict] = {}
    if items_path.exists():
        for line in open(items_path):
            if line.strip():
                it = json.loads(line)
                if all(f"{v:g}" in it["status"].get(s, {}) for s in stages for v in lifts):
                    done[it["pair_index"]] = it
    dataset_dir, _ = dataset_bridge.resolve_dataset_dir(args.data)
    recipe = dataset_bridge.read_recipe(dataset_dir)
    library = build_library(
        dataset_bridge.dataset_config_from_recipe(recipe).library, progress=False
    )
    stability = evaluate.protocol_stability()
    t0 = time.time()
    todo = [r for r in records if r["pair_index"] not in done]
    items_path.parent.mkdir(parents=True, exist_ok=True)
    with open(items_path, "a") as fh:
        for r in tqdm(todo, desc="release lift", unit="pair", disable=args.no_progress):
            scene = build_scene(library.objects[r["object"]], library.supports[r["support"]])
            it = {
                "pair_index": r["pair_index"],
                "category": r["category"],
                "stored": {s: r[s]["status"] for s in stages},
                "status": judge_pair(scene, r, stages, lifts, stability),
            }
            fh.write(json.dumps(it) + "\n")
            fh.flush()
            done[r["pair_index"]] = it
    items = [done[r["pair_index"]] for r in records]
    results = {
        "label": args.label,
        "records": os.fspath(args.records),
        "pairs": len(items),
        "lifts_m": lifts,
        "protocol": "evaluate.protocol_stability, MuJoCo on the CPU; the stage's chosen pose "
        "moved lift metres along +z of the support frame (rotation kept)",
        "stages": summarize(items, stages, lifts),
        "seconds": round(time.time() - t0, 1),
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    for s in stages:
        row = {k: round(v["mean"], 1) for k, v in results["stages"][s]["by_lift"].items()}
        print(f"{s}: success by lift (m) {row}; stored {results['stages'][s]['stored_mean']:.1f}")
    return results


if __name__ == "__main__":
    _cli.run(main)
