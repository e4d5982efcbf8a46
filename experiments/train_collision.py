"""Train the collision estimators (the NCE and the HCE normal net) on the dataset's collision labels.

    python -m experiments.train_collision --data datasets/paper --out runs/collision \\
        --preset contact --train-pairs 200 --test-pairs 60 --time-budget nce=600,normals=120

1. Derives what the estimators need for the chosen pairs (``collision_data.derive_collision_pairs``,
   resumable, cached in ``DATA/derived/collision/<split>/``): the partial clouds with normals,
   the pair's collision poses with their labels, its stable poses and near-contact poses
   labelled on the full meshes. Training pairs come from the training split, evaluation pairs
   from the held-out split (a pair is held out when its object or its support is); training
   pairs with ``pair_index % --val-every == 0`` are validation pairs, never trained on.
2. Trains the NCE with cross entropy (random point subsets each step) on the dataset's poses
   labelled by the planner's ground truth (mesh penetration > 1 mm), ``--far-per-pair`` far
   free poses, the stable poses (free) and the moved near-contact poses (``--near-share`` of
   every batch), and the HCE normal net with the paper's ``-sum(n_hat . n)`` on object and
   support clouds, each under a time budget.
3. Chooses the NCE threshold on the validation pairs (``--goal-pass`` of their stable poses
   called free) and the HCE thresholds (predicted and true normals) on training labels (best
   balanced accuracy), then reports accuracy / precision / recall (positive = colliding) of
   all three estimators on held-out labels, with the clouds subsampled exactly as the planner
   does, and the NCE's near-contact metrics on held-out pairs.

Writes ``OUT/nce/`` and ``OUT/hce_normals/`` (``config.json`` + ``params.msgpack``),
``OUT/hce_true_normals.json`` (its threshold), ``OUT/metrics.json`` and the NCE's curves
(``OUT/nce_history.jsonl``, ``OUT/nce_curves.png``); prints the metrics. ``--resume`` starts
from the weights already in OUT.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from omnihang_jax import collision
from omnihang_jax.collision_data import (
    NEAR_KINDS,
    NEAR_STABLE,
    NEAR_TRANSIT,
    CollisionData,
    derive_collision_pairs,
    load_collision_data,
)

T_IMPORT = time.time()  # the phases' clock (train_collision's start)
SUBSET_SEED_OBJECT, SUBSET_SEED_SUPPORT = 0, 1  # the planner's fixed cloud subsets


# ----------------------------------------------------------------------------------------------
# Training


def _sample_points(key, clouds, n):
    """clouds [B, K, 3] -> [B, n, 3] random rows (with replacement) of each cloud."""
    idx = jax.random.randint(key, (clouds.shape[0], n), 0, clouds.shape[1])
    return jnp.take_along_axis(clouds, idx[..., None], axis=1)


def train_nce(
    data: CollisionData,
    config: collision.NCEConfig,
    steps: int,
    time_budget: float,
    batch: int = 64,
    learning_rate: float = 1e-3,
    seed: int = 0,
    params=None,
    progress: bool = True,
    stop_at: float | None = None,
    near_share: float = 0.0,
    schedule: str = "constant",
    val: CollisionData | None = None,
    val_every: int = 0,
    val_labels: int = 8192,
) -> tuple[dict, dict]:
    """Cross entropy on (pair, pose, label) triples. Returns (params, log). ``stop_at``: a
    unix time training stops at, whatever the budget (initialisation and compilation
    included).

    ``near_share``: this fraction of every batch is drawn from the near-contact training poses
    (``CollisionData.far_near``; the rest uniformly from all rows), so that the millimetres
    around the goals, where the planner's last edges run, get more of the training.
    ``schedule``: "constant" (the paper's Adam at ``learning_rate``) or "cosine" (a linear
    warm-up over the first 3 % of the time budget, then cosine decay to 5 % of the rate at
    its end: the budget, not a step count, is what a device call fixes).
    ``val`` (pairs never trained on) with ``val_every`` > 0: every ``val_every`` steps the
    loss and accuracy on a fixed set of at most ``val_labels`` of their labelled poses (half
    near-contact poses, planner labels; half dataset poses), with the planner's fixed cloud
    subsets, go to ``log["val_history"]``."""
    nets = collision.make_nce(config)
    key = jax.random.key(seed)
    key, init_key = jax.random.split(key)
    params = nets.init(init_key) if params is None else params
    opt = optax.inject_hyperparams(optax.adam)(learning_rate=learning_rate)
    opt_state = opt.init(params)
    obj_clouds = jnp.asarray(data.object_points)
    sup_clouds = jnp.asarray(data.support_points)
    pair, poses, labels = data.pair, data.poses, data.labels
    near_rows = np.zeros(0, np.int64)
    if data.far_poses is not None:  # far / stable (free) and near-contact poses
        if data.far_near is not None:
            near_rows = len(pair) + np.flatnonzero(data.far_near)
        pair = np.concatenate([pair, data.far_pair])
        poses = np.concatenate([poses, data.far_poses])
        labels = np.concatenate([labels, data.far_labels])
    n_near = int(round(near_share * batch)) if len(near_rows) else 0
    if near_share > 0 and not n_near:
        print("warning: --near-share without near-contact training poses: uniform batches")
    near_rows = jnp.asarray(near_rows if n_near else np.zeros(1, np.int64))
    pair, poses = jnp.asarray(pair), jnp.asarray(poses)
    labels = jnp.asarray(labels, jnp.float32)

    @jax.jit
    def step(params, opt_state, key):
        k_pick, k_near, k_obj, k_sup = jax.random.split(key, 4)
        pick = jax.random.randint(k_pick, (batch - n_near,), 0, labels.shape[0])
        if n_near:
            near = near_rows[jax.random.randint(k_near, (n_near,), 0, near_rows.shape[0])]
            pick = jnp.concatenate([pick, near])
        p = pair[pick]
        obj = _sample_points(k_obj, obj_clouds[p], config.object_input)
        sup = _sample_points(k_sup, sup_clouds[p], config.support_input)

        def loss_fn(params):
            logits = nets.apply(params, obj, sup, poses[pick])
            loss = optax.sigmoid_binary_cross_entropy(logits, labels[pick]).mean()
            return loss, jnp.mean((logits > 0) == (labels[pick] > 0.5))

        (loss, acc), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, acc

    lr_at = None
    if schedule == "cosine":
        lr_at = functools.partial(warmup_cosine, peak=learning_rate)
    elif schedule != "constant":
        raise ValueError(f"schedule must be 'constant' or 'cosine', got {schedule!r}")
    evaluate = None
    if val is not None and val_every > 0:
        evaluate = _validation_fn(nets, config, val, val_labels, seed)
    params, log = _loop(
        step, params, opt_state, key, steps, time_budget, batch, "nce", progress, stop_at,
        lr_at=lr_at, evaluate=evaluate, eval_every=val_every,
    )  # fmt: skip
    log |= dict(near_share=n_near / batch, schedule=schedule, peak_lr=learning_rate)
    return params, log


def warmup_cosine(frac: float, peak: float, warmup: float = 0.03, final: float = 0.05) -> float:
    """The learning rate at ``frac`` (0..1) of a run: linear warm-up from 10 % of ``peak``
    over the first ``warmup`` of it, then cosine decay to ``final`` x ``peak`` at its end."""
    frac = min(max(frac, 0.0), 1.0)
    if frac < warmup:
        return peak * (0.1 + 0.9 * frac / warmup)
    t = (frac - warmup) / (1.0 - warmup)
    return peak * (final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * t)))


def validation_rows(val: CollisionData, max_labels: int, seed: int = 0):
    """A fixed validation set: (pair [V], poses [V, 7], labels [V] bool, near [V] bool), at
    most ``max_labels`` rows, half near-contact poses (planner labels; not the transit ones)
    where the files have them, the rest dataset poses."""
    rng = np.random.default_rng([seed, 7])
    kinds = np.zeros(0, np.int8) if val.near_kind is None else val.near_kind
    pool = np.flatnonzero(kinds != NEAR_TRANSIT)
    n_near = min(len(pool), max_labels // 2)
    near = np.sort(pool[rng.choice(len(pool), n_near, False)]) if n_near else np.zeros(0, int)
    n_data = min(len(val.labels), max_labels - n_near)
    rows = np.sort(rng.choice(len(val.labels), n_data, False))
    has = val.near_poses is not None
    pair = np.concatenate([val.pair[rows], val.near_pair[near] if has else []])
    poses = np.concatenate([val.poses[rows], val.near_poses[near] if has else np.zeros((0, 7))])
    labels = np.concatenate([val.labels[rows], val.near_labels[near] if has else []])
    is_near = np.concatenate([np.zeros(n_data, bool), np.ones(n_near, bool)])
    return pair.astype(np.int32), poses.astype(np.float32), labels.astype(bool), is_near


def _validation_fn(nets, config, val: CollisionData, max_labels: int, seed: int):
    """evaluate(params) -> dict of the validation loss / accuracy (all rows and near-contact
    rows) on :func:`validation_rows`, with the planner's fixed cloud subsets."""
    pair, poses, labels, is_near = validation_rows(val, max_labels, seed)
    obj, sup = zip(
        *(
            planner_clouds(o, s, config.object_input, config.support_input)
            for o, s in zip(val.object_points, val.support_points)
        )
    )
    obj, sup = jnp.asarray(np.stack(obj)), jnp.asarray(np.stack(sup))
    chunk = 1024
    pad = (-len(pair)) % chunk
    pair_p = jnp.asarray(np.concatenate([pair, np.repeat(pair[:1], pad)]))
    poses_p = jnp.asarray(np.concatenate([poses, np.repeat(poses[:1], pad, 0)]))

    @jax.jit
    def logits_of(params, p, x):
        return nets.apply(params, obj[p], sup[p], x)

    y = labels.astype(np.float32)

    def evaluate(params) -> dict:
        logits = np.concatenate(
            [
                np.asarray(logits_of(params, pair_p[a : a + chunk], poses_p[a : a + chunk]))
                for a in range(0, len(pair_p), chunk)
            ]
        )[: len(pair)]
        loss = np.asarray(optax.sigmoid_binary_cross_entropy(logits, y))
        right = (logits > 0) == labels
        out = dict(val_loss=float(loss.mean()), val_accuracy=float(right.mean()))
        if is_near.any():
            out |= dict(
                val_near_loss=float(loss[is_near].mean()),
                val_near_accuracy=float(right[is_near].mean()),
            )
        return out

    return evaluate


