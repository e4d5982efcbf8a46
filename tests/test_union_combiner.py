"""experiments.union_combiner: a learned listwise answer rule, cross-validated over objects."""

from __future__ import annotations

import gzip
import json

import numpy as np
import pytest

from experiments import union_combiner, union_views
from experiments.rerank_stage3 import read_records

K = 2
GRID = ("0.0005_0.005", "0.001_0.005")


def _run(path, seed, n=40):
    """K = 2 records where a candidate hangs iff CEM's V is high; the rankers are noise."""
    rng = np.random.default_rng(seed)
    with gzip.open(path, "wt") as f:
        for i in range(n):
            v = rng.uniform(0.1, 0.9, 4 * K + 1)
            poses = np.concatenate(
                [rng.normal(size=(4 * K + 1, 3)), np.tile([1.0, 0, 0, 0], (4 * K + 1, 1))], 1
            )
            row = {
                "pair_index": i, "object": f"obj_{i}", "category": ["mug", "bag"][i % 2],
                "v": v.tolist(), "v_rank": rng.uniform(0.1, 0.9, (2, 4 * K + 1)).tolist(),
                "stable_all": (v > 0.6).tolist(), "poses_all": poses.tolist(),
                "inside_counts": {g: np.zeros(4 * K + 1, int).tolist() for g in GRID},
            }  # fmt: skip
            f.write(json.dumps(row) + "\n")
    return str(path)


def test_learned_rule_finds_the_signal_the_default_ignores(tmp_path):
    keys = [",".join(_run(tmp_path / f"k{k}v{v}.jsonl.gz", 10 * k + v) for v in range(2))
            for k in range(2)]  # fmt: skip
    held = [",".join(_run(tmp_path / f"h{v}.jsonl.gz", 100 + v) for v in range(2))]
    res = union_combiner.main(["--select-on", *keys, "--apply-to", *held, "--l2", "0.001,0.1",
                               "--out", str(tmp_path / "c.json")])  # fmt: skip
    # the default rule's figure is union_views' answer
    for key, got in zip(keys, res["default_validation"]["per_key"], strict=True):
        want = union_views.union([read_records(p) for p in key.split(",")])["union"]["mean"]
        assert got == pytest.approx(want)
    best = res["cross_validated"][f"{res['chosen_l2']:g}"]["mean"]
    assert best > res["default_validation"]["mean"] + 10
    assert res["weights"]["log_v"] > 0
    assert res["held_out"]["learned"]["mean"] > res["held_out"]["default"]["mean"] + 10
    assert json.loads((tmp_path / "c.json").read_text())["features"][0] == "rank_mean"


def test_object_folds_keep_an_object_in_one_fold():
    rows = [{"object": o} for o in ["a", "b", "a", "c", "b"]]
    folds = union_combiner.object_folds(rows)
    assert folds[0] == folds[2] and folds[1] == folds[4]
    assert set(folds.tolist()) <= set(range(union_combiner.FOLDS))
