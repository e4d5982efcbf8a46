"""The Stage-3 answer rule with shape completion: candidates whose COMPLETED clouds overlap.

    python -m experiments.rerank_completed --select-on results/validation_where_s26/val_base_s24.pairs.jsonl.gz \\
        --apply-to results/hanging_success_stage3_s22_rankset.pairs.jsonl.gz \\
        --completion weights/completion_s25 --out results/rerank_completed_s26.json

Issue 12, twenty-sixth session. Of the committed pipeline's 334 held-out failures (key 0), 211
pick a candidate that starts inside the support (true meshes overlapping by > 3 mm) though the
observed clouds show no object point inside it: the overlap is in what neither camera saw. An
oracle that dropped every penetrating candidate before the ranking would reach 85.8 % (from
81.4). The completion networks of issue 13 (``omnihang_jax.completion``) predict the hidden
surface of both bodies; this study asks whether their points tell the penetrating candidates
apart, with the records of runs that simulated every candidate (no new simulation).

For each pair: the derived observed clouds (``experiments.derive_dataset --clouds-only``, the
same renders as the run's), the predicted points of both bodies carved with each body's camera
(``completion.predict_points`` with the eyes), normals for the predicted points by PCA over
their neighbours in the completed cloud, turned to face AWAY from the body's camera (the
carved points lie behind the observed surface: back faces). Then for every pooled refined
candidate, three inside counts over a (depth, radius) grid, the test of
``selection.inside_counts`` (points more than ``depth`` behind the nearest surface point and
within ``radius`` of it sideways):

- ``object``: predicted object points inside the observed support (true normals);
- ``support``: observed object points inside the predicted support surface;
- ``both``: the completed object (observed + predicted) inside the completed support, plus the
  completed support's points inside the completed object (the symmetric test).

Rules: the committed key (rankers' mean log P, observed inside points first, ``selection.CHOSEN``)
then ``- 100 * max(count - m, 0)`` for a variant's count: lexicographic (log P lies in
[-50, 0]): a candidate over the completed limit ranks below every one within it, above every
one the observed test rejects. Soft rules: ``- lambda * count`` (:data:`PENALTIES`). Chosen on --select-on (validation objects) by the mean over
categories; applied once to --apply-to beside the committed rule; the whole table is written
with both columns.

The per-candidate counts are cached per run (``--cache``, resumable: pairs already there are
skipped) so the rules can be re-scored in seconds.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from experiments import _cli
from experiments.rerank_stage3 import (
    category_means,
    pool_indices,
    proposals_of,
    read_records,
    rule_keys,
)
from omnihang_jax import collision, completion

DEPTHS = (0.001, 0.002, 0.003, 0.005)
RADII = (0.003, 0.005, 0.008)
GRID = tuple((d, r) for d in DEPTHS for r in RADII)
VARIANTS = ("object", "support", "both")
MAX_POINTS = (0, 1, 2, 5, 10, 20, 40)
PENALTIES = (0.01, 0.03, 0.1, 0.3, 1.0)  # soft rules: log P minus this x the count
NORMAL_NEIGHBOURS = 12
N_OBJECT = 1024  # observed object points kept, and as many predicted (the planner's subset)
_COMPLETED_WEIGHT = 100.0


def facing_normals(points: np.ndarray, cloud: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """[K, 3] unit PCA normals of ``points`` over their nearest neighbours in ``cloud``, signed
    to face away from ``eye`` (hidden points are back faces)."""
    if len(points) == 0:
        return np.zeros((0, 3))
    k = min(NORMAL_NEIGHBOURS, len(cloud))
    _, idx = cKDTree(cloud).query(points, k=k)
    nb = cloud[idx] - cloud[idx].mean(1, keepdims=True)
    _, _, vt = np.linalg.svd(nb, full_matrices=False)
    normals = vt[:, -1, :]
    flip = np.einsum("ij,ij->i", normals, points - np.asarray(eye, float)) < 0
    normals[flip] *= -1
    return normals


def inside_grid(
    posed: np.ndarray,
    surface: np.ndarray,
    normals: np.ndarray,
    margin: float | None = None,
    grid=GRID,
    max_dist: float | None = None,
) -> np.ndarray:
    """posed [P, N, 3] points, a surface [M, 3] with outward normals -> [G, P] counts of
    ``grid``'s (depth, radius) settings (the test of ``collision.inside_points``). With ``margin``
    (m) only the points within that far of the surface's bounding box are tested: the rest cannot
    meet it, and the test alone would count a point far behind a partial surface as inside.
    With ``max_dist`` (m) a point farther than that from every surface point is outside: the
    nearest-point search stops there (a dense, flat surface, such as a pegboard's, makes an
    unbounded search of far points a thousand times slower)."""
    out = np.zeros((len(grid), posed.shape[0]), np.int32)
    if len(surface) == 0 or posed.shape[1] == 0:
        return out
    if margin is None:
        tested = np.ones(posed.shape[:2], bool)
    else:
        lo, hi = surface.min(0) - margin, surface.max(0) + margin
        tested = np.all((posed > lo) & (posed < hi), axis=-1)  # [P, N]
    if not tested.any():
        return out
    flat = posed[tested]
    if max_dist is None:
        dist, k = cKDTree(surface).query(flat, k=1)
    else:
        dist, k = cKDTree(surface).query(flat, k=1, distance_upper_bound=max_dist)
        near = np.isfinite(dist)
        flat, dist, k = flat[near], dist[near], k[near]
        tested[tested] = near
    along = np.einsum("ij,ij->i", flat - surface[k], normals[k])
    lateral2 = dist**2 - along**2
    which = np.nonzero(tested)[0]  # the candidate of each tested point
    for g, (d, r) in enumerate(grid):
        out[g] = np.bincount(which[(along < -d) & (lateral2 < r**2)], minlength=len(posed))
    return out


def candidate_counts(nets, clouds: dict, eyes, poses: np.ndarray, seed: int = 0) -> dict:
    """variant -> [G, P] inside counts of the candidates ``poses`` [P, 7] of one pair."""
    obs_o, obs_s = clouds["object_points"], clouds["support_points"]
    pred_o, pred_s = completion.predict_points(nets, obs_o, obs_s, eyes, seed=seed)
    pred_o, pred_s = np.asarray(pred_o, float), np.asarray(pred_s, float)
    keep_o = collision.subsample_indices(len(obs_o), N_OBJECT, seed)
    sub_o = np.asarray(obs_o, float)[keep_o]
    n_sub_o = np.asarray(clouds["object_normals"], float)[keep_o]
    sub_po = collision.subsample_cloud(pred_o, N_OBJECT, seed) if len(pred_o) else pred_o
    comp_o = np.concatenate([sub_o, sub_po])
    comp_s = np.concatenate([obs_s, pred_s])
    n_pred_s = facing_normals(pred_s, comp_s, eyes[1])
    n_pred_o = facing_normals(sub_po, comp_o, eyes[0])
    n_obs_s = np.asarray(clouds["support_normals"], float)
    poses = np.asarray(poses, float)

    def pose_obj(points):  # object frame -> support frame, [P, N, 3]
        return collision.posed_points(poses, points)

    out = {
        "object": inside_grid(pose_obj(sub_po), np.asarray(obs_s, float), n_obs_s),
        "support": inside_grid(pose_obj(sub_o), pred_s, n_pred_s),
    }
    comp_n_s = np.concatenate([n_obs_s, n_pred_s])
    comp_n_o = np.concatenate([n_sub_o, n_pred_o])
    # the symmetric part: completed support points (a 2,048 subset) in the object frame
    sub_s = collision.subsample_cloud(comp_s, 2048, seed).astype(float)
    local = np.asarray(collision.inverse_transform_points(poses, sub_s), float)
    out["both"] = inside_grid(pose_obj(comp_o), comp_s, comp_n_s) + inside_grid(
        local, comp_o, comp_n_o
    )
    return out


def load_clouds(data: Path, row: dict) -> dict:
    split = "test" if (data / "derived" / "test_clouds" / row["file"]).exists() else "train"
    path = data / "derived" / f"{split}_clouds" / row["file"]
    if not path.exists():
        raise FileNotFoundError(
            f"{path} missing: derive the run's clouds first (python -m experiments.derive_dataset "
            f"--data {data} --split <split> --pairs-from RUN.pairs.jsonl.gz --clouds-only)"
        )
    with np.load(path) as z:
        return {k: z[k] for k in ("object_points", "object_normals", "support_points",
                                  "support_normals")}  # fmt: skip


def run_counts(rows, k, data, nets, eyes_of, cache: Path, progress=True) -> dict:
    """pair_index -> variant -> [G, 2K] counts of the pooled refined candidates (cached)."""
    have = {}
    if cache.exists():
        with np.load(cache) as z:
            have = {int(i): {v: z[f"{v}"][j] for v in VARIANTS} for j, i in enumerate(z["pair"])}
    idx = pool_indices(k, "stage1_2")
    todo = [r for r in rows if int(r["pair_index"]) not in have]
    for n, r in enumerate(tqdm(todo, desc=f"completed counts {cache.stem}", disable=not progress)):
        poses = np.asarray(r["poses_all"], float)[idx]
        clouds = load_clouds(data, r)
        have[int(r["pair_index"])] = candidate_counts(
            nets, clouds, eyes_of[int(r["pair_index"])], poses
        )
        if (n + 1) % 100 == 0 or n + 1 == len(todo):
            save_cache(cache, have)
    return have


def save_cache(cache: Path, have: dict) -> None:
    cache.parent.mkdir(parents=True, exist_ok=True)
    pairs = sorted(have)
    tmp = cache.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, pair=np.asarray(pairs),
                        **{v: np.stack([have[p][v] for p in pairs]) for v in VARIANTS})  # fmt: skip
    tmp.replace(cache)


def committed_key(rows, k) -> np.ndarray:
    """[N, 2K] the pipeline's key: the rankers' mean log P, observed inside points first
    (``rerank_stage3.rule_keys``)."""
    return rule_keys(rows, k)[0]


def oracle_no_penetrating(rows, k) -> float:
    """The committed key with every candidate the simulation calls ``penetrating`` dropped:
    what a perfect penetration test could reach (mean over categories, percent)."""
    idx = pool_indices(k, "stage1_2")
    key = committed_key(rows, k)
    statuses = np.asarray([r["stage1_3"]["statuses"] + r["all_stages"]["statuses"][-k:]
                           for r in rows])  # fmt: skip
    key = np.where(statuses == "penetrating", -np.inf, key)
    stable = np.asarray([np.asarray(r["stable_all"])[idx] for r in rows])
    return category_means(rows, stable[np.arange(len(rows)), key.argmax(1)])["mean"]


def score_rules(rows, k, counts) -> list[dict]:
    idx = pool_indices(k, "stage1_2")
    base = committed_key(rows, k)
    stable = np.asarray([np.asarray(r["stable_all"])[idx] for r in rows])
    table = []

    def add(label, key, **extra):
        picks = key.argmax(1)
        res = category_means(rows, stable[np.arange(len(rows)), picks])
        table.append({"rule": label, **extra, **res})

    add("committed", base)
    for v in VARIANTS:
        c = np.stack([counts[int(r["pair_index"])][v] for r in rows])  # [N, G, P]
        for g, (d, rad) in enumerate(GRID):
            for m in MAX_POINTS:
                key = base - _COMPLETED_WEIGHT * np.maximum(c[:, g] - m, 0)
                add(f"{v} d{d * 1e3:g} r{rad * 1e3:g} m{m}", key, variant=v, depth=d, radius=rad,
                    max_points=m, penalty=None)  # fmt: skip
            for lam in PENALTIES:
                key = base - lam * c[:, g]
                add(f"{v} d{d * 1e3:g} r{rad * 1e3:g} soft{lam:g}", key, variant=v, depth=d,
                    radius=rad, max_points=None, penalty=lam)  # fmt: skip
    return table


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--select-on", required=True, help="records of validation-object pairs")
    ap.add_argument("--apply-to", required=True, help="records of the held-out pairs")
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--completion", default="weights/completion_s25")
    ap.add_argument("--cache", default="out/rerank_completed", help="folder of the counts")
    ap.add_argument("--out", default=None, help="JSON")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    from sim import dataset

    data = Path(args.data)
    nets = completion.load_nets(args.completion)
    eyes_of = {int(r["pair_index"]): (np.asarray(r["object_eye"], float),
                                      np.asarray(r["support_eye"], float))
               for r in dataset.load_records(data)}  # fmt: skip
    runs, oracle = {}, {}
    for name, path in (("select_on", args.select_on), ("apply_to", args.apply_to)):
        rows = read_records(path)
        k = proposals_of(rows)
        cache = Path(args.cache) / (Path(path).name.split(".")[0] + ".npz")
        counts = run_counts(rows, k, data, nets, eyes_of, cache, not args.no_progress)
        runs[name] = score_rules(rows, k, counts)
        oracle[name] = oracle_no_penetrating(rows, k)
    sel, app = runs["select_on"], runs["apply_to"]
    for a, b in zip(sel, app, strict=True):
        a["held_out"] = {"mean": b["mean"], "pair_mean": b["pair_mean"],
                         "per_category": b["per_category"]}  # fmt: skip
    best = max(sel[1:], key=lambda r: r["mean"])
    result = {
        "select_on": args.select_on,
        "apply_to": args.apply_to,
        "completion": args.completion,
        "committed": {"validation": sel[0]["mean"], "held_out": sel[0]["held_out"]["mean"]},
        "oracle_no_penetrating": {
            "validation": oracle["select_on"],
            "held_out": oracle["apply_to"],
        },  # fmt: skip
        "chosen": {
            k: best[k] for k in ("rule", "variant", "depth", "radius", "max_points", "penalty")
        }
        | {
            "validation": best["mean"],
            "held_out": best["held_out"]["mean"],
            "held_out_per_category": best["held_out"]["per_category"],
        },  # fmt: skip
        "table": [
            {k: r[k] for k in ("rule", "mean", "pair_mean")} | {"held_out": r["held_out"]["mean"]}
            for r in sel
        ],  # fmt: skip
    }
    print(f"committed: validation {sel[0]['mean']:.2f}, held-out {sel[0]['held_out']['mean']:.2f}")
    top = sorted(sel[1:], key=lambda r: -r["mean"])[:15]
    for r in top:
        print(f"  {r['rule']:28s} validation {r['mean']:.2f}  held-out {r['held_out']['mean']:.2f}")
    print(
        f"chosen: {best['rule']} validation {best['mean']:.2f} held-out {best['held_out']['mean']:.2f}"
    )
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    _cli.run(main)
