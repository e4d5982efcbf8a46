"""The answer's rankers: V fine-tuned on the pipeline's own refined candidates.

    # 1. pools (omnihang_jax.pools): the default pipeline's 60 refined candidates of training
    #    pairs, ranked by V, each simulated on the true meshes; resumable (GPU + CPU workers):
    python -m experiments.train_ranker pools --data datasets/paper --split train --pairs 4840 \\
        --out out/ranker/pools --workers 15
    python -m experiments.train_ranker pools --data datasets/paper --split validation \\
        --out out/ranker/val_pools --workers 15
    # 2. fine-tune V on them (pair files from DATA/derived/train):
    python -m experiments.train_ranker train --pools out/ranker/pools \\
        --val-pools out/ranker/val_pools --data datasets/paper --init weights/value \\
        --steps 2500 --out out/ranker/listwise

The committed rankers (``weights/rankers/*``, docs/where.md): ``listwise`` 2,500 steps on
4,840 pairs' pools; ``listwise_big`` 5,000 steps on 9,680 pairs with ``--seed 1``; ``near``
2,500 steps with ``--support-near 256 --object-near 256`` (each state's 512 points of a cloud
are 256 evenly spaced ones and the 256 nearest the other cloud). Every other option at its
default. Their pools held the 20 candidates of one view (K = 10, Stages 1 and 2 starts); the
pools here hold the default pipeline's 60 (three views).

Why: V was trained on perturbations and CEM's top members of half-resolution training clouds;
the answer is chosen among the pipeline's final candidates. A ranker is the same network (same
``ValueConfig``, so it plugs into ``PipelineConfig.rank_values``), started from V and fine-tuned
on exactly that decision, every candidate of a pair's pool labelled by the simulation, with

    L = list_weight * L_list + bce_weight * BCE

where ``L_list = logsumexp(s[clear]) - logsumexp(s[clear & stable])`` (s: the network's
log-odds) over the candidates the answer rule chooses among (no observed object point inside
the support, ``pools.RULE``), for pairs where both clear outcomes occur, and BCE keeps the
calibration on all candidates. V's optimiser (clipping, AdamW, warm-up + cosine) at this run's
learning rate; validation every ``--eval-every`` steps on the validation objects' pools (the
rule's success with the ranker against the pools' own V ranking); a resumable checkpoint;
curves.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import flax
import jax
import jax.numpy as jnp
import numpy as np
import optax

from experiments import _cli
from omnihang_jax import pools as pools_mod
from omnihang_jax import refine, stage3
from omnihang_jax.stage3 import PairClouds

# ----------------------------------------------------------------------------------------------
# Loss and scores (pure)


def ranking_loss(logits, stable, clear, list_weight: float, bce_weight: float):
    """logits [B, P, 2], stable / clear [B, P] bool -> (loss, metrics). The listwise term
    counts only pairs with a clear stable and a clear unstable candidate."""
    s = logits[..., 1] - logits[..., 0]
    logp = jax.nn.log_softmax(logits, axis=-1)
    ce = -jnp.where(stable, logp[..., 1], logp[..., 0])
    pos = clear & stable
    mixed = jnp.any(pos, -1) & jnp.any(clear & ~stable, -1)
    neg_inf = jnp.finfo(s.dtype).min
    lse_all = jax.nn.logsumexp(jnp.where(clear, s, neg_inf), axis=-1)
    lse_pos = jax.nn.logsumexp(jnp.where(pos, s, neg_inf), axis=-1)
    per_pair = jnp.where(mixed, lse_all - lse_pos, 0.0)
    n_mixed = jnp.maximum(mixed.sum(), 1)
    l_list = per_pair.sum() / n_mixed
    loss = list_weight * l_list + bce_weight * ce.mean()
    # the rule's pick among the clear candidates (by s) hangs?
    key = jnp.where(clear, s, neg_inf)
    pick = jnp.argmax(key, axis=-1)
    hit = jnp.take_along_axis(stable, pick[:, None], axis=-1)[:, 0]
    return loss, {
        "loss": loss,
        "listwise": l_list,
        "bce": ce.mean(),
        "mixed_pairs": mixed.mean(),
        "pick_hangs_mixed": jnp.sum(hit & mixed) / n_mixed,
    }


def make_scorer(config):
    """jitted ``(params, clouds [B, ...] subsampled, poses [B, P, 7]) -> [B, P]`` log P(hang)."""
    value = stage3.make_value(config)
    return jax.jit(jax.vmap(value.score, in_axes=(None, 0, 0)))


def load_bank(pools: dict, data: str, config, progress: bool) -> refine.PairBank:
    """The pools' pairs' clouds (DATA/derived/train), subsampled for ``config``, in pool order."""
    from omnihang_jax import dataset_bridge

    _, derived = dataset_bridge.resolve_dataset_dir(data)
    files = [Path(derived) / "train" / str(f) for f in pools["pair_file"]]
    missing = [f for f in files if not f.exists()]
    if missing:
        raise FileNotFoundError(
            f"{len(missing)} pair files of the pools missing (e.g. {missing[0]}): derive them "
            "(python -m experiments.derive_dataset --split train)"
        )
    return refine.PairBank.from_files(files, config, progress=progress)


def score_pools(scorer, params, bank: refine.PairBank, poses: np.ndarray, batch: int):
    """[N, C] log P(hang) of every pooled candidate ``poses`` [N, C, 7] (pairs in bank order)."""
    n = len(poses)
    out = np.zeros(poses.shape[:2], np.float32)
    for i in range(0, n, batch):
        sl = np.arange(i, min(i + batch, n))
        m = len(sl)
        sl = np.concatenate([sl, np.repeat(sl[:1], batch - m)])  # one compiled shape
        clouds = PairClouds(*(jnp.asarray(x[sl]) for x in bank.clouds))
        out[i : i + m] = np.asarray(scorer(params, clouds, jnp.asarray(poses[sl])))[:m]
    return out


def ordered(scores: np.ndarray, stable: np.ndarray, clear: np.ndarray) -> float:
    """Of the (stable, unstable) pairs of clear candidates of a pool, the share ``scores`` [N, C]
    order stable first (%), mean over the pools that hold both (what the listwise term asks)."""
    both = (stable & clear)[:, :, None] & (~stable & clear)[:, None, :]
    right = (scores[:, :, None] > scores[:, None, :]) & both
    n = both.sum((1, 2))
    return 100.0 * float(np.mean(right.sum((1, 2))[n > 0] / n[n > 0])) if (n > 0).any() else 0.0


def score_variants(pools: dict, ranker_logp: np.ndarray) -> dict:
    """The rule's success (mean over categories, %) with the pools' own ranking (V, the
    pipeline the pools come from) and with the ranker; how often some candidate hangs; the
    clear (stable, unstable) pairs the ranker orders right."""
    clear = pools["counts"] <= pools_mod.RULE.max_points
    return {
        "pool_v": pools_mod.rule_success(pools, pools["keys"])["mean"],
        "ranker": pools_mod.rule_success(pools, ranker_logp)["mean"],
        "any_stable": 100.0 * float(np.mean(pools["stable"].any(1))),
        "ordered": ordered(ranker_logp, pools["stable"], clear),
    }


# ----------------------------------------------------------------------------------------------
# Training


def train(args) -> dict:
    from sim import atomic

    t_start = time.time()  # the time budget counts the loading too
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    table = pools_mod.read_pools(args.pools)
    val = pools_mod.read_pools(args.val_pools) if args.val_pools else None
    if val is not None and set(val["pair_index"]) & set(table["pair_index"]):
        raise ValueError("the validation pools share pairs with the training pools")
    config, init_params = refine.load_value(args.init)
    # the state's near points (stage3.near_points): same encoder and head, so V's weights start it
    config = dataclasses.replace(config, support_near=args.support_near,
                                 object_near=args.object_near, near_pool=args.near_pool)  # fmt: skip
    progress = not args.no_progress
    n_pairs = len(table["pair_file"])
    if args.pairs_per_batch > n_pairs:
        raise ValueError(f"--pairs-per-batch {args.pairs_per_batch} > {n_pairs} pooled pairs")
    val_bank = load_bank(val, args.data, config, progress) if val else None
    clear = table["counts"] <= pools_mod.RULE.max_points
    print(f"{n_pairs} training pairs, {table['poses'].shape[1]} candidates each; validation "
          f"pairs {0 if val is None else len(val['pair_file'])}", flush=True)  # fmt: skip

    # V's own optimiser (clipping, AdamW, warm-up + cosine) with this run's lr and warm-up
    run_config = dataclasses.replace(config, learning_rate=args.lr, warmup_steps=args.warmup)
    schedule = refine.make_schedule(run_config, args.steps)
    tx = refine.make_optimizer(run_config, args.steps)
    net = stage3.make_value(config)
    bank = load_bank(table, args.data, config, progress)
    bank_dev = jax.tree.map(jnp.asarray, bank.clouds)
    poses_dev = jnp.asarray(table["poses"])
    stable_dev, clear_dev = jnp.asarray(table["stable"]), jnp.asarray(clear)

    def loss_fn(params, slots, key):
        clouds = jax.tree.map(lambda x: x[slots], bank_dev)
        poses = poses_dev[slots]
        b, p = poses.shape[:2]
        tiled = jax.tree.map(lambda x: jnp.repeat(x, p, axis=0), clouds)
        logits = net.logits(params, tiled, poses.reshape(b * p, 7), key).reshape(b, p, 2)
        return ranking_loss(logits, stable_dev[slots], clear_dev[slots],
                            args.list_weight, args.bce_weight)  # fmt: skip

    @jax.jit
    def step(params, opt_state, slots, key):
        (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, slots, key)
        updates, opt_state = tx.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, metrics

    scorer = make_scorer(config)
    ckpt = out / "checkpoint.msgpack"
    params, opt_state, start = init_params, tx.init(init_params), 0
    if ckpt.exists():  # resume
        blob = flax.serialization.from_bytes(
            {"params": params, "opt_state": opt_state, "step": 0}, ckpt.read_bytes()
        )
        params, opt_state, start = blob["params"], blob["opt_state"], int(blob["step"])
        print(f"resumed at step {start}", flush=True)
    metrics_path, val_path = out / "metrics.jsonl", out / "val_metrics.jsonl"

    def validate(params, step_i):
        if val is None:
            return None
        logp = score_pools(scorer, params, val_bank, val["poses"], args.score_batch)
        res = {"step": step_i, **score_variants(val, logp)}
        with open(val_path, "a") as f:
            f.write(json.dumps(res) + "\n")
        print(f"[val] step {step_i}: " + json.dumps(res), flush=True)
        return res

    if start == 0:
        for p in (metrics_path, val_path):
            p.unlink(missing_ok=True)
        validate(params, 0)
    rng = np.random.default_rng(args.seed + start)
    key = jax.random.fold_in(jax.random.key(args.seed), start)
    t0, t_budget = time.time(), args.time_budget
    i = start
    for i in range(start, args.steps):
        slots = jnp.asarray(rng.choice(n_pairs, args.pairs_per_batch, replace=False))
        params, opt_state, m = step(params, opt_state, slots, jax.random.fold_in(key, i))
        if (i + 1) % args.log_every == 0:
            row = {"step": i + 1, "lr": float(schedule(i)), **{k: float(v) for k, v in m.items()},
                   "seconds": time.time() - t0}  # fmt: skip
            with open(metrics_path, "a") as f:
                f.write(json.dumps(row) + "\n")
        last = i + 1 == args.steps or (t_budget and time.time() - t_start > t_budget)
        if (i + 1) % args.eval_every == 0 or last:
            validate(params, i + 1)
            blob = flax.serialization.to_bytes(
                {"params": params, "opt_state": opt_state, "step": i + 1}
            )
            atomic.write_atomic(ckpt, lambda f, blob=blob: f.write(blob))
        if last:
            break
    done = i + 1 if args.steps > start else start
    refine.save_value(out / "value", config, params, note=(
        f"ranker: {args.init} fine-tuned {done} steps on the pools of {n_pairs} training "
        "pairs (experiments.train_ranker)"))  # fmt: skip
    plot_curves(out)
    summary = {"steps": done, "seconds": time.time() - t0, "args": vars(args),
               "training_pairs": n_pairs,
               "validation": [json.loads(line) for line in open(val_path)] if val else []}  # fmt: skip
    refine.write_json(out / "summary.json", summary)
    return summary


def plot_curves(out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def rows_of(name):
        path = out / name
        return [json.loads(line) for line in open(path)] if path.exists() else []

    rows, val = rows_of("metrics.jsonl"), rows_of("val_metrics.jsonl")
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    if rows:
        st = [r["step"] for r in rows]
        for k in ("loss", "listwise", "bce"):
            ax[0].plot(st, [r[k] for r in rows], label=f"train {k}")
        ax[0].set_xlabel("step")
        ax[0].legend()
    if val:
        st = [r["step"] for r in val]
        for k in ("pool_v", "ranker"):
            ax[1].plot(st, [r[k] for r in val], marker="o", label=k)
        ax[1].set_xlabel("step")
        ax[1].set_ylabel("answer rule's success, validation objects (%)")
        ax[1].legend()
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=100)
    plt.close(fig)


# ----------------------------------------------------------------------------------------------
# CLI


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    po = sub.add_parser("pools", help="the pipeline's simulated candidates of training pairs")
    po.add_argument("--data", default="datasets/paper", help="dataset (recipe.json, derived/)")
    po.add_argument("--split", default="train", choices=("train", "validation"),
                    help="training objects, or the validation objects")  # fmt: skip
    po.add_argument("--pairs", type=int, default=None, help="at most this many (balanced)")
    po.add_argument("--out", required=True, help="folder of shards (resumable)")
    po.add_argument("--seed", type=int, default=0, help="the answer's seed")
    po.add_argument("--batch", type=int, default=8, help="pairs per network call")
    po.add_argument("--workers", type=int, default=0, help="simulation processes (0: here)")
    po.add_argument("--shard-pairs", type=int, default=64, help="pairs per shard")
    po.add_argument("--no-progress", action="store_true")
    tr = sub.add_parser("train", help="fine-tune V as a ranker on pools")
    tr.add_argument("--pools", nargs="+", required=True, help="pool folders or shards")
    tr.add_argument("--val-pools", nargs="*", default=None, help="validation objects' pools")
    tr.add_argument("--data", default="datasets/paper", help="dataset with derived/train/")
    tr.add_argument("--init", default="weights/value", help="V to start from")
    tr.add_argument("--out", required=True)
    tr.add_argument("--steps", type=int, default=2500)
    tr.add_argument("--pairs-per-batch", type=int, default=16)
    tr.add_argument("--lr", type=float, default=1e-4)
    tr.add_argument("--warmup", type=int, default=100)
    tr.add_argument("--list-weight", type=float, default=1.0)
    tr.add_argument("--bce-weight", type=float, default=0.5)
    tr.add_argument("--eval-every", type=int, default=250)
    tr.add_argument("--log-every", type=int, default=25)
    tr.add_argument("--score-batch", type=int, default=32)
    tr.add_argument("--time-budget", type=float, default=0.0, help="s (0: none)")
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--support-near", type=int, default=0,
                    help="of the state's support points, this many nearest the object "
                         "(ValueConfig.support_near; 0: evenly spaced only)")  # fmt: skip
    tr.add_argument("--object-near", type=int, default=0, help="ValueConfig.object_near")
    tr.add_argument("--near-pool", type=int, default=2048, help="ValueConfig.near_pool")
    tr.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)

    if args.command == "pools":
        if args.batch < 1 or args.shard_pairs < 1 or args.workers < 0:
            parser.error("--batch and --shard-pairs must be >= 1, --workers >= 0")
        files = pools_mod.pair_files(args.data, args.split, args.pairs)
        t0 = time.time()
        res = pools_mod.build_pools(files, args.out, seed=args.seed, batch=args.batch,
                                    workers=args.workers, shard_pairs=args.shard_pairs,
                                    progress=not args.no_progress)  # fmt: skip
        res["seconds"] = round(time.time() - t0, 1)
        print(f"{args.split}: {res['pairs']} pairs pooled, {res['skipped']} already there -> "
              f"{args.out} ({res['seconds']} s)")  # fmt: skip
        return res
    if args.steps < 1 or args.pairs_per_batch < 1:
        parser.error("--steps and --pairs-per-batch must be >= 1")
    if not os.path.exists(args.init):
        parser.error(f"--init {args.init}: no such value folder")
    return train(args)


if __name__ == "__main__":
    _cli.run(main)
