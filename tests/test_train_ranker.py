"""The answer's rankers: pools of the pipeline's simulated candidates (omnihang_jax.pools: the
pairs of training and validation objects, shards that round trip and refuse mixed pools,
resumable building over the product's answer) and the fine-tuning (experiments.train_ranker:
the loss against numpy, a run on a toy pool that learns to put stable candidates first)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import train_ranker
from omnihang_jax import data, dataset_bridge, pipeline, pools, refine, selection, stage3, where
from omnihang_jax.dataset_bridge import META_KEYS

CFG = stage3.VALUE_TINY  # 64 + 64 state points


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
    l2, _ = train_ranker.ranking_loss(jnp.asarray(moved), jnp.asarray(stable),
                                      jnp.asarray(clear), 1.0, 0.0)  # fmt: skip
    l1, _ = train_ranker.ranking_loss(jnp.asarray(logits), jnp.asarray(stable),
                                      jnp.asarray(clear), 1.0, 0.0)  # fmt: skip
    assert float(l2) == pytest.approx(float(l1), rel=1e-6)
    assert 0.0 <= float(m["mixed_pairs"]) <= 0.5


# ---------------------------------------------------------------------------------------------
# Toy pairs and pools


def _name(i: int, category: str, obj: int) -> str:
    return f"{i:05d}_{category}_{obj:04d}__rack_0000.npz"


def _dataset(tmp_path: Path, names: list[str], n: int = 64, seed: int = 0) -> Path:
    """A dataset folder (recipe.json, derived/train/) of tiny derived pair files."""
    ds = tmp_path / "ds"
    folder = ds / "derived" / "train"
    folder.mkdir(parents=True, exist_ok=True)
    (ds / "recipe.json").write_text("{}")
    rng = np.random.default_rng(seed)
    for name in names:
        obj = rng.normal(scale=0.01, size=(n, 3)).astype(np.float32)
        sup = rng.normal(scale=0.03, size=(n, 3)).astype(np.float32)
        stem = name.split("__")[0].split("_", 1)[1]
        meta = (int(name[:5]), stem, "rack_0000", stem.rsplit("_", 1)[0], "rack", "train")
        np.savez(folder / name, object_points=obj,
                 object_normals=obj / np.linalg.norm(obj, axis=1, keepdims=True),
                 support_points=sup, support_normals=sup / np.linalg.norm(sup, axis=1, keepdims=True),
                 stable_poses=np.float32([[0, 0, 0, 1, 0, 0, 0]]),
                 object_contact_maps=np.zeros((1, n), np.float32),
                 support_contact_maps=np.zeros((1, n), np.float32),
                 contact_pairs=np.zeros((1, 1, 2), np.int32),
                 **{k: np.asarray(v) for k, v in zip(META_KEYS, meta, strict=True)})  # fmt: skip
    return ds


def _poses(n_pairs: int, c: int, seed: int = 0) -> np.ndarray:
    """[n, c, 7] identity rotations at heights 0-6 cm: a candidate hangs iff low (z < 3 cm),
    which the posed state shows."""
    rng = np.random.default_rng(seed)
    poses = np.zeros((n_pairs, c, 7), np.float32)
    poses[..., 3] = 1.0
    poses[..., 2] = rng.uniform(0.0, 0.06, size=(n_pairs, c))
    return poses


def _table(names: list[str], poses: np.ndarray) -> dict:
    n, c = poses.shape[:2]
    return dict(
        poses=poses, keys=np.zeros((n, c)), counts=np.zeros((n, c), int),
        status=np.where(poses[..., 2] < 0.03, 0, 1), stable=poses[..., 2] < 0.03,
        start=np.zeros((n, c), int), proposal=np.tile(np.arange(c), (n, 1)),
        pair_index=[int(x[:5]) for x in names], pair_file=names,
        category=[x.split("__")[0].split("_", 1)[1].rsplit("_", 1)[0] for x in names],
        object=[x.split("__")[0].split("_", 1)[1] for x in names], support=["rack_0000"] * n,
    )  # fmt: skip


def _shard(path, names, poses):
    pools.write_shard(path, _table(names, poses), ["stage2", "stage1"], 0, pools.POOL_CONFIG)


def test_pool_shards_round_trip_and_refuse_mixed_pools(tmp_path):
    names = [_name(i, "mug", i) for i in range(5)]
    poses = _poses(5, 4)
    folder = tmp_path / "pools"
    folder.mkdir()
    _shard(folder / "shard_00000.npz", names[:3], poses[:3])
    _shard(folder / "shard_00001.npz", names[3:], poses[3:])
    table = pools.read_pools(folder)
    assert list(table["pair_file"]) == names and list(table["starts"]) == ["stage2", "stage1"]
    np.testing.assert_array_equal(table["poses"], poses)
    assert table["counts"].dtype == np.int16 and table["status"].dtype == np.int8
    assert (
        pools.pooled_pairs(folder) == set(range(5)) and pools.pooled_pairs(tmp_path / "x") == set()
    )
    # the rule: the best-scored clear candidate (an oracle score hangs wherever one does)
    oracle = np.where(table["stable"], 0.0, -1.0)
    assert pools.rule_success(table, oracle)["pair_mean"] == 100 * table["stable"].any(1).mean()
    other = tmp_path / "other"
    other.mkdir()
    _shard(other / "shard_00000.npz", names[:1], poses[:1])
    with pytest.raises(ValueError, match="more than one shard"):
        pools.read_pools([folder, other])
    _shard(other / "shard_00000.npz", [_name(9, "mug", 9)], _poses(1, 6))
    with pytest.raises(ValueError, match="different sizes"):
        pools.read_pools([folder, other])
    bad = poses[:1].copy()
    bad[0, 1, 0] = np.nan
    _shard(other / "shard_00000.npz", [_name(9, "mug", 9)], bad)
    with pytest.raises(ValueError, match="non-finite"):
        pools.read_pools(other)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no pool shards"):
        pools.read_pools(tmp_path / "empty")
    with pytest.raises(FileNotFoundError, match="no such pool shard"):
        pools.read_pools(tmp_path / "missing")


def test_pair_files_are_training_or_validation_objects_balanced_over_categories(tmp_path):
    names = [_name(100 * c + o, cat, o) for c, cat in enumerate(("bag", "cap", "mug"))
             for o in range(12)]  # fmt: skip
    ds = _dataset(tmp_path, names)
    train = pools.pair_files(ds, "train")
    val = pools.pair_files(ds, "validation")
    objects = sorted({data.object_name_of(n) for n in names})
    want_val = data.validation_objects(objects, 0.1)
    assert want_val and {data.object_name_of(f.name) for f in val} == want_val
    assert {f.name for f in train} | {f.name for f in val} == set(names)
    assert not {data.object_name_of(f.name) for f in train} & want_val
    assert [f.name.split("_")[1] for f in train[:3]] == ["bag", "cap", "mug"]  # round robin
    assert pools.pair_files(ds, "train", 4) == train[:4]
    with pytest.raises(ValueError, match="split"):
        pools.pair_files(ds, "test")


def test_build_pools_labels_every_candidate_and_resumes(tmp_path, monkeypatch):
    """Over a stand-in answer (the product's own runs in the slow test below): every candidate
    of the ranked pool is simulated and kept in the rule's order with its inside counts; a
    second call pools only the pairs not yet in a shard."""
    names = [_name(i, cat, i) for i, cat in enumerate(("bag", "cap", "mug", "bag", "cap"))]
    ds = _dataset(tmp_path, names)
    c = 6
    poses = _poses(5, c, seed=1)
    poses[:, :, :2] = 0.0  # over the support's centre: some candidates inside it
    poses[:, :, 2] -= 0.02
    answered = []

    def answer(clouds, ids, seed):
        ids = [int(i) for i in ids]
        answered.extend(ids)
        ranked = poses[ids]
        return where.WhereOutput(
            ranked[:, :2], ranked[:, :2], ranked, -np.arange(c, dtype=float)[None].repeat(len(ids), 0),
            np.array([["stage2", "stage1"] * (c // 2)] * len(ids)), np.zeros((len(ids), c), int),
        )  # fmt: skip

    monkeypatch.setattr(where, "load_where", lambda config: where.Where(config, answer, None, None))
    monkeypatch.setattr(refine, "_labeller_init", lambda dataset_dir: None)
    monkeypatch.setattr(pools, "simulate", lambda job: np.where(job[2][:, 2] < 0.0, 0, 1))
    files = sorted((ds / "derived" / "train").glob("*.npz"))
    first = pools.build_pools(files[:3], tmp_path / "pools", batch=2, shard_pairs=2,
                              progress=False, dataset_dir=ds)  # fmt: skip
    assert first == {"pairs": 3, "skipped": 0, "shards": 2}
    assert set(answered) == {0, 1, 2}  # (a short batch is padded with its first pair)
    answered.clear()
    again = pools.build_pools(files, tmp_path / "pools", batch=2, shard_pairs=2, progress=False,
                              dataset_dir=ds)  # fmt: skip
    assert again == {"pairs": 2, "skipped": 3, "shards": 1}
    assert set(answered) == {3, 4}  # only the pairs not yet pooled
    table = pools.read_pools(tmp_path / "pools")
    order = [int(f.name[:5]) for f in files]
    assert list(table["pair_index"]) == order
    np.testing.assert_allclose(table["poses"], poses[order])
    np.testing.assert_array_equal(table["stable"], poses[order, :, 2] < 0.0)
    np.testing.assert_array_equal(table["start"][0], [0, 1] * (c // 2))
    for b, f in enumerate(files):
        sample, _ = dataset_bridge.load_pair_file(f)
        counts = selection.inside_counts(sample.object_points, sample.support_points,
                                         sample.support_normals, poses[order[b]],
                                         pools.RULE.depth, pools.RULE.radius)  # fmt: skip
        np.testing.assert_array_equal(table["counts"][b], np.asarray(counts))
    assert table["counts"].any()


# ---------------------------------------------------------------------------------------------
# Training


def _toy_run(tmp_path, steps: int) -> tuple[list[str], Path, Path, list[str], dict]:
    names = [_name(i, ("bag", "cap", "mug")[i % 3], i) for i in range(12)]
    ds = _dataset(tmp_path, names)
    poses = _poses(12, 8, seed=2)
    (tmp_path / "pools").mkdir()
    (tmp_path / "val").mkdir()
    _shard(tmp_path / "pools" / "shard_00000.npz", names[:8], poses[:8])
    _shard(tmp_path / "val" / "shard_00000.npz", names[8:], poses[8:])
    init = tmp_path / "v0"
    refine.save_value(init, CFG, jax.jit(stage3.make_value(CFG).init)(jax.random.key(1)))
    out = tmp_path / "ranker"
    args = ["train", "--pools", str(tmp_path / "pools"), "--val-pools", str(tmp_path / "val"),
            "--data", str(ds), "--init", str(init), "--out", str(out), "--steps", str(steps),
            "--pairs-per-batch", "4", "--lr", "3e-3", "--warmup", "5", "--eval-every", "15",
            "--log-every", "5", "--score-batch", "4", "--no-progress"]  # fmt: skip
    return names, ds, out, args, train_ranker.main(args)


def test_training_learns_to_put_stable_candidates_first(tmp_path):
    """train on a toy pool (a candidate hangs iff it sits low): on the validation pools the
    fine-tuned network orders stable above unstable candidates far better than the V it starts
    from, and its pick hangs at least as often as at step 0; the run writes a value folder that
    loads, metrics and curves."""
    _, ds, out, _, summary = _toy_run(tmp_path, 30)
    assert summary["steps"] == 30 and (out / "curves.png").exists()
    val = summary["validation"]
    assert [v["step"] for v in val] == [0, 15, 30] and val[-1]["ranker"] >= val[0]["ranker"]
    assert len((out / "metrics.jsonl").read_text().splitlines()) == 6
    config, _ = refine.load_value(out / "value")
    assert config == CFG
    # the held-out toy pairs' (stable, unstable) candidate pairs ordered right, % (by hand too)
    assert val[-1]["ordered"] > 90.0 and val[-1]["ordered"] > val[0]["ordered"] + 20.0, val
    stable = np.array([[True, False, False], [True, True, True]])
    scores = np.array([[0.0, 1.0, -1.0], [0.0, 0.0, 0.0]])
    assert train_ranker.ordered(scores, stable, np.ones_like(stable)) == 50.0


@pytest.mark.slow  # ~40 s on 2 cores: two runs, each compiles its step
def test_training_resumes_from_its_checkpoint(tmp_path):
    _, _, out, args, _ = _toy_run(tmp_path, 15)
    more = train_ranker.main([*args[:-1], "--steps", "20", "--no-progress"])  # resumes at 15
    assert more["steps"] == 20 and [v["step"] for v in more["validation"]] == [0, 15, 20]
    assert json.loads((out / "summary.json").read_text())["steps"] == 20
    assert [json.loads(x)["step"] for x in (out / "metrics.jsonl").read_text().splitlines()] == [
        5,
        10,
        15,
        20,
    ]


def test_train_refuses_overlapping_validation_and_a_missing_init(tmp_path):
    names = [_name(i, "mug", i) for i in range(4)]
    _shard(tmp_path / "p.npz", names, _poses(4, 4))
    with pytest.raises(ValueError, match="share pairs"):
        train_ranker.main(["train", "--pools", str(tmp_path / "p.npz"), "--val-pools",
                           str(tmp_path / "p.npz"), "--init", str(tmp_path), "--out", str(tmp_path / "o")])  # fmt: skip
    with pytest.raises(SystemExit):
        train_ranker.main(["train", "--pools", str(tmp_path / "p.npz"), "--init",
                           str(tmp_path / "none"), "--out", str(tmp_path / "o")])  # fmt: skip


@pytest.mark.slow  # ~60 s on 2 cores: compiles the real Stage 1 + 2 networks and a tiny CEM
def test_pools_of_the_product_answer_on_dataset_pairs(tmp_path):
    """The pools command over the product's answer (a tiny random V, K = 3, one view) on two
    derived training pairs of datasets/paper, simulated on the true meshes: each pool is the
    answer's ranked candidates (keys descending) with valid statuses, and resumes."""
    derived = Path("datasets/paper/derived/train")
    if not derived.exists() or len(list(derived.glob("*.npz"))) < 2:
        pytest.skip("no derived training pairs (experiments.derive_dataset --split train)")
    folder = tmp_path / "value"
    refine.save_value(folder, CFG, jax.jit(stage3.make_value(CFG).init)(jax.random.key(0)))
    pipe = dataclasses.replace(pipeline.ANSWER_PIPELINE, num_proposals=3, views=((0, 1),),
                               cem=stage3.CEMConfig(population=8, iterations=2, elites=3))  # fmt: skip
    tiny = dataclasses.replace(pools.POOL_CONFIG, value=str(folder), pipeline=pipe)
    files = pools.pair_files("datasets/paper", "train", 2)
    res = pools.build_pools(files, tmp_path / "pools", tiny, batch=2, progress=False)
    assert res == {"pairs": 2, "skipped": 0, "shards": 1}
    table = pools.read_pools(tmp_path / "pools")
    assert table["poses"].shape == (2, 6, 7)
    assert np.all(np.diff(table["keys"], axis=1) <= 1e-6)
    assert set(np.unique(table["status"])) <= {0, 1, 2, 3}
    np.testing.assert_array_equal(table["stable"], table["status"] == 0)
    # the rule's key is log V minus 1e4 per inside point: the counts are the pipeline's
    log_v = table["keys"] + 1e4 * table["counts"]
    assert np.all((log_v <= 1e-3) & (log_v > -200))
    again = pools.build_pools(files, tmp_path / "pools", tiny, progress=False)
    assert again == {"pairs": 0, "skipped": 2, "shards": 0}
