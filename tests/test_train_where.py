"""Training loop, checkpoints, predictor, data contract and the train/predict entry points."""

import dataclasses
import json
import os

import jax
import numpy as np
import pytest

from experiments import pack_dataset, train_where
from omnihang_jax import data, predict, train
from omnihang_jax.config import config_from_dict, config_to_dict


def _tiny(**train_overrides):
    cfg = train.WHERE_TINY
    return dataclasses.replace(
        cfg, train=dataclasses.replace(cfg.train, batch_size=2, log_every=1, **train_overrides)
    )


@pytest.fixture(scope="module")
def pool():
    return data.ArrayDataset(data.synthetic_batch(jax.random.key(0), 6, 128))


@pytest.mark.parametrize("preset", sorted(train.PRESETS))
def test_config_json_round_trip(preset):
    cfg = train.PRESETS[preset]
    text = json.dumps(config_to_dict(cfg))
    assert config_from_dict(train.NetworksConfig, json.loads(text)) == cfg


def test_checkpoint_resume_round_trip(tmp_path, pool):
    """3 steps + resume to 6 == 6 straight steps, bit for bit; the folder alone rebuilds it."""
    cfg = _tiny(checkpoint_every=3)
    straight = train.train_stage("1", cfg, pool, str(tmp_path / "a"), steps=6, progress=False)
    first = train.train_stage("1", cfg, pool, str(tmp_path / "b"), steps=3, progress=False)
    assert int(first.step) == 3
    resumed = train.train_stage("1", cfg, pool, str(tmp_path / "b"), steps=6, progress=False)
    assert int(resumed.step) == 6
    jax.tree.map(np.testing.assert_array_equal, resumed.params, straight.params)

    config, params, step = train.restore_stage(str(tmp_path / "b" / "stage1"))
    assert config == cfg and step == 6
    jax.tree.map(np.testing.assert_array_equal, params, straight.params)
    stage_dir = tmp_path / "b" / "stage1"
    rows = [json.loads(x) for x in open(stage_dir / "metrics.jsonl")]
    assert [r["step"] for r in rows] == [1, 2, 3, 4, 5, 6]
    assert all(np.isfinite(r["loss"]) for r in rows)
    assert (stage_dir / "loss.png").exists()
    # A folder trained with another architecture is never silently resumed.
    other = dataclasses.replace(train.WHERE_ORIGINAL, train=cfg.train)
    with pytest.raises(ValueError, match="different architecture"):
        train.train_stage("1", other, pool, str(tmp_path / "b"), steps=7, progress=False)


def test_time_budget_stops_and_checkpoints_and_records_throughput(tmp_path, pool):
    """A zero budget stops after the first step (saved); a rerun without it continues; the
    stage folder records the measured samples/s."""
    cfg = _tiny(checkpoint_every=100)
    state = train.train_stage(
        "1", cfg, pool, str(tmp_path), steps=50, progress=False, time_budget_s=0.0
    )
    assert int(state.step) == 1
    _, _, step = train.restore_stage(str(tmp_path / "stage1"))
    assert step == 1
    state = train.train_stage("1", cfg, pool, str(tmp_path), steps=4, progress=False)
    assert int(state.step) == 4
    tp = json.loads((tmp_path / "stage1" / "throughput.json").read_text())
    assert tp["steps_timed"] == 2 and tp["samples_per_s"] > 0
    assert tp["stopped_by_time_budget"] is False


@pytest.fixture(scope="module")
def trained_dir(tmp_path_factory):
    """All three stages through the command line, 2 steps each on synthetic pairs."""
    out = str(tmp_path_factory.mktemp("where"))
    argv = ["--data", "synthetic", "--out", out, "--preset", "tiny", "--steps", "2"]
    summary = train_where.main(argv + ["--batch", "2", "--no-progress"])
    assert summary == {"1": 2, "2a": 2, "2b": 2}
    return out


