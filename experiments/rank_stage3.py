"""A learned answer ranker for Stage 3, studied after the evaluation runs (issue 12).

    python -m experiments.rank_stage3 \\
        --fit-on results/validation_where_s9/val_s9_counts.pairs.jsonl.gz,results/validation_where_s10/val_6dlatest.pairs.jsonl.gz \\
        --apply-to results/hanging_success_stage3_s10_answer.pairs.jsonl.gz --out results/rank_stage3.json

The hand-made rule (``selection.CHOSEN``: the highest V among refined candidates with no
observed point inside the support) leaves 19 points between the pipeline's answer and "some
refined candidate hangs" on the held-out pairs. This asks whether the same observations,
weighed by a model instead of a fixed rule, pick better: a logistic regression over each of
the 2K refined candidates' features (logit V; log(1 + inside count) for every (depth, radius)
of ``selection.INSIDE_GRID``; the same of its unrefined start; whether it started from Stage 1;
its V and inside count relative to the best of its pair) predicting "stays hanging"; the answer
is the candidate of the highest predicted logit. Everything is in the records of an
``eval_stage3`` run (every candidate was simulated), so no simulation runs here.

Protocol: fitted on --fit-on (records of the validation OBJECTS, never trained on by Stages
1-3); the L2 strength is chosen by cross-validation over groups of validation objects (folds
by object name: a pair's candidates never straddle folds), scored like everything else as the
answer's success, mean over categories; the rule's success on the same folds is reported
beside. The chosen model is refitted on all --fit-on records and applied once to --apply-to.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from experiments import _cli
from experiments.rerank_stage3 import (
    category_means,
    pool_indices,
    proposals_of,
    read_records,
    successes,
)
from omnihang_jax import refine, selection

POOL = "stage1_2"  # the 2K candidates refined from Stages 1 and 2 (indices 2K..4K)


def features(rows: list[dict], k: int) -> tuple[np.ndarray, np.ndarray]:
    """[n, 2K, F] features of every refined candidate and [n, 2K] bool "stays hanging"."""
    idx = pool_indices(k, POOL)
    start = idx - 2 * k  # the unrefined proposal each refined candidate started from
    keys = [selection.grid_key(d, r) for d, r in selection.INSIDE_GRID]
    v = np.clip(np.asarray([r["v"] for r in rows], np.float64), 1e-6, 1 - 1e-6)
    logit = np.log(v) - np.log1p(-v)
    counts = np.log1p(np.asarray([[r["inside_counts"][g] for g in keys] for r in rows], float))
    cand, origin = counts[:, :, idx], counts[:, :, start]  # [n, G, 2K]
    lv = logit[:, idx]
    main = counts[:, keys.index(selection.grid_key(0.0005, 0.005))][:, idx]
    from_stage1 = np.broadcast_to((np.arange(2 * k) < k).astype(float), lv.shape)
    f = np.concatenate([
        lv[..., None], logit[:, start][..., None],
        np.moveaxis(cand, 1, 2), np.moveaxis(origin, 1, 2),
        from_stage1[..., None],
        (lv - lv.max(1, keepdims=True))[..., None],
        (main - main.min(1, keepdims=True))[..., None],
    ], axis=-1)  # fmt: skip
    y = np.asarray([r["stable_all"] for r in rows], bool)[:, idx]
    return f, y


def fit(x: np.ndarray, y: np.ndarray, l2: float, loss: str = "pointwise"):
    """A linear score on standardised features [n, C, F] -> (weights, mean, std).
    "pointwise": logistic regression of every candidate's outcome; "listwise": the softmax
    over a pair's candidates puts its mass on those that hang (-log of that mass, pairs
    where one hangs)."""
    flat = x.reshape(-1, x.shape[-1])
    mu, sd = flat.mean(0), flat.std(0) + 1e-6
    z = np.concatenate([(x - mu) / sd, np.ones(x.shape[:-1] + (1,))], -1)  # [n, C, F+1]
    t = y.astype(float)
    some = y.any(1)

    def objective(w):
        s = z @ w  # [n, C]
        if loss == "pointwise":
            value = np.mean(np.logaddexp(0, s) - t * s)
            ds = (1 / (1 + np.exp(-s)) - t) / t.size
        else:
            sp, tp = s[some], t[some]
            m = sp.max(1, keepdims=True)
            e = np.exp(sp - m)
            all_, good = e.sum(1), (e * tp).sum(1)
            value = np.mean(np.log(all_) - np.log(good))
            ds = np.zeros_like(s)
            ds[some] = (e / all_[:, None] - e * tp / good[:, None]) / len(sp)
        grad = np.einsum("nc,ncf->f", ds, z)
        reg = 0.5 * l2 * np.sum(w[:-1] ** 2)
        return value + reg, grad + l2 * np.concatenate([w[:-1], [0.0]])

    loss_fn = objective

    w = minimize(loss_fn, np.zeros(z.shape[-1]), jac=True, method="L-BFGS-B").x
    return w, mu, sd


def scores(model, x: np.ndarray) -> np.ndarray:
    w, mu, sd = model
    return ((x - mu) / sd) @ w[:-1] + w[-1]


def success_of(rows: list[dict], picks: np.ndarray, y: np.ndarray) -> dict:
    return category_means(rows, [yy[p] for p, yy in zip(picks, y, strict=True)])


def folds_by_object(rows: list[dict], n: int, seed: int = 0) -> np.ndarray:
    objects = sorted({r["object"] for r in rows})
    order = np.random.default_rng(seed).permutation(len(objects))
    fold_of = {objects[j]: i % n for i, j in enumerate(order)}
    return np.asarray([fold_of[r["object"]] for r in rows])


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--fit-on", required=True, help="comma-separated validation records")
    parser.add_argument("--apply-to", default=None, help="held-out records (.pairs.jsonl[.gz])")
    parser.add_argument(
        "--proposals",
        type=int,
        default=None,
        help="K of the runs, checked against their records (default: read from them)",
    )
    parser.add_argument("--folds", type=int, default=5, help="cross-validation folds (objects)")
    parser.add_argument("--l2", default="0.001,0.01,0.1,1,10", help="comma-separated")
    parser.add_argument("--losses", default="pointwise,listwise", help="comma-separated")
    parser.add_argument("--out", required=True, help="JSON")
    args = parser.parse_args(argv)
    val = [r for p in args.fit_on.split(",") for r in read_records(p)]
    k = proposals_of(val, args.proposals)
    x, y = features(val, k)
    folds = folds_by_object(val, args.folds)
    rule = successes(val, k, POOL, selection.CHOSEN)["mean"]
    table = []
    for loss in args.losses.split(","):
        for l2 in (float(s) for s in args.l2.split(",")):
            picks = np.zeros(len(val), int)
            for f in range(args.folds):
                tr, te = folds != f, folds == f
                model = fit(x[tr], y[tr], l2, loss)
                picks[te] = np.argmax(scores(model, x[te]), axis=1)
            table.append({"loss": loss, "l2": l2, "cv_mean": success_of(val, picks, y)["mean"]})
            print(f"{loss} l2 {l2:g}: cross-validated {table[-1]['cv_mean']:.1f} % "
                  f"(rule {rule:.1f} %)")  # fmt: skip
    best = max(table, key=lambda row: row["cv_mean"])
    model = fit(x, y, best["l2"], best["loss"])
    result = {
        "fit_on": args.fit_on.split(","),
        "fit_pairs": len(val),
        "features": "logit V, logit V of the start, log1p inside counts (12 settings) of the "
        "candidate and of its start, from Stage 1, logit V - best of pair, log1p count "
        "(0.5 mm, 5 mm) - least of pair",
        "rule_on_fit_set": rule,
        "cross_validation": {"folds": args.folds, "grouped_by": "object", "table": table},
        "chosen": best,
        "weights": model[0].tolist(),
    }
    if args.apply_to:
        held = read_records(args.apply_to)
        kh = proposals_of(held, args.proposals)
        xh, yh = features(held, kh)
        picks = np.argmax(scores(model, xh), axis=1)
        result["apply_to"] = args.apply_to
        result["held_out"] = {
            "learned": success_of(held, picks, yh),
            "rule": successes(held, kh, POOL, selection.CHOSEN),
            "any_refined": success_of(held, np.argmax(yh, axis=1), yh)["mean"],
        }
        h = result["held_out"]
        print(f"held-out ({len(held)} pairs): learned {h['learned']['mean']:.1f} %, rule "
              f"{h['rule']['mean']:.1f} %, any refined {h['any_refined']:.1f} %")  # fmt: skip
    refine.write_json(Path(args.out), result)
    return result


if __name__ == "__main__":
    _cli.run(main)
