"""Training of the goal-pose networks: Stage 1, Stage 2a (contact scores), Stage 2b
(correspondences).

Pure pieces (``train_losses.make_loss_fn``, ``make_init_state``, ``make_train_step``) are
factories returning un-jitted functions; ``train_stage`` is the host loop: it jits the step
once, resumes from the latest orbax checkpoint by default, writes ``config.json`` beside the
checkpoints (a model is rebuilt from its folder alone, ``restore_stage``), appends metrics to
``metrics.jsonl`` and plots ``loss.png``.

Folder layout written by ``train_where(out=...)``::

    out/stage1/{config.json, checkpoints/<step>/, metrics.jsonl, loss.png}
    out/stage2a/...
    out/stage2b/...     (initialised from stage2a's parameters)
    out/stagecanon/...  (the object-frame network, ``omnihang_jax.canon``; --stage canon)
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import flax
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp

from omnihang_jax import augment, sharding
from omnihang_jax import data as data_lib
from omnihang_jax.canon import CANON_SMALL, CANON_TINY, CanonConfig, make_canon
from omnihang_jax.config import config_from_dict, config_to_dict
from omnihang_jax.data import HangSample
from omnihang_jax.stage1 import (
    STAGE1_ORIGINAL,
    STAGE1_SMALL,
    STAGE1_TINY,
    Stage1Config,
    make_stage1,
)
from omnihang_jax.stage2 import (
    STAGE2_ORIGINAL,
    STAGE2_SMALL,
    STAGE2_TINY,
    Stage2Config,
    make_stage2,
)
from omnihang_jax.train_losses import ALL_STAGES, STAGES, make_loss_fn

__all__ = [
    "STAGES",
    "ALL_STAGES",
    "TrainConfig",
    "NetworksConfig",
    "WHERE_ORIGINAL",
    "WHERE_TINY",
    "WHERE_SMALL",
    "PRESETS",
    "TrainState",
    "make_init_state",
    "make_train_step",
    "train_stage",
    "restore_stage",
    "export_weights",
    "train_where",
    "make_dataset",
    "plot_metrics",
]


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimisation and bookkeeping settings."""

    batch_size: int = 32  # pairs per step (facts)
    lr_stage1: float = 5e-4  # Adam (facts)
    lr_stage2: float = 1e-4  # Adam, both 2a and 2b (facts)
    steps: int = 100_000  # default steps per stage when the caller gives none (ours)
    log_every: int = 50
    checkpoint_every: int = 1000
    max_to_keep: int = 3
    seed: int = 0
    synthetic_pairs: int = 256  # size of the synthetic pool for --data synthetic dry runs
    # Learning-rate schedule (ours; the facts give a constant Adam lr): linear warm-up over
    # ``warmup_steps`` (at most a tenth of the run), then "cosine" decay to
    # ``final_lr_ratio`` x lr at ``steps``, or "constant" (the original's setting).
    schedule: str = "cosine"
    warmup_steps: int = 1000
    final_lr_ratio: float = 0.05
    clip_norm: float = 1.0  # global gradient-norm clip (0 = off)
    # Validation on pairs whose OBJECT is in a fixed subset of the training objects
    # (``data.validation_objects``, the same subset as Stage 3's): losses and the Stage-1
    # pose-error proxy every ``eval_every`` steps over ``val_batches`` fixed batches.
    val_fraction: float = 0.1
    eval_every: int = 1000
    val_batches: int = 8
    # Stage-1 training augmentation (ours, ``omnihang_jax.augment``): point noise (m) and a
    # random turn of the whole pair about the vertical in [-augment_yaw, augment_yaw] (rad).
    # 0 = off: the step is then exactly the unaugmented one (same keys).
    augment_jitter: float = 0.0
    augment_yaw: float = 0.0
    # Stages 1 and 2: every sample's object read about its box centre, in the frame that the
    # nearest of M frame hypotheses leaves of a uniform random frame (``where.FRAMES`` reads
    # objects so); 1 = a uniform random frame, 0 = off (``augment.augment_pair``)
    augment_object_turn: int = 0


