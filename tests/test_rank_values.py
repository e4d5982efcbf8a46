"""Value networks ranking CEM's candidates (``PipelineConfig.rank_values``): the pipeline's
final scores are the mean log V over CEM's V and the ranking networks, or over the networks
alone (``rank_with_value=False``, the default answer's), each network on its own subsample of
the clouds (near points, views); CEM itself is unchanged. And the committed rankers
(``where.DEFAULT.rankers``) load beside the CEM's V they were fine-tuned from."""

from __future__ import annotations

import dataclasses
import functools

import jax
import numpy as np
import pytest

from omnihang_jax import pipeline, predict, refine, selection, stage3, where
from omnihang_jax.stage1 import STAGE1_TINY
from omnihang_jax.stage2 import STAGE2_TINY
from tests.test_selection_pipeline import CLEAR, PIPE, params, plane_pairs  # noqa: F401

CFG = stage3.VALUE_TINY


@functools.cache
def _jitted(config: stage3.ValueConfig):
    """(init, score) of a value network of ``config``, jitted once (eager dispatch is slow)."""
    net = stage3.make_value(config)
    return jax.jit(net.init), jax.jit(net.score)


def _init(config, seed: int):
    return _jitted(config)[0](jax.random.key(seed))


V2 = _init(CFG, 7)  # a second, different V


def _scores(net_params, config, clouds, poses):
    """[B, P] log V of ``poses`` [B, P, 7] by one network on its own subsample of ``clouds``."""
    small = stage3.subsample_clouds(jax.tree.map(np.asarray, clouds), config)
    score = _jitted(config)[1]
    return np.stack([np.asarray(score(net_params, jax.tree.map(lambda x, i=i: x[i], small),
                                      poses[i])) for i in range(len(poses))])  # fmt: skip


@pytest.mark.slow  # 25-45 s on 2 cores
def test_pipeline_ranks_by_the_mean_log_v(params):  # noqa: F811
    """Same key: CEM is unchanged by a ranking V; the final scores are the mean of the CEM's
    log V and the second V's on the refined poses; a copy of the CEM's own V as the second
    member changes nothing; a wrong number of networks is refused."""
    clouds = plane_pairs()
    base = dataclasses.replace(PIPE, select=CLEAR, pool_starts=True)
    one = jax.jit(pipeline.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, CFG, base))
    ens_cfg = dataclasses.replace(base, rank_values=1)
    ens = jax.jit(pipeline.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, CFG, ens_cfg))
    key = jax.random.key(3)
    out1 = one(params, key, clouds)
    out2 = ens({**params, "rank_values": [V2]}, key, clouds)
    for name in base.starts:
        np.testing.assert_array_equal(
            np.asarray(out1.refined[name]), np.asarray(out2.refined[name])
        )
        v2 = _scores(V2, CFG, clouds, np.asarray(out2.refined[name]))
        want = (np.asarray(out1.scores[name]) + v2) / 2
        np.testing.assert_allclose(np.asarray(out2.scores[name]), want, rtol=1e-5, atol=1e-5)
    same = ens({**params, "rank_values": [params["value"]]}, key, clouds)
    np.testing.assert_array_equal(np.asarray(same.pose), np.asarray(out1.pose))
    with pytest.raises(ValueError, match="rank_values"):
        ens({**params, "rank_values": []}, key, clouds)


@pytest.mark.slow  # 25-45 s on 2 cores
def test_pipeline_ranks_by_the_ranker_alone(params):  # noqa: F811
    """rank_with_value=False (the default answer's): the final scores are the ranking
    network's log V alone; CEM is unchanged."""
    clouds = plane_pairs()
    base = dataclasses.replace(PIPE, select=selection.CHOSEN, pool_starts=True, rank_values=1)
    mean = jax.jit(pipeline.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, CFG, base))
    alone_cfg = dataclasses.replace(base, rank_with_value=False)
    alone = jax.jit(pipeline.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, CFG, alone_cfg))
    key = jax.random.key(3)
    out_m = mean({**params, "rank_values": [V2]}, key, clouds)
    out_a = alone({**params, "rank_values": [V2]}, key, clouds)
    for name in base.starts:
        np.testing.assert_array_equal(np.asarray(out_m.refined[name]),
                                      np.asarray(out_a.refined[name]))  # fmt: skip
        want = _scores(V2, CFG, clouds, np.asarray(out_a.refined[name]))
        np.testing.assert_allclose(np.asarray(out_a.scores[name]), want, rtol=1e-5, atol=1e-5)
    assert pipeline.ANSWER_PIPELINE.rank_with_value is False


