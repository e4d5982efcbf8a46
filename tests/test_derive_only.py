"""``train_collision.derive_collision_pairs(derive_only=)``: the chosen pairs are the same list;
only those the predicate accepts are derived (e.g. a study's validation objects' pairs, never
the rest)."""

from __future__ import annotations

import numpy as np

from omnihang_jax import collision_data as train_collision
from omnihang_jax import dataset_bridge


def test_derive_only_derives_the_accepted_pairs_and_keeps_the_chosen_list(tmp_path, monkeypatch):
    from sim import dataset

    pairs = [(f"mug_{i:04d}", "hook_0000", "train") for i in range(6)]
    records = [
        dict(pair_index=i, stable_poses=np.zeros((1, 7)), collision_kept=np.ones(3, bool))
        for i in range(6)
    ]
    monkeypatch.setattr(dataset_bridge, "read_recipe", lambda data: {"pairs": pairs})
    monkeypatch.setattr(dataset, "load_records", lambda data: records)
    monkeypatch.setattr(train_collision, "_worker_init", lambda recipe, data: None)
    derived = []
    monkeypatch.setattr(
        train_collision, "_derive_one", lambda job: derived.append(job[0]["pair_index"])
    )

    def chosen(**kw):
        return train_collision.derive_collision_pairs(
            tmp_path, {"train": 6}, 1, False, out_dir=tmp_path / "out", **kw
        )["train"]

    everything = chosen()
    assert sorted(derived) == list(range(6))
    derived.clear()
    some = chosen(derive_only=lambda i: i % 2 == 0)
    assert some == everything  # the same chosen pairs, in the same order
    assert sorted(derived) == [0, 2, 4]  # only the accepted ones derived
    assert {p.name for p in some} == {
        dataset_bridge.pair_file_name(i, f"mug_{i:04d}", "hook_0000") for i in range(6)
    }
