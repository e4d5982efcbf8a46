"""Issue 13, from the rows of whole `eval_paths` runs of one planner under different OMPL seeds (no
planning; forty-sixth session, docs/paths.md): what a planner that runs k seeds side by side
and keeps one of their paths would score. Each k-subset of the runs is one reading; a pair gets
no path when none of the k runs returned one, else the path the rule picks:

- ``first``: the one whose pipeline (approach search, planning, clearance pass) finished first,
  as a k-process planner that stops at the first path would return;
- ``fewest_flags``: the fewest estimator flags on the dense path, then the first;
- ``widest_gap``: the largest observed clearance after the clearance pass.

Only what the planner knows at run time picks the path (never the mesh check). The k = 1 readings
are the runs themselves. Outcomes and figures as `scripts/compare_path_runs.py`.

    python scripts/probe_multistart.py --runs results/paths_s45/full_seed1.pairs.jsonl \\
        results/paths_s46/full_seed2.pairs.jsonl results/paths_s43/full_seed3.pairs.jsonl \\
        --out results/paths_s46/multistart.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_path_runs import figures, outcome  # noqa: E402

from experiments.eval_paths import read_rows  # noqa: E402


def pipeline_s(row: dict) -> float:
    """Seconds from the approach search to the cleared path (what a first-wins race compares)."""
    return (
        row["planning_s"]
        + row.get("clear_s", 0.0)
        + (row.get("approach") or {}).get("seconds", 0.0)
    )


RULES = {
    "first": pipeline_s,
    "fewest_flags": lambda r: (r["estimator_dense_flags"], pipeline_s(r)),
    "widest_gap": lambda r: -r.get("clear_gap_after_m", 0.0),
}


def pick(rows: list[dict], rule: str) -> str:
    returned = [r for r in rows if r["returned"]]
    return outcome(min(returned, key=RULES[rule])) if returned else "none"


def multistart(runs: dict[str, dict[str, dict]], rule: str) -> dict:
    common = sorted(set.intersection(*(set(rows) for rows in runs.values())))
    names = list(runs)
    out = {}
    for k in range(1, len(names) + 1):
        readings = {}
        for combo in itertools.combinations(names, k):
            outs = [pick([runs[n][p] for n in combo], rule) for p in common]
            readings[" + ".join(combo)] = figures(outs)
        keys = ("precision", "recall", "f1")
        mean = {key: round(float(np.mean([f[key] for f in readings.values()])), 1) for key in keys}
        out[f"k{k}"] = dict(mean=mean, readings=readings)
    return dict(pairs=len(common), by_k=out)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", required=True, help="whole runs' pairs.jsonl, one a seed")
    ap.add_argument("--out", required=True, help="JSON")
    args = ap.parse_args(argv)
    if len(args.runs) < 2:
        ap.error("--runs needs two runs or more")
    runs = {run: read_rows(run) for run in args.runs}
    summary = {rule: multistart(runs, rule) for rule in RULES}
    Path(args.out).write_text(json.dumps(summary, indent=1) + "\n")
    for rule, s in summary.items():
        line = ", ".join(f"k={k[1:]}: {v['mean']['precision']} / {v['mean']['recall']} / {v['mean']['f1']}"
                         for k, v in s["by_k"].items())  # fmt: skip
        print(f"{rule:13s} {line}  ({s['pairs']} pairs)")
    return summary


if __name__ == "__main__":
    main()
