"""Dataset engine: labels, resumable shards, no leaks, deterministic derived arrays, export."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from sim import dataset, dataset_io
from sim.library import build_library

ROOT = Path(__file__).resolve().parents[1]
CFG = dataset.PRESETS["tiny"]  # 4 pairs: mug, wrench x single_rod_hook, towel_bar


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds")
    card = dataset.generate(CFG, out, preset="test", progress=False)
    return out, card


def test_card_and_labels(generated):
    out, card = generated
    for key in (
        "pairs_with_stable_poses",
        "train_pairs",
        "test_pairs",
        "train_objects",
        "test_objects",
        "objects",
        "supports",
    ):
        assert key in card
    assert card["pairs_done"] == card["pairs_total"] == 4
    assert card["pairs_with_stable_poses"] >= 1
    assert (out / "dataset_card.md").read_text().startswith("# Dataset card")
    records = dataset.load_records(out)
    for r in records:
        poses = r["stable_poses"]
        assert poses.dtype == np.float32 and poses.shape[1] == 7 and np.isfinite(poses).all()
        assert len(poses) <= CFG.max_stable
        assert len(r["collision_kept"]) == CFG.n_collision
        assert r["negative_kept"].sum() <= CFG.max_negatives
        assert len(r["negative_kept"]) == (CFG.negative_candidates if len(poses) else 0)
        assert not (r["collision_label"] & ~r["collision_kept"]).any()


def test_no_test_object_in_training(generated):
    out, card = generated
    lib = build_library(CFG.library, progress=False)
    test_objs = set(lib.split["test"]["objects"])
    assert not test_objs & set(card["train_objects"])
    recipe = json.loads((out / "recipe.json").read_text())
    for obj, sup, split in recipe["pairs"]:
        if split == "train":
            assert lib.split_of(obj) == "train" and lib.split_of(sup) == "train"


def test_resume_redoes_nothing_and_regenerates_lost_shard_identically(generated):
    out, _ = generated
    shards = sorted((out / "shards").glob("shard_*.npz"))
    assert len(shards) == 2
    before = {p.name: p.read_bytes() for p in shards}
    card = dataset.generate(CFG, out, preset="test", progress=False)
    assert card["timings"]["pairs_this_run"] == 0
    # a job killed while writing leaves only a temp file, which never looks finished
    (out / "shards" / ".tmp_deadbeef.npz").write_bytes(b"partial")
    shards[1].unlink()
    card = dataset.generate(CFG, out, preset="test", progress=False)
    assert card["timings"]["pairs_this_run"] == CFG.shard_size
    with (
        np.load(shards[1]) as new,
        np.load(__import__("io").BytesIO(before[shards[1].name])) as old,
    ):
        for key in old.files:
            np.testing.assert_array_equal(new[key], old[key])


def test_parts_and_workers_give_the_same_shards(generated, tmp_path):
    """Two machines each doing half the shards (one with 2 worker processes), merged by
    copying, equal the single-process dataset bit for bit; the runs are logged."""
    out, _ = generated
    a, b = tmp_path / "a", tmp_path / "b"
    card_a = dataset.generate(CFG, a, preset="test", progress=False, part=(0, 2))
    assert card_a["pairs_done"] == CFG.shard_size
    dataset.generate(CFG, b, preset="test", progress=False, part=(1, 2), workers=2)
    for p in (b / "shards").glob("shard_*.npz"):
        p.rename(a / "shards" / p.name)
    card = dataset.generate(CFG, a, preset="test", progress=False)
    assert card["pairs_done"] == 4 and card["timings"]["pairs_this_run"] == 0
    assert [r["part"] for r in card["runs"]] == [[0, 2]]
    assert dataset.load_runs(b)[0]["workers"] == 2
    # provenance: which shards each run wrote
    assert dataset.load_runs(b)[0]["shards"] == [1]
    assert dataset.load_runs(a)[0]["shards"] == [0]
    # time per stage comes back from the worker processes too
    stages = dataset.load_runs(b)[0]["stage_seconds"]
    assert {"stability", "takeoff", "collision_labels", "views"} <= set(stages)
    assert all(v >= 0 for v in stages.values()) and stages["stability"] > 0
    assert set(card["time_per_stage_s"]) >= {"stability", "views"}
    for p in sorted((out / "shards").glob("shard_*.npz")):
        with np.load(p) as x, np.load(a / "shards" / p.name) as y:
            assert sorted(x.files) == sorted(y.files)
            for key in x.files:
                np.testing.assert_array_equal(x[key], y[key])
    with pytest.raises(ValueError, match="part"):
        dataset.generate(CFG, a, preset="test", progress=False, part=(2, 2))
    # a job past its start deadline starts no shard, loses nothing, and the next run resumes
    c = tmp_path / "c"
    card = dataset.generate(CFG, c, preset="test", progress=False, stop_after_s=0.0)
    assert card["pairs_done"] == 0 and not list((c / "shards").glob("*.npz"))
    card = dataset.generate(CFG, c, preset="test", progress=False, stop_after_s=0.0, workers=2)
    assert card["pairs_done"] == 0


def test_other_config_refuses_to_mix(generated):
    out, _ = generated
    recipe = json.loads((out / "recipe.json").read_text())
    assert recipe["labels_version"] == dataset.LABELS_VERSION
    old = out.parent / (out.name + "_v1")
    old.mkdir()
    (old / "recipe.json").write_text(json.dumps({**recipe, "labels_version": 1}))
    with pytest.raises(ValueError, match="labels of version 1"):
        dataset.generate(CFG, old, preset="test", progress=False)
    with pytest.raises(ValueError, match="another config"):
        dataset.generate(dataclasses.replace(CFG, max_stable=5), out, progress=False)


def test_derived_arrays_are_deterministic_and_export_roundtrips(generated, tmp_path):
    out, _ = generated
    recipe = json.loads((out / "recipe.json").read_text())
    lib = build_library(CFG.library, progress=False)
    rec = next(r for r in dataset.load_records(out) if len(r["stable_poses"]))
    obj, sup, _ = recipe["pairs"][int(rec["pair_index"])]
    a = dataset.derive_pair(lib.objects[obj], lib.supports[sup], rec, CFG)
    b = dataset.derive_pair(lib.objects[obj], lib.supports[sup], rec, CFG)
    for key in ("object_points", "support_points", "object_contact_maps", "support_contact_maps"):
        np.testing.assert_array_equal(a[key], b[key])
    assert a["object_points"].shape == (256, 3)
    assert a["object_contact_maps"].shape == (len(rec["stable_poses"]), 256)
    folder = dataset_io.export_sample(lib, rec, recipe["pairs"], tmp_path / "sample")
    meta = json.loads((folder / "pose.json").read_text())
    mesh = trimesh.load(folder / "object.obj", force="mesh")
    m = np.asarray(meta["matrix_4x4"])
    rot = Rotation.from_quat(meta["quaternion_xyzw"]).as_matrix()
    np.testing.assert_allclose(m[:3, :3], rot, atol=1e-6)
    moved = mesh.vertices @ m[:3, :3].T + m[:3, 3]
    assert np.isfinite(moved).all()


def test_pose_quantisation_is_below_a_tenth_of_a_millimetre():
    rng = np.random.default_rng(0)
    poses = np.concatenate([rng.uniform(-1.5, 1.5, (200, 3)), rng.normal(size=(200, 4))], axis=1)
    poses[:, 3:] /= np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
    back = dataset_io.dequantise_poses(*dataset_io.quantise_poses(poses))
    assert np.abs(back[:, :3] - poses[:, :3]).max() <= dataset_io.POSITION_STEP / 2 + 1e-6
    angle = 2 * np.arccos(np.clip(np.abs(np.sum(back[:, 3:] * poses[:, 3:], axis=1)), 0, 1))
    assert angle.max() < 1e-3  # radians
    with pytest.raises(ValueError, match="3.27"):
        dataset_io.quantise_poses(np.array([[4.0, 0, 0, 1, 0, 0, 0]]))


def test_near_misses_start_close_and_fall(generated):
    """Regenerated negatives start clear of the support (within 1 cm) and do not stay put."""
    out, _ = generated
    recipe = json.loads((out / "recipe.json").read_text())
    lib = build_library(CFG.library, progress=False)
    from sim import kernels
    from sim.scene import build_scene

    found = 0
    for r in dataset.load_records(out):
        if not r["negative_kept"].any():
            continue
        obj, sup, _ = recipe["pairs"][int(r["pair_index"])]
        scene = build_scene(lib.objects[obj], lib.supports[sup])
        cand = dataset.negative_candidates(r["stable_poses"], int(r["pair_seed"]), CFG)[
            r["negative_kept"]
        ]
        con = kernels.contact_query(scene, cand)
        assert (con.penetration == 0).all() and (con.distance <= CFG.negative_gap + 1e-6).all()
        found += len(cand)
    assert found > 0


def test_max_pairs_is_a_seeded_subset():
    lib = build_library(CFG.library, progress=False)
    full = dataset.pair_list(lib, dataclasses.replace(CFG, max_objects_per_category=None))
    sub = dataset.pair_list(
        lib, dataclasses.replace(CFG, max_objects_per_category=None, max_pairs=5)
    )
    again = dataset.pair_list(
        lib, dataclasses.replace(CFG, max_objects_per_category=None, max_pairs=5)
    )
    assert len(sub) == 5 and sub == again and set(sub) <= set(full)


def test_datasets_from_before_a_new_config_field_stay_resumable(generated):
    out, _ = generated
    path = out / "recipe.json"
    original = path.read_text()
    recipe = json.loads(original)
    del recipe["config"]["max_pairs"]  # as written by a version without that field
    del recipe["config"]["camera"]["depth_noise"]
    path.write_text(json.dumps(recipe))
    card = dataset.generate(CFG, out, preset="test", progress=False)
    assert card["timings"]["pairs_this_run"] == 0
    recipe["config"]["n_views"] += 1  # a real difference is still refused, by name
    path.write_text(json.dumps(recipe))
    with pytest.raises(ValueError, match="n_views"):
        dataset.generate(CFG, out, preset="test", progress=False)
    path.write_text(original)  # the module's fixture is shared


def test_export_sample_cli(generated, tmp_path, capsys):
    from experiments import export_sample

    out, _ = generated
    rows = export_sample.main(["--data", str(out), "--list", "3"])["pairs"]
    assert rows and all(r["poses"] > 0 for r in rows)
    meta = export_sample.main(
        ["--data", str(out), "--pair", str(rows[0]["pair"]), "--out", str(tmp_path / "s")]
    )
    assert (tmp_path / "s" / "object.obj").exists() and (tmp_path / "s" / "support.obj").exists()
    assert np.asarray(meta["matrix_4x4"]).shape == (4, 4)
    with pytest.raises(SystemExit):
        export_sample.main(["--data", str(out), "--pair", "99999", "--out", str(tmp_path / "x")])


def test_mjx_backend_without_warp_says_what_to_install(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "warp", None)  # import warp -> ImportError
    with pytest.raises(ValueError, match="warp-lang"):
        dataset.generate(CFG, tmp_path, preset="test", progress=False, backend="mjx")
    assert not list((tmp_path / "shards").glob("*.npz"))


def test_an_interrupted_run_keeps_its_shards_and_logs_itself(tmp_path, monkeypatch):
    real = dataset._shard_records
    calls = []

    def stop_on_second(*args):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt  # what SIGTERM becomes in experiments.generate_dataset
        return real(*args)

    monkeypatch.setattr(dataset, "_shard_records", stop_on_second)
    with pytest.raises(KeyboardInterrupt):
        dataset.generate(CFG, tmp_path, preset="test", progress=False)
    assert len(list((tmp_path / "shards").glob("shard_*.npz"))) == 1
    (run,) = dataset.load_runs(tmp_path)
    assert run["interrupted"] and run["pairs"] == CFG.shard_size
    assert run["shards"] == [0]


POOL_SCRIPT = """
import signal, sys, time
from sim import workers