def train_normals(
    data: CollisionData,
    config: collision.NormalNetConfig,
    steps: int,
    time_budget: float,
    batch: int = 16,
    learning_rate: float = 1e-3,
    seed: int = 1,
    params=None,
    progress: bool = True,
    stop_at: float | None = None,
) -> tuple[dict, dict]:
    """The paper's normal loss on object and support clouds alike. Returns (params, log)."""
    nets = collision.make_normal_net(config)
    key = jax.random.key(seed)
    key, init_key = jax.random.split(key)
    params = nets.init(init_key) if params is None else params
    opt = optax.adam(learning_rate)
    opt_state = opt.init(params)
    points = jnp.asarray(np.concatenate([data.object_points, data.support_points]))
    normals = jnp.asarray(np.concatenate([data.object_normals, data.support_normals]))

    @jax.jit
    def step(params, opt_state, key):
        k_pick, k_pts = jax.random.split(key)
        pick = jax.random.randint(k_pick, (batch,), 0, points.shape[0])
        idx = jax.random.randint(k_pts, (batch, config.points), 0, points.shape[1])
        pts = jnp.take_along_axis(points[pick], idx[..., None], axis=1)
        nrm = jnp.take_along_axis(normals[pick], idx[..., None], axis=1)

        def loss_fn(params):
            pred = nets.apply(params, pts)
            return collision.normal_loss(pred, nrm), jnp.mean(jnp.sum(pred * nrm, -1))

        (loss, cos), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, cos

    return _loop(
        step, params, opt_state, key, steps, time_budget, batch, "normals", progress, stop_at
    )


