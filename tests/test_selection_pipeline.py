"""The answer rule (omnihang_jax.selection) inside the Stages 1-3 pipeline and the evaluation:
the paper's rule is unchanged, "value_clear" picks by V and the observed-cloud inside counts,
and every evaluation record carries what experiments.rerank_stage3 needs."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from omnihang_jax import dataset_bridge, eval_pipeline, predict, refine, selection, stage3
from omnihang_jax.stage1 import STAGE1_TINY
from omnihang_jax.stage2 import STAGE2_TINY
from tests.test_stage2_clearance_pipeline import (
    PIPE,
    _fake_load_predictor,
    _fake_load_value,
    _fake_pair,
    _FakeLabeller,
    _plane_pairs,
    params,  # noqa: F401  (module fixture)
)

CLEAR = selection.SelectConfig("value_clear", depth=0.001, radius=0.003, max_points=0)


def test_pipeline_value_clear_picks_by_v_and_inside_counts(params):  # noqa: F811
    clouds = _plane_pairs()
    key = jax.random.key(7)
    paper = jax.jit(stage3.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, PIPE))
    cfg = dataclasses.replace(PIPE, select=CLEAR)
    clear = jax.jit(stage3.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, cfg))
    a, b = paper(params, key, clouds), clear(params, key, clouds)
    for name in PIPE.starts:  # same candidates and scores, only the pick differs
        np.testing.assert_array_equal(np.asarray(a.refined[name]), np.asarray(b.refined[name]))
        np.testing.assert_array_equal(np.asarray(a.scores[name]), np.asarray(b.scores[name]))
        np.testing.assert_array_equal(
            np.asarray(a.best[name]), np.argmax(np.asarray(a.scores[name]), axis=1)
        )
        counts = np.stack([
            np.asarray(selection.inside_counts(
                clouds.object_points[i], clouds.support_points[i], clouds.support_normals[i],
                b.refined[name][i], CLEAR.depth, CLEAR.radius))
            for i in range(len(clouds.object_points))
        ])  # fmt: skip
        want = np.asarray(selection.select(b.scores[name], counts, CLEAR))
        np.testing.assert_array_equal(np.asarray(b.best[name]), want)
    first = PIPE.starts[0]
    pick = np.take_along_axis(
        np.asarray(b.refined[first]), np.asarray(b.best[first])[:, None, None], 1
    )
    np.testing.assert_array_equal(np.asarray(b.pose), pick[:, 0])


def _evaluate(monkeypatch, select):
    monkeypatch.setattr(predict, "load_predictor", _fake_load_predictor([]))
    monkeypatch.setattr(refine, "load_value", _fake_load_value)
    monkeypatch.setattr(refine, "Labeller", _FakeLabeller)
    monkeypatch.setattr(dataset_bridge, "load_pair_file", _fake_pair)
    files = ["00003_x.npz", "00004_x.npz"]
    return eval_pipeline.evaluate_pipeline(
        files, "W", "V", "D", num_proposals=2, batch=2, progress=False, select=select,
        cem=stage3.CEMConfig(population=8, iterations=2, elites=3),
    )[0]  # fmt: skip


def test_evaluation_records_counts_and_applies_the_rule(monkeypatch):
    k = 2
    paper = _evaluate(monkeypatch, selection.SelectConfig())
    clear = _evaluate(monkeypatch, CLEAR)
    for rp, rc in zip(paper, clear, strict=True):
        assert len(rp["poses_all"]) == 4 * k + 1 and len(rp["v"]) == 4 * k + 1
        assert set(rp["inside_counts"]) == {
            selection.grid_key(d, r) for d, r in selection.INSIDE_GRID
        }
        assert all(len(c) == 4 * k for c in rp["inside_counts"].values())
        # the paper's rule: the highest V; same candidates (same keys) under both rules
        assert rp["best_all_stages"] == rp["best_all_stages_value"]
        np.testing.assert_allclose(rp["poses_all"][: 4 * k], rc["poses_all"][: 4 * k])
        counts = np.asarray(rc["inside_counts"][selection.grid_key(CLEAR.depth, CLEAR.radius)])
        v = np.asarray(rc["v"], np.float32)
        want = int(
            np.argmax(np.asarray(selection.select_key(v[3 * k : 4 * k], counts[3 * k :], CLEAR)))
        )
        # v is V on the final poses = CEM's final score: the same order
        assert rc["best_all_stages"] == want


def test_pipeline_pools_the_starts(params):  # noqa: F811
    clouds = _plane_pairs()
    key = jax.random.key(8)
    cfg = dataclasses.replace(PIPE, select=CLEAR, pool_starts=True)
    out = jax.jit(stage3.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, cfg))(
        params, key, clouds
    )
    cands = np.concatenate([np.asarray(out.refined[n]) for n in cfg.starts], axis=1)
    scores = np.concatenate([np.asarray(out.scores[n]) for n in cfg.starts], axis=1)
    counts = np.stack([
        np.asarray(selection.inside_counts(
            clouds.object_points[i], clouds.support_points[i], clouds.support_normals[i],
            cands[i], CLEAR.depth, CLEAR.radius))
        for i in range(len(cands))
    ])  # fmt: skip
    pick = np.asarray(selection.select(scores, counts, CLEAR))
    np.testing.assert_array_equal(np.asarray(out.pose), cands[np.arange(len(cands)), pick])
