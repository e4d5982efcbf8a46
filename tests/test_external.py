"""The external object set (datasets/external) and its evaluation command (experiments.external):
the manifest names a licensed public source for every mesh, the meshes load through the user-mesh
path, and the summary counts what the records say."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from experiments import external

ROOT = Path(__file__).resolve().parents[1] / "datasets" / "external"


def test_the_manifest_names_a_source_and_licence_for_every_mesh():
    objects = json.loads((ROOT / "manifest.json").read_text())["objects"]
    assert len(objects) >= 30 and len({o["category"] for o in objects}) >= 6
    import sim.assets.objects  # noqa: F401  (registers the categories)
    from sim.assets.base import OBJECT_CATEGORIES

    for o in objects:
        assert (ROOT / o["file"]).is_file(), o["name"]
        assert o["category"] in OBJECT_CATEGORIES, o["category"]
        assert o["licence"] and o["source"]["package"] and o["source"]["fetch"], o["name"]
    size = sum(p.stat().st_size for p in ROOT.rglob("*") if p.is_file())
    assert size < 4_000_000  # the set travels with the tree


@pytest.mark.parametrize("name", ["mug_pybullet", "scissors_cc0scissors", "bag_briefcase"])
def test_external_meshes_load_through_the_user_mesh_path(name):
    """The loader (repairs, centring) keeps each mesh's size as the manifest gives it, in metres."""
    from sim.meshio import load_user_mesh

    entry = external.read_objects(ROOT / "manifest.json", [name])[0]
    mesh, _ = load_user_mesh(ROOT / entry["file"])
    np.testing.assert_allclose(mesh.extents, entry["extents_m"], atol=1e-3)
    assert 0.05 < max(mesh.extents) < 1.0


def test_unknown_objects_are_refused_by_name():
    with pytest.raises(ValueError, match="no_such_mug"):
        external.read_objects(ROOT / "manifest.json", ["mug_pybullet", "no_such_mug"])


def test_the_summary_counts_the_records():
    rows = [
        dict(object="a", category="mug", support="s1", seed=0, meshes=True, clouds=False),
        dict(object="a", category="mug", support="s2", seed=0, meshes=True, clouds=True),
        dict(object="b", category="bag", support="s1", seed=0, meshes=False, clouds=False),
        dict(object="b", category="bag", support="s2", seed=0, error="bad mesh"),
    ]
    s = external.summarise(rows)
    assert (s["pairs"], s["errors"], s["objects"]) == (3, 1, 2)
    assert s["meshes"] == pytest.approx(66.7) and s["clouds"] == pytest.approx(33.3)
    assert s["per_object"]["a"] == dict(category="mug", pairs=2, meshes=100.0, clouds=50.0)
    assert s["per_category"]["bag"] == dict(meshes=0.0, clouds=0.0)
