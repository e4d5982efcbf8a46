"""The Stage-3 answer rule with the collision estimator of issue 13: drop what the NCE calls colliding.

    python -m experiments.rerank_nce \\
        --select-on results/validation_where_s27/val_k10_v0.pairs.jsonl.gz \\
                    results/validation_where_s27/val_k10_v1of2.pairs.jsonl.gz \\
        --apply-to results/hanging_success_stage3_s27_k10_view0.pairs.jsonl.gz \\
                   results/hanging_success_stage3_s27_k10_view1of2.pairs.jsonl.gz \\
        --weights weights/collision_s18_contact --out results/rerank_nce_s28.json

Issue 12, twenty-eighth session. Of the default pipeline's held-out failures, 149 of 348 pick a
candidate that starts inside the support while another refined candidate hangs (twenty-seventh
session); the penetrations are millimetres deep and the observed clouds show no object point
inside the support (the rule's inside test). Issue 13's contact NCE
(``collision.NCEConfig.local_points``) was trained for exactly that scale: near-contact poses,
a stable pose moved 0.5-30 mm, labelled by the meshes at 1 mm. Never trained on a held-out
pair. This study asks whether its probability tells the pipeline's penetrating candidates
apart, from the records of runs that simulated every candidate (no new simulation).

Several runs (``--select-on`` and ``--apply-to`` each take one run per view of the default
pipeline, ``stage3.ANSWER_PIPELINE``, as ``experiments.union_views`` does) are pooled: each
candidate keeps its own run's answer key (``rerank_stage3.rule_keys``: the rankers' mean log P,
observed inside points first), and the NCE's probability P of every pooled candidate is
computed with the pair's observed clouds (the planner's fixed subsets). Rules:
- ``lex t``: candidates with P > t rank below every other clear candidate (``key - 100``;
  the inside test's 1e4 still ranks first);
- ``soft lambda``: ``key + lambda * log(1 - P)``.
Chosen on --select-on (validation objects) by the mean over categories; applied once to
--apply-to beside the committed rule and the NCE's own threshold (chosen on its validation
pairs' stable poses, fixed before this study). The NCE trained on training-split pairs, which
include the validation objects' pairs (pair_index % 20 != 0): its validation figures are
optimistic, the held-out ones are not. Probabilities are cached (``--cache``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import numpy as np
from tqdm.auto import tqdm

from experiments import _cli
from experiments.eval_paths import SUBSET_SEED_OBJECT, SUBSET_SEED_SUPPORT
from experiments.rerank_completed import load_clouds
from experiments.rerank_stage3 import (
    category_means,
    pool_indices,
    proposals_of,
    read_records,
    rule_keys,
)
from omnihang_jax import collision

LEX = (0.3, 0.4, 0.5, 0.56, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99)
SOFT = (0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 4.0)
_NCE_WEIGHT = 100.0  # log P lies in [-50, 0]: below every clear candidate, above the inside test


def nce_scores(rows, k, data: Path, weights: str, cache: Path | None, progress=True) -> np.ndarray:
    """[N, 2K] the NCE's collision probability of each record's pooled refined candidates."""
    idx = pool_indices(k, "stage1_2")
    have: dict[int, np.ndarray] = {}
    if cache is not None and cache.exists():
        with np.load(cache) as z:
            have = dict(zip(z["pair_index"].tolist(), z["p"], strict=True))
    todo = [r for r in rows if int(r["pair_index"]) not in have]
    if todo:
        cfg, params, _ = collision.load_estimator(Path(weights, "nce"))
        if cfg.input_clouds != "observed":
            raise ValueError(
                f"{weights}: an NCE on {cfg.input_clouds} clouds; this study gives observed ones"
            )
        prob = jax.jit(collision.nce_probability(cfg))
        for r in tqdm(todo, desc="NCE", disable=not progress):
            c = load_clouds(data, r)
            oc = collision.subsample_cloud(c["object_points"], cfg.object_input, SUBSET_SEED_OBJECT)
            sc = collision.subsample_cloud(
                c["support_points"], cfg.support_input, SUBSET_SEED_SUPPORT
            )
            poses = np.asarray(r["poses_all"], np.float32)[idx]
            have[int(r["pair_index"])] = np.asarray(prob(params, oc, sc, poses))
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            keys = sorted(have)
            np.savez(cache, pair_index=np.asarray(keys), p=np.stack([have[i] for i in keys]))
    return np.stack([have[int(r["pair_index"])] for r in rows])


def pooled(paths: list[str], data: Path, weights: str, cache_dir: Path | None, progress=True):
    """(rows of the first run, [N, R*2K] keys, stable, NCE P, statuses) over the runs."""
    runs = [read_records(p) for p in paths]
    order = [int(r["pair_index"]) for r in runs[0]]
    keys, stable, prob, status = [], [], [], []
    for path, rows in zip(paths, runs, strict=True):
        if [int(r["pair_index"]) for r in rows] != order:
            raise ValueError(f"{path}: other pairs (or another order) than {paths[0]}")
        k = proposals_of(rows)
        key, st = rule_keys(rows, k)
        name = Path(path).name.split(".")[0]
        cache = cache_dir / f"{name}__{Path(weights).name}.npz" if cache_dir else None
        keys.append(key)
        stable.append(st)
        prob.append(nce_scores(rows, k, data, weights, cache, progress))
        status.append(np.asarray([r["all_stages"]["statuses"] for r in rows]))
    cat = lambda xs: np.concatenate(xs, axis=1)  # noqa: E731
    return runs[0], cat(keys), cat(stable), cat(prob), cat(status)


def auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """P(a positive scores above a negative), ties half (the Mann-Whitney U over n+ n-)."""
    from scipy.stats import rankdata

    if not len(pos) or not len(neg):
        return float("nan")
    ranks = rankdata(np.concatenate([pos, neg]))  # average ranks of ties, from 1
    return float((ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def score_rules(rows, key, stable, prob, nce_threshold: float) -> list[dict]:
    table = []
    n = np.arange(len(rows))

    def add(label, k, **extra):
        res = category_means(rows, stable[n, k.argmax(1)])
        table.append({"rule": label, **extra, **res})

    add("committed", key)
    for t in sorted(set(LEX) | {round(nce_threshold, 4)}):
        add(f"lex {t:g}", key - _NCE_WEIGHT * (prob > t), threshold=t)
    for lam in SOFT:
        add(f"soft {lam:g}", key + lam * np.log(np.clip(1.0 - prob, 1e-6, 1.0)), penalty=lam)
    return table


def separation(key, stable, prob, status) -> dict:
    """How the NCE's P separates the pooled candidates: AUC penetrating vs stable (clear ones
    only: the inside test already ranks the others last), and the shares above thresholds."""
    clear = key > -1e3  # rule_keys: log P >= -28, minus 1e4 per inside point over the limit
    pen = prob[(status == "penetrating") & clear]
    st = prob[stable & clear]
    out = dict(
        clear_penetrating=len(pen), clear_stable=len(st), auc_penetrating_vs_stable=auc(pen, st)
    )
    for t in (0.3, 0.5, 0.56, 0.7, 0.9):
        out[f"above_{t:g}"] = dict(
            penetrating=float(np.mean(pen > t)), stable=float(np.mean(st > t))
        )
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--select-on", nargs="+", required=True, help="validation runs, one per view")
    ap.add_argument("--apply-to", nargs="+", required=True, help="held-out runs, one per view")
    ap.add_argument(
        "--weights", default="weights/collision_s18_contact", help="NCE folder (FOLDER/nce)"
    )
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--cache", default="out/rerank_nce", help="per-run probability cache folder")
    ap.add_argument("--out", default=None, help="JSON")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    cfg, _, _ = collision.load_estimator(Path(args.weights, "nce"))
    cache = Path(args.cache) if args.cache else None
    res: dict = {"weights": args.weights, "nce_threshold": cfg.threshold}
    tables = {}
    for name, paths in (("select_on", args.select_on), ("apply_to", args.apply_to)):
        rows, key, stable, prob, status = pooled(paths, Path(args.data), args.weights, cache,
                                                 not args.no_progress)  # fmt: skip
        tables[name] = score_rules(rows, key, stable, prob, cfg.threshold)
        res[name] = dict(records=paths, pairs=len(rows),
                         separation=separation(key, stable, prob, status),
                         some_candidate_hangs=category_means(rows, stable.any(1))["mean"])  # fmt: skip
    best = max(tables["select_on"], key=lambda t: t["mean"])
    applied = {t["rule"]: t for t in tables["apply_to"]}
    res["chosen"] = best["rule"]
    res["table"] = [
        dict(
            rule=t["rule"],
            validation=round(t["mean"], 2),
            held_out=round(applied[t["rule"]]["mean"], 2),
        )
        for t in tables["select_on"]
    ]
    res["held_out_committed"] = applied["committed"]
    res["held_out_chosen"] = applied[best["rule"]]
    for row in res["table"]:
        print(
            f"{row['rule']:>12}: validation {row['validation']:6.2f}  held-out {row['held_out']:6.2f}"
        )
    print(f"chosen on validation: {best['rule']} -> held-out {applied[best['rule']]['mean']:.2f} "
          f"(committed {applied['committed']['mean']:.2f})")  # fmt: skip
    for name in ("select_on", "apply_to"):
        print(name, json.dumps(res[name]["separation"]))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    return res


if __name__ == "__main__":
    _cli.run(main)
