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

    from sim import dataset

    with np.load(sorted(glob.glob(f"{DATA}/shards/shard_*.npz"))[0]) as z:
        records = dataset.unpack({k: z[k] for k in z.files})
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
    cfg = dataclasses.replace(PRESETS["tiny"], rounds=1)
    out = tmp_path / "job"
    first = rl.train_stage3(cfg, out, DATA, "weights/where_small_paper", progress=False)
    n1 = first["buffer"]["transitions"]
    assert first["state"]["round"] == 1 and first["state"]["seeded"]
    assert (out / "value" / "params.msgpack").exists() and (out / "curves.png").exists()
    seed_s = json.loads((out / "state.json").read_text())["seed_s"]
    second = rl.train_stage3(dataclasses.replace(cfg, rounds=2), out, DATA,
                             "weights/where_small_paper", progress=False)  # fmt: skip
    assert second["state"]["round"] == 2
    assert second["state"]["seed_s"] == seed_s  # seeding not redone
    assert second["buffer"]["transitions"] > n1
    rounds = [json.loads(x) for x in (out / "rounds.jsonl").read_text().splitlines()]
    assert [r.get("round") for r in rounds if "round" in r] == [1, 2]
