"""Summaries of held-out evaluation runs from their per-pair files (no simulation).

    # pose errors of every stage's chosen pose of an eval_stage3 run
    python -m experiments.summarise_heldout errors \
        --pairs results/hanging_success_stage3_s8.pairs.jsonl.gz --out results/pose_errors.json

    # several runs' success rates on the pairs they all have (mean over categories)
    python -m experiments.summarise_heldout compare --runs \
        results/hanging_success_stage3.pairs.jsonl.gz,results/hanging_success_stage3_s8.pairs.jsonl.gz

Success and errors are read from the per-pair JSONL (``eval_where`` / ``eval_stage3`` write
one row per pair: ``category`` and per stage ``success``, ``status``, ``any_of_k``,
``translation_error_m``, ``rotation_error_deg``, ``min_rotation_error_deg``).
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import os

import numpy as np

from experiments import _cli

STAGES = ("stage1", "stage1_2", "stage1_3", "all_stages", "all_stages_paper")
ERRORS = ("translation_error_m", "rotation_error_deg", "min_rotation_error_deg")


def read_rows(path: str) -> list[dict]:
    """Rows of a per-pair JSONL (optionally gzipped); ValueError when it has none."""
    opener = gzip.open if path.endswith(".gz") else open
    with opener(path, "rt") as f:
        rows = [json.loads(line) for line in f if line.strip()]
    if not rows:
        raise ValueError(f"{path}: no pairs")
    return rows


def read_pairs(path: str) -> dict[int, dict]:
    """Rows of a per-pair JSONL (optionally gzipped), by pair index."""
    return {int(r["pair_index"]): r for r in read_rows(path)}


def category_mean(rows: list[dict], stage: str, key: str = "success") -> float:
    """Percent, mean over categories of the per-category mean of ``row[stage][key]``."""
    by_cat = collections.defaultdict(list)
    for r in rows:
        by_cat[r["category"]].append(float(r[stage][key]))
    return 100.0 * float(np.mean([np.mean(v) for v in by_cat.values()]))


def _stats(x) -> dict:
    x = np.asarray(x, float)
    return {
        "mean": float(x.mean()),
        "median": float(np.median(x)),
        "p90": float(np.quantile(x, 0.9)),
    }


def pose_errors(rows: list[dict]) -> dict:
    """Per stage present: mean / median / p90 of each error, and the median per category."""
    out = {}
    for stage in STAGES:
        have = [r for r in rows if stage in r and ERRORS[0] in r[stage]]
        if not have:
            continue
        out[stage] = {e: _stats([r[stage][e] for r in have]) for e in ERRORS}
        by_cat = collections.defaultdict(list)
        for r in have:
            by_cat[r["category"]].append(r[stage]["translation_error_m"])
        out[stage]["translation_error_m_median_per_category"] = {
            c: float(np.median(v)) for c, v in sorted(by_cat.items())
        }
        out[stage]["statuses"] = dict(collections.Counter(r[stage]["status"] for r in have))
    return out


def compare(paths: list[str]) -> dict:
    """Every run's success (and any-of-K) per stage on the pairs common to all runs."""
    runs = {p: read_pairs(p) for p in paths}
    common = sorted(set.intersection(*(set(r) for r in runs.values())))
    table = {}
    for p, rows_by in runs.items():
        rows = [rows_by[i] for i in common]
        table[p] = {
            s: {
                "mean": category_mean(rows, s),
                "any_of_k": category_mean(rows, s, "any_of_k")
                if "any_of_k" in rows[0][s]
                else None,
            }
            for s in STAGES
            if s in rows[0]
        }
    return {"pairs": len(common), "runs": table}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="what", required=True)
    e = sub.add_parser("errors", help="pose errors of a run's chosen poses")
    e.add_argument("--pairs", required=True, help="per-pair JSONL(.gz) of eval_where/eval_stage3")
    e.add_argument("--out", default=None, help="JSON to write")
    e.add_argument("--label", default="", help="free text stored in the JSON")
    c = sub.add_parser("compare", help="runs' success rates on their common pairs")
    c.add_argument("--runs", required=True, help="comma-separated per-pair JSONL(.gz) files")
    c.add_argument("--out", default=None, help="JSON to write")
    args = parser.parse_args(argv)
    if args.what == "errors":
        rows = list(read_pairs(args.pairs).values())
        result = {
            "label": args.label,
            "pairs": len(rows),
            "source": args.pairs,
            "definition": "translation_error_m: distance to the nearest ground-truth stable "
            "position; rotation_error_deg: geodesic angle to the ground-truth pose nearest in "
            "position; min_rotation_error_deg: to the nearest ground-truth rotation; each "
            "stage's chosen (evaluated) pose",
            **pose_errors(rows),
        }
    else:
        result = compare([p for p in args.runs.split(",") if p])
    text = json.dumps(result, indent=1)
    print(text if len(text) < 4000 else text[:4000] + "\n...")
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            f.write(text + "\n")
    return result


if __name__ == "__main__":
    _cli.run(main)
