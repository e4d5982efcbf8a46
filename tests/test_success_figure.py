"""experiments.success_figure: the per-category figure against the paper's table."""

import json

import pytest

from experiments import success_figure as F


def _row(v):
    return {"mean": v, "per_category": {c: v for c in F.CATEGORIES}}


def test_figure_and_table_from_a_results_file(tmp_path):
    res = tmp_path / "hs.json"
    res.write_text(json.dumps({"pairs": 3, "stage1": _row(10.0), "all_stages": _row(70.0)}))
    out = F.main(["--results", str(res), "--out", str(tmp_path / "f.png")])  # JSON beside it
    assert (tmp_path / "f.png").stat().st_size > 1000
    assert set(out["stages"]) == {"stage1", "all_stages"}  # only the rows present
    assert out["stages"]["all_stages"]["paper"]["mean"] == 68.3
    assert out["stages"]["stage1"]["ours"]["per_category"]["bag"] == 10.0
    assert (
        json.loads((tmp_path / "f.json").read_text())["stages"]["stage1"]["paper"]["mean"] == 36.0
    )
    # a stage's "answer" (how the results chose it) travels with its row, absent ones stay absent
    assert F.table({"stage1": {**_row(5.0), "answer": "released 7.5 mm up"}})["stage1"][
        "answer"
    ] == ("released 7.5 mm up")
    assert "answer" not in out["stages"]["stage1"]
    # the paper's table: 11 categories per row, its means as printed
    for mean, cats in F.PAPER.values():
        assert set(cats) == set(F.CATEGORIES) and 0 < mean < 100


def test_incomplete_results_are_refused(tmp_path):
    row = _row(5.0)
    del row["per_category"]["mug"]
    with pytest.raises(ValueError, match="mug"):
        F.table({"stage1": row})
    with pytest.raises(ValueError, match="none of"):
        F.table({"label": "x"})
