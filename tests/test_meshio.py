"""User mesh loading: formats, clear errors, repairs, and the cached CoACD decomposition."""

from __future__ import annotations

import dataclasses
import logging

import coacd
import numpy as np
import pytest
import trimesh

from sim import decompose
from sim.assets.base import HangLoop, Peg
from sim.geometry import MAX_HULL_VERTICES, ConvexMesh
from sim.meshio import MeshError, load_user_mesh


def _torus() -> trimesh.Trimesh:
    """A 256-face torus, 12.4 cm across (a ring object, hangable through its hole)."""
    mesh = trimesh.creation.torus(
        major_radius=0.05, minor_radius=0.012, major_sections=16, minor_sections=8
    )
    mesh.apply_translation([0.3, -0.2, 1.0])  # off-centre, to check the centring
    return mesh


def _open_box() -> trimesh.Trimesh:
    """A 10 cm box with one triangle missing: not watertight."""
    box = trimesh.creation.box(extents=[0.1, 0.06, 0.04])
    return trimesh.Trimesh(box.vertices, box.faces[:-1], process=False)


@pytest.mark.parametrize("fmt", ["obj", "stl", "ply", "glb"])
def test_loads_each_format_centred(tmp_path, fmt):
    source = _torus()
    path = tmp_path / f"torus.{fmt}"
    source.export(path)
    mesh, report = load_user_mesh(path)
    assert len(mesh.faces) == len(source.faces)
    assert mesh.is_watertight and report["watertight"]
    np.testing.assert_allclose(mesh.bounds.mean(0), 0.0, atol=1e-6)  # bbox-centred
    np.testing.assert_allclose(report["centre"], [0.3, -0.2, 1.0], atol=1e-6)
    np.testing.assert_allclose(mesh.extents, source.extents, atol=1e-6)
    np.testing.assert_allclose(mesh.volume, source.volume, rtol=1e-5)
    assert report["format"] == fmt


def test_scene_is_concatenated_with_transforms(tmp_path):
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(extents=[0.05] * 3), node_name="a")
    scene.add_geometry(
        trimesh.creation.box(extents=[0.05] * 3),
        node_name="b",
        transform=trimesh.transformations.translation_matrix([0.2, 0, 0]),
    )
    path = tmp_path / "two.glb"
    scene.export(path)
    mesh, _ = load_user_mesh(path)
    np.testing.assert_allclose(mesh.extents, [0.25, 0.05, 0.05], atol=1e-6)
    assert len(mesh.faces) == 24


def test_target_size_and_scale(tmp_path):
    path = tmp_path / "mm.stl"
    big = _torus()
    big.apply_scale(1000.0)  # the same torus in millimetres
    big.export(path)
    with pytest.raises(MeshError, match="millimetres"):
        load_user_mesh(path)
    mesh, report = load_user_mesh(path, scale=0.001)
    assert mesh.extents.max() == pytest.approx(0.124, rel=1e-5)
    mesh, report = load_user_mesh(path, target_size=0.2)
    assert mesh.extents.max() == pytest.approx(0.2, rel=1e-9)
    assert report["scale"] == pytest.approx(0.2 / 124.0, rel=1e-5)


def test_y_up_files_are_turned_z_up(tmp_path):
    path = tmp_path / "tall.gltf"
    trimesh.creation.box(extents=[0.02, 0.3, 0.05]).export(path)  # tall along +y
    mesh, _ = load_user_mesh(path, up="y")
    np.testing.assert_allclose(mesh.extents, [0.02, 0.05, 0.3], atol=1e-6)


def _write(path, text):
    path.write_text(text)
    return path


TETRA = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


@pytest.mark.parametrize(
    "name, content, problem",
    [
        ("empty.obj", "", "empty"),
        ("points.obj", "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\n", "no triangles"),
        ("nan.obj", TETRA.replace("v 0 0.1 0", "v 0 nan 0"), "NaN or infinite"),
        ("inf.obj", TETRA.replace("v 0 0.1 0", "v 0 inf 0"), "NaN or infinite"),
        (
            "flat.obj",  # a unit square sheet, tilted: zero volume
            "v 0 0 0\nv 0.1 0 0.1\nv 0 0.1 0\nv 0.1 0.1 0.1\nf 1 2 3\nf 2 4 3\n",
            "flat",
        ),
        ("point.obj", "v 0.1 0.1 0.1\nv 0.1 0.1 0.1\nv 0.1 0.1 0.1\nf 1 2 3\n", "degenerate"),
        ("km.obj", TETRA.replace("0.1", "10000"), "absurd size"),
        ("tiny.obj", TETRA.replace("0.1", "0.001"), "absurd size"),
        ("broken.glb", "definitely not a glb file", "unreadable"),
        ("mesh.fbx", TETRA, "unsupported format"),
    ],
)
def test_bad_input_names_file_and_problem(tmp_path, name, content, problem):
    path = _write(tmp_path / name, content)
    with pytest.raises(MeshError, match=problem) as info:
        load_user_mesh(path)
    assert str(path) in str(info.value)


