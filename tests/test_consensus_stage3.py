"""experiments.consensus_stage3: the consensus key on a synthetic pair's candidates."""

from __future__ import annotations

import numpy as np

from experiments.consensus_stage3 import consensus_keys, quaternion_angles, score


def _poses(xs):
    return np.array([[x, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0] for x in xs])


def test_quaternion_angles():
    c, s = np.cos(0.25), np.sin(0.25)  # 0.5 rad about z
    q = np.array([[1.0, 0, 0, 0], [c, 0, 0, s], [-1.0, 0, 0, 0]])
    a = quaternion_angles(q)
    np.testing.assert_allclose(a[0, 1], 0.5, atol=1e-6)
    np.testing.assert_allclose(a[0, 2], 0.0, atol=1e-6)  # q and -q: the same rotation


def test_consensus_prefers_the_crowded_basin_and_lam_zero_is_the_rule():
    # candidate 0: a lone high V; candidates 1-3: slightly lower V, 1 mm apart; 4: inside
    v = np.array([0.9, 0.8, 0.8, 0.8, 0.99])
    counts = np.array([0, 0, 0, 0, 5])
    poses = _poses([0.5, 0.0, 0.001, 0.002, 0.0])
    plain = consensus_keys(v, counts, poses, 0.0, 0.005, 0.2, True)
    assert int(np.argmax(plain)) == 0  # the rule: highest V among the clear ones
    crowd = consensus_keys(v, counts, poses, 1.0, 0.005, 0.2, True)
    assert int(np.argmax(crowd)) in (1, 2, 3)


def test_score_reads_records_like_the_pipeline():
    k = 1  # 4K + 1 = 5 candidates; the pooled refined ones are 2 and 3
    rows = [
        dict(category=c, v=[0.1, 0.1, 0.9, 0.2, 0.1], poses_all=_poses([0, 0, 0, 1, 0]).tolist(),
             inside_counts={"0.0005_0.005": [0, 0, 0, 0, 0]},
             stable_all=[False, False, ok, not ok, False])
        for c, ok in (("mug", True), ("cap", False))
    ]  # fmt: skip
    s = score(rows, k)
    assert s["mean"] == 50.0 and s["per_category"] == {"cap": 0.0, "mug": 100.0}
