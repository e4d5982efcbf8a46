"""Stage 3 by reinforcement learning with simulated rewards (paper, "Local Refinement").

``train_stage3(config, workdir)``: a resumable job in phases, every phase writing its state
to ``workdir`` so a killed run loses at most the step in progress:

1. **seed**: the replay buffer starts from what the dataset holds and from simulation:
   the stable poses of the training pairs (reward 1), perturbations of them inside CEM's box
   and a tighter one (labelled by ``sim.kernels``), and the Stage-1 and Stage-2 proposals of
   the committed where-to-hang weights (labelled). ``buffer.npz``.
2. **pretrain** V on the buffer (50/50 sampling, warm-up + cosine, clipping); validation
   on pairs whose *object* is in a fixed validation subset of the training objects.
3. **rounds** of the paper's loop: run the pipeline (Stages 1-2 + CEM on the current V) on
   random training pairs, simulate the chosen poses (one batched job per pair), add the
   transitions, train V. Each round logs the success of the chosen poses (on-policy, training
   pairs) and, every ``val_every`` rounds, on the validation pairs.

``value/`` (config.json + params.msgpack) is the committed artefact the pipeline loads;
``metrics.jsonl``, ``rounds.jsonl`` and ``curves.png`` record training.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from omnihang_jax import data as data_lib
from omnihang_jax import refine, stage3
from omnihang_jax.refine import Labeller, PairBank, ReplayBuffer
from omnihang_jax.stage3 import CEMConfig, PairClouds, ValueConfig

__all__ = [
    "RLConfig",
    "validation_objects",
    "train_stage3",
    "run_pipeline_on_pairs",
    "learning_curve",
]


@dataclasses.dataclass(frozen=True)
class RLConfig:
    """Settings of a Stage-3 training job (presets in experiments/train_stage3.py)."""

    value: ValueConfig = stage3.VALUE_SMALL
    cem: CEMConfig = CEMConfig()
    num_proposals: int = 5  # K proposals refined per pair (facts: 5)
    max_pairs: int = 0  # 0: every derived training pair
    val_fraction: float = 0.1  # of training OBJECTS held out for validation (fixed by name)
    perturb_wide: int = 16  # per pair: stable poses moved within CEM's box (+-2 cm, +-0.5 rad)
    perturb_tight: int = 16  # per pair: within +-5 mm, +-0.1 rad (the boundary that matters)
    seed_proposals: bool = True  # label the Stage-1/2 proposals of the committed weights
    pretrain_steps: int = 4000
    rounds: int = 10
    round_pairs: int = 256
    round_steps: int = 500
    val_every: int = 2  # rounds between validation-pair success checks
    val_pairs: int = 128
    eval_every: int = 500  # steps between validation-accuracy checks
    workers: int = 0  # labelling processes (0: in this process)
    seed: int = 0
    time_budget: float = 0.0  # s; 0 = no limit (phases stop cleanly when it runs out)
    # hard-negative rounds: label not only CEM's answers but the keep_top
    # best-scored members of every final population (V's false positives are among them)
    keep_top: int = 0  # per proposal; 0: only the answers (the earlier rounds)
    explore: bool = True  # also one perturbed copy (+-4 mm, 0.05 rad) of each answer
    hard_fraction: float = 0.0  # share of each batch drawn from the hard cases (balanced)
    init_value: str = ""  # start V from these weights (a value/ folder); "" = from scratch
    # pairs arriving while the job runs (a background derive)
    min_pairs: int = 1  # wait (within time_budget) until this many pairs are derived
    ingest_every: int = 0  # rounds between looks for newly derived pairs (0: only at start)
    ingest_min: int = 1  # ingest when at least this many new pairs are there
    seed_chunk: int = 2000  # pairs seeded per chunk (buffer saved after each)
    seed_share: float = 1.0  # of time_budget a run may spend seeding (the rest: rounds)
    bank_capacity: int = 0  # device bank padded to at least this many pairs (one shape)
    cem_batch: int = 32  # pairs per jitted CEM call (B x K x population states at once)
    # the proposals CEM starts from in a round: "stage2" (the paper's), "stage1", or
    # "alternate" (Stage 2 in odd rounds, Stage 1 in even ones: the answer pipeline refines
    # both, pipeline.ANSWER_PIPELINE, so V's hard cases should come from both)
    round_start: str = "stage2"


# A fixed subset of object names by a hash of the name: the same validation objects as the
# Stage 1-2 trainer's (one function, omnihang_jax.data).
validation_objects = data_lib.validation_objects


# ----------------------------------------------------------------------------------------------


def _load_where(weights: str | os.PathLike):
    from omnihang_jax.predict import load_predictor

    return load_predictor(weights)


def run_pipeline_on_pairs(
    predictor, refine_fn, value_params, bank: PairBank, slots, key, num_proposals: int,
    batch: int = 32, start: str = "stage2", starts_override=None,
):  # fmt: skip
    """Stages 1-2 (full clouds from the pair files) + CEM on V for ``bank`` pairs ``slots``.

    Returns dict of numpy: stage1 [n, K, 7], stage2 [n, K, 7], refined [n, K, 7], scores
    [n, K], initial [n, K], best [n]; ``refine_fn`` None: Stages 1-2 only (refined = the
    starts). ``starts_override`` [n, K, 7] replaces the Stage-1/2
    start (the learning-curve experiment's uniform start). Batches are padded (one
    compilation per batch size)."""
    slots = np.asarray(slots)
    names = ("stage1", "stage2", "refined", "scores", "initial", "best", "top_poses", "top_scores")
    out = {k: [] for k in names}
    for i in range(0, len(slots), batch):
        chunk = slots[i : i + batch]
        m = len(chunk)
        pad = np.concatenate([chunk, np.repeat(chunk[:1], batch - m)])
        if starts_override is None:
            obj, sup = _full_clouds([bank.meta[s]["file"] for s in pad])
            pred = predictor(obj, sup, key=jax.random.fold_in(key, i), num_proposals=num_proposals)
            s1, s2 = pred.stage1_poses, pred.stage2_poses
            starts = s2 if start == "stage2" else s1
        else:
            st = np.asarray(starts_override)[i : i + batch]
            starts = np.concatenate([st, np.repeat(st[:1], batch - m, axis=0)])
            s1 = s2 = starts
        if refine_fn is None:  # Stages 1-2 only
            b, k = np.shape(starts)[:2]
            res = stage3.Refined(starts, np.zeros((b, k)), np.zeros((b, k)), np.zeros(b, int),
                                 np.zeros((b, k, 0, 7)), np.zeros((b, k, 0)))  # fmt: skip
        else:
            clouds = PairClouds(*(jnp.asarray(x[pad]) for x in bank.clouds))
            res = refine_fn(value_params, jax.random.fold_in(key, 10_000 + i), clouds,
                            jnp.asarray(starts, jnp.float32))  # fmt: skip
        for k, v in (("stage1", s1), ("stage2", s2), ("refined", res.poses),
                     ("scores", res.scores), ("initial", res.initial_scores),
                     ("best", res.best), ("top_poses", res.top_poses),
                     ("top_scores", res.top_scores)):  # fmt: skip
            out[k].append(np.asarray(v)[:m])
    return {k: np.concatenate(v) for k, v in out.items()}


def _full_clouds(files) -> tuple[np.ndarray, np.ndarray]:
    """Object and support points [n, N, 3] of pair files (only those two arrays are read)."""
    obj, sup = [], []
    for f in files:
        with np.load(f) as z:
            obj.append(np.asarray(z["object_points"], np.float32))
            sup.append(np.asarray(z["support_points"], np.float32))
    return np.stack(obj), np.stack(sup)


class _Job:
    """Workdir state: phase bookkeeping in ``state.json``, V train state in ``train_state``."""

    def __init__(self, workdir: str | os.PathLike, config: RLConfig):
        self.dir = Path(workdir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.config = config
        self.state_path = self.dir / "state.json"
        self.state = (
            json.loads(self.state_path.read_text())
            if self.state_path.exists()
            else {"seeded": False, "pretrain_step": 0, "round": 0}
        )

    def save_state(self):
        refine.write_json(self.state_path, self.state)

    def log(self, name: str, row: dict):
        with open(self.dir / name, "a") as f:
            f.write(json.dumps(row) + "\n")


def _total_steps(config: RLConfig) -> int:
    return config.pretrain_steps + config.rounds * config.round_steps


def _derived_train_files(derived_dir) -> list[Path]:
    """Sorted training pair files present now (none is fine: the derive may still run);
    atomic-write temporaries (``.tmp_*``) are skipped."""
    d = Path(derived_dir, "train")
    if not d.is_dir():
        return []
    return sorted(f for f in d.glob("*.npz") if not f.name.startswith("."))


class _Bank:
    """The job's pairs: a :class:`PairBank` that only grows (slots never move), cached in
    ``bank.npz``, mirrored on the device padded to a capacity (so the jitted steps keep one
    shape while pairs arrive), with the fit/validation split by object name."""

    def __init__(self, job: _Job, config: RLConfig, derived_dir, progress: bool):
        self.job, self.config, self.derived_dir, self.progress = job, config, derived_dir, progress
        self.path = job.dir / "bank.npz"
        if self.path.exists():
            self.bank = PairBank.load(self.path)
        else:
            self.bank = PairBank.from_files([], config.value, progress=False)
            split = job.dir / "split.json"
            if split.exists():  # a job of the earlier code: same pairs, same order
                names = json.loads(split.read_text())["files"]
                self.bank = PairBank.from_files(
                    [Path(derived_dir, "train", n) for n in names], config.value, progress
                )
        self.dev = None
        self._update_split()

    def __len__(self) -> int:
        return len(self.bank)

    def new_files(self) -> list[Path]:
        have = {os.path.basename(m["file"]) for m in self.bank.meta}
        new = [f for f in _derived_train_files(self.derived_dir) if f.name not in have]
        cap = self.config.max_pairs
        if cap:
            room = cap - len(self.bank)
            if room <= 0:
                return []
            if len(new) > room:  # a fixed random subset (seeded): every category represented
                pick = np.random.default_rng(self.config.seed + len(self.bank)).permutation(
                    len(new)
                )
                new = [new[i] for i in sorted(pick[:room])]
        return new

    def ingest(self, files) -> np.ndarray:
        """Append ``files``; returns their slots."""
        first = len(self.bank)
        if files:
            self.bank.extend(PairBank.from_files(files, self.config.value, self.progress))
            self.bank.save(self.path)
            self._update_split()
            self.dev = None
        return np.arange(first, len(self.bank))

    def _update_split(self) -> None:
        names = sorted({m["object_name"] for m in self.bank.meta})
        val_objects = validation_objects(names, self.config.val_fraction)
        is_val = np.array([m["object_name"] in val_objects for m in self.bank.meta], bool)
        self.fit_slots, self.val_slots = np.flatnonzero(~is_val), np.flatnonzero(is_val)
        refine.write_json(self.job.dir / "split.json", {
            "pairs": len(self.bank), "fit_pairs": len(self.fit_slots),
            "val_pairs": len(self.val_slots), "val_objects": sorted(val_objects),
            "files": [os.path.basename(m["file"]) for m in self.bank.meta],
        })  # fmt: skip

    def device(self) -> PairClouds:
        """The clouds on the device, padded to max(len, bank_capacity) rounded up to 1,024
        rows (a new shape, hence a recompilation, only when the bank outgrows it)."""
        if self.dev is None:
            n = len(self.bank)
            cap = max(n, self.config.bank_capacity, 1)
            cap = -(-cap // 1024) * 1024 if cap > 1024 else cap
            self.dev = PairClouds(*(
                jnp.asarray(np.concatenate([x, np.zeros((cap - n,) + x.shape[1:], x.dtype)]))
                for x in self.bank.clouds
            ))  # fmt: skip
        return self.dev


def train_stage3(
    config: RLConfig, workdir: str | os.PathLike, data: str | os.PathLike, weights: str,
    progress: bool = True,
) -> dict:  # fmt: skip
    """Run (or resume) a Stage-3 job; returns a summary dict (also ``workdir/summary.json``).

    Pairs may arrive while the job runs (a derive in the background): at the start and every
    ``ingest_every`` rounds the job appends the newly derived pairs to its bank and seeds
    them, so a rerun in the same folder trains on everything derived by then."""
    from omnihang_jax import dataset_bridge
    from omnihang_jax.config import save_config

    t_start = time.time()

    def time_left() -> float:
        return (
            float("inf") if not config.time_budget else config.time_budget - (time.time() - t_start)
        )

    job = _Job(workdir, config)
    save_config(config, job.dir / "config.json", data=os.fspath(data), weights=weights)
    dataset_dir, derived_dir = dataset_bridge.resolve_dataset_dir(data)
    pairs = _Bank(job, config, derived_dir, progress)
    if "seeded_pairs" not in job.state:  # a job of the earlier code: all or nothing
        job.state["seeded_pairs"] = len(pairs) if job.state.get("seeded") else 0
    while len(pairs) + len(pairs.new_files()) < max(config.min_pairs, 1):
        if time_left() < 120 or not config.time_budget:
            break
        time.sleep(5)  # the derive is still writing the first pairs
    pairs.ingest(pairs.new_files())
    if not len(pairs):
        raise FileNotFoundError(
            f"no derived training pairs under {derived_dir}/train: derive them first "
            f"(python -m experiments.derive_dataset --data {dataset_dir} --split train)"
        )
    rng = np.random.default_rng(config.seed + 1000 * job.state["round"] + job.state["seeded_pairs"])
    key = jax.random.key(config.seed)
    predictor = _load_where(weights)
    buffer_path = job.dir / "buffer.npz"
    buffer = ReplayBuffer.load(buffer_path) if buffer_path.exists() else ReplayBuffer()
    timings = {"seed_per_pair": job.state.get("seed_per_pair"), "round": None}
    # what each phase keeps free for the ones after it (saving, packing): 45 s of a long
    # budget, a tenth of a short one
    reserve = min(45.0, 0.1 * config.time_budget) if config.time_budget else 0.0

    labeller = Labeller(dataset_dir, config.workers)
    try:
        # 1. seed ------------------------------------------------------------------------------
        def seed(slots_all: np.ndarray) -> None:
            bank = pairs.bank
            for s in slots_all:
                sp = bank.stable_poses[s]
                buffer.add(np.full(len(sp), s), sp, np.ones(len(sp)), "stable")
            cand_slots, cand_poses, cand_src = [], [], []
            for s in slots_all:
                sp = bank.stable_poses[s]
                if not len(sp):
                    continue
                for n, tr, rot in ((config.perturb_wide, config.cem.clip_translation,
                                    config.cem.clip_rotation),
                                   (config.perturb_tight, 0.005, 0.1)):  # fmt: skip
                    if n:
                        cand_poses.append(refine.perturb_poses(sp, rng, n, tr, rot))
                        cand_slots.append(np.full(n, s))
                        cand_src.append(np.full(n, "perturbed"))
            if config.seed_proposals:
                pred = run_pipeline_on_pairs(
                    predictor, None, None, bank, slots_all,
                    jax.random.fold_in(key, int(slots_all[0])), config.num_proposals,
                )  # fmt: skip
                for name in ("stage1", "stage2"):
                    cand_poses.append(pred[name].reshape(-1, 7))
                    cand_slots.append(np.repeat(slots_all, config.num_proposals))
                    cand_src.append(np.full(len(slots_all) * config.num_proposals, name))
            if cand_slots:
                slots = np.concatenate(cand_slots)
                poses = np.concatenate(cand_poses)
                src = np.concatenate(cand_src)
                rewards, _ = _label_chunked(labeller, bank, slots, poses, progress)
                for name in np.unique(src):
                    m = src == name
                    buffer.add(slots[m], poses[m], rewards[m], str(name))

        seed_used = [0.0]  # seconds of seeding in this run (capped by seed_share)

        def seed_pending(min_left: float) -> None:
            """Seed the pairs not seeded yet, in chunks sized to the time left, while this
            run's seeding stays within ``seed_share`` of the budget (the rest is rounds)."""
            while job.state["seeded_pairs"] < len(pairs):
                lo = job.state["seeded_pairs"]
                n = min(config.seed_chunk, len(pairs) - lo)
                per_pair = timings["seed_per_pair"]
                if config.time_budget:
                    avail = min(time_left() - min_left,
                                config.seed_share * config.time_budget - seed_used[0])  # fmt: skip
                    if lo and avail <= 0:  # (the first pairs are seeded whatever the share)
                        break
                    if per_pair:  # a smaller chunk rather than none
                        n = min(n, int(avail / (1.3 * per_pair)))
                        if n < min(config.seed_chunk, len(pairs) - lo, 32):
                            break
                chunk = np.arange(lo, lo + n)
                t0 = time.time()
                seed(chunk)
                buffer.save(buffer_path)
                dt = time.time() - t0
                seed_used[0] += dt
                timings["seed_per_pair"] = job.state["seed_per_pair"] = dt / len(chunk)
                job.state["seeded_pairs"] = int(chunk[-1]) + 1
                job.state["seed_s"] = job.state.get("seed_s", 0.0) + dt
                job.state["seeded"] = job.state["seeded_pairs"] == len(pairs)
                job.save_state()
                job.log("rounds.jsonl", {"phase": "seed", "pairs": [int(lo), int(chunk[-1]) + 1],
                                         "s": dt, **buffer.stats()})  # fmt: skip

        seed_pending(min_left=1.5 * reserve)

        # 2. V ---------------------------------------------------------------------------------
        trainer = refine.make_value_trainer(config.value, _total_steps(config))
        init_params = refine.load_value(config.init_value)[1] if config.init_value else None
        state = trainer.init(jax.random.key(config.seed), init_params)
        ckpt = job.dir / "train_state.msgpack"
        if ckpt.exists():
            state = flax.serialization.from_bytes(state, ckpt.read_bytes())
        refine_fn = jax.jit(stage3.make_refiner(config.value, config.cem, config.keep_top))

        def save(state):
            blob = flax.serialization.to_bytes(state)
            from sim import atomic

            atomic.write_atomic(ckpt, lambda f: f.write(blob))
            refine.save_value(job.dir / "value", config.value, state.params,
                              step=int(state.step))  # fmt: skip
            buffer.save(buffer_path)

        hard_ids = [refine.SOURCES.index(x) for x in refine.HARD_SOURCES]

        def validate(state) -> dict:
            """V on transitions of the validation pairs (never trained on): all of them
            (4,096 at most) and the hard cases alone (CEM's answers and top-scored members
            on the validation pairs: V's precision where it matters)."""
            d = buffer.data
            m = np.isin(d["slot"], pairs.val_slots)
            out = {}
            hard = np.isin(d["source"], hard_ids)
            # two fixed kinds: the seed transitions (stable, perturbed, Stage-1/2 proposals)
            # and the hard cases; mixing them would move the figure as hard cases are added
            for tag, mm in (("val", m & ~hard), ("val_hard", m & hard)):
                if not mm.any():
                    continue
                idx = np.flatnonzero(mm)
                if len(idx) > 4096:
                    idx = np.random.default_rng(0).choice(idx, 4096, replace=False)
                prob = refine.predict_in_batches(trainer, state.params, pairs.device(),
                                                 d["slot"][idx], d["pose"][idx])  # fmt: skip
                out.update({f"{tag}_{k}": v for k, v in
                            refine.classification_metrics(prob, d["reward"][idx]).items()})  # fmt: skip
            return out

        def train(state, steps: int, tag: str):
            fit = buffer.select(np.isin(buffer.data["slot"], pairs.fit_slots))
            if not len(fit):
                print(f"train V ({tag}): no transitions of fit pairs yet ({len(pairs)} pairs, "
                      f"{len(pairs.val_slots)} of them validation pairs): skipped", flush=True)  # fmt: skip
                return state
            bank_dev = pairs.device()
            bar = tqdm(range(steps), desc=f"train V ({tag})", disable=not progress)
            t0 = time.time()
            for i in bar:
                if time_left() < (reserve if tag == "fill" else 0.5 * reserve):
                    break
                idx = fit.sample(rng, config.value.batch_size, config.hard_fraction)
                d = fit.data
                state, metrics = trainer.step(
                    state, bank_dev, d["slot"][idx], d["pose"][idx], d["reward"][idx],
                    jax.random.fold_in(key, int(state.step)),
                )  # fmt: skip
                if (i + 1) % 50 == 0 or i == steps - 1:
                    row = {"step": int(state.step), "tag": tag,
                           **{k: float(v) for k, v in metrics.items()},
                           "samples_per_s": (i + 1) * config.value.batch_size / (time.time() - t0)}  # fmt: skip
                    if (int(state.step) % config.eval_every) < 50 or i == steps - 1:
                        row.update(validate(state))
                    job.log("metrics.jsonl", row)
                    bar.set_postfix(loss=f"{row['cross_entropy']:.3f}",
                                    acc=f"{row['accuracy']:.2f}")  # fmt: skip
            return state

        if job.state["pretrain_step"] < config.pretrain_steps and time_left() > reserve:
            state = train(state, config.pretrain_steps - job.state["pretrain_step"], "pretrain")
            job.state["pretrain_step"] = int(state.step)
            save(state)
            job.save_state()

        def cem_round(slots, r: int, tag_key: int, start: str | None = None):
            """CEM on the current V from the K Stage-2 proposals of ``slots``; labels the
            refined poses, the top ``keep_top`` members of each final population and one
            perturbed copy of each refined pose in one simulation call. Returns the
            pipeline's output, the per-source (slots, poses, rewards) and figures."""
            k, mt = config.num_proposals, config.keep_top
            out = run_pipeline_on_pairs(predictor, refine_fn, state.params, pairs.bank, slots,
                                        jax.random.fold_in(key, tag_key), k,
                                        batch=config.cem_batch,
                                        start=start or round_start(config.round_start, r))  # fmt: skip
            n = len(slots)
            refined = out["refined"].reshape(-1, 7)
            parts = {"cem": (np.repeat(slots, k), refined)}
            if mt:
                parts["cem_top"] = (np.repeat(slots, k * mt), out["top_poses"].reshape(-1, 7))
            if config.explore:
                parts["cem_explore"] = (
                    np.repeat(slots, k), refine.perturb_poses(refined, rng, len(refined), 0.004, 0.05)
                )  # fmt: skip
            s_all = np.concatenate([v[0] for v in parts.values()])
            p_all = np.concatenate([v[1] for v in parts.values()])
            rew, _ = _label_chunked(labeller, pairs.bank, s_all, p_all, False)
            labelled, i = {}, 0
            for name, (sl, po) in parts.items():
                labelled[name] = (sl, po, rew[i : i + len(sl)])
                i += len(sl)
            rr = labelled["cem"][2].reshape(n, k)
            figs = {"chosen_success": float(rr[np.arange(n), out["best"]].mean()),
                    "any_refined_success": float(rr.any(1).mean())}  # fmt: skip
            if mt:
                # the top members as V judged them before training on them: how many hang,
                # and V's precision (P > 0.5) on them (V's false positives = hard negatives)
                tr = labelled["cem_top"][2]
                tp = np.exp(out["top_scores"].reshape(-1))
                figs.update(top_success=float(tr.mean()), top_called_good=float((tp > 0.5).mean()),
                            top_precision=float(tr[tp > 0.5].mean()) if (tp > 0.5).any() else 0.0)  # fmt: skip
            return out, labelled, figs

        # 3. RL rounds -------------------------------------------------------------------------
        while job.state["round"] < config.rounds and time_left() > reserve:
            r = job.state["round"] + 1
            if config.ingest_every and r % config.ingest_every == 0:
                new = pairs.new_files()
                if len(new) >= config.ingest_min:
                    pairs.ingest(new)
            seed_pending(min_left=2 * reserve)
            # the first round of a call also compiles: the last call's round time x 1.5, at
            # least a tenth of the budget
            est = timings["round"] or max(1.5 * job.state.get("round_s", 0.0),
                                          0.1 * config.time_budget)  # fmt: skip
            if time_left() < reserve + 1.3 * est:
                break
            t0 = time.time()
            seeded_fit = pairs.fit_slots[pairs.fit_slots < job.state["seeded_pairs"]]
            slots = rng.choice(seeded_fit, min(config.round_pairs, len(seeded_fit)), replace=False)
            if not len(slots):
                break
            out, labelled, figs = cem_round(slots, r, 7 * r)
            for name, (sl, po, rw) in labelled.items():
                buffer.add(sl, po, rw, name, r)
            row = {"round": r, "start": round_start(config.round_start, r), "pairs": len(slots),
                   **figs, "transitions": len(buffer),
                   "bank_pairs": len(pairs), "seeded_pairs": job.state["seeded_pairs"]}  # fmt: skip
            state = train(state, config.round_steps, f"round {r}")
            if config.val_every and r % config.val_every == 0 and len(pairs.val_slots):
                vs = pairs.val_slots[pairs.val_slots < job.state["seeded_pairs"]][
                    : config.val_pairs
                ]
                if len(vs):
                    vo, vl, vf = cem_round(vs, r, 99, "stage2")  # one start: comparable
                    for name, (sl, po, rw) in vl.items():  # validation pairs: never trained on
                        buffer.add(sl, po, rw, name, r)
                    s2 = vo["stage2"][:, 0]
                    vr2, _ = _label_chunked(labeller, pairs.bank, vs, s2, False)
                    row.update(val_pairs=len(vs), val_stage1_2_success=float(vr2.mean()),
                               val_all_stages_success=vf["chosen_success"],
                               **{f"val_{k}": v for k, v in vf.items() if k != "chosen_success"})  # fmt: skip
            row["s"] = time.time() - t0
            row.update(validate(state))
            timings["round"] = job.state["round_s"] = row["s"]
            job.log("rounds.jsonl", row)
            job.state["round"] = r
            save(state)
            job.save_state()
            if progress:
                print(json.dumps(row))
        if job.state["pretrain_step"] < config.pretrain_steps and time_left() > reserve:
            # pairs that arrived late: whatever pretraining the budget left undone
            state = train(state, config.pretrain_steps - job.state["pretrain_step"], "pretrain")
            job.state["pretrain_step"] = int(state.step)
        elif job.state["round"] < config.rounds and time_left() > 1.5 * reserve:
            # too little time for another round: train V on the buffer as it is (new pairs'
            # seeds, the last round's hard cases) until the reserve
            state = train(state, 2 * config.round_steps, "fill")
        save(state)
        job.save_state()
    finally:
        labeller.close()
    summary = {"state": job.state, "buffer": buffer.stats(), "pairs": len(pairs),
               "wall_s": time.time() - t_start}  # fmt: skip
    refine.write_json(job.dir / "summary.json", summary)
    plot_curves(job.dir)
    return summary


