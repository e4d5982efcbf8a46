"""The Stage-3 answer rule studied after an evaluation run (``omnihang_jax.selection``).

    python -m experiments.rerank_stage3 --select-on results/validation_where_s9/RUN.pairs.jsonl.gz \\
        --apply-to results/hanging_success_stage3_s9.pairs.jsonl.gz --out results/rerank_stage3.json

An ``eval_stage3`` run simulates every candidate of every pair (``stable_all``) and, since the
ninth session, records each candidate's V (``v``) and its observed-cloud inside counts for a grid
of (depth, radius) (``inside_counts``), so any selection rule over those numbers is scored
without a new simulation. The settings (rule ``value_clear``: the highest V among candidates
with at most ``max_points`` object points inside the observed support, else the fewest; every
(depth, radius) of the grid; ``max_points`` in --max-points; the refined candidates from Stage 2
(the paper's pool) or from Stages 1 and 2) are scored on --select-on (pairs of validation
OBJECTS, never trained on); the best by mean success over categories is applied once to
--apply-to (the held-out pairs) beside the paper's rule (highest V). Mean over categories as
everywhere (docs/evaluation.md).

``--write-pairs OUT.pairs.jsonl.gz --summary OUT.json``: the --apply-to records rewritten with
the chosen rule as the all-stages answer, as ``eval_stage3`` (whose defaults are that rule,
``selection.CHOSEN``, pooled) writes them: ``all_stages`` = the rule's pick (success, status,
any of the pool, statuses, pose; its pose errors are not recorded), ``all_stages_paper`` = the
run's highest-V answer; and the run's summary with those figures (``eval_pipeline.
summarize_pipeline``). A run of the paper's rule is so turned into the chosen rule's without
a new simulation: every candidate was simulated.
"""

from __future__ import annotations

import argparse
import gzip
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from experiments import _cli
from omnihang_jax import eval_pipeline, refine, selection

POOLS = {"stage2": ("all_stages",), "stage1_2": ("stage1_3", "all_stages")}


def read_records(path: str) -> list[dict]:
    opener = gzip.open if str(path).endswith(".gz") else open
    with opener(path, "rt") as f:
        rows = [json.loads(line) for line in f if line.strip()]
    if not rows:
        raise ValueError(f"{path}: no records")
    missing = [k for k in ("stable_all", "v", "inside_counts") if k not in rows[0]]
    if missing:
        raise ValueError(
            f"{path}: records lack {missing}; rerun experiments.eval_stage3 (the ninth "
            "session's version records V and the inside counts of every candidate)"
        )
    return rows


def proposals_of(rows: list[dict], given: int | None = None) -> int:
    """K of an evaluation run, read from its records (each holds 4K + 1 candidates: Stage 1,
    1+2, 1+3, all stages, separated). ``given`` (a --proposals flag) must agree: records of a
    K = 10 run scored as K = 5 would silently pick from the wrong candidates."""
    sizes = {len(r["v"]) for r in rows}
    if len(sizes) != 1 or (next(iter(sizes)) - 1) % 4:
        raise ValueError(f"records hold {sorted(sizes)} candidates each; expected one 4K + 1")
    k = (sizes.pop() - 1) // 4
    if given is not None and given != k:
        raise ValueError(f"--proposals {given}, but the records are of a K = {k} run")
    return k


def pool_indices(k: int, pool: str) -> np.ndarray:
    """Candidate indices of a pool in a record's 4K+1 candidates (Stage 1, 1+2, 1+3, all
    stages, separated)."""
    start = {"stage1_3": 2 * k, "all_stages": 3 * k}
    return np.concatenate([np.arange(start[s], start[s] + k) for s in POOLS[pool]])


def successes(rows: list[dict], k: int, pool: str, config: selection.SelectConfig) -> dict:
    """Per pair: the chosen candidate's simulated outcome under a rule -> mean over
    categories, over pairs, and the per-category means (percent)."""
    idx = pool_indices(k, pool)
    key = selection.grid_key(config.depth, config.radius)
    v = np.asarray([r["v"] for r in rows], np.float32)[:, idx]
    counts = np.asarray([r["inside_counts"][key] for r in rows], np.int32)[:, idx]
    picks = np.asarray(selection.select(v, counts, config))
    return category_means(rows, [r["stable_all"][idx[p]] for r, p in zip(rows, picks, strict=True)])


