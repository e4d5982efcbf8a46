"""Issue 12 probe (forty-first session): do mirror images of the observed object cloud show the
penetrations the answer rule cannot see?

Of the default pipeline's held-out failures, ~9 % of pairs pick a candidate that starts inside
the support while another candidate hangs; the overlap is where neither camera saw (docs/stage3.md,
twenty-sixth and thirty-second sessions). Most objects of the library are mirror-symmetric (a
tote bag's two handles, a mug's two sides, a cap, a hanger): the hidden half of the object is, to
a millimetre, the mirror image of the observed half. This probe adds, for each pair, the observed
object points mirrored in the object frame's planes ``x = 0`` and ``y = 0`` (and both: a half
turn about z), keeps the mirrored points that fall where nothing was observed (more than
``--new`` from every observed point) and, for every pooled refined candidate of the records,
counts those points inside the OBSERVED support (``experiments.rerank_completed.inside_grid``:
more than ``depth`` behind the nearest support point's surface, within ``radius`` sideways).

The planes are the object frame's own, as the library generates it: this is a bound on what
symmetry could give, not a method (a deployed one would estimate the plane from the cloud). If
the bound is level, estimating the plane is not worth building.

Rules (as ``experiments.rerank_completed``): the default union's key (the rankers' mean log P,
observed inside points first, each run's candidates on their own view) minus ``lambda x count``
(soft) or minus 100 x max(count - m, 0) (lexicographic), the answer the argmax over the union
of the runs of one CEM key. Chosen on the validation objects' records (three keys, mean), read
once on the held-out records (three keys).

    python scripts/probe_symmetry.py --out results/probe_symmetry_s41.json     # ~10 min, CPU
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from experiments.rerank_completed import GRID, inside_grid, load_clouds
from experiments.rerank_stage3 import (
    category_means,
    pool_indices,
    proposals_of,
    read_records,
    rule_keys,
)
from experiments.union_views import HELDOUT_RECORDS as HELDOUT  # noqa: E402
from experiments.union_views import VALIDATION_RECORDS as VALIDATION  # noqa: E402
from omnihang_jax import collision

PLANES = {"x": np.array([-1.0, 1, 1]), "y": np.array([1.0, -1, 1])}
PLANES["xy"] = PLANES["x"] * PLANES["y"]
VARIANTS = ("x", "y", "xy", "x+y", "all")
MAX_POINTS = (0, 1, 2, 5, 10, 20)
PENALTIES = (0.003, 0.01, 0.03, 0.1, 0.3)
N_MIRRORED = 1024


def mirrored(object_points: np.ndarray, new: float, seed: int = 0) -> dict:
    """plane -> [<= N_MIRRORED, 3] the observed object points mirrored in that plane of the
    object frame, only those more than ``new`` from every observed point (hidden by the view)."""
    pts = np.asarray(object_points, float)
    tree = cKDTree(pts)
    out = {}
    for name, flip in PLANES.items():
        m = pts * flip
        d, _ = tree.query(m, k=1)
        m = m[d > new]
        out[name] = collision.subsample_cloud(m, N_MIRRORED, seed) if len(m) > N_MIRRORED else m
    return out


def pair_counts(clouds: dict, poses: np.ndarray, new: float) -> dict:
    """plane -> [G, P] counts of mirrored object points inside the observed support, for the
    candidate poses [P, 7] (object frame -> support frame)."""
    mir = mirrored(clouds["object_points"], new)
    sup = np.asarray(clouds["support_points"], float)
    nrm = np.asarray(clouds["support_normals"], float)
    out = {}
    for name, pts in mir.items():
        if len(pts) == 0:
            out[name] = np.zeros((len(GRID), len(poses)), np.int32)
            continue
        out[name] = inside_grid(collision.posed_points(poses, pts), sup, nrm)
    return out


def variant_counts(c: dict, variant: str) -> np.ndarray:
    if variant in PLANES:
        return c[variant]
    if variant == "x+y":
        return c["x"] + c["y"]
    return c["x"] + c["y"] + c["xy"]


def key_runs(
    runs: list[list[dict]],
    data: Path,
    new: float,
    progress: bool,
    counts_fn=None,
    variants=VARIANTS,
    combine=None,
):
    """Per run of one key: (rows, [N, 2K] committed key, [N, 2K] stable, counts: variant ->
    [N, G, 2K]). ``counts_fn(row, clouds, poses) -> {part: [G, P]}`` (default: the mirrored
    counts) and ``combine(parts, variant) -> [G, P]`` make the probe's variants."""
    counts_fn = counts_fn or (lambda r, clouds, poses: pair_counts(clouds, poses, new))
    combine = combine or variant_counts
    out = []
    for rows in runs:
        k = proposals_of(rows)
        idx = pool_indices(k, "stage1_2")
        keys, stable = rule_keys(rows, k)
        counts = []
        for r in tqdm(rows, desc="mirrored counts", disable=not progress, leave=False):
            poses = np.asarray(r["poses_all"], float)[idx]
            counts.append(counts_fn(r, load_clouds(data, r), poses))
        counts = {v: np.stack([combine(c, v) for c in counts]) for v in variants}
        out.append((rows, keys, stable, counts))  # counts: variant -> [N, G, 2K]
    return out


