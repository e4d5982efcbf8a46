"""Train the approach network: which straight approach into a
hang is free, from the partial clouds (``omnihang_jax.approach``).

1. Derives training pairs (``collision_data.derive_collision_pairs``: the collision
   estimator's pair files, the NCE's validation pairs excluded, resumable).
2. Labels every stable pose of each with the full meshes: for each of the planner's 26 retreat
   directions, is the straight ``--length`` approach free (``approach.approach_labels``; cached
   per pair under ``DATA/derived/approach/``, resumable).
3. Splits by whole objects (``--val-mod``: an object is validation when crc32(name) % mod == 0),
   trains with warm-up + cosine decay, validates every ``--val-every`` steps, and writes the
   weights, ``curves.png`` and a JSON of the curves and the final figures.
4. Scores held-out pairs (``--test-pairs``, the path evaluation's order): how often the best-scored direction is truly free, against the prior
   (the direction most often free in training).

    python -m experiments.train_approach --pairs 8000 --steps 10000 --threshold 0.8 \\
        --out weights/approach --results out/approach.json
    python -m experiments.train_approach --pairs 8000 --steps 3000 --first-lengths 0.015 0.03 \\
        --init weights/approach --out weights/approach_routes --results out/approach_routes.json
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

from experiments import train_collision
from omnihang_jax import approach, collision, collision_data, dataset_bridge

LABEL_VERSION = 1
ROUTE_LABEL_VERSION = 1  # route networks' labels (approach.route_labels)


def _label_one(job: tuple) -> str:
    """Label one pair file's stable poses (the first ``goals`` of them when > 0; a route
    network's labels when ``config.first_lengths``); returns the label file (written
    atomically)."""
    from sim.scene import build_scene

    pair_file, out_file, config, goals = job
    lib = collision_data._WORKER["library"]  # collision_data._worker_init's
    with np.load(pair_file) as f:
        obj, sup = lib.objects[f["object_name"].item()], lib.supports[f["support_name"].item()]
        stable = f["stable_poses"].astype(float)
    if goals > 0:
        stable = stable[:goals]
    scene = build_scene(obj, sup)
    if config.first_lengths:
        labels, version = approach.route_labels(scene, stable, config), ROUTE_LABEL_VERSION
    else:
        labels = approach.approach_labels(scene, stable, config.length, config.resolution)
        version = LABEL_VERSION
    tmp = out_file + ".tmp.npz"
    np.savez(tmp, labels=labels, length=np.float32(config.length), version=np.int64(version),
             goals=np.int64(goals))  # fmt: skip
    os.replace(tmp, out_file)
    return out_file


def _labels_done(path: str, version: int = LABEL_VERSION, goals: int = 0) -> bool:
    try:
        with np.load(path) as f:
            return int(f["version"]) == version and int(f.get("goals", 0)) == goals
    except (OSError, ValueError, KeyError, EOFError):
        return False


def label_dir(data: str, config) -> Path:
    """Where a config's labels live: ``derived/approach`` (straight approaches) or
    ``derived/approach_routes_<first lengths in mm>_<clear mm>`` (route networks)."""
    name = "approach"
    if config.first_lengths:
        mm = "-".join(f"{1000 * x:g}" for x in config.first_lengths)
        name = f"approach_routes_{mm}_{1000 * config.clear:g}"
    return Path(data) / collision_data.DERIVED.replace("collision", name)


def label_pairs(data: str, files: list[Path], config, workers: int, progress: bool = True,
                goals: int = 0) -> list[Path]:  # fmt: skip
    """The label file of every pair file (derived where missing; resumable). ``goals`` > 0:
    only each pair's first ``goals`` stable poses (route labels cost ~30 ms a goal)."""
    out_dir = label_dir(data, config)
    version = ROUTE_LABEL_VERSION if config.first_lengths else LABEL_VERSION
    outs, todo = [], []
    for f in files:
        out = out_dir / f.parent.name / f.name
        out.parent.mkdir(parents=True, exist_ok=True)
        outs.append(out)
        if not _labels_done(os.fspath(out), version, goals):
            todo.append((os.fspath(f), os.fspath(out), config, goals))
    recipe = dataset_bridge.read_recipe(data)
    bar = tqdm(total=len(todo), desc="label approaches", unit="pair", disable=not progress)
    if todo and workers <= 1:
        collision_data._worker_init(recipe, data)
        for job in todo:
            _label_one(job)
            bar.update(1)
    elif todo:
        from sim.workers import spawn_pool

        with spawn_pool(workers, collision_data._worker_init, (recipe, data)) as pool:
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
                if int(zl.get("goals", 0)) > 0:  # the first goals only
                    stable = stable[: int(zl["goals"])]
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