def rule_keys(rows: list[dict], k: int) -> tuple[np.ndarray, np.ndarray]:
    """([N, 2K] the default pipeline's answer key, [N, 2K] simulated stable) of each record's
    pooled refined candidates (Stages 1 and 2 starts): the ranking networks' mean log P
    (``v_rank``; the run's V where none was recorded), observed inside points first
    (``selection.CHOSEN``). The answer is the argmax (``experiments.rerank_completed``,
    ``experiments.union_views``)."""
    idx = pool_indices(k, "stage1_2")
    grid = selection.grid_key(selection.CHOSEN.depth, selection.CHOSEN.radius)
    keys, stable = [], []
    for r in rows:
        ranks = np.asarray(r.get("v_rank") or [r["v"]], np.float64)[:, idx]
        score = np.log(np.clip(ranks, 1e-12, 1.0)).mean(0)
        counts = np.asarray(r["inside_counts"][grid], np.int64)[idx]
        keys.append(np.asarray(selection.select_key(score, counts, selection.CHOSEN)))
        stable.append(np.asarray(r["stable_all"], bool)[idx])
    return np.stack(keys), np.stack(stable)


def category_means(rows: list[dict], outcomes) -> dict:
    """Per pair a success (bool) -> the mean over object categories (the figure everywhere),
    over pairs, and per category (percent)."""
    by_cat = defaultdict(list)
    for r, ok in zip(rows, outcomes, strict=True):
        by_cat[r["category"]].append(bool(ok))
    per_cat = {c: 100.0 * float(np.mean(x)) for c, x in sorted(by_cat.items())}
    return {
        "mean": float(np.mean(list(per_cat.values()))),
        "pair_mean": 100.0 * float(np.mean([x for xs in by_cat.values() for x in xs])),
        "per_category": per_cat,
        "pairs": sum(len(x) for x in by_cat.values()),
    }


def any_refined(rows: list[dict], k: int, pool: str) -> float:
    idx = pool_indices(k, pool)
    by_cat = defaultdict(list)
    for r in rows:
        by_cat[r["category"]].append(any(r["stable_all"][i] for i in idx))
    return 100.0 * float(np.mean([np.mean(x) for x in by_cat.values()]))


def answer_records(rows: list[dict], k: int, pool: str, config: selection.SelectConfig):
    """The records with the rule's pick over ``pool`` as the all-stages answer (module
    docstring); the recorded answer of the run moves to ``all_stages_paper`` unless there."""
    idx = pool_indices(k, pool)
    key = selection.grid_key(config.depth, config.radius)
    v = np.asarray([r["v"] for r in rows], np.float32)[:, idx]
    counts = np.asarray([r["inside_counts"][key] for r in rows], np.int32)[:, idx]
    picks = np.asarray(selection.select(v, counts, config))
    out = []
    for r, pick in zip(rows, picks, strict=True):
        r = dict(r)
        paper = r.setdefault("all_stages_paper", r["all_stages"])
        statuses = paper["statuses"][-k:]  # the Stage-2 starts' refined candidates
        if pool == "stage1_2":
            statuses = r["stage1_3"]["statuses"] + statuses
        c = int(idx[pick])
        r["all_stages"] = {
            "success": bool(r["stable_all"][c]),
            "status": statuses[int(pick)],
            "any_of_k": any(r["stable_all"][i] for i in idx),
            "statuses": statuses,
            "pose": r["poses_all"][c],
        }
        r["answer_index"] = c
        out.append(r)
    return out


