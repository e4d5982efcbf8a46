"""Dataset -> HangSample bridge and the hanging-success evaluation protocol."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest

from omnihang_jax import data, dataset_bridge, evaluate
from omnihang_jax.predict import Predictor
from omnihang_jax.stage1 import STAGE1_TINY, make_stage1
from omnihang_jax.stage2 import STAGE2_TINY, make_stage2
from sim import dataset, kernels
from sim.library import build_library

CFG = dataset.PRESETS["tiny"]  # 4 pairs: mug, wrench x single_rod_hook, towel_bar


@pytest.fixture(scope="module")
def derived(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds")
    dataset.generate(CFG, out, preset="test", progress=False)
    summary = dataset_bridge.derive_dataset(out, progress=False)
    return out, summary


@pytest.fixture(scope="module")
def library():
    return build_library(CFG.library, progress=False)


def test_derived_files_load_as_hang_samples(derived):
    out, summary = derived
    recipe = json.loads((out / "recipe.json").read_text())
    with_stable = summary["files_per_split"]["train"] + summary["files_per_split"]["test"]
    assert with_stable + summary["pairs_without_stable_poses"] == len(recipe["pairs"])
    assert summary["files_per_split"]["train"] >= 1 and summary["files_per_split"]["test"] >= 1
    for split in ("train", "test"):
        # Both the dataset folder (what train_where --data gets) and derived/ itself work.
        for root in (out, out / "derived"):
            ds = data.load_hang_dataset(root, split=split)
            assert len(ds) == summary["files_per_split"][split]
            batch = ds.sample_batch(np.random.default_rng(0), 3)
            assert batch.object_points.shape == (3, CFG.camera.n_points, 3)
            assert batch.stable_poses.shape == (3, data.MAX_STABLE_POSES, 7)
        for path in dataset_bridge.derived_files(out / "derived", split):
            sample, meta = dataset_bridge.load_pair_file(path)
            assert meta["split"] == split == recipe["pairs"][meta["pair_index"]][2]
            assert [meta["object_name"], meta["support_name"]] == recipe["pairs"][
                meta["pair_index"]
            ][:2]
            assert np.asarray(sample.pose_mask).sum() >= 1


def test_derive_is_resumable_and_checks_its_input(derived, tmp_path):
    out, summary = derived
    again = dataset_bridge.derive_dataset(out, progress=False)
    assert again["written_this_run"] == 0
    assert again["skipped_existing"] == sum(summary["files_per_split"].values())
    with pytest.raises(FileNotFoundError, match="recipe.json"):
        dataset_bridge.derive_dataset(tmp_path, progress=False)


def test_derive_with_workers_writes_the_same_files(derived, tmp_path):
    out, summary = derived
    par = dataset_bridge.derive_dataset(out, tmp_path / "par", progress=False, workers=2)
    assert par["files_per_split"] == summary["files_per_split"]
    for split in ("train", "test"):
        for path in dataset_bridge.derived_files(out / "derived", split):
            with np.load(path) as a, np.load(tmp_path / "par" / split / path.name) as b:
                for key in a.files:
                    np.testing.assert_array_equal(a[key], b[key])


def test_clouds_only_derive_keeps_the_clouds_and_is_refused_for_stage2(derived, tmp_path):
    from omnihang_jax import train

    out, summary = derived
    fast = dataset_bridge.derive_dataset(
        out, tmp_path / "d", splits=("train",), progress=False, clouds_only=True
    )
    assert fast["clouds_only"] and fast["files_per_split"] == {
        "train_clouds": summary["files_per_split"]["train"]
    }
    full_files = dataset_bridge.derived_files(out / "derived", "train")
    for path in full_files:
        with np.load(path) as a, np.load(tmp_path / "d" / "train_clouds" / path.name) as b:
            for key in ("object_points", "object_normals", "support_points", "stable_poses"):
                np.testing.assert_array_equal(a[key], b[key])
            assert bool(a["contact_maps"]) and not bool(b["contact_maps"])
            assert not b["object_contact_maps"].any() and not b["contact_mask"].any()
    meta = data.pack_dataset(
        sorted((tmp_path / "d" / "train_clouds").glob("*.npz")), tmp_path / "p", progress=False
    )
    assert meta["has_contact_maps"] is False
    config = train.WHERE_TINY
    with pytest.raises(ValueError, match="clouds-only"):
        train.make_dataset(str(tmp_path / "p"), config)
    fit, _ = train.make_dataset(str(tmp_path / "p"), config, fields=train.STAGE1_FIELDS)
    assert len(fit) >= 1


def test_half_resolution_clouds_derive_to_their_own_folder(derived, tmp_path):
    """--camera-scale 0.5: half the recipe's resolution (640 x 480 -> 320 x 240) into train_clouds_r50/, the same number of finite
    points near the full-resolution clouds of the same view; refused without clouds_only."""
    from scipy.spatial import cKDTree

    out, summary = derived
    half = dataset_bridge.derive_dataset(
        out, tmp_path / "h", splits=("train",), progress=False, clouds_only=True, camera_scale=0.5
    )
    cam = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(out)).camera
    assert half["camera_resolution"] == [round(cam.width / 2), round(cam.height / 2)]
    assert half["files_per_split"] == {"train_clouds_r50": summary["files_per_split"]["train"]}
    for path in dataset_bridge.derived_files(out / "derived", "train"):
        with np.load(path) as a, np.load(tmp_path / "h" / "train_clouds_r50" / path.name) as b:
            np.testing.assert_array_equal(a["stable_poses"], b["stable_poses"])
            for key in ("object_points", "support_points"):
                assert b[key].shape == a[key].shape and np.isfinite(b[key]).all()
                assert not np.array_equal(a[key], b[key])  # a different pixel grid
                gap = cKDTree(a[key]).query(b[key])[0]
                assert np.median(gap) < 0.01  # the same visible surface
    with pytest.raises(ValueError, match="clouds-only"):
        dataset_bridge.derive_dataset(out, tmp_path / "x", progress=False, camera_scale=0.5)


def test_another_view_derives_and_packs_beside_the_first(derived, tmp_path):
    """view=1: the pair's next candidate view (not the record's), same poses, own folder;
    pack_dataset --split a,b packs both views; refused without clouds_only."""
    from experiments import pack_dataset

    out, summary = derived
    n = summary["files_per_split"]["train"]
    for view in (0, 1):
        got = dataset_bridge.derive_dataset(
            out,
            tmp_path / "derived",
            splits=("train",),
            progress=False,
            clouds_only=True,
            view=view,
        )
        assert got["view"] == view
    assert got["files_per_split"] == {"train_clouds_v1": n}
    for path in sorted((tmp_path / "derived" / "train_clouds").glob("*.npz")):
        with np.load(path) as a, np.load(tmp_path / "derived" / "train_clouds_v1" / path.name) as b:
            np.testing.assert_array_equal(a["stable_poses"], b["stable_poses"])
            assert not np.allclose(
                a["support_points"].mean(0), b["support_points"].mean(0), atol=1e-4
            )
    packed = pack_dataset.main(
        ["--data", str(tmp_path), "--split", "train_clouds,train_clouds_v1", "--out",
         str(tmp_path / "p"), "--threads", "1", "--no-progress"]
    )  # fmt: skip
    assert packed["pairs"] == 2 * n
    with pytest.raises(ValueError, match="clouds-only"):
        dataset_bridge.derive_dataset(out, tmp_path / "x", progress=False, view=1)


def _shifted_fn(shift) -> evaluate.PredictFn:
    truth = evaluate.ground_truth_fn()

    def predict(sample, meta):
        pose = truth(sample, meta).stage1_poses.copy()
        pose[:, :3] += shift
        return evaluate.PairPrediction(pose, pose)

    return predict


def test_protocol_labels_ground_truth_stable_and_far_pose_failed(derived, library):
    out, _ = derived
    files = dataset_bridge.derived_files(out / "derived", "test")
    good = evaluate.evaluate_pairs(files, evaluate.ground_truth_fn(), library, progress=False)
    # 20 cm out from the wall (supports reach towards +y): nothing to hang on.
    bad = evaluate.evaluate_pairs(files, _shifted_fn([0.0, 0.2, 0.0]), library, progress=False)
    for g, b in zip(good, bad):
        for stage in ("stage1", "stage1_2"):
            assert g[stage]["success"] and g[stage]["status"] == "stable", g
            assert g[stage]["translation_error_m"] == pytest.approx(0.0, abs=1e-6)
            assert g[stage]["rotation_error_deg"] == pytest.approx(0.0, abs=1e-2)
            assert not b[stage]["success"] and b[stage]["status"] != "stable", b
            assert b[stage]["translation_error_m"] > 0.1
    summary = evaluate.summarize_success(good, "stage1")
    assert summary["mean"] == 100.0 and summary["pairs"] == len(files)
    assert evaluate.summarize_success(bad, "stage1_2")["mean"] == 0.0


def test_protocol_settings():
    cfg = evaluate.protocol_stability()
    assert isinstance(cfg, kernels.StabilityConfig)
    assert cfg.duration == 1.0  # 100 steps of 1/100 s
    assert cfg.max_penetration == 0.003  # 3 mm


def test_pose_errors_against_hand_computed_values():
    sample = data.make_hang_sample(
        object_points=np.zeros((4, 3)),
        object_normals=np.tile([0.0, 0.0, 1.0], (4, 1)),
        support_points=np.zeros((4, 3)),
        support_normals=np.tile([0.0, 0.0, 1.0], (4, 1)),
        stable_poses=[[0, 0, 0, 1, 0, 0, 0], [1, 0, 0, 1, 0, 0, 0]],
        object_contact_maps=np.zeros((2, 4)),
        support_contact_maps=np.zeros((2, 4)),
        contact_pairs=[np.zeros((1, 2), int), np.zeros((1, 2), int)],
    )
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)  # 90 degrees about z
    err = evaluate.pose_errors(np.array([[0.9, 0.0, 0.1, c, 0, 0, s]]), sample)
    assert err["translation_error_m"][0] == pytest.approx(np.hypot(0.1, 0.1))
    assert err["rotation_error_deg"][0] == pytest.approx(90.0)
    assert err["min_rotation_error_deg"][0] == pytest.approx(90.0)


def test_evaluate_where_writes_results(derived, library, tmp_path):
    out, _ = derived
    results = evaluate.evaluate_where(
        None, out, tmp_path / "success.json", tmp_path / "errors.json", progress=False
    )
    saved = json.loads((tmp_path / "success.json").read_text())
    assert saved == json.loads(json.dumps(results))
    for stage in ("stage1", "stage1_2"):
        assert set(saved[stage]) >= {"mean", "per_category"}
        assert saved[stage]["mean"] == 100.0
    for key in ("pairs", "model", "dataset", "protocol"):
        assert key in saved
    assert saved["protocol"]["stage2_clearance_m"] is None  # the model's own
    errors = json.loads((tmp_path / "errors.json").read_text())
    assert {"stage1", "stage2"} <= set(errors)
    lines = (tmp_path / "success.pairs.jsonl").read_text().splitlines()
    assert len(lines) == saved["pairs"] >= 1

    # The network path: an untrained TINY predictor gives finite poses that get labelled.
    key1, key2 = jax.random.split(jax.random.key(0))
    predictor = Predictor(
        STAGE1_TINY,
        make_stage1(STAGE1_TINY).init(key1),
        STAGE2_TINY,
        make_stage2(STAGE2_TINY).init(key2),
    )
    files = dataset_bridge.derived_files(out / "derived", "test")[:1]
    records = evaluate.evaluate_pairs(
        files, evaluate.predictor_fn(predictor, 2), library, progress=False
    )
    assert records[0]["num_proposals"] == 2
    for stage in ("stage1", "stage1_2"):
        assert records[0][stage]["status"] in kernels.STATUS_NAMES
        assert np.isfinite(records[0][stage]["pose"]).all()

    # EvalConfig.stage2_clearance reaches Stage 2 with the pair's observed support normals:
    # the Stage-2 translation moves by exactly the clearance, Stage 1 is untouched.
    sample, meta = dataset_bridge.load_pair_file(files[0])
    moved = Predictor(
        STAGE1_TINY,
        predictor.stage1_params,
        dataclasses.replace(STAGE2_TINY, clearance=0.006),
        predictor.stage2_params,
    )
    a = evaluate.predictor_fn(predictor, 2)(sample, meta)
    b = evaluate.predictor_fn(moved, 2)(sample, meta)
    np.testing.assert_array_equal(a.stage1_poses, b.stage1_poses)
    shift = np.linalg.norm(b.stage2_poses[:, :3] - a.stage2_poses[:, :3], axis=-1)
    np.testing.assert_allclose(shift, 0.006, atol=1e-5)

    # EvalConfig.stage1_lift (evaluate.lifted_fn): every Stage-1 pose moves exactly that far
    # up (+z), rotation and Stage 2 untouched
    c = evaluate.lifted_fn(evaluate.predictor_fn(predictor, 2), 0.0075)(sample, meta)
    np.testing.assert_allclose(c.stage1_poses[:, 2] - a.stage1_poses[:, 2], 0.0075, atol=1e-7)
    np.testing.assert_array_equal(
        c.stage1_poses[:, [0, 1, 3, 4, 5, 6]], a.stage1_poses[:, [0, 1, 3, 4, 5, 6]]
    )
    np.testing.assert_array_equal(c.stage2_poses, a.stage2_poses)

    # EvalConfig.stage2_lift (evaluate.lifted_stage2_fn) wraps the ranked predictor: the answer
    # is chosen first, then every Stage-2 pose (the answer first) is released exactly that far
    # up, order, rotations and Stage 1 untouched
    ranked = evaluate.ranked_fn(evaluate.predictor_fn(predictor, 2))
    r = ranked(sample, meta)
    d = evaluate.lifted_stage2_fn(ranked, 0.005)(sample, meta)
    np.testing.assert_allclose(d.stage2_poses[:, 2] - r.stage2_poses[:, 2], 0.005, atol=1e-7)
    np.testing.assert_array_equal(
        d.stage2_poses[:, [0, 1, 3, 4, 5, 6]], r.stage2_poses[:, [0, 1, 3, 4, 5, 6]]
    )
    np.testing.assert_array_equal(d.stage1_poses, r.stage1_poses)


def test_stage2_from_ground_truth_diagnostic(derived):
    out, _ = derived
    files = dataset_bridge.derived_files(out / "derived", "test")[:2]
    params = make_stage2(STAGE2_TINY).init(jax.random.key(0))
    diag = evaluate.stage2_from_ground_truth(STAGE2_TINY, params, files, 0.01, 0.05)
    assert diag["pairs"] == len(files) >= 1
    for key in ("input", "stage2", "oracle_contacts"):
        assert np.isfinite(diag[key]["mean"]) and diag[key]["min"] >= 0.0
    # Perfect correspondences land close to the ground-truth pose (the data is consistent).
    assert diag["oracle_contacts"]["max"] < 0.02


def test_derive_order_is_round_robin_over_categories():
    """A derive cut short (time budget, --limit) covers every category present: jobs go
    round robin over object categories, each in pair-index order."""
    pairs = [
        (f"{c}_{i:04d}", "hook_0000", "train") for c in ("bag", "cap", "mug") for i in range(3)
    ]
    pairs = pairs[:7]  # bag x3, cap x3, mug x1
    jobs = [({"pair_index": i}, f"p{i}") for i in range(len(pairs))]
    order = [j[1] for j in dataset_bridge.interleave_by_category(jobs, pairs)]
    assert order == ["p0", "p3", "p6", "p1", "p4", "p2", "p5"]
    assert dataset_bridge.interleave_by_category([], pairs) == []
