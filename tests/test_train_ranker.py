"""The answer's ranker (experiments.train_ranker, twentieth session): its loss against numpy,
that it learns, the slim records round trip, the CLI end to end on tiny pair files, and the
pipeline ranking by the ranker alone (``PipelineConfig.rank_with_value=False``)."""

from __future__ import annotations

import dataclasses
import gzip
import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from experiments import train_ranker
from omnihang_jax import refine, selection, stage3
from omnihang_jax.dataset_bridge import META_KEYS
from omnihang_jax.stage1 import STAGE1_TINY
from omnihang_jax.stage2 import STAGE2_TINY
from tests.test_stage2_clearance_pipeline import PIPE, _plane_pairs
from tests.test_stage2_clearance_pipeline import params as params  # noqa: F401 (fixture)


def _numpy_loss(logits, stable, clear, lw, bw):
    s = logits[..., 1] - logits[..., 0]
    logp = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
    ce = -np.where(stable, logp[..., 1], logp[..., 0]).mean()
    per, n = [], 0
    for b in range(len(s)):
        pos, neg = clear[b] & stable[b], clear[b] & ~stable[b]
        if pos.any() and neg.any():
            n += 1
            per.append(np.log(np.exp(s[b][clear[b]]).sum()) - np.log(np.exp(s[b][pos]).sum()))
    return lw * (sum(per) / max(n, 1)) + bw * ce


def test_ranking_loss_matches_numpy_and_skips_unmixed_pairs():
    rng = np.random.default_rng(0)
    logits = rng.normal(size=(4, 6, 2)).astype(np.float32)
    stable = rng.random((4, 6)) < 0.5
    clear = rng.random((4, 6)) < 0.7
    stable[2] = False  # no hanging candidate: no listwise term
    clear[3] = False  # nothing clear: no listwise term
    loss, m = train_ranker.ranking_loss(jnp.asarray(logits), jnp.asarray(stable),
                                        jnp.asarray(clear), 1.0, 0.5)  # fmt: skip
    assert float(loss) == pytest.approx(_numpy_loss(logits, stable, clear, 1.0, 0.5), rel=1e-5)
    # a candidate that is not clear never enters the listwise term
    moved = logits.copy()
    moved[0, ~clear[0], 1] += 5.0
    l2, m2 = train_ranker.ranking_loss(jnp.asarray(moved), jnp.asarray(stable),
                                       jnp.asarray(clear), 1.0, 0.0)  # fmt: skip
    l1, _ = train_ranker.ranking_loss(jnp.asarray(logits), jnp.asarray(stable),
                                      jnp.asarray(clear), 1.0, 0.0)  # fmt: skip
    assert float(l2) == pytest.approx(float(l1), rel=1e-6)
    assert 0.0 <= float(m["mixed_pairs"]) <= 0.5


def _synthetic(n_pairs=6, p=8, seed=0):
    """Pairs of tiny clouds; a candidate hangs iff it sits low (z < 0.03): learnable from the
    posed state."""
    rng = np.random.default_rng(seed)
    cfg = stage3.VALUE_TINY
    n, m = cfg.num_object_points, cfg.num_support_points
    obj = rng.normal(scale=0.01, size=(n_pairs, n, 3)).astype(np.float32)
    sup = rng.normal(scale=0.03, size=(n_pairs, m, 3)).astype(np.float32)
    normals = lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)  # noqa: E731
    clouds = stage3.PairClouds(obj, normals(obj), sup, normals(sup))
    poses = np.zeros((n_pairs, p, 7), np.float32)
    poses[..., 3] = 1.0
    poses[..., 2] = rng.uniform(0.0, 0.06, size=(n_pairs, p))
    stable = poses[..., 2] < 0.03
    return clouds, poses, stable


