"""The object's neural unsigned distance field (omnihang_jax.distance_field, issue 12, session 49):
its labels, that it learns, that its trainer resumes, that the extraction finds a known surface,
and the probe's files of per-pair points (scripts/field_points.py)."""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from omnihang_jax import distance_field as df
from omnihang_jax.completion import CompletionData

ROOT = Path(__file__).resolve().parents[1]
TINY = df.FieldConfig(n_input=64, k=4, encoder=(16, 32), encoder2=(32, 16), local=(16, 32),
                      glob=16, head=(32, 16), quantiles=(0.5, 0.9))  # fmt: skip


def _sphere(rng, n, r, centre):
    u = rng.normal(size=(n, 3))
    return centre + r * u / np.linalg.norm(u, axis=1, keepdims=True)


def _spheres(rng, a, views=3, points=96, targets=512):
    """Spheres of 2-5 cm radius; each view the half facing a random direction."""
    inputs, surfaces = [], []
    for _ in range(a):
        r, c = rng.uniform(0.02, 0.05), rng.uniform(-0.02, 0.02, 3)
        surf = _sphere(rng, targets, r, c)
        vs = []
        for _ in range(views):
            d = rng.normal(size=3)
            s = _sphere(rng, 4 * points, r, c)
            vs.append(s[(s - c) @ d > 0][:points])
        inputs.append(np.stack(vs))
        surfaces.append(surf)
    return CompletionData(np.stack(inputs).astype(np.float32),
                          np.stack(surfaces).astype(np.float32), np.arange(a).astype(str))  # fmt: skip


def test_pinball_is_half_the_l1_at_the_median_and_asymmetric_above_it():
    pred, true = jnp.array([[0.01, 0.01]]), jnp.array([0.004])
    got = np.asarray(df.pinball(pred, true, (0.5, 0.9)))
    np.testing.assert_allclose(got, [0.5 * 0.006 + 0.1 * 0.006], rtol=1e-5)  # over: (1 - q) x
    got = np.asarray(df.pinball(jnp.array([[0.0, 0.0]]), true, (0.5, 0.9)))
    np.testing.assert_allclose(got, [0.5 * 0.004 + 0.9 * 0.004], rtol=1e-5)  # under: q x
    with pytest.raises(ValueError, match="quantiles"):
        df.FieldConfig(quantiles=(0.5, 1.0))


def test_true_distance_and_queries_match_a_kd_tree():
    rng = np.random.default_rng(0)
    surf = rng.uniform(-0.05, 0.05, (2, 300, 3)).astype(np.float32)
    q = df.sample_queries(jax.random.key(0), jnp.asarray(surf), 101)
    assert q.shape == (2, 101, 3)
    got = np.asarray(df.true_distance(q, jnp.asarray(surf), 0.01))
    for b in range(2):
        want = np.minimum(cKDTree(surf[b]).query(np.asarray(q[b]))[0], 0.01)
        np.testing.assert_allclose(got[b], want, atol=2e-5)
    assert got.max() <= 0.01 + 1e-7 and (got < 0.006).mean() > 0.3  # half are drawn near it


def test_the_field_learns_and_its_trainer_resumes(tmp_path):
    rng = np.random.default_rng(1)
    fit, val = _spheres(rng, 12), _spheres(rng, 4)
    init, _ = df.make_field(TINY)
    before = df.evaluate(init(jax.random.key(0)), val, TINY, views=2, queries=256)
    tc = df.FieldTrainConfig(steps=150, batch=8, queries=256, lr=3e-3, warmup=20, eval_every=75)
    df.train_field(TINY, fit, val, tmp_path / "f", tc, progress=False)
    cfg, params, meta = df.load_field(tmp_path / "f")
    after = df.evaluate(params, val, cfg, views=2, queries=256)
    assert cfg == TINY and meta["step"] in (75, 150)
    assert after["l1_mm"] < 0.6 * before["l1_mm"], (before, after)
    # the upper (0.9) quantile lies above the truth far more often than the median does
    assert after["upper_covers"] > 0.7, after
    x = val.inputs[:, 0, : TINY.n_input]
    q = val.targets[:, :200] + np.random.default_rng(0).normal(0, 0.003, (len(x), 200, 3))
    med, up = df.field_fn(cfg)(params, x, q), df.upper_fn(cfg)(params, x, q)
    assert np.mean(np.asarray(up) >= np.asarray(med)) > 0.9
    rows = (tmp_path / "f" / "history.jsonl").read_text().splitlines()
    assert len(rows) == 2 and (tmp_path / "f" / "curves.png").exists()
    longer = df.FieldTrainConfig(**{**tc.__dict__, "steps": 225})  # resumes at 150
    df.train_field(TINY, fit, val, tmp_path / "f", longer, progress=False)
    rows = (tmp_path / "f" / "history.jsonl").read_text().splitlines()
    assert len(rows) == 3
    with pytest.raises(ValueError, match="another network"):
        df.train_field(df.FieldConfig(n_input=64, k=5), fit, val, tmp_path / "f", longer,
                       progress=False)  # fmt: skip


