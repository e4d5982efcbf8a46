"""experiments.judge_stage3: the subset it draws, its summary, and a real run on two pairs
of the held-out Stage-3 evaluation (both engines, the scene's solid wall)."""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import pytest

from experiments import judge_stage3
from omnihang_jax.eval_pipeline import STAGES

ROOT = Path(__file__).resolve().parents[1]
PAIRS = ROOT / "results" / "hanging_success_stage3.pairs.jsonl.gz"
PAPER = ROOT / "datasets" / "paper"


def _record(i: int, category: str, success=(False, False, False, False)) -> dict:
    return {
        "pair_index": i,
        "object": f"{category}_{i}",
        "support": "hook",
        "category": category,
        "family": "hook",
    } | {s: {"success": ok, "pose": [0.0] * 7} for s, ok in zip(STAGES, success, strict=True)}


def test_spread_order_is_a_permutation_whose_prefixes_spread():
    for n in (1, 2, 3, 7, 50, 177):
        order = judge_stage3.spread_order(n)
        assert sorted(order) == list(range(n))
    assert judge_stage3.spread_order(10)[:4] == [0, 8, 4, 2]


def test_select_nests_and_alternates_categories():
    records = [_record(i, "a") for i in range(9)] + [_record(100 + i, "b") for i in range(3)]
    small, large = judge_stage3.select(records, 2), judge_stage3.select(records, 5)
    assert [r["category"] for r in small] == ["a", "b", "a", "b"]
    assert {r["pair_index"] for r in small} <= {r["pair_index"] for r in large}
    assert len(large) == 5 + 3  # b has only 3
    assert [r["pair_index"] for r in large if r["category"] == "a"] == [0, 8, 4, 2, 6]


def test_summary_uses_the_balanced_prefix_and_counts_each_judge():
    a = [_record(i, "a", (True, False, True, True)) for i in range(4)]
    b = [_record(10 + i, "b") for i in range(4)]
    chosen = judge_stage3.select(a + b, 4)
    t, f = [True] * 4, [False] * 4

    def item(i, mj, pb):
        status = lambda v: ["stable" if x else "fallen" for x in v]  # noqa: E731
        return {"pair_index": i, "mujoco": mj, "pybullet": pb} | {
            "mujoco_status": status(mj),
            "pybullet_status": status(pb),
        }

    # a: MuJoCo says every stage hangs, PyBullet none; b: neither. b's picks in spread
    # order are 10, 12, 11, 13: its third is missing, so two of each category count.
    done = {r["pair_index"]: item(r["pair_index"], t, f) for r in a}
    done |= {i: item(i, f, f) for i in (10, 12, 13)}
    out = judge_stage3.summarize(chosen, done)
    assert out["pairs"] == 4 and out["pairs_per_category"] == {"a": 2, "b": 2}
    assert out["mujoco"]["stage1"]["mean"] == 50.0  # a 100 %, b 0 %
    assert out["pybullet"]["stage1"]["mean"] == 0.0 and out["both"]["stage1"]["mean"] == 0.0
    assert out["stored"]["stage1_2"]["mean"] == 0.0 and out["stored"]["stage1"]["mean"] == 50.0
    assert out["agreement"] == 0.5
    assert out["mujoco_vs_stored"]["stage1"] == 1.0 and out["mujoco_vs_stored"]["stage1_2"] == 0.5
    assert len(out["disagreements"]) == 2 * 4  # pairs of a, every stage
    done[11] = item(11, f, f)
    assert judge_stage3.summarize(chosen, done)["pairs"] == 8  # all judged: all used


@pytest.mark.skipif(not (PAPER / "recipe.json").exists(), reason="paper dataset not present")
def test_two_held_out_pairs_under_both_judges(tmp_path):
    """Three held-out pairs whose chosen poses fall, start penetrating and hang: both engines
    give every stage the same verdict as the evaluation run stored, the summary counts
    them, and a second call with the same items file judges nothing again. The clothes
    hanger's last pose follows three penetrating ones: in one shared PyBullet world it read
    28 mm deep from the manifold points those left behind (0 mm in a fresh world)."""
    pick = {12746: ["fallen", "fallen", "penetrating", "stable"],  # knife on a coat-rack knob
            24038: ["penetrating", "stable", "stable", "stable"],  # wrench on a two-rod hook
            4846: ["penetrating", "penetrating", "penetrating", "stable"]}  # hanger, mug tree  # fmt: skip
    with gzip.open(PAIRS, "rt") as f:
        lines = [x for x in f if json.loads(x)["pair_index"] in pick]
    pairs = tmp_path / "pairs.jsonl"
    pairs.write_text("".join(lines))
    items, out = tmp_path / "items.jsonl", tmp_path / "judges.json"
    out.write_text(json.dumps({"pairs": 1, "note": "an older run"}))
    args = ["--pairs", str(pairs), "--per-category", "1", "--items", str(items), "--out", str(out)]
    result = judge_stage3.main(args + ["--keep-previous", "old"])
    judged = {json.loads(x)["pair_index"]: json.loads(x) for x in items.read_text().splitlines()}
    assert set(judged) == set(pick)
    for i, statuses in pick.items():
        assert judged[i]["mujoco_status"] == statuses
        assert judged[i]["pybullet_status"] == statuses
    assert result["pairs"] == 3 and result["agreement"] == 1.0
    assert result["scene"] == {"labels_version": 3, "wall_thickness_m": 0.5}
    assert result["both"]["stage1"]["mean"] == 0.0
    assert result["both"]["stage1_2"]["mean"] == pytest.approx(100 / 3)  # wrench 100, others 0
    assert result["both"]["all_stages"]["mean"] == 100.0
    assert result["mujoco_vs_stored"]["all"] == 1.0
    assert json.loads(out.read_text())["old"]["note"] == "an older run"
    again = judge_stage3.main(args + ["--summarize-only", "--keep-previous", "old"])
    assert items.read_text().count("\n") == 3
    assert again["both"] == result["both"]
    assert again["old"]["note"] == "an older run"  # kept, not nested twice
    results = tmp_path / "hanging_success.json"
    results.write_text(json.dumps({"stage1": {"mean": 1.0}, "judges": {"pairs": 44}}))
    judge_stage3.main(args + ["--summarize-only", "--into", str(results), "--keep-previous", "old"])
    data = json.loads(results.read_text())
    assert data["stage1"] == {"mean": 1.0}  # other keys untouched
    assert data["judges"]["both"]["all_stages"] == 100.0 and data["judges"]["pairs"] == 3
    assert data["judges"]["old"] == {"pairs": 44} and data["judges"]["file"] == str(out)