def test_the_ranker_learns_to_put_a_hanging_candidate_first():
    """A tiny V trained with the ranking loss: the loss falls and the pick among the clear
    candidates hangs more often than at the start."""
    clouds, poses, stable = _synthetic()
    clear = np.ones_like(stable)
    net = stage3.make_value(stage3.VALUE_TINY)
    params = net.init(jax.random.key(0))
    b, p = poses.shape[:2]
    tiled = jax.tree.map(lambda x: jnp.repeat(jnp.asarray(x), p, axis=0), clouds)

    def loss_fn(prm):
        logits = net.logits(prm, tiled, jnp.asarray(poses.reshape(b * p, 7))).reshape(b, p, 2)
        return train_ranker.ranking_loss(logits, jnp.asarray(stable), jnp.asarray(clear), 1.0, 0.5)

    tx = optax.adam(3e-3)
    opt = tx.init(params)

    @jax.jit
    def step(prm, opt):
        (loss, m), g = jax.value_and_grad(loss_fn, has_aux=True)(prm)
        up, opt = tx.update(g, opt, prm)
        return optax.apply_updates(prm, up), opt, loss

    first, _ = loss_fn(params)
    for _ in range(80):
        params, opt, loss = step(params, opt)
    last, m = loss_fn(params)
    assert float(last) < 0.5 * float(first)
    assert float(m["pick_hangs_mixed"]) == 1.0


def _write_pair(path, clouds, i, index):
    np.savez(path, object_points=clouds.object_points[i], object_normals=clouds.object_normals[i],
             support_points=clouds.support_points[i], support_normals=clouds.support_normals[i],
             stable_poses=np.zeros((1, 7), np.float32),
             **{k: np.asarray(v) for k, v in zip(META_KEYS, (index, f"obj_{i}", "sup", "mug",
                                                              "rod", "train"), strict=True)})  # fmt: skip


def _records(clouds, poses, stable, k):
    """eval_stage3-like records: 4K + 1 candidates, the pool (2K..4K) from ``poses``."""
    key = selection.grid_key(selection.CHOSEN.depth, selection.CHOSEN.radius)
    rows = []
    for i in range(len(poses)):
        allp = np.zeros((4 * k + 1, 7), np.float32)
        allp[:, 3] = 1.0
        allp[2 * k : 4 * k] = poses[i]
        st = np.zeros(4 * k + 1, bool)
        st[2 * k : 4 * k] = stable[i]
        rows.append({
            "pair_index": i, "file": f"{i:05d}_obj_{i}__sup.npz", "category": "mug",
            "poses_all": allp.tolist(), "stable_all": st.tolist(),
            "v": np.full(4 * k + 1, 0.5).tolist(),  # the run's V: no preference
            "inside_counts": {key: [0] * (4 * k + 1)},
        })  # fmt: skip
    return rows


def test_cli_slims_trains_and_scores_on_pair_files(tmp_path):
    """slim -> train (a checkpoint, curves, a value folder that loads) -> score; the ranker's
    pick beats the run's V (which ties) on the training records; a second train call resumes
    from the checkpoint instead of starting over."""
    k = 4
    clouds, poses, stable = _synthetic(n_pairs=6, p=2 * k)
    folder = tmp_path / "ds" / "derived" / "train"
    folder.mkdir(parents=True)
    rows = _records(clouds, poses, stable, k)
    for i, r in enumerate(rows):
        _write_pair(folder / r["file"], clouds, i, i)
    rec = tmp_path / "run.pairs.jsonl.gz"
    with gzip.open(rec, "wt") as f:
        f.write("".join(json.dumps(r) + "\n" for r in rows))
    init = tmp_path / "v0"
    refine.save_value(init, stage3.VALUE_TINY, stage3.make_value(stage3.VALUE_TINY).init(
        jax.random.key(1)))  # fmt: skip
    slim = tmp_path / "run.npz"
    assert train_ranker.main(["slim", str(rec), str(slim)])["pairs"] == 6
    table = train_ranker.load_table(slim)
    assert table["poses"].shape == (6, 2 * k, 7) and table["stable"].sum() == stable.sum()
    out = tmp_path / "ranker"
    args = ["train", "--records", str(slim), "--data", str(tmp_path / "ds"), "--init", str(init),
            "--out", str(out), "--val-records", str(rec), "--steps", "60", "--pairs-per-batch",
            "4", "--lr", "3e-3", "--warmup", "5", "--eval-every", "30", "--log-every", "10",
            "--no-progress"]  # fmt: skip
    summary = train_ranker.main(args)
    assert summary["steps"] == 60 and (out / "curves.png").exists()
    val = summary["validation"]
    assert val[0]["step"] == 0 and val[-1]["ranker"] >= val[0]["ranker"]
    assert val[-1]["ranker"] > val[-1]["run_v"] or val[-1]["run_v"] == 100.0
    config, _ = refine.load_value(out / "value")
    assert config == stage3.VALUE_TINY
    # resumed: the checkpoint is at step 60, so a longer run starts there
    more = train_ranker.main([*args[:-1], "--steps", "70", "--no-progress"])
    assert more["steps"] == 70
    assert [v["step"] for v in more["validation"]] == [0, 30, 60, 70]
    res = train_ranker.main(["score", "--ranker", f"r={out / 'value'}", "--records", str(slim),
                             "--data", str(tmp_path / "ds"), "--split", "train", "--out",
                             str(tmp_path / "score.json"), "--no-progress"])  # fmt: skip
    run = res["runs"]["run.npz"]["r"]
    # the same ranker on the same pairs: score's table is the last validation row's
    assert run["ranker"]["mean"] == pytest.approx(more["validation"][-1]["ranker"])
    assert run["run_v"]["mean"] == pytest.approx(more["validation"][-1]["run_v"])
    assert (tmp_path / "score.npz").exists()


