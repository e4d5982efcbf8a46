"""Train the object-frame network (``omnihang_jax.frame``) that lets where to hang take an object
in any frame.

    # 1. partial clouds of every training object, cameras anywhere on the sphere (resumable):
    python -m experiments.train_frame render --data datasets/paper --views 24 \\
        --out out/frame/clouds.npz --workers 2
    # 2. train on turned copies; validation on the validation objects (never trained on):
    python -m experiments.train_frame train --clouds out/frame/clouds.npz --steps 8000 \\
        --out out/frame/run --export weights/frame

Clouds are rendered like the dataset's (``sim.camera.partial_cloud``, the dataset's camera at
``--camera-scale`` of its resolution, resampled), one camera per view drawn uniformly on the
sphere around the object; the object stays in its library frame, so each cloud is its own target.
Training turns every cloud by a uniform random rotation and adds ``--jitter`` of depth noise; the
loss is ``frame.frame_loss`` (winner-takes-all Chamfer over the hypotheses + the score's
cross-entropy). The validation objects are ``data.validation_objects(names, 0.1)``, the same
10 % of training objects every trainer holds out; ``history.jsonl`` has their curve (Chamfer of
the chosen hypothesis, its rotation error, score accuracy), the checkpoint resumes a killed
run and the best validation step is exported.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from experiments import _cli
from omnihang_jax import checkpoints, frame

KEEP_POINTS = 1024  # points kept per rendered cloud (the network reads 512 of them)


# ----------------------------------------------------------------------------------------------
# Rendering (CPU workers holding the asset library)


def _render_object(job: tuple) -> tuple[str, np.ndarray, np.ndarray]:
    """(object name, views, camera config, seed) -> (name, points [V, KEEP, 3], normals)."""
    from omnihang_jax.refine import worker_library
    from sim import camera, library
    from sim.scene import build_scene

    name, views, cam, seed = job
    lib = worker_library()
    obj = lib.objects[name]
    support = next(iter(lib.supports.values()))
    scene = build_scene(obj, support)
    rng = np.random.default_rng([seed, library.stable_id(name)])
    radius = float(np.linalg.norm(obj.extents) / 2)
    pts, nrm = [], []
    while len(pts) < views:
        eye = camera.sample_eye(rng, np.zeros(3), radius, cam)
        try:
            cloud = camera.partial_cloud(scene, "object", eye, rng, cam)
        except ValueError:  # a camera that sees nothing (never for a closed mesh): draw again
            continue
        idx = rng.choice(len(cloud.points), KEEP_POINTS, replace=False)
        pts.append(cloud.points[idx])
        nrm.append(cloud.normals[idx])
    return name, np.stack(pts), np.stack(nrm)


def render(args) -> int:
    from omnihang_jax import dataset_bridge, refine

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    card = Path(args.data) / "dataset_card.json"
    if not card.exists():
        raise FileNotFoundError(f"{card} not found: --data must be a generated dataset folder")
    names = sorted(json.loads(card.read_text())["train_objects"])
    done: dict[str, tuple] = {}
    if out.exists():
        with np.load(out) as z:
            done = {n: (z["points"][i], z["normals"][i]) for i, n in enumerate(z["names"])}
    recipe = dataset_bridge.read_recipe(args.data)  # the dataset's camera, at --camera-scale
    cam = dataset_bridge.scaled_config(
        dataset_bridge.dataset_config_from_recipe(recipe), args.camera_scale
    ).camera
    todo = [(n, args.views, cam, args.seed) for n in names if n not in done]
    print(f"render: {len(done)} objects done, {len(todo)} to go ({args.views} views each)")
    pool = refine.library_pool(args.data, args.workers)
    t0 = time.time()
    try:
        results = pool.imap_unordered(_render_object, todo) if pool else map(_render_object, todo)
        for i, (name, p, n) in enumerate(results, 1):
            done[name] = (p, n)
            if i % 20 == 0 or i == len(todo):
                _save_clouds(out, done)
                print(f"  {i}/{len(todo)} objects, {time.time() - t0:.0f} s", flush=True)
    finally:
        if pool is not None:
            pool.__exit__(None, None, None)
    _save_clouds(out, done)
    return 0


def _save_clouds(path: Path, done: dict) -> None:
    from sim import atomic

    names = sorted(done)
    arrays = dict(
        names=np.array(names),
        points=np.stack([done[n][0] for n in names]).astype(np.float32),
        normals=np.stack([done[n][1] for n in names]).astype(np.float16),
    )
    atomic.write_atomic(path, lambda f: np.savez(f, **arrays))


# ----------------------------------------------------------------------------------------------
# Training


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    steps: int = 8000
    batch: int = 32
    lr: float = 1e-3
    warmup: int = 300
    weight_decay: float = 1e-4
    jitter: float = 0.001  # m, Gaussian noise on every point
    eval_every: int = 250
    seed: int = 0


def load_clouds(path, fraction: float = 0.1):
    """(train points, train normals, val points, val normals, val names): [O, V, P, 3] arrays,
    split by object with the trainers' validation objects."""
    from omnihang_jax import data

    with np.load(path) as z:
        names = [str(n) for n in z["names"]]
        pts, nrm = z["points"], z["normals"].astype(np.float32)
    val = data.validation_objects(names, fraction)
    is_val = np.array([n in val for n in names])
    if is_val.all() or not is_val.any():
        raise ValueError(f"{path}: the validation split needs both kinds of objects ({len(names)})")
    return pts[~is_val], nrm[~is_val], pts[is_val], nrm[is_val], [n for n in names if n in val]