def test_extract_finds_a_sphere_from_its_exact_field_hidden_half_included():
    r, c = 0.04, np.array([0.01, -0.02, 0.03], np.float32)

    def fn(params, clouds, q):
        return jnp.abs(jnp.linalg.norm(q - c, axis=-1) - r)

    def gfn(params, clouds, q):
        d, vjp = jax.vjp(lambda x: fn(params, clouds, x), q)
        return d, vjp(jnp.ones_like(d))[0]

    rng = np.random.default_rng(2)
    s = _sphere(rng, 4000, r, c)
    cloud = s[(s - c)[:, 2] > 0][: TINY.n_input].astype(np.float32)  # the top half is seen
    pts = df.extract(None, TINY, cloud, step=0.008, max_points=3000, chunk=2048, fns=(fn, gfn))
    assert 1000 < len(pts) <= 3000
    dist = np.abs(np.linalg.norm(pts - c, axis=1) - r)
    assert dist.max() < 0.0015
    truth = _sphere(rng, 2000, r, c)
    near = cKDTree(pts).query(truth)[0]
    assert np.mean(near < 0.005) > 0.95  # the whole sphere, its unseen bottom too
    assert np.mean(near[(truth - c)[:, 2] < -0.02] < 0.005) > 0.95
    with pytest.raises(ValueError, match="finite"):
        df.extract(None, TINY, np.full((TINY.n_input, 3), np.nan, np.float32), fns=(fn, gfn))


def test_field_points_extract_writes_parts_the_probe_reads(tmp_path):
    sys.path.insert(0, str(ROOT / "scripts"))
    import field_points

    rng = np.random.default_rng(3)
    data = _spheres(rng, 4)
    tc = df.FieldTrainConfig(steps=20, batch=4, queries=128, warmup=5, eval_every=20)
    df.train_field(TINY, data, data, tmp_path / "f", tc, progress=False)
    clouds = data.inputs[:, 0, : TINY.n_input]
    np.savez(tmp_path / "in.npz", pair=np.array([7, 3, 11, 5]), clouds=clouds.astype(np.float16))
    field_points.main(["extract", "--field", str(tmp_path / "f"), "--inputs", str(tmp_path / "in.npz"),
                       "--out", str(tmp_path / "fp"), "--max-points", "200", "--final", "0.2",
                       "--chunk", "1024", "--part-mb", "0.0001", "--step", "0.1", "--no-progress"])  # fmt: skip
    parts = sorted(tmp_path.glob("fp.part*.npz"))
    assert len(parts) >= 2  # the size limit splits them
    got = field_points.load_points(str(tmp_path / "fp"))
    assert sorted(got) == [3, 5, 7, 11]
    for j, i in enumerate([7, 3, 11, 5]):
        p = got[i]
        assert p.dtype == np.float32 and p.shape[1] == 3 and len(p) <= 200
        # each point's upper quantile is stored and filters: none is below 0, all below 1 m
        assert len(field_points.load_points(str(tmp_path / "fp"), upper_max=0.0)[i]) == 0
        np.testing.assert_array_equal(
            field_points.load_points(str(tmp_path / "fp"), upper_max=1.0)[i], p
        )
        if len(p):  # nothing within --new (3 mm) of its own input
            assert cKDTree(clouds[j]).query(p)[0].min() > 0.003 - 1e-4
    with pytest.raises(FileNotFoundError):
        field_points.load_points(str(tmp_path / "none"))
