"""A planner's figure over several OMPL seeds: precision / recall / F1 of each run (an
``eval_paths`` pairs.jsonl, spliced or whole) and their mean, with the sample standard deviation
of F1 over the runs (the "+-" of docs/paths.md since the thirty-first session). CPU, instant.

    python scripts/seed_means.py --runs results/paths_s41/first_seed{1,2,3}.pairs.jsonl \\
        --out results/paths_s41/first_seeds1to3.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_path_runs import figures, outcome  # noqa: E402

from experiments.eval_paths import read_rows  # noqa: E402


def seed_means(runs: list[str]) -> dict:
    per_run = {}
    for run in runs:
        rows = read_rows(run)
        per_run[run] = figures([outcome(r) for r in rows.values()]) | {"pairs": len(rows)}
    keys = ("precision", "recall", "f1")
    mean = {k: round(float(np.mean([f[k] for f in per_run.values()])), 1) for k in keys}
    f1 = [f["f1"] for f in per_run.values()]
    sd = round(float(np.std(f1, ddof=1)), 1) if len(f1) > 1 else None
    return dict(runs=per_run, mean=mean, f1_sd=sd)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", required=True, help="eval_paths pairs.jsonl, one a seed")
    ap.add_argument("--out", default=None, help="JSON")
    args = ap.parse_args(argv)
    result = seed_means(args.runs)
    m = result["mean"]
    print(
        f"{m['precision']} / {m['recall']} / {m['f1']} +- {result['f1_sd']} over {len(args.runs)} runs"
    )
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