def test_missing_file(tmp_path):
    path = tmp_path / "nowhere.obj"
    with pytest.raises(MeshError, match="file not found") as info:
        load_user_mesh(path)
    assert str(path) in str(info.value)


def test_thin_but_solid_is_accepted(tmp_path):
    """A 1 mm thick blade is a real shape, not a degenerate one."""
    path = tmp_path / "blade.stl"
    trimesh.creation.box(extents=[0.2, 0.03, 0.001]).export(path)
    mesh, report = load_user_mesh(path)
    assert report["watertight"] and mesh.extents.min() == pytest.approx(0.001, rel=1e-5)


def test_repairs_winding_and_duplicates(tmp_path):
    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    faces = box.faces.copy()
    faces[[0, 5]] = faces[[0, 5]][:, ::-1]  # two faces wound the wrong way
    faces = np.concatenate([faces, faces[:1]])  # and a duplicate
    path = tmp_path / "messy.obj"
    trimesh.Trimesh(box.vertices, faces, process=False).export(path)
    mesh, report = load_user_mesh(path)
    assert report["duplicate_faces_removed"] >= 1
    assert report["winding_flipped"] > 0
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(1e-3, rel=1e-6)  # outward normals


def test_winding_is_repaired_beside_a_face_with_no_neighbour(tmp_path):
    """A lone triangle (its own component, nothing to agree with) beside a box with a face wound
    the wrong way: the box is repaired and the lone face left as it is (public meshes have both)."""
    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    faces = box.faces.copy()
    faces[0] = faces[0][::-1]
    lone = np.array([[0.2, 0.0, 0.0], [0.21, 0.0, 0.0], [0.2, 0.01, 0.0]])
    vertices = np.concatenate([box.vertices, lone])
    faces = np.concatenate([faces, [[8, 9, 10]]])
    path = tmp_path / "box_and_lone_face.obj"
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    mesh, report = load_user_mesh(path)
    assert report["winding_flipped"] > 0 and mesh.is_winding_consistent


def test_open_mesh_is_repaired(tmp_path):
    path = tmp_path / "open_box.obj"
    _open_box().export(path)
    mesh, report = load_user_mesh(path)
    assert report["holes_filled"] == 1 and report["watertight"]
    assert mesh.volume == pytest.approx(0.1 * 0.06 * 0.04, rel=1e-6)


def test_unrepairable_open_mesh_warns_and_decomposes(tmp_path, caplog):
    """An open cup surface (a big rim loop) stays open: a warning, and CoACD still copes."""
    cup = trimesh.creation.cylinder(radius=0.04, height=0.1, sections=12)
    top = cup.face_normals[:, 2] > 0.9
    path = tmp_path / "cup.ply"
    trimesh.Trimesh(cup.vertices, cup.faces[~top], process=False).export(path)
    with caplog.at_level(logging.WARNING, logger="sim.meshio"):
        mesh, report = load_user_mesh(path)
    assert not report["watertight"]
    assert "not watertight" in caplog.text and str(path) in caplog.text
    # A zero-thickness shell is CoACD's hardest case: a coarse threshold keeps it ~1 s.
    coarse = dataclasses.replace(decompose.FAST, threshold=0.2)
    result = decompose.decompose(mesh, coarse, tmp_path / "cache")
    assert result.hulls and all(len(h.vertices) <= MAX_HULL_VERTICES for h in result.hulls)


# ----------------------------------------------------------------------------- decomposition


def test_decomposition_is_cached(tmp_path, monkeypatch):
    mesh, _ = load_user_mesh(_export(_torus(), tmp_path / "torus.obj"))
    first = decompose.decompose(mesh, decompose.FAST, tmp_path)
    assert not first.stats["cache_hit"] and first.stats["seconds"] > 0
    assert len(first.hulls) >= 4  # a ring needs several convex pieces
    assert all(isinstance(h, ConvexMesh) for h in first.hulls)
    assert max(first.stats["hull_vertices"]) <= MAX_HULL_VERTICES
    assert first.stats["volume_kept"] > 0.97
    # The hulls cover the torus: its vertices lie inside (or on) the union of hulls.
    hull_meshes = [h.to_trimesh() for h in first.hulls]
    inside = np.zeros(len(mesh.vertices), bool)
    for h in hull_meshes:
        inside |= h.nearest.signed_distance(mesh.vertices) > -3e-3
    assert inside.mean() > 0.95

    def no_coacd(*args, **kwargs):
        raise AssertionError("CoACD ran although the result is cached")

    monkeypatch.setattr(coacd, "run_coacd", no_coacd)
    second = decompose.decompose(mesh, decompose.FAST, tmp_path)
    assert second.stats["cache_hit"]
    for a, b in zip(first.hulls, second.hulls, strict=True):
        np.testing.assert_array_equal(a.vertices, b.vertices)
    # Float noise below the key precision still hits; other settings miss.
    jittered = mesh.copy()
    jittered.vertices += 1e-9
    assert decompose.decompose(jittered, decompose.FAST, tmp_path).stats["cache_hit"]
    assert decompose.cache_key(mesh.vertices, mesh.faces, decompose.FAST) != decompose.cache_key(
        mesh.vertices, mesh.faces, decompose.CoacdSettings()
    )