def make_batch(key, points, normals, batch: int, n: int, jitter: float):
    """Draw ``batch`` (object, view) clouds, ``n`` of their points, a uniform turn each:
    (turned points, turned normals, canonical points, rotations)."""
    k1, k2, k3, k4, k5 = jax.random.split(key, 5)
    o = jax.random.randint(k1, (batch,), 0, points.shape[0])
    v = jax.random.randint(k2, (batch,), 0, points.shape[1])
    idx = jax.vmap(lambda k: jax.random.choice(k, points.shape[2], (n,), replace=False))(
        jax.random.split(k3, batch)
    )
    p = jnp.take_along_axis(points[o, v], idx[..., None], axis=1)
    nr = jnp.take_along_axis(normals[o, v], idx[..., None], axis=1)
    rot = frame.random_rotations(k4, batch)
    turned = jnp.einsum("bij,bnj->bni", rot, p) + jitter * jax.random.normal(k5, p.shape)
    return turned, jnp.einsum("bij,bnj->bni", rot, nr), p, rot


def rotation_error_deg(chosen_rot, true_rot):
    """Angle (deg) of G R: 0 when the chosen hypothesis undoes the turn."""
    m = jnp.einsum("bij,bjk->bik", chosen_rot, true_rot)
    cos = (jnp.trace(m, axis1=1, axis2=2) - 1) / 2
    return jnp.degrees(jnp.arccos(jnp.clip(cos, -1, 1)))


