"""Stage-3 training pieces: the 50/50 replay buffer, simulated rewards, V learning."""

import jax
import numpy as np
import pytest

from omnihang_jax import refine, stage3
from omnihang_jax.refine import PairBank, ReplayBuffer
from omnihang_jax.stage3 import PairClouds

DATA = "datasets/paper"


def test_buffer_samples_half_successes_and_round_trips(tmp_path):
    buf = ReplayBuffer()
    poses = np.tile(np.float32([0, 0, 0, 1, 0, 0, 0]), (100, 1))
    rewards = (np.arange(100) < 10).astype(np.uint8)  # 10 % successes
    buf.add(np.arange(100) % 7, poses, rewards, "perturbed")
    buf.add([0], [[np.nan] * 7], [1], "cem")  # a non-finite pose is dropped
    assert len(buf) == 100
    idx = buf.sample(np.random.default_rng(0), 64)
    assert buf.data["reward"][idx].sum() == 32
    buf.save(tmp_path / "b.npz")
    again = ReplayBuffer.load(tmp_path / "b.npz")
    np.testing.assert_array_equal(again.data["slot"], buf.data["slot"])
    assert again.stats()["perturbed"]["success_rate"] == pytest.approx(0.1)
    np.savez(tmp_path / "other.npz", slot=np.zeros(3))  # an npz, but not a buffer
    with pytest.raises(ValueError, match="not a replay buffer"):
        ReplayBuffer.load(tmp_path / "other.npz")


def test_perturbations_stay_in_the_box():
    base = np.float32([[0.1, 0.2, 0.3, 1, 0, 0, 0]])
    p = refine.perturb_poses(base, np.random.default_rng(0), 200, 0.02, 0.5)
    assert np.all(np.abs(p[:, :3] - base[:, :3]) <= 0.02 + 1e-6)
    np.testing.assert_allclose(np.linalg.norm(p[:, 3:], axis=1), 1, atol=1e-5)


def test_simulated_rewards_known_hang_stays_shifted_pose_falls():
    """Physics, not bookkeeping: a dataset stable pose earns reward 1, the same pose 8 cm
    sideways (nothing to hang on) earns 0."""
    import glob

    from sim import dataset_io

    with np.load(sorted(glob.glob(f"{DATA}/shards/shard_*.npz"))[0]) as z:
        records = dataset_io.unpack({k: z[k] for k in z.files})
    from omnihang_jax import dataset_bridge

    recipe = dataset_bridge.read_recipe(DATA)
    rec = next(r for r in records if len(r["stable_poses"]) >= 2)
    obj, sup, _ = recipe["pairs"][int(rec["pair_index"])]
    good = rec["stable_poses"][:2]
    moved = good.copy()
    moved[:, 0] += 0.08
    bank = PairBank(
        clouds=None,
        meta=[{"object_name": obj, "support_name": sup}],
        stable_poses=[good],
    )
    with refine.Labeller(DATA, workers=0) as lab:
        rewards, status = refine.label_poses(
            lab, bank, np.zeros(4, int), np.concatenate([good, moved])
        )
    np.testing.assert_array_equal(rewards, [1, 1, 0, 0])


def _plane_bank(n_pairs=4, n=64, seed=0):
    rng = np.random.default_rng(seed)
    obj = rng.normal(size=(n_pairs, n, 3)).astype(np.float32)
    obj /= np.linalg.norm(obj, axis=-1, keepdims=True)
    sup = rng.uniform(-1, 1, size=(n_pairs, n, 3)).astype(np.float32) * 0.05
    sup[..., 2] = 0.0
    sup_n = np.zeros_like(sup)
    sup_n[..., 2] = 1.0
    clouds = PairClouds(obj * 0.02, obj, sup, sup_n)
    return PairBank(clouds, [{"object_name": "x", "support_name": "y"}] * n_pairs, [None] * n_pairs)


