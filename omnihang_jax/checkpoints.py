"""The resumable training loop's bookkeeping of a point-set trainer that saves a
best-on-validation network and continues a killed run (``completion.train_completion``): the
optimiser and its schedule, the run folder's ``run.json`` check, and the checkpoint written at
every evaluation.

A run folder holds ``run.json`` (the network and training configs), ``history.jsonl`` (one row
per evaluation) and ``checkpoint.msgpack`` (params, optimiser state, step, best validation figure
and its step). A folder with a checkpoint of another network or batch size is refused, not
overwritten; a folder without a checkpoint starts a fresh history.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import flax.serialization
import jax
import optax

__all__ = ["CHECKPOINT_FILE", "optimizer", "open_run", "save_checkpoint"]

CHECKPOINT_FILE = "checkpoint.msgpack"


def optimizer(tc) -> tuple[optax.GradientTransformation, optax.Schedule]:
    """``tc`` (``lr``, ``warmup``, ``steps``, ``weight_decay``) -> AdamW with a warm-up then cosine
    decay to 2 % of ``lr``, gradients clipped to norm 1, and its schedule."""
    sched = optax.warmup_cosine_decay_schedule(
        0.0, tc.lr, tc.warmup, max(tc.steps, tc.warmup + 1), tc.lr * 0.02
    )
    opt = optax.chain(
        optax.clip_by_global_norm(1.0), optax.adamw(sched, weight_decay=tc.weight_decay)
    )
    return opt, sched


def open_run(folder: Path, config, tc, state: dict, name: str) -> dict:
    """Start or resume the run in ``folder``: ``state`` (params, opt, step, best, best_step) is the
    fresh one, returned as is, or the checkpoint's. Writes ``run.json``; raises ValueError when the
    folder's checkpoint is of another network (``config``) or batch size."""
    from sim import atomic

    ckpt, history = folder / CHECKPOINT_FILE, folder / "history.jsonl"
    run = json.loads(json.dumps(dict(config=dataclasses.asdict(config),
                                     train=dataclasses.asdict(tc))))  # fmt: skip
    if ckpt.exists() and (folder / "run.json").exists():
        old = json.loads((folder / "run.json").read_text())
        if old["config"] != run["config"] or old["train"]["batch"] != tc.batch:
            raise ValueError(f"{folder}: a checkpoint of another network or batch is there "
                             f"({old}); choose another folder or delete it")  # fmt: skip
    atomic.write_text(folder / "run.json", json.dumps(run, indent=2))
    if ckpt.exists():
        state = flax.serialization.from_bytes(state, ckpt.read_bytes())
        state["step"] = int(state["step"])
        print(f"{name}: resuming at step {state['step']}", flush=True)
    elif history.exists():
        history.unlink()
    return state


def save_checkpoint(
    folder: Path, params, opt_state, step: int, best: float, best_step: int
) -> dict:
    """Write the run's checkpoint atomically; returns the state it holds."""
    from sim import atomic

    state = dict(params=params, opt=opt_state, step=step, best=best, best_step=best_step)
    blob = flax.serialization.to_bytes(jax.device_get(state))
    atomic.write_atomic(folder / CHECKPOINT_FILE, lambda f, b=blob: f.write(b))
    return state
