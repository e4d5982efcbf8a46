"""``experiments.rank_views``: the re-ranked answer reproduces the records' pooled answer with
the committed rankers' recorded scores, an extra ranker that knows the outcome is chosen on the
validation keys, and a bad run list is refused (thirty-first session, issue 12)."""

from __future__ import annotations

import gzip
import json

import numpy as np
import pytest

from experiments import rank_views, union_views
from experiments.rerank_stage3 import read_records

K = 2  # 4K + 1 = 9 candidates a record; the pool is the last 2K of the first 4K (Stages 1+3, all)


def _write_run(path, rng, n_pairs, stable):
    rows = []
    for i in range(n_pairs):
        ranks = rng.uniform(0.05, 0.95, (3, 4 * K + 1))
        rows.append({
            "pair_index": i, "file": f"{i:05d}.npz", "category": ("mug", "cap")[i % 2],
            "v": ranks[0].tolist(), "v_rank": ranks.tolist(),
            "poses_all": rng.normal(0, 0.01, (4 * K + 1, 7)).tolist(),
            "stable_all": stable[i].tolist(),
            "inside_counts": {"0.0005_0.005": rng.integers(0, 2, 4 * K + 1).tolist()},
        })  # fmt: skip
    with gzip.open(path, "wt") as f:
        f.write("\n".join(json.dumps(r) for r in rows) + "\n")
    return str(path)


def test_rank_views_reproduces_the_union_and_chooses_an_informed_ranker(tmp_path):
    rng = np.random.default_rng(0)
    runs = {}
    for key in ("val0", "val1", "held0"):
        stable = [rng.random((20, 4 * K + 1)) < 0.4 for _ in range(2)]
        runs[key] = [
            _write_run(tmp_path / f"{key}_v{v}.jsonl.gz", rng, 20, stable[v]) for v in range(2)
        ]
    keys = {k: rank_views.load_key(p) for k, p in runs.items()}
    for k, paths in runs.items():  # the committed rankers' answer = union_views' union
        d = keys[k]
        committed = np.mean(list(rank_views.committed_scores(d).values()), 0)
        want = union_views.union([read_records(p) for p in paths])["union"]["mean"]
        assert rank_views.answer(d, committed) == pytest.approx(want)
    # an "oracle" ranker (log P high exactly where the candidate hangs) beats every other set
    oracle = {k: np.where(d["stable"], 0.0, -20.0).astype(np.float32) for k, d in keys.items()}
    res = rank_views.sets(keys, {"oracle": oracle})
    assert res["chosen"]["set"] == "oracle"
    assert res["chosen"]["held"] >= res["committed"]["held"]
    assert len(res["table"]) == 2**4 - 1
    with pytest.raises(ValueError, match="view runs"):
        rank_views.load_key(runs["val0"][:1])


def test_three_view_keys_pack_and_score_from_the_table(tmp_path, monkeypatch):
    """A key of three view runs (the default's 0, 1/2, 3/4) loads with its views; pack's table
    round-trips what score reads, and score --table scores each view on its own subset."""
    rng = np.random.default_rng(1)
    stable = [rng.random((6, 4 * K + 1)) < 0.4 for _ in range(3)]
    paths = [_write_run(tmp_path / f"v{v}.jsonl.gz", rng, 6, stable[v]) for v in range(3)]
    d = rank_views.load_key(paths)
    assert d["poses"].shape == (6, 3, 2 * K, 7)
    assert d["views"].tolist() == [[0, 1], [1, 2], [3, 4]]
    want = union_views.union([read_records(p) for p in paths])["union"]["mean"]
    committed = np.mean(list(rank_views.committed_scores(d).values()), 0)
    assert rank_views.answer(d, committed) == pytest.approx(want)
    rank_views.pack(d, tmp_path / "held0.npz")
    back = rank_views.load_pack(tmp_path / "held0.npz")
    assert back["files"] == d["files"]
    np.testing.assert_array_equal(back["poses"], d["poses"])
    seen = []

    def fake_score(ranker, table, clouds_dir):  # what score() receives from the table
        seen.append(table)
        return np.zeros(table["poses"].shape[:3], np.float32)

    monkeypatch.setattr(rank_views, "score", fake_score)
    res = rank_views.main(["score", "--ranker", "r", "--name", "x", "--table",
                           str(tmp_path / "held0.npz"), "--clouds", ".", "--out", str(tmp_path)])  # fmt: skip
    assert res["out"] == [str(tmp_path / "x_held0.npy")]
    assert np.load(tmp_path / "x_held0.npy").shape == (6, 3, 2 * K)
    assert seen[0]["views"].tolist() == [[0, 1], [1, 2], [3, 4]]
    with pytest.raises(SystemExit):
        rank_views.main(["score", "--ranker", "r", "--name", "x", "--clouds", ".", "--out", "o"])
