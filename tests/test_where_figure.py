"""The predicted-hangs figure of the evaluation (experiments.where_figure, eval_where --figure)."""

from __future__ import annotations

import gzip
import shutil

from PIL import Image

from experiments import eval_where, where_figure
from omnihang_jax import dataset_bridge
from sim import dataset

CFG = dataset.PRESETS["tiny"]  # 4 pairs: mug, wrench x single_rod_hook, towel_bar


def _expected_height(rows: int) -> float:
    """Figure height in pixels for ``rows`` pairs (the layout of draw_where_figure)."""
    row_h = where_figure.PANEL_PX[1] / where_figure.DPI + where_figure.TITLE_IN
    row_h += where_figure.ROW_HEAD_IN
    return where_figure.DPI * (rows * row_h + 0.62)


def _size(path) -> tuple[int, int]:
    with Image.open(path) as im:
        return im.size


def test_select_pairs_spreads_categories_and_outcomes():
    rows = [
        {
            "pair_index": i,
            "category": ("mug", "bag", "cap")[i % 3],
            "family": ("hook", "rack")[i % 2],
            "stage1": {"success": i % 4 == 0},
            "stage1_2": {"success": False},
        }
        for i in range(24)
    ]
    picked = where_figure.select_pairs(rows, 6)
    assert picked == where_figure.select_pairs(list(reversed(rows)), 6)  # deterministic
    assert sorted(r["category"] for r in picked) == ["bag", "bag", "cap", "cap", "mug", "mug"]
    outcomes = [r["stage1"]["success"] for r in picked]
    assert any(outcomes) and not all(outcomes)
    assert len(where_figure.select_pairs(rows[:2], 8)) == 2


def test_eval_where_draws_the_figure_and_redraws_it_from_the_jsonl(tmp_path):
    data = tmp_path / "ds"
    dataset.generate(CFG, data, preset="test", progress=False)
    dataset_bridge.derive_dataset(data, progress=False)
    out = tmp_path / "results" / "hanging_success.json"
    argv = ["--model", "ground_truth", "--data", str(data), "--out", str(out)]
    results = eval_where.main(argv + ["--no-progress", "--figure"])
    # ground truth runs no Stage 2, so no clearance is recorded (a model's run records
    # eval_where's default, stage2.ANSWER_CLEARANCE: tests/test_train_where.py)
    assert results["protocol"]["stage2_clearance_m"] is None
    png = tmp_path / "results" / "hanging_success.png"  # default: beside --out
    assert png.exists()
    rows = min(8, results["pairs"])
    width, height = _size(png)
    assert 880 <= width <= 920  # 3 panels of 300 px
    assert abs(height - _expected_height(rows)) <= 4

    # Afterwards, from the per-pair JSONL only (no model); the derived folder works as --data.
    jsonl = out.with_suffix(".pairs.jsonl")
    gz = tmp_path / "archived.pairs.jsonl.gz"  # archived results are gzipped
    gz.write_bytes(gzip.compress(jsonl.read_bytes()))
    assert where_figure.read_pairs_jsonl(gz) == where_figure.read_pairs_jsonl(jsonl)
    again = eval_where.main(
        ["--figure-from", str(jsonl), "--data", str(data / "derived"), "--figure-pairs", "1"]
    )
    assert again["figure"] == str(png) and len(again["rows"]) == 1
    assert abs(_size(png)[1] - _expected_height(1)) <= 4
    assert again["rows"][0]["stage1"]["status"] == "stable"  # ground truth as the prediction

    # Pairs never derived: ground truth and clouds come from the shard records.
    shutil.rmtree(data / "derived")
    other = tmp_path / "clouds.png"
    drawn = where_figure.draw_where_figure(jsonl, data, other, 1, clouds=True)
    assert other.exists() and drawn[0]["ground_truth"]["status"] == "stable"