def test_value_learns_penetration_from_transitions():
    """V trained on (pose, reward) transitions separates poses that sink > 3 mm into a plane
    (reward 0) from poses resting on it (reward 1): held-out accuracy well above chance."""
    cfg = stage3.VALUE_TINY
    bank = _plane_bank()
    rng = np.random.default_rng(1)

    def transitions(m):
        z = rng.uniform(0.0, 0.04, m)  # sphere of radius 2 cm: z < 1.7 cm penetrates > 3 mm
        poses = np.zeros((m, 7), np.float32)
        poses[:, 2], poses[:, 3] = z, 1.0
        poses[:, :2] = rng.uniform(-0.01, 0.01, (m, 2))
        return rng.integers(len(bank), size=m), poses, (z > 0.017).astype(np.uint8)

    buf = ReplayBuffer()
    buf.add(*transitions(2000), "perturbed")
    trainer = refine.make_value_trainer(cfg, 300)
    state = trainer.init(jax.random.key(0))
    dev = jax.tree.map(jax.numpy.asarray, bank.clouds)
    vs, vp, vr = transitions(256)
    before = refine.classification_metrics(
        refine.predict_in_batches(trainer, state.params, dev, vs, vp, 128), vr
    )
    for i in range(150):
        idx = buf.sample(rng, cfg.batch_size)
        d = buf.data
        state, _ = trainer.step(state, dev, d["slot"][idx], d["pose"][idx], d["reward"][idx],
                                jax.random.key(i))  # fmt: skip
    after = refine.classification_metrics(
        refine.predict_in_batches(trainer, state.params, dev, vs, vp, 128), vr
    )
    assert after["balanced_accuracy"] > 0.8
    assert after["balanced_accuracy"] > before["balanced_accuracy"] + 0.15


def test_save_and_load_value(tmp_path):
    cfg = stage3.VALUE_TINY
    params = stage3.make_value(cfg).init(jax.random.key(0))
    refine.save_value(tmp_path / "v", cfg, params, step=3)
    cfg2, params2 = refine.load_value(tmp_path / "v")
    assert cfg2 == cfg
    leaves = jax.tree.leaves(params)
    np.testing.assert_array_equal(np.asarray(leaves[0]), np.asarray(jax.tree.leaves(params2)[0]))
    with pytest.raises(FileNotFoundError, match="train V first"):
        refine.load_value(tmp_path / "missing")


@pytest.mark.slow
def test_train_stage3_tiny_runs_and_resumes(tmp_path):
    """The whole RL job on a few derived pairs (tiny preset), then a rerun of the same folder
    with one more round: it resumes (no second seeding, the round counter continues, the
    buffer keeps its transitions) and writes V, metrics and curves."""
    import dataclasses
    import json

    from experiments.train_stage3 import PRESETS
    from omnihang_jax import dataset_bridge, rl

    dataset_bridge.derive_dataset(DATA, splits=("train",), limit=12, progress=False)
    cfg = dataclasses.replace(PRESETS["tiny"], rounds=1, round_start="alternate")
    out = tmp_path / "job"
    first = rl.train_stage3(cfg, out, DATA, "weights/stage12", progress=False)
    n1 = first["buffer"]["transitions"]
    assert first["state"]["round"] == 1 and first["state"]["seeded"]
    assert (out / "value" / "params.msgpack").exists() and (out / "curves.png").exists()
    seed_s = json.loads((out / "state.json").read_text())["seed_s"]
    second = rl.train_stage3(dataclasses.replace(cfg, rounds=2), out, DATA,
                             "weights/stage12", progress=False)  # fmt: skip
    assert second["state"]["round"] == 2
    assert second["state"]["seed_s"] == seed_s  # seeding not redone
    assert second["buffer"]["transitions"] > n1
    rounds = [json.loads(x) for x in (out / "rounds.jsonl").read_text().splitlines()]
    assert [r.get("round") for r in rounds if "round" in r] == [1, 2]
    # round_start="alternate": Stage 2's proposals in odd rounds, Stage 1's in even ones
    assert [r["start"] for r in rounds if "round" in r] == ["stage2", "stage1"]


def test_round_start_rule():
    from omnihang_jax.rl import round_start

    assert [round_start("alternate", r) for r in (1, 2, 3, 4)] == ["stage2", "stage1"] * 2
    assert round_start("stage1", 1) == round_start("stage1", 2) == "stage1"
    assert round_start("stage2", 2) == "stage2"
    with pytest.raises(ValueError, match="round_start"):
        round_start("uniform", 1)


def test_buffer_hard_stream_is_balanced_and_weighted():
    """hard_fraction f: round(f * batch) indices from the hard sources (CEM's answers and its
    top-scored members), half successes / half failures there, the rest 50/50 overall."""
    buf = ReplayBuffer()
    pose = np.float32([0, 0, 0, 1, 0, 0, 0])
    buf.add(np.zeros(1000), np.tile(pose, (1000, 1)), np.arange(1000) % 2, "perturbed")
    buf.add(np.zeros(20), np.tile(pose, (20, 1)), np.arange(20) < 5, "cem_top")  # 5 hang
    rng = np.random.default_rng(0)
    idx = buf.sample(rng, 64, hard_fraction=0.25)
    src, rew = buf.data["source"][idx], buf.data["reward"][idx]
    hard = src == refine.SOURCES.index("cem_top")
    # 16 drawn from the hard stream (8 + 8); the other 48 may hit them only by their 2 % share
    assert hard.sum() >= 16 and rew[hard].sum() >= 8 and (~rew[hard].astype(bool)).sum() >= 8
    assert rew.sum() == 32  # the batch stays balanced
    assert (buf.sample(rng, 64) >= 1000).sum() < 8  # without: their share (2 %)
    only_neg = ReplayBuffer()
    only_neg.add(np.zeros(10), np.tile(pose, (10, 1)), np.arange(10) % 2, "perturbed")
    only_neg.add(np.zeros(4), np.tile(pose, (4, 1)), np.zeros(4), "cem")  # no hard success
    idx = only_neg.sample(rng, 16, hard_fraction=0.5)
    assert (idx >= 10).sum() >= 8 and len(idx) == 16


