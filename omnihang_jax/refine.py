"""Stage 3 training: transitions (pose, reward) from simulation, a success/failure replay
buffer sampled 50/50 (facts), and the value function trained on it (host loop).

The pieces, host and device kept apart:

* :class:`PairBank` (host numpy, copied once to the device): the subsampled observed clouds
  of many pairs, indexed by a slot; transitions refer to pairs by slot.
* :class:`ReplayBuffer` (host numpy, ``.npz`` on disk): ``slot, pose [7], reward, source,
  round`` per transition; ``sample`` draws half from successes and half from failures.
* :func:`label_poses` (host, a process pool): reward 1 iff ``sim.kernels.stability`` under
  ``omnihang_jax.evaluate.protocol_stability`` says STABLE; one batched rollout per pair,
  never a call per pose. Diverged or non-finite poses are failures.
* :func:`make_value_trainer` (device, pure + jitted): one AdamW step with warm-up + cosine
  schedule and global-norm clipping on a batch gathered on the device.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import flax.serialization
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from omnihang_jax import stage3
from omnihang_jax.stage3 import PairClouds, ValueConfig

__all__ = [
    "SOURCES",
    "HARD_SOURCES",
    "PairBank",
    "ReplayBuffer",
    "perturb_poses",
    "uniform_poses",
    "label_poses",
    "ValueTrainState",
    "make_value_trainer",
    "save_value",
    "load_value",
]

# Where a transition came from (ReplayBuffer.source).
SOURCES = ("stable", "perturbed", "stage1", "stage2", "cem", "uniform", "cem_explore", "cem_top")
# The hard cases: poses CEM chose or V scored highest in CEM's final populations (V's false
# positives are among them); ``ReplayBuffer.sample(hard_fraction=...)`` draws a stream of them.
HARD_SOURCES = ("cem", "cem_top")


# ----------------------------------------------------------------------------------------------
# Pairs


@dataclasses.dataclass
class PairBank:
    """Observed clouds of P pairs, subsampled for V (``stage3.subsample_clouds``).

    clouds: PairClouds of [P, n, 3] float32; meta: one dict per pair (pair_index, object_name,
    support_name, object_category, support_family, split, file); stable_poses: list of [D, 7].
    """

    clouds: PairClouds
    meta: list[dict]
    stable_poses: list[np.ndarray]

    def __len__(self) -> int:
        return len(self.meta)

    @classmethod
    def from_files(
        cls, files: Sequence[str | os.PathLike], config: ValueConfig, progress: bool = True
    ) -> PairBank:
        """Read the pair files (only the clouds, stable poses and metadata: not the contact
        maps) and subsample the clouds as ``stage3.subsample_clouds`` does."""
        from tqdm.auto import tqdm

        parts, meta, stable = [], [], []
        for f in tqdm(files, desc="load pairs", unit="pair", disable=not progress):
            c, m, sp = _read_pair_light(f, config)
            parts.append(c)
            meta.append(m)
            stable.append(sp)
        if not parts:
            n = len(stage3.subsample_index(1, config, "object"))
            m = len(stage3.subsample_index(1, config, "support"))
            clouds = PairClouds(*(np.zeros((0, k, 3), np.float32) for k in (n, n, m, m)))
            return cls(clouds, [], [])
        clouds = PairClouds(*(np.stack(x) for x in zip(*parts, strict=True)))
        return cls(clouds, meta, stable)

    def extend(self, other: PairBank) -> None:
        """Append ``other``'s pairs (slots continue after this bank's)."""
        self.clouds = PairClouds(
            *(np.concatenate([a, b]) for a, b in zip(self.clouds, other.clouds, strict=True))
        )
        self.meta = self.meta + other.meta
        self.stable_poses = self.stable_poses + other.stable_poses

    def save(self, path: str | os.PathLike) -> None:
        """One ``.npz`` (clouds, metadata as JSON, stable poses concatenated + offsets): a
        job reloads it instead of re-reading thousands of pair files."""
        from sim import atomic

        counts = np.array([len(p) for p in self.stable_poses], np.int64)
        atomic.savez(
            os.fspath(path),
            compressed=False,  # ~0.7 GB at 15k pairs: compression would cost a minute
            **{f: getattr(self.clouds, f) for f in PairClouds._fields},
            meta=np.array(json.dumps(self.meta)),
            stable=np.concatenate(self.stable_poses) if len(self) else np.zeros((0, 7), np.float32),
            stable_offsets=np.concatenate([[0], np.cumsum(counts)]),
        )

    @classmethod
    def load(cls, path: str | os.PathLike) -> PairBank:
        with np.load(path) as z:
            clouds = PairClouds(*(z[f] for f in PairClouds._fields))
            meta = json.loads(z["meta"].item())
            off, st = z["stable_offsets"], z["stable"]
        stable = [st[off[i] : off[i + 1]] for i in range(len(meta))]
        return cls(clouds, meta, stable)


def _read_pair_light(path, config: ValueConfig):
    """(subsampled PairClouds of numpy, metadata dict, stable poses [D, 7]) of a pair file."""
    from omnihang_jax.dataset_bridge import META_KEYS

    with np.load(path) as f:
        missing = [k for k in META_KEYS if k not in f.files]
        if missing:
            raise ValueError(f"{path}: no pair metadata {missing}; derive it with derive_dataset")
        op, on = f["object_points"], f["object_normals"]
        sp, sn = f["support_points"], f["support_normals"]
        poses = np.asarray(f["stable_poses"], np.float32)
        mask = np.asarray(f["pose_mask"], bool) if "pose_mask" in f.files else None
        meta = {k: f[k].item() for k in META_KEYS}
    meta["pair_index"] = int(meta["pair_index"])
    meta["file"] = os.fspath(path)
    io = stage3.subsample_index(len(op), config, "object")
    js = stage3.subsample_index(len(sp), config, "support")
    clouds = PairClouds(*(np.asarray(x, np.float32) for x in (op[io], on[io], sp[js], sn[js])))
    return clouds, meta, poses if mask is None else poses[mask]


# ----------------------------------------------------------------------------------------------
# Replay buffer


class ReplayBuffer:
    """Transitions (slot, pose, reward) of a :class:`PairBank`, saved as one ``.npz``."""

    FIELDS = {"slot": np.int32, "pose": np.float32, "reward": np.uint8, "source": np.uint8,
              "round": np.int16}  # fmt: skip

    def __init__(self):
        self.data = {k: np.zeros((0, 7) if k == "pose" else 0, t) for k, t in self.FIELDS.items()}
        self._index = None  # (length, positives, negatives, hard positives, hard negatives)

    def __len__(self) -> int:
        return len(self.data["slot"])

    def add(self, slots, poses, rewards, source: str, round_index: int = 0) -> None:
        slots = np.asarray(slots, np.int32).reshape(-1)
        poses = np.asarray(poses, np.float32).reshape(-1, 7)
        rewards = np.asarray(rewards).reshape(-1)
        if not (len(slots) == len(poses) == len(rewards)):
            raise ValueError("slots, poses and rewards must have one row per transition")
        keep = np.isfinite(poses).all(1)  # a non-finite pose has no state to learn from
        new = {
            "slot": slots[keep],
            "pose": poses[keep],
            "reward": rewards[keep].astype(np.uint8),
            "source": np.full(keep.sum(), SOURCES.index(source), np.uint8),
            "round": np.full(keep.sum(), round_index, np.int16),
        }
        self.data = {k: np.concatenate([self.data[k], new[k]]) for k in self.FIELDS}
        self._index = None

    def select(self, mask: np.ndarray) -> ReplayBuffer:
        out = ReplayBuffer()
        out.data = {k: v[mask] for k, v in self.data.items()}
        out._index = None
        return out

    def sample(
        self, rng: np.random.Generator, batch: int, hard_fraction: float = 0.0
    ) -> np.ndarray:
        """Indices: half successes, half failures (facts), with replacement; all from one
        side when the other is empty.

        ``hard_fraction`` f > 0: a third stream, ``round(f * batch)`` of the indices drawn
        from the hard cases (sources ``HARD_SOURCES``: CEM's answers and the top-scored
        members of its final populations), again half successes and half failures (all
        failures when the hard cases hold no success), the rest 50/50 from everything. So the
        batch stays balanced while the poses V liked most, and the false positives among them,
        come far more often than their share of the buffer."""
        r = self.data["reward"]
        if self._index is None or self._index[0] != len(r):  # once per buffer, not per batch
            hard = np.isin(self.data["source"], [SOURCES.index(s) for s in HARD_SOURCES])
            self._index = (len(r), np.flatnonzero(r == 1), np.flatnonzero(r == 0),
                           np.flatnonzero(hard & (r == 1)), np.flatnonzero(hard & (r == 0)))  # fmt: skip
        _, pos, neg, hp, hn = self._index
        n_hard = int(round(hard_fraction * batch)) if hard_fraction > 0 else 0
        out = []
        if n_hard:
            if len(hn):
                h = n_hard // 2 if len(hp) else 0
                out += [rng.choice(hp, h) if h else np.zeros(0, np.int64),
                        rng.choice(hn, n_hard - h)]  # fmt: skip
            else:
                n_hard = 0
        rest = batch - n_hard
        if len(pos) == 0 or len(neg) == 0:
            out.append(rng.integers(len(r), size=rest))
        else:
            h = rest // 2
            out += [rng.choice(pos, h), rng.choice(neg, rest - h)]
        return np.concatenate(out).astype(np.int64)

    def stats(self) -> dict:
        r, s = self.data["reward"], self.data["source"]
        out = {"transitions": len(self), "successes": int(r.sum())}
        for i, name in enumerate(SOURCES):
            m = s == i
            if m.any():
                out[name] = {"n": int(m.sum()), "success_rate": float(r[m].mean())}
        return out

    def save(self, path: str | os.PathLike) -> None:
        from sim import atomic

        # uncompressed: saved after every round, millions of rows at full scale
        atomic.savez(os.fspath(path), compressed=False, **self.data)

    @classmethod
    def load(cls, path: str | os.PathLike) -> ReplayBuffer:
        out = cls()
        with np.load(path) as z:
            missing = set(cls.FIELDS) - set(z.files)
            if missing:
                raise ValueError(f"{path}: not a replay buffer (missing {sorted(missing)})")
            out.data = {k: z[k].astype(t) for k, t in cls.FIELDS.items()}
        return out


# ----------------------------------------------------------------------------------------------
# Candidate poses


def perturb_poses(
    poses: np.ndarray, rng: np.random.Generator, n: int, translation: float, rotation: float
) -> np.ndarray:
    """[n, 7] copies of random rows of ``poses`` shifted uniformly within +-``translation``
    per axis (m) and turned about their origin by a rotation vector uniform within
    +-``rotation`` per component (rad): the CEM box around a stable pose."""
    from scipy.spatial.transform import Rotation

    poses = np.asarray(poses, np.float64).reshape(-1, 7)
    base = poses[rng.integers(len(poses), size=n)]
    shift = rng.uniform(-translation, translation, size=(n, 3))
    turn = Rotation.from_rotvec(rng.uniform(-rotation, rotation, size=(n, 3)))
    quat = (turn * Rotation.from_quat(np.roll(base[:, 3:], -1, axis=1))).as_quat()
    return np.concatenate([base[:, :3] + shift, np.roll(quat, 1, axis=1)], 1).astype(np.float32)


def uniform_poses(
    support_points: np.ndarray, rng: np.random.Generator, n: int, margin: float = 0.05
) -> np.ndarray:
    """[n, 7] poses uniform in the observed support cloud's box grown by ``margin`` (m),
    orientations uniform on SO(3): the "Stage 3 alone" start of the learning-curve
    experiment (paper: "a uniformly sampled pose")."""
    from scipy.spatial.transform import Rotation

    lo = support_points.min(0) - margin
    hi = support_points.max(0) + margin
    xyz = rng.uniform(lo, hi, size=(n, 3))
    q = Rotation.random(n, random_state=rng).as_quat()
    return np.concatenate([xyz, np.roll(q, 1, axis=1)], 1).astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Simulated rewards

_WORKER: dict = {}


def _labeller_init(dataset_dir: str) -> None:
    from omnihang_jax import dataset_bridge
    from sim.library import build_library

    if _WORKER.get("dataset_dir") == dataset_dir:  # built already in this process
        return
    recipe = dataset_bridge.read_recipe(dataset_dir)
    config = dataset_bridge.dataset_config_from_recipe(recipe)
    _WORKER["library"] = build_library(config.library, progress=False)
    _WORKER["dataset_dir"] = dataset_dir


def worker_library():
    """The asset library of the process (a worker of :func:`library_pool`, or this one)."""
    return _WORKER["library"]


def library_pool(dataset_dir: str | os.PathLike, workers: int):
    """``workers`` > 0: a pool of spawned single-threaded processes that each hold the
    dataset's asset library (:func:`worker_library`) and keep JAX off the GPU (they only
    simulate); 0: None, the library loaded in this process instead."""
    if workers <= 0:
        _labeller_init(os.fspath(dataset_dir))
        return None
    from sim import workers as workers_mod

    saved = os.environ.get("JAX_PLATFORMS")
    os.environ["JAX_PLATFORMS"] = "cpu"
    try:
        return workers_mod.spawn_pool(workers, _labeller_init, (os.fspath(dataset_dir),))
    finally:
        if saved is None:
            os.environ.pop("JAX_PLATFORMS", None)
        else:
            os.environ["JAX_PLATFORMS"] = saved


def label_job(job: tuple[str, str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(object name, support name, poses [n, 7]) -> ([n] int8 status, [n] initial penetration m)
    on the true meshes under the evaluation protocol, in one batched rollout; a non-finite pose
    is DIVERGED. Runs in a :func:`library_pool` worker (or after ``library_pool(..., 0)``)."""
    from omnihang_jax.evaluate import protocol_stability
    from sim import kernels
    from sim.scene import build_scene

    obj_name, sup_name, poses = job
    lib = _WORKER["library"]
    poses = np.asarray(poses, np.float64).reshape(-1, 7)
    status = np.full(len(poses), kernels.DIVERGED, np.int8)
    pen = np.full(len(poses), np.nan)
    ok = np.isfinite(poses).all(1) & (np.linalg.norm(poses[:, 3:], axis=1) > 1e-6)
    if ok.any():
        scene = build_scene(lib.objects[obj_name], lib.supports[sup_name])
        res = kernels.stability(scene, poses[ok], protocol_stability(), nthread=1)
        status[ok], pen[ok] = res.status, res.initial_penetration
    return status, pen