def test_user_settings_keep_a_ring_open_without_remeshing(tmp_path):
    """The hang command's settings for user meshes (no manifold remeshing): the ring's hole stays
    free of hulls while its tube is covered, as with the library's settings."""
    assert decompose.PRESETS["user"] == decompose.USER and decompose.USER.preprocess_mode == "off"
    mesh, _ = load_user_mesh(_export(_torus(), tmp_path / "torus.obj"))
    result = decompose.decompose(mesh, decompose.USER, tmp_path)
    hulls = [h.to_trimesh() for h in result.hulls]
    major = 0.5 * (mesh.bounds[1, 0] - mesh.bounds[0, 0]) - 0.5 * mesh.extents[2]
    hole = np.array([[0.0, 0.0, 0.0], [0.3 * major, 0.0, 0.0], [0.0, -0.3 * major, 0.0]])
    tube = np.array([[major, 0.0, 0.0], [0.0, major, 0.0], [-major, 0.0, 0.0]])
    assert not any(h.contains(hole).any() for h in hulls)
    assert all(any(h.contains(p[None])[0] for h in hulls) for p in tube)


def test_corrupt_cache_is_reported_and_recomputed(tmp_path, caplog):
    mesh, _ = load_user_mesh(_export(_open_box(), tmp_path / "box.obj"))
    first = decompose.decompose(mesh, decompose.FAST, tmp_path)
    cache_file = tmp_path / f"{first.stats['key']}.npz"
    cache_file.write_bytes(cache_file.read_bytes()[:50])  # truncated write
    with caplog.at_level(logging.WARNING, logger="sim.decompose"):
        second = decompose.decompose(mesh, decompose.FAST, tmp_path)
    assert "corrupt" in caplog.text and str(cache_file) in caplog.text
    assert not second.stats["cache_hit"]
    assert decompose.decompose(mesh, decompose.FAST, tmp_path).stats["cache_hit"]
    assert not list(tmp_path.glob("*.tmp"))  # atomic writes leave no temporaries
    assert decompose.clear_cache(tmp_path) == 1


def test_default_cache_dir_follows_env(monkeypatch, tmp_path):
    monkeypatch.setenv("OMNIHANG_CACHE", str(tmp_path))
    assert decompose.default_cache_dir() == tmp_path / "coacd"


def test_convex_decompose_api(tmp_path):
    mesh, _ = load_user_mesh(_export(_torus(), tmp_path / "torus.stl"))
    hulls = decompose.convex_decompose(
        mesh, threshold=0.08, max_convex_hull=6, settings=decompose.FAST, cache_dir=tmp_path
    )
    assert 1 <= len(hulls) <= 6
    assert all(len(h.vertices) <= MAX_HULL_VERTICES for h in hulls)


def test_asset_from_user_mesh(tmp_path):
    path = _export(_torus(), tmp_path / "ring.obj")
    loop = HangLoop(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.03)
    obj = decompose.asset_from_user_mesh(
        path, "others", features=[loop], settings=decompose.FAST, cache_dir=tmp_path
    )
    assert obj.kind == "object" and obj.source == str(path) and obj.features == [loop]
    assert obj.name == "others_ring" and obj.seed == -1
    np.testing.assert_allclose(obj.extents, [0.124, 0.124, 0.024], atol=3e-3)
    assert obj.mesh.is_watertight  # the user mesh itself, not the union of hulls
    hook = decompose.asset_from_user_mesh(
        _export(_open_box(), tmp_path / "stand.stl"),
        "user",
        "support",
        wall=False,
        features=[Peg(np.zeros(3), np.array([0.0, 0.0, 0.05]), 0.005)],
        settings=decompose.FAST,
        cache_dir=tmp_path,
    )
    assert hook.wall_y is None and hook.ground_parts
    assert hook.floor_z == pytest.approx(hook.bounds()[0, 2])
    with pytest.raises(TypeError):
        decompose.asset_from_user_mesh(
            path, "user", "support", features=[loop], settings=decompose.FAST, cache_dir=tmp_path
        )


def _export(mesh: trimesh.Trimesh, path):
    mesh.export(path)
    return path