def test_pair_bank_light_read_extend_and_cache(tmp_path):
    """The bank reads only what V needs, equal to subsample_clouds of the full pair; extend
    keeps slots; the .npz cache round-trips."""
    from omnihang_jax import dataset_bridge

    # its own 3 pairs (a fresh clone has no derived files)
    dataset_bridge.derive_dataset(DATA, tmp_path / "d", splits=("train",), limit=3,
                                  progress=False)  # fmt: skip
    files = sorted(dataset_bridge.derived_files(tmp_path / "d", "train"))[:3]
    cfg = stage3.VALUE_TINY
    bank = PairBank.from_files(files[:2], cfg, progress=False)
    bank.extend(PairBank.from_files(files[2:], cfg, progress=False))
    sample, meta = dataset_bridge.load_pair_file(files[2])
    full = PairClouds(sample.object_points, sample.object_normals, sample.support_points,
                      sample.support_normals)  # fmt: skip
    ref = stage3.subsample_clouds(full, cfg)
    for a, b in zip(ref, bank.clouds, strict=True):
        np.testing.assert_array_equal(np.asarray(a), b[2])
    assert bank.meta[2]["object_name"] == meta["object_name"] and len(bank) == 3
    np.testing.assert_array_equal(bank.stable_poses[2], sample.stable_poses[sample.pose_mask])
    bank.save(tmp_path / "bank.npz")
    again = PairBank.load(tmp_path / "bank.npz")
    assert again.meta == bank.meta
    np.testing.assert_array_equal(again.clouds.support_points, bank.clouds.support_points)
    for a, b in zip(again.stable_poses, bank.stable_poses, strict=True):
        np.testing.assert_array_equal(a, b)


def test_hard_negatives_teach_v_the_boundary():
    """The point of the hard stream: V trained on many easy cases (deep penetration, clear
    hangs) and a few hard negatives just past the boundary separates the boundary better
    when a share of every batch comes from those hard cases."""
    cfg = stage3.VALUE_TINY
    bank = _plane_bank()

    def poses_at(z, rng):
        p = np.zeros((len(z), 7), np.float32)
        p[:, 2], p[:, 3] = z, 1.0
        p[:, :2] = rng.uniform(-0.01, 0.01, (len(z), 2))
        return p

    def buffer(rng):
        buf = ReplayBuffer()
        easy_neg = rng.uniform(0.0, 0.008, 1500)  # far inside the plane
        pos = rng.uniform(0.017, 0.03, 1500)  # resting on it or above
        hard_neg = rng.uniform(0.011, 0.017, 60)  # 3-9 mm inside: V's false positives
        hard_pos = rng.uniform(0.017, 0.021, 60)
        for z, r, src in ((easy_neg, 0, "perturbed"), (pos, 1, "perturbed"),
                          (hard_neg, 0, "cem_top"), (hard_pos, 1, "cem_top")):  # fmt: skip
            buf.add(rng.integers(len(bank), size=len(z)), poses_at(z, rng), np.full(len(z), r), src)
        return buf

    dev = jax.tree.map(jax.numpy.asarray, bank.clouds)
    trng = np.random.default_rng(7)
    tz = np.concatenate([trng.uniform(0.011, 0.017, 200), trng.uniform(0.017, 0.021, 200)])
    ts, tp, tr = (
        trng.integers(len(bank), size=400),
        poses_at(tz, trng),
        (tz > 0.017).astype(np.uint8),
    )
    acc = {}
    for f in (0.0, 0.5):
        rng = np.random.default_rng(1)
        buf = buffer(rng)
        trainer = refine.make_value_trainer(cfg, 200)
        state = trainer.init(jax.random.key(0))
        for i in range(200):
            idx = buf.sample(rng, cfg.batch_size, hard_fraction=f)
            d = buf.data
            state, _ = trainer.step(state, dev, d["slot"][idx], d["pose"][idx], d["reward"][idx],
                                    jax.random.key(i))  # fmt: skip
        prob = refine.predict_in_batches(trainer, state.params, dev, ts, tp, 128)
        acc[f] = refine.classification_metrics(prob, tr)["balanced_accuracy"]
    assert acc[0.5] > acc[0.0] + 0.05, acc


