"""The asset library: determinism, counts, split protocol, manifest, user assets."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from sim import decompose
from sim.assets.base import OBJECT_CATEGORIES, SUPPORT_FAMILIES
from sim.library import (
    TINY,
    LibraryConfig,
    asset_seed,
    build_library,
    check_split,
    held_out_indices,
)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def library():
    return build_library(TINY, progress=False)


def test_two_builds_are_identical(library):
    again = build_library(TINY, progress=False)
    assert list(again.objects) == list(library.objects)
    assert list(again.supports) == list(library.supports)
    assert again.split == library.split
    assert again.manifest() == library.manifest()
    for name, asset in library.objects.items():
        assert again.objects[name].seed == asset.seed
        np.testing.assert_array_equal(again.objects[name].bounds(), asset.bounds())


def test_seeds_are_stable_across_processes():
    """Seeds come from SHA-256 and SeedSequence, never from Python's salted hash()."""
    code = "from sim.library import asset_seed; print(asset_seed(7, 'object', 'mug', 3))"
    outputs = {
        subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            check=True,
            env={"PYTHONHASHSEED": str(h), "PATH": ""},
            cwd=REPO,
        ).stdout.strip()
        for h in (1, 2)
    }
    assert outputs == {str(asset_seed(7, "object", "mug", 3))}


def test_seeds_differ_between_assets_and_base_seeds():
    seeds = {asset_seed(0, "object", c, i) for c in ("mug", "knife") for i in range(50)}
    assert len(seeds) == 100
    assert asset_seed(0, "object", "mug", 0) != asset_seed(1, "object", "mug", 0)
    assert asset_seed(0, "object", "mug", 0) != asset_seed(0, "support", "mug", 0)


def test_counts_sum_to_config(library):
    assert sum(library.objects_per_category().values()) == TINY.n_objects
    assert sum(library.supports_per_family().values()) == TINY.n_supports
    assert library.objects_per_category() == TINY.objects_per_category()
    assert library.supports_per_family() == TINY.supports_per_family()
    for counts in (TINY.objects_per_category(), TINY.supports_per_family()):
        assert max(counts.values()) - min(counts.values()) <= 1  # as even as possible


def test_default_config_counts():
    config = LibraryConfig()
    assert sum(config.objects_per_category().values()) == 340
    assert sum(config.supports_per_family().values()) == 72
    assert set(config.objects_per_category()) == set(OBJECT_CATEGORIES)
    assert set(config.supports_per_family()) == set(SUPPORT_FAMILIES)


@pytest.mark.parametrize("category", sorted(OBJECT_CATEGORIES))
def test_every_category_is_in_both_splits(library, category):
    names = [n for n in library.objects if library.objects[n].category == category]
    splits = {library.split_of(n) for n in names}
    assert names and (len(names) < 2 or splits == {"train", "test"})


@pytest.mark.parametrize("family", sorted(SUPPORT_FAMILIES))
def test_every_family_is_in_both_splits(library, family):
    names = [n for n in library.supports if library.supports[n].category == family]
    splits = {library.split_of(n) for n in names}
    assert names and (len(names) < 2 or splits == {"train", "test"})


def test_split_fraction_and_disjoint():
    n = 40
    held = held_out_indices(0, "object", "mug", n, 0.15)
    assert len(held) == 6 and len(set(held)) == 6 and all(0 <= i < n for i in held)
    assert held == held_out_indices(0, "object", "mug", n, 0.15)
    assert held != held_out_indices(1, "object", "mug", n, 0.15)
    assert held_out_indices(0, "object", "mug", 1, 0.15) == []  # a lone asset trains
    assert held_out_indices(0, "object", "mug", 3, 0.9) != [0, 1, 2]  # one always trains
    assert held_out_indices(0, "object", "mug", 10, 0.0) == []


def test_split_is_disjoint_and_complete(library):
    for group, table in (("objects", library.objects), ("supports", library.supports)):
        train, test = set(library.split["train"][group]), set(library.split["test"][group])
        assert not train & test
        assert train | test == set(table)
    check_split(library)