def job(x):
    time.sleep(60 if x == 0 else 0.01)  # one busy worker, the others wait for work
    return x

if __name__ == "__main__":
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        with workers.spawn_pool(3) as pool:
            for x in pool.imap_unordered(job, range(6)):
                print("done", x, flush=True)
    except KeyboardInterrupt:
        print("interrupted", flush=True)
        sys.exit(130)
"""


def _run_and_signal_group(cmd, ready, tmp_path):
    """Start cmd in its own process group, SIGTERM the group once ready() holds; returns
    (returncode, stdout + stderr, seconds from the signal to the exit)."""
    import os
    import signal
    import subprocess
    import time

    with open(tmp_path / "log.txt", "w+") as log:
        proc = subprocess.Popen(cmd, start_new_session=True, stdout=log, stderr=log, cwd=ROOT)
        t0 = time.time()
        while time.time() - t0 < 300 and proc.poll() is None and not ready():
            time.sleep(0.1)
        assert proc.poll() is None, "finished before the signal: make the job longer"
        os.killpg(proc.pid, signal.SIGTERM)
        t_kill = time.time()
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            raise AssertionError("still running 60 s after SIGTERM") from None
        seconds = time.time() - t_kill
        log.seek(0)
        return proc.returncode, log.read(), seconds


def test_sigterm_to_the_process_group_does_not_hang_the_worker_pool(tmp_path):
    """`timeout` and job schedulers signal the whole process group. A multiprocessing.Pool
    whose idle worker dies that way hangs forever in terminate() (a device call lost its
    shards so); sim.workers.WorkerPool leaves the signal to the parent, which kills the
    workers and goes on at once."""
    import sys

    (tmp_path / "pool_job.py").write_text(POOL_SCRIPT)
    log = tmp_path / "log.txt"
    rc, out, seconds = _run_and_signal_group(
        [sys.executable, str(tmp_path / "pool_job.py")],
        lambda: log.exists() and log.read_text().count("done") >= 5,
        tmp_path,
    )
    assert rc == 130 and "interrupted" in out, out
    assert seconds < 20


@pytest.mark.slow  # ~20 s on 2 cores: a real generation run killed mid-shard
def test_sigterm_mid_run_keeps_finished_shards_and_logs_the_run(tmp_path):
    """Kill `generate_dataset` (process group, SIGTERM) once its first shard is written:
    it exits 130 at once, the run is logged as interrupted with the shards it finished, and
    no partial file is left."""
    import sys

    out = tmp_path / "ds"
    cmd = [sys.executable, "-m", "experiments.generate_dataset", "--preset", "demo"]
    cmd += ["--max-pairs", "40", "--out", str(out), "--workers", "2", "--no-progress"]
    # shard_*.npz, not *.npz: pathlib's * also matches a worker's `.tmp_*.npz` being written,
    # and a kill then (the worker is SIGKILLed mid-write) leaves no shard at all
    ready = lambda: any(out.glob("shards/shard_*.npz"))  # noqa: E731
    rc, log, seconds = _run_and_signal_group(cmd, ready, tmp_path)
    assert rc == 130 and "interrupted" in log, log
    assert seconds < 30
    shards = sorted(out.glob("shards/shard_*.npz"))
    # a worker killed mid-write may leave a stray `.tmp_` file (no reader globs for it), never a
    # truncated shard: every shard on disk loads
    assert shards and all(f.name.startswith((".tmp_", "shard_")) for f in out.glob("shards/*"))
    for f in shards:
        with np.load(f) as z:
            assert z.files
    (run,) = dataset.load_runs(out)  # every shard on disk, also one written just before the kill
    assert run["interrupted"] and sorted(run["shards"]) == [int(f.stem[6:]) for f in shards]
    assert len(shards) < 5 and run["pairs"] == 8 * len(shards)


@pytest.mark.parametrize("pooled", [False, True])
def test_grouped_generation_equals_cpu_shards(generated, pooled):
    """sim.dataset_batched.generate_groups (the GPU generator's pipeline), run on the CPU
    reference physics: both shards of the tiny preset in one group, the per-pair CPU stage
    in a 2-process pool (or in this process), give the CPU generator's shards bit for bit."""
    import collections

    from sim import workers

    dataset_batched = pytest.importorskip("sim.dataset_batched")
    out, _ = generated
    library = build_library(CFG.library, progress=False)
    pairs = dataset.pair_list(library, CFG)
    rec = dataset.recipe(CFG, library, pairs, "test")
    got = {}

    def save(k, records, chunk, ids):
        got[k] = dataset_io.pack_shard(records, chunk, ids)

    seconds = collections.Counter()
    groups = [[0, 1]]
    if pooled:
        with workers.spawn_pool(2, dataset._worker_init, (CFG, rec, "cpu")) as pool:
            n = dataset_batched.generate_groups(
                library, CFG, pairs, rec, groups, save, None, pool, stage_seconds=seconds
            )
    else:
        n = dataset_batched.generate_groups(
            library, CFG, pairs, rec, [[0], [1]], save, None, stage_seconds=seconds
        )
    assert n == 2 and sorted(got) == [0, 1]
    assert {"stability", "takeoff", "negatives", "collision_labels", "views"} <= set(seconds)
    for k, packed in got.items():
        with np.load(out / "shards" / f"shard_{k:05d}.npz") as ref:
            assert sorted(packed) == sorted(ref.files)
            for key in ref.files:
                np.testing.assert_array_equal(packed[key], ref[key], err_msg=key)
    # a deadline already passed starts no group
    assert (
        dataset_batched.generate_groups(library, CFG, pairs, rec, groups, save, None, deadline=0)
        == 0
    )


def test_spawned_workers_start_single_threaded(monkeypatch):
    """sim.workers.spawn_pool: the workers see one-thread settings for the BLAS/OpenMP
    pools and XLA; the parent's environment is unchanged afterwards."""
    import os

    from sim import workers

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delenv("OMNIHANG_WORKER_THREADS", raising=False)
    with workers.spawn_pool(1) as pool:
        env = pool.apply(workers.thread_settings)
    assert env["OMP_NUM_THREADS"] == env["OPENBLAS_NUM_THREADS"] == "1"
    assert "--xla_cpu_multi_thread_eigen=false" in env["XLA_FLAGS"]
    assert "OMP_NUM_THREADS" not in os.environ
    monkeypatch.setenv("OMNIHANG_WORKER_THREADS", "0")  # library defaults, for measuring
    with workers.worker_environment():
        assert "OMP_NUM_THREADS" not in os.environ


def test_max_shards_bounds_one_run_and_the_next_resumes(tmp_path):
    dataset.generate(CFG, tmp_path, preset="test", progress=False, max_shards=1)
    assert len(list((tmp_path / "shards").glob("shard_*.npz"))) == 1
    dataset.generate(CFG, tmp_path, preset="test", progress=False, max_shards=5)
    assert len(list((tmp_path / "shards").glob("shard_*.npz"))) == 2
    assert [r["shards"] for r in dataset.load_runs(tmp_path)] == [[0], [1]]
    with pytest.raises(ValueError, match="max_shards"):
        dataset.generate(CFG, tmp_path, preset="test", progress=False, max_shards=-1)


def test_compare_shards_of_one_generation_with_itself(generated, tmp_path):
    from experiments import compare_shards

    out, card = generated
    result = compare_shards.main(
        ["--a", str(out), "--b", str(out), "--out", str(tmp_path / "c.json")]
    )
    total = result["total"]
    assert total["with_stable_agree"] == total["pairs"] == 4
    assert total["stable_poses_a"] == total["stable_poses_b"] > 0
    assert total["collision_labels_equal"] == total["collision_labels_compared"] > 0
    assert json.loads((tmp_path / "c.json").read_text())["shards"] == 2