@pytest.mark.slow  # 25-45 s on 2 cores
def test_pipeline_ranks_with_a_near_point_ranker(params):  # noqa: F811
    """Ranking networks of different configs (``make_hang_pipeline(..., rank_configs)``): a
    plain one and one with near points, each on its own subsample of the clouds; the final
    scores are the mean of their log V; CEM is unchanged."""
    clouds = plane_pairs()
    near = dataclasses.replace(CFG, support_near=16, object_near=8, near_pool=128)
    v3 = _init(CFG, 8)
    cfg = dataclasses.replace(PIPE, select=selection.CHOSEN, pool_starts=True, rank_values=2,
                              rank_with_value=False)  # fmt: skip
    plain = jax.jit(pipeline.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, CFG, cfg))
    ranked = jax.jit(pipeline.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, CFG, cfg, (CFG, near)))
    key = jax.random.key(3)
    out_p = plain({**params, "rank_values": [V2, v3]}, key, clouds)
    out_n = ranked({**params, "rank_values": [V2, v3]}, key, clouds)
    for name in cfg.starts:
        np.testing.assert_array_equal(np.asarray(out_p.refined[name]),
                                      np.asarray(out_n.refined[name]))  # fmt: skip
        poses = np.asarray(out_n.refined[name])
        want = 0.5 * _scores(V2, CFG, clouds, poses) + 0.5 * _scores(v3, near, clouds, poses)
        np.testing.assert_allclose(np.asarray(out_n.scores[name]), want, rtol=1e-5, atol=1e-5)
        assert not np.allclose(np.asarray(out_n.scores[name]), np.asarray(out_p.scores[name]))


def _poses_near(clouds, per_pair=6):
    b = clouds.object_points.shape[0]
    rng = np.random.default_rng(1)
    xyz = rng.normal(scale=0.02, size=(b, per_pair, 3))
    quat = rng.normal(size=(b, per_pair, 4))
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    return np.concatenate([xyz, quat], axis=-1).astype(np.float32)


def test_ensemble_stacks_networks_of_one_config():
    """Three ranking networks, two of one config (run as one network over stacked parameters)
    and one with near points: the ensemble is the plain mean of each network's log V, scored
    one by one on its own subsample; with_first adds the first V's scores to the mean."""
    clouds = plane_pairs()
    near = dataclasses.replace(CFG, support_near=16, object_near=8, near_pool=128)
    configs = (CFG, near, CFG)
    nets = [_init(c, k) for c, k in zip(configs, (7, 9, 8), strict=True)]
    poses = _poses_near(clouds)
    first = np.random.default_rng(0).normal(size=poses.shape[:2]).astype(np.float32)
    alone = jax.jit(pipeline.make_ensemble_score(configs, with_first=False))
    got = np.asarray(alone(first, nets, clouds, poses))
    each = [_scores(p, c, clouds, poses) for c, p in zip(configs, nets, strict=True)]
    np.testing.assert_allclose(got, np.mean(each, axis=0), rtol=1e-5, atol=1e-5)
    assert not np.allclose(each[0], each[2])  # the two stacked networks differ
    with_v = jax.jit(pipeline.make_ensemble_score(configs, with_first=True))
    np.testing.assert_allclose(np.asarray(with_v(first, nets, clouds, poses)),
                               (first + np.sum(each, axis=0)) / 4, rtol=1e-5, atol=1e-5)  # fmt: skip


def test_load_rank_values_keeps_each_config(monkeypatch):
    """Each ranking network keeps its own config (its own subsample of the clouds); none:
    empty."""
    near = dataclasses.replace(CFG, support_near=16, near_pool=128)
    monkeypatch.setattr(refine, "load_value", lambda f: (near if f == "X" else CFG, V2))
    configs, nets = predict.load_rank_values(["X", "Y"])
    assert configs == (near, CFG) and len(nets) == 2 and nets[0] is V2
    assert predict.load_rank_values([]) == ((), [])


def test_committed_rankers_fit_beside_the_cem_value():
    """The default answer's CEM V and rankers are committed; each ranker shares the V's encoder
    and head (fine-tuned from it), differing at most in how the state picks its points (near
    points: its own subsample of the clouds)."""
    from pathlib import Path

    from omnihang_jax.config import load_config

    def config_of(folder):
        assert (Path(folder) / "params.msgpack").exists(), folder
        return load_config(stage3.ValueConfig, Path(folder) / "config.json")[0]

    config = config_of(where.DEFAULT.value)
    configs = [config_of(f) for f in where.DEFAULT.rankers]
    assert len(configs) == 3 and where.DEFAULT.value not in where.DEFAULT.rankers
    for folder, c in zip(where.DEFAULT.rankers, configs, strict=True):
        plain = dataclasses.replace(c, support_near=0, object_near=0)
        assert plain == config, folder
    assert [(c.support_near, c.object_near) for c in configs] == [(0, 0), (0, 0), (256, 256)]