def _loop(
    step, params, opt_state, key, steps, time_budget, batch, name, progress, stop_at=None,
    lr_at=None, evaluate=None, eval_every=0,
):  # fmt: skip
    """Run ``step`` until ``steps`` or the time budget. ``lr_at(frac)``: the learning rate at
    this fraction of the budget (an ``optax.inject_hyperparams`` state); ``evaluate(params)``
    every ``eval_every`` steps (and at the end) -> a dict logged in ``val_history``."""
    t_compile = time.perf_counter()
    key, k = jax.random.split(key)

    def set_lr(frac):
        if lr_at is not None:
            opt_state.hyperparams["learning_rate"] = jnp.asarray(lr_at(frac), jnp.float32)

    set_lr(0.0)
    params, opt_state, loss, metric = step(params, opt_state, k)
    jax.block_until_ready(loss)
    compile_s = time.perf_counter() - t_compile
    t0 = time.perf_counter()
    history, val_history = [], []
    done = 1
    bar = tqdm(total=steps, desc=f"train {name}", disable=not progress)
    bar.update(1)
    losses, metrics = [], []
    if stop_at is not None:  # the budget, or less if the wall clock says so
        time_budget = min(time_budget, stop_at - time.time())

    def validate():
        if evaluate is not None:
            t = time.perf_counter()
            row = dict(step=done, seconds=round(t - t0, 1), **evaluate(params))
            val_history.append(row)
            print(f"{name} validation at step {done}: " + json.dumps(row), flush=True)
            return time.perf_counter() - t  # not counted against the training budget
        return 0.0

    paused = validate()
    while (
        done < steps
        and time.perf_counter() - t0 - paused < time_budget
        and (stop_at is None or time.time() < stop_at)
    ):
        set_lr((time.perf_counter() - t0 - paused) / max(time_budget, 1e-9))
        key, k = jax.random.split(key)
        params, opt_state, loss, metric = step(params, opt_state, k)
        losses.append(loss)
        metrics.append(metric)
        done += 1
        bar.update(1)
        if done % 50 == 0:
            mean_loss = float(jnp.mean(jnp.stack(losses)))
            mean_metric = float(jnp.mean(jnp.stack(metrics)))
            history.append((done, mean_loss, mean_metric))
            bar.set_postfix(loss=f"{mean_loss:.3f}", metric=f"{mean_metric:.3f}")
            losses, metrics = [], []
        if eval_every and done % eval_every == 0:
            paused += validate()
    jax.block_until_ready(params)
    if evaluate is not None and (not val_history or val_history[-1]["step"] != done):
        paused += validate()
    bar.close()
    seconds = time.perf_counter() - t0 - paused
    log = dict(
        steps=done,
        batch=batch,
        train_s=round(seconds, 1),
        compile_s=round(compile_s, 1),
        samples_per_s=round((done - 1) * batch / max(seconds, 1e-9), 1),
        history=history,
    )
    if evaluate is not None:
        log["val_history"] = val_history
    return params, log


