"""The answer rule re-chosen for a several-view pipeline, on validation keys (issue 12).

    python -m experiments.union_rules \\
        --select-on V0_KEY0.pairs.jsonl.gz,V1_KEY0.pairs.jsonl.gz V0_KEY1...,V1_KEY1... \\
        --apply-to H0_KEY0...,H1_KEY0... H0_KEY1...,H1_KEY1... --out results/union_rules.json

Each argument of --select-on / --apply-to is one CEM key: the comma-joined ``eval_stage3``
records of the pipeline's views under that key (as ``experiments.union_views`` joins them).
The default answer rule (``selection.CHOSEN``: the rankers' mean log P among the candidates with
no observed object point more than 0.5 mm inside the observed support within 5 mm) was chosen
in the tenth session on one view's records of CEM's V. Here every rule of the family

    key = mean log P(rankers) - weight * max(inside_count(depth, radius) - max_points, 0)

(every recorded (depth, radius), ``max_points`` in --max-points, ``weight`` in --weights; a
weight of 1e4 is the lexicographic rule of ``selection``) answers among the union of the views'
pooled candidates; the rule with the best mean over the --select-on keys (validation objects)
is applied once to the --apply-to keys (held-out), beside the default. Mean over categories as
everywhere.
"""

from __future__ import annotations

import argparse

import numpy as np

from experiments import _cli
from experiments.rerank_stage3 import category_means, pool_indices, proposals_of, read_records
from omnihang_jax import refine, selection

LEXICOGRAPHIC = 1e4  # selection._INSIDE_WEIGHT: no clear candidate loses to an inside one


class UnionPool:
    """One key's pooled candidates over its views: [N, C] mean log P of the rankers, inside
    counts per (depth, radius) grid key, simulated stable; rows (category per pair)."""

    def __init__(self, runs: list[list[dict]]):
        order = [int(r["pair_index"]) for r in runs[0]]
        for rows in runs[1:]:
            if [int(r["pair_index"]) for r in rows] != order:
                raise ValueError("the views' runs hold different pairs (or another order)")
        self.rows = runs[0]
        self.grid = sorted(runs[0][0]["inside_counts"])
        scores, stable, counts = [], [], {g: [] for g in self.grid}
        for rows in runs:
            idx = pool_indices(proposals_of(rows), "stage1_2")
            ranks = [np.asarray(r.get("v_rank") or [r["v"]], np.float64)[:, idx] for r in rows]
            scores.append(np.stack([np.log(np.clip(x, 1e-12, 1.0)).mean(0) for x in ranks]))
            stable.append(np.stack([np.asarray(r["stable_all"], bool)[idx] for r in rows]))
            for g in self.grid:
                counts[g].append(
                    np.stack([np.asarray(r["inside_counts"][g], np.int64)[idx] for r in rows])
                )
        self.scores = np.concatenate(scores, axis=1)
        self.stable = np.concatenate(stable, axis=1)
        self.counts = {g: np.concatenate(c, axis=1) for g, c in counts.items()}

    def success(self, grid: str, max_points: int, weight: float) -> dict:
        excess = np.maximum(self.counts[grid] - max_points, 0)
        pick = np.argmax(self.scores - weight * excess, axis=1)
        return category_means(self.rows, self.stable[np.arange(len(self.rows)), pick])


def rules(grid: list[str], max_points: list[int], weights: list[float]) -> list[dict]:
    return [{"grid": g, "max_points": m, "weight": w}
            for g in grid for m in max_points for w in weights]  # fmt: skip


def default_rule() -> dict:
    c = selection.CHOSEN
    return {"grid": selection.grid_key(c.depth, c.radius), "max_points": c.max_points,
            "weight": LEXICOGRAPHIC}  # fmt: skip


def score(pools: list[UnionPool], rule: dict) -> dict:
    per_key = [p.success(rule["grid"], rule["max_points"], rule["weight"]) for p in pools]
    cats = per_key[0]["per_category"]
    return {
        "per_key": [r["mean"] for r in per_key],
        "mean": float(np.mean([r["mean"] for r in per_key])),
        "per_category": {c: float(np.mean([r["per_category"][c] for r in per_key])) for c in cats},
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--select-on", nargs="+", required=True, metavar="RUNS",
                    help="validation keys, each the comma-joined records of its views")  # fmt: skip
    ap.add_argument("--apply-to", nargs="*", default=[], metavar="RUNS",
                    help="held-out keys, each the comma-joined records of its views")  # fmt: skip
    ap.add_argument("--max-points", default="0,1,2,4,8")
    ap.add_argument("--weights", default="0.02,0.05,0.1,0.2,0.5,1,1e4",
                    help="penalty per inside point beyond max_points (1e4: lexicographic)")  # fmt: skip
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    def load(keys):
        return [UnionPool([read_records(p) for p in key.split(",")]) for key in keys]

    val = load(args.select_on)
    grid = val[0].grid
    table = rules(grid, [int(x) for x in args.max_points.split(",")],
                  [float(x) for x in args.weights.split(",")])  # fmt: skip
    base = default_rule()
    if base["grid"] not in grid:
        raise ValueError(
            f"the records' inside-count grid {grid} lacks the default's {base['grid']}"
        )
    scored = [{**r, **score(val, r)} for r in table]
    best = max(scored, key=lambda r: r["mean"])
    res = {
        "select_on": args.select_on, "apply_to": args.apply_to,
        "default": {**base, "validation": score(val, base)},
        "chosen": {k: best[k] for k in ("grid", "max_points", "weight")},
        "chosen_validation": {k: best[k] for k in ("per_key", "mean", "per_category")},
        "table": [{k: r[k] for k in ("grid", "max_points", "weight", "per_key", "mean")}
                  for r in sorted(scored, key=lambda r: -r["mean"])],
    }  # fmt: skip
    print(f"validation: default {res['default']['validation']['mean']:.2f}, chosen "
          f"{best['mean']:.2f} ({res['chosen']})")  # fmt: skip
    if args.apply_to:
        held = load(args.apply_to)
        res["held_out"] = {"default": score(held, base), "chosen": score(held, best)}
        print(f"held-out: default {res['held_out']['default']['mean']:.2f}, chosen "
              f"{res['held_out']['chosen']['mean']:.2f}")  # fmt: skip
    if args.out:
        refine.write_json(args.out, res)
    return res


if __name__ == "__main__":
    _cli.run(main)
