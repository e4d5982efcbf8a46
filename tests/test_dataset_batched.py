"""Shard-level batched generation (sim.dataset_batched) against the per-pair engine.

The CPU reference run through the batched bookkeeping must equal ``_shard_records`` bit for
bit (same random streams, same poses per kernel call); the MuJoCo Warp impl (Warp's CPU
device here, slow: few candidates, 64 lanes) must give records of the same structure, the
same candidate counts and mostly the same per-candidate labels.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from sim import dataset, dataset_io, kernels
from sim.library import build_library
from sim.scene import build_scene

pytest.importorskip("jax")
pytest.importorskip("warp")
mjx_kernels = pytest.importorskip("sim.mjx_kernels")
mjx_warp = pytest.importorskip("sim.mjx_warp")
from sim import dataset_batched  # noqa: E402

CFG = dataclasses.replace(
    dataset.PRESETS["tiny"], max_candidates=64, batch=64, negative_candidates=20, n_collision=20
)
WARP = mjx_kernels.MJXSettings(impl="warp", lanes=64, chunk=64)


@pytest.fixture(scope="module")
def shard():
    library = build_library(CFG.library, progress=False)
    pairs = dataset.pair_list(library, CFG)
    rec = dataset.recipe(CFG, library, pairs, "test")
    return library, pairs, rec


def _cpu_statuses(library, pairs, chunk, config):
    """Per pair, the CPU reference's status of every candidate generate_pair draws."""
    out = []
    for i in chunk:
        o, s, _ = pairs[i]
        obj, sup = library.objects[o], library.supports[s]
        seed = dataset.pair_seed(config.seed, o, s)
        rng = np.random.default_rng([seed, 1])
        cand = dataset.draw_candidates(obj, sup, rng, config.batch, config)
        out.append(kernels.stability(build_scene(obj, sup), cand, config.stability).status)
    return out


def _same_structure(got: list[dict], ref: list[dict]) -> None:
    assert len(got) == len(ref)
    for g, r in zip(got, ref):
        assert g.keys() == r.keys()
        for key in r:
            a, b = np.asarray(g[key]), np.asarray(r[key])
            assert a.dtype == b.dtype, key
            if key != "stable_poses" and key != "negative_kept":
                assert a.shape == b.shape, key
            else:  # as many poses as each engine keeps; [S, 7] / [negative_candidates or 0]
                assert a.shape[1:] == b.shape[1:], key


def test_cpu_reference_through_batched_rounds_equals_shard_records(shard):
    """Several rounds (batch 4 of 64): identical records and packed shards."""
    library, pairs, rec = shard
    cfg = dataclasses.replace(CFG, batch=4)
    ref, chunk, ids = dataset._shard_records(library, cfg, pairs, rec, 0, "cpu")
    run = dataset_batched.shard_run_batched(library, cfg, pairs, rec, 0, settings=None)
    assert (run.chunk, run.ids) == (chunk, ids)
    assert run.kernel_calls["stability"] >= 2  # rounds happened
    _same_structure(run.records, ref)
    a, b = dataset_io.pack_shard(run.records, chunk, ids), dataset_io.pack_shard(ref, chunk, ids)
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_warp_shard_matches_cpu_structure_counts_and_labels(shard):
    library, pairs, rec = shard
    ref, chunk, ids = dataset._shard_records(library, CFG, pairs, rec, 0, "cpu")
    cached = len(mjx_warp._WARP_BATCHES)
    t0 = time.time()
    run = dataset_batched.shard_run_batched(library, CFG, pairs, rec, 0, settings=WARP)
    elapsed = time.time() - t0
    assert (run.chunk, run.ids) == (chunk, ids)
    _same_structure(run.records, ref)
    assert [r["n_candidates"] for r in run.records] == [r["n_candidates"] for r in ref]
    for g, r in zip(run.records, ref):
        assert (g["mass"], g["friction"]) == (r["mass"], r["friction"])  # same rng draws
        np.testing.assert_array_equal(g["collision_kept"], r["collision_kept"])  # CPU part
        np.testing.assert_array_equal(g["collision_label"], r["collision_label"])
    # one kernel call per step for the whole shard: one round (batch = max_candidates)
    assert run.kernel_calls["stability"] == 1 and run.kernel_calls["takeoff"] <= 1
    cpu = _cpu_statuses(library, pairs, chunk, CFG)
    got = np.concatenate(run.candidate_status)
    want = np.concatenate(cpu)
    agree = float((got == want).mean())
    agree_stable = float(((got == kernels.STABLE) == (want == kernels.STABLE)).mean())
    print(
        f"\nwarp vs cpu over {len(got)} candidates: status agreement {agree:.3f}, "
        f"stable/not agreement {agree_stable:.3f}; stable raw warp "
        f"{[r['n_stable_raw'] for r in run.records]} cpu {[r['n_stable_raw'] for r in ref]}; "
        f"kept warp {[len(r['stable_poses']) for r in run.records]} "
        f"cpu {[len(r['stable_poses']) for r in ref]}; {elapsed:.1f} s"
    )
    assert agree >= 0.9
    assert agree_stable >= 0.9
    # the device model of the shard is released
    assert len(mjx_warp._WARP_BATCHES) == cached


