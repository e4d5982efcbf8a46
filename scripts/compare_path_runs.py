"""Two or more eval_paths runs on the pairs all of them planned: precision / recall / F1 of
each over the common pairs (a run cut short is compared on what it finished), and how many
pairs' outcomes differ. CPU, seconds.

    python scripts/compare_path_runs.py --runs out/s34/paths80_oracle_seed1/pairs.jsonl \\
        results/paths80_goal_stable_s33_replan_seed1.pairs.jsonl \\
        --out results/paths80_s34_oracle_vs_replan_seed1.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def outcome(row: dict) -> str:
    """'free', 'colliding' or 'none' (no path returned)."""
    if not row["returned"]:
        return "none"
    return "free" if row["collision_free"] else "colliding"


def figures(outcomes: list[str]) -> dict:
    """Precision / recall / F1 in percent (one decimal) over the pairs of ``outcomes``."""
    returned = sum(o != "none" for o in outcomes)
    free = outcomes.count("free")
    p = 100.0 * free / returned if returned else 0.0
    r = 100.0 * free / len(outcomes) if outcomes else 0.0
    f = 2 * p * r / (p + r) if p + r else 0.0
    return dict(pairs=len(outcomes), returned=returned, collision_free=free,
                precision=round(p, 1), recall=round(r, 1), f1=round(f, 1))  # fmt: skip


def approach_used(row: dict):
    """The learned approach's direction the first plan used (a tuple), or None (plain plan)."""
    first = (row.get("approach") or {}).get("first_tried")
    return None if first is None else tuple(first)


def compare(runs: dict[str, dict[str, dict]]) -> dict:
    """``runs``: name -> {pair: row}. Figures of each on the pairs every run has, and the same
    split by ``approach_decision``: ``same`` where every run's first plan made the same
    approach decision (the same direction, or none), ``differ`` where they did not (thirty-
    seventh session: runs of one OMPL seed nearly repeat, so a paired difference between two
    approach rules comes almost all from the ``differ`` pairs)."""
    common = sorted(set.intersection(*(set(rows) for rows in runs.values())))
    out = {name: figures([outcome(rows[p]) for p in common]) for name, rows in runs.items()}
    kinds = [[outcome(rows[p]) for rows in runs.values()] for p in common]
    same = {p for p in common if len({approach_used(rows[p]) for rows in runs.values()}) == 1}
    split = {
        key: {name: figures([outcome(rows[p]) for p in common if (p in same) == (key == "same")])
              for name, rows in runs.items()}
        for key in ("same", "differ")
    }  # fmt: skip
    return dict(common_pairs=len(common), runs=out,
                pairs_differing=sum(len(set(k)) > 1 for k in kinds),
                approach_decision=split)  # fmt: skip


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", required=True, help="pairs.jsonl files")
    ap.add_argument("--method", default="nce_geometric")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    runs = {}
    for f in args.runs:
        rows = [json.loads(x) for x in Path(f).read_text().splitlines() if x.strip()]
        runs[f] = {r["pair"]: r for r in rows if r["method"] == args.method}  # last row counts
    summary = compare(runs)
    Path(args.out).write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    main()
