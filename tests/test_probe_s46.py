"""The forty-sixth session's issue-12 probe: a training object's whole surface retrieved for the
observed object cloud (scripts/probe_retrieval.py), and its hidden points."""

import importlib.util
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))


def _load(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / f"scripts/{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _box(size, n, rng):
    """n points on the surface of an axis-aligned box of half-sizes ``size``."""
    p = rng.uniform(-1, 1, (n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.sign(p[np.arange(n), axis])
    return p * np.asarray(size)


def test_retrieval_finds_the_shape_the_observed_half_came_from_and_aligns_it():
    pr = _load("probe_retrieval")
    rng = np.random.default_rng(0)
    shapes = {"thin": (0.05, 0.01, 0.01), "cube": (0.03, 0.03, 0.03), "slab": (0.05, 0.05, 0.005)}
    names = list(shapes)
    surfaces = [_box(s, 2048, rng) for s in shapes.values()]
    retrieval = pr.Retrieval(names, surfaces, beta=0.5)
    truth = _box(shapes["cube"], 4096, rng) + np.array([0.004, -0.003, 0.0])  # a shifted cube
    observed = truth[truth[:, 0] > 0.0]  # the camera saw its +x half
    got = retrieval.fit(observed)
    assert got[0][0] == "cube"
    aligned = got[0][1]
    assert np.allclose(aligned.mean(0), [0.004, -0.003, 0.0], atol=2e-3)  # the ICP's shift
    hidden = pr.hidden_points(aligned, observed, 0.003)
    assert len(hidden) > 0 and np.mean(hidden[:, 0] < 0.004) > 0.9  # the unseen -x half