def test_load_table_refuses_non_finite_poses(tmp_path):
    k = 2
    clouds, poses, stable = _synthetic(n_pairs=2, p=2 * k)
    rows = _records(clouds, poses, stable, k)
    rows[1]["poses_all"][2 * k][0] = float("nan")
    rec = tmp_path / "bad.pairs.jsonl"
    rec.write_text("".join(json.dumps(r) + "\n" for r in rows))
    with pytest.raises(ValueError, match="non-finite"):
        train_ranker.load_table(rec)


@pytest.mark.slow  # 25-45 s on 2 cores (thirty-second session: the default suite neared 20 min)
def test_pipeline_ranks_by_the_ranker_alone(params):  # noqa: F811
    """rank_with_value=False: the final scores are the ranking network's log V alone; CEM is
    unchanged."""
    clouds = _plane_pairs()
    v2 = stage3.make_value(stage3.VALUE_TINY).init(jax.random.key(7))
    base = dataclasses.replace(PIPE, select=selection.CHOSEN, pool_starts=True, rank_values=1)
    mean = jax.jit(stage3.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, base))
    alone_cfg = dataclasses.replace(base, rank_with_value=False)
    alone = jax.jit(
        stage3.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, alone_cfg)
    )
    key = jax.random.key(3)
    out_m = mean({**params, "rank_values": [v2]}, key, clouds)
    out_a = alone({**params, "rank_values": [v2]}, key, clouds)
    small = stage3.subsample_clouds(jax.tree.map(np.asarray, clouds), stage3.VALUE_TINY)
    value = stage3.make_value(stage3.VALUE_TINY)
    for name in base.starts:
        np.testing.assert_array_equal(np.asarray(out_m.refined[name]),
                                      np.asarray(out_a.refined[name]))  # fmt: skip
        poses = np.asarray(out_a.refined[name])
        want = np.stack([
            np.asarray(value.score(v2, jax.tree.map(lambda x, i=i: x[i], small), poses[i]))
            for i in range(len(poses))
        ])  # fmt: skip
        np.testing.assert_allclose(np.asarray(out_a.scores[name]), want, rtol=1e-5, atol=1e-5)
    assert stage3.ANSWER_PIPELINE.rank_with_value is stage3.RANK_WITH_CEM_VALUE


