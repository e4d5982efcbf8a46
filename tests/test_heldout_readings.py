"""experiments.heldout_readings: per-group success from an evaluation's per-pair rows."""

import gzip
import json

import pytest

from experiments import heldout_readings


def _row(obj, sup, cat, s1, all_):
    return {"object": obj, "support": sup, "category": cat,
            "stage1": {"success": s1}, "all_stages": {"success": all_}}  # fmt: skip


def test_groups_by_seen_object_and_support(tmp_path):
    recipe = {"pairs": [["mug_a", "hook_a", "train"], ["cap_a", "hook_b", "train"],
                        ["mug_b", "hook_a", "test"], ["mug_b", "hook_c", "test"],
                        ["mug_a", "hook_c", "test"], ["cap_b", "hook_a", "test"]]}  # fmt: skip
    (tmp_path / "recipe.json").write_text(json.dumps(recipe))
    rows = [
        _row("mug_b", "hook_a", "mug", True, True),  # unseen object, seen support
        _row("cap_b", "hook_a", "cap", False, True),  # unseen object, seen support
        _row("mug_b", "hook_c", "mug", False, False),  # both unseen
        _row("mug_a", "hook_c", "mug", True, False),  # seen object, unseen support
    ]
    path = tmp_path / "pairs.jsonl.gz"
    with gzip.open(path, "wt") as f:
        f.write("\n".join(json.dumps(r) for r in rows))
    out = heldout_readings.main(["--pairs", str(path), "--data", str(tmp_path),
                                 "--out", str(tmp_path / "r.json")])  # fmt: skip
    groups = out["groups"]
    seen_sup = groups["unseen object, seen support"]
    assert seen_sup["pairs"] == 2
    assert seen_sup["stage1"]["mean_over_categories"] == pytest.approx(50.0)  # mug 1, cap 0
    assert seen_sup["all_stages"]["mean_over_pairs"] == pytest.approx(100.0)
    assert groups["unseen object, unseen support"]["stage1"]["mean_over_pairs"] == 0.0
    assert groups["seen object, unseen support"]["stage1"]["mean_over_pairs"] == 100.0
    assert groups["all"]["pairs"] == 4 and "stage1_3" not in groups["all"]
    assert json.loads((tmp_path / "r.json").read_text())["groups"] == groups


def test_rejects_a_file_that_is_not_per_pair_rows(tmp_path):
    (tmp_path / "recipe.json").write_text(json.dumps({"pairs": []}))
    (tmp_path / "x.jsonl").write_text(json.dumps({"pair_index": 1}) + "\n")
    with pytest.raises(ValueError, match="lack"):
        heldout_readings.main(["--pairs", str(tmp_path / "x.jsonl"), "--data", str(tmp_path)])