@dataclasses.dataclass(frozen=True)
class NetworksConfig:
    """Everything needed to rebuild and train the "where to hang" networks."""

    stage1: Stage1Config = STAGE1_ORIGINAL
    stage2: Stage2Config = STAGE2_ORIGINAL
    train: TrainConfig = TrainConfig()
    canon: CanonConfig = CANON_SMALL  # the object-frame network (``omnihang_jax.canon``)
    preset: str = "original"

    @property
    def num_object_points(self) -> int:
        return self.stage1.encoder.num_points


WHERE_ORIGINAL = NetworksConfig()
WHERE_TINY = NetworksConfig(
    stage1=STAGE1_TINY,
    stage2=STAGE2_TINY,
    canon=CANON_TINY,
    # constant lr, no clipping: the tests memorise a few pairs in a few hundred steps
    train=TrainConfig(
        batch_size=8,
        log_every=10,
        checkpoint_every=100,
        synthetic_pairs=32,
        schedule="constant",
        clip_norm=0.0,
        eval_every=10,
        val_batches=2,
    ),
    preset="tiny",
)
WHERE_SMALL = NetworksConfig(
    stage1=STAGE1_SMALL,
    stage2=STAGE2_SMALL,
    train=TrainConfig(batch_size=8, log_every=25, checkpoint_every=250, synthetic_pairs=32),
    preset="small",
)
PRESETS = {"original": WHERE_ORIGINAL, "tiny": WHERE_TINY, "small": WHERE_SMALL}


@flax.struct.dataclass
class TrainState:
    """step: [] int32; params: the stage's parameter tree; opt_state: optax state."""

    step: jax.Array
    params: Any
    opt_state: Any


# ----------------------------------------------------------------------------------------------
# Train state and step