def test_cli_train_and_predict(trained_dir):
    """The trained folder loads as a predictor: K finite Stage-1 and Stage-2 poses per pair."""
    for stage in ("stage1", "stage2a", "stage2b"):
        assert os.path.exists(os.path.join(trained_dir, stage, "config.json"))
    predictor = predict.load_predictor(trained_dir)
    rng = np.random.default_rng(0)
    obj = rng.normal(scale=0.03, size=(2, 256, 3)).astype(np.float32)
    sup = rng.normal(scale=0.05, size=(2, 256, 3)).astype(np.float32)
    out = predictor(obj, sup, num_proposals=3)
    assert out.stage1_poses.shape == (2, 3, 7) and out.stage2_poses.shape == (2, 3, 7)
    assert np.isfinite(out.stage1_poses).all() and np.isfinite(out.stage2_poses).all()
    # Stage 2 keeps Stage 1's rotation and moves only the translation
    np.testing.assert_allclose(out.stage2_poses[..., 3:], out.stage1_poses[..., 3:], atol=1e-6)


def test_exported_weights_predict_like_the_checkpoints(trained_dir, tmp_path):
    steps = train.export_weights(trained_dir, str(tmp_path / "w"))
    assert steps == {"1": 2, "2a": 2, "2b": 2}
    assert not (tmp_path / "w" / "stage1" / "checkpoints").exists()
    obj = np.random.default_rng(0).normal(scale=0.05, size=(2, 128, 3)).astype(np.float32)
    sup = np.random.default_rng(1).normal(scale=0.1, size=(2, 128, 3)).astype(np.float32)
    key = jax.random.key(3)
    a = predict.load_predictor(trained_dir)(obj, sup, key=key, num_proposals=3)
    b = predict.load_predictor(str(tmp_path / "w"))(obj, sup, key=key, num_proposals=3)
    np.testing.assert_allclose(a.stage2_poses, b.stage2_poses, rtol=1e-6, atol=1e-6)


def test_predictor_is_jitted_batched_and_finite(trained_dir):
    predictor = predict.load_predictor(trained_dir)
    batch = data.synthetic_batch(jax.random.key(5), 3, 128)
    out = predictor(batch.object_points, batch.support_points, jax.random.key(0), num_proposals=4)
    k3 = predictor.stage2_config.k_pairs
    assert out.stage1_poses.shape == (3, 4, 7) and out.stage2_poses.shape == (3, 4, 7)
    assert out.object_indices.shape == (3, 4, k3) and out.object_indices.dtype == np.int32
    for poses7 in (out.stage1_poses, out.stage2_poses):
        assert np.all(np.isfinite(poses7))
        np.testing.assert_allclose(np.linalg.norm(poses7[..., 3:], axis=-1), 1.0, atol=1e-5)
    # Stage 2 keeps Stage 1's rotation.
    np.testing.assert_allclose(out.stage2_poses[..., 3:], out.stage1_poses[..., 3:], atol=1e-6)
    # The pure function itself jits (traced once per static num_proposals).
    fn = jax.jit(
        predict.make_predict(predictor.stage1_config, predictor.stage2_config),
        static_argnames="num_proposals",
    )
    again = fn(
        predictor.stage1_params,
        predictor.stage2_params,
        batch.object_points,
        batch.support_points,
        jax.random.key(0),
        num_proposals=4,
    )
    np.testing.assert_allclose(again.stage2_poses, out.stage2_poses, atol=1e-6)


def test_nan_clouds_raise_at_the_boundary(trained_dir):
    predictor = predict.load_predictor(trained_dir)
    batch = data.synthetic_batch(jax.random.key(5), 1, 128)
    bad = np.array(batch.object_points)
    bad[0, 3, 1] = np.nan
    with pytest.raises(ValueError, match="object_points contains 1 non-finite"):
        predictor(bad, batch.support_points)
    with pytest.raises(ValueError, match=r"\[B, N, 3\]"):
        predictor(batch.object_points[..., :2], batch.support_points)


