"""Issue 12 probe (forty-eighth session): what a PERFECT completion of the object would give the
answer rule, as a bound before a completion trained for millimetre accuracy is built.

Four hidden-side priors were level against the rankers (mirror, completion, camera-ray slab,
retrieval; docs/stage3.md, sessions 26, 41, 45, 46). Each was an estimate of the object's hidden
side; none measured what the hidden side itself, known exactly, is worth. This probe takes each
pair's OWN object's whole outer surface (``sim.camera.surface_cloud``, the completion networks'
target, in the object frame the clouds are in), keeps its points more than ``--new`` from every
observed object point (what the view hid) and, for every pooled refined candidate of the
three-view default's records, counts those points inside the OBSERVED support
(``experiments.rerank_completed.inside_grid`` with ``margin``: the points within 2 cm of the
support cloud's box). Variant ``hidden``: those points; ``hidden_nX`` (``--noise``): the same points moved by
isotropic Gaussian noise of X mm per axis; ``hidden_sX`` (``--shift``): the whole hidden side moved
X mm in one random direction per pair. Stand-ins for a completion's error (scattered and
coherent), so that the bound says how accurate a completion must be; ``completed_<net>``
(``--completion``): a completion network's predicted points more than ``--new`` from every
observed point, the method the bound is for; ``points_<name>`` (``--points``, forty-ninth
session): per-pair points read from files, the distance field's (``scripts/field_points.py``),
likewise (with each model's hidden points measured against the true hidden side: median distance to it, share of it covered within 2 / 3 / 5 mm). Rules, choice on the three validation keys and one held-out reading as
``scripts/probe_symmetry.py``.

It is an oracle: the surface is the ground truth. If it is level, no completion of the object,
however accurate, lifts the answer rule, and the lever closes; if it reaches the aim, a
millimetre completion is worth its sessions.

    python -m experiments.derive_dataset --data datasets/paper --split train --pairs-from VAL.jsonl --clouds-only
    python -m experiments.derive_dataset --data datasets/paper --split test --pairs-from TEST.jsonl --clouds-only
    python scripts/probe_true_surface.py --out results/probe_true_surface_s48.json
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))

from probe_symmetry import (  # noqa: E402
    HELDOUT,
    VALIDATION,
    finish,
    key_runs,
    separation,
    table,
)

from experiments.rerank_completed import GRID, inside_grid  # noqa: E402
from experiments.rerank_stage3 import read_records  # noqa: E402
from omnihang_jax import collision  # noqa: E402

N_SURFACE = 32768  # surface points rendered per object (~1 mm from the observed ones)
N_POSED = 4096  # hidden surface points posed per candidate
SUPPORT_SPACING = 0.001  # m: a support's true surface is sampled about this far apart
SUPPORT_MAX_POINTS = 200_000
MARGIN = 0.02  # m: posed points farther than this outside the support cloud's box are not tested

_W: dict = {}


def _init(data: str, n_dirs: int) -> None:
    from omnihang_jax import dataset_bridge
    from sim.library import build_library

    cfg = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(data))
    _W.update(library=build_library(cfg.library, progress=False), camera=cfg.camera, n_dirs=n_dirs)


def surface(name: str) -> np.ndarray:
    """[N_SURFACE, 3] the object's whole outer surface in its own frame (full-resolution
    cameras, so the points are a few millimetres apart)."""
    from sim import camera
    from sim.scene import build_scene

    lib = _W["library"]
    scene = build_scene(lib.objects[name], next(iter(lib.supports.values())))
    rng = np.random.default_rng([0, *name.encode()])
    return camera.surface_cloud(
        scene, "object", rng, _W["camera"], n_dirs=_W["n_dirs"], n_points=N_SURFACE
    ).astype(np.float32)


def support_surface(asset, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The support's whole true surface in its asset frame (the frame of its clouds): points
    sampled on its union mesh about ``SUPPORT_SPACING`` apart, with the faces' outward normals
    (``scripts/probe_support_surface.py``, the fiftieth session's bound)."""
    import trimesh

    mesh = asset.mesh
    n = int(np.clip(mesh.area / SUPPORT_SPACING**2, 4096, SUPPORT_MAX_POINTS))
    pts, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts, float), np.asarray(mesh.face_normals[face], float)


def penetration_oracle(runs: list[list[list[dict]]]) -> dict:
    """The union's answer per key when every candidate the simulator found penetrating is dropped
    before the committed rule ranks (a perfect penetration test), beside the committed answer and
    "some candidate hangs"."""
    from experiments.rerank_stage3 import category_means, proposals_of, rule_keys

    out = {"committed": [], "no_penetrating": [], "some_candidate_hangs": []}
    for key in runs:
        keys, pens, stables = [], [], []
        for rows in key:
            k = proposals_of(rows)
            kk, st = rule_keys(rows, k)
            statuses = [r["stage1_3"]["statuses"] + r["all_stages"]["statuses"][-k:] for r in rows]
            keys.append(kk)
            stables.append(st)
            pens.append(np.asarray(statuses) == "penetrating")
        kk, pen, st = (np.concatenate(x, 1) for x in (keys, pens, stables))
        n, rows = np.arange(len(kk)), key[0]
        out["committed"].append(category_means(rows, st[n, kk.argmax(1)])["mean"])
        out["no_penetrating"].append(
            category_means(rows, st[n, np.where(pen, -1e9, kk).argmax(1)])["mean"]
        )
        out["some_candidate_hangs"].append(category_means(rows, st.any(1))["mean"])
    return {k: dict(per_key=[round(float(x), 3) for x in v], mean=round(float(np.mean(v)), 3))
            for k, v in out.items()}  # fmt: skip