def label_summary(labels: np.ndarray, config) -> str:
    """One line on the labels: the positive share per direction (straight approaches), or for
    a route network the share of goals with a positive one-move / two-move route."""
    if not config.first_lengths:
        return f"free share per direction {np.round(labels.mean(0), 2).tolist()}"
    one = config.routes[:, 0] < 0
    return (f"goals off in one move {labels[:, one].any(1).mean():.3f}, in one or two moves "
            f"{labels.any(1).mean():.3f}; mean positive routes a goal {labels.sum(1).mean():.1f} "
            f"of {labels.shape[1]}")  # fmt: skip


def object_split(names: list[str], mod: int) -> np.ndarray:
    """[P] bool: the pair's object is a validation object (crc32 of its name % mod == 0)."""
    return np.array([zlib.crc32(n.encode()) % mod == 0 for n in names])


def score_rows(config, params, data: ApproachData, rows: np.ndarray, batch: int = 64,
               seed: int = 0) -> np.ndarray:  # fmt: skip
    """[len(rows), outputs] probabilities with the planner's fixed cloud subsets (``seed`` 0; another
    seed draws other ``local_from`` subsets); batches padded to ``batch`` goals, so one compiled
    shape."""
    probs = approach.jitted_probabilities(config)
    result = np.zeros((len(rows), config.outputs), np.float32)
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


def warm_start(params, init_folder: str, config, prior: np.ndarray):
    """``params`` with every layer but the last taken from a trained approach network (the
    same architecture); the last layer's columns of the one-move routes from its straight
    approaches' columns, the others' biases at the training prior's logit (a route network
    started from ``weights/approach``); from a route network of the same
    routes, its last layer too."""
    old_config, old, _ = approach.load(init_folder)
    for field in ("pointnet", "local_pointnet", "object_points", "support_points",
                  "local_points", "local_from", "head"):  # fmt: skip
        if getattr(old_config, field) != getattr(config, field):
            raise ValueError(f"--init {init_folder}: its {field} differs from the preset's")
    params = dict(params)  # top-level layers replaced below, none changed in place
    last = f"Dense_{len(config.head)}"
    p = np.clip(prior, 1e-4, 1 - 1e-4)
    bias = np.log(p / (1 - p)).astype(np.float32)
    kernel = np.array(params[last]["kernel"])
    one_move = np.flatnonzero(config.routes[:, 0] < 0)
    old_kernel, old_bias = np.asarray(old[last]["kernel"]), np.asarray(old[last]["bias"])
    if old_kernel.shape == kernel.shape:  # a route network of the same routes: all of it
        kernel, bias = old_kernel.copy(), old_bias.copy()
    elif old_kernel.shape[1] == len(one_move):
        kernel[:, one_move] = old_kernel
        bias[one_move] = old_bias
    for key in old:
        if key != last:
            params[key] = old[key]
    params[last] = dict(kernel=jnp.asarray(kernel), bias=jnp.asarray(bias))
    return params


def train(data: ApproachData, val: ApproachData | None, config, steps: int, batch: int,
          learning_rate: float, seed: int, time_budget: float, val_every: int, val_rows: int,
          progress: bool = True, init: str | None = None):  # fmt: skip
    nets = approach.make_approach_net(config)
    params = nets.init(jax.random.key(seed))
    if init:
        params = warm_start(params, init, config, data.labels.mean(0))
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


def threshold_sweep(prob: np.ndarray, labels: np.ndarray, thresholds=None) -> list[dict]:
    """For each threshold: the share of goals whose best output reaches it (``used``), how
    often that best output is truly positive (``used_free``) and how many are not
    (``used_blocked``). The rule picks the lowest threshold with ``used_free`` >= 0.9."""
    thresholds = np.round(np.arange(0.3, 0.96, 0.05), 2) if thresholds is None else thresholds
    top = prob.argmax(1)
    good = labels[np.arange(len(top)), top]
    out = []
    for t in thresholds:
        used = prob.max(1) >= t
        out.append(dict(threshold=float(t), used=round(float(used.mean()), 4),
                        used_free=round(float(good[used].mean()), 4) if used.any() else None,
                        used_blocked=int((used & ~good).sum())))  # fmt: skip
    return out


