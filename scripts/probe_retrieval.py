"""Issue 12 probe (forty-sixth session): does the nearest TRAINING object's whole surface, fitted
to the observed object cloud, show the penetrations the answer rule cannot see?

The ranking's blind spot is the object's own hidden part (forty-fifth session: the support's
hidden half flags penetrating and hanging candidates alike). The library's objects come from a
few procedural families per category, so a held-out object's hidden side may be told, to a few
millimetres, by the training object most like its observed side. For each pair this probe
retrieves, among the training objects that are not validation objects
(`scripts/retrieval_surfaces.py`; never the pair's own object: 712 held-out pairs are a
training object on a held-out support), the K surfaces that best explain the observed object cloud
(score: mean distance observed -> surface plus ``--beta`` x the mean distance surface ->
observed, each clipped at 1 cm; the best ``TOP`` refined by a translation-only ICP), keeps their
points more than ``--new`` from every observed point (the hidden side, as that object would
have it) and, for every pooled refined candidate of the records, counts those points inside the
OBSERVED support (`experiments.rerank_completed.inside_grid`).

The surfaces are compared in the object frame as the library builds it (an object's frame is
its family's canonical one): a bound on retrieval with a known frame, not a method; a deployed
one would estimate the frame from the cloud. If the bound is level, the frame is not worth
estimating. Rules, choice (three validation keys) and one held-out reading as
``scripts/probe_symmetry.py``; the variant ``top1``: the best surface's hidden points
(``N_HIDDEN`` of them). Each split's table head is also written beside ``--out`` as it finishes.

    python scripts/retrieval_surfaces.py --out out/s46/surfaces.npz              # ~5 min
    python scripts/probe_retrieval.py --surfaces out/s46/surfaces.npz --out results/probe_retrieval_s46.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))

from probe_symmetry import (  # noqa: E402
    HELDOUT,
    MAX_POINTS,
    VALIDATION,
    finish,
    key_runs,
    separation,
    table,
)

from experiments.rerank_completed import GRID, inside_grid  # noqa: E402
from experiments.rerank_stage3 import read_records  # noqa: E402
from omnihang_jax import collision  # noqa: E402

VARIANTS = ("top1",)
CLIP = 0.01
TOP = 3
N_OBS = 1024
N_COARSE = 512  # surface points of the first pass (half as many observed)
N_HIDDEN = 512  # hidden points posed per surface


def chamfer_score(surface, tree, obs, obs_tree, beta: float) -> float:
    """Mean distance observed -> surface plus ``beta`` x surface -> observed, each clipped at
    ``CLIP`` (``tree``: the surface's, ``obs_tree``: the observed points')."""
    d_om, _ = tree.query(obs, k=1)
    d_mo, _ = obs_tree.query(surface, k=1)
    return float(np.minimum(d_om, CLIP).mean() + beta * np.minimum(d_mo, CLIP).mean())


class Retrieval:
    """The base surfaces' trees; ``fit(observed)`` -> the best ``TOP`` (name, aligned surface,
    score), best first."""

    def __init__(self, names, surfaces, beta: float):
        self.names = list(names)
        self.surfaces = [np.asarray(s, float) for s in surfaces]
        self.trees = [cKDTree(s) for s in self.surfaces]
        coarse = [s[collision.subsample_indices(len(s), N_COARSE, 0)] for s in self.surfaces]
        self.coarse = [(c, cKDTree(c)) for c in coarse]
        self.beta = beta

    def icp(self, i: int, obs: np.ndarray, steps: int = 5) -> np.ndarray:
        """A translation that moves surface ``i`` onto the observed points (nearest pairs
        within 2 cm)."""
        shift = np.zeros(3)
        for _ in range(steps):
            d, k = self.trees[i].query(obs - shift, k=1)
            near = d < 0.02
            if near.sum() < 10:
                break
            shift = shift + np.mean((obs - shift)[near] - self.surfaces[i][k[near]], axis=0)
        return shift

    def fit(self, observed: np.ndarray, exclude: str | None = None) -> list[tuple]:
        """A first pass over the whole base on ``N_COARSE`` points of each surface (half as many
        observed), then the best ``3 x TOP`` aligned by :meth:`icp` and scored on all points."""
        obs = observed[collision.subsample_indices(len(observed), N_OBS, 0)]
        tree = cKDTree(obs)
        few = obs[collision.subsample_indices(len(obs), N_COARSE // 2, 1)]
        few_tree = cKDTree(few)
        first = sorted(
            (chamfer_score(*self.coarse[i], few, few_tree, self.beta), i)
            for i in range(len(self.names))
            if self.names[i] != exclude
        )
        out = []
        for _, i in first[: 3 * TOP]:
            shift = self.icp(i, obs)
            # the surface moved by ``shift`` against obs == obs moved by -shift against the surface
            aligned = self.surfaces[i] + shift
            out.append(
                (chamfer_score(aligned, self.trees[i], obs - shift, tree, self.beta), i, aligned)
            )
        out.sort(key=lambda x: x[0])
        return [(self.names[i], aligned, s) for s, i, aligned in out[:TOP]]


def hidden_points(surface: np.ndarray, observed: np.ndarray, new: float) -> np.ndarray:
    d, _ = cKDTree(observed).query(surface, k=1)
    hidden = surface[d > new]
    return (
        hidden[collision.subsample_indices(len(hidden), N_HIDDEN, 0)]
        if len(hidden) > N_HIDDEN
        else hidden
    )


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--surfaces", default="out/s46/surfaces.npz")
    ap.add_argument("--beta", type=float, default=0.5)
    ap.add_argument("--new", type=float, default=0.003, help="m: a surface point is hidden beyond")
    ap.add_argument("--keys", type=int, default=3, help="CEM keys read on validation (1-3)")
    ap.add_argument("--heldout-keys", type=int, default=3, help="... and held out")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    with np.load(args.surfaces) as z:
        retrieval = Retrieval(z["names"], z["surfaces"], args.beta)
    data, progress = Path(args.data), not args.no_progress
    cache: dict[int, list] = {}
    fits: dict[str, list] = {}

    def counts_fn(row, clouds, poses):
        i = int(row["pair_index"])
        if i not in cache:
            obs = np.asarray(clouds["object_points"], float)
            got = retrieval.fit(obs, exclude=row["object"])  # never the pair's own object
            fits[str(i)] = [(n, round(s * 1000, 2)) for n, _, s in got]
            cache[i] = hidden_points(got[0][1], obs, args.new)  # the best surface's hidden side
        if len(cache[i]) == 0:
            return {"top1": np.zeros((len(GRID), len(poses)), np.int32)}
        sup = np.asarray(clouds["support_points"], float)
        nrm = np.asarray(clouds["support_normals"], float)
        return {"top1": inside_grid(collision.posed_points(poses, cache[i]), sup, nrm)}

    result = dict(settings=vars(args), grid=[list(x) for x in GRID], max_points=list(MAX_POINTS))
    tables = {}
    for split, runs in (("validation", VALIDATION), ("heldout", HELDOUT)):
        parts = [
            key_runs([read_records(p) for p in key], data, 0.0, progress, counts_fn, VARIANTS,
                     lambda c, v: c[v])
            for key in runs[: args.keys if split == "validation" else args.heldout_keys]
        ]  # fmt: skip
        tables[split] = table(parts, progress, VARIANTS)
        result[f"separation_{split}"] = separation(parts, VARIANTS)
        cat = {}
        for r in parts[0][0][0]:
            got = fits[str(int(r["pair_index"]))]
            cat.setdefault(r["category"], []).append(got[0][0].rsplit("_", 1)[0])
        result[f"retrieved_same_category_{split}"] = {
            c: round(float(np.mean([n == c for n in v])), 3) for c, v in sorted(cat.items())
        }
        result[f"median_fit_mm_{split}"] = round(float(np.median(
            [fits[str(int(r["pair_index"]))][0][1] for r in parts[0][0][0]])), 2)  # fmt: skip
        print(f"{split}: {len(tables[split])} rules, {time.perf_counter() - t0:.0f} s", flush=True)
        Path(args.out).with_suffix(f".{split}.json").write_text(
            json.dumps(
                dict(
                    committed=tables[split][0],
                    best=max(tables[split][1:], key=lambda r: r["mean"]),
                    **{k: v for k, v in result.items() if k.endswith(split)},
                ),
                indent=1,
            )
            + "\n"
        )
    result["fits"] = fits
    return finish(result, tables, ("variant", "depth", "radius", "rule", "value"), args.out, t0)


if __name__ == "__main__":
    main()