@pytest.mark.slow  # 25-45 s on 2 cores (thirty-second session: the default suite neared 20 min)
def test_pipeline_ranks_with_a_near_point_ranker(params):  # noqa: F811
    """Ranking networks of different configs (``make_hang_pipeline(..., rank_configs)``): a
    plain one and one with near points, each on its own subsample of the clouds; the final
    scores are the mean of their log V; CEM is unchanged."""
    clouds = _plane_pairs()
    near = dataclasses.replace(stage3.VALUE_TINY, support_near=16, object_near=8, near_pool=128)
    v2 = stage3.make_value(stage3.VALUE_TINY).init(jax.random.key(7))
    v3 = stage3.make_value(stage3.VALUE_TINY).init(jax.random.key(8))
    cfg = dataclasses.replace(PIPE, select=selection.CHOSEN, pool_starts=True, rank_values=2,
                              rank_with_value=False)  # fmt: skip
    plain = jax.jit(stage3.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, cfg))
    ranked = jax.jit(
        stage3.make_hang_pipeline(
            STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, cfg, (stage3.VALUE_TINY, near)
        )
    )
    key = jax.random.key(3)
    out_p = plain({**params, "rank_values": [v2, v3]}, key, clouds)
    out_n = ranked({**params, "rank_values": [v2, v3]}, key, clouds)
    full = jax.tree.map(np.asarray, clouds)
    small = stage3.subsample_clouds(full, near)
    small3 = stage3.subsample_clouds(full, stage3.VALUE_TINY)
    value = stage3.make_value(near)
    value3 = stage3.make_value(stage3.VALUE_TINY)
    for name in cfg.starts:
        np.testing.assert_array_equal(np.asarray(out_p.refined[name]),
                                      np.asarray(out_n.refined[name]))  # fmt: skip
        poses = np.asarray(out_n.refined[name])
        want = np.stack([
            0.5 * np.asarray(value3.score(v2, jax.tree.map(lambda x, i=i: x[i], small3), poses[i]))
            + 0.5 * np.asarray(value.score(v3, jax.tree.map(lambda x, i=i: x[i], small), poses[i]))
            for i in range(len(poses))
        ])  # fmt: skip
        np.testing.assert_allclose(np.asarray(out_n.scores[name]), want, rtol=1e-5, atol=1e-5)
        assert not np.allclose(np.asarray(out_n.scores[name]), np.asarray(out_p.scores[name]))


def test_choose_sets_picks_the_set_best_on_the_selection_table(tmp_path):
    """``train_ranker sets``: every set of scored rankers, ranked by the rule's success on the
    selection table; a ranker that always prefers the hanging candidate wins alone."""
    n = 6
    table = {"poses": np.zeros((n, 2, 7), np.float32), "stable": np.tile([False, True], (n, 1)),
             "v": np.zeros((n, 2), np.float32), "counts": np.zeros((n, 2), np.int16),
             "files": np.array([f"{i:05d}_mug_0000__rack_0000.npz" for i in range(n)]),
             "category": np.array(["mug"] * n), "pair_index": np.arange(n), "k": np.asarray(1)}  # fmt: skip
    for name in ("val.npz", "held.npz", "x.npz"):
        np.savez(tmp_path / name, **table)
    good, bad = np.tile([-2.0, -0.1], (n, 1)), np.tile([-0.1, -5.0], (n, 1))
    np.savez(tmp_path / "s.npz", **{f"good|{r}": good for r in ("val.npz", "held.npz")},
             **{f"bad|{r}": bad for r in ("val.npz", "held.npz")})  # fmt: skip
    res = train_ranker.choose_sets(
        [tmp_path / "s.npz"], tmp_path / "val.npz", [tmp_path / "held.npz"]
    )
    assert res["chosen"]["set"] == ["good"] and res["chosen"]["select_on"] == 100.0
    assert res["chosen"]["runs"] == [100.0]
    # {bad} and {bad, good} both pick the falling candidate: a tie, the smaller set first
    assert [r["set"] for r in res["sets"]][1:] == [["bad"], ["bad", "good"]]
    assert res["sets"][1]["select_on"] == res["sets"][2]["select_on"] == 0.0
    with pytest.raises(ValueError, match="no scores"):
        train_ranker.choose_sets([tmp_path / "s.npz"], tmp_path / "val.npz", [tmp_path / "x.npz"])