@pytest.mark.slow
def test_hardneg_job_labels_the_top_members_and_takes_arriving_pairs(tmp_path):
    """The hard-negative job (preset hardneg_tiny) on 8 derived pairs, then on 12 after 4
    more "arrive" (the chain's background derive): slots keep their pairs, only the new
    pairs are seeded, rounds continue; every round adds K x keep_top top-scored members per
    pair, and their rewards are what the physics says when the poses are labelled again."""
    import dataclasses
    import json
    import os
    from pathlib import Path

    from experiments.train_stage3 import PRESETS
    from omnihang_jax import dataset_bridge, rl

    dataset_bridge.derive_dataset(DATA, splits=("train",), limit=12, progress=False)
    files = sorted(dataset_bridge.derived_files(f"{DATA}/derived", "train"))
    files = files[:: max(1, len(files) // 12)][:12]  # several objects: fit and val pairs
    ds = tmp_path / "ds"
    (ds / "derived" / "train").mkdir(parents=True)
    os.symlink(os.path.abspath(f"{DATA}/recipe.json"), ds / "recipe.json")
    os.symlink(os.path.abspath(f"{DATA}/shards"), ds / "shards")

    import shutil

    # copies, not links: the shared derived folder may be rewritten while the test runs
    store = tmp_path / "store"
    store.mkdir()
    files = [Path(shutil.copy(f, store / f.name)) for f in files]

    def arrive(fs):
        for f in fs:
            os.symlink(f, ds / "derived" / "train" / f.name)

    arrive(files[:8])
    cfg = dataclasses.replace(PRESETS["hardneg_tiny"], rounds=1, val_every=0, round_pairs=3)
    out = tmp_path / "job"
    first = rl.train_stage3(cfg, out, ds, "weights/stage12", progress=False)
    split1 = json.loads((out / "split.json").read_text())["files"]
    assert first["pairs"] == 8 and first["state"]["seeded_pairs"] == 8
    assert first["state"]["round"] == 1
    n_stable = first["buffer"]["stable"]["n"]
    arrive(files[8:])
    second = rl.train_stage3(dataclasses.replace(cfg, rounds=2), out, ds,
                             "weights/stage12", progress=False)  # fmt: skip
    split2 = json.loads((out / "split.json").read_text())["files"]
    assert second["pairs"] == 12 and split2[:8] == split1  # slots never move
    assert second["state"]["seeded_pairs"] == 12 and second["state"]["round"] == 2
    assert second["buffer"]["stable"]["n"] > n_stable  # the new pairs seeded, once
    buf = ReplayBuffer.load(out / "buffer.npz")
    d = buf.data
    top = d["source"] == refine.SOURCES.index("cem_top")
    for r in (1, 2):
        k, m = cfg.num_proposals, cfg.keep_top
        pairs_r = len(np.unique(d["slot"][top & (d["round"] == r)]))
        assert (top & (d["round"] == r)).sum() == pairs_r * k * m > 0
    rows = [json.loads(x) for x in (out / "rounds.jsonl").read_text().splitlines()]
    assert all("top_precision" in x for x in rows if "round" in x)
    # the labels are the physics': label the stored top members again
    bank = PairBank.load(out / "bank.npz")
    idx = np.flatnonzero(top)
    with refine.Labeller(ds, workers=0) as lab:
        again, _ = refine.label_poses(lab, bank, d["slot"][idx], d["pose"][idx])
    np.testing.assert_array_equal(again, d["reward"][idx])


def test_train_stage3_cli_applies_every_flag(monkeypatch):
    """Each train_stage3 flag reaches the job's RLConfig (a flag parsed and then dropped once
    cost a device call 211 s of seeding in a 464-s budget)."""
    from experiments import train_stage3 as T

    seen = {}
    monkeypatch.setattr(
        T, "train_stage3", lambda config, *a, **k: seen.setdefault("c", config) and {}
    )
    T.main(
        [
            "--preset",
            "hardneg",
            "--out",
            "x",
            "--seed-share",
            "0.25",
            "--round-start",
            "alternate",
            "--round-steps",
            "77",
            "--batch",
            "32",
            "--no-progress",
        ]
    )
    c = seen["c"]
    assert (c.seed_share, c.round_start, c.round_steps, c.value.batch_size) == (
        0.25,
        "alternate",
        77,
        32,
    )
