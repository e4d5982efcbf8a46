"""More value networks ranking CEM's candidates (``PipelineConfig.rank_values``, the
twelfth session's ensemble): in the pipeline, in the evaluation's records and in
experiments.ensemble_stage3 on such records."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest

from omnihang_jax import dataset_bridge, eval_pipeline, predict, refine, selection, stage3
from omnihang_jax.stage1 import STAGE1_TINY
from omnihang_jax.stage2 import STAGE2_TINY
from tests.test_stage2_clearance_pipeline import (
    PIPE,
    _cloud_bodies,
    _fake_load_predictor,
    _fake_pair,
    _FakeLabeller,
    _plane_pairs,
    params,  # noqa: F401  (module fixture)
)

CLEAR = selection.SelectConfig("value_clear", depth=0.001, radius=0.003, max_points=0)
V2 = stage3.make_value(stage3.VALUE_TINY).init(jax.random.key(7))  # a second, different V


@pytest.mark.slow  # 25-45 s on 2 cores (thirty-second session: the default suite neared 20 min)
def test_pipeline_ranks_by_the_mean_log_v(params):  # noqa: F811
    """Same key: CEM is unchanged by a ranking V; the final scores are the mean of the CEM's
    log V and the second V's on the refined poses; the picks follow the rule on them; a copy of
    the CEM's own V as the second member changes nothing."""
    clouds = _plane_pairs()
    base = dataclasses.replace(PIPE, select=CLEAR, pool_starts=True)
    one = jax.jit(stage3.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, base))
    ens_cfg = dataclasses.replace(base, rank_values=1)
    ens = jax.jit(stage3.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, ens_cfg))
    key = jax.random.key(3)
    out1 = one(params, key, clouds)
    out2 = ens({**params, "rank_values": [V2]}, key, clouds)
    small = stage3.subsample_clouds(jax.tree.map(np.asarray, clouds), stage3.VALUE_TINY)
    value = stage3.make_value(stage3.VALUE_TINY)
    for name in base.starts:
        np.testing.assert_array_equal(
            np.asarray(out1.refined[name]), np.asarray(out2.refined[name])
        )
        poses = np.asarray(out2.refined[name])
        v2 = np.stack([
            np.asarray(value.score(V2, jax.tree.map(lambda x, i=i: x[i], small), poses[i]))
            for i in range(len(poses))
        ])  # fmt: skip
        want = (np.asarray(out1.scores[name]) + v2) / 2
        np.testing.assert_allclose(np.asarray(out2.scores[name]), want, rtol=1e-5, atol=1e-5)
    same = ens({**params, "rank_values": [params["value"]]}, key, clouds)
    np.testing.assert_array_equal(np.asarray(same.pose), np.asarray(out1.pose))
    with pytest.raises(ValueError, match="rank_values"):
        ens({**params, "rank_values": []}, key, clouds)


def _fake_values(folder):
    """V1 for the run's folder, V2 for any other: two different networks of one config."""
    p = stage3.make_value(stage3.VALUE_TINY).init(jax.random.key(2)) if folder == "V" else V2
    return stage3.VALUE_TINY, p


