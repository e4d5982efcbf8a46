"""experiments.bench_stage3's answer names (the pipelines timed side by side)."""

from __future__ import annotations

import jax
import pytest

from experiments import bench_stage3
from experiments.bench_stage3 import Answer, parse_answer
from omnihang_jax import pointnet2


@pytest.mark.parametrize(
    "text,want",
    [
        ("chosen", Answer("chosen", False, False, None, None)),
        ("views3@10", Answer("views3", False, False, None, 10)),
        ("views2-seq", Answer("views2", True, False, None, None)),
        ("views3-bf16-fps8@10", Answer("views3", False, True, 8, 10)),
        ("views2-seq-fps128@16", Answer("views2", True, False, 128, 16)),
        ("views3-fps8-bqcount@10", Answer("views3", False, False, 8, 10, "count")),
        ("views2-bqtop_k", Answer("views2", False, False, None, None, "top_k")),
    ],
)
def test_answer_names_parse(text, want):
    assert parse_answer(text) == want


@pytest.mark.parametrize(
    "text", ["views3@0", "views3-fps0", "views3-fpsx@10", "views3@", "a-b", "views3-bqsort"]
)
def test_malformed_answer_names_are_refused(text, tmp_path):
    assert parse_answer(text) is None
    with pytest.raises(SystemExit):  # before any weights are loaded
        bench_stage3.main(["--answers", text, "--out", str(tmp_path / "b.json")])


def test_context_sets_the_fps_unroll_and_ball_query_for_the_trace_and_restores_them():
    before = pointnet2.FPS_UNROLL, pointnet2.BALL_QUERY_METHOD
    seen = []

    @jax.jit
    def f(x):
        seen.append((pointnet2.FPS_UNROLL, pointnet2.BALL_QUERY_METHOD))
        return x + 1

    with bench_stage3._context(parse_answer("views3-fps8-bqcount@10")):
        f(1.0)
    assert seen == [(8, "count")]
    assert (pointnet2.FPS_UNROLL, pointnet2.BALL_QUERY_METHOD) == before
    with pytest.raises(RuntimeError), bench_stage3._context(parse_answer("views3-fps4-bqtop_k")):
        raise RuntimeError("a failed trace")
    assert (pointnet2.FPS_UNROLL, pointnet2.BALL_QUERY_METHOD) == before
