"""The ranking networks on several subsets of the clouds (issue 12, twenty-sixth session).

    python -m experiments.rank_subsets --select-on VAL.pairs.jsonl.gz --apply-to HELD.pairs.jsonl.gz \\
        --data datasets/paper --subsets 1,2,4,8 --out results/rank_subsets_s26.json

Each ranking network of the pipeline (``stage3.RANK_VALUES``) sees 512 + 512 evenly spaced
points of the 4,096-point observed clouds (``stage3.subsample_clouds``). Which 512 is an
accident of the index: rolled by a fraction of the stride, the same network sees another,
equally valid subset (``stage3.subset_clouds``), and on the 345 validation-object pairs its
answer moves by several points from one subset to the next. Averaging each network's log P
over T subsets (test-time augmentation; ``PipelineConfig.rank_subsets``) removes that noise.

This study scores the refined candidates an ``eval_stage3`` run recorded (records or
``experiments.train_ranker slim`` tables: poses, simulated outcome, observed inside counts),
no new simulation: every network on each of the largest T's subsets, then the answer rule
(``selection.CHOSEN`` over the mean log P) for every T of --subsets and for every single subset.
T is chosen on --select-on (validation objects) by the mean over categories, then applied
once to --apply-to (held-out). The clouds are read from DATA/derived/<split> (the full
derive: the run's own renders; a clouds-only derive on another machine differs slightly).
``--scores`` keeps every score ([networks, subsets, pairs, candidates] log P) for later study.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from experiments import _cli
from experiments.train_ranker import load_table, make_scorer, rule_success
from omnihang_jax import refine, stage3
from omnihang_jax.stage3 import PairClouds


def load_clouds(folder: Path, files) -> list[tuple[np.ndarray, ...]]:
    """Full observed clouds (points, normals of both bodies) of the pair files."""
    paths = [folder / str(f) for f in files]
    missing = [p for p in paths if not p.exists()]
    if missing:
        raise FileNotFoundError(
            f"{len(missing)} pair files missing under {folder} (e.g. {missing[0].name}): derive "
            f"them (python -m experiments.derive_dataset --split <split> --pairs-from RUN)"
        )
    out = []
    for p in paths:
        with np.load(p) as z:
            lacking = [f for f in PairClouds._fields if f not in z.files]
            if lacking:
                raise ValueError(f"{p}: no {lacking} (not a derived pair file)")
            arrays = tuple(np.asarray(z[f], np.float32) for f in PairClouds._fields)
        if not all(np.all(np.isfinite(a)) for a in arrays):
            raise ValueError(f"{p}: non-finite cloud points or normals")
        out.append(arrays)
    return out


def score_subsets(nets, clouds, poses: np.ndarray, subsets: int, batch: int, progress=True):
    """[R, subsets, N, P] log P(hang) of every candidate (poses [N, P, 7]) under each network
    (config, params) on each subset (``stage3.subset_clouds``)."""
    n = len(clouds)
    out = np.zeros((len(nets), subsets, n, poses.shape[1]), np.float32)
    scorers = {}
    bar = tqdm(total=len(nets) * subsets * ((n + batch - 1) // batch), desc="scores",
               disable=not progress)  # fmt: skip
    for r, (config, params) in enumerate(nets):
        if config not in scorers:
            scorers[config] = make_scorer(config)
        scorer = scorers[config]
        for j in range(subsets):
            for i in range(0, n, batch):
                sl = list(range(i, min(i + batch, n)))
                m = len(sl)
                sl += [sl[0]] * (batch - m)  # pad: one compilation
                full = PairClouds(*(jnp.asarray(np.stack([clouds[q][f] for q in sl]))
                                    for f in range(4)))  # fmt: skip
                sub = stage3.subset_clouds(full, config, j, subsets)
                out[r, j, i : i + m] = np.asarray(scorer(params, sub, jnp.asarray(poses[sl])))[:m]
                bar.update()
    bar.close()
    return out


def subset_table(table: dict, scores: np.ndarray, ts: list[int]) -> dict:
    """The rule's success for each T of ``ts`` (subsets j * tmax / T of the ``tmax`` scored),
    each network alone at each T, and every single subset."""
    tmax = scores.shape[1]
    out = {"by_t": {}, "single_subset": []}
    for t in ts:
        pick = scores[:, [j * tmax // t for j in range(t)]]  # [R, t, N, P]
        ens = rule_success(table, pick.mean((0, 1)))
        out["by_t"][str(t)] = {
            "mean": ens["mean"],
            "pair_mean": ens["pair_mean"],
            "per_category": ens["per_category"],
            "each_network": [
                rule_success(table, pick[r].mean(0))["mean"] for r in range(len(scores))
            ],  # fmt: skip
        }
    for j in range(tmax):
        out["single_subset"].append(rule_success(table, scores[:, j].mean(0))["mean"])
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--select-on", required=True, help="records or slim table, validation objects")
    ap.add_argument("--apply-to", required=True, help="records or slim table, held-out pairs")
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--select-split", default="train", help="DATA/derived/<this> for --select-on")
    ap.add_argument("--apply-split", default="test", help="DATA/derived/<this> for --apply-to")
    ap.add_argument("--rank-value", action="append", default=None,
                    help="ranking networks (default stage3.RANK_VALUES)")  # fmt: skip
    ap.add_argument("--subsets", default="1,2,4,8", help="the T to compare; the largest is scored")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--scores", default=None, help="NPZ of every score (both runs)")
    ap.add_argument("--out", default=None, help="JSON")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    ts = sorted({int(t) for t in args.subsets.split(",") if t})
    tmax = ts[-1]
    if ts[0] < 1 or any(tmax % t for t in ts):
        raise ValueError(f"--subsets {args.subsets}: each T must be >= 1 and divide the largest")
    dirs = list(stage3.RANK_VALUES) if args.rank_value is None else args.rank_value
    nets = [refine.load_value(d) for d in dirs]
    derived = Path(args.data) / "derived"  # as train_ranker.load_bank
    result = {"rank_values": dirs, "subsets": ts, "device": str(jax.devices()[0]),
              "jax": jax.__version__}  # fmt: skip
    saved = {}
    for name, path, split in (("select_on", args.select_on, args.select_split),
                              ("apply_to", args.apply_to, args.apply_split)):  # fmt: skip
        t0 = time.time()
        table = load_table(path)
        clouds = load_clouds(derived / split, table["files"])
        scores = score_subsets(nets, clouds, table["poses"], tmax, args.batch,
                               not args.no_progress)  # fmt: skip
        result[name] = {"records": path, "pairs": len(table["files"]),
                        "seconds": round(time.time() - t0, 1),
                        **subset_table(table, scores, ts)}  # fmt: skip
        saved[f"{name}_scores"] = scores
        saved[f"{name}_pair_index"] = table["pair_index"]
    by_val = result["select_on"]["by_t"]
    best = max(ts, key=lambda t: (round(by_val[str(t)]["mean"], 6), -t))
    result["chosen_subsets"] = best
    result["chosen"] = {"validation": by_val[str(best)]["mean"],
                        "held_out": result["apply_to"]["by_t"][str(best)]["mean"],
                        "held_out_t1": result["apply_to"]["by_t"]["1"]["mean"]
                        if "1" in result["apply_to"]["by_t"] else None}  # fmt: skip
    for t in ts:
        print(f"T = {t:2d}: validation {by_val[str(t)]['mean']:.2f}, held-out "
              f"{result['apply_to']['by_t'][str(t)]['mean']:.2f}")  # fmt: skip
    for name in ("select_on", "apply_to"):
        single = result[name]["single_subset"]
        print(f"{name}: single subsets {min(single):.2f}-{max(single):.2f}")
    print(f"chosen on validation: T = {best}")
    if args.scores:
        Path(args.scores).parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(args.scores, **saved)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    _cli.run(main)