def learning_rate_schedule(stage: str, config: NetworksConfig) -> optax.Schedule:
    """The stage's learning rate per step (``TrainConfig.schedule``, warm-up + cosine)."""
    cfg = config.train
    lr = cfg.lr_stage1 if stage in ("1", "canon") else cfg.lr_stage2
    if cfg.schedule == "constant":
        return optax.constant_schedule(lr)
    if cfg.schedule != "cosine":
        raise ValueError(f"unknown schedule {cfg.schedule!r}; expected 'cosine' or 'constant'")
    total = max(int(cfg.steps), 2)
    warmup = min(int(cfg.warmup_steps), total // 10)
    return optax.warmup_cosine_decay_schedule(
        init_value=lr * (0.0 if warmup else 1.0),
        peak_value=lr,
        warmup_steps=warmup,
        decay_steps=total,
        end_value=lr * cfg.final_lr_ratio,
    )


def make_optimizer(stage: str, config: NetworksConfig) -> optax.GradientTransformation:
    """Adam on the stage's schedule, after global-norm clipping (``clip_norm`` > 0)."""
    adam = optax.adam(learning_rate_schedule(stage, config))
    if config.train.clip_norm > 0:
        return optax.chain(optax.clip_by_global_norm(config.train.clip_norm), adam)
    return adam


def make_init_state(stage: str, config: NetworksConfig) -> Callable[..., TrainState]:
    """``init(key, params=None) -> TrainState``; ``params`` overrides the random init (2b from
    2a)."""
    tx = make_optimizer(stage, config)
    if stage == "canon":
        net_init = make_canon(config.canon).init
    elif stage == "1":
        net_init = make_stage1(config.stage1).init
    else:
        net_init = make_stage2(config.stage2).init

    def init(key, params=None) -> TrainState:
        params = net_init(key) if params is None else params
        return TrainState(step=jnp.array(0, jnp.int32), params=params, opt_state=tx.init(params))

    return init


def make_train_step(stage: str, config: NetworksConfig) -> Callable:
    """``train_step(state, batch: HangSample, key) -> (state, metrics)``: one Adam step.

    Pure; jit it once at the top (``jax.jit(make_train_step(stage, config))``).
    """
    loss_fn = make_loss_fn(stage, config)
    tx = make_optimizer(stage, config)
    schedule = learning_rate_schedule(stage, config)  # logged per step

    cfg = config.train
    augmenting = stage == "1" and (cfg.augment_jitter > 0 or cfg.augment_yaw > 0)
    # Stage 1 turns inside augment_pair; the object-frame network turns its clouds itself
    turning = stage in ("2a", "2b") and cfg.augment_object_turn

    def train_step(state: TrainState, batch: HangSample, key):
        if augmenting or (stage == "1" and cfg.augment_object_turn):
            key, k_aug = jax.random.split(key)
            batch = augment.augment_pair(batch, k_aug, cfg.augment_jitter, cfg.augment_yaw,
                                         cfg.augment_object_turn)  # fmt: skip
        elif turning:
            key, k_aug = jax.random.split(key)
            batch = augment.augment_pair(batch, k_aug, 0.0, 0.0, True)
        grads, metrics = jax.grad(loss_fn, has_aux=True)(state.params, batch, key)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        metrics = dict(metrics, grad_norm=optax.global_norm(grads), lr=schedule(state.step))
        return TrainState(step=state.step + 1, params=params, opt_state=opt_state), metrics

    return train_step


def make_eval_step(stage: str, config: NetworksConfig) -> Callable:
    """``eval_step(params, batch, key) -> metrics``: the stage's loss and metrics, no update.
    With ``augment_object_turn`` the objects are turned as in training (from ``key``: the
    validator's keys are fixed), so validation measures the frames the network is made for."""
    loss_fn = make_loss_fn(stage, config)
    turn = config.train.augment_object_turn if stage != "canon" else 0

    def eval_step(params, batch: HangSample, key):
        if turn:
            key, k_aug = jax.random.split(key)
            batch = augment.augment_pair(batch, k_aug, 0.0, 0.0, turn)
        return loss_fn(params, batch, key)[1]

    return eval_step


# ----------------------------------------------------------------------------------------------
# Host loop, checkpoints, logs


@functools.lru_cache(maxsize=16)
def _jitted(stage: str, config: NetworksConfig) -> tuple[Callable, Callable, Callable]:
    """Jit init and step once per (stage, config): resuming in one process does not recompile."""
    return (
        jax.jit(make_init_state(stage, config)),
        jax.jit(make_train_step(stage, config)),
        jax.jit(make_eval_step(stage, config)),
    )


def _stage_dir(workdir: str, stage: str) -> str:
    return os.path.join(os.path.abspath(workdir), f"stage{stage}")


def _write_config(stage_dir: str, stage: str, config: NetworksConfig) -> None:
    """Write config.json; refuse to resume a folder trained with another architecture."""
    path = os.path.join(stage_dir, "config.json")
    if os.path.exists(path):
        with open(path) as f:
            old = config_from_dict(NetworksConfig, json.load(f)["config"])
        if (old.stage1, old.stage2, old.canon) != (config.stage1, config.stage2, config.canon):
            raise ValueError(
                f"{stage_dir} holds a model with a different architecture (preset "
                f"{old.preset!r}); use another --out folder or the same preset"
            )
    with open(path, "w") as f:
        json.dump({"stage": stage, "config": config_to_dict(config)}, f, indent=2)


def _checkpoint_manager(stage_dir: str, config: NetworksConfig) -> ocp.CheckpointManager:
    return ocp.CheckpointManager(
        os.path.join(stage_dir, "checkpoints"),
        options=ocp.CheckpointManagerOptions(max_to_keep=config.train.max_to_keep, create=True),
    )


def _restore(manager: ocp.CheckpointManager, target: TrainState, step: int) -> TrainState:
    abstract = jax.tree.map(
        ocp.utils.to_shape_dtype_struct, flax.serialization.to_state_dict(target)
    )
    restored = manager.restore(step, args=ocp.args.StandardRestore(abstract))
    return flax.serialization.from_state_dict(target, restored)


def restore_stage(stage_dir: str, step: int | None = None) -> tuple[NetworksConfig, Any, int]:
    """Rebuild a trained stage from its folder alone.

    stage_dir: e.g. ``out/stage1``. Returns (config, params, step) of the latest (or given)
    checkpoint. Raises FileNotFoundError when the folder has no config or checkpoint.
    """
    stage_dir = os.path.abspath(stage_dir)
    path = os.path.join(stage_dir, "config.json")
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path} not found: not a trained stage folder")
    with open(path) as f:
        saved = json.load(f)
    stage, config = saved["stage"], config_from_dict(NetworksConfig, saved["config"])
    exported = os.path.join(stage_dir, WEIGHTS_FILE)
    if not os.path.isdir(os.path.join(stage_dir, "checkpoints")) and os.path.exists(exported):
        target = jax.eval_shape(make_init_state(stage, config), jax.random.key(0)).params
        with open(exported, "rb") as f:
            params = flax.serialization.from_bytes(target, f.read())
        return config, jax.tree.map(jnp.asarray, params), int(saved.get("step", -1))
    manager = _checkpoint_manager(stage_dir, config)
    step = manager.latest_step() if step is None else step
    if step is None:
        raise FileNotFoundError(f"no checkpoint under {stage_dir}/checkpoints")
    target = jax.eval_shape(make_init_state(stage, config), jax.random.key(0))
    state = _restore(manager, target, step)
    manager.close()
    return config, state.params, step


