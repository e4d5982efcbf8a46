"""The Stage-2 clearance through the Stages 1-3 code: ``stage3.make_hang_pipeline`` (support
normals from its clouds), ``predict.load_hang_pipeline``, ``eval_pipeline.evaluate_pipeline``
behind ``experiments.eval_stage3 --stage2-clearance`` and ``hang`` (``--stage2-clearance``)."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from omnihang_jax import data, dataset_bridge, eval_pipeline, predict, refine, stage3
from omnihang_jax.predict import Predictor, make_predict
from omnihang_jax.stage1 import STAGE1_TINY, make_stage1
from omnihang_jax.stage2 import STAGE2_TINY, clearance_offset, make_stage2
from omnihang_jax.stage3 import CEMConfig, HangOutput, PairClouds

C = 0.006  # m
PIPE = stage3.PipelineConfig(
    num_proposals=2, cem=CEMConfig(population=8, iterations=2, elites=3),
    starts=("stage2", "stage1"),
)  # fmt: skip


def _tiny2(clearance: float):
    return dataclasses.replace(STAGE2_TINY, clearance=clearance)


@pytest.fixture(scope="module")
def params():
    return {
        "stage1": make_stage1(STAGE1_TINY).init(jax.random.key(0)),
        "stage2": make_stage2(STAGE2_TINY).init(jax.random.key(1)),
        "value": stage3.make_value(stage3.VALUE_TINY).init(jax.random.key(2)),
    }


def _plane_pairs(batch=2, n=128, m=128):
    """A 2-cm sphere over a flat support patch z = 0 (outward normals +z), per pair."""
    rng = np.random.default_rng(0)
    obj = rng.normal(size=(batch, n, 3)).astype(np.float32)
    obj /= np.linalg.norm(obj, axis=-1, keepdims=True)
    sup = np.zeros((batch, m, 3), np.float32)
    sup[..., :2] = rng.uniform(-0.05, 0.05, (batch, m, 2))
    sup_n = np.broadcast_to(np.float32([0, 0, 1]), (batch, m, 3)).copy()
    return PairClouds(0.02 * obj, obj, sup, sup_n)


def _old_pipeline(stage1_config, stage2_config, value_config, config):
    """make_hang_pipeline as it was before the support normals reached Stage 2."""
    pred_fn = make_predict(stage1_config, stage2_config)
    refine_fn = stage3.make_refiner(value_config, config.cem)

    def hang(params, key, clouds):
        k1, k3 = jax.random.split(key)
        pred = pred_fn(params["stage1"], params["stage2"], clouds.object_points,
                       clouds.support_points, k1, config.num_proposals)  # fmt: skip
        small = stage3.subsample_clouds(clouds, value_config)
        starts = {"stage1": pred.stage1_poses, "stage2": pred.stage2_poses}
        refined, scores, initial, best = {}, {}, {}, {}
        for i, name in enumerate(config.starts):
            res = refine_fn(params["value"], jax.random.fold_in(k3, i), small, starts[name])
            refined[name], scores[name] = res.poses, res.scores
            initial[name], best[name] = res.initial_scores, res.best
        first = config.starts[0]
        pose = jnp.take_along_axis(refined[first], best[first][:, None, None], axis=1)[:, 0]
        return HangOutput(pred.stage1_poses, pred.stage2_poses, refined, scores, initial, best,
                          pose)  # fmt: skip

    return hang


def _expected_offset(params, clouds, key, clearance):
    """The predictor's own clearance offset [B, K, 3] for the pipeline's Stage-1 key."""
    k1, _ = jax.random.split(key)
    pred = jax.jit(make_predict(STAGE1_TINY, _tiny2(clearance)), static_argnames="num_proposals")(
        params["stage1"], params["stage2"], clouds.object_points, clouds.support_points, k1,
        num_proposals=PIPE.num_proposals, support_normals=clouds.support_normals,
    )  # fmt: skip
    idx = np.asarray(pred.support_indices)  # [B, K, K3]
    normals = np.take_along_axis(
        np.asarray(clouds.support_normals)[:, None], idx[..., None], axis=2
    )  # [B, K, K3, 3]
    b, k, k3 = idx.shape
    off = clearance_offset(
        jnp.asarray(normals.reshape(b * k, k3, 3)),
        jnp.asarray(pred.weight).reshape(b * k, k3),
        clearance,
    )
    return np.asarray(off).reshape(b, k, 3), pred


@pytest.mark.slow  # three more pipeline compilations (~40 s on 2 cores); a refactor guard
def test_pipeline_clearance_zero_is_the_output_before_the_normals(params):
    clouds = _plane_pairs()
    key = jax.random.key(5)
    old = jax.jit(_old_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, PIPE))
    new = jax.jit(stage3.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, PIPE))
    a, b = old(params, key, clouds), new(params, key, clouds)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))  # bit-identical


def test_pipeline_clearance_c_moves_stage2_exactly(params):
    clouds = _plane_pairs()
    key = jax.random.key(5)
    new = jax.jit(stage3.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, PIPE))
    b = new(params, key, clouds)
    moved = jax.jit(stage3.make_hang_pipeline(STAGE1_TINY, _tiny2(C), stage3.VALUE_TINY, PIPE))
    m = moved(params, key, clouds)
    np.testing.assert_array_equal(np.asarray(m.stage1_poses), np.asarray(b.stage1_poses))
    np.testing.assert_array_equal(  # Stage 2 keeps the Stage-1 rotation
        np.asarray(m.stage2_poses)[..., 3:], np.asarray(b.stage2_poses)[..., 3:]
    )
    shift = np.asarray(m.stage2_poses)[..., :3] - np.asarray(b.stage2_poses)[..., :3]
    off, pred = _expected_offset(params, clouds, key, C)
    np.testing.assert_allclose(shift, off, atol=1e-7)  # exactly the predictor's offset
    np.testing.assert_allclose(shift, np.broadcast_to([0, 0, C], shift.shape), atol=1e-7)
    np.testing.assert_allclose(np.asarray(m.stage2_poses), pred.stage2_poses, atol=1e-7)
    assert np.isfinite(np.asarray(m.pose)).all()


def _fake_load_predictor(calls):
    def load(folder, seed=0, stage2_overrides=None):
        calls.append(stage2_overrides)
        p1 = make_stage1(STAGE1_TINY).init(jax.random.key(0))
        p2 = make_stage2(STAGE2_TINY).init(jax.random.key(1))
        config2 = dataclasses.replace(STAGE2_TINY, **(stage2_overrides or {}))
        return Predictor(STAGE1_TINY, p1, config2, p2, seed=seed)

    return load


def _fake_load_value(folder):
    return stage3.VALUE_TINY, stage3.make_value(stage3.VALUE_TINY).init(jax.random.key(2))


def test_load_hang_pipeline_takes_stage2_overrides(monkeypatch):
    """The overrides reach load_predictor and the pipeline is built on its Stage-2 config
    (that config's clearance moves Stage 2: test_pipeline_clearance_c_moves_stage2_exactly);
    the default pipeline is the answer pipeline, ranked by CEM's V and stage3.RANK_VALUES."""
    calls, built = [], []
    monkeypatch.setattr(predict, "load_predictor", _fake_load_predictor(calls))
    monkeypatch.setattr(refine, "load_value", _fake_load_value)
    make = stage3.make_hang_pipeline

    def spy(stage1_config, stage2_config, value_config, config, rank_configs=None):
        built.append((stage2_config.clearance, config))
        return make(stage1_config, stage2_config, value_config, config, rank_configs)

    monkeypatch.setattr(stage3, "make_hang_pipeline", spy)
    for clearance in (None, C):
        overrides = None if clearance is None else {"clearance": clearance}
        hang, params = predict.load_hang_pipeline("W", "V", PIPE, stage2_overrides=overrides)
        assert callable(hang) and set(params) == {"stage1", "stage2", "value"}
    hang, params = predict.load_hang_pipeline("W", "V")
    assert calls == [None, {"clearance": C}, None]
    ranked = dataclasses.replace(stage3.ANSWER_PIPELINE, rank_values=len(stage3.RANK_VALUES))
    assert built == [(0.0, PIPE), (C, PIPE), (0.0, ranked)]
    assert len(params.get("rank_values", [])) == len(stage3.RANK_VALUES)


class _FakeLabeller:
    """Every candidate 'stable' without simulating."""

    def __init__(self, dataset_dir, workers=0):
        pass

    def __call__(self, jobs, progress=False):
        return [(np.zeros(len(p), np.int8), np.zeros(len(p))) for _, _, p in jobs]

    def close(self):
        pass


def _fake_pair(path):
    """A synthetic ring-on-peg pair in place of a derived file (metadata from its name)."""
    i = int(str(path).rsplit("/", 1)[-1][:5])
    sample = data.synthetic_sample(jax.random.key(i), n_object=128, n_support=128)
    sample = data.HangSample(*(np.asarray(x) for x in sample))
    meta = {"pair_index": i, "object_name": f"mug_{i:04d}", "support_name": "hook_0000",
            "object_category": "mug", "support_family": "hook", "split": "test"}  # fmt: skip
    return sample, meta


@pytest.mark.slow  # 25-45 s on 2 cores (thirty-second session: the default suite neared 20 min)
def test_eval_stage3_stage2_clearance_reaches_the_predictor(monkeypatch, tmp_path):
    """--stage2-clearance M: load_predictor gets {"clearance": M}, the predictor the pairs'
    support normals; Stage-1 poses stay, Stage-2 poses move by M; the summary records M."""
    from experiments import eval_stage3

    calls, normals = [], []
    monkeypatch.setattr(predict, "load_predictor", _fake_load_predictor(calls))
    monkeypatch.setattr(refine, "load_value", _fake_load_value)
    monkeypatch.setattr(refine, "Labeller", _FakeLabeller)
    monkeypatch.setattr(dataset_bridge, "load_pair_file", _fake_pair)
    call = Predictor.__call__

    def spy(self, *args, **kwargs):
        normals.append(kwargs.get("support_normals"))
        return call(self, *args, **kwargs)

    monkeypatch.setattr(Predictor, "__call__", spy)
    (tmp_path / "recipe.json").write_text("{}")
    (tmp_path / "derived" / "test").mkdir(parents=True)
    for i in (1, 2):
        (tmp_path / "derived" / "test" / f"{i:05d}_mug_{i:04d}__hook_0000.npz").write_bytes(b"")
    poses, summaries = {}, {}
    for clearance in (None, C):
        out = tmp_path / f"c{clearance}.json"
        argv = ["--data", str(tmp_path), "--out", str(out), "--proposals", "2", "--batch", "2",
                "--no-progress"] + ([] if clearance is None else ["--stage2-clearance", str(C)])  # fmt: skip
        eval_stage3.main(argv)
        summaries[clearance] = json.loads(out.read_text())
        recs = [json.loads(x) for x in out.with_suffix(".pairs.jsonl").read_text().splitlines()]
        poses[clearance] = {
            s: np.array([r[s]["pose"] for r in recs]) for s in ("stage1", "stage1_2")
        }
    assert calls == [None, {"clearance": C}]
    assert len(normals) == 2 and all(n is not None and n.shape == (2, 128, 3) for n in normals)
    assert summaries[None]["stage2_clearance_m"] is None
    assert summaries[C]["stage2_clearance_m"] == C
    np.testing.assert_array_equal(poses[C]["stage1"], poses[None]["stage1"])
    shift = np.linalg.norm(poses[C]["stage1_2"][:, :3] - poses[None]["stage1_2"][:, :3], axis=-1)
    np.testing.assert_allclose(shift, C, atol=1e-6)  # unit mean normal x M


def test_evaluate_pipeline_clearance_none_keeps_the_model_stage2(monkeypatch):
    calls = []
    monkeypatch.setattr(predict, "load_predictor", _fake_load_predictor(calls))
    monkeypatch.setattr(refine, "load_value", _fake_load_value)
    monkeypatch.setattr(refine, "Labeller", _FakeLabeller)
    monkeypatch.setattr(dataset_bridge, "load_pair_file", _fake_pair)
    records, _ = eval_pipeline.evaluate_pipeline(
        ["00003_x.npz"], "W", "V", "D", num_proposals=2, batch=1, progress=False,
        stage2_clearance=0.0,
    )  # fmt: skip
    assert calls == [{"clearance": 0.0}] and len(records) == 1


def _cloud_bodies(n: int, scale: float):
    """An object and a support for the hang command's where step: N random points of std
    SCALE each, normals pointing out from the origin, no meshes (seed 0)."""
    from omnihang_jax import hang as H

    rng = np.random.default_rng(0)

    def body(kind):
        pts = rng.normal(size=(n, 3)).astype(np.float32) * scale
        nrm = pts / np.linalg.norm(pts, axis=1, keepdims=True)
        return H.Body(kind, kind, "cloud", None, pts, nrm, None, None, {})

    return body("object"), body("support")


def test_hang_stage2_clearance_option(monkeypatch):
    from experiments import hang as hang_cli
    from omnihang_jax import hang as H

    assert H.HangConfig().stage2_overrides() is None
    assert H.HangConfig(stage2_clearance=0.008).stage2_overrides() == {"clearance": 0.008}
    seen = {}

    class Stop(Exception):
        pass

    def fake_hang(obj, sup, out, config, log=None):
        seen["config"] = config
        raise Stop

    monkeypatch.setattr(H, "hang", fake_hang)
    for argv, want in (([], None), (["--stage2-clearance", "0.008"], 0.008)):
        with pytest.raises(Stop):
            hang_cli.main(argv + ["--quiet"])
        assert seen["config"].stage2_clearance == want

    # stages_where hands the support cloud's normals to the predictor
    got = {}

    def predictor(obj, sup, key=None, num_proposals=None, support_normals=None):
        got["normals"] = support_normals
        k = num_proposals
        pose = np.tile(np.float32([0, 0, 0.05, 1, 0, 0, 0]), (1, k, 1))
        return predict.Prediction(pose, pose, None, None, None, None)

    obj, sup = _cloud_bodies(64, 0.02)
    cands = H.stages_where(predictor, 2, None)(obj, sup, 0)
    assert len(cands.poses) == 4
    np.testing.assert_array_equal(got["normals"], sup.normals[None])


@pytest.mark.slow  # 75-90 s on 2 cores (fortieth session: the default suite neared 20 min)
def test_evaluate_pipeline_stage1_rounds_change_only_the_stage1_starts(monkeypatch):
    """``cem_stage1`` (eval_stage3 --stage1-rounds): a second CEM round for the Stage-1
    starts moves their refined candidates; the Stage-2 starts' stay exactly as with one."""
    from omnihang_jax import stage3

    monkeypatch.setattr(predict, "load_predictor", _fake_load_predictor([]))
    monkeypatch.setattr(refine, "load_value", _fake_load_value)
    monkeypatch.setattr(refine, "Labeller", _FakeLabeller)
    monkeypatch.setattr(dataset_bridge, "load_pair_file", _fake_pair)
    k = 2
    runs = {}
    for rounds in (None, 2):
        records, _ = eval_pipeline.evaluate_pipeline(
            ["00003_x.npz"], "W", "V", "D", num_proposals=k, batch=1, progress=False,
            cem_stage1=None if rounds is None else stage3.CEMConfig(rounds=rounds),
        )  # fmt: skip
        runs[rounds] = np.asarray(records[0]["poses_all"])
    one, two = runs[None], runs[2]
    np.testing.assert_array_equal(one[: 2 * k], two[: 2 * k])  # the proposals themselves
    np.testing.assert_array_equal(one[3 * k : 4 * k], two[3 * k : 4 * k])  # Stage-2 starts
    assert not np.allclose(one[2 * k : 3 * k], two[2 * k : 3 * k])  # Stage-1 starts moved


def test_hang_views_reach_stage3_and_the_cli(monkeypatch):
    """``HangConfig.views`` / ``--views`` (thirty-second session): every view refines the same
    best-V starts on its own subsample (``view`` handed to refine and rank), so three views give
    three times the refined candidates; a bad --views is refused before anything runs."""
    from experiments import hang as hang_cli
    from omnihang_jax import hang as H

    seen = {}

    class Stop(Exception):
        pass

    def fake_hang(obj, sup, support_name, config, log=None, **kw):
        seen["config"] = config
        raise Stop

    monkeypatch.setattr(H, "hang", fake_hang)
    for argv, want in (([], H.VIEWS), (["--views", "0/1,1/2,3/4"], ((0, 1), (1, 2), (3, 4)))):
        with pytest.raises(Stop):
            hang_cli.main(argv + ["--quiet"])
        assert seen["config"].views == want
    with pytest.raises(SystemExit):
        hang_cli.main(["--views", "0/1,0/2", "--quiet"])  # the same subsample twice

    def predictor(obj, sup, key=None, num_proposals=None, support_normals=None):
        pose = np.tile(np.float32([0, 0, 0.05, 1, 0, 0, 0]), (1, num_proposals, 1))
        return predict.Prediction(pose, pose, None, None, None, None)

    views_seen = []

    def refine_fn(obj, sup, starts, seed, view=(0, 1)):
        views_seen.append(tuple(view))
        return np.asarray(starts, np.float64), np.zeros(len(starts))

    def rank(obj, sup, poses, view=(0, 1)):
        return np.zeros(len(poses))

    s3 = H.Stage3("fake", lambda obj, sup, poses: np.zeros(len(poses)), refine_fn, rank, ("r",))
    obj, sup = _cloud_bodies(64, 0.02)
    k = 3
    views = ((0, 1), (1, 2), (3, 4))
    cands = H.stages_where(predictor, k, s3, views)(obj, sup, 0)
    assert views_seen == list(views)
    n = 2 * min(H.CEM_STARTS, k)
    assert len(cands.poses) == 2 * k + n * len(views)
    assert (np.isin(cands.stage, ["stage1_3", "stage3"])).sum() == n * len(views)