def test_ensemble_stacks_networks_of_one_config():
    """Three ranking networks, two of one config (run as one network over stacked parameters)
    and one with near points: the ensemble is the plain mean of each network's log V, scored
    one by one on its own subsample; with_first adds the first V's scores to the mean."""
    clouds = _plane_pairs()
    near = dataclasses.replace(stage3.VALUE_TINY, support_near=16, object_near=8, near_pool=128)
    nets = [stage3.make_value(c).init(jax.random.key(k))
            for c, k in ((stage3.VALUE_TINY, 7), (near, 9), (stage3.VALUE_TINY, 8))]  # fmt: skip
    configs = (stage3.VALUE_TINY, near, stage3.VALUE_TINY)
    full = jax.tree.map(np.asarray, clouds)
    poses = np.asarray(_plane_pairs_poses(full))
    first = np.random.default_rng(0).normal(size=poses.shape[:2]).astype(np.float32)
    alone = jax.jit(stage3.make_ensemble_score(configs, with_first=False))
    got = np.asarray(alone(first, nets, clouds, poses))
    each, scorers = [], {}  # one jitted reference scorer per config (eager dispatch is slow)
    for c, p in zip(configs, nets, strict=True):
        small = stage3.subsample_clouds(full, c)
        score = scorers.setdefault(c, jax.jit(stage3.make_value(c).score))
        each.append(np.stack([
            np.asarray(score(p, jax.tree.map(lambda x, i=i: x[i], small), poses[i]))
            for i in range(len(poses))
        ]))  # fmt: skip
    np.testing.assert_allclose(got, np.mean(each, axis=0), rtol=1e-5, atol=1e-5)
    assert not np.allclose(each[0], each[2])  # the two stacked networks differ
    with_v = jax.jit(stage3.make_ensemble_score(configs, with_first=True))
    np.testing.assert_allclose(np.asarray(with_v(first, nets, clouds, poses)),
                               (first + np.sum(each, axis=0)) / 4, rtol=1e-5, atol=1e-5)  # fmt: skip


def _plane_pairs_poses(full):
    """Six poses a pair, near the support (object above the support's points)."""
    b = full.object_points.shape[0]
    rng = np.random.default_rng(1)
    xyz = rng.normal(scale=0.02, size=(b, 6, 3))
    quat = rng.normal(size=(b, 6, 4))
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    return np.concatenate([xyz, quat], axis=-1).astype(np.float32)


def test_union_puts_the_view_runs_of_the_same_pairs_side_by_side(tmp_path):
    """union: the pool per pair is every run's candidates in run order; the rule on the union
    picks the best clear candidate over all runs; runs of other pairs are refused."""
    k = 2
    tables = []
    for v in range(3):
        clouds, poses, stable = _synthetic(n_pairs=5, p=2 * k, seed=v)
        rows = _records(clouds, poses, stable, k)
        rec = tmp_path / f"v{v}.pairs.jsonl.gz"
        with gzip.open(rec, "wt") as f:
            f.write("".join(json.dumps(r) + "\n" for r in rows))
        train_ranker.main(["slim", str(rec), str(tmp_path / f"v{v}.npz")])
        tables.append(train_ranker.load_table(tmp_path / f"v{v}.npz"))
    res = train_ranker.main(["union", *(str(tmp_path / f"v{v}.npz") for v in range(3)),
                             str(tmp_path / "u.npz")])  # fmt: skip
    assert res == {"pairs": 5, "candidates": 6 * k}
    u = train_ranker.load_table(tmp_path / "u.npz")
    for f in train_ranker.SLIM_FIELDS:
        np.testing.assert_array_equal(u[f][:, 2 * k : 4 * k], tables[1][f])
    assert list(u["files"]) == list(tables[0]["files"])
    # an oracle score on the union hangs wherever some run's clear candidate hangs
    oracle = np.where(u["stable"], 0.0, -9.0).astype(np.float32)
    clear_hang = (u["stable"] & (u["counts"] <= selection.CHOSEN.max_points)).any(1)
    ok = u["stable"][np.arange(5), np.argmax(np.where(u["counts"] <= selection.CHOSEN.max_points,
                                                      oracle, -99.0), 1)]  # fmt: skip
    assert np.array_equal(ok, clear_hang)
    assert train_ranker.rule_success(u, oracle)["mean"] >= max(
        train_ranker.rule_success(t, np.where(t["stable"], 0.0, -9.0))["mean"] for t in tables
    )
    other = dict(tables[1], pair_index=tables[1]["pair_index"] + 1)
    with pytest.raises(ValueError, match="different pairs"):
        train_ranker.union_tables([tables[0], other])
