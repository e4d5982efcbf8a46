"""``omnihang_jax.where`` (one answer for the command and the evaluation) and its held-out
evaluation ``omnihang_jax.where_eval`` / ``experiments.evaluate where``, on tiny networks."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import flax.serialization
import jax
import numpy as np
import pytest

from omnihang_jax import config as config_mod
from omnihang_jax import pipeline, refine, stage3, train, where, where_eval

PAPER = Path(__file__).resolve().parents[1] / "datasets" / "paper"
# one worker for the module: its tests share the tiny answer's compiled program
pytestmark = pytest.mark.xdist_group("where")


def random_params(init, seed: int):
    """Parameters of ``init``'s shapes drawn at random, without running ``init`` (an eager
    init of the networks costs seconds of op-by-op dispatch on the CPU)."""
    rng = np.random.default_rng(seed)
    shapes = jax.eval_shape(init, jax.random.key(0))
    return jax.tree.map(lambda x: (0.1 * rng.standard_normal(x.shape)).astype(x.dtype), shapes)


def save_tiny_stage12(folder: Path) -> None:
    """A Stage 1 + 2 folder of the tiny preset with random parameters, in the exported
    format ``predict.load_predictor`` reads (``train.export_weights``)."""
    cfg = train.WHERE_TINY
    for i, stage in enumerate(("1", "2b")):
        dst = Path(train._stage_dir(str(folder), stage))
        dst.mkdir(parents=True)
        params = random_params(lambda k, s=stage: train.make_init_state(s, cfg)(k).params, i)
        (dst / train.WEIGHTS_FILE).write_bytes(flax.serialization.to_bytes(params))
        saved = dict(stage=stage, config=config_mod.config_to_dict(cfg), step=0)
        (dst / "config.json").write_text(json.dumps(saved))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> where.WhereConfig:
    root = tmp_path_factory.mktemp("tiny_where")
    save_tiny_stage12(root / "stage12")
    for name, seed in (("value", 0), ("ranker", 1)):
        net = stage3.make_value(stage3.VALUE_TINY)
        refine.save_value(root / name, stage3.VALUE_TINY, random_params(net.init, seed))
    pipe = dataclasses.replace(
        pipeline.ANSWER_PIPELINE, num_proposals=3, views=((0, 1), (1, 2)),
        cem=stage3.CEMConfig(population=8, iterations=2, elites=3),
    )  # fmt: skip
    return where.WhereConfig(stage12=str(root / "stage12"), value=str(root / "value"),
                             rankers=(str(root / "ranker"),), pipeline=pipe, check=4)  # fmt: skip


def pairs(batch: int, seed: int = 0, n: int = 4096) -> stage3.PairClouds:
    """A small ball over a bar (support along x at z = 0) per pair."""
    rng = np.random.default_rng(seed)
    obj = rng.normal(size=(batch, n, 3)).astype(np.float32)
    obj_n = obj / np.linalg.norm(obj, axis=-1, keepdims=True)
    sup = np.zeros((batch, n, 3), np.float32)
    sup[..., 0] = rng.uniform(-0.1, 0.1, (batch, n))
    ang = rng.uniform(0, 2 * np.pi, (batch, n))
    sup[..., 1], sup[..., 2] = 0.005 * np.cos(ang), 0.005 * np.sin(ang)
    sup_n = np.stack([np.zeros_like(ang), np.cos(ang), np.sin(ang)], -1).astype(np.float32)
    return stage3.PairClouds(0.03 * obj_n + [0, 0, 0.04], obj_n, sup, sup_n)


def test_named_configs_differ_where_the_paper_does():
    assert where.DEFAULT.pipeline == pipeline.ANSWER_PIPELINE and where.DEFAULT.check > 0
    assert where.PAPER.pipeline == pipeline.PipelineConfig()  # K = 5, Stage-2 starts, highest V
    assert where.PAPER.rankers == () and where.PAPER.check == 0
    assert (where.PAPER.stage12, where.PAPER.value) == (where.DEFAULT.stage12, where.DEFAULT.value)
    for folder in (where.DEFAULT.stage12, where.DEFAULT.value, *where.DEFAULT.rankers):
        assert Path(folder).exists(), folder  # the committed weights the configs name
    assert where.DEFAULT.pipeline.frames == 0 and where.FRAMES.pipeline.frames == 32
    assert dataclasses.replace(where.FRAMES.pipeline, frames=0) == where.DEFAULT.pipeline
    with pytest.raises(ValueError, match="check"):
        where.WhereConfig(check=-1)


def test_answer_is_ranked_and_a_pair_does_not_depend_on_its_batch(tiny):
    w = where.load_where(tiny)
    clouds = pairs(2)
    out = w.answer(clouds, [10, 11], seed=0)
    k, views = 3, 2
    assert out.stage1.shape == (2, k, 7) and out.stage2.shape == (2, k, 7)
    assert out.ranked.shape == (2, 2 * k * views, 7)  # both starts, every view
    assert (np.diff(out.keys, axis=1) <= 1e-6).all()  # the rule's order, best first
    assert sorted(set(out.start.ravel())) == ["stage1", "stage2"]
    assert ((out.proposal >= 0) & (out.proposal < k)).all()
    np.testing.assert_allclose(np.linalg.norm(out.ranked[..., 3:], axis=-1), 1.0, atol=1e-5)
    # the same pairs in the other order (same shape: no new compile): each pair's answer is
    # its own, fixed by (seed, pair id), not by its place in the batch
    swapped = w.answer(jax.tree.map(lambda x: x[::-1], clouds), [11, 10], seed=0)
    np.testing.assert_allclose(swapped.ranked[::-1], out.ranked, atol=1e-4)
    other = w.answer(clouds, [10, 11], seed=1)
    assert not np.allclose(other.stage1, out.stage1)  # the seed changes the draws


def test_check_is_the_first_candidate_that_stays_on_the_observed_clouds(tiny, monkeypatch):
    """``check`` asks sim.observed.first_staying with the config's reach; off (0) it is the
    rule's first candidate without any simulation."""
    from sim import observed

    w = where.load_where(tiny)
    out = w.answer(pairs(2), [0, 1])
    seen = {}

    def fake(clouds, poses, floor_z, wall_y, top, nthread=1):
        seen.update(top=top, n=len(poses))
        return 2, np.array([1, 1, 0] + [-2] * (len(poses) - 3), np.int8)

    monkeypatch.setattr(observed, "first_staying", fake)
    pick, status = w.check(out, 0, {}, -1.0, None)
    assert pick == 2 and seen == dict(top=4, n=out.ranked.shape[1]) and status[2] == 0
    off = where.load_where(dataclasses.replace(tiny, check=0))
    assert off.check(out, 0, {}, -1.0, None)[0] == 0


