"""Issue 13 diagnostic (thirty-third session): would planning each pair with several OMPL seeds
(a portfolio, one process per seed, the same wall time) and keeping one returned path per pair
raise the best hybrid's precision or recall?

From the per-pair rows of eval_paths runs on the same pairs (``pairs.jsonl`` files, e.g. the
best hybrid under OMPL seeds 1, 2, 3), for every pair the returned paths of all runs are pooled
and one is kept by a rule that uses only what the planner knows (the path's clearance from the
observed support after clearing, its waypoints, its planning time, the runs' order), against
the oracle that keeps a free path whenever one was returned (the mesh check's verdict, not
available to a planner). Precision = free kept paths / kept paths, recall = free kept paths /
pairs, as eval_paths. Also the clearance of free and colliding returned paths (does a colliding
path pass closer to the observed support?). Seconds, CPU.

    python scripts/probe_portfolio.py --runs results/paths80_goal_stable_s24_keep45.pairs.jsonl,\
results/paths80_goal_stable_s24_keep45_seed2.pairs.jsonl,results/paths80_goal_stable_s31_keep45_seed3.pairs.jsonl \
        --out results/paths80_s33_portfolio_probe.json
"""

import argparse
import json
from pathlib import Path

import numpy as np

# rule name -> (row field, sign): the kept path maximises sign * field among the returned ones
RULES = {
    "largest_clearance_after": ("clear_gap_after_m", 1.0),
    "largest_clearance_before": ("clear_gap_before_m", 1.0),
    "fewest_waypoints": ("waypoints", -1.0),
    "first_in_time": ("planning_s", -1.0),
}


def scores(kept: list, pairs: int) -> dict:
    """P / R / F1 (percent) of one kept row (or None) per pair."""
    returned = [r for r in kept if r is not None]
    free = sum(bool(r["collision_free"]) for r in returned)
    p = 100.0 * free / max(len(returned), 1)
    rec = 100.0 * free / max(pairs, 1)
    f1 = 2 * p * rec / (p + rec) if p + rec > 0 else 0.0
    return {"precision": p, "recall": rec, "f1": f1, "returned": len(returned), "free": free}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", required=True, help="eval_paths pairs.jsonl files, comma-separated")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    files = args.runs.split(",")
    runs = []
    for f in files:
        rows = [json.loads(line) for line in Path(f).read_text().splitlines() if line.strip()]
        runs.append({int(r["pair_index"]): r for r in rows})
    pairs = sorted(set.intersection(*(set(r) for r in runs)))
    if not pairs:
        ap.error("the runs share no pair")
    pooled = {p: [r[p] for r in runs if r[p].get("returned")] for p in pairs}
    result = {
        "runs": files,
        "pairs": len(pairs),
        "each_run": [
            scores([r[p] if r[p].get("returned") else None for p in pairs], len(pairs))
            for r in runs
        ],  # fmt: skip
        "first_run_that_returned": scores([(c or [None])[0] for c in pooled.values()], len(pairs)),
        "oracle": scores(
            [([x for x in c if x["collision_free"]] or c or [None])[0] for c in pooled.values()],
            len(pairs),
        ),
    }
    for name, (field, sign) in RULES.items():
        kept = [max(c, key=lambda x: sign * float(x.get(field, 0.0))) if c else None
                for c in pooled.values()]  # fmt: skip
        result[name] = scores(kept, len(pairs))
    # finite clearances only (a path the clearing never measured records none or inf)
    gaps = [(float(r["clear_gap_after_m"]), bool(r["collision_free"]))
            for c in pooled.values() for r in c
            if r.get("clear_gap_after_m") is not None
            and np.isfinite(float(r["clear_gap_after_m"]))]  # fmt: skip
    for label, want in (("free", True), ("colliding", False)):
        g = np.asarray([x for x, free in gaps if free == want])
        result[f"clearance_after_{label}_m"] = (
            {"n": int(g.size), "median": float(np.median(g)), "p25": float(np.percentile(g, 25)),
             "p75": float(np.percentile(g, 75))} if g.size else {"n": 0}
        )  # fmt: skip
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    for k in ("first_run_that_returned", *RULES, "oracle"):
        s = result[k]
        print(f"{k:28s} P {s['precision']:5.1f} R {s['recall']:5.1f} F1 {s['f1']:5.1f} "
              f"({s['free']} free of {s['returned']})")  # fmt: skip
    return result


if __name__ == "__main__":
    main()
