"""experiments.mix_stage1: two runs' refined candidates pooled, scored from the records."""

import gzip
import json

import numpy as np
import pytest

from experiments import mix_stage1
from omnihang_jax import selection, stage3

K = 2  # records of a K = 2 run hold 4K + 1 = 9 candidates


def _record(i, category, v, stable, counts=None):
    key = selection.grid_key(
        stage3.ANSWER_PIPELINE.select.depth, stage3.ANSWER_PIPELINE.select.radius
    )
    return {
        "file": f"{i:05d}_x.npz",
        "category": category,
        "v": v,
        "stable_all": stable,
        "inside_counts": {key: counts or [0] * (4 * K)},
        "all_stages": {"success": bool(stable[2 * K + int(np.argmax(v[2 * K : 4 * K]))])},
    }


def _write(path, rows):
    with gzip.open(path, "wt") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")
    return str(path)


def test_pooling_picks_the_highest_v_and_the_table_is_scored(tmp_path):
    # pair 0: run A's best refined candidate fails, run B's (higher V) hangs; pair 1: the reverse
    lo, hi = 0.1, 0.9
    a = [
        _record(0, "mug", [0, 0, 0, 0, hi * 0.5, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0, 0, 0, 0]),
        _record(1, "cap", [0, 0, 0, 0, hi, 0, 0, 0, 0], [0, 0, 0, 0, 1, 0, 0, 0, 0]),
    ]
    b = [
        _record(0, "mug", [0, 0, 0, 0, hi, 0, 0, 0, 0], [0, 0, 0, 0, 1, 0, 0, 0, 0]),
        _record(1, "cap", [0, 0, 0, 0, lo, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0, 0, 0, 0]),
    ]
    ra, rb = _write(tmp_path / "a.gz", a), _write(tmp_path / "b.gz", b)
    assert mix_stage1.mix_outcomes(a, b, K, 2, 0) == [False, True]
    assert mix_stage1.mix_outcomes(a, b, K, 0, 2) == [True, False]
    assert mix_stage1.mix_outcomes(a, b, K, 2, 2) == [True, True]
    # the first proposal of each run only: A's proposal 0 is index 4 / 6, B's the same
    assert mix_stage1.mix_outcomes(a, b, K, 1, 1) == [True, True]
    out = mix_stage1.main(
        ["--select-on", ra, rb, "--apply-to", ra, rb, "--out", str(tmp_path / "m.json")]
    )
    assert out["recorded_answer_a"] == pytest.approx(50.0)
    assert out["validation"]["2+2"]["mean"] == pytest.approx(100.0)
    assert out["chosen"] in ("2+2", "1+1") and out["heldout_chosen"] == pytest.approx(100.0)


def test_runs_of_different_pairs_are_refused(tmp_path):
    a = [_record(0, "mug", [0.5] * 9, [0] * 9)]
    b = [_record(7, "mug", [0.5] * 9, [0] * 9)]
    with pytest.raises(ValueError, match="different pairs"):
        mix_stage1.paired(_write(tmp_path / "a.gz", a), _write(tmp_path / "b.gz", b))