WEIGHTS_FILE = "params.msgpack"


def _network_fields(config: NetworksConfig, stage: str):
    """The parts of a config that shape a stage's parameters."""
    if stage == "canon":
        return config.canon
    return config.stage1 if stage == "1" else config.stage2.pointnet


def export_weights(
    run_dir: str, out_dir: str, stages: Sequence[str] = ALL_STAGES, which: str = "latest"
) -> dict[str, int]:
    """Copy a training folder's parameters (no optimiser state, no checkpoint history)
    to ``out_dir/stage<name>/{config.json, params.msgpack}``: a few MB that
    :func:`restore_stage` and ``predict.load_predictor`` read like the full folder.
    which: "latest" checkpoint, or "best" (lowest validation loss, ``best/``; the latest
    where a stage has no validation record).
    Returns the exported step per stage; stages without a trained folder are skipped."""
    if which not in ("latest", "best"):
        raise ValueError(f"which must be 'latest' or 'best', got {which!r}")
    steps = {}
    for stage in stages:
        src = _stage_dir(run_dir, stage)
        if not os.path.exists(os.path.join(src, "config.json")):
            continue
        config, params, step = restore_stage(src)
        best_json = os.path.join(src, "best", "best.json")
        if which == "best" and os.path.exists(best_json):
            with open(best_json) as f:
                step = int(json.load(f)["step"])
            with open(os.path.join(src, "best", WEIGHTS_FILE), "rb") as f:
                params = flax.serialization.from_bytes(jax.device_get(params), f.read())
        dst = _stage_dir(out_dir, stage)
        os.makedirs(dst, exist_ok=True)
        with open(os.path.join(src, "config.json")) as f:
            saved = json.load(f)
        saved["step"] = int(step)
        with open(os.path.join(dst, WEIGHTS_FILE), "wb") as f:
            f.write(flax.serialization.to_bytes(jax.device_get(params)))
        with open(os.path.join(dst, "config.json"), "w") as f:
            json.dump(saved, f, indent=2)
        steps[stage] = int(step)
    return steps


def _to_float(metrics: dict) -> dict:
    return {k: float(v) for k, v in metrics.items()}


_LOSS_KEYS = ("loss", "huber", "contact_loss", "cross_entropy", "listnet", "listnet_excess")


