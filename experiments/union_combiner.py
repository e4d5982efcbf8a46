"""A learned answer rule over the views' pooled candidates (issue 12): a linear listwise scorer
of what the records already hold, fitted on validation objects, applied once to held-out pairs.

    python -m experiments.union_combiner \\
        --select-on V0_KEY0.pairs.jsonl.gz,V1_KEY0.pairs.jsonl.gz ... \\
        --apply-to H0_KEY0.pairs.jsonl.gz,H1_KEY0.pairs.jsonl.gz ... --out results/union_combiner.json

Arguments as for ``experiments.union_rules`` (one per CEM key: the comma-joined records of the
pipeline's views). The default answer (``selection.CHOSEN``) is lexicographic: the rankers' mean
log P among the candidates the observed clouds call clear. Here each candidate of a key's union
pool is described by the numbers its record holds -- the rankers' mean and individual log P, CEM's
log V, log(1 + inside count) for every recorded (depth, radius), "clear" under the default's
setting, the Stage-1 start flag, the score's gap to the pool's best, and the log of how many other
candidates of the pool lie within 5 mm and 0.1 rad (agreement across views and starts) -- and a
linear scorer w . f is fitted by the listwise loss -log sum_{c stable} softmax(w . f)_c with an
L2 penalty (pairs without a hanging candidate carry no signal and are left out of the fit).

Protocol: the penalty is chosen by 5-fold cross-validation over the validation OBJECTS (each
fold's objects never fitted on; all keys' pairs of an object in one fold), against the default
rule on the same pairs; the scorer refitted on every validation pair is applied once to the
held-out keys beside the default. Mean over categories as everywhere.
"""

from __future__ import annotations

import argparse
import zlib

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from experiments import _cli
from experiments.rerank_stage3 import category_means, pool_indices, proposals_of, read_records
from omnihang_jax import refine, selection

AGREE_T = 0.005  # m: two candidates "agree" within 5 mm ...
AGREE_R = 0.1  # rad: ... and 0.1 rad
FOLDS = 5


def _quat_angle(q: np.ndarray) -> np.ndarray:
    """[C, 4] wxyz -> [C, C] rotation angle between every two."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    dot = np.clip(np.abs(q @ q.T), 0.0, 1.0)
    return 2.0 * np.arccos(dot)


def features(
    runs: list[list[dict]],
) -> tuple[list[dict], np.ndarray, np.ndarray, list[str], np.ndarray]:
    """One key's views -> (rows, [N, C, F] features, [N, C] stable, feature names, [N, C] the
    default rule's key: ``rerank_stage3.rule_keys``, as ``union_views`` answers)."""
    order = [int(r["pair_index"]) for r in runs[0]]
    for rows in runs[1:]:
        if [int(r["pair_index"]) for r in rows] != order:
            raise ValueError("the views' runs hold different pairs (or another order)")
    grid = sorted(runs[0][0]["inside_counts"])
    default = selection.grid_key(selection.CHOSEN.depth, selection.CHOSEN.radius)
    feats, stable, dkeys = [], [], []
    for i in range(len(order)):
        f_pair, s_pair, poses, d_pair = [], [], [], []
        for rows in runs:
            k = proposals_of(rows)
            idx = pool_indices(k, "stage1_2")
            r = rows[i]
            ranks = np.log(np.clip(np.asarray(r.get("v_rank") or [r["v"]], np.float64)[:, idx],
                                   1e-12, 1.0))  # fmt: skip
            v = np.log(np.clip(np.asarray(r["v"], np.float64)[idx], 1e-12, 1.0))
            counts = np.stack([np.asarray(r["inside_counts"][g], np.float64)[idx] for g in grid])
            inside = np.asarray(r["inside_counts"][default], np.int64)[idx]
            clear = inside <= selection.CHOSEN.max_points
            d_pair.append(np.asarray(selection.select_key(ranks.mean(0), inside, selection.CHOSEN)))
            stage1 = (np.arange(2 * k) < k).astype(np.float64)
            f_pair.append(np.column_stack([ranks.mean(0), ranks.T, v, np.log1p(counts).T, clear,
                                           stage1]))  # fmt: skip
            s_pair.append(np.asarray(r["stable_all"], bool)[idx])
            poses.append(np.asarray(r["poses_all"], np.float64)[idx])
        f = np.concatenate(f_pair)
        p = np.concatenate(poses)
        near = (np.linalg.norm(p[:, None, :3] - p[None, :, :3], axis=-1) < AGREE_T) & (
            _quat_angle(p[:, 3:]) < AGREE_R
        )
        agree = np.log1p(near.sum(1) - 1.0)
        gap = f[:, 0] - f[:, 0].max()
        feats.append(np.column_stack([f, gap, agree]))
        stable.append(np.concatenate(s_pair))
        dkeys.append(np.concatenate(d_pair))
    n_rank = len(runs[0][0].get("v_rank") or [0])
    names = (["rank_mean"] + [f"rank_{j}" for j in range(n_rank)] + ["log_v"]
             + [f"inside_{g}" for g in grid] + ["clear", "stage1_start", "gap", "agree"])  # fmt: skip
    return runs[0], np.stack(feats), np.stack(stable), names, np.stack(dkeys)


