"""The symmetric observed-cloud test in the Stage-3 answer rule, studied after the runs.

    # 1. the support-side counts of every refined candidate of a run (needs its derived pairs)
    python -m experiments.symmetric_stage3 count --records RUN.pairs.jsonl.gz \\
        --data datasets/paper --split test --out RUN_sym.pairs.jsonl.gz
    # 2. the rule with both tests, chosen on validation objects, applied once to held-out
    python -m experiments.symmetric_stage3 choose --select-on VAL_sym.pairs.jsonl.gz \\
        --apply-to HELDOUT_sym.pairs.jsonl.gz --out results/symmetric_stage3.json

``selection.CHOSEN`` calls a candidate clear when no observed OBJECT point lies inside the
observed support. Of the held-out answers that still fail, most are clear by that test and yet
start penetrating: the overlap is where the clouds are thin (a hook's tip or a rod passing
through a handle seen edge-on). The symmetric test (``selection.support_inside_counts_grid``)
counts observed SUPPORT points inside the posed observed object. Here a candidate is clear
when the object-side count (at CHOSEN's 0.5 mm / 5 mm) is 0 and the support-side count at
(depth, radius) is at most ``max_points``; the answer is the highest V among clear ones, else
the fewest points inside (both sides), over the 2K refined candidates, as CHOSEN. The
(depth, radius, max_points) are chosen on validation-object records by mean success over
categories; "off" (CHOSEN alone) is one of the settings.
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from experiments import _cli
from experiments.rerank_stage3 import category_means, pool_indices, proposals_of, read_records
from omnihang_jax import dataset_bridge, refine, selection

POOL = "stage1_2"
GRID = tuple((d, r) for d in (0.001, 0.002, 0.003, 0.005) for r in (0.002, 0.003, 0.005))
MAX_POINTS = (0, 1, 2, 5, 10)


def count(args) -> None:
    rows = read_records(args.records)
    _, derived = dataset_bridge.resolve_dataset_dir(args.data)
    k = proposals_of(rows, args.proposals)
    idx = pool_indices(k, POOL)
    fn = jax.jit(lambda o, n, s, p: selection.support_inside_counts_grid(o, n, s, p, GRID))
    out = []
    for r in tqdm(rows, desc="support-side counts", disable=args.no_progress):
        path = os.path.join(derived, args.split, r["file"])
        if not os.path.exists(path):
            raise FileNotFoundError(f"{path}: derive the run's pairs first (derive_dataset)")
        sample, _ = dataset_bridge.load_pair_file(path)
        poses = jnp.asarray(np.asarray(r["poses_all"], np.float32)[idx])
        c = np.asarray(fn(jnp.asarray(sample.object_points), jnp.asarray(sample.object_normals),
                          jnp.asarray(sample.support_points), poses))  # fmt: skip
        out.append(dict(r, support_inside_counts={
            selection.grid_key(d, rr): c[g].tolist() for g, (d, rr) in enumerate(GRID)
        }))  # fmt: skip
    opener = gzip.open if args.out.endswith(".gz") else open
    with opener(args.out, "wt") as f:
        f.writelines(json.dumps(r) + "\n" for r in out)
    print(f"{len(out)} records with support-side counts -> {args.out}")


def picks_of(rows, k, setting) -> np.ndarray:
    """The answer (index into the 2K refined candidates) of every pair under a setting
    (None: CHOSEN alone)."""
    idx = pool_indices(k, POOL)
    ck = selection.grid_key(selection.CHOSEN.depth, selection.CHOSEN.radius)
    v = np.asarray([r["v"] for r in rows], np.float64)[:, idx]
    obj = np.asarray([r["inside_counts"][ck] for r in rows], np.float64)[:, idx]
    excess = obj
    if setting is not None:
        d, rr, m = setting
        sup = np.asarray([r["support_inside_counts"][selection.grid_key(d, rr)] for r in rows])
        excess = obj + np.maximum(sup - m, 0)
    return np.argmax(np.log(np.clip(v, 1e-9, 1)) - 1e4 * excess, axis=1)


def success(rows, k, picks) -> dict:
    idx = pool_indices(k, POOL)
    return category_means(rows, [r["stable_all"][idx[p]] for r, p in zip(rows, picks, strict=True)])


def choose(args) -> dict:
    val = read_records(args.select_on)
    k = proposals_of(val, args.proposals)
    settings = [None] + [(d, r, m) for d, r in GRID for m in MAX_POINTS]
    table = [{"setting": s, "mean": success(val, k, picks_of(val, k, s))["mean"]} for s in settings]
    best = max(table, key=lambda row: row["mean"])
    off = table[0]
    print(f"validation ({len(val)} pairs): CHOSEN alone {off['mean']:.1f} %, best {best['mean']:.1f} "
          f"% at {best['setting']}")  # fmt: skip
    result = {"select_on": args.select_on, "select_on_pairs": len(val), "chosen_alone": off,
              "chosen": best, "table": sorted(table, key=lambda row: -row["mean"])}  # fmt: skip
    if args.apply_to:
        held = read_records(args.apply_to)
        kh = proposals_of(held, args.proposals)
        result["apply_to"] = args.apply_to
        result["held_out"] = {
            "chosen_alone": success(held, kh, picks_of(held, kh, None)),
            "with_symmetric": success(held, kh, picks_of(held, kh, best["setting"])),
        }
        h = result["held_out"]
        print(f"held-out ({len(held)} pairs): CHOSEN alone {h['chosen_alone']['mean']:.1f} %, "
              f"with the symmetric test {h['with_symmetric']['mean']:.1f} %")  # fmt: skip
    refine.write_json(Path(args.out), result)
    return result


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="what", required=True)
    c = sub.add_parser("count", help="support-side counts of a run's refined candidates")
    c.add_argument("--records", required=True)
    c.add_argument("--data", default="datasets/paper")
    c.add_argument("--split", default="test")
    c.add_argument("--out", required=True)
    c.add_argument("--no-progress", action="store_true")
    s = sub.add_parser("choose", help="choose the setting on validation, apply to held-out")
    s.add_argument("--select-on", required=True)
    s.add_argument("--apply-to", default=None)
    s.add_argument("--out", required=True)
    for p in (c, s):
        p.add_argument(
            "--proposals", type=int, default=None,
            help="K of the run(s), checked against the records (default: read from them)",
        )  # fmt: skip
    args = parser.parse_args(argv)
    return count(args) if args.what == "count" else choose(args)


if __name__ == "__main__":
    _cli.run(main)
