"""Train the approach network (issue 13, thirty-fifth session): which straight approach into a
hang is free, from the partial clouds (``omnihang_jax.approach``).

1. Derives training pairs (``train_collision.derive_collision_pairs``: the collision
   estimator's pair files, the NCE's validation pairs excluded, resumable).
2. Labels every stable pose of each with the full meshes: for each of the planner's 26 retreat
   directions, is the straight ``--length`` approach free (``approach.approach_labels``; cached
   per pair under ``DATA/derived/approach/``, resumable).
3. Splits by whole objects (``--val-mod``: an object is validation when crc32(name) % mod == 0),
   trains with warm-up + cosine decay, validates every ``--val-every`` steps, and writes the
   weights, ``curves.png`` and a JSON of the curves and the final figures.
4. Scores the held-out pairs (``--test-pairs``, the pairs of ``--pairs-from``, the path
   benchmark's goals): how often the best-scored direction is truly free, against the prior
   (the direction most often free in training).

    python -m experiments.train_approach --pairs 1600 --steps 3000 --out weights/approach_s35 \\
        --results results/approach_s35.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
import zlib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from experiments import eval_paths, train_collision
from omnihang_jax import approach, collision, dataset_bridge

LABEL_VERSION = 1


def _label_one(job: tuple[str, str, float, float]) -> str:
    """Label one pair file's stable poses; returns the label file (written atomically)."""
    from sim.scene import build_scene

    pair_file, out_file, length, resolution = job
    lib = train_collision._WORKER["library"]  # train_collision._worker_init's
    with np.load(pair_file) as f:
        obj, sup = lib.objects[f["object_name"].item()], lib.supports[f["support_name"].item()]
        stable = f["stable_poses"].astype(float)
    labels = approach.approach_labels(build_scene(obj, sup), stable, length, resolution)
    tmp = out_file + ".tmp.npz"
    np.savez(tmp, labels=labels, length=np.float32(length), version=np.int64(LABEL_VERSION))
    os.replace(tmp, out_file)
    return out_file


def _labels_done(path: str) -> bool:
    try:
        with np.load(path) as f:
            return int(f["version"]) == LABEL_VERSION
    except (OSError, ValueError, KeyError, EOFError):
        return False


def label_pairs(data: str, files: list[Path], length: float, resolution: float, workers: int,
                progress: bool = True) -> list[Path]:  # fmt: skip
    """The label file of every pair file (derived where missing; resumable)."""
    out_dir = Path(data) / train_collision.DERIVED.replace("collision", "approach")
    outs, todo = [], []
    for f in files:
        out = out_dir / f.parent.name / f.name
        out.parent.mkdir(parents=True, exist_ok=True)
        outs.append(out)
        if not _labels_done(os.fspath(out)):
            todo.append((os.fspath(f), os.fspath(out), length, resolution))
    recipe = dataset_bridge.read_recipe(data)
    bar = tqdm(total=len(todo), desc="label approaches", unit="pair", disable=not progress)
    if todo and workers <= 1:
        train_collision._worker_init(recipe, data)
        for job in todo:
            _label_one(job)
            bar.update(1)
    elif todo:
        from sim.workers import spawn_pool

        with spawn_pool(workers, train_collision._worker_init, (recipe, data)) as pool:
            for _ in pool.imap_unordered(_label_one, todo, chunksize=4):
                bar.update(1)
    bar.close()
    return outs