@pytest.mark.slow  # 75-90 s on 2 cores (fortieth session: the default suite neared 20 min)
def test_evaluation_ranks_by_the_ensemble_and_records_each_v(monkeypatch, tmp_path):
    """evaluate_pipeline(rank_value_dirs=): each record holds the second V of every
    candidate (v_rank); the answers are the rule over the mean log V; the paper's answer
    stays the CEM's highest V. experiments.ensemble_stage3 on the records recomputes both Vs
    and scores the recorded answer as its "mean log V" row."""
    monkeypatch.setattr(predict, "load_predictor", _fake_load_predictor([]))
    monkeypatch.setattr(refine, "load_value", _fake_values)
    monkeypatch.setattr(refine, "Labeller", _FakeLabeller)
    monkeypatch.setattr(dataset_bridge, "load_pair_file", _fake_pair)
    k, files = 2, ["00003_x.npz", "00004_x.npz"]
    records, _ = eval_pipeline.evaluate_pipeline(
        files, "W", "V", "D", num_proposals=k, batch=2, progress=False, select=CLEAR,
        cem=stage3.CEMConfig(population=8, iterations=2, elites=3), pool_starts=True,
        rank_value_dirs=["V2"],
    )  # fmt: skip
    for rc in records:
        v = np.log(np.asarray(rc["v"], np.float64))
        (v2,) = np.log(np.asarray(rc["v_rank"], np.float64))
        assert len(v2) == 4 * k + 1 and not np.allclose(v, v2)
        ens = (v + v2) / 2
        counts = np.asarray(rc["inside_counts"][selection.grid_key(CLEAR.depth, CLEAR.radius)])
        key = np.asarray(selection.select_key(ens[2 * k : 4 * k], counts[2 * k : 4 * k], CLEAR))
        assert rc["answer_index"] == 2 * k + int(np.argmax(key))
        assert rc["best_all_stages_value"] == int(np.argmax(v[3 * k : 4 * k]))

    from experiments import ensemble_stage3

    monkeypatch.setattr(ensemble_stage3.refine, "load_value", _fake_values)
    runs = tmp_path / "run.pairs.jsonl"
    runs.write_text("".join(json.dumps(r, default=float) + "\n" for r in records))
    folder = tmp_path / "derived" / "test"
    folder.mkdir(parents=True)
    for r in records:
        (folder / r["file"]).write_bytes(b"")  # _fake_pair reads the name only
    for d in ("V", "V2"):
        (tmp_path / d).mkdir()
        (tmp_path / d / "params.msgpack").write_bytes(b"")
    monkeypatch.chdir(tmp_path)
    out = ensemble_stage3.main([
        "--select-on", str(runs), "--select-split", "test", "--data", str(tmp_path),
        "--value", "V", "--extra-value", "V2", "--batch", "2", "--out", "ens.json",
        "--no-progress",
    ])  # fmt: skip
    assert out["v_check_select_on"]["max_abs_diff"] < 1e-4
    rows = {r["score"]: r for r in out["table"]}
    assert set(rows) == {"V", "V2", "mean V", "mean log V"}
    recorded = np.mean([rc["all_stages"]["success"] for rc in records]) * 100
    assert rows["mean log V"]["pair_mean"] == pytest.approx(recorded)
    # the pipeline's choices, from the recorded v / v_rank (no pair file read): the set {V2}
    # reproduces the recorded answer; the choice is one of the sets the pipeline can rank with
    monkeypatch.setattr(ensemble_stage3, "pool_values", None)  # must not be called
    rec = ensemble_stage3.main([
        "--select-on", str(runs), "--value", "V", "--extra-value", "V2", "--from-records",
        "--out", "rec.json", "--no-progress",
    ])  # fmt: skip
    prow = {tuple(r["rank_values"]): r for r in rec["pipeline_table"]}
    assert set(prow) == {(), ("V2",)} and rec["v_source"] == "records"
    assert prow[("V2",)]["pair_mean"] == pytest.approx(recorded)
    assert rec["chosen_rank_values"] == list(max(
        rec["pipeline_table"], key=lambda r: r["mean"])["rank_values"])  # fmt: skip
    with pytest.raises(ValueError, match="ranking networks"):
        ensemble_stage3.main(
            [
                "--select-on",
                str(runs),
                "--value",
                "V",
                "--extra-value",
                "V2",
                "--extra-value",
                "V3",
                "--from-records",
                "--out",
                "x.json",
                "--no-progress",
            ]
        )
    assert ensemble_stage3.pipeline_sets(2) == [(), (1,), (2,), (1, 2)]


def test_load_rank_values_keeps_each_config(monkeypatch):
    """Each ranking network keeps its own config (its own subsample of the clouds); none:
    empty."""
    near = dataclasses.replace(stage3.VALUE_TINY, support_near=16, near_pool=128)
    monkeypatch.setattr(
        refine, "load_value", lambda f: (near if f == "X" else stage3.VALUE_TINY, V2)
    )
    configs, nets = predict.load_rank_values(["X", "Y"])
    assert configs == (near, stage3.VALUE_TINY) and len(nets) == 2 and nets[0] is V2
    assert predict.load_rank_values([]) == ((), [])


def test_hang_command_ranks_by_the_mean_log_v(tmp_path):
    """The hang command's Stage 3 (omnihang_jax.hang.load_stage3) with a ranking network:
    rank = the mean of the two networks' log V (stage3.RANK_WITH_CEM_VALUE) or the ranking
    network's alone; without one, rank = V's own score; the
    default finds stage3.RANK_VALUES only beside the committed V they were chosen with."""
    from omnihang_jax import hang as H

    for name, key in (("v1", 2), ("v2", 7)):
        net = stage3.make_value(stage3.VALUE_TINY)
        refine.save_value(tmp_path / name, stage3.VALUE_TINY, net.init(jax.random.key(key)))
    obj, sup = _cloud_bodies(256, 0.03)
    # the command refines as many proposals of each stage as the evaluated pipeline (a constant
    # there: omnihang_jax.hang imports no jax at module level)
    assert stage3.ANSWER_PIPELINE.num_proposals == H.CEM_STARTS
    assert stage3.ANSWER_PIPELINE.views == H.VIEWS  # and on the same subsamples of the clouds
    # and searches on the pipeline's CEM V first (the one the ranking networks were chosen with)
    assert H.VALUE_WEIGHTS[0] == stage3.CEM_VALUE
    poses = np.tile(np.asarray([[0, 0, 0.05, 1, 0, 0, 0]], np.float32), (3, 1))
    poses[:, 0] = [0.0, 0.01, 0.02]
    one = H.load_stage3(tmp_path / "v1")
    assert one.rank_folders == ()  # not the committed V: no ranking networks by default
    np.testing.assert_allclose(one.rank(obj, sup, poses), one.score(obj, sup, poses), rtol=1e-6)
    two = H.load_stage3(tmp_path / "v1", [tmp_path / "v2"])
    other = H.load_stage3(tmp_path / "v2", [])
    want = (one.score(obj, sup, poses) + other.score(obj, sup, poses)) / 2
    with pytest.MonkeyPatch.context() as mp:  # the twelfth session's mean log V
        mp.setattr(stage3, "RANK_WITH_CEM_VALUE", True)
        np.testing.assert_allclose(two.rank(obj, sup, poses), want, rtol=1e-5, atol=1e-6)
    with pytest.MonkeyPatch.context() as mp:  # the twentieth session's: the ranker alone
        mp.setattr(stage3, "RANK_WITH_CEM_VALUE", False)
        np.testing.assert_allclose(two.rank(obj, sup, poses), other.score(obj, sup, poses),
                                   rtol=1e-5, atol=1e-6)  # fmt: skip