def rule_threshold(sweep: list[dict], target: float = 0.9) -> float | None:
    """The lowest threshold of ``sweep`` whose used outputs are >= ``target`` positive (rows
    with ``threshold`` and ``used_free``)."""
    ok = [r["threshold"] for r in sweep if r["used_free"] is not None and r["used_free"] >= target]
    return min(ok) if ok else None


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
    ap.add_argument(
        "--first-lengths", type=float, nargs="*", default=[], metavar="M",
        help="a route network: one output per route of one or two straight "
        "moves (first moves of these lengths, m), labelled free and ending --clear off",
    )  # fmt: skip
    ap.add_argument("--clear", type=float, default=0.01, help="route networks: m off at the end")
    ap.add_argument("--goals-per-pair", type=int, default=0,
                    help="label each pair's first N stable poses only (0: all)")  # fmt: skip
    ap.add_argument("--init", metavar="DIR", help="warm start from a trained approach network")
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
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", required=True, help="weights folder")
    ap.add_argument("--results", help="JSON of the curves and figures")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    progress = not args.no_progress
    config = approach.PRESETS[args.preset]
    config = approach.ApproachConfig(**{**config.__dict__, "length": args.length,
                                        "threshold": args.threshold,
                                        "first_lengths": tuple(args.first_lengths),
                                        "clear": args.clear})  # fmt: skip
    t0 = time.time()
    files = collision_data.derive_collision_pairs(
        args.data, {"train": args.pairs}, args.workers, progress, shuffle_seed=0,
        only=lambda i: i % collision_data.VAL_EVERY != 0,
    )["train"]  # fmt: skip
    labels = label_pairs(args.data, files, config, args.workers, progress, args.goals_per_pair)
    data = ApproachData.from_files(files, labels)
    is_val = object_split(data.object_names, args.val_mod)
    train_set = data.subset(np.flatnonzero(~is_val))
    val_set = data.subset(np.flatnonzero(is_val)) if is_val.any() else None
    print(f"{len(files)} pairs ({int(is_val.sum())} validation, whole objects), "
          f"{len(train_set.goals)} training goals, {0 if val_set is None else len(val_set.goals)} "
          f"validation; {label_summary(data.labels, config)}", flush=True)  # fmt: skip
    params, log, prior = train(train_set, val_set, config, args.steps, args.batch, args.lr,
                               args.seed, args.time_budget, args.val_every, args.val_rows,
                               progress, args.init)  # fmt: skip
    out = Path(args.out)
    approach.save(out, config, params, steps=log["steps"], pairs=len(files),
                  val_objects=sorted(set(val_set.object_names)) if val_set else [],
                  prior=prior.round(4).tolist())  # fmt: skip
    plot_curves(log, out / "curves.png")
    summary = dict(config=config.__dict__ | {"head": list(config.head)}, pairs=len(files),
                   train_goals=len(train_set.goals),
                   val_goals=0 if val_set is None else len(val_set.goals),
                   prior=prior.round(4).tolist(), log=log, weights=str(out),
                   curves=str(out / "curves.png"), init=args.init,
                   goals_per_pair=args.goals_per_pair)  # fmt: skip
    if val_set is not None:  # the validation rule on each validation pair's first goal
        first = val_set.first_row
        sweep = threshold_sweep(score_rows(config, params, val_set, first), val_set.labels[first])
        summary["validation_first_goal"] = dict(goals=len(first), sweep=sweep,
                                                rule_threshold=rule_threshold(sweep))  # fmt: skip
    if args.test_pairs:
        test_files = collision_data.derive_collision_pairs(
            args.data, {"test": args.test_pairs}, args.workers, progress, shuffle_seed=0,
        )["test"]  # fmt: skip
        test = ApproachData.from_files(test_files, label_pairs(
            args.data, test_files, config, args.workers, progress, args.goals_per_pair))  # fmt: skip
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