@dataclasses.dataclass
class ApproachData:
    """Clouds per pair [P, N, 3] and one row per stable pose: pair [R] (rows of a pair
    contiguous, pairs in order), goals [R, 7], labels [R, 26]."""

    object_points: np.ndarray
    support_points: np.ndarray
    pair: np.ndarray
    goals: np.ndarray
    labels: np.ndarray
    object_names: list[str]

    @classmethod
    def from_files(cls, files: list[Path], label_files: list[Path]) -> ApproachData:
        objs, sups, pair, goals, labels, names = [], [], [], [], [], []
        for i, (f, lf) in enumerate(zip(files, label_files)):
            with np.load(f) as z, np.load(lf) as zl:
                objs.append(z["object_points"].astype(np.float32))
                sups.append(z["support_points"].astype(np.float32))
                names.append(z["object_name"].item())
                stable = z["stable_poses"].astype(np.float32)
                lab = zl["labels"].astype(bool)
            if len(lab) != len(stable):
                raise RuntimeError(f"{lf}: {len(lab)} label rows for {len(stable)} stable poses")
            pair.append(np.full(len(stable), i, np.int32))
            goals.append(stable)
            labels.append(lab)
        return cls(np.stack(objs), np.stack(sups), np.concatenate(pair), np.concatenate(goals),
                   np.concatenate(labels), names)  # fmt: skip

    @property
    def first_row(self) -> np.ndarray:
        """[P] each pair's first stable pose (the path benchmark's goal)."""
        return np.unique(self.pair, return_index=True)[1]

    def subset(self, pairs: np.ndarray) -> ApproachData:
        """The pairs ``pairs`` (increasing indices), renumbered 0..len-1."""
        keep = np.isin(self.pair, pairs)
        remap = np.full(len(self.object_points), -1, np.int32)
        remap[pairs] = np.arange(len(pairs))
        return ApproachData(self.object_points[pairs], self.support_points[pairs],
                            remap[self.pair[keep]], self.goals[keep], self.labels[keep],
                            [self.object_names[i] for i in pairs])  # fmt: skip


def object_split(names: list[str], mod: int) -> np.ndarray:
    """[P] bool: the pair's object is a validation object (crc32 of its name % mod == 0)."""
    return np.array([zlib.crc32(n.encode()) % mod == 0 for n in names])


def score_rows(config, params, data: ApproachData, rows: np.ndarray, batch: int = 64,
               seed: int = 0) -> np.ndarray:  # fmt: skip
    """[len(rows), 26] probabilities with the planner's fixed cloud subsets (``seed`` 0; another
    seed draws other ``local_from`` subsets); batches padded to ``batch`` goals, so one compiled
    shape."""
    probs = approach.jitted_probabilities(config)
    result = np.zeros((len(rows), len(approach.DIRECTIONS)), np.float32)
    for p in np.unique(data.pair[rows]):
        obj = collision.subsample_cloud(data.object_points[p], config.local_from, seed)
        sup = collision.subsample_cloud(data.support_points[p], config.local_from, seed)
        at = np.flatnonzero(data.pair[rows] == p)
        for k in range(0, len(at), batch):
            idx = at[k : k + batch]
            goals = data.goals[rows[idx]]
            goals = np.concatenate([goals, np.repeat(goals[-1:], batch - len(idx), axis=0)])
            result[idx] = np.asarray(probs(params, obj, sup, goals))[: len(idx)]
    return result


def ranking_figures(
    prob: np.ndarray, labels: np.ndarray, prior: np.ndarray, threshold: float
) -> dict:
    """How the best-scored direction fares: ``top1_free`` (share of goals whose top-1 is truly
    free), the same among goals with any free approach (``top1_free_when_any``), the prior's
    (one fixed direction for every goal), and at ``threshold``: the share of goals with top-1
    probability >= it (``used``) and how often those are free (``used_free``)."""
    top = prob.argmax(1)
    free = labels[np.arange(len(top)), top]
    anyfree = labels.any(1)
    used = prob.max(1) >= threshold
    prior_free = labels[:, int(np.argmax(prior))]
    return dict(
        goals=int(len(top)),
        any_free=round(float(anyfree.mean()), 4),
        top1_free=round(float(free.mean()), 4),
        top1_free_when_any=round(float(free[anyfree].mean()), 4) if anyfree.any() else None,
        prior_free=round(float(prior_free.mean()), 4),
        used=round(float(used.mean()), 4),
        used_free=round(float(free[used].mean()), 4) if used.any() else None,
    )