def test_bench_times_configs_side_by_side(tmp_path, monkeypatch):
    """experiments.bench_where: a row per config and batch, timed calls of each config's
    answer (here stand-ins of known cost: the harness, not the networks), the first config's
    ratio 1 and the slower one's about its cost ratio."""
    import time

    from experiments import bench_where

    def fake(cost):
        def answer(clouds, ids, seed):
            assert clouds.object_points.shape == (2, 64, 3) and len(ids) == 2
            time.sleep(cost)

        return where.Where(None, answer, None, None)

    loaded = {"fast": fake(0.01), "slow": fake(0.03)}
    monkeypatch.setattr(where, "load_where", lambda config: loaded[config])
    monkeypatch.setattr(where, "CONFIGS", {"fast": "fast", "slow": "slow"})
    out = tmp_path / "bench.json"
    result = bench_where.main(["--configs", "fast,slow", "--batches", "2", "--repeat", "3",
                               "--points", "64", "--out", str(out)])  # fmt: skip
    rows = result["rows"]
    assert [(r["config"], r["batch"]) for r in rows] == [("fast", 2), ("slow", 2)]
    assert rows[0]["ratio_to_first_config"] == 1.0
    assert 2.0 < rows[1]["ratio_to_first_config"] < 4.0
    assert rows[0]["median_ms"] >= 10 and rows[0]["pairs_per_s"] <= 200
    assert json.loads(out.read_text())["rows"] == rows
    with pytest.raises(ValueError, match="configs"):
        bench_where.main(["--configs", "nope"])