class Labeller:
    """A pool of single-threaded workers that each hold the asset library; ``__call__``
    labels many pairs' poses at once. ``workers=0``: in this process (tests, debugging)."""

    def __init__(self, dataset_dir: str | os.PathLike, workers: int = 0):
        self.dataset_dir = os.fspath(dataset_dir)
        self.workers = workers
        self.pool = library_pool(self.dataset_dir, workers)

    def __call__(
        self, jobs: Sequence[tuple[str, str, np.ndarray]], progress: bool = False
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """jobs: (object_name, support_name, poses [n, 7]) -> per job (status [n] int8 of
        ``sim.kernels.STATUS_NAMES``, initial_penetration [n] m)."""
        from tqdm.auto import tqdm

        if self.pool is None:
            return [label_job(j) for j in tqdm(jobs, desc="simulate", disable=not progress)]
        return self.pool.map_async(label_job, list(jobs), chunksize=4).get()

    def close(self) -> None:
        if self.pool is not None:
            self.pool.__exit__(None, None, None)
            self.pool = None

    def __enter__(self) -> Labeller:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def label_poses(labeller: Labeller, bank: PairBank, slots: np.ndarray, poses: np.ndarray):
    """Rewards [n] uint8 (1 = STABLE) and statuses [n] for poses of the bank's pairs, grouped
    into one simulation job per pair."""
    from sim import kernels

    slots = np.asarray(slots)
    order = np.argsort(slots, kind="stable")
    uniq, starts = np.unique(slots[order], return_index=True)
    groups = np.split(order, starts[1:])
    jobs = [
        (bank.meta[s]["object_name"], bank.meta[s]["support_name"], poses[g])
        for s, g in zip(uniq, groups, strict=True)
    ]
    status = np.empty(len(slots), np.int8)
    for g, (st, _) in zip(groups, labeller(jobs), strict=True):
        status[g] = st
    return (status == kernels.STABLE).astype(np.uint8), status


# ----------------------------------------------------------------------------------------------
# Value training (device)


@flax.struct.dataclass
class ValueTrainState:
    step: jax.Array
    params: Any
    opt_state: Any


def make_schedule(config: ValueConfig, total_steps: int) -> optax.Schedule:
    """Warm-up to ``config.learning_rate``, then cosine to 5 % of it over ``total_steps``."""
    return optax.warmup_cosine_decay_schedule(
        0.0, config.learning_rate, config.warmup_steps, max(total_steps, config.warmup_steps + 1),
        end_value=config.learning_rate * 0.05,
    )  # fmt: skip


def make_optimizer(config: ValueConfig, total_steps: int) -> optax.GradientTransformation:
    schedule = make_schedule(config, total_steps)
    return optax.chain(
        optax.clip_by_global_norm(config.grad_clip),
        optax.adamw(schedule, weight_decay=config.weight_decay),
    )


class ValueTrainer(NamedTuple):
    """init(key) -> state; step(state, clouds_device, slots, poses, rewards, key) -> (state,
    metrics); evaluate(params, clouds_device, slots, poses) -> P(hang) [B]."""

    init: Callable
    step: Callable
    predict: Callable


def make_value_trainer(config: ValueConfig, total_steps: int) -> ValueTrainer:
    """Jitted init/step/predict; the batch is gathered from the device-resident bank."""
    net = stage3.make_value(config)
    tx = make_optimizer(config, total_steps)

    def init(key, params=None):
        params = net.init(key) if params is None else params
        return ValueTrainState(jnp.array(0, jnp.int32), params, tx.init(params))

    def loss_fn(params, clouds, poses, rewards, key):
        logits = net.logits(params, clouds, poses, key)
        return stage3.value_loss(logits, rewards)

    def step(state, bank_clouds, slots, poses, rewards, key):
        clouds = jax.tree.map(lambda x: x[slots], bank_clouds)
        (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            state.params, clouds, poses, rewards, key
        )
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        metrics = dict(metrics, grad_norm=optax.global_norm(grads))
        return ValueTrainState(state.step + 1, params, opt_state), metrics

    def predict(params, bank_clouds, slots, poses):
        clouds = jax.tree.map(lambda x: x[slots], bank_clouds)
        return net.value(params, clouds, poses)

    return ValueTrainer(jax.jit(init), jax.jit(step), jax.jit(predict))


def predict_in_batches(trainer, params, bank_clouds, slots, poses, batch: int = 512):
    """P(hang) [n] for many transitions (padded to whole batches: one compilation)."""
    n = len(slots)
    out = np.zeros(n, np.float32)
    for i in range(0, n, batch):
        s, p = slots[i : i + batch], poses[i : i + batch]
        m = len(s)
        if m < batch:
            s = np.concatenate([s, np.repeat(s[:1], batch - m)])
            p = np.concatenate([p, np.repeat(p[:1], batch - m, axis=0)])
        out[i : i + m] = np.asarray(trainer.predict(params, bank_clouds, s, p))[:m]
    return out


def classification_metrics(prob: np.ndarray, reward: np.ndarray) -> dict:
    """Accuracy, precision, recall, balanced accuracy of P(hang) > 0.5 against rewards."""
    pred = prob > 0.5
    r = reward.astype(bool)
    tp, fp, fn = int((pred & r).sum()), int((pred & ~r).sum()), int((~pred & r).sum())
    tn = int((~pred & ~r).sum())
    rec = tp / max(tp + fn, 1)
    spec = tn / max(tn + fp, 1)
    return {
        "n": len(r),
        "positives": int(r.sum()),
        "accuracy": float((pred == r).mean()) if len(r) else float("nan"),
        "precision": tp / max(tp + fp, 1),
        "recall": rec,
        "balanced_accuracy": 0.5 * (rec + spec),
    }


def save_value(folder: str | os.PathLike, config: ValueConfig, params, **extra) -> None:
    """``folder/config.json`` + ``folder/params.msgpack``: rebuildable from the folder alone."""
    from omnihang_jax.config import save_config
    from sim import atomic

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    save_config(config, folder / "config.json", **extra)
    blob = flax.serialization.to_bytes(params)
    atomic.write_atomic(folder / "params.msgpack", lambda f: f.write(blob))


def load_value(folder: str | os.PathLike) -> tuple[ValueConfig, Any]:
    from omnihang_jax.config import load_config

    folder = Path(folder)
    if not (folder / "params.msgpack").exists():
        raise FileNotFoundError(
            f"{folder}/params.msgpack not found: train V first (python -m experiments.train_stage3)"
        )
    config, _ = load_config(ValueConfig, folder / "config.json")
    # the parameters' shapes without running the network (an eager init compiles every layer)
    template = jax.eval_shape(stage3.make_value(config).init, jax.random.key(0))
    params = flax.serialization.from_bytes(template, (folder / "params.msgpack").read_bytes())
    return config, jax.tree.map(jnp.asarray, params)


def write_json(path: str | os.PathLike, data: dict) -> None:
    from sim import atomic

    atomic.write_text(os.fspath(path), json.dumps(data, indent=1))
