"""Held-out success read two ways: by whether the pair's object and support were seen in
training (the paper's split holds out both; a split by pairs would not).

    python -m experiments.heldout_readings --pairs results/hanging_success_stage3.pairs.jsonl.gz \\
        --out results/hanging_success_readings.json

Reads an evaluation's per-pair JSONL (eval_where or eval_stage3; .gz allowed) and the
dataset's recipe, groups the pairs by (object seen in training, support seen in training) and
reports, per stage found in the file (stage1, stage1_2, stage1_3, all_stages), the success
rate as the mean over categories (the evaluation's own protocol) and over pairs, with counts.
No simulation: the per-pair outcomes are the evaluation's.
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from experiments import _cli
from experiments.summarise_heldout import STAGES, category_mean, read_rows

GROUPS = {
    (False, True): "unseen object, seen support",
    (True, False): "seen object, unseen support",
    (False, False): "unseen object, unseen support",
    (True, True): "seen object, seen support",
}


def readings(rows: list[dict], recipe: dict) -> dict:
    train = [p for p in recipe["pairs"] if p[2] == "train"]
    seen_objects, seen_supports = {p[0] for p in train}, {p[1] for p in train}
    stages = [s for s in STAGES if rows and s in rows[0]]
    groups: dict[str, list[dict]] = {"all": rows}
    for r in rows:
        key = GROUPS[(r["object"] in seen_objects, r["support"] in seen_supports)]
        groups.setdefault(key, []).append(r)
    out = {}
    for name, members in groups.items():
        entry = {"pairs": len(members)}
        for stage in stages:
            entry[stage] = {
                "mean_over_categories": category_mean(members, stage),
                "mean_over_pairs": 100 * float(np.mean([bool(r[stage]["success"]) for r in members])),
                "categories": len({r["category"] for r in members}),
            }  # fmt: skip
        out[name] = entry
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--pairs", required=True, help="per-pair JSONL(.gz) of an evaluation")
    parser.add_argument("--data", default="datasets/paper", help="dataset (recipe.json)")
    parser.add_argument("--out", default=None, help="JSON")
    args = parser.parse_args(argv)
    with open(os.path.join(args.data, "recipe.json")) as f:
        recipe = json.load(f)
    rows = read_rows(args.pairs)  # raises on an empty file
    missing = [k for k in ("object", "support", "category") if k not in rows[0]]
    if missing:
        raise ValueError(f"{args.pairs}: rows lack {missing}; not an evaluation's per-pair file")
    result = {"source": args.pairs, "groups": readings(rows, recipe)}
    for name, entry in result["groups"].items():
        figures = ", ".join(
            f"{s} {entry[s]['mean_over_categories']:.1f}" for s in STAGES if s in entry
        )
        print(f"{name:32s} {entry['pairs']:5d} pairs: {figures}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    _cli.run(main)