def fit(f: np.ndarray, stable: np.ndarray, l2: float, mask: np.ndarray | None = None) -> np.ndarray:
    """Listwise linear scorer on standardised features -> weights [F]. ``mask`` [N, C]: the
    candidates the scorer ranks (the others are out of each pair's list)."""
    mask = np.ones(stable.shape, bool) if mask is None else mask
    keep = (stable & mask).any(1)
    x, y, m = jnp.asarray(f[keep]), jnp.asarray(stable[keep] & mask[keep]), jnp.asarray(mask[keep])

    def loss(w):
        logits = jnp.where(m, x @ w, -1e9)
        lse = jax.nn.logsumexp(logits, axis=1)
        pos = jax.nn.logsumexp(jnp.where(y, logits, -jnp.inf), axis=1)
        return jnp.mean(lse - pos) + l2 * jnp.sum(w**2)

    vg = jax.jit(jax.value_and_grad(loss))

    def fun(w):
        value, grad = vg(jnp.asarray(w, jnp.float32))
        return float(value), np.asarray(grad, np.float64)

    w0 = np.zeros(f.shape[-1])
    w0[0] = 1.0  # start from the rankers' mean
    return scipy.optimize.minimize(fun, w0, jac=True, method="L-BFGS-B").x


class Scaler:
    def __init__(self, f: np.ndarray):
        flat = f.reshape(-1, f.shape[-1])
        self.mean, self.std = flat.mean(0), flat.std(0) + 1e-6

    def __call__(self, f: np.ndarray) -> np.ndarray:
        return (f - self.mean) / self.std


def success(rows, stable, keys) -> dict:
    return category_means(rows, stable[np.arange(len(rows)), np.argmax(keys, axis=1)])


def object_folds(rows: list[dict], folds: int = FOLDS) -> np.ndarray:
    """[N] fold of each pair by its object (a stable hash: the same split on every machine)."""
    return np.asarray([zlib.crc32(r["object"].encode()) % folds for r in rows])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--select-on", nargs="+", required=True, metavar="RUNS")
    ap.add_argument("--apply-to", nargs="*", default=[], metavar="RUNS")
    ap.add_argument("--l2", default="0.0001,0.001,0.01,0.1,1")
    ap.add_argument(
        "--within-clear", action="store_true",
        help="keep the default's order of clear before inside candidates and learn the order "
        "within each group (the scorer fitted on the clear candidates of each pair)",
    )  # fmt: skip
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    def load(keys):
        return [features([read_records(p) for p in key.split(",")]) for key in keys]

    val = load(args.select_on)
    clear_at = -4  # the "clear" feature

    def keys_of(scaled, raw, w):
        k = scaled @ w
        return k + 1e4 * (raw[..., clear_at] > 0.5) if args.within_clear else k

    def mask_of(raw):
        return raw[..., clear_at] > 0.5 if args.within_clear else None

    names = val[0][3]
    folds = [object_folds(rows) for rows, *_ in val]
    f_all = np.concatenate([f for _, f, _, _, _ in val])
    s_all = np.concatenate([s for _, _, s, _, _ in val])
    fold_all = np.concatenate(folds)
    cv = {}
    for l2 in (float(x) for x in args.l2.split(",")):
        keys = [np.zeros(s.shape) for _, _, s, _, _ in val]
        for k in range(FOLDS):
            train = fold_all != k
            scale = Scaler(f_all[train])
            w = fit(scale(f_all[train]), s_all[train], l2, mask_of(f_all[train]))
            for j, (_, f, _, _, _) in enumerate(val):
                test = folds[j] == k
                keys[j][test] = keys_of(scale(f[test]), f[test], w)
        per_key = [
            success(rows, s, kk)["mean"] for (rows, _, s, _, _), kk in zip(val, keys, strict=True)
        ]
        cv[l2] = {"per_key": per_key, "mean": float(np.mean(per_key))}
        print(
            f"l2 {l2:g}: cross-validated {cv[l2]['mean']:.2f} ({', '.join(f'{m:.2f}' for m in per_key)})"
        )
    base = [success(rows, s, d)["mean"] for rows, _, s, _, d in val]
    print(f"default rule on the same pairs: {np.mean(base):.2f}")
    best = max(cv, key=lambda x: cv[x]["mean"])
    scale = Scaler(f_all)
    w = fit(scale(f_all), s_all, best, mask_of(f_all))
    res = {
        "select_on": args.select_on, "apply_to": args.apply_to, "features": names,
        "folds": FOLDS, "within_clear": args.within_clear, "cross_validated": {f"{k:g}": v for k, v in cv.items()},
        "default_validation": {"per_key": base, "mean": float(np.mean(base))},
        "chosen_l2": best, "weights": dict(zip(names, map(float, w), strict=True)),
    }  # fmt: skip
    if args.apply_to:
        held = load(args.apply_to)
        mine = [success(rows, s, keys_of(scale(f), f, w)) for rows, f, s, _, _ in held]
        dflt = [success(rows, s, d) for rows, _, s, _, d in held]
        res["held_out"] = {
            name: {"per_key": [r["mean"] for r in rs], "mean": float(np.mean([r["mean"] for r in rs])),
                   "per_category": {c: float(np.mean([r["per_category"][c] for r in rs]))
                                    for c in rs[0]["per_category"]}}
            for name, rs in (("learned", mine), ("default", dflt))
        }  # fmt: skip
        print(f"held-out: learned {res['held_out']['learned']['mean']:.2f}, default "
              f"{res['held_out']['default']['mean']:.2f}")  # fmt: skip
    if args.out:
        refine.write_json(args.out, res)
    return res


if __name__ == "__main__":
    _cli.run(main)