def test_takeoff_per_pair_materials_equal_scalar_path(shard):
    """takeoff_many(materials=(mass [P], friction [P])) with every pair given the same
    values reproduces the scalar TakeoffConfig(mass=, friction=) path exactly."""
    library, pairs, _ = shard
    scenes = [build_scene(library.objects[o], library.supports[s]) for o, s, _ in pairs[:2]]
    poses, owner = [], []
    for p, sc in enumerate(scenes):
        obj, sup = sc.obj, sc.support
        rng = np.random.default_rng([p, 1])
        poses.append(dataset.draw_candidates(obj, sup, rng, 2, CFG))
        owner.append(np.full(2, p, np.int32))
    poses, owner = np.concatenate(poses), np.concatenate(owner)
    cfg = kernels.TakeoffConfig(push_time=0.1, free_time=0.1)
    settings = mjx_kernels.MJXSettings(impl="warp", lanes=44, chunk=44)
    scalar = dataclasses.replace(cfg, mass=0.45, friction=0.25)
    a = mjx_warp.takeoff_warp_removed(scenes, owner, poses, scalar, settings)
    mats = (np.full(2, 0.45), np.full(2, 0.25))
    b = mjx_warp.takeoff_warp_removed(scenes, owner, poses, cfg, settings, mats)
    np.testing.assert_array_equal(a, b)
    # per-pair fields: each pair row gets its own material, mirroring kernels.with_material
    batch = mjx_warp.warp_batch_for(scenes, settings)
    fields = mjx_warp.warp_material(batch.fields, np.array([0.3, 0.8]), np.array([0.1, 0.5]))
    body = mjx_warp.W_OBJECT_BODY
    np.testing.assert_allclose(np.asarray(fields["body_mass"][:, body]), [0.3, 0.8], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(fields["geom_friction"][0, :, 0]), 0.1, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(fields["geom_friction"][1, :, 0]), 0.5, rtol=1e-6)
    for p, (m, f) in enumerate([(0.3, 0.1), (0.8, 0.5)]):
        ref = kernels.with_material(scenes[p], m, f)
        np.testing.assert_allclose(
            np.asarray(fields["body_inertia"][p, body]),
            ref.body_inertia[scenes[p].object_body],
            rtol=1e-5,
        )
    res = mjx_kernels.takeoff_many(scenes, owner, poses, cfg, settings, materials=mats)
    assert res.removable.tolist() == a.any(1).tolist()
    dataset_batched.release(scenes, settings)


def test_generate_mjx_groups_of_shards_with_a_cpu_stage_pool(shard, tmp_path):
    """generate(backend="mjx", shards_per_call=2, workers=2): both tiny shards in one Warp
    model, the per-pair CPU stage in a 2-process pool; the CPU-made fields equal the CPU
    generator's and the run is logged with its grouping."""
    library, pairs, rec = shard
    card = dataset.generate(
        CFG,
        tmp_path,
        preset="test",
        backend="mjx",
        progress=False,
        workers=2,
        shards_per_call=2,
        mjx_settings=WARP,
    )
    assert card["pairs_done"] == len(pairs)
    (run,) = dataset.load_runs(tmp_path)
    assert run["backend"] == "mjx" and run["shards_per_call"] == 2 and run["shards"] == [0, 1]
    assert {"stability", "views", "collision_labels"} <= set(run["stage_seconds"])
    got = dataset.load_records(tmp_path)
    for k in (0, 1):
        ref, _, _ = dataset._shard_records(library, CFG, pairs, rec, k, "cpu")
        mine = [
            r for r in got if r["pair_index"] in range(k * CFG.shard_size, (k + 1) * CFG.shard_size)
        ]
        for g, r in zip(mine, ref):
            np.testing.assert_array_equal(g["collision_label"], r["collision_label"])
            assert g["n_candidates"] == r["n_candidates"]