def test_stage1_answer_releases_the_least_penetrating_proposal():
    """A proposal sunk into a flat support and one resting on it: the resting one is the
    answer, lifted by stage1.ANSWER_LIFT."""
    from omnihang_jax.stage1 import ANSWER_LIFT

    rng = np.random.default_rng(0)
    obj = rng.uniform(-0.02, 0.02, (400, 3)).astype(np.float32)
    sup = np.zeros((900, 3), np.float32)
    sup[:, :2] = rng.uniform(-0.1, 0.1, (900, 2))
    nrm = np.tile(np.float32([0, 0, 1]), (900, 1))
    sunk, rest = [0, 0, 0, 1, 0, 0, 0], [0, 0, 0.021, 1, 0, 0, 0]
    pose = where.stage1_answer(obj, sup, nrm, np.array([sunk, rest], np.float32))
    np.testing.assert_allclose(pose, np.array(rest) + [0, 0, ANSWER_LIFT, 0, 0, 0, 0], atol=1e-6)


def test_summary_is_the_mean_over_categories_and_seeds():
    rows = [
        dict(pair_index=i, seed=s, category=c, success={"all_stages": ok})
        for i, (c, ok) in enumerate([("mug", True), ("mug", False), ("cap", True)])
        for s in (0, 1)
    ]
    rows[-1]["success"]["all_stages"] = False  # seed 1: cap fails
    out = where_eval.summarise(rows)["all_stages"]
    assert out["per_seed"] == {"0": 75.0, "1": 25.0} and out["mean"] == 50.0
    assert out["per_category"] == {"cap": 50.0, "mug": 50.0} and out["pairs"] == 3


@pytest.mark.skipif(not (PAPER / "shards").is_dir(), reason="paper dataset labels not present")
def test_evaluate_where_end_to_end_on_two_held_out_pairs(tiny, tmp_path, monkeypatch):
    """Two held-out pairs derived from the committed dataset, the tiny answer, every answer
    simulated on the true meshes; the records resume (a second run simulates nothing new)
    and ``experiments.evaluate`` writes the summary under the config's name."""
    from experiments import evaluate
    from omnihang_jax import dataset_bridge

    derived = tmp_path / "derived"
    dataset_bridge.derive_dataset(PAPER, derived, splits=("test",), limit=2, progress=False,
                                  workers=1)  # fmt: skip
    files = where_eval.pair_files(derived, "test")
    assert len(files) == 2
    records = tmp_path / "where.jsonl"
    rows = where_eval.evaluate_where(tiny, files, records, seed=0, batch=2, progress=False,
                                     dataset_dir=PAPER)  # fmt: skip
    assert len(rows) == 2
    for r in rows:
        assert set(r["status"]) == set(where_eval.ANSWERS)
        assert set(r["status"].values()) <= {"stable", "fallen", "penetrating", "diverged"}
        assert r["check_tried"] <= tiny.check
    calls = []
    monkeypatch.setattr(where_eval, "judge_pair", lambda job: calls.append(job))
    assert len(where_eval.evaluate_where(tiny, files, records, seed=0, progress=False,
                                         dataset_dir=PAPER)) == 2  # fmt: skip
    assert calls == []  # resumed: nothing simulated again
    monkeypatch.setitem(where.CONFIGS, "tiny", tiny)
    monkeypatch.chdir(tmp_path)
    os.makedirs("results")
    entry = evaluate.main(["where", "--config", "tiny", "--data", str(derived), "--seed", "0",
                           "--records", str(records), "--results", "results/hs.json",
                           "--no-progress", "--workers", "0"])  # fmt: skip
    # two pairs, fewer than the record sample: a key of its own, never the config's whole run
    saved = json.loads(Path("results/hs.json").read_text())["tiny_pairs2"]
    assert saved["all_stages"]["pairs"] == 2 and saved["seeds"] == [0]
    assert saved["all_stages"] == entry["all_stages"]
    assert entry["timing"]["pairs_per_s"] == 0  # every row resumed: none evaluated in this run


