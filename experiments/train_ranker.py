"""A ranker for Stage 3's answer: V fine-tuned on the pipeline's own refined candidates.

    # 0. a list of training pairs of training objects (stable poses, none in earlier lists):
    python -m experiments.train_ranker pairs --per-category 220 --seed 2 \\
        --exclude results/ranker_pairs_a.jsonl results/ranker_pairs_b.jsonl \\
        --out results/ranker_pairs_c.jsonl
    # 1. records of the committed pipeline on TRAINING pairs of training objects (GPU):
    VAL_PAIRS=results/ranker_pairs_a.jsonl VAL_NAME=rank_a bash scripts/device_full.sh val
    # 2. the records made compact (the pool's poses, outcomes, V, inside counts):
    python -m experiments.train_ranker slim out/val_rank_a.pairs.jsonl.gz out/rank_a.npz
    # 3. fine-tune (pair files from DATA/derived/<split>/, derived by step 1 on the machine):
    python -m experiments.train_ranker train --records out/rank_a.npz out/rank_b.npz \\
        --data /tmp/full/ds --init weights/value_s16_hardneg --out out/ranker \\
        --val-records results/validation_where_s15/val_k16.pairs.jsonl.gz
    # 2b. the view runs of the same pairs as one pool a pair (the default's three views):
    python -m experiments.train_ranker union out/rank_f_v0.npz out/rank_f_v1of2.npz \\
        out/rank_f_v3of4.npz out/rank_f.npz
    # 4. its scores on any run's records, and the answer rule's success with them:
    python -m experiments.train_ranker score --ranker out/ranker/value --records R.npz \\
        --data DS --split test --out scores.npz

Why: V's ranking among the clear refined candidates is the largest loss of the answer rule
(docs/stage3.md: ~280 of ~430 held-out failures pick a clear candidate that does not hang
while another clear one does). V was trained on a 50/50 replay buffer of perturbations and
CEM's top members, with half-resolution training clouds; the answer is chosen among the
pipeline's final candidates on full-resolution clouds. The ranker is the same network (same
``ValueConfig``, so it plugs into ``PipelineConfig.rank_values``), started from V and
fine-tuned on exactly that decision: every refined candidate of a pair (the 2K of the
answer pool), labelled by the simulation (the evaluation protocol, ``stable_all`` of an
``eval_stage3`` run), with

    L = list_weight * L_list + bce_weight * BCE

where ``L_list = logsumexp(s[clear]) - logsumexp(s[clear & stable])`` (s: V's log-odds) over
the candidates the answer rule chooses among (no observed object point inside the support,
``selection.CHOSEN``), for pairs where both clear outcomes occur, and BCE keeps V's
calibration on all candidates. Warm-up + cosine learning rate, validation every
``--eval-every`` steps on validation-OBJECT records (the rule's success with the ranker alone
and with the mean log P(hang) of the ranker and the run's V), a resumable checkpoint, curves.
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
from experiments.rerank_stage3 import category_means, pool_indices, proposals_of, read_records
from omnihang_jax import refine, selection, stage3
from omnihang_jax.stage3 import PairClouds

POOL = "stage1_2"
SLIM_FIELDS = ("poses", "stable", "v", "counts")


# ----------------------------------------------------------------------------------------------
# Pair lists and records


def training_pairs(
    data: str, per_category: int, seed: int, exclude=(), val_fraction: float = 0.1
) -> list[dict]:
    """Training-split pairs of TRAINING objects (never a validation object, ``data.
    validation_objects``) with at least one stable pose in the dataset, none of ``exclude``
    (pair indices), ``per_category`` drawn at random a category (fewer where fewer remain),
    sorted by pair index: one line each for ``device_full.sh val`` (``VAL_PAIRS``)."""
    from omnihang_jax.data import validation_objects

    with open(os.path.join(data, "recipe.json")) as f:
        pairs = json.load(f)["pairs"]
    n_stable = np.zeros(len(pairs), np.int64)
    shards = sorted(Path(data, "shards").glob("shard_*.npz"))
    if not shards:
        raise FileNotFoundError(f"no dataset shards in {data}/shards (generate the dataset)")
    for shard in shards:
        with np.load(shard) as z:
            n_stable[z["pair_index"]] = np.diff(z["stable_offsets"])
    objects = sorted({p[0] for p in pairs if p[2] == "train"})
    val = validation_objects(objects, val_fraction)
    excluded = set(int(i) for i in exclude)
    by_category: dict[str, list[int]] = {}
    for i, (obj, _, split) in enumerate(pairs):
        if split == "train" and obj not in val and n_stable[i] > 0 and i not in excluded:
            by_category.setdefault(obj.rsplit("_", 1)[0], []).append(i)
    rng = np.random.default_rng(seed)
    picked = []
    for category in sorted(by_category):
        pool = by_category[category]
        picked += [int(i) for i in rng.choice(pool, min(per_category, len(pool)), replace=False)]
    rows = []
    for i in sorted(picked):
        obj, support, _ = pairs[i]
        rows.append({"pair_index": i, "object": obj, "support": support,
                     "category": obj.rsplit("_", 1)[0], "file": f"{i:05d}_{obj}__{support}.npz"})  # fmt: skip
    return rows


def slim_records(rows: list[dict], config: selection.SelectConfig = selection.CHOSEN) -> dict:
    """An ``eval_stage3`` run's records -> arrays of the answer pool (the 2K refined
    candidates): poses [N, 2K, 7] float32, stable [N, 2K] bool, v [N, 2K] (the run's V),
    counts [N, 2K] (observed inside points at the rule's depth and radius) + per-pair file,
    category, pair_index."""
    k = proposals_of(rows)
    idx = pool_indices(k, POOL)
    key = selection.grid_key(config.depth, config.radius)
    if key not in rows[0]["inside_counts"]:
        raise ValueError(f"records hold no inside counts at {key} (the rule's setting)")
    return {
        "poses": np.asarray([r["poses_all"] for r in rows], np.float32)[:, idx],
        "stable": np.asarray([r["stable_all"] for r in rows], bool)[:, idx],
        "v": np.asarray([r["v"] for r in rows], np.float32)[:, idx],
        "counts": np.asarray([r["inside_counts"][key] for r in rows], np.int16)[:, idx],
        "files": np.asarray([r["file"] for r in rows]),
        "category": np.asarray([r["category"] for r in rows]),
        "pair_index": np.asarray([int(r["pair_index"]) for r in rows], np.int64),
        "k": np.asarray(k),
    }


def load_table(path: str | os.PathLike) -> dict:
    """A slim ``.npz`` (``slim``) or an ``eval_stage3`` ``.pairs.jsonl[.gz]`` -> the arrays."""
    path = os.fspath(path)
    if path.endswith(".npz"):
        with np.load(path) as z:
            table = {f: z[f] for f in z.files}
    else:
        table = slim_records(read_records(path))
    n = len(table["files"])
    for f in SLIM_FIELDS:
        if table[f].shape[0] != n:
            raise ValueError(f"{path}: {f} holds {table[f].shape[0]} pairs, files {n}")
    if not np.all(np.isfinite(table["poses"])):
        raise ValueError(f"{path}: non-finite candidate poses")
    return table


def concat_tables(tables: list[dict]) -> dict:
    keys = [f for f in tables[0] if f != "k"]
    ks = {int(t["k"]) for t in tables}
    if len(ks) != 1:
        raise ValueError(f"records of runs with different K: {sorted(ks)}")
    out = {f: np.concatenate([t[f] for t in tables]) for f in keys}
    out["k"] = np.asarray(ks.pop())
    return out


def union_tables(tables: list[dict]) -> dict:
    """The view runs of the SAME pairs (e.g. views 0, 1/2, 3/4 of the default pipeline) -> one
    table whose pool per pair is every run's candidates side by side, [N, V x 2K]: what the
    pipeline's answer is chosen among (forty-seventh session)."""
    first = tables[0]
    for t in tables[1:]:
        if not np.array_equal(t["pair_index"], first["pair_index"]):
            raise ValueError("union: the runs hold different pairs (or another order)")
        if int(t["k"]) != int(first["k"]):
            raise ValueError(f"union: runs of different K ({int(first['k'])}, {int(t['k'])})")
    out = {f: np.concatenate([t[f] for t in tables], axis=1) for f in SLIM_FIELDS}
    out |= {f: first[f] for f in ("files", "category", "pair_index", "k")}
    return out


def load_bank(table: dict, data: str, split: str, config, progress: bool) -> refine.PairBank:
    folder = Path(data) / "derived" / split
    files = [folder / str(f) for f in table["files"]]
    missing = [f for f in files if not f.exists()]
    if missing:
        raise FileNotFoundError(
            f"{len(missing)} pair files missing (e.g. {missing[0]}): derive them "
            f"(experiments.derive_dataset --split {split.split('_')[0]} --pairs-from ...)"
        )
    return refine.PairBank.from_files(files, config, progress=progress)


# ----------------------------------------------------------------------------------------------
# Loss and scores (pure)


def load_subset_bank(table: dict, data: str, split: str, config, subsets: int,
                     progress: bool) -> PairClouds:  # fmt: skip
    """[subsets, N, ...] the pairs' clouds on each of ``subsets`` evenly spaced subsets
    (``stage3.subset_clouds``; subset 0 is :func:`load_bank`'s)."""
    from experiments.rank_subsets import load_clouds

    full = load_clouds(Path(data) / "derived" / split, table["files"])
    stacked = PairClouds(*(np.stack([c[f] for c in full]) for f in range(4)))
    del full
    parts = [stage3.subset_clouds(stacked, config, j, subsets) for j in range(subsets)]
    return PairClouds(*(np.stack([np.asarray(getattr(p, f)) for p in parts])
                        for f in PairClouds._fields))  # fmt: skip


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


def score_table(scorer, params, bank: refine.PairBank, table: dict, batch: int) -> np.ndarray:
    """[N, P] log P(hang) of every pool candidate of ``table`` (pairs in ``bank`` order)."""
    n = len(table["files"])
    out = np.zeros(table["poses"].shape[:2], np.float32)
    for i in range(0, n, batch):
        sl = np.arange(i, min(i + batch, n))
        m = len(sl)
        sl = np.concatenate([sl, np.repeat(sl[:1], batch - m)])
        clouds = PairClouds(*(jnp.asarray(x[sl]) for x in bank.clouds))
        out[i : i + m] = np.asarray(scorer(params, clouds, jnp.asarray(table["poses"][sl])))[:m]
    return out


def rule_success(table: dict, scores: np.ndarray, config=selection.CHOSEN) -> dict:
    """The answer rule's success (percent, mean over categories) when ``scores`` [N, P] rank
    the pool (``selection.select``: the highest among the clear candidates, else the fewest
    inside points)."""
    picks = np.asarray(selection.select(jnp.asarray(scores), jnp.asarray(table["counts"]), config))
    rows = [{"category": str(c)} for c in table["category"]]
    ok = table["stable"][np.arange(len(picks)), picks]
    return category_means(rows, ok)


def score_variants(table: dict, ranker_logp: np.ndarray) -> dict:
    """The rule's success with the run's V, the ranker alone, and their mean log P(hang)."""
    v_log = np.log(np.clip(table["v"], 1e-12, 1.0))
    return {
        "run_v": rule_success(table, v_log),
        "ranker": rule_success(table, ranker_logp),
        "mean_log": rule_success(table, 0.5 * (v_log + ranker_logp)),
        "any_refined": 100.0 * float(np.mean(table["stable"].any(1))),
    }


# ----------------------------------------------------------------------------------------------
# Training


def train(args) -> dict:
    from sim import atomic

    t_start = time.time()  # the time budget counts the loading too
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    config, init_params = refine.load_value(args.init)
    # the state's near points (stage3.near_points): same encoder and head, so V's weights start it
    config = dataclasses.replace(config, support_near=args.support_near,
                                 object_near=args.object_near, near_pool=args.near_pool)  # fmt: skip
    progress = not args.no_progress
    table = concat_tables([load_table(p) for p in args.records])
    n_pairs = len(table["files"])
    val = load_table(args.val_records) if args.val_records else None
    val_bank = load_bank(val, args.data, args.val_split, config, progress) if val else None
    clear = table["counts"] <= selection.CHOSEN.max_points
    print(f"{n_pairs} training pairs, "
          f"{table['poses'].shape[1]} candidates each; validation pairs "
          f"{0 if val is None else len(val['files'])}", flush=True)  # fmt: skip

    # V's own optimiser (clipping, AdamW, warm-up + cosine) with this run's lr and warm-up
    run_config = dataclasses.replace(config, learning_rate=args.lr, warmup_steps=args.warmup)
    schedule = refine.make_schedule(run_config, args.steps)
    tx = refine.make_optimizer(run_config, args.steps)
    net = stage3.make_value(config)
    n_sub = args.subset_augment
    if n_sub > 1:  # [n_sub, N, ...]: each step draws a subset per pair
        clouds = load_subset_bank(table, args.data, args.split, config, n_sub, progress)
    else:  # [1, N, ...]: subset 0, as the pipeline's own subsample
        bank = load_bank(table, args.data, args.split, config, progress)
        clouds = jax.tree.map(lambda x: x[None], bank.clouds)
    bank_dev = jax.tree.map(jnp.asarray, clouds)
    poses_dev = jnp.asarray(table["poses"])
    stable_dev, clear_dev = jnp.asarray(table["stable"]), jnp.asarray(clear)

    def loss_fn(params, slots, key):
        which = jax.random.randint(jax.random.fold_in(key, 1), slots.shape, 0, n_sub)
        clouds = jax.tree.map(lambda x: x[which, slots], bank_dev)
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
        logp = score_table(scorer, params, val_bank, val, args.score_batch)
        res = {"step": step_i, **{k: (v["mean"] if isinstance(v, dict) else v)
                                   for k, v in score_variants(val, logp).items()}}  # fmt: skip
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
    done = i + 1
    refine.save_value(out / "value", config, params, note=(
        f"ranker: {args.init} fine-tuned {done} steps on the refined candidates of "
        f"{n_pairs} training pairs (experiments.train_ranker)"))  # fmt: skip
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

    rows = [json.loads(line) for line in open(out / "metrics.jsonl")] if (
        out / "metrics.jsonl").exists() else []  # fmt: skip
    val = [json.loads(line) for line in open(out / "val_metrics.jsonl")] if (
        out / "val_metrics.jsonl").exists() else []  # fmt: skip
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    if rows:
        st = [r["step"] for r in rows]
        for k in ("loss", "listwise", "bce"):
            ax[0].plot(st, [r[k] for r in rows], label=f"train {k}")
        ax[0].set_xlabel("step")
        ax[0].legend()
    if val:
        st = [r["step"] for r in val]
        for k in ("run_v", "ranker", "mean_log"):
            ax[1].plot(st, [r[k] for r in val], marker="o", label=k)
        ax[1].set_xlabel("step")
        ax[1].set_ylabel("answer rule's success, validation objects (%)")
        ax[1].legend()
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=100)
    plt.close(fig)


def choose_sets(score_files, select_on: str, records) -> dict:
    """Every non-empty set of the rankers in ``score_files`` (``score``'s .npz: arrays keyed
    ``NAME|RUN``), each ranking by the mean log P(hang) of its networks alone: the rule's
    success on the ``select_on`` table and on each of ``records``; sorted by the first (ties:
    the smaller set); ``chosen`` is the first."""
    import itertools

    logp = {}
    for f in score_files:
        with np.load(f) as z:
            logp.update({k: z[k] for k in z.files})
    tables = {Path(p).name: load_table(p) for p in [select_on, *records]}
    names = sorted({k.split("|")[0] for k in logp})
    missing = [f"{n}|{r}" for n in names for r in tables if f"{n}|{r}" not in logp]
    if missing:
        raise ValueError(f"no scores for {missing[:4]}...: score every ranker on every table")

    def success(combo, run):
        return rule_success(tables[run], np.mean([logp[f"{n}|{run}"] for n in combo], 0))

    first, others = Path(select_on).name, [Path(p).name for p in records]
    rows = []
    for r in range(1, len(names) + 1):
        for combo in itertools.combinations(names, r):
            runs = [success(combo, run) for run in others]
            rows.append({"set": list(combo), "select_on": success(combo, first)["mean"],
                         "runs": [x["mean"] for x in runs],
                         "runs_mean": float(np.mean([x["mean"] for x in runs])),
                         "per_category_first_run": runs[0]["per_category"] if runs else {}})  # fmt: skip
    rows.sort(key=lambda x: (-x["select_on"], len(x["set"])))
    return {"select_on": first, "runs": others, "chosen": rows[0], "sets": rows}


# ----------------------------------------------------------------------------------------------
# CLI


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    pa = sub.add_parser("pairs", help="a list of training pairs of training objects (jsonl)")
    pa.add_argument("--data", default="datasets/paper", help="dataset (recipe.json, shards/)")
    pa.add_argument("--per-category", type=int, default=220)
    pa.add_argument("--seed", type=int, default=0)
    pa.add_argument("--exclude", nargs="*", default=[], help="earlier lists (jsonl)")
    pa.add_argument("--val-fraction", type=float, default=0.1)
    pa.add_argument("--out", required=True)
    sl = sub.add_parser("slim", help="records -> compact .npz of the answer pool")
    sl.add_argument("records")
    sl.add_argument("out")
    un = sub.add_parser("union", help="slim tables of view runs of the same pairs -> one pool")
    un.add_argument("tables", nargs="+", help="slim .npz (or records) of each view run, then OUT")
    tr = sub.add_parser("train", help="fine-tune V as the answer's ranker")
    tr.add_argument("--records", nargs="+", required=True, help="training-pair records")
    tr.add_argument("--data", required=True, help="dataset folder with derived/<split>/")
    tr.add_argument("--split", default="train")
    tr.add_argument("--init", default=stage3.CEM_VALUE, help="V to start from")
    tr.add_argument("--out", required=True)
    tr.add_argument("--val-records", default=None, help="validation-OBJECT records")
    tr.add_argument("--val-split", default="train")
    tr.add_argument("--steps", type=int, default=2000)
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
    tr.add_argument("--subset-augment", type=int, default=1, metavar="N",
                    help="each training pair is seen on a random one of N evenly spaced subsets "
                         "of its clouds a step (stage3.subset_clouds; 1: subset 0 only, as "
                         "the committed rankers), for rankers used with "
                         "PipelineConfig.rank_subsets")  # fmt: skip
    tr.add_argument("--no-progress", action="store_true")
    sc = sub.add_parser("score", help="a ranker's scores on a run's records + the rule's table")
    sc.add_argument("--ranker", nargs="+", required=True,
                    help="value folders (train's OUT/value), each as DIR or NAME=DIR")  # fmt: skip
    sc.add_argument("--records", nargs="+", required=True)
    sc.add_argument("--data", required=True)
    sc.add_argument("--split", default="test")
    sc.add_argument("--out", required=True, help="JSON (scores beside it as .npz)")
    sc.add_argument("--score-batch", type=int, default=32)
    sc.add_argument("--no-progress", action="store_true")
    se = sub.add_parser("sets", help="every set of scored rankers, chosen on one run's table")
    se.add_argument("--scores", nargs="+", required=True, help="score's .npz files")
    se.add_argument("--select-on", required=True, help="the table the set is chosen on")
    se.add_argument("--records", nargs="+", required=True, help="tables reported beside it")
    se.add_argument("--out", required=True, help="JSON")
    args = parser.parse_args(argv)

    if args.command == "pairs":
        exclude = [json.loads(line)["pair_index"] for f in args.exclude for line in open(f)]
        rows = training_pairs(args.data, args.per_category, args.seed, exclude, args.val_fraction)
        with open(args.out, "w") as f:
            f.writelines(json.dumps(r) + "\n" for r in rows)
        print(f"{len(rows)} pairs ({len(exclude)} excluded) -> {args.out}")
        return {"pairs": len(rows), "out": args.out}
    if args.command == "sets":
        result = choose_sets(args.scores, args.select_on, args.records)
        refine.write_json(args.out, result)
        best = result["chosen"]
        print(f"chosen {'+'.join(best['set'])}: {args.select_on} {best['select_on']:.2f}, "
              f"others {[round(x, 2) for x in best['runs']]}")  # fmt: skip
        return result
    if args.command == "slim":
        table = slim_records(read_records(args.records))
        np.savez_compressed(args.out, **table)
        return {"pairs": len(table["files"]), "out": args.out}
    if args.command == "union":
        if len(args.tables) < 3:
            parser.error("union: give at least two tables and the output")
        table = union_tables([load_table(p) for p in args.tables[:-1]])
        np.savez_compressed(args.tables[-1], **table)
        print(f"{len(table['files'])} pairs, {table['poses'].shape[1]} candidates each -> "
              f"{args.tables[-1]}")  # fmt: skip
        return {"pairs": len(table["files"]), "candidates": int(table["poses"].shape[1])}
    if args.command == "train":
        if args.steps < 1 or args.pairs_per_batch < 1:
            parser.error("--steps and --pairs-per-batch must be >= 1")
        return train(args)
    rankers = {}
    for d in args.ranker:  # NAME=DIR or DIR
        name, _, folder = d.rpartition("=")
        config, params = refine.load_value(folder)
        rankers[name or folder] = (config, params, make_scorer(config))
    result = {"rankers": args.ranker, "runs": {}}
    scores = {}
    for path in args.records:  # each run's pair files are read once per ranker config
        table = load_table(path)
        banks = {c: load_bank(table, args.data, args.split, c, not args.no_progress)
                 for c in {c for c, _, _ in rankers.values()}}  # fmt: skip
        run = Path(path).name
        result["runs"][run] = {"pairs": len(table["files"])}
        for name, (config, params, scorer) in rankers.items():
            logp = score_table(scorer, params, banks[config], table, args.score_batch)
            scores[f"{name}|{run}"] = logp
            res = score_variants(table, logp)
            result["runs"][run][name] = res
            print(run, name, json.dumps({k: v["mean"] if isinstance(v, dict) else v
                                         for k, v in res.items()}), flush=True)  # fmt: skip
    np.savez_compressed(Path(args.out).with_suffix(".npz"), **scores)
    refine.write_json(args.out, result)
    return result


if __name__ == "__main__":
    _cli.run(main)
