"""Two Stage-1 networks' refined candidates pooled, studied on two evaluations' records.

    python -m experiments.mix_stage1 \\
        --select-on results/validation_where_s15/val_k16.pairs.jsonl.gz \\
                    results/validation_where_s17/val_k16_orig22k.pairs.jsonl.gz \\
        --apply-to results/hanging_success_stage3_s16_k16.pairs.jsonl.gz \\
                   results/hanging_success_stage3_s17_orig.pairs.jsonl.gz \\
        --out results/mix_stage1_s17.json

The `small` and the `original` Stage-1 presets (issue 14) propose differently: the original's
first proposal hangs more often (held-out 30.9 vs 24.6 %), but its K = 16 proposals cover
fewer stable poses (a stable pose within CEM's box of some proposal: 72.2 vs 78.4 %). Each
``eval_stage3`` run simulated every refined candidate and recorded its V (the same CEM V in
both runs), so a pipeline that refines the proposals of both networks is scored without
simulation: its answer is the answer rule (``stage3.ANSWER_PIPELINE.select``: highest V among
the candidates with no observed object point inside the support) over the pooled candidates.
Mixes: each run alone (its recorded answer, reproduced), the first k_a of run A's K proposals
with the first k_b of run B's (the proposals are independent draws of the noise, so the first
k of K are a K = k run's; the CEM keys differ, which does not change the distribution). The
mix with the best validation mean (``--select-on``: records of the validation objects, A then
B) is applied once to ``--apply-to`` (held-out, A then B).
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from experiments import _cli
from experiments.rerank_stage3 import category_means, proposals_of, read_records
from omnihang_jax import selection, stage3

# (k_a, k_b) as quarters of the runs' K: proposals of run A and of run B whose refined
# candidates are pooled; the runs' own cost where k_a + k_b = K (K = 16: 16+0, 0+16, 12+4,
# 8+8, 4+12, and 16+16 at twice the cost)
MIXES = ((4, 0), (0, 4), (3, 1), (2, 2), (1, 3), (4, 4))


def mixes(k: int) -> list[tuple[int, int]]:
    out = []
    for qa, qb in MIXES:
        m = (k * qa // 4, k * qb // 4)
        if m not in out and sum(m) > 0:
            out.append(m)
    return out


def paired(path_a: str, path_b: str) -> tuple[list[dict], list[dict], int]:
    """Records of the two runs, matched by pair file (both must hold the same pairs)."""
    a, b = read_records(path_a), read_records(path_b)
    k = proposals_of(a)
    if proposals_of(b) != k:
        raise ValueError(f"{path_a} and {path_b}: runs of different K")
    by_file = {r["file"]: r for r in b}
    missing = [r["file"] for r in a if r["file"] not in by_file]
    if missing or len(a) != len(b):
        raise ValueError(
            f"the runs hold different pairs ({len(a)} vs {len(b)}; e.g. {missing[:3]})"
        )
    return a, [by_file[r["file"]] for r in a], k


def refined(k: int, n: int) -> np.ndarray:
    """Indices, in a record's 4K + 1 candidates, of the refined candidates (both starts: from
    Stage 1 and from Stage 2) of the first n proposals."""
    return np.concatenate([np.arange(2 * k, 2 * k + n), np.arange(3 * k, 3 * k + n)])


def mix_outcomes(a: list[dict], b: list[dict], k: int, ka: int, kb: int) -> list[bool]:
    """Per pair: the simulated outcome of the answer rule over the pooled refined candidates
    (both starts, Stage 1 and Stage 2, of the first ka proposals of A and kb of B)."""
    config = stage3.ANSWER_PIPELINE.select
    key = selection.grid_key(config.depth, config.radius)
    out = []
    for ra, rb in zip(a, b, strict=True):
        v, counts, ok = [], [], []
        for r, n in ((ra, ka), (rb, kb)):
            idx = refined(k, n)
            v += [r["v"][i] for i in idx]
            counts += [r["inside_counts"][key][i] for i in idx]
            ok += [r["stable_all"][i] for i in idx]
        keys = np.asarray(
            selection.select_key(np.asarray(v, np.float32), np.asarray(counts), config)
        )
        out.append(bool(ok[int(np.argmax(keys))]))
    return out


def study(a: list[dict], b: list[dict], k: int) -> dict:
    table = {}
    for ka, kb in mixes(k):
        res = category_means(a, mix_outcomes(a, b, k, ka, kb))
        hangs = [
            any(ra["stable_all"][i] for i in refined(k, ka))
            or any(rb["stable_all"][i] for i in refined(k, kb))
            for ra, rb in zip(a, b, strict=True)
        ]
        res["any_refined"] = category_means(a, hangs)["mean"]
        table[f"{ka}+{kb}"] = res
    return table


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--select-on", nargs=2, required=True, metavar=("A", "B"),
                        help="validation-object records of run A and run B")  # fmt: skip
    parser.add_argument("--apply-to", nargs=2, default=None, metavar=("A", "B"),
                        help="held-out records of the same two pipelines")  # fmt: skip
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    for p in args.select_on + (args.apply_to or []):
        if not os.path.exists(p):
            parser.error(f"no such records: {p}")
    a, b, k = paired(*args.select_on)
    # the answer rule's log V keys on the recorded V reproduce run A's recorded answers
    recorded = category_means(a, [r["all_stages"]["success"] for r in a])["mean"]
    val = study(a, b, k)
    chosen = max(val, key=lambda m: (val[m]["mean"], -sum(map(int, m.split("+")))))
    result = {
        "select_on": args.select_on,
        "proposals": k,
        "recorded_answer_a": recorded,
        "validation": {
            m: {"mean": r["mean"], "any_refined": r["any_refined"]} for m, r in val.items()
        },
        "chosen": chosen,
    }
    print(f"validation ({len(a)} pairs): run A recorded {recorded:.2f}; "
          + ", ".join(f"{m} {r['mean']:.2f}" for m, r in val.items()) + f"; chosen {chosen}")  # fmt: skip
    if args.apply_to:
        ha, hb, hk = paired(*args.apply_to)
        if hk != k:
            parser.error("the held-out runs' K differs from the validation runs'")
        held = study(ha, hb, hk)
        result["apply_to"] = args.apply_to
        result["heldout"] = {m: {"mean": r["mean"], "any_refined": r["any_refined"],
                                 "per_category": r["per_category"]} for m, r in held.items()}  # fmt: skip
        result["heldout_chosen"] = held[chosen]["mean"]
        print(f"held-out ({len(ha)} pairs): " + ", ".join(f"{m} {r['mean']:.2f}" for m, r in held.items())
              + f"; the chosen mix {chosen}: {held[chosen]['mean']:.2f}")  # fmt: skip
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    _cli.run(main)