def test_check_split_catches_leaks():
    leaky = build_library(TINY, progress=False)
    leaked = leaky.split["train"]["objects"][0]
    leaky.split["test"]["objects"].append(leaked)
    with pytest.raises(ValueError, match=f"both train and test.*{leaked}"):
        check_split(leaky)

    twin = build_library(TINY, progress=False)
    test_name = twin.split["test"]["supports"][0]
    train_name = twin.split["train"]["supports"][0]
    # A renamed copy of a train shape in test is a leak too.
    twin.supports[test_name] = dataclasses.replace(twin.supports[train_name], name=test_name)
    with pytest.raises(ValueError, match="same shape"):
        check_split(twin)

    orphan = build_library(TINY, progress=False)
    orphan.split["train"]["objects"].pop()
    with pytest.raises(ValueError, match="in no split"):
        check_split(orphan)


def test_manifest_is_json_and_complete(library, tmp_path):
    manifest = library.manifest()
    assert json.loads(json.dumps(manifest)) == manifest
    records = manifest["objects"] + manifest["supports"]
    assert len(records) == TINY.n_objects + TINY.n_supports
    for record in records:
        asset = (library.objects if record["kind"] == "object" else library.supports)[
            record["name"]
        ]
        assert record["seed"] == asset.seed and record["n_parts"] == len(asset.parts)
        assert sum(record["part_kinds"].values()) == record["n_parts"]
        assert record["split"] == library.split_of(record["name"])
        assert 0 <= record["max_hull_vertices"] <= 32
        assert record["source"] == "procedural"
    library.save_manifest(tmp_path / "manifest.json")
    assert json.loads((tmp_path / "manifest.json").read_text()) == manifest


def test_sub_selection_and_unknown_category():
    category = sorted(OBJECT_CATEGORIES)[0]
    config = LibraryConfig(n_objects=5, n_supports=3, object_categories=(category,))
    lib = build_library(config, progress=False)
    assert lib.objects_per_category() == {category: 5}
    with pytest.raises(ValueError, match="unknown object category"):
        LibraryConfig(object_categories=("teapot",)).categories()


def test_meshes_are_lazy_and_cached(tmp_path):
    config = LibraryConfig(n_objects=2, n_supports=2, seed=3)
    lib = build_library(config, cache_dir=tmp_path, progress=False)
    assert all(a._mesh is None for a in lib.objects.values())  # nothing built yet
    lib.build_meshes(progress=False)
    assert len(list((tmp_path / "meshes").glob("*.npz"))) == 4
    again = build_library(config, cache_dir=tmp_path, progress=False)
    again.build_meshes(progress=False)
    for name, asset in lib.objects.items():
        np.testing.assert_array_equal(again.objects[name].mesh.vertices, asset.mesh.vertices)
        assert asset.mesh.is_watertight


def test_add_user_assets(tmp_path):
    lib = build_library(LibraryConfig(n_objects=2, n_supports=2), cache_dir=tmp_path)
    ring = trimesh.creation.torus(0.05, 0.012, major_sections=16, minor_sections=8)
    ring.apply_scale(1000.0)  # millimetres
    ring.export(tmp_path / "ring.stl")
    obj = lib.add_user_object(tmp_path / "ring.stl", scale=0.001, settings=decompose.FAST)
    assert obj.name in lib.split["test"]["objects"] and obj.category == "others"
    hook = trimesh.creation.box(extents=[0.04, 0.1, 0.01])
    hook.export(tmp_path / "hook.obj")
    sup = lib.add_user_support(
        tmp_path / "hook.obj", name="my_hook", split="train", settings=decompose.FAST
    )
    assert sup.name in lib.split["train"]["supports"] and sup.wall_y is not None
    assert list((tmp_path / "coacd").glob("*.npz"))  # the library's own CoACD cache
    check_split(lib)
    record = next(r for r in lib.manifest()["objects"] if r["name"] == obj.name)
    assert record["source"].endswith("ring.stl") and record["part_kinds"]["mesh"] >= 1
    with pytest.raises(ValueError, match="already"):
        lib.add_user_support(tmp_path / "hook.obj", name="my_hook", settings=decompose.FAST)