def plot_metrics(metrics_path: str, png_path: str) -> None:
    """Plot a metrics.jsonl: losses (log scale) on the left, other metrics on the right."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(metrics_path) as f:
        rows = [json.loads(line) for line in f if line.strip()]
    if not rows:
        return
    val_path = os.path.join(os.path.dirname(metrics_path), "val_metrics.jsonl")
    val_rows = []
    if os.path.exists(val_path):
        with open(val_path) as f:
            val_rows = [json.loads(line) for line in f if line.strip()]
    steps = [r["step"] for r in rows]
    skip = ("step", "grad_norm", "lr")
    loss_keys = [k for k in rows[-1] if k in _LOSS_KEYS]
    other_keys = [k for k in rows[-1] if k not in _LOSS_KEYS and k not in skip]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, keys, scale in ((axes[0], loss_keys, "log"), (axes[1], other_keys, "linear")):
        for k in keys:
            (line,) = ax.plot(steps, [r.get(k, np.nan) for r in rows], label=k, alpha=0.7)
            if val_rows and f"val_{k}" in val_rows[-1]:
                ax.plot([r["step"] for r in val_rows], [r.get(f"val_{k}", np.nan) for r in val_rows],
                        "--o", ms=3, color=line.get_color(), label=f"val {k}")  # fmt: skip
        ax.set_yscale(scale)
        ax.set_xlabel("step")
        if keys:
            ax.legend(fontsize=7)
    axes[0].set_title(f"{os.path.basename(os.path.dirname(metrics_path))}: losses")
    axes[1].set_title("metrics")
    fig.tight_layout()
    fig.savefig(png_path, dpi=100)
    plt.close(fig)


def train_stage(
    stage: str,
    config: NetworksConfig,
    dataset: data_lib.HangDataset,
    workdir: str,
    steps: int | None = None,
    init_params: Any = None,
    progress: bool = True,
    time_budget_s: float | None = None,
    val_dataset: data_lib.HangDataset | None = None,
) -> TrainState:
    """Train one stage to ``steps`` total steps, resuming from ``workdir/stage<stage>``.

    val_dataset: pairs of held-out training objects; every ``eval_every`` steps (and at the
    end) the stage's metrics over ``val_batches`` fixed batches go to ``val_metrics.jsonl``
    (keys ``val_*``), and the parameters with the lowest validation loss so far to
    ``best/params.msgpack`` (+ ``best/best.json``; :func:`export_weights` can take them).

    time_budget_s: stop earlier, after the step that passes this many seconds of training
    after the first (compiling) step (a checkpoint is saved there; rerun to continue). The next batch is read in a background thread
    while the device runs the step. ``stage<stage>/throughput.json`` gets the measured
    training samples/s (steps after the first, which includes compilation).

    init_params: parameters to start from when no checkpoint exists (2b starts from 2a).
    Data and noise are keyed by (seed, step), so a resumed run continues the same stream.
    Returns the final TrainState.
    """
    from tqdm.auto import tqdm

    if stage not in ALL_STAGES:
        raise ValueError(f"unknown stage {stage!r}; expected one of {ALL_STAGES}")
    steps = config.train.steps if steps is None else steps
    stage_dir = _stage_dir(workdir, stage)
    os.makedirs(stage_dir, exist_ok=True)
    _write_config(stage_dir, stage, config)

    seed, stage_id = config.train.seed, ALL_STAGES.index(stage)
    init_key, base_key = jax.random.split(jax.random.fold_in(jax.random.key(seed), stage_id))
    init_state, train_step, eval_step = _jitted(stage, config)
    state = init_state(init_key, init_params)
    manager = _checkpoint_manager(stage_dir, config)
    if manager.latest_step() is not None:
        state = _restore(manager, state, manager.latest_step())
    start = int(state.step)
    # data parallel over every visible device (one device: unchanged)
    mesh = sharding.data_mesh()
    state = sharding.replicate(state, mesh)

    metrics_path = os.path.join(stage_dir, "metrics.jsonl")
    log_every, ckpt_every = config.train.log_every, config.train.checkpoint_every
    bar = tqdm(
        range(start, steps), desc=f"stage {stage}", disable=not progress, initial=start, total=steps
    )

    def load(step: int) -> HangSample:
        return dataset.sample_batch(np.random.default_rng([seed, stage_id, step]), batch_size)

    batch_size = config.train.batch_size
    validate = _make_validator(stage, config, val_dataset, eval_step, stage_dir)
    t_start = time.perf_counter()
    t_first = None  # after the first step (compilation) has finished
    done = start
    with ThreadPoolExecutor(1) as prefetch:
        upcoming = prefetch.submit(load, start) if start < steps else None
        for step in bar:
            batch = upcoming.result()
            if step + 1 < steps:
                upcoming = prefetch.submit(load, step + 1)
            batch = sharding.shard_batch(batch, mesh)
            state, metrics = train_step(state, batch, jax.random.fold_in(base_key, step))
            done = step + 1
            if t_first is None:
                jax.block_until_ready(state.step)
                t_first = time.perf_counter()
                first_step_s = t_first - t_start
            # the budget counts training time, not the first step's compilation (under load
            # it took longer than a short budget, and a stage stopped after one step)
            out_of_time = (
                time_budget_s is not None and time.perf_counter() - t_first > time_budget_s
            )
            if done % log_every == 0 or done == steps or out_of_time:
                row = {"step": done, **_to_float(metrics)}
                with open(metrics_path, "a") as f:
                    f.write(json.dumps(row) + "\n")
                bar.set_postfix(loss=f"{row['loss']:.4g}")
            eval_every = config.train.eval_every
            if validate and (done % eval_every == 0 or done == steps or out_of_time):
                validate(state.params, done)
            if done % ckpt_every == 0 or done == steps or out_of_time:
                manager.save(
                    done, args=ocp.args.StandardSave(flax.serialization.to_state_dict(state))
                )
            if out_of_time:
                break
    jax.block_until_ready(state.params)
    t_end = time.perf_counter()
    manager.wait_until_finished()
    manager.close()
    if t_first is not None and done - start > 1:
        timed = done - start - 1
        throughput = {
            "stage": stage,
            "steps_this_run": done - start,
            "steps_timed": timed,
            "batch_size": batch_size,
            "samples_per_s": timed * batch_size / (t_end - t_first),
            "step_ms": 1000 * (t_end - t_first) / timed,
            "first_step_s": first_step_s,
            "stopped_by_time_budget": done < steps,
            "device": str(jax.devices()[0].device_kind),
            "jax": jax.__version__,
        }
        with open(os.path.join(stage_dir, "throughput.json"), "w") as f:
            json.dump(throughput, f, indent=1)
    if os.path.exists(metrics_path):
        plot_metrics(metrics_path, os.path.join(stage_dir, "loss.png"))
    return state


def _make_validator(stage, config, val_dataset, eval_step, stage_dir):
    """``validate(params, step)`` for :func:`train_stage`, or None without validation pairs.

    The batches are fixed (same pairs, same noise keys every time), so the curve measures the
    parameters, not the sampling; the best parameters so far are kept under ``best/``."""
    if val_dataset is None or len(val_dataset) == 0 or config.train.val_batches <= 0:
        return None
    val_path = os.path.join(stage_dir, "val_metrics.jsonl")
    best_dir = os.path.join(stage_dir, "best")
    best_json = os.path.join(best_dir, "best.json")
    best = {"val_loss": float("inf")}
    if os.path.exists(best_json):
        with open(best_json) as f:
            best = json.load(f)
    batches = [
        val_dataset.sample_batch(
            np.random.default_rng([config.train.seed, 777, i]), config.train.batch_size
        )  # fmt: skip
        for i in range(config.train.val_batches)
    ]
    key = jax.random.key(config.train.seed + 777)

    def validate(params, step: int) -> dict:
        rows = [_to_float(eval_step(params, b, jax.random.fold_in(key, i)))
                for i, b in enumerate(batches)]  # fmt: skip
        row = {"step": int(step), "val_pairs": len(val_dataset)}
        row.update({f"val_{k}": float(np.mean([r[k] for r in rows])) for k in rows[0]})
        with open(val_path, "a") as f:
            f.write(json.dumps(row) + "\n")
        if row["val_loss"] < best["val_loss"]:
            best.clear()
            best.update(step=int(step), val_loss=row["val_loss"])
            os.makedirs(best_dir, exist_ok=True)
            with open(os.path.join(best_dir, WEIGHTS_FILE), "wb") as f:
                f.write(flax.serialization.to_bytes(jax.device_get(params)))
            with open(best_json, "w") as f:
                json.dump(best, f, indent=1)
        return row

    return validate


STAGE1_FIELDS = ("object_points", "support_points", "stable_poses", "pose_mask")


def make_dataset(
    data: str,
    config: NetworksConfig,
    split: str = "train",
    on_device: bool = False,
    fields: Sequence[str] | None = None,
) -> tuple[data_lib.HangDataset, data_lib.HangDataset | None]:
    """(fit, validation) datasets.

    ``"synthetic"`` -> an in-memory pool of ring-on-peg pairs (no validation set); a folder
    with ``pack.json`` (``data.pack_dataset``) -> :class:`data.PackedDataset` on the device
    (``fields``: only these on the device); else a dataset directory
    (``data.load_hang_dataset``; several, comma-separated, are read as one; ``on_device``:
    all pairs in device memory). Pairs whose
    object is in the fixed validation subset of objects (``TrainConfig.val_fraction``) form
    the validation set, never trained on.
    """
    if data == "synthetic":
        n = config.num_object_points
        pool = data_lib.synthetic_batch(
            jax.random.key(config.train.seed + 12345), config.train.synthetic_pairs, n
        )
        return data_lib.ArrayDataset(pool), None
    fraction = config.train.val_fraction
    if os.path.exists(os.path.join(data, data_lib.PACK_FILE)):
        with open(os.path.join(data, data_lib.PACK_FILE)) as f:
            meta = json.load(f)
        names = meta["object_names"]
        missing = [f for f in (fields or HangSample._fields) if "contact" in f]
        if missing and not meta.get("has_contact_maps", True):
            raise ValueError(
                f"{data} was packed from --clouds-only pairs (no contact maps): it trains Stage 1 "
                "only (--stage 1); pack a fully derived split for Stage 2"
            )
        fit, val = data_lib.split_by_object(names, fraction)
        return (
            data_lib.PackedDataset(data, fit, fields),
            data_lib.PackedDataset(data, val, fields) if len(val) else None,
        )
    # several folders, comma-separated (e.g. more views of the same pairs): one dataset, the
    # validation objects held out of every folder
    folders = [d for d in data.split(",") if d]
    parts = [data_lib.load_hang_dataset(d, split=split, cache=True) for d in folders]
    full = parts[0]
    if len(parts) > 1:
        full = data_lib.NpzDirectoryDataset([f for p in parts for f in p.files],
                                            max_contacts=max(p.max_contacts for p in parts),
                                            cache=True)  # fmt: skip
    fit, val = data_lib.split_by_object([data_lib.object_name_of(f) for f in full.files], fraction)

    def subset(idx):
        files = [full.files[i] for i in idx]
        if on_device:
            return data_lib.DeviceDataset(files, max_contacts=full.max_contacts)
        return data_lib.NpzDirectoryDataset(files, max_contacts=full.max_contacts, cache=True)

    return subset(fit), (subset(val) if len(val) else None)


def train_where(
    data: str,
    out: str,
    stages: Sequence[str] = STAGES,
    config: NetworksConfig = WHERE_ORIGINAL,
    steps: int | None = None,
    progress: bool = True,
    time_budget_s: dict[str, float] | None = None,
    data_on_device: bool = False,
    init_from: str | None = None,
) -> dict[str, TrainState]:
    """Train the requested stages in order (1, 2a, 2b) into ``out``; resumes each stage.

    2b starts from 2a's latest parameters when it has no checkpoint of its own.
    ``init_from``: a weights folder (``export_weights``' layout, e.g. weights/stage12)
    whose stage parameters start a stage that has no checkpoint yet (fine-tuning; fresh
    optimiser state and schedule); its network config must equal ``config``'s.
    Returns the final TrainState per stage.
    """
    if steps is not None:  # the schedule decays over the run's total steps
        config = dataclasses.replace(config, train=dataclasses.replace(config.train, steps=steps))
    fields = STAGE1_FIELDS if set(stages) <= {"1", "canon"} else None
    dataset, val_dataset = make_dataset(data, config, on_device=data_on_device, fields=fields)
    states = {}
    for stage in ALL_STAGES:
        if stage not in stages:
            continue
        init_params = None
        if init_from is not None and os.path.exists(
            os.path.join(_stage_dir(init_from, stage), "config.json")
        ):
            init_config, init_params, init_step = restore_stage(_stage_dir(init_from, stage))
            if _network_fields(init_config, stage) != _network_fields(config, stage):
                raise ValueError(
                    f"--init-from {init_from}: stage {stage}'s network config differs from the "
                    "preset's (same --preset as those weights?)"
                )
            print(f"stage {stage}: parameters from {init_from} (step {init_step})")
        elif stage == "2b":
            if "2a" in states:
                init_params = states["2a"].params
            elif os.path.exists(os.path.join(_stage_dir(out, "2a"), "config.json")):
                init_params = restore_stage(_stage_dir(out, "2a"))[1]
        budget = (time_budget_s or {}).get(stage)
        states[stage] = train_stage(
            stage, config, dataset, out, steps, init_params, progress, time_budget_s=budget,
            val_dataset=val_dataset,
        )  # fmt: skip
    return states