def train(data: ApproachData, val: ApproachData | None, config, steps: int, batch: int,
          learning_rate: float, seed: int, time_budget: float, val_every: int, val_rows: int,
          progress: bool = True):  # fmt: skip
    nets = approach.make_approach_net(config)
    params = nets.init(jax.random.key(seed))
    schedule = optax.warmup_cosine_decay_schedule(
        0.1 * learning_rate, learning_rate, max(1, int(0.03 * steps)), steps, 0.05 * learning_rate
    )  # the NCE's warm-up + cosine, counted in steps
    opt = optax.chain(optax.clip_by_global_norm(1.0),
                      optax.adamw(schedule, weight_decay=1e-4))  # fmt: skip
    opt_state = opt.init(params)
    obj_all = jnp.asarray(data.object_points)
    sup_all = jnp.asarray(data.support_points)
    goals_all = jnp.asarray(data.goals)
    labels_all = jnp.asarray(data.labels, jnp.float32)
    pair_all = jnp.asarray(data.pair)
    n_rows = len(data.goals)

    def loss_fn(params, obj, sup, goals, labels):
        logits = nets.apply(params, obj, sup, goals)
        return optax.sigmoid_binary_cross_entropy(logits, labels).mean()

    @jax.jit
    def step(params, opt_state, key):
        k1, k2, k3 = jax.random.split(key, 3)
        rows = jax.random.randint(k1, (batch,), 0, n_rows)
        pair = pair_all[rows]
        obj = train_collision._sample_points(k2, obj_all[pair], config.local_from)
        sup = train_collision._sample_points(k3, sup_all[pair], config.local_from)
        loss, grads = jax.value_and_grad(loss_fn)(
            params, obj, sup, goals_all[rows], labels_all[rows]
        )
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, loss

    prior = data.labels.mean(0)
    evaluate = None
    if val is not None:
        rng = np.random.default_rng(0)
        rows = np.sort(rng.choice(len(val.goals), min(val_rows, len(val.goals)), replace=False))

        def evaluate(params):
            prob = score_rows(config, params, val, rows)
            lab = val.labels[rows]
            eps = 1e-6
            bce = -np.mean(lab * np.log(prob + eps) + (1 - lab) * np.log(1 - prob + eps))
            return dict(val_loss=round(float(bce), 4),
                        **ranking_figures(prob, lab, prior, config.threshold))  # fmt: skip

    params, log = train_collision._loop(
        step, params, opt_state, jax.random.key(seed + 1), steps, time_budget, batch,
        "approach", progress, evaluate=evaluate, eval_every=val_every,
    )  # fmt: skip
    return params, log, prior