def test_dataset_directory_round_trip_and_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        data.load_hang_dataset(tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="one .npz per"):
        data.load_hang_dataset(tmp_path)
    (tmp_path / "recipe.json").write_text("{}")
    with pytest.raises(FileNotFoundError, match="derive_pair"):
        data.load_hang_dataset(tmp_path)

    samples = data.unstack(data.synthetic_batch(jax.random.key(1), 3, 64, max_poses=3))
    os.makedirs(tmp_path / "train")
    for i, s in enumerate(samples):
        d = int(s.pose_mask.sum())  # store unpadded, as the engine would
        trimmed = s._replace(
            stable_poses=s.stable_poses[:d],
            pose_mask=s.pose_mask[:d],
            object_contact_maps=s.object_contact_maps[:d],
            support_contact_maps=s.support_contact_maps[:d],
            contact_pairs=s.contact_pairs[:d, :1],
            contact_mask=s.contact_mask[:d, :1],
        )
        np.savez(tmp_path / "train" / f"pair_{i}.npz", **trimmed._asdict())
    dataset = data.load_hang_dataset(tmp_path, max_poses=5)
    assert len(dataset) == 3
    batch = dataset.sample_batch(np.random.default_rng(0), 4)
    assert batch.stable_poses.shape == (4, 5, 7) and batch.pose_mask.shape == (4, 5)
    assert batch.contact_pairs.shape == (4, 5, 1, 2) and batch.contact_pairs.dtype == np.int32
    assert not batch.pose_mask[:, 3:].any()
    # the device-resident dataset gives the very same batches for the same rng, and so do
    # the host cache and the plain reader
    on_device = data.load_hang_dataset(tmp_path, max_poses=5, on_device=True)
    cached = data.load_hang_dataset(tmp_path, max_poses=5, cache=True)
    assert isinstance(on_device, data.DeviceDataset) and len(on_device) == 3
    for seed in (0, 1):
        ref = dataset.sample_batch(np.random.default_rng(seed), 4)
        for other in (on_device, cached):
            got = other.sample_batch(np.random.default_rng(seed), 4)
            for field, a, b in zip(data.HangSample._fields, ref, got, strict=True):
                np.testing.assert_array_equal(np.asarray(b), a, err_msg=field)

    # NaN in a stored cloud -> clear ValueError naming the file, when it is read.
    bad_points = samples[0].support_points.copy()
    bad_points[7] = np.nan
    bad = samples[0]._replace(support_points=bad_points)
    np.savez(tmp_path / "train" / "pair_0.npz", **bad._asdict())
    with pytest.raises(ValueError, match="pair_0.npz: support_points contains 1 non-finite"):
        data.load_hang_dataset(tmp_path).sample_batch(np.random.default_rng(0), 8)


def test_make_hang_sample_pads_ragged_contacts():
    s = data.unstack(data.synthetic_batch(jax.random.key(2), 1, 32, max_poses=2))[0]
    sample = data.make_hang_sample(
        **{k: v for k, v in s._asdict().items() if k not in ("contact_pairs",)},
        contact_pairs=[np.array([[1, 2], [3, 4], [5, 6]]), np.zeros((0, 2))],
    )
    assert sample.contact_pairs.shape == (2, 3, 2)
    np.testing.assert_array_equal(sample.contact_mask, [[1, 1, 1], [0, 0, 0]])
    nan_sample = s._replace(object_points=s.object_points * np.nan)
    with pytest.raises(ValueError, match="non-finite"):
        data.validate_sample(nan_sample)


def test_synthetic_batch_is_physically_plausible():
    """The ring rests on the peg at every stable pose: no penetration, contact at the top."""
    from omnihang_jax.poses import pose7_to_pose6, transform_points

    batch = data.synthetic_batch(jax.random.key(3), 3, 512)
    for b in range(3):
        peg_r = np.linalg.norm(batch.support_points[b, :400, 1:], axis=1).mean()
        for d in np.flatnonzero(batch.pose_mask[b]):
            moved = np.asarray(
                transform_points(pose7_to_pose6(batch.stable_poses[b, d]), batch.object_points[b])
            )
            radial = np.linalg.norm(moved[:, 1:], axis=1)
            assert radial.min() > peg_r - 1e-3  # tube never inside the peg
            assert radial.min() < peg_r + 2e-3  # and touching it
        assert batch.object_contact_maps[b][batch.pose_mask[b]].max() == pytest.approx(1.0)


