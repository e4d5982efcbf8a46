"""The forty-eighth session's issue-12 probe (scripts/probe_true_surface.py: the true hidden side
of the object in the answer rule, a bound on completion; the answer rule's inside test with a
margin) and the completion trainer's network flags (experiments.train_completion)."""

import argparse
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))


def _load(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / f"scripts/{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _plate(n, rng):
    """A support: the plane z = 0 seen from above, normals +z, 10 cm square."""
    p = np.c_[rng.uniform(-0.05, 0.05, (n, 2)), np.zeros(n)]
    return p, np.tile([0.0, 0.0, 1.0], (n, 1))


def test_inside_grid_with_a_margin_counts_what_the_rule_counts_near_the_support_only():
    from experiments.rerank_completed import GRID, inside_grid

    pt = _load("probe_true_surface")  # the probe's margin
    rng = np.random.default_rng(0)
    sup, nrm = _plate(2000, rng)
    # candidate 0 sinks 4 mm into the plate, candidate 1 rests 1 mm above it,
    # candidate 2 is 5 cm under it (behind the partial support: the plain test would count it)
    body = np.c_[rng.uniform(-0.01, 0.01, (300, 2)), np.zeros(300)]
    posed = np.stack([body + [0, 0, -0.004], body + [0, 0, 0.001], body + [0, 0, -0.05]])
    got = inside_grid(posed, sup, nrm, margin=pt.MARGIN)
    want = inside_grid(posed, sup, nrm)
    assert got.shape == (len(GRID), 3)
    np.testing.assert_array_equal(got[:, :2], want[:, :2])  # the same counts within the margin
    g1 = GRID.index((0.001, 0.003))
    assert got[g1, 0] == 300 and got[g1, 1] == 0
    assert want[g1, 2] == 300 and got[g1, 2] == 0  # far behind: tested no more
    far = np.stack([body + [1.0, 0, 0]])  # nowhere near: nothing tested, nothing counted
    assert not inside_grid(far, sup, nrm, margin=pt.MARGIN).any()


def test_train_completion_network_flags_make_the_config():
    from experiments.train_completion import network_config
    from omnihang_jax.completion import CompletionConfig

    base = CompletionConfig(kind="object")
    ns = argparse.Namespace(n_coarse=None, fold=None, fold_size=None, width=1)
    assert network_config("object", ns) == base
    ns = argparse.Namespace(n_coarse=512, fold="2x4", fold_size=0.03, width=2)
    cfg = network_config("support", ns)
    assert cfg.kind == "support" and cfg.n_coarse == 512 and cfg.fold == (2, 4)
    assert cfg.n_output == 4096 and cfg.fold_size == pytest.approx(0.03)
    assert cfg.encoder == tuple(2 * x for x in base.encoder)
    assert cfg.decoder == tuple(2 * x for x in base.decoder)


def test_support_surface_is_the_whole_mesh_with_outward_normals_and_fixes_the_partial_test():
    """The fiftieth session's support bound (scripts/probe_support_surface.py): the support's true
    surface is its mesh sampled ~1 mm apart with outward normals, and against it a point beyond
    the far side of the support is outside, where the observed (one-sided) cloud counts it in."""
    import types

    import trimesh

    from experiments.rerank_completed import inside_grid

    pt = _load("probe_true_surface")
    box = trimesh.creation.box([0.04, 0.04, 0.01])  # a 1 cm thick plate, the support
    pts, nrm = pt.support_surface(types.SimpleNamespace(mesh=box))
    assert len(pts) >= int(box.area / pt.SUPPORT_SPACING**2)
    assert not box.contains(pts + 0.001 * nrm).any()  # normals point out
    assert box.contains(pts - 0.001 * nrm).mean() > 0.99  # (the ray test is loose at edges)
    grid = ((0.0005, 0.005),)
    seen = pts[pts[:, 2] > 0.0049]  # the camera saw the top face only
    seen_n = nrm[pts[:, 2] > 0.0049]
    inside, above, beyond = [0, 0, 0.002], [0, 0, 0.006], [0, 0, -0.008]  # 3 mm under the bottom
    posed = np.asarray([[inside], [above], [beyond]], float)
    whole = inside_grid(posed, pts, nrm, margin=pt.MARGIN, grid=grid)[0]
    partial = inside_grid(posed, seen, seen_n, margin=pt.MARGIN, grid=grid)[0]
    np.testing.assert_array_equal(whole, [1, 0, 0])
    np.testing.assert_array_equal(partial, [1, 0, 1])  # the one-sided cloud's false inside
    # the bounded search (the probe's MAX_DIST) counts the same; a bound below the inside point's
    # 3 mm depth calls it outside
    bounded = inside_grid(posed, pts, nrm, margin=pt.MARGIN, grid=grid, max_dist=0.03)[0]
    np.testing.assert_array_equal(bounded, whole)
    assert not inside_grid(posed, pts, nrm, margin=pt.MARGIN, grid=grid, max_dist=0.002).any()
