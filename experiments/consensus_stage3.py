"""Consensus ranking of Stage 3's refined candidates, studied on an evaluation's records.

    python -m experiments.consensus_stage3 \\
        --select-on results/validation_where_s15/val_k16.pairs.jsonl.gz \\
        --apply-to results/hanging_success_stage3_s16_k16.pairs.jsonl.gz \\
        --out results/consensus_stage3_s16.json

V's ranking among the clear refined candidates is the largest loss of the pipeline (284 of its
~450 failed held-out answers: another clear candidate hangs). The 2K CEM runs of a pair often
end near each other; a pose that several runs reach, each with a high V, may be a wider, surer
basin than a lone high-V one. The rule studied here adds to the answer rule's key (log V of the
candidate, minus 1e4 per observed object point inside the support: ``selection.select_key``)

    lam * log( sum_j V_j * clear_j * exp(-|t_i - t_j|^2 / st^2 - angle(R_i, R_j)^2 / sr^2) )

over the pair's refined candidates j (``clear_only``: only those with no point inside; else
all). Every candidate of an ``eval_stage3`` run was simulated, so a ranking is scored without
simulation. The setting (lam, st, sr, clear_only) with the best mean over categories on the
``--select-on`` records (validation objects) is applied once to ``--apply-to`` (held-out);
lam = 0 is the recorded rule (its reproduction is checked against the recorded answers).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os

import numpy as np

from experiments import _cli
from experiments.rerank_stage3 import category_means, pool_indices, proposals_of, read_records
from omnihang_jax import selection, stage3

LAMBDAS = (0.25, 0.5, 1.0, 2.0)
SIGMA_T = (0.003, 0.005, 0.01, 0.02)  # m
SIGMA_R = (0.1, 0.2, 0.4)  # rad


def quaternion_angles(q: np.ndarray) -> np.ndarray:
    """[P, 4] unit quaternions (wxyz) -> [P, P] rotation angles between them (rad)."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    dot = np.clip(np.abs(q @ q.T), 0.0, 1.0)
    return 2.0 * np.arccos(dot)


def consensus_keys(v, counts, poses, lam: float, st: float, sr: float, clear_only: bool):
    """The answer keys of one pair's candidates: v [P], counts [P] (observed object points
    inside the support), poses [P, 7] -> [P]; lam = 0 gives ``selection.select_key``'s
    value_clear key."""
    config = stage3.ANSWER_PIPELINE.select
    key = np.asarray(selection.select_key(np.asarray(v, np.float32), np.asarray(counts), config))
    if lam:
        v = np.asarray(v, float)
        w = v * ((np.asarray(counts) <= config.max_points) if clear_only else 1.0)
        d2 = ((poses[:, None, :3] - poses[None, :, :3]) ** 2).sum(-1)
        kernel = np.exp(-d2 / st**2 - quaternion_angles(poses[:, 3:]) ** 2 / sr**2)
        key = key + lam * np.log(np.clip(kernel @ w, 1e-12, None))
    return key


def score(rows, k: int, lam=0.0, st=0.005, sr=0.2, clear_only=True) -> dict:
    """Mean over categories (and per category) of the rule's picks among the pooled refined
    candidates of every record."""
    idx = pool_indices(k, "stage1_2")
    config = stage3.ANSWER_PIPELINE.select
    grid = selection.grid_key(config.depth, config.radius)
    outcomes = []
    for r in rows:
        poses = np.asarray(r["poses_all"], float)[idx]
        keys = consensus_keys(
            np.asarray(r["v"])[idx], np.asarray(r["inside_counts"][grid])[idx], poses,
            lam, st, sr, clear_only,
        )  # fmt: skip
        outcomes.append(r["stable_all"][idx[int(np.argmax(keys))]])
    return category_means(rows, outcomes)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--select-on", required=True, help="validation run's .pairs.jsonl[.gz]")
    parser.add_argument("--apply-to", required=True, help="held-out run's .pairs.jsonl[.gz]")
    parser.add_argument("--out", required=True, help="results JSON")
    args = parser.parse_args(argv)
    val, held = read_records(args.select_on), read_records(args.apply_to)
    k_val, k_held = proposals_of(val), proposals_of(held)
    base_val, base_held = score(val, k_val), score(held, k_held)
    recorded = category_means(val, [r["all_stages"]["success"] for r in val])
    table = []
    for lam, st, sr, clear_only in itertools.product(LAMBDAS, SIGMA_T, SIGMA_R, (True, False)):
        s = score(val, k_val, lam, st, sr, clear_only)
        table.append(dict(lam=lam, st=st, sr=sr, clear_only=clear_only, mean=s["mean"]))
    table.sort(key=lambda row: -row["mean"])
    best = table[0]
    chosen = {x: best[x] for x in ("lam", "st", "sr", "clear_only")}
    applied = score(held, k_held, **chosen)
    out = dict(
        select_on=os.fspath(args.select_on),
        apply_to=os.fspath(args.apply_to),
        proposals=k_val,
        rule=__doc__.split("\n\n")[2],
        recorded_rule={"validation": base_val["mean"], "held_out": base_held["mean"]},
        recorded_validation_answers=recorded["mean"],
        validation_table=table,
        chosen=chosen,
        validation_chosen=best["mean"],
        held_out_chosen=applied["mean"],
        held_out_chosen_per_category=applied["per_category"],
        held_out_top5=[
            dict(row, held_out=score(held, k_held, **{x: row[x] for x in chosen})["mean"])
            for row in table[:5]
        ],
    )
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(out, f, indent=1)
    print(
        f"recorded rule: validation {base_val['mean']:.2f}, held-out {base_held['mean']:.2f}; "
        f"chosen {chosen}: validation {best['mean']:.2f}, held-out {applied['mean']:.2f}"
    )
    return out


if __name__ == "__main__":
    _cli.run(main)