def mean_quality(rows: list[dict]) -> dict:
    """The mean of each per-pair quality field, over the pairs where it is defined (a pair with
    no hidden or no predicted point has none)."""
    return {
        k: round(float(np.nanmean([np.nan if x[k] is None else x[k] for x in rows])), 4)
        for k in rows[0]
    }


def surfaces(names: list[str], data: str, n_dirs: int, workers: int, cache: Path) -> dict:
    """name -> surface, rendered once and kept in ``cache`` (an .npz)."""
    have: dict = {}
    if cache.exists():
        with np.load(cache) as z:
            have = {str(n): s for n, s in zip(z["names"], z["surfaces"], strict=True)}
    todo = [n for n in names if n not in have]
    if todo:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, ctx, initializer=_init, initargs=(data, n_dirs)) as ex:
            got = list(tqdm(ex.map(surface, todo), total=len(todo), desc="true surfaces"))
        have.update(zip(todo, got, strict=True))
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            cache, names=np.asarray(list(have)), surfaces=np.stack(list(have.values()))
        )
    return have


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--new", type=float, default=0.003, help="m: a surface point is hidden beyond")
    ap.add_argument("--n-dirs", type=int, default=20, help="cameras over the sphere per surface")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--cache", default="out/s48/true_surfaces.npz")
    ap.add_argument("--keys", type=int, default=3, help="CEM keys read on validation (1-3)")
    ap.add_argument("--heldout-keys", type=int, default=3, help="... and held out")
    ap.add_argument("--noise", default="", help="m, comma-separated: noisy variants' sigmas")
    ap.add_argument("--shift", default="", help="m, comma-separated: shifted variants' lengths")
    ap.add_argument(
        "--completion",
        default="",
        help="comma-separated completion folders (omnihang_jax.completion.load_completion): "
        "variants completed_<folder name>, the network's hidden points",
    )
    ap.add_argument(
        "--points",
        default="",
        help="comma-separated NAME=PREFIX[:UPPER_MM]: variants points_NAME, per-pair object points "
        "a model put on the hidden side (scripts/field_points.py extract writes PREFIX.partNN.npz; "
        "UPPER_MM: only those whose upper quantile lies below it)",
    )
    ap.add_argument(
        "--no-true", action="store_true", help="only the noisy / shifted / completed variants"
    )
    ap.add_argument(
        "--quality-only",
        action="store_true",
        help="only measure the --completion networks' hidden points (no rules)",
    )
    ap.add_argument(
        "--oracle-only",
        action="store_true",
        help="only the perfect penetration test's figure (from the records, seconds)",
    )
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    sigmas = [float(x) for x in args.noise.split(",") if x]
    shifts = [float(x) for x in args.shift.split(",") if x]
    variants = ([] if args.no_true else ["hidden"]) + [f"hidden_n{1e3 * x:g}" for x in sigmas]
    variants += [f"hidden_s{1e3 * x:g}" for x in shifts]
    nets = {}
    for folder in (x for x in args.completion.split(",") if x):
        from omnihang_jax import completion

        cfg, params, _ = completion.load_completion(folder)
        nets[f"completed_{Path(folder).parent.name}_{Path(folder).name}"] = (
            cfg, params, completion.complete_fn(cfg))  # fmt: skip
    variants += list(nets)
    given = {}  # points_NAME -> pair index -> [M, 3] (a model's points, read from files)
    for item in (x for x in args.points.split(",") if x):
        from field_points import load_points

        name, _, prefix = item.partition("=")
        if not prefix:
            raise SystemExit(f"--points: NAME=PREFIX[:UPPER_MM] expected, got {item!r}")
        prefix, _, mm = prefix.partition(":")
        given[f"points_{name}"] = load_points(prefix, float(mm) / 1e3 if mm else None)
    variants += list(given)
    if not variants:
        raise SystemExit("--no-true needs --noise, --shift, --completion or --points")
    quality: dict[str, list] = {v: [] for v in [*nets, *given]}
    data, progress = Path(args.data), not args.no_progress
    records = {
        split: [[read_records(p) for p in key] for key in runs[:n]]
        for split, runs, n in (("validation", VALIDATION, args.keys),
                               ("heldout", HELDOUT, args.heldout_keys))
    }  # fmt: skip
    if args.oracle_only:
        result = {split: penetration_oracle(runs) for split, runs in records.items()}
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
        print(json.dumps(result, indent=1))
        return result
    names = sorted({r["object"] for s in records.values() for r in s[0][0]})
    true = surfaces(names, args.data, args.n_dirs, args.workers, Path(args.cache))
    print(f"{len(true)} true surfaces, {time.perf_counter() - t0:.0f} s", flush=True)
    fit: dict[str, float] = {}
    cache: dict[int, dict] = {}

    def counts_fn(row, clouds, poses):
        i = int(row["pair_index"])
        if i not in cache:
            obs = np.asarray(clouds["object_points"], float)
            surf = true[row["object"]].astype(float)
            obs_tree, true_tree = cKDTree(obs), cKDTree(surf)
            fit[str(i)] = float(np.median(true_tree.query(obs, k=1)[0]))  # the frames agree?
            d, _ = obs_tree.query(surf, k=1)
            pick = collision.subsample_indices
            hidden = surf[d > args.new]
            hidden = hidden[pick(len(hidden), N_POSED, 0)] if len(hidden) > N_POSED else hidden
            rng = np.random.default_rng(i)
            cache[i] = {"hidden": hidden} if "hidden" in variants else {}
            for x in sigmas:
                cache[i][f"hidden_n{1e3 * x:g}"] = hidden + rng.normal(0.0, x, hidden.shape)
            for x in shifts:  # the whole hidden side off by x in one random direction
                u = rng.normal(size=3)
                cache[i][f"hidden_s{1e3 * x:g}"] = hidden + x * u / np.linalg.norm(u)
            preds = {}
            for v, (cfg, params, fn) in nets.items():  # as completion.predict_points: seed 0
                sub = obs[
                    np.random.default_rng(0).choice(
                        len(obs), cfg.n_input, replace=len(obs) < cfg.n_input
                    )
                ]
                preds[v] = np.asarray(fn(params, sub[None].astype(np.float32)))[0].astype(float)
            for v, per_pair in given.items():
                if i not in per_pair:
                    raise KeyError(f"{v}: no points for pair {i} (extract them for these records)")
                preds[v] = per_pair[i].astype(float)
            for v, pred in preds.items():
                pred = pred[obs_tree.query(pred, k=1)[0] > args.new] if len(pred) else pred
                cache[i][v] = pred
                near = (
                    cKDTree(pred).query(hidden, k=1)[0]
                    if len(pred)
                    else np.full(len(hidden), np.inf)
                )
                cover = {f"covered_{t}mm": float(np.mean(near < t / 1e3)) if len(hidden) else None
                         for t in (2, 3, 5)}  # fmt: skip
                to_true = true_tree.query(pred, k=1)[0] if len(pred) else None
                quality[v].append(dict(
                    to_true_mm=1e3 * float(np.median(to_true)) if len(pred) else None,
                    **cover, points=len(pred),
                    # the share of its points on the true surface (the rest is false surface)
                    accurate_3mm=float(np.mean(to_true < 0.003)) if len(pred) else None))  # fmt: skip
        sup = np.asarray(clouds["support_points"], float)
        nrm = np.asarray(clouds["support_normals"], float)
        out = {}
        for v, pts in cache[i].items():
            out[v] = (
                inside_grid(collision.posed_points(poses, pts), sup, nrm, margin=MARGIN)
                if len(pts)
                else np.zeros((len(GRID), len(poses)), np.int32)
            )
        return out

    result = dict(settings=vars(args), grid=[list(x) for x in GRID])
    if args.quality_only:  # the completions' hidden points against the true ones, no rules
        from experiments.rerank_completed import load_clouds

        for split, runs in records.items():
            for row in runs[0][0]:
                counts_fn(row, load_clouds(data, row), np.zeros((0, 7)))
            for v, q in quality.items():
                result[f"quality_{v}_{split}"] = mean_quality(q)
                q.clear()
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
        print(json.dumps({k: v for k, v in result.items() if k.startswith("quality")}, indent=1))
        return result
    tables = {}
    for split, runs in records.items():
        parts = [key_runs(key, data, 0.0, progress, counts_fn, variants, lambda c, v: c[v])
                 for key in runs]  # fmt: skip
        tables[split] = table(parts, progress, variants)
        result[f"separation_{split}"] = separation(parts, variants)
        med = [fit[str(int(r["pair_index"]))] for r in parts[0][0][0]]
        result[f"median_observed_to_true_mm_{split}"] = round(1000 * float(np.median(med)), 3)
        for v, q in quality.items():  # the completion's hidden points against the true hidden side
            result[f"quality_{v}_{split}"] = mean_quality(q)
            q.clear()
        print(f"{split}: {len(tables[split])} rules, {time.perf_counter() - t0:.0f} s", flush=True)
        best = {v: max((r for r in tables[split][1:] if r["variant"] == v), key=lambda r: r["mean"])
                for v in variants}  # fmt: skip
        Path(args.out).with_suffix(f".{split}.json").write_text(
            json.dumps(dict(committed=tables[split][0], best_per_variant=best,
                            separation=result[f"separation_{split}"]), indent=1) + "\n"
        )  # fmt: skip
    return finish(result, tables, ("variant", "depth", "radius", "rule", "value"), args.out, t0)


if __name__ == "__main__":
    main()
