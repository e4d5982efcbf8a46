"""experiments.summarise_heldout: success on common pairs (mean over categories) and errors."""

import gzip
import json

import pytest

from experiments import summarise_heldout


def _row(i, cat, s1, all_stages, err=0.01):
    stage = lambda ok: {  # noqa: E731
        "success": ok,
        "status": "stable" if ok else "penetrating",
        "any_of_k": True,
        "translation_error_m": err,
        "rotation_error_deg": 10.0,
        "min_rotation_error_deg": 5.0,
    }
    return {"pair_index": i, "category": cat, "stage1": stage(s1), "all_stages": stage(all_stages)}


def _write(path, rows, gz=False):
    opener = gzip.open if gz else open
    with opener(path, "wt") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")
    return str(path)


def test_compare_uses_common_pairs_and_category_means(tmp_path):
    a = _write(
        tmp_path / "a.jsonl",
        [_row(0, "mug", 1, 1), _row(1, "mug", 0, 1), _row(2, "cap", 0, 0), _row(3, "cap", 1, 1)],
    )
    b = _write(
        tmp_path / "b.jsonl.gz",
        [_row(0, "mug", 0, 0), _row(2, "cap", 1, 1), _row(3, "cap", 1, 0)],
        gz=True,
    )
    out = summarise_heldout.compare([a, b])
    assert out["pairs"] == 3  # pair 1 only in a
    # a on pairs 0, 2, 3: mug 1/1, cap 1/2 -> (100 + 50) / 2
    assert out["runs"][a]["stage1"]["mean"] == pytest.approx(75.0)
    assert out["runs"][b]["stage1"]["mean"] == pytest.approx(50.0)  # mug 0, cap 100
    assert out["runs"][b]["all_stages"]["mean"] == pytest.approx(25.0)  # mug 0, cap 50


def test_errors_and_cli(tmp_path):
    p = _write(tmp_path / "a.jsonl", [_row(i, "mug", 1, 0, err=0.01 * (i + 1)) for i in range(5)])
    res = summarise_heldout.main(["errors", "--pairs", p, "--out", str(tmp_path / "e.json")])
    assert res["pairs"] == 5
    assert res["stage1"]["translation_error_m"]["median"] == pytest.approx(0.03)
    assert res["all_stages"]["statuses"] == {"penetrating": 5}
    assert json.loads((tmp_path / "e.json").read_text())["stage1"]["statuses"] == {"stable": 5}
    with pytest.raises(ValueError, match="no pairs"):
        summarise_heldout.read_pairs(_write(tmp_path / "empty.jsonl", []))