def test_only_the_default_answer_on_the_record_sample_with_three_seeds_is_promoted():
    """The top-level figures of record come from the default config on the held-out split, on
    every pair or at least ``RECORD_PAIRS`` of them, with three seeds or more."""
    from argparse import Namespace

    from experiments.evaluate import promotes

    full = dict(figure="where", config="default", split="test", pairs=None, seed=[0, 1, 2],
                depth_noise=0.0, dropout=0.0)  # fmt: skip
    n = where_eval.RECORD_PAIRS
    assert promotes(Namespace(**full), {"pairs": 6345})
    assert promotes(Namespace(**{**full, "pairs": n}), {"pairs": n})
    assert not promotes(Namespace(**{**full, "pairs": n}), {"pairs": n - 1})  # too few derived
    assert not promotes(Namespace(**{**full, "pairs": 11}), {"pairs": 11})
    assert not promotes(Namespace(**{**full, "seed": [0]}), {"pairs": n})
    assert not promotes(Namespace(**{**full, "config": "paper"}), {"pairs": n})
    assert not promotes(Namespace(**{**full, "split": "validation"}), {"pairs": n})
    assert not promotes(Namespace(**{**full, "depth_noise": 1.0}), {"pairs": n})
    assert not promotes(Namespace(**{**full, "dropout": 0.2}), {"pairs": n})