@pytest.mark.slow
def test_original_preset_forward_and_train_step():
    """ORIGINAL sizes (4096-point clouds, 1024-d encodings, K1 = K2 = 128): one train step of
    every stage and one prediction, all finite."""
    cfg = dataclasses.replace(
        train.WHERE_ORIGINAL, train=dataclasses.replace(train.WHERE_ORIGINAL.train, batch_size=2)
    )
    batch = data.synthetic_batch(jax.random.key(0), 2, 4096)
    params = {}
    for stage in train.STAGES:
        state = jax.jit(train.make_init_state(stage, cfg))(jax.random.key(1))
        state, metrics = jax.jit(train.make_train_step(stage, cfg))(state, batch, jax.random.key(2))
        assert all(np.isfinite(float(v)) for v in metrics.values()), (stage, metrics)
        params[stage] = state.params
    predictor = predict.Predictor(cfg.stage1, params["1"], cfg.stage2, params["2b"])
    out = predictor(batch.object_points, batch.support_points, num_proposals=5)
    assert out.stage2_poses.shape == (2, 5, 7) and np.all(np.isfinite(out.stage2_poses))
    assert out.object_indices.shape == (2, 5, 3)


def test_learning_rate_schedule_warms_up_and_decays():
    cfg = dataclasses.replace(
        train.WHERE_SMALL,
        train=dataclasses.replace(
            train.WHERE_SMALL.train, steps=1000, warmup_steps=50, final_lr_ratio=0.1
        ),
    )
    lr = train.learning_rate_schedule("1", cfg)
    peak = cfg.train.lr_stage1
    assert float(lr(0)) == 0.0
    assert float(lr(25)) == pytest.approx(peak / 2, rel=1e-5)
    assert float(lr(50)) == pytest.approx(peak, rel=1e-5)
    assert peak * 0.1 < float(lr(500)) < peak
    assert float(lr(1000)) == pytest.approx(peak * 0.1, rel=1e-4)
    const = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, schedule="constant"))
    assert float(train.learning_rate_schedule("2a", const)(999)) == const.train.lr_stage2
    bad = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, schedule="step"))
    with pytest.raises(ValueError, match="unknown schedule"):
        train.learning_rate_schedule("1", bad)


def _write_named_pairs(folder, objects, pairs_per_object=2):
    os.makedirs(folder, exist_ok=True)
    batch = data.synthetic_batch(jax.random.key(3), len(objects) * pairs_per_object, 128)
    files, k = [], 0
    for name in objects:
        for j in range(pairs_per_object):
            one = {f: np.asarray(x[k]) for f, x in batch._asdict().items()}
            path = os.path.join(folder, f"{k:05d}_{name}__peg_{j:04d}.npz")
            np.savez(path, **one)
            files.append(path)
            k += 1
    return files


