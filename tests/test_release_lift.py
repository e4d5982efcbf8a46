"""The release height (experiments.release_lift, stage1.ANSWER_LIFT) proved with physics: a
hanging pose pushed a few millimetres into the hook penetrates, the same pose let go a little
above the hook drops onto it and stays; the tool's bookkeeping agrees with the kernel."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments import release_lift
from omnihang_jax import evaluate, stage1
from sim import kernels
from sim.scene import build_scene
from tests.test_kernels import make_ring, middle_pose, support_of


@pytest.fixture(scope="module")
def ring_scene():
    ring = make_ring()
    hook = support_of("single_rod_hook", style="straight")
    scene = build_scene(ring, hook)
    # where the ring comes to rest on the rod: the reference hang
    rest = kernels.stability(scene, middle_pose(ring, hook)[None]).settled_pose[0]
    return scene, np.asarray(rest, np.float64)


def test_a_pose_inside_the_hook_hangs_when_released_above_it(ring_scene):
    scene, rest = ring_scene
    sunk = rest.copy()
    sunk[2] -= 0.006  # 6 mm down into the rod: the protocol's > 3 mm penetration
    record = {"all_stages": {"pose": sunk.tolist(), "status": "penetrating"}}
    lifts = [0.0, stage1.ANSWER_LIFT]
    got = release_lift.judge_pair(
        scene, record, ["all_stages"], lifts, evaluate.protocol_stability()
    )["all_stages"]
    assert got["0"] == "penetrating", got
    assert got[f"{stage1.ANSWER_LIFT:g}"] == "stable", got  # 1.5 mm above the rest pose
    # far above the hook the same ring still drops onto it, far beside it falls
    res = kernels.stability(
        scene, np.stack([evaluate.lift_poses(rest, 0.02), rest + [0.1, 0, 0, 0, 0, 0, 0]])
    )
    assert res.status.tolist() == [kernels.STABLE, kernels.FALLEN]


def test_release_lift_cli_resumes_and_summarises(tmp_path, monkeypatch):
    """main(): every (stage, lift) judged once per pair, appended to --items; a rerun judges
    nothing again and writes the same summary; lift 0 is always added; bad lifts are refused."""
    calls = []

    def fake_judge(scene, record, stages, lifts, stability):
        calls.append(record["pair_index"])
        return {s: {f"{v:g}": ("stable" if v > 0 or record["ok"] else "penetrating")
                    for v in lifts} for s in stages}  # fmt: skip

    rows = [{"pair_index": i, "object": "o", "support": "s", "category": c, "ok": i == 0,
             "stage1": {"pose": [0, 0, 0, 1, 0, 0, 0], "status": "stable" if i == 0 else "penetrating"}}
            for i, c in enumerate(["mug", "mug", "cap"])]  # fmt: skip
    path = tmp_path / "rec.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))

    class Lib:
        objects = {"o": None}
        supports = {"s": None}

    monkeypatch.setattr(release_lift, "judge_pair", fake_judge)
    import sim.library
    import sim.scene

    monkeypatch.setattr(sim.library, "build_library", lambda *a, **k: Lib())
    monkeypatch.setattr(sim.scene, "build_scene", lambda o, s: None)
    monkeypatch.setattr(release_lift.dataset_bridge, "resolve_dataset_dir", lambda d: (d, d))
    monkeypatch.setattr(release_lift.dataset_bridge, "read_recipe", lambda d: {})
    monkeypatch.setattr(
        release_lift.dataset_bridge, "dataset_config_from_recipe",
        lambda r: type("C", (), {"library": None})(),
    )  # fmt: skip
    argv = ["--records", str(path), "--data", "x", "--lifts", "0.005", "--out", str(tmp_path / "o.json"),
            "--no-progress"]  # fmt: skip
    first = release_lift.main(argv)
    assert calls == [0, 1, 2]
    assert first["lifts_m"] == [0.0, 0.005]
    s1 = first["stages"]["stage1"]
    assert s1["by_lift"]["0"]["mean"] == pytest.approx(25.0)  # mug 50 %, cap 0 %
    assert s1["by_lift"]["0.005"]["mean"] == pytest.approx(100.0)
    assert s1["stored_agreement"] == {"pairs": 3, "same_status_at_lift_0": 3}
    again = release_lift.main(argv)
    assert calls == [0, 1, 2]  # resumed from the items file: nothing judged twice
    assert again["stages"] == first["stages"]
    with pytest.raises(ValueError, match="lifts"):
        release_lift.parse_lifts("0.005,abc")
    with pytest.raises(ValueError, match="lifts"):
        release_lift.parse_lifts("-0.01")
