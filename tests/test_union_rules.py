"""experiments.union_rules: the answer rule re-chosen over several views' pooled candidates."""

from __future__ import annotations

import gzip
import json

import numpy as np
import pytest

from experiments import union_rules, union_views
from experiments.rerank_stage3 import read_records

K = 2
GRID = ("0.0005_0.005", "0.001_0.005")


def _run(path, seed, n=6):
    """A K = 2 run's records (4K + 1 candidates; the pool is Stage 1+3 and all stages, indices
    2K..4K-1): random rankers' P, inside counts, outcomes."""
    rng = np.random.default_rng(seed)
    with gzip.open(path, "wt") as f:
        for i in range(n):
            row = {
                "pair_index": i, "category": ["mug", "bag"][i % 2],
                "v": rng.uniform(0.1, 0.9, 4 * K + 1).tolist(),
                "v_rank": rng.uniform(0.1, 0.9, (2, 4 * K + 1)).tolist(),
                "stable_all": (rng.uniform(size=4 * K + 1) < 0.5).tolist(),
                "inside_counts": {g: rng.integers(0, 3, 4 * K + 1).tolist() for g in GRID},
            }  # fmt: skip
            f.write(json.dumps(row) + "\n")
    return str(path)


def test_default_rule_reproduces_the_union_and_the_best_rule_is_chosen(tmp_path):
    keys = [",".join(_run(tmp_path / f"k{k}v{v}.jsonl.gz", 10 * k + v) for v in range(2))
            for k in range(2)]  # fmt: skip
    held = [",".join(_run(tmp_path / f"h{k}v{v}.jsonl.gz", 100 + 10 * k + v) for v in range(2))
            for k in range(2)]  # fmt: skip
    res = union_rules.main(["--select-on", *keys, "--apply-to", *held,
                            "--max-points", "0,1", "--weights", "0.1,1e4"])  # fmt: skip
    # the default rule (selection.CHOSEN) is union_views' answer, key by key
    for key, got in zip(keys, res["default"]["validation"]["per_key"], strict=True):
        want = union_views.union([read_records(p) for p in key.split(",")])["union"]["mean"]
        assert got == pytest.approx(want)
    assert len(res["table"]) == len(GRID) * 2 * 2
    assert res["chosen_validation"]["mean"] == max(r["mean"] for r in res["table"])
    assert res["chosen_validation"]["mean"] >= res["default"]["validation"]["mean"]
    assert set(res["held_out"]) == {"default", "chosen"}
    assert len(res["held_out"]["chosen"]["per_key"]) == 2


def test_a_soft_penalty_lets_a_slightly_inside_candidate_win(tmp_path):
    rows = [{"category": "mug"}]
    pool = union_rules.UnionPool.__new__(union_rules.UnionPool)
    pool.rows = rows
    pool.scores = np.log(np.array([[0.2, 0.9]]))
    pool.stable = np.array([[False, True]])
    pool.counts = {GRID[0]: np.array([[0, 1]])}
    assert pool.success(GRID[0], 0, union_rules.LEXICOGRAPHIC)["mean"] == 0.0  # clear first
    assert pool.success(GRID[0], 0, 0.5)["mean"] == 100.0  # log 0.9 - 0.5 > log 0.2
    assert pool.success(GRID[0], 1, union_rules.LEXICOGRAPHIC)["mean"] == 100.0