def round_start(rule: str, r: int) -> str:
    """The proposals round ``r`` (1-based) refines: ``RLConfig.round_start``."""
    if rule == "alternate":
        return "stage2" if r % 2 else "stage1"
    if rule not in ("stage1", "stage2"):
        raise ValueError(f"round_start must be stage1, stage2 or alternate, not {rule!r}")
    return rule


def _label_chunked(labeller, bank, slots, poses, progress: bool, chunk: int = 20_000):
    rewards = np.zeros(len(slots), np.uint8)
    status = np.zeros(len(slots), np.int8)
    bar = tqdm(range(0, len(slots), chunk), desc="simulate", disable=not progress)
    for i in bar:
        r, s = refine.label_poses(labeller, bank, slots[i : i + chunk], poses[i : i + chunk])
        rewards[i : i + chunk], status[i : i + chunk] = r, s
    return rewards, status


def plot_curves(workdir: str | os.PathLike) -> None:
    """``curves.png``: training loss/accuracy, validation accuracy, round success."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = Path(workdir)
    rows = [json.loads(x) for x in (d / "metrics.jsonl").read_text().splitlines()] if (
        d / "metrics.jsonl").exists() else []  # fmt: skip
    rounds = [json.loads(x) for x in (d / "rounds.jsonl").read_text().splitlines()] if (
        d / "rounds.jsonl").exists() else []  # fmt: skip
    rounds = [r for r in rounds if "round" in r]
    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    if rows:
        st = [r["step"] for r in rows]
        ax[0].plot(st, [r["cross_entropy"] for r in rows], label="train CE")
        ax[0].set_xlabel("step")
        ax[0].legend()
        ax[1].plot(st, [r["accuracy"] for r in rows], label="train acc (50/50 batches)")
        v = [r for r in rows if "val_balanced_accuracy" in r]
        ax[1].plot([r["step"] for r in v], [r["val_balanced_accuracy"] for r in v], "o-",
                   label="val balanced acc (held-out objects)")  # fmt: skip
        ax[1].set_xlabel("step")
        ax[1].legend()
    if rounds:
        ax[2].plot([r["round"] for r in rounds], [r["chosen_success"] for r in rounds], "o-",
                   label="chosen pose hangs (training pairs)")  # fmt: skip
        v = [r for r in rounds if "val_all_stages_success" in r]
        ax[2].plot([r["round"] for r in v], [r["val_all_stages_success"] for r in v], "s-",
                   label="all stages (val pairs)")  # fmt: skip
        ax[2].plot([r["round"] for r in v], [r["val_stage1_2_success"] for r in v], "x--",
                   label="stages 1+2 (val pairs)")  # fmt: skip
        ax[2].set_xlabel("RL round")
        ax[2].legend()
    fig.tight_layout()
    fig.savefig(d / "curves.png", dpi=90)
    plt.close(fig)


def learning_curve(
    data: str | os.PathLike, weights: str, out_json: str | os.PathLike, num_pairs: int = 100,
    max_steps: int = 10_000, steps_per_round: int = 1_000, train_steps: int = 200,
    config: RLConfig = RLConfig(), starts: tuple[str, ...] = ("stage2", "uniform"),
    progress: bool = True,
) -> dict:  # fmt: skip
    """The paper's refinement-learning experiment: on ``num_pairs`` random training pairs,
    success against RL steps (simulated transitions) for Stage 3 started from Stage 2's
    proposals and from uniformly sampled poses; V starts untrained each time.

    A round: CEM on the current V from K starts per pair, the best-V pose of each pair is
    the pair's answer (success = it hangs, measured before V trains on it), every refined
    pose and a perturbed copy are added to the buffer (``steps_per_round`` transitions in
    all), V trains ``train_steps`` steps. Returns (and writes) the curves."""
    from omnihang_jax import dataset_bridge

    dataset_dir, derived_dir = dataset_bridge.resolve_dataset_dir(data)
    files = sorted(dataset_bridge.derived_files(derived_dir, "train"))
    if len(files) < num_pairs:
        raise FileNotFoundError(f"{len(files)} derived training pairs, {num_pairs} needed")
    rng0 = np.random.default_rng(config.seed)
    files = [files[i] for i in sorted(rng0.permutation(len(files))[:num_pairs])]
    bank = PairBank.from_files(files, config.value, progress=progress)
    bank_dev = PairClouds(*(jnp.asarray(x) for x in bank.clouds))
    predictor = _load_where(weights)
    k = config.num_proposals
    per_round = max(1, steps_per_round // (2 * k * num_pairs))  # CEM runs per pair per round
    refine_fn = jax.jit(stage3.make_refiner(config.value, config.cem))
    curves = {}
    slots = np.arange(num_pairs)
    with Labeller(dataset_dir, config.workers) as labeller:
        for start in starts:
            rng = np.random.default_rng(config.seed)
            key = jax.random.key(config.seed)
            trainer = refine.make_value_trainer(config.value, max_steps // steps_per_round * train_steps)  # fmt: skip
            state = trainer.init(jax.random.key(config.seed))
            buffer = ReplayBuffer()
            rows, steps, r = [], 0, 0
            t0 = time.time()
            bar = tqdm(total=max_steps, desc=f"RL from {start}", disable=not progress)
            while steps < max_steps:
                r += 1
                new_slots, new_poses, chosen_ok = [], [], []
                for j in range(per_round):
                    kr = jax.random.fold_in(key, 100 * r + j)
                    override = None
                    if start == "uniform":
                        override = np.stack([refine.uniform_poses(bank.clouds.support_points[s], rng, k)
                                             for s in slots])  # fmt: skip
                    out = run_pipeline_on_pairs(predictor, refine_fn, state.params, bank, slots,
                                                kr, k, starts_override=override)  # fmt: skip
                    poses = out["refined"].reshape(-1, 7)
                    explore = refine.perturb_poses(poses, rng, len(poses), 0.004, 0.05)
                    s_all = np.concatenate([np.repeat(slots, k)] * 2)
                    p_all = np.concatenate([poses, explore])
                    rew, _ = _label_chunked(labeller, bank, s_all, p_all, False)
                    chosen = rew[: len(poses)].reshape(-1, k)[np.arange(num_pairs), out["best"]]
                    chosen_ok.append(chosen)
                    new_slots.append(s_all)
                    new_poses.append((p_all, rew))
                for s_all, (p_all, rew) in zip(new_slots, new_poses, strict=True):
                    buffer.add(s_all, p_all, rew, "cem", r)
                steps = len(buffer)
                succ = float(np.mean(chosen_ok))
                for _ in range(train_steps):
                    idx = buffer.sample(rng, config.value.batch_size)
                    d = buffer.data
                    state, _m = trainer.step(state, bank_dev, d["slot"][idx], d["pose"][idx],
                                             d["reward"][idx], jax.random.fold_in(key, int(state.step)))  # fmt: skip
                rows.append({"round": r, "steps": steps, "success": succ,
                             "buffer_success_rate": float(buffer.data["reward"].mean()),
                             "s": time.time() - t0})  # fmt: skip
                bar.update(steps - bar.n)
                bar.set_postfix(success=f"{succ:.2f}")
            bar.close()
            curves[start] = rows
    result = {
        "what": "success of the best-V pose (before V trains on it) against RL steps "
        "(simulated transitions) on random training pairs; V untrained at step 0",
        "pairs": num_pairs, "max_steps": max_steps, "steps_per_round": steps_per_round,
        "train_steps_per_round": train_steps, "proposals": k,
        "files": [os.path.basename(f) for f in files], "curves": curves,
        "paper": {"stage2_start_at_10k": 71.0, "uniform_start_at_10k": 10.0},
    }  # fmt: skip
    refine.write_json(out_json, result)
    _plot_learning_curve(result, Path(out_json).with_suffix(".png"))
    return result


def _plot_learning_curve(result: dict, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    names = {
        "stage2": "Stage 3 from Stage 2's proposals",
        "uniform": "Stage 3 alone (uniform start)",
    }
    for start, rows in result["curves"].items():
        ax.plot([0] + [r["steps"] for r in rows], [np.nan] + [100 * r["success"] for r in rows],
                "o-", label=names.get(start, start))  # fmt: skip
    ax.axhline(71, ls="--", c="C0", lw=0.8, label="paper, from Stage 2 (10k steps)")
    ax.axhline(10, ls="--", c="C1", lw=0.8, label="paper, uniform (10k steps)")
    ax.set_xlabel("RL steps (simulated transitions)")
    ax.set_ylabel(f"success on {result['pairs']} training pairs (%)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