def write_curves(out: Path, log: dict) -> None:
    """Append this call's NCE log to ``OUT/nce_history.jsonl`` (one line per training call:
    a resumed job keeps every call's curve) and draw all calls, steps counted on, into
    ``OUT/nce_curves.png``: training loss and, where measured, validation loss (all rows,
    near-contact rows)."""
    with open(out / "nce_history.jsonl", "a") as f:
        f.write(json.dumps(log) + "\n")
    calls = [json.loads(line) for line in open(out / "nce_history.jsonl") if line.strip()]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    offset = 0
    for i, call in enumerate(calls):
        hist = np.asarray(call.get("history") or np.zeros((0, 3)), float).reshape(-1, 3)
        ax.plot(offset + hist[:, 0], hist[:, 1], "C0", lw=1, label="train" if i == 0 else None)
        val = call.get("val_history") or []
        if val:
            steps = offset + np.array([r["step"] for r in val])
            ax.plot(steps, [r["val_loss"] for r in val], "C1o-", ms=3,
                    label="validation" if i == 0 else None)  # fmt: skip
            if "val_near_loss" in val[0]:
                ax.plot(steps, [r["val_near_loss"] for r in val], "C2s--", ms=3,
                        label="validation, near contact" if i == 0 else None)  # fmt: skip
        if i:
            ax.axvline(offset, color="0.7", lw=0.8)
        offset += int(call.get("steps", 0))
    ax.set_xlabel("NCE step (calls joined; grey: a resumed call)")
    ax.set_ylabel("cross entropy")
    ax.set_yscale("log")
    ax.legend()
    ax.set_title("NCE training")
    fig.tight_layout()
    fig.savefig(out / "nce_curves.png", dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------------------------
# Evaluation on labels


def planner_clouds(object_points, support_points, n_object: int, n_support: int):
    """The fixed cloud subsets every estimator sees at planning time."""
    return (
        collision.subsample_cloud(object_points, n_object, SUBSET_SEED_OBJECT),
        collision.subsample_cloud(support_points, n_support, SUBSET_SEED_SUPPORT),
    )


def score_poses(data: CollisionData, pair, poses, score_fn, n_object, n_support) -> np.ndarray:
    """Scores [L] of ``poses`` [L, 7] of pairs ``pair`` [L], pair by pair, with the planner's
    cloud subsets. score_fn(pair_index, object_cloud, support_cloud, poses) -> [B]."""
    scores = np.zeros(len(pair))
    for p in np.unique(pair):
        rows = np.flatnonzero(pair == p)
        oc, sc = planner_clouds(data.object_points[p], data.support_points[p], n_object, n_support)
        for a in range(0, len(rows), 512):  # chunks padded to 512: one compilation
            r = rows[a : a + 512]
            chunk = poses[r]
            padded = np.concatenate([chunk, np.repeat(chunk[:1], 512 - len(r), 0)])
            scores[r] = np.asarray(score_fn(p, oc, sc, padded))[: len(r)]
    return scores


def estimator_scores(
    data: CollisionData, score_fn, n_object, n_support, max_labels=None, seed=0, max_pairs=None
):
    """Scores of (a random subset of at most ``max_labels``) labelled poses, pair by pair (of
    the first ``max_pairs`` pairs only: one call per pair and chunk, so thousands of pairs
    cost minutes). score_fn(pair_index, object_cloud, support_cloud, poses) -> [B].
    Returns (scores, labels)."""
    chosen = np.arange(len(data.labels))
    if max_pairs is not None:
        chosen = chosen[data.pair < max_pairs]
    if max_labels is not None and max_labels < len(chosen):
        chosen = np.sort(np.random.default_rng(seed).choice(len(chosen), max_labels, False))
    scores = score_poses(data, data.pair[chosen], data.poses[chosen], score_fn, n_object, n_support)
    return scores, data.labels[chosen]


def near_metrics(scores: np.ndarray, data: CollisionData, threshold: float) -> dict:
    """What the planner needs near the goal, from the scores of ``data.near_poses``:
    ``goal_pass`` = fraction of stable poses called free (a hanging pose that is called
    colliding cannot be reached), and accuracy / precision / recall (positive = colliding
    deeper than 1 mm on the full meshes) of the moved near-contact poses, all of them and per
    kind (jitter: a few mm into or next to the support; approach: the straight line from the
    start; lift: above the hanging pose; transit: where the planner's paths pass the
    support). ``near`` leaves the transit poses out."""
    called = scores > threshold
    stable = data.near_kind == NEAR_STABLE
    moved = ~stable & (data.near_kind != NEAR_TRANSIT)
    out = dict(
        threshold=float(threshold),
        goal_pass=float(np.mean(~called[stable])) if stable.any() else float("nan"),
        stable_poses=int(stable.sum()),
        near=collision.binary_metrics(called[moved], data.near_labels[moved]),
    )
    for name, kind in NEAR_KINDS.items():
        rows = data.near_kind == kind
        out[name] = collision.binary_metrics(called[rows], data.near_labels[rows])
    return out


def goal_pass_threshold(
    scores: np.ndarray, data: CollisionData, target: float, lowest=0.5, highest=0.95
) -> float:
    """The lowest probability threshold in [lowest, highest] (steps of 0.01) at which at
    least ``target`` of the stable poses are called free (``highest`` if none): stable goals
    pass while as many near-contact collisions as possible stay detected."""
    stable = scores[data.near_kind == NEAR_STABLE]
    for t in np.arange(lowest, highest + 1e-9, 0.01):
        if np.mean(stable <= t) >= target:
            return round(float(t), 2)
    return float(highest)


def nce_score_fn(config, params):
    prob = jax.jit(collision.nce_probability(config))
    return lambda p, oc, sc, poses: prob(params, oc, sc, poses)


def hce_score_fn(config, params):
    """Predicted-normal heuristic: the normal net sees the planner's support subset."""
    normals_fn = jax.jit(
        lambda prm, pts: collision.make_normal_net(config).apply(prm, pts[None])[0]
    )
    score = jax.jit(collision.heuristic_score)
    cache = {}

    def fn(p, oc, sc, poses):
        if p not in cache:
            cache[p] = normals_fn(params, sc)
        return score(oc, sc, cache[p], poses)

    return fn


def true_normals_score_fn(data: CollisionData, n_support):
    score = jax.jit(collision.heuristic_score)

    def fn(p, oc, sc, poses):
        normals = collision.subsample_cloud(data.support_normals[p], n_support, SUBSET_SEED_SUPPORT)
        return score(oc, sc, normals, poses)

    return fn


def _budgets(text: str) -> dict[str, float]:
    out = {"nce": 300.0, "normals": 60.0}
    for item in filter(None, text.split(",")):
        name, _, value = item.partition("=")
        if name not in out:
            raise ValueError(f"--time-budget: unknown part {name!r} (nce, normals)")
        out[name] = float(value)
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add = parser.add_argument
    add("--data", default="datasets/paper", help="dataset (recipe.json + shards/)")
    add("--out", required=True, help="output folder for the weights")
    add("--preset", default="contact", choices=sorted(collision.NCE_PRESETS),
        help="NCE preset; the normal net's is collision.NORMAL_PRESETS[preset]")  # fmt: skip
    add("--train-pairs", type=int, default=200)
    add("--test-pairs", type=int, default=60)
    add("--steps", type=int, default=1_000_000, help="cap on steps per network")
    add("--time-budget", default="nce=300,normals=60",
        help="seconds per network (normals=0: no normal net, no HCE metrics)")  # fmt: skip
    add("--batch", type=int, default=64, help="NCE batch (poses)")
    add("--normal-batch", type=int, default=16, help="normal-net batch (clouds)")
    add("--lr", type=float, default=1e-3, help="Adam lr (the cosine's peak)")
    add("--lr-schedule", choices=["constant", "cosine"], default="cosine",
        help="NCE: constant, or warm-up + cosine decay over its time budget (train_nce)")  # fmt: skip
    add("--near-share", type=float, default=0.3,
        help="NCE: fraction of each batch drawn from the near-contact training poses")  # fmt: skip
    add("--far-per-pair", type=int, default=100,
        help="far free poses per training pair (collision_data.far_free_poses)")  # fmt: skip
    add("--val-curve-every", type=int, default=0,
        help="NCE: validation loss on the validation pairs every N steps (0: off)")  # fmt: skip
    add("--val-every", type=int, default=20,
        help="training-split pairs with pair_index %% N == 0 are not trained on: the NCE "
        "threshold is chosen on them (0: none, threshold 0.5)")  # fmt: skip
    add("--goal-pass", type=float, default=0.95,
        help="NCE threshold: the lowest in [0.5, 0.95] that calls this fraction of the "
        "validation pairs' stable poses free (0: keep 0.5)")  # fmt: skip
    add("--eval-labels", type=int, default=20000, help="held-out labels scored")
    add("--threshold-labels", type=int, default=20000, help="training labels")
    add("--threshold-pairs", type=int, default=400, help="HCE thresholds: of these first pairs")
    add("--derived-dir", default=None, help="pair files (default: DATA/derived/collision)")
    add("--workers", type=int, default=1, help="derive processes (0 = all cores)")
    add("--resume", action="store_true", help="start from the weights in OUT")
    add("--derive-only", action="store_true", help="derive the pairs, then stop")
    add("--existing-only", action="store_true", help="use only pairs already derived")
    add("--deadline", type=float, default=0.0,
        help="unix time by which everything must be written: the NCE trains for what is left "
        "after loading, compilation and the reserves (0: --time-budget only)")  # fmt: skip
    add("--post-reserve-s", type=float, default=60.0, help="--deadline: after the NCE trains")
    add("--compile-reserve-s", type=float, default=45.0, help="--deadline: per compilation")
    add("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    progress = not args.no_progress
    budgets = _budgets(args.time_budget)
    train_normal_net = budgets["normals"] > 0
    phases: list = []

    def phase(name: str) -> None:  # wall-clock log of the phases (stdout, flushed)
        seconds = round(time.time() - T_IMPORT, 1)
        phases.append((name, seconds))
        print(f"[{seconds} s since start] {name}", flush=True)

    workers = args.workers or len(os.sched_getaffinity(0))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    nce_cfg = collision.NCE_PRESETS[args.preset]
    normal_cfg = collision.NORMAL_PRESETS[args.preset]

    t0 = time.time()
    files = derive_collision_pairs(
        args.data,
        {"test": args.test_pairs, "train": args.train_pairs},  # held-out first: a cut-short
        workers,  # derive still has them all
        progress,
        out_dir=args.derived_dir,
        existing_only=args.existing_only,
    )
    train_files, test_files = files["train"], files["test"]
    val_files = []
    if args.val_every > 0:
        val_files = [f for f in train_files if int(f.stem.split("_")[0]) % args.val_every == 0]
        train_files = [f for f in train_files if f not in set(val_files)]
    derive_s = time.time() - t0
    if args.derive_only:
        print(
            f"derived: {len(train_files)} train, {len(test_files)} test pairs in {derive_s:.0f} s"
        )
        return {"train_files": len(train_files), "test_files": len(test_files)}
    train = load_collision_data(
        train_files, far_per_pair=args.far_per_pair, training=True, planner_labels=True
    )
    test = load_collision_data(test_files)
    # the validation curve measures the training objective: the same labels as training
    # (the threshold and the metrics below read the near-contact poses, labelled either way)
    val = load_collision_data(val_files, planner_labels=True) if val_files else None
    held_out = {m["pair_index"] for m in test.meta}
    if val is not None:
        held_out |= {m["pair_index"] for m in val.meta}
    if held_out & {m["pair_index"] for m in train.meta} or any(
        m["split"] != "train" for m in train.meta
    ):
        raise RuntimeError("a held-out (or validation) pair reached the training set")
    print(
        f"pairs: {len(train.meta)} train ({len(train.labels)} labels, "
        f"{train.labels.mean():.1%} colliding), {len(test.meta)} held out "
        f"({len(test.labels)} labels), {len(val_files)} validation pairs; "
        f"{0 if train.far_labels is None else len(train.far_labels)} extra training poses "
        f"({args.far_per_pair} far free per pair, stable, near contact); "
        f"derived in {derive_s:.0f} s; device {jax.devices()[0]}"
    )

    phase("loaded")
    nce_params = normal_params = None
    if args.resume and (out / "nce" / "config.json").exists():
        nce_cfg, nce_params, _ = collision.load_estimator(out / "nce")
    if args.resume and (out / "hce_normals" / "config.json").exists():
        normal_cfg, normal_params, _ = collision.load_estimator(out / "hce_normals")

    # the NCE's training time: what --deadline leaves after loading (measured), compilation
    # and what must follow (NCE threshold + held-out metrics, then the normal net and HCEs)
    nce_budget = budgets["nce"]
    after = args.post_reserve_s + (budgets["normals"] if train_normal_net else 0.0)
    if args.deadline:
        nce_budget = min(nce_budget, args.deadline - time.time() - args.compile_reserve_s - after)
        if nce_budget < 1:
            raise SystemExit(
                f"--deadline leaves no time to train the NCE ({nce_budget:.0f} s after loading; "
                f"reserves: compile {args.compile_reserve_s:.0f} s, after {after:.0f} s)"
            )
        print(
            f"NCE time budget {nce_budget:.0f} s (deadline in {args.deadline - time.time():.0f} s)"
        )
    nce_params, nce_log = train_nce(
        train, nce_cfg, args.steps, nce_budget, args.batch, args.lr, params=nce_params,
        progress=progress, stop_at=args.deadline - after if args.deadline else None,
        near_share=args.near_share, schedule=args.lr_schedule,
        val=val if args.val_curve_every > 0 else None, val_every=args.val_curve_every,
    )  # fmt: skip
    collision.save_estimator(out / "nce", nce_cfg, nce_params, train=nce_log, evaluated=False)
    write_curves(out, nce_log)
    phase(f"NCE trained ({nce_log['steps']} steps, compiled in {nce_log['compile_s']} s)")

    # the NCE threshold: stable goals of validation pairs pass (near_metrics, --goal-pass)
    n_obj, n_sup = nce_cfg.object_input, nce_cfg.support_input
    nce_fn = nce_score_fn(nce_cfg, nce_params)
    validation = {}
    if val is not None and args.goal_pass > 0 and val.near_poses is not None:
        s = score_poses(val, val.near_pair, val.near_poses, nce_fn, n_obj, n_sup)
        threshold = goal_pass_threshold(s, val, args.goal_pass)
        validation = {
            "at_0.5": near_metrics(s, val, 0.5),
            "chosen": near_metrics(s, val, threshold),
        }
        nce_cfg = dataclasses.replace(nce_cfg, threshold=threshold)
    metrics = {}
    s, y = estimator_scores(test, nce_fn, n_obj, n_sup, args.eval_labels)
    metrics["nce"] = collision.binary_metrics(s > nce_cfg.threshold, y)
    metrics["nce_at_0.5"] = collision.binary_metrics(s > 0.5, y)
    near_held_out = {}
    if test.near_poses is not None:
        s = score_poses(test, test.near_pair, test.near_poses, nce_fn, n_obj, n_sup)
        near_held_out = {
            "nce": near_metrics(s, test, nce_cfg.threshold),
            "nce_at_0.5": near_metrics(s, test, 0.5),
        }
    summary = dict(
        device=str(jax.devices()[0]),
        train_pairs=len(train.meta),
        train_labels=int(len(train.labels)),
        test_pairs=len(test.meta),
        test_labels=int(len(test.labels)),
        derive_s=round(derive_s, 1),
        far_free_per_pair=args.far_per_pair,
        nce=nce_log,
        nce_threshold=nce_cfg.threshold,
        near_share=args.near_share,
        lr=args.lr,
        lr_schedule=args.lr_schedule,
        validation_pairs=len(val_files),
        validation=validation,
        held_out=metrics,
        held_out_near=near_held_out,
        phases=phases,
    )
    extra = dict(train_pairs=len(train.meta), held_out=metrics, held_out_near=near_held_out)
    collision.save_estimator(out / "nce", nce_cfg, nce_params, train=nce_log, **extra)
    with open(out / "metrics.json", "w") as f:  # written again below with the HCEs
        json.dump(summary, f, indent=2)
    phase("NCE threshold and held-out metrics")

    if train_normal_net:
        normal_budget = budgets["normals"]
        if args.deadline:  # what is left after compiling it and the HCE metrics
            normal_budget = min(
                normal_budget,
                args.deadline - time.time() - args.compile_reserve_s - args.post_reserve_s / 2,
            )
        if normal_budget < 1:
            print(f"skipped the normal net and the HCEs: {normal_budget:.0f} s left for them")
            train_normal_net = False
    if train_normal_net:
        normal_params, normal_log = train_normals(
            train, normal_cfg, args.steps, normal_budget, args.normal_batch, args.lr,
            params=normal_params, progress=progress,
            stop_at=args.deadline - args.post_reserve_s / 2 if args.deadline else None,
        )  # fmt: skip
        collision.save_estimator(
            out / "hce_normals", normal_cfg, normal_params, train=normal_log, evaluated=False
        )
        phase(f"normal net trained ({normal_log['steps']} steps)")
        # HCE thresholds on training labels, metrics on held-out labels
        h_obj, h_sup = nce_cfg.object_points, normal_cfg.points
        hce_train, y_train = estimator_scores(
            train, hce_score_fn(normal_cfg, normal_params), h_obj, h_sup,
            args.threshold_labels, max_pairs=args.threshold_pairs,
        )  # fmt: skip
        hce_threshold = collision.balanced_threshold(hce_train, y_train)
        true_train, y_true_train = estimator_scores(
            train, true_normals_score_fn(train, h_sup), h_obj, h_sup, args.threshold_labels,
            max_pairs=args.threshold_pairs,
        )  # fmt: skip
        true_threshold = collision.balanced_threshold(true_train, y_true_train)
        normal_cfg = dataclasses.replace(normal_cfg, threshold=hce_threshold)
        s, y = estimator_scores(
            test, hce_score_fn(normal_cfg, normal_params), h_obj, h_sup, args.eval_labels
        )
        metrics["hce"] = collision.binary_metrics(s > hce_threshold, y)
        s, y = estimator_scores(
            test, true_normals_score_fn(test, h_sup), h_obj, h_sup, args.eval_labels
        )
        metrics["hce_true_normals"] = collision.binary_metrics(s > true_threshold, y)
        summary |= dict(
            normals=normal_log, hce_threshold=hce_threshold,
            hce_true_normals_threshold=true_threshold,
        )  # fmt: skip
        collision.save_estimator(
            out / "hce_normals", normal_cfg, normal_params, train=normal_log, **extra
        )
        with open(out / "hce_true_normals.json", "w") as f:
            json.dump(dict(threshold=true_threshold, points=h_sup, held_out=metrics), f, indent=2)
        phase("HCE thresholds and held-out metrics")
    with open(out / "metrics.json", "w") as f:
        json.dump(summary, f, indent=2)
    for name, m in metrics.items():
        print(
            f"held-out {name}: accuracy {m['accuracy']:.3f} precision {m['precision']:.3f} "
            f"recall {m['recall']:.3f} balanced {m['balanced_accuracy']:.3f} (n={m['n']})"
        )
    for name, m in near_held_out.items():
        print(
            f"held-out near {name} (threshold {m['threshold']:.2f}): goal pass "
            f"{m['goal_pass']:.3f} of {m['stable_poses']} stable poses; near-contact accuracy "
            f"{m['near']['accuracy']:.3f} precision {m['near']['precision']:.3f} recall "
            f"{m['near']['recall']:.3f} free precision {m['near']['free_precision']:.3f} "
            f"(n={m['near']['n']}); jitter P/R {m['jitter']['precision']:.3f}/"
            f"{m['jitter']['recall']:.3f}"
        )
    return summary


if __name__ == "__main__":
    main()
