"""experiments.profile_stage3: the answer pipeline's parts, timed one by one (issue 12's latency)."""

from __future__ import annotations

import json

import pytest

from experiments import profile_stage3


@pytest.mark.slow  # 25-45 s on 2 cores (thirty-second session: the default suite neared 20 min)
def test_profile_times_the_parts_asked_for(tmp_path):
    out = tmp_path / "p.json"
    res = profile_stage3.main([
        "--proposals", "1", "--views", "0/1", "--points", "1024", "--repeat", "2",
        "--parts", "cem_iteration_state,fps_unroll_1,fps_unroll_4,ball_query_count",
        "--out", str(out),
    ])  # fmt: skip
    assert list(res["parts"]) == [
        "cem_iteration_state", "fps_unroll_1", "fps_unroll_4", "ball_query_count",
    ]  # fmt: skip
    for row in res["parts"].values():
        assert row["median_ms"] > 0 and row["p10_ms"] <= row["p90_ms"]
    # one view x 2 starts (Stage 1 and 2) x K = 1 x the CEM's population
    assert res["population_states"] == 2 * res["cem"]["population"]
    assert json.loads(out.read_text())["views"] == [[0, 1]]


def test_profile_refuses_an_unknown_part(tmp_path):
    with pytest.raises(SystemExit):
        profile_stage3.main(["--proposals", "1", "--parts", "nope", "--out", str(tmp_path / "p")])
