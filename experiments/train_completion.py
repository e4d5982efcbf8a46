"""Train the shape-completion networks (object and support) that fill in the hidden backs.

    python -m experiments.train_completion --out weights/completion_s25          # the device
    python -m experiments.train_completion --out runs/completion_tiny --steps 200 --views 4 \\
        --support-views 4 --objects 12 --supports 6                                # a quick look

1. Renders, per asset, ``--views`` partial clouds from random cameras drawn like the dataset's
   (the recipe's depth camera; objects from any side in their own frame, supports from the
   front in the world frame), keeping ``--points`` of each, and the whole visible surface as
   the target (``sim.camera.surface_cloud``: 42 cameras over the sphere). Cached, resumable,
   in ``DATA/derived/completion/<kind>_<split>.npz`` (ignored by git).
2. Splits the training assets by name into fit / validation (the same hash as every trainer,
   ``data.validation_objects``, 15 %); the held-out (test split) assets are never trained on.
3. Trains one network per kind (``omnihang_jax.completion``), writes ``OUT/<kind>/``
   (best-on-validation weights, ``history.jsonl``, ``curves.png``, a resumable checkpoint) and
   ``OUT/metrics.json``: Chamfer distance, coverage of the true surface by observed +
   predicted points (and by the observed alone), accuracy of the predicted points, on the
   validation and the held-out assets.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from omnihang_jax import completion, dataset_bridge
from omnihang_jax.data import validation_objects

DERIVED = os.path.join(dataset_bridge.DERIVED_DIRNAME, "completion")
VALIDATION_FRACTION = 0.15

_W: dict = {}


def _init(recipe: dict, library_overrides: dict) -> None:
    from sim.library import build_library

    config = dataset_bridge.dataset_config_from_recipe(recipe)
    lib_cfg = dataclasses.replace(config.library, **library_overrides)
    _W.update(library=build_library(lib_cfg, progress=False), camera=config.camera)


def render_asset(job: tuple) -> tuple[np.ndarray, np.ndarray]:
    """(views [V, P, 3], surface [T, 3]) of one asset, deterministic in its name and ``seed``
    (``job``: kind, name, views, points, seed, target points T)."""
    from sim import camera
    from sim.scene import build_scene

    kind, name, views, points, seed, target_points = job
    lib = _W["library"]
    if kind == "object":
        scene = build_scene(lib.objects[name], next(iter(lib.supports.values())))
        body = scene.obj
    else:
        scene = build_scene(next(iter(lib.objects.values())), lib.supports[name])
        body = scene.support
    cam = _W["camera"]
    rng = np.random.default_rng([seed, *name.encode()])
    radius = float(np.linalg.norm(body.extents)) / 2
    front = kind == "support" and scene.support.wall_y is not None
    out = []
    for _ in range(views):
        eye = camera.sample_eye(rng, np.zeros(3), radius, cam, front_only=front)
        cloud = camera.partial_cloud(
            scene, kind, eye, rng, dataclasses.replace(cam, n_points=points)
        )
        out.append(cloud.points)
    coarse = dataclasses.replace(cam, width=cam.width // 2, height=cam.height // 2)
    surface = camera.surface_cloud(scene, kind, rng, coarse, n_points=target_points)
    return np.stack(out), surface


def build_views(data: str, kind: str, names: list[str], views: int, points: int, workers: int,
                cache: Path | None, library_overrides: dict | None = None,
                seed: int = 0, target_points: int = 2048) -> completion.CompletionData:  # fmt: skip
    """Render (or read from ``cache``) the views and surfaces of ``names``."""
    if cache is not None and cache.exists():
        with np.load(cache) as f:
            got = completion.CompletionData(f["inputs"], f["targets"], f["names"])
        same = got.inputs.shape[1:3] == (views, points) and got.targets.shape[1] == target_points
        if list(got.names) == list(names) and same:
            return got
        print(f"{cache}: another set of assets or views; rendering again", flush=True)
    recipe = dataset_bridge.read_recipe(data)
    overrides = library_overrides or {}
    jobs = [(kind, n, views, points, seed, target_points) for n in names]
    from tqdm.auto import tqdm

    if workers <= 1:
        _init(recipe, overrides)
        results = [render_asset(j) for j in tqdm(jobs, desc=f"render {kind}s")]
    else:
        ctx = multiprocessing.get_context("spawn")  # JAX is loaded: never fork it
        with ProcessPoolExecutor(
            workers, ctx, initializer=_init, initargs=(recipe, overrides)
        ) as ex:
            results = list(tqdm(ex.map(render_asset, jobs, chunksize=2), total=len(jobs),
                                desc=f"render {kind}s"))  # fmt: skip
    got = completion.CompletionData(
        np.stack([r[0] for r in results]).astype(np.float32),
        np.stack([r[1] for r in results]).astype(np.float32),
        np.asarray(names),
    )
    got.check(f"{kind} views")
    if cache is not None:
        from sim import atomic

        atomic.savez(cache, **got._asdict())
    return got


def network_config(kind: str, args) -> completion.CompletionConfig:
    """The network of ``--n-coarse`` / ``--fold`` / ``--fold-size`` / ``--width`` (defaults: the
    twenty-fifth session's)."""
    base = completion.CompletionConfig(kind=kind)
    w = max(1, int(args.width))
    change: dict = dict(
        encoder=tuple(w * x for x in base.encoder),
        encoder2=tuple(w * x for x in base.encoder2),
        decoder=tuple(w * x for x in base.decoder),
        fine=tuple(w * x for x in base.fine),
    )
    if args.n_coarse:
        change["n_coarse"] = int(args.n_coarse)
    if args.fold:
        a, b = (int(x) for x in args.fold.lower().split("x"))
        change["fold"] = (a, b)
    if args.fold_size:
        change["fold_size"] = float(args.fold_size)
    return dataclasses.replace(base, **change)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])  # fmt: skip
    ap.add_argument("--data", default="datasets/paper", help="dataset folder (its recipe)")
    ap.add_argument("--out", default="weights/completion", help="output folder")
    ap.add_argument("--kinds", default="object,support")
    ap.add_argument("--views", type=int, default=32, help="partial views per object")
    ap.add_argument("--support-views", type=int, default=96, help="partial views per support")
    ap.add_argument("--points", type=int, default=2048, help="points kept per view")
    ap.add_argument("--objects", type=int, default=None, help="at most this many training objects")
    ap.add_argument("--supports", type=int, default=None, help="... and supports (quick looks)")
    ap.add_argument(
        "--target-points",
        type=int,
        default=2048,
        help="points of each whole-surface target (denser: finer Chamfer)",
    )
    ap.add_argument("--n-coarse", type=int, default=None, help="CompletionConfig.n_coarse")
    ap.add_argument("--fold", default=None, help="CompletionConfig.fold, e.g. 4x4")
    ap.add_argument("--fold-size", type=float, default=None, help="CompletionConfig.fold_size")
    ap.add_argument(
        "--width",
        type=int,
        default=1,
        help="every layer of the encoder, decoder and folding MLP this many times wider",
    )
    ap.add_argument(
        "--tol",
        type=float,
        default=0.005,
        help="m: coverage / accuracy tolerance of the metrics (and twice it)",
    )
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--eval-every", type=int, default=1000)
    ap.add_argument("--workers", type=int, default=max(1, (os.cpu_count() or 2)))
    ap.add_argument("--no-cache", action="store_true", help="render again, write no cache")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    kinds = [k for k in args.kinds.split(",") if k]
    bad = [k for k in kinds if k not in completion.KINDS]
    if bad:
        raise ValueError(f"--kinds: unknown {bad} (choose from {completion.KINDS})")
    from sim.library import build_library

    config = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(args.data))
    library = build_library(config.library, progress=False)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    metrics_path = out / "metrics.json"
    metrics = json.loads(metrics_path.read_text()) if metrics_path.exists() else {}
    t0 = time.time()
    for kind in kinds:
        group = "objects" if kind == "object" else "supports"
        limit = args.objects if kind == "object" else args.supports
        views = args.views if kind == "object" else args.support_views
        train_names = sorted(library.split["train"][group])
        if limit:
            train_names = train_names[:limit]
        val_set = validation_objects(train_names, VALIDATION_FRACTION)
        if not val_set:
            val_set = {train_names[-1]}
        fit_names = [n for n in train_names if n not in val_set]
        val_names = [n for n in train_names if n in val_set]
        test_names = sorted(library.split["test"][group])
        if limit:
            test_names = test_names[: max(1, limit // 4)]

        tp = args.target_points
        tail = "" if tp == 2048 else f"_t{tp}"

        def cache(split, views, kind=kind, n=len(train_names), tail=tail):
            if args.no_cache:
                return None
            return Path(args.data, DERIVED, f"{kind}_{split}_v{views}_n{n}{tail}.npz")

        all_train = build_views(args.data, kind, train_names, views, args.points, args.workers,
                                cache("train", views), target_points=tp)  # fmt: skip
        test = build_views(args.data, kind, test_names, 4, args.points, args.workers,
                           cache("test", 4), target_points=tp)  # fmt: skip
        idx = {n: i for i, n in enumerate(train_names)}
        fit = all_train.take([idx[n] for n in fit_names])
        val = all_train.take([idx[n] for n in val_names])
        cfg = network_config(kind, args)
        tc = completion.CompletionTrainConfig(steps=args.steps, batch=args.batch, lr=args.lr, tol=args.tol,
                                              eval_every=min(args.eval_every, args.steps))  # fmt: skip
        summary = completion.train_completion(cfg, fit, val, out / kind, tc,
                                              progress=not args.no_progress)  # fmt: skip
        cfg, params, meta = completion.load_completion(out / kind)
        _, apply = completion.make_completion(cfg)
        held = completion.evaluate(apply, params, test, cfg, tc.tol)
        metrics[kind] = dict(
            fit_assets=len(fit_names), validation_assets=len(val_names), test_assets=len(test_names),
            views=views, steps=args.steps, best_step=summary["best_step"], tolerance_m=tc.tol,
            validation=meta["val"], held_out=held,
        )  # fmt: skip
        print(f"{kind}: validation {meta['val']}\n{kind}: held-out {held}", flush=True)
    metrics["seconds"] = round(time.time() - t0, 1)
    from sim import atomic

    atomic.write_text(metrics_path, json.dumps(metrics, indent=2))
    return metrics


if __name__ == "__main__":
    from experiments import _cli

    _cli.run(main)
