"""The object-frame network (``omnihang_jax.canon``): the principal frame turns with the cloud,
so the network's hypotheses do too and the answer's starts do not depend on the object's frame;
the Chamfer loss is blind to an object's symmetries; the network learns to write a turned object
as the library does."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from omnihang_jax import canon, pipeline, stage3, train
from omnihang_jax import poses as P
from omnihang_jax.stage1 import STAGE1_TINY, make_stage1
from omnihang_jax.stage2 import STAGE2_TINY, make_stage2


def _skewed_cloud(n: int, seed: int) -> np.ndarray:
    """An L-shaped cloud (a mug's body and handle, roughly): distinct spreads and moments."""
    rng = np.random.default_rng(seed)
    body = rng.normal(size=(n - n // 4, 3)) * [0.02, 0.03, 0.05]
    handle = rng.normal(size=(n // 4, 3)) * [0.01, 0.005, 0.015] + [0.045, 0.0, 0.01]
    return np.concatenate([body, handle]).astype(np.float32)


def test_the_principal_frame_turns_with_the_cloud():
    pts = _skewed_cloud(512, 0)
    frame = np.asarray(P.principal_frame(jnp.asarray(pts)))
    np.testing.assert_allclose(frame.T @ frame, np.eye(3), atol=1e-5)
    assert np.linalg.det(frame) == pytest.approx(1.0, abs=1e-5)
    for seed in range(4):
        a = Rotation.random(random_state=seed).as_matrix()
        turned = np.asarray(P.principal_frame(jnp.asarray(pts @ a.T + [0.2, -0.1, 0.3])))
        np.testing.assert_allclose(turned, a @ frame, atol=1e-4)


def test_the_chamfer_distance_is_blind_to_symmetry_and_sees_a_turn():
    """A ring turned about its axis is the same ring (distance ~ the sampling's); turned
    about another axis it is not."""
    t = np.linspace(0, 2 * np.pi, 256, endpoint=False)
    ring = np.stack([0.05 * np.cos(t), 0.05 * np.sin(t), np.zeros_like(t)], 1).astype(np.float32)
    about_axis = ring @ Rotation.from_euler("z", 37, degrees=True).as_matrix().T
    tilted = ring @ Rotation.from_euler("x", 60, degrees=True).as_matrix().T
    same = float(canon.chamfer(jnp.asarray(about_axis), jnp.asarray(ring)))
    other = float(canon.chamfer(jnp.asarray(tilted), jnp.asarray(ring)))
    assert same < 1e-3 and other > 5e-3
    assert float(canon.rotation_angle(jnp.eye(3), jnp.asarray(
        Rotation.from_euler("y", 30, degrees=True).as_matrix()))) == pytest.approx(np.pi / 6, abs=1e-4)  # fmt: skip


def test_the_hypotheses_turn_with_the_cloud():
    """rot(A p) A = rot(p): the cloud the network writes is the same in any frame."""
    net = canon.make_canon(canon.CANON_TINY)
    params = net.init(jax.random.key(0))
    pts = _skewed_cloud(128, 1)
    pts = pts - np.asarray(P.box_centre(jnp.asarray(pts)))
    a = Rotation.random(random_state=5).as_matrix().astype(np.float32)
    rot, shift, score = net.frames(params, jnp.asarray(np.stack([pts, pts @ a.T])))
    assert rot.shape == (2, canon.CANON_TINY.hypotheses, 3, 3)
    np.testing.assert_allclose(np.asarray(rot[1]) @ a, np.asarray(rot[0]), atol=2e-4)
    np.testing.assert_allclose(shift[1], shift[0], atol=1e-4)
    np.testing.assert_allclose(score[1], score[0], atol=1e-3)


@pytest.mark.slow  # compiles tiny Stages 1-2, V and the object-frame network (~30 s on 2 cores)
def test_the_starts_from_the_learned_frames_do_not_depend_on_the_object_frame():
    """With the object-frame network's hypotheses alone (``PipelineConfig.canon``, frames 0),
    Stages 1-2 read the same clouds whatever frame the object is given in: the starts for the
    turned cloud place the object exactly where those of the cloud as given do."""
    cfg = dataclasses.replace(pipeline.PipelineConfig(num_proposals=2), canon=True)
    vcfg = stage3.VALUE_TINY
    params = {"stage1": make_stage1(STAGE1_TINY).init(jax.random.key(0)),
              "stage2": make_stage2(STAGE2_TINY).init(jax.random.key(1)),
              "value": stage3.make_value(vcfg).init(jax.random.key(2)),
              "canon": canon.make_canon(canon.CANON_TINY).init(jax.random.key(3))}  # fmt: skip
    rng = np.random.default_rng(0)
    obj = _skewed_cloud(128, 2)
    obj = obj - np.asarray(P.box_centre(jnp.asarray(obj)))
    a = Rotation.random(random_state=7).as_matrix().astype(np.float32)
    objs = np.stack([obj, obj @ a.T])
    sup = np.broadcast_to(rng.uniform(-0.05, 0.05, (128, 3)).astype(np.float32), (2, 128, 3))
    normals = np.broadcast_to(np.float32([0, 0, 1]), (2, 128, 3))
    fn = jax.jit(pipeline.make_frame_starts(STAGE1_TINY, STAGE2_TINY, stage3.make_value(vcfg),
                                            cfg, vcfg, canon.CANON_TINY))  # fmt: skip
    # each cloud on its own with the same key (a pair's key draws its Stage-1 noise)
    outs = [fn(params, jax.random.key(5), stage3.PairClouds(objs[i:i + 1], normals[:1], sup[:1],
                                                            normals[:1])) for i in range(2)]  # fmt: skip
    first, second, pool = (np.concatenate([np.asarray(o[j]) for o in outs]) for j in range(3))
    assert pool.shape == (2, 2 * canon.CANON_TINY.hypotheses, 7)
    for poses in (pool, first, second):
        for p0, p1 in zip(poses[0], poses[1], strict=True):
            placed0 = Rotation.from_quat(p0[[4, 5, 6, 3]]).apply(obj) + p0[:3]
            placed1 = Rotation.from_quat(p1[[4, 5, 6, 3]]).apply(obj @ a.T) + p1[:3]
            np.testing.assert_allclose(placed1, placed0, atol=2e-3)


def test_the_object_frame_network_learns_the_library_frame(tmp_path):
    """Trained on one object's clouds turned at random, the network writes held-out turns of
    it back in the object's own frame: within 20 degrees of the true turn (from about 95 at
    the start) and the Chamfer distance well below the start's."""
    from omnihang_jax import data as data_lib

    cloud = _skewed_cloud(128, 3)
    pool = data_lib.synthetic_batch(jax.random.key(0), 8, 128)
    pool = pool._replace(object_points=jnp.broadcast_to(jnp.asarray(cloud), (8, 128, 3)))
    config = dataclasses.replace(  # noiseless clouds: 150 steps of a tiny network
        train.WHERE_TINY,
        train=dataclasses.replace(train.WHERE_TINY.train, lr_stage1=3e-3),
        canon=dataclasses.replace(train.WHERE_TINY.canon, jitter=0.0),
    )
    loss_fn = jax.jit(train.make_eval_step("canon", config))
    init = train.make_init_state("canon", config)(jax.random.key(1))
    key = jax.random.key(9)
    before = loss_fn(init.params, pool, key)
    state = train.train_stage("canon", config, data_lib.ArrayDataset(pool), str(tmp_path),
                              steps=150, progress=False)  # fmt: skip
    after = loss_fn(state.params, pool, key)
    assert float(before["angle_deg"]) > 60 and float(after["angle_deg"]) < 20, (before, after)
    assert float(after["chamfer_mm"]) < 0.6 * float(before["chamfer_mm"]), (before, after)


def test_pairs_per_object_covers_every_object_of_the_split_with_at_most_n():
    from omnihang_jax.dataset_bridge import pairs_per_object

    pairs = [[f"obj_{i % 5}", f"sup_{i}", "train" if i % 7 else "test"] for i in range(200)]
    chosen = pairs_per_object(pairs, "train", 3)
    assert chosen == pairs_per_object(pairs, "train", 3)  # seeded
    objects = [pairs[i][0] for i in chosen]
    assert all(pairs[i][2] == "train" for i in chosen)
    assert sorted(set(objects)) == [f"obj_{i}" for i in range(5)]
    assert max(objects.count(o) for o in set(objects)) == 3


def test_several_data_folders_train_as_one_with_the_same_validation_objects(tmp_path):
    """``--data A,B`` (e.g. more views of the same pairs): one dataset, and an object held out
    for validation is held out of every folder."""
    from omnihang_jax import data as data_lib

    pool = data_lib.synthetic_batch(jax.random.key(0), 40, 32)
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        for i in range(40):
            sample = jax.tree.map(lambda x, i=i: np.asarray(x[i]), pool)
            np.savez(tmp_path / folder / f"{i:05d}_obj_{i % 20:04d}__hook_0000.npz",
                     **sample._asdict())  # fmt: skip
    fit, val = train.make_dataset(f"{tmp_path / 'a'},{tmp_path / 'b'}", train.WHERE_TINY)
    assert len(fit) + len(val) == 80 and len(val) > 0
    names = lambda ds: {data_lib.object_name_of(f) for f in ds.files}  # noqa: E731
    assert not names(fit) & names(val)
    assert {f.split("/")[-2] for f in val.files} == {"a", "b"}
