"""The answer among the refined candidates of several runs, each ranked by its own run.

    python -m experiments.union_views --runs RUN_VIEW0.pairs.jsonl.gz RUN_VIEW4of8.pairs.jsonl.gz \\
        --out results/views_s26_heldout.json
    python -m experiments.union_views --keys UNION_KEY0.json UNION_KEY1.json UNION_KEY2.json \
        --out results/views_s32_heldout_views3_keys3.json

Twenty-sixth session (issue 12). ``eval_stage3 --view J/T`` runs the whole pipeline (CEM's V and
the ranking networks) on another evenly spaced subsample of the clouds. Runs of the same pairs
with the same key but different views find different candidates and rank them differently;
``PipelineConfig.views`` runs several views in one call and answers with the best of all their
candidates by the answer rule's key (the rankers' mean log P from each candidate's own view,
observed inside points first, ``selection.CHOSEN``). This computes that answer from the runs'
records (every candidate was simulated): per run, the union, and how often some candidate of
the union hangs. Mean over categories, as everywhere.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from experiments import _cli
from experiments.rerank_stage3 import category_means, proposals_of, read_records, rule_keys
from omnihang_jax import refine

# The default pipeline's records (three views 0, 1/2, 3/4; K = 10; one CEM key per row): the
# validation objects' 345 pairs and the held-out 1,794, each evaluated under CEM keys 0-2.
V = "results/validation_where_s27"
H = "results/hanging_success_stage3"
VALIDATION_RECORDS = [
    [f"{V}/val_k10_v0.pairs.jsonl.gz", f"{V}/val_k10_v1of2.pairs.jsonl.gz",
     f"{V}/val_k10_v3of4.pairs.jsonl.gz"],
    [f"{V}/val_k10_v0_seed1.pairs.jsonl.gz", f"{V}/val_k10_v1of2_seed1.pairs.jsonl.gz",
     f"{V}/val_k10_v3of4_seed1.pairs.jsonl.gz"],
    [f"{V}/val_k10_v0_seed2.pairs.jsonl.gz", f"{V}/val_k10_v1of2_seed2.pairs.jsonl.gz",
     f"{V}/val_k10_v3of4_seed2.pairs.jsonl.gz"],
]  # fmt: skip
HELDOUT_RECORDS = [
    [f"{H}_s27_k10_view0.pairs.jsonl.gz", f"{H}_s27_k10_view1of2.pairs.jsonl.gz",
     f"{H}_s31_k10_view3of4.pairs.jsonl.gz"],
    [f"{H}_s30_k10_view0_seed1.pairs.jsonl.gz", f"{H}_s30_k10_view1of2_seed1.pairs.jsonl.gz",
     f"{H}_s32_k10_view3of4_seed1.pairs.jsonl.gz"],
    [f"{H}_s30_k10_view0_seed2.pairs.jsonl.gz", f"{H}_s30_k10_view1of2_seed2.pairs.jsonl.gz",
     f"{H}_s32_k10_view3of4_seed2.pairs.jsonl.gz"],
]  # fmt: skip


def union(runs: list[list[dict]]) -> dict:
    order = [int(r["pair_index"]) for r in runs[0]]
    for rows in runs[1:]:
        if [int(r["pair_index"]) for r in rows] != order:
            raise ValueError("the runs hold different pairs (or another order)")
    ks = [proposals_of(rows) for rows in runs]
    parts = [rule_keys(rows, k) for rows, k in zip(runs, ks, strict=True)]
    rows0 = runs[0]
    out = {"runs": []}
    for keys, stable in parts:
        pick = stable[np.arange(len(rows0)), keys.argmax(1)]
        out["runs"].append(category_means(rows0, pick))
    keys = np.concatenate([p[0] for p in parts], axis=1)
    stable = np.concatenate([p[1] for p in parts], axis=1)
    out["union"] = category_means(rows0, stable[np.arange(len(rows0)), keys.argmax(1)])
    # Stages 1+3: the same rule over the Stage-1 starts' refined candidates alone (the first K
    # of each run's 2K pooled candidates, rerank_stage3.pool_indices)
    keys1 = np.concatenate([p[0][:, :k] for p, k in zip(parts, ks, strict=True)], axis=1)
    stable1 = np.concatenate([p[1][:, :k] for p, k in zip(parts, ks, strict=True)], axis=1)
    out["union_stage1_3"] = category_means(rows0, stable1[np.arange(len(rows0)), keys1.argmax(1)])
    out["union_any_hangs"] = category_means(rows0, stable.any(1))["mean"]
    # why the union's answer fails (thirty-second session): its simulated status, split by
    # whether another candidate of the union hangs (a ranking loss) or none does (a search loss)
    # (records without statuses: "stable" / "failed" from the simulated outcome)
    statuses = np.concatenate([
        np.asarray([r["all_stages"]["statuses"] if "statuses" in r.get("all_stages", {})
                    else np.where(part, "stable", "failed") for r, part in zip(rows, p[1], strict=True)])
        for rows, p in zip(runs, parts, strict=True)
    ], axis=1)  # fmt: skip
    pick = keys.argmax(1)
    answer = statuses[np.arange(len(rows0)), pick]
    fails = ~stable[np.arange(len(rows0)), pick]
    breakdown = {"another_hangs": {}, "none_hangs": {}}
    for i in np.flatnonzero(fails):
        side = "another_hangs" if stable[i].any() else "none_hangs"
        cat = breakdown[side].setdefault(str(answer[i]), {})
        cat[rows0[i]["category"]] = cat.get(rows0[i]["category"], 0) + 1
    out["failures"] = {
        side: {status: {"pairs": sum(c.values()), "per_category": dict(sorted(c.items()))}
               for status, c in sorted(d.items())}
        for side, d in breakdown.items()
    }  # fmt: skip
    out["first_any_hangs"] = category_means(rows0, parts[0][1].any(1))["mean"]
    return out


def keys_summary(unions: list[dict]) -> dict:
    """Several unions of one pipeline under different CEM keys (this module's JSONs) -> the
    mean and spread over keys of the answer's success (all stages and Stages 1+3), of "some
    candidate hangs", and the per-category success averaged over keys."""
    out = {}
    for field in ("union", "union_stage1_3"):
        means = [u[field]["mean"] for u in unions]
        cats = unions[0][field]["per_category"]
        out[field] = {
            "per_key": means, "mean": float(np.mean(means)), "std": float(np.std(means)),
            "per_category": {c: float(np.mean([u[field]["per_category"][c] for u in unions]))
                             for c in cats},
        }  # fmt: skip
    anyh = [u["union_any_hangs"] for u in unions]
    out["union_any_hangs"] = {"per_key": anyh, "mean": float(np.mean(anyh))}
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    group = ap.add_mutually_exclusive_group(required=True)
    group.add_argument("--runs", nargs="+", help="eval_stage3 records, same pairs")
    group.add_argument(
        "--keys", nargs="+", metavar="UNION_JSON",
        help="instead: this module's JSONs of one pipeline under different CEM keys -> their "
        "mean and spread (keys_summary)",
    )  # fmt: skip
    ap.add_argument("--out", default=None, help="JSON")
    args = ap.parse_args(argv)
    if args.keys:
        res = {"unions": args.keys,
               **keys_summary([json.loads(Path(p).read_text()) for p in args.keys])}  # fmt: skip
        print(f"over {len(args.keys)} keys: {res['union']['mean']:.2f} +- {res['union']['std']:.2f}"
              f" (per key {', '.join(f'{m:.2f}' for m in res['union']['per_key'])}); Stages 1+3 "
              f"{res['union_stage1_3']['mean']:.2f}; some candidate hangs "
              f"{res['union_any_hangs']['mean']:.2f}")  # fmt: skip
        if args.out:
            refine.write_json(args.out, res)
        return res
    if len(args.runs) < 2:
        raise ValueError("--runs needs two runs or more")
    res = {"records": args.runs, **union([read_records(p) for p in args.runs])}
    for path, r in zip(args.runs, res["runs"], strict=True):
        print(f"{Path(path).name}: {r['mean']:.2f}")
    print(f"union, Stages 1+3: {res['union_stage1_3']['mean']:.2f}")
    print(f"union: {res['union']['mean']:.2f} (some candidate hangs: {res['union_any_hangs']:.2f}, "
          f"first run alone {res['first_any_hangs']:.2f})")  # fmt: skip
    for side, d in res["failures"].items():
        print(f"failing answers, {side.replace('_', ' ')}: "
              + (", ".join(f"{s} {v['pairs']}" for s, v in d.items()) or "none"))  # fmt: skip
    if args.out:
        refine.write_json(args.out, res)
    return res


if __name__ == "__main__":
    _cli.run(main)