def test_answer_failures_sorts_each_failed_answer_by_cause():
    """eval_pipeline.answer_failures: the 2K refined candidates (K = 1: indices 2, 3) of each
    failed answer: another clear one hangs (ranking), none hangs, only an inside one hangs,
    none clear; successes are not counted."""
    key = selection.grid_key(selection.CHOSEN.depth, selection.CHOSEN.radius)

    def rec(success, ok, counts):
        return {"all_stages": {"success": success}, "stable_all": [False, False, *ok, False],
                "inside_counts": {key: [0, 0, *counts]}}  # fmt: skip

    rows = [
        rec(True, [True, False], [0, 0]),  # a success
        rec(False, [False, True], [0, 0]),  # ranking: the other clear one hangs
        rec(False, [False, False], [0, 3]),  # no refined candidate hangs
        rec(False, [False, True], [0, 4]),  # only the inside one hangs
        rec(False, [True, False], [2, 5]),  # no clear candidate
    ]
    out = eval_pipeline.answer_failures(rows, 1)
    assert {k: out[k] for k in ("failed", "ranking", "no_hanging", "only_inside_hang",
                                "no_clear")} == {"failed": 4, "ranking": 1, "no_hanging": 1,
                                                 "only_inside_hang": 1, "no_clear": 1}  # fmt: skip


def test_committed_cem_value_loads_beside_the_ranking_networks():
    """stage3.CEM_VALUE and every stage3.RANK_VALUES folder are committed and load; each
    ranking network shares the CEM's V's encoder and head (fine-tuned from it), differing at
    most in how the state picks its points (near points: its own subsample of the clouds)."""
    config, _ = refine.load_value(stage3.CEM_VALUE)
    configs, _ = predict.load_rank_values(stage3.RANK_VALUES)
    for folder, c in zip(stage3.RANK_VALUES, configs, strict=True):
        plain = dataclasses.replace(c, support_near=0, object_near=0)
        assert plain == config, folder
    assert stage3.CEM_VALUE not in stage3.RANK_VALUES


def test_pessimistic_combinations_over_the_ranking_networks():
    """With the run's V and two or more ranking networks, the combinations include the
    networks' own mean log V, their smallest and the mean minus lambda sd: a candidate the
    networks disagree on ranks below one they agree on at the same mean."""
    from experiments import ensemble_stage3

    run_v = np.full((1, 2), 0.5)
    agree = np.array([[0.4, 0.4, 0.4]]).T  # candidate 0: every network says 0.4
    spread = np.array([[0.1, 0.4, 0.9]]).T  # candidate 1: they disagree
    nets = np.concatenate([agree, spread], axis=1)[:, None, :]  # [3, 1, 2]
    values = np.concatenate([run_v[None], nets])  # [4, 1, 2]
    combos = ensemble_stage3.combinations(values, ["run", "a", "b", "c"])
    assert {"rankers: mean log V", "rankers: min log V", "rankers: median log V"} <= set(combos)
    for lam in ensemble_stage3.PESSIMISM:
        assert f"rankers: mean - {lam} sd log V" in combos
    logs = np.log(nets[:, 0])
    np.testing.assert_allclose(combos["rankers: mean log V"][0], np.exp(logs.mean(0)))
    np.testing.assert_allclose(combos["rankers: min log V"][0], [0.4, 0.1])
    sd = combos["rankers: mean - 1.0 sd log V"][0]
    assert sd[0] == pytest.approx(0.4) and sd[1] < np.exp(logs[:, 1].mean())
    assert "rankers: min log V" not in ensemble_stage3.combinations(values[:2], ["r", "a"])