def settings(rows: list[dict], max_points: list[int]) -> list[tuple[str, selection.SelectConfig]]:
    out = [(pool, selection.SelectConfig()) for pool in POOLS]
    grid = sorted({tuple(float(x) for x in key.split("_")) for key in rows[0]["inside_counts"]})
    for pool in POOLS:
        for depth, radius in grid:
            for m in max_points:
                out.append((pool, selection.SelectConfig("value_clear", depth, radius, m)))
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--select-on", required=True, help="validation run's .pairs.jsonl[.gz]")
    parser.add_argument("--apply-to", default=None, help="held-out run's .pairs.jsonl[.gz]")
    parser.add_argument(
        "--proposals",
        type=int,
        default=None,
        help="K of the runs, checked against their records (default: read from them)",
    )
    parser.add_argument("--max-points", default="0,2,5,10,20,50", help="comma-separated")
    parser.add_argument("--out", required=True, help="JSON")
    parser.add_argument(
        "--write-pairs", default=None, metavar="PAIRS_JSONL",
        help="the --apply-to records with the chosen rule as the all-stages answer (.gz ok)",
    )  # fmt: skip
    parser.add_argument(
        "--summary", default=None, metavar="JSON",
        help="with --write-pairs: eval_stage3's summary of those records",
    )  # fmt: skip
    args = parser.parse_args(argv)
    val = read_records(args.select_on)
    k = proposals_of(val, args.proposals)
    table = []
    for pool, config in settings(val, [int(x) for x in args.max_points.split(",")]):
        s = successes(val, k, pool, config)
        table.append({"pool": pool, **_describe(config), "mean": s["mean"],
                      "pair_mean": s["pair_mean"]})  # fmt: skip
    best = max(table, key=lambda row: row["mean"])
    paper = next(r for r in table if r["pool"] == "stage2" and r["rule"] == "value")
    result = {
        "select_on": args.select_on,
        "select_on_pairs": len(val),
        "any_refined": {pool: any_refined(val, k, pool) for pool in POOLS},
        "paper_rule": paper,
        "chosen": best,
        "table": sorted(table, key=lambda row: -row["mean"]),
    }
    print(f"validation ({len(val)} pairs): paper's rule {paper['mean']:.1f} %, chosen "
          f"{best['mean']:.1f} % ({_label(best)}); any refined {result['any_refined']}")  # fmt: skip
    if args.apply_to:
        held = read_records(args.apply_to)
        kh = proposals_of(held, args.proposals)  # the rule is K-free: runs may differ
        chosen = _config(best)
        result["apply_to"] = args.apply_to
        result["held_out"] = {
            "paper_rule": successes(held, kh, "stage2", selection.SelectConfig()),
            "chosen": successes(held, kh, best["pool"], chosen),
            "any_refined": any_refined(held, kh, best["pool"]),
        }
        h = result["held_out"]
        print(f"held-out ({len(held)} pairs): paper's rule {h['paper_rule']['mean']:.1f} %, "
              f"chosen {h['chosen']['mean']:.1f} %, any refined {h['any_refined']:.1f} %")  # fmt: skip
        if args.write_pairs:
            rows = answer_records(held, kh, best["pool"], chosen)
            opener = gzip.open if args.write_pairs.endswith(".gz") else open
            with opener(args.write_pairs, "wt") as f:
                f.writelines(json.dumps(r) + "\n" for r in rows)
            if args.summary:
                summary = eval_pipeline.summarize_pipeline(rows, kh)
                summary.update(
                    select={**_describe(chosen), "pool": best["pool"]},
                    pool_starts=best["pool"] == "stage1_2",
                    source=args.apply_to, rule_chosen_on=args.select_on,
                )  # fmt: skip
                refine.write_json(Path(args.summary), summary)
    refine.write_json(Path(args.out), result)
    return result


def _describe(config: selection.SelectConfig) -> dict:
    return {"rule": config.rule, "depth_m": config.depth, "radius_m": config.radius,
            "max_points": config.max_points}  # fmt: skip


def _config(row: dict) -> selection.SelectConfig:
    return selection.SelectConfig(row["rule"], row["depth_m"], row["radius_m"], row["max_points"])


def _label(row: dict) -> str:
    if row["rule"] == "value":
        return f"highest V, pool {row['pool']}"
    return (f"value_clear depth {row['depth_m'] * 1e3:g} mm radius {row['radius_m'] * 1e3:g} mm "
            f"max {row['max_points']} points, pool {row['pool']}")  # fmt: skip


if __name__ == "__main__":
    _cli.run(main)