def plot_curves(log: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    hist = np.asarray(log["history"] or np.zeros((0, 3)), float).reshape(-1, 3)
    a.plot(hist[:, 0], hist[:, 1], "C0", lw=1, label="train")
    val = log.get("val_history") or []
    if val:
        s = [r["step"] for r in val]
        a.plot(s, [r["val_loss"] for r in val], "C1o-", ms=3, label="validation (whole objects)")
        b.plot(s, [r["top1_free"] for r in val], "C1o-", ms=3, label="top-1 free")
        b.plot(s, [r["used_free"] or 0 for r in val], "C2s--", ms=3, label="top-1 free when used")
        b.plot(s, [r["prior_free"] for r in val], "k:", label="prior (one direction)")
        b.plot(s, [r["any_free"] for r in val], "0.6", lw=1, label="any direction free")
    a.set(xlabel="step", ylabel="binary cross entropy", title="approach network")
    b.set(xlabel="step", ylabel="share of validation goals", ylim=(0, 1))
    a.legend()
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--pairs", type=int, default=1600, help="training pairs (default 1600)")
    ap.add_argument("--preset", default="contact", choices=sorted(approach.PRESETS))
    ap.add_argument("--length", type=float, default=0.045, help="approach length, m")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--time-budget", type=float, default=3600.0, help="s of training at most")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=1e-3, help="peak (warm-up + cosine decay)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--val-mod", type=int, default=7, help="whole-object validation split")
    ap.add_argument("--val-every", type=int, default=250)
    ap.add_argument("--val-rows", type=int, default=1024)
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument("--test-pairs", type=int, default=80, help="held-out pairs scored (0: none)")
    ap.add_argument(
        "--pairs-from", default="results/hanging_success_stage3_s14_cemv.pairs.jsonl.gz"
    )
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", required=True, help="weights folder")
    ap.add_argument("--results", help="JSON of the curves and figures")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    progress = not args.no_progress
    config = approach.PRESETS[args.preset]
    config = approach.ApproachConfig(**{**config.__dict__, "length": args.length,
                                        "threshold": args.threshold})  # fmt: skip
    t0 = time.time()
    files = train_collision.derive_collision_pairs(
        args.data, {"train": args.pairs}, args.workers, progress, shuffle_seed=0,
        only=lambda i: i % eval_paths.VAL_EVERY != 0,
    )["train"]  # fmt: skip
    labels = label_pairs(args.data, files, args.length, config.resolution, args.workers, progress)
    data = ApproachData.from_files(files, labels)
    is_val = object_split(data.object_names, args.val_mod)
    train_set = data.subset(np.flatnonzero(~is_val))
    val_set = data.subset(np.flatnonzero(is_val)) if is_val.any() else None
    print(f"{len(files)} pairs ({int(is_val.sum())} validation, whole objects), "
          f"{len(train_set.goals)} training goals, {0 if val_set is None else len(val_set.goals)} "
          f"validation; free share per direction {np.round(data.labels.mean(0), 2).tolist()}",
          flush=True)  # fmt: skip
    params, log, prior = train(train_set, val_set, config, args.steps, args.batch, args.lr,
                               args.seed, args.time_budget, args.val_every, args.val_rows,
                               progress)  # fmt: skip
    out = Path(args.out)
    approach.save(out, config, params, steps=log["steps"], pairs=len(files),
                  val_objects=sorted(set(val_set.object_names)) if val_set else [],
                  prior=prior.round(4).tolist())  # fmt: skip
    plot_curves(log, out / "curves.png")
    summary = dict(config=config.__dict__ | {"head": list(config.head)}, pairs=len(files),
                   train_goals=len(train_set.goals),
                   val_goals=0 if val_set is None else len(val_set.goals),
                   prior=prior.round(4).tolist(), log=log, weights=str(out),
                   curves=str(out / "curves.png"))  # fmt: skip
    if args.test_pairs:
        records = eval_paths.read_answers(args.pairs_from)
        test_files = train_collision.derive_collision_pairs(
            args.data, {"test": args.test_pairs}, args.workers, progress, shuffle_seed=0,
            only=records.__contains__,
        )["test"]  # fmt: skip
        test = ApproachData.from_files(test_files, label_pairs(args.data, test_files, args.length,
                                                    config.resolution, args.workers, progress))  # fmt: skip
        every = np.arange(len(test.goals))
        prob = score_rows(config, params, test, every)
        summary["held_out"] = dict(
            pairs=len(test_files),
            first_goal=ranking_figures(
                prob[test.first_row], test.labels[test.first_row], prior, config.threshold
            ),  # fmt: skip
            every_goal=ranking_figures(prob, test.labels, prior, config.threshold),
        )
        print("held out:", json.dumps(summary["held_out"]), flush=True)
    summary["seconds"] = round(time.time() - t0, 1)
    if args.results:
        Path(args.results).write_text(json.dumps(summary, indent=1) + "\n")
    return summary


if __name__ == "__main__":
    main()