def union_success(parts, variant: str | None, g: int, rule: str, value: float) -> dict:
    """The union's answer under one rule (None variant: the committed key)."""
    rows0 = parts[0][0]
    keys, stable = [], []
    for _rows, key, st, counts in parts:
        if variant is not None:
            c = counts[variant][:, g].astype(float)
            if rule == "soft":
                key = key - value * c
            else:
                key = key - 100.0 * np.maximum(c - value, 0)
        keys.append(key)
        stable.append(st)
    keys, stable = np.concatenate(keys, 1), np.concatenate(stable, 1)
    return category_means(rows0, stable[np.arange(len(rows0)), keys.argmax(1)])


def table(
    split_parts: list, progress: bool, variants=VARIANTS, grid=GRID, names=("depth", "radius")
) -> list[dict]:
    """Every rule's success under each key of a split and their mean (a grid setting's two
    numbers under ``names``)."""
    rules = [(None, 0, "committed", 0.0)]
    for v in variants:
        for g in range(len(grid)):
            rules += [(v, g, "lex", float(m)) for m in MAX_POINTS]
            rules += [(v, g, "soft", lam) for lam in PENALTIES]
    out = []
    for v, g, rule, value in tqdm(rules, desc="rules", disable=not progress, leave=False):
        per_key = [union_success(parts, v, g, rule, value) for parts in split_parts]
        d, rad = grid[g]
        out.append(dict(variant=v, **dict(zip(names, (d, rad), strict=True)), rule=rule, value=value,
                        per_key=[round(p["mean"], 3) for p in per_key],
                        mean=round(float(np.mean([p["mean"] for p in per_key])), 3),
                        per_category={c: round(float(np.mean([p["per_category"][c] for p in per_key])), 2)
                                      for c in per_key[0]["per_category"]}))  # fmt: skip
    return out


def separation(split_parts, variants=VARIANTS, g=None) -> dict:
    """How the mirrored counts tell penetrating from hanging candidates that the observed test
    passes (key > -50: no observed inside point), over a split's first key: per plane variant
    at the grid's ``g``-th setting (default (2 mm, 5 mm)), the share of each with a count > 0."""
    g = GRID.index((0.002, 0.005)) if g is None else g
    out = {}
    for v in variants:
        pen, ok = [], []
        for rows, key, st, counts in split_parts[0]:
            k = proposals_of(rows)
            for i, r in enumerate(rows):
                statuses = np.asarray(r["stage1_3"]["statuses"] + r["all_stages"]["statuses"][-k:])
                c = counts[v][i, g]
                clear = key[i] > -50
                pen += list(c[clear & (statuses == "penetrating")] > 0)
                ok += list(c[clear & st[i]] > 0)
        out[v] = dict(penetrating_flagged=round(float(np.mean(pen)), 4), penetrating=len(pen),
                      stable_flagged=round(float(np.mean(ok)), 4), stable=len(ok))  # fmt: skip
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--new", type=float, default=0.003, help="m: a mirrored point is new beyond")
    ap.add_argument("--keys", type=int, default=3, help="CEM keys read (1-3)")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    data, progress = Path(args.data), not args.no_progress
    result = dict(settings=vars(args), grid=[list(x) for x in GRID])
    tables = {}
    for split, runs in (("validation", VALIDATION), ("heldout", HELDOUT)):
        parts = [key_runs([read_records(p) for p in key], data, args.new, progress)
                 for key in runs[: args.keys]]  # fmt: skip
        tables[split] = table(parts, progress)
        result[f"separation_{split}"] = separation(parts)
        print(f"{split}: {len(tables[split])} rules, {time.perf_counter() - t0:.0f} s", flush=True)
    return finish(result, tables, ("variant", "depth", "radius", "rule", "value"), args.out, t0)


def finish(result: dict, tables: dict, fields: tuple, out: str, t0: float) -> dict:
    """The rule chosen on validation read held out (matched on ``fields``), the committed and
    best held-out rows beside it, written to ``out`` and summarised on stdout."""
    best = max(tables["validation"][1:], key=lambda r: r["mean"])
    held = next(x for x in tables["heldout"] if all(x[k] == best[k] for k in fields))
    result |= dict(
        committed={s: t[0] for s, t in tables.items()},
        chosen_on_validation=dict(rule=best, heldout=held),
        best_heldout=max(tables["heldout"][1:], key=lambda r: r["mean"]),
        seconds=round(time.perf_counter() - t0, 1),
        validation=tables["validation"], heldout=tables["heldout"],
    )  # fmt: skip
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text(json.dumps(result, indent=1) + "\n")
    show = {k: result[k] for k in ("committed", "chosen_on_validation", "best_heldout")}
    show |= {k: result[k] for k in result if k.startswith("separation")}
    json.dump(show, sys.stdout, indent=1)
    print()
    return result


if __name__ == "__main__":
    main()