def test_degraded_clouds_are_noisy_along_the_rays_and_thinned():
    """``degrade_clouds``: depth noise moves each point along its camera ray by about the
    asked standard deviation (normals re-estimated, unit, facing the camera); dropout keeps
    the point count with a share of the points gone; nothing changes without either."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.05, 0.05, (2000, 2))
    plane = np.c_[xy, np.zeros(len(xy))]  # a flat patch seen from above
    up = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    clouds = dict(object_points=plane, object_normals=up, support_points=plane + [0, 0, 1.0],
                  support_normals=up)  # fmt: skip
    eyes = (np.array([0.0, 0.0, 0.5]), np.array([0.0, 0.0, 1.5]))
    same = where_eval.degrade_clouds(clouds, eyes, 0.0, 0.0, np.random.default_rng(1))
    for k in where_eval.CLOUD_KEYS:
        np.testing.assert_allclose(same[k], clouds[k], atol=1e-7)
    noisy = where_eval.degrade_clouds(clouds, eyes, 0.003, 0.0, np.random.default_rng(1))
    moved = noisy["object_points"] - plane
    ray = plane - eyes[0]
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    along = np.einsum("ij,ij->i", moved, ray)
    assert 0.0027 < along.std() < 0.0033  # 3 mm along the rays
    np.testing.assert_allclose(moved, along[:, None] * ray, atol=1e-6)  # and only along them
    n = noisy["object_normals"]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    assert (np.einsum("ij,ij->i", n, eyes[0] - noisy["object_points"]) > 0).all()  # to the eye
    assert np.median(n[:, 2]) > 0.7  # mostly up, the patch's normal, at 3 mm of noise
    thin = where_eval.degrade_clouds(clouds, eyes, 0.0, 0.2, np.random.default_rng(1))
    assert thin["object_points"].shape == plane.shape
    distinct = len(np.unique(thin["object_points"], axis=0))
    assert distinct == 1600  # 20 % of the points gone, the rest drawn again


@pytest.mark.skipif(not (PAPER / "shards").is_dir(), reason="paper dataset labels not present")
def test_any_frame_evaluation_turns_the_clouds_and_the_answers_back(tiny, tmp_path, monkeypatch):
    """``--frame any``: each pair's clouds reach the answer turned (object: a random rotation
    and shift; free-standing supports: about z), the answers come back as placements of the true
    meshes (every one simulated), the records say which frame, and a records file of the other
    frame is refused. (Batch 2, as the end-to-end test above: the same compiled answer.)"""
    from experiments import evaluate
    from omnihang_jax import dataset_bridge

    derived = tmp_path / "derived"
    dataset_bridge.derive_dataset(PAPER, derived, splits=("test",), limit=2, progress=False,
                                  workers=1)  # fmt: skip
    files = where_eval.pair_files(derived, "test")
    seen = []
    judge = where_eval.judge_pair
    monkeypatch.setattr(where_eval, "judge_pair", lambda job: seen.append(job) or judge(job))
    records = tmp_path / "any.jsonl"
    rows = where_eval.evaluate_where(tiny, files, records, seed=0, batch=2, progress=False,
                                     dataset_dir=PAPER, frame="any")  # fmt: skip
    assert len(rows) == 2 and {r["frame"] for r in rows} == {"any"}
    for row, job, f in zip(rows, seen, files, strict=True):
        assert set(row["status"]) == set(where_eval.ANSWERS)
        sample, meta = dataset_bridge.load_pair_file(f)
        turn = job["turn"]
        assert (turn["support_yaw"] != 0) == where_eval.free_standing(meta["support_family"])
        np.testing.assert_allclose(job["clouds"]["object_points"],
                                   np.asarray(sample.object_points) @ turn["object_rotation"].T
                                   + turn["object_shift"], atol=1e-5)  # fmt: skip
        # the simulated pose of each answer is the turned answer mapped to the library frames
        for name, pose in row["poses"].items():
            if name != "all_stages":
                expect = where_eval.poses_to_library(job["answers"][name][None], turn)[0]
                np.testing.assert_allclose(pose, expect, atol=1e-5)
    with pytest.raises(ValueError, match="frame"):
        where_eval.evaluate_where(tiny, files, records, seed=1, progress=False,
                                  dataset_dir=PAPER, frame="library")  # fmt: skip
    monkeypatch.setitem(where.CONFIGS, "tiny", tiny)
    monkeypatch.chdir(tmp_path)
    entry = evaluate.main(["where", "--config", "tiny", "--frame", "any", "--data", str(derived),
                           "--seed", "0", "--batch", "2", "--records", str(records),
                           "--results", "hs.json", "--no-progress", "--workers", "0"])  # fmt: skip
    assert json.loads(Path("hs.json").read_text())["tiny_any_frame_pairs2"]["frame"] == "any"
    # degraded clouds: the records say how, and another setting is not resumed from them
    clean = seen[0]["clouds"]["object_points"]
    seen.clear()
    noisy = where_eval.evaluate_where(tiny, files, tmp_path / "noisy.jsonl", seed=0, batch=2,
                                      progress=False, dataset_dir=PAPER, frame="any",
                                      depth_noise=0.001, dropout=0.2)  # fmt: skip
    assert {(r["depth_noise_m"], r["dropout"]) for r in noisy} == {(0.001, 0.2)}
    degraded = seen[0]["clouds"]["object_points"]  # the same turn, a worse sensor
    assert degraded.shape == clean.shape and not np.allclose(degraded, clean, atol=1e-4)
    with pytest.raises(ValueError, match="other clouds"):
        where_eval.evaluate_where(tiny, files, tmp_path / "noisy.jsonl", seed=1, progress=False,
                                  dataset_dir=PAPER, frame="any")  # fmt: skip
    assert entry["all_stages"]["pairs"] == 2


def test_the_hang_command_offers_every_named_answer():
    from experiments import hang as hang_cli

    (action,) = [a for a in hang_cli.build_parser()._actions if a.dest == "where"]
    assert sorted(action.choices) == sorted(where.CONFIGS)


@pytest.mark.slow  # a tiny answer with frame hypotheses compiled (~60 s on 2 cores)
def test_the_frames_answer_does_not_depend_on_where_the_objects_origin_is(tiny):
    """``PipelineConfig.frames``: the answer reads the object about its own box centre, so the
    same cloud handed over shifted gives the same placements (every candidate places every
    point in the same spot), and its poses are unit quaternions."""
    cfg = dataclasses.replace(tiny, pipeline=dataclasses.replace(tiny.pipeline, frames=3))
    w = where.load_where(cfg)
    clouds = pairs(2)
    shift = np.float32([0.07, -0.04, 0.09])
    moved = clouds._replace(object_points=clouds.object_points + shift)
    a, b = w.answer(clouds, [3, 4], seed=0), w.answer(moved, [3, 4], seed=0)
    assert a.ranked.shape == (2, 12, 7)  # K starts a stage, as without frames
    np.testing.assert_allclose(np.linalg.norm(a.ranked[..., 3:], axis=-1), 1.0, atol=1e-5)
    # pose b of the shifted cloud == pose a of the cloud: t_b = t_a - R shift. Up to float
    # rounding: the centred clouds differ in the last bits, which can flip a near-tie of the
    # tiny random V (one start, so a candidate or two); without the centring none would match.
    from omnihang_jax import paths

    same = np.all(np.abs(paths.move_origin(b.ranked, shift) - a.ranked) < 2e-4, axis=-1)
    assert same.mean() >= 0.9, same
    assert not np.all(np.abs(b.ranked - a.ranked) < 2e-4, axis=-1).any()  # the poses do move