def train(args) -> int:
    cfg = frame.FRAME_TINY if args.tiny else frame.FrameConfig(hypotheses=args.hypotheses)
    tc = TrainConfig(steps=args.steps, batch=args.batch, lr=args.lr, seed=args.seed,
                     eval_every=args.eval_every, jitter=args.jitter)  # fmt: skip
    tp, tn, vp, vn, val_names = load_clouds(args.clouds)
    print(f"train: {len(tp)} objects x {tp.shape[1]} views; validation: {len(vp)} objects")
    tp, tn, vp, vn = map(jnp.asarray, (tp, tn, vp, vn))
    net = frame.FrameNet(cfg)
    n = cfg.num_points
    params = net.init(jax.random.key(tc.seed), jnp.zeros((1, n, 3)), jnp.zeros((1, n, 3)))
    opt, sched = checkpoints.optimizer(tc)
    folder = Path(args.out)
    folder.mkdir(parents=True, exist_ok=True)
    state = dict(params=params, opt=opt.init(params), step=0, best=float("inf"), best_step=-1)
    state = checkpoints.open_run(folder, cfg, tc, state, "train_frame")

    @jax.jit
    def step_fn(params, opt_state, key, tp, tn):  # the clouds as arguments, not constants
        turned, nrm, canon, _ = make_batch(key, tp, tn, tc.batch, n, tc.jitter)

        def loss_fn(p):
            return frame.frame_loss(net.apply(p, turned, nrm), turned, canon)

        (loss, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, metrics

    # a fixed validation set: every validation object x 8 views x 4 turns, the same every time
    vkey = jax.random.key(12345)
    val_batches = [make_batch(jax.random.fold_in(vkey, i), vp, vn, 64, n, 0.0) for i in range(8)]

    @jax.jit
    def eval_fn(params, turned, nrm, canon, rot):
        out = net.apply(params, turned, nrm)
        _, metrics = frame.frame_loss(out, turned, canon)
        chosen = jnp.argmax(out.logits, axis=1)
        g = jnp.take_along_axis(out.rotation, chosen[:, None, None, None], axis=1)[:, 0]
        err = rotation_error_deg(g, rot)
        return {**metrics, "rot_err_deg_median": jnp.median(err),
                "within_20deg": jnp.mean(err < 20)}  # fmt: skip

    params, opt_state = state["params"], state["opt"]
    best, best_step = state["best"], state["best_step"]
    key = jax.random.key(tc.seed + 1)
    history = folder / "history.jsonl"
    t0 = time.time()
    for step in range(state["step"], tc.steps):
        if args.max_seconds and time.time() - t0 > args.max_seconds:
            print(f"train_frame: stopped at step {step} after {args.max_seconds} s (resumable)")
            break
        params, opt_state, loss, metrics = step_fn(
            params, opt_state, jax.random.fold_in(key, step), tp, tn
        )
        if not np.isfinite(float(loss)):
            raise FloatingPointError(f"train_frame: the loss is {float(loss)} at step {step}")
        if (step + 1) % tc.eval_every == 0 or step + 1 == tc.steps:
            vals = [jax.device_get(eval_fn(params, *b)) for b in val_batches]
            val = {k: round(float(np.mean([v[k] for v in vals])), 4) for k in vals[0]}
            row = dict(step=step + 1, loss=round(float(loss), 4), lr=float(sched(step)),
                       wall_s=round(time.time() - t0, 1),
                       train={k: round(float(v), 4) for k, v in metrics.items()},
                       validation=val)  # fmt: skip
            with history.open("a") as f:
                f.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)
            if val["chamfer_chosen_mm"] < best:
                best, best_step = val["chamfer_chosen_mm"], step + 1
                frame.save_frame(folder / "best", cfg, params,
                                 dict(step=best_step, validation=val,
                                      validation_objects=len(val_names)))  # fmt: skip
            checkpoints.save_checkpoint(folder, params, opt_state, step + 1, best, best_step)
    print(f"best validation Chamfer {best:.2f} mm at step {best_step}")
    if args.export:
        import shutil

        if best_step < 0:
            raise ValueError(f"{folder}: no evaluated step to export")
        shutil.copytree(folder / "best", args.export, dirs_exist_ok=True)
        shutil.copy(history, Path(args.export) / "history.jsonl")  # the validation curve
        print(f"exported the step-{best_step} network to {args.export}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("render", help="partial clouds of every training object")
    r.add_argument("--data", default="datasets/paper")
    r.add_argument("--views", type=int, default=24)
    r.add_argument("--camera-scale", type=float, default=0.5)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    r.add_argument("--out", default="out/frame/clouds.npz")
    t = sub.add_parser("train", help="train on turned copies (resumable)")
    t.add_argument("--clouds", default="out/frame/clouds.npz")
    t.add_argument("--steps", type=int, default=TrainConfig.steps)
    t.add_argument("--batch", type=int, default=TrainConfig.batch)
    t.add_argument("--lr", type=float, default=TrainConfig.lr)
    t.add_argument("--jitter", type=float, default=TrainConfig.jitter)
    t.add_argument("--eval-every", type=int, default=TrainConfig.eval_every)
    t.add_argument("--hypotheses", type=int, default=frame.FrameConfig.hypotheses)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--tiny", action="store_true", help="the test-size network")
    t.add_argument(
        "--max-seconds",
        type=float,
        default=0,
        help="stop (checkpointed, resumable) after this many seconds; 0: no limit",
    )
    t.add_argument("--out", default="out/frame/run")
    t.add_argument("--export", default=None, help="copy the best network here (weights/frame)")
    args = ap.parse_args(argv)
    return render(args) if args.cmd == "render" else train(args)


if __name__ == "__main__":
    _cli.run(main)