def test_object_split_pack_and_validation_curve(tmp_path):
    objects = [f"mug_{i:04d}" for i in range(12)]
    files = _write_named_pairs(str(tmp_path / "derived" / "train"), objects)
    names = [data.object_name_of(f) for f in files]
    assert names[0] == "mug_0000" and data.object_name_of("a/pair.npz") == "pair"
    fit, val = data.split_by_object(names, 0.3)
    assert len(val) and len(fit) and len(fit) + len(val) == len(files)
    # whole objects: no object on both sides, and the split does not depend on order
    assert not {names[i] for i in fit} & {names[i] for i in val}
    assert data.validation_objects(objects[::-1], 0.3) == {names[i] for i in val}

    # a broken file is skipped with its reason, the rest is packed
    with open(tmp_path / "derived" / "train" / "99999_bad_0000__peg_0000.npz", "wb") as f:
        f.write(b"not an npz")
    pack = str(tmp_path / "pack")
    summary = pack_dataset.main(
        ["--data", str(tmp_path), "--out", pack, "--threads", "2", "--no-progress"]
    )
    assert summary["packed"] == len(files) and summary["skipped"] == 1
    packed = data.PackedDataset(pack)
    ref = data.NpzDirectoryDataset(files, max_contacts=packed.meta["max_contacts"])
    rng_a, rng_b = np.random.default_rng(5), np.random.default_rng(5)
    a, b = packed.sample_batch(rng_a, 3), ref.sample_batch(rng_b, 3)
    np.testing.assert_array_equal(np.asarray(a.object_points), b.object_points)
    np.testing.assert_array_equal(np.asarray(a.contact_pairs), b.contact_pairs)
    np.testing.assert_allclose(np.asarray(a.object_contact_maps), b.object_contact_maps, atol=2e-3)
    lean = data.PackedDataset(pack, fields=train.STAGE1_FIELDS)
    assert lean.sample_batch(rng_a, 2).object_contact_maps.shape == (2, 1)

    # training from the pack: validation rows, best parameters, export of the best
    out = str(tmp_path / "run")
    train_where.main(
        [
            "--data",
            pack,
            "--out",
            out,
            "--preset",
            "tiny",
            "--stage",
            "1",
            "--steps",
            "20",
            "--batch",
            "2",
            "--val-fraction",
            "0.3",
            "--eval-every",
            "10",
            "--export",
            str(tmp_path / "w"),
            "--no-progress",
        ]  # fmt: skip
    )
    with open(os.path.join(out, "stage1", "val_metrics.jsonl")) as f:
        rows = [json.loads(line) for line in f]
    assert [r["step"] for r in rows] == [10, 20]
    assert rows[0]["val_pairs"] == len(val) and np.isfinite(rows[-1]["val_loss"])
    with open(os.path.join(out, "stage1", "best", "best.json")) as f:
        best = json.load(f)
    assert best["val_loss"] == min(r["val_loss"] for r in rows)
    with open(tmp_path / "w" / "stage1" / "config.json") as f:
        assert json.load(f)["step"] == best["step"]


@pytest.mark.slow  # the fine-tuning start (--init-from), an option of the trainer
def test_init_from_exported_weights_starts_there(trained_dir, tmp_path):
    """--init-from: a stage without a checkpoint starts from the given weights (a tiny lr
    leaves them in place), and a mismatched preset is refused."""
    train.export_weights(trained_dir, str(tmp_path / "w"), ("1",))
    out = str(tmp_path / "ft")
    argv = ["--data", "synthetic", "--preset", "tiny", "--stage", "1", "--steps", "1"]
    argv += ["--batch", "2", "--lr-stage1", "1e-12", "--no-progress"]
    train_where.main(argv + ["--out", out, "--init-from", str(tmp_path / "w")])
    _, start, _ = train.restore_stage(os.path.join(tmp_path, "w", "stage1"))
    _, tuned, step = train.restore_stage(os.path.join(out, "stage1"))
    assert step == 1
    for a, b in zip(jax.tree.leaves(start), jax.tree.leaves(tuned)):
        np.testing.assert_allclose(a, b, atol=1e-6)
    with pytest.raises(ValueError, match="network config differs"):
        small = argv[:3] + ["small"] + argv[4:]
        train_where.main(small + ["--out", str(tmp_path / "x"), "--init-from", str(tmp_path / "w")])


def test_object_turn_needs_at_least_one_frame_hypothesis(tmp_path, capsys):
    from experiments import train_where

    with pytest.raises(SystemExit) as stop:
        train_where.main(["--data", "synthetic", "--out", str(tmp_path / "run"),
                          "--augment-object-turn", "0"])  # fmt: skip
    assert stop.value.code == 2 and "M >= 1" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()  # nothing written
