"""The asset showcase job end to end on a tiny library, and the headless renderer."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from experiments import assets as job
from sim import render
from sim.assets.base import OBJECT_CATEGORIES, SUPPORT_FAMILIES, build_object, build_support
from sim.library import build_library  # noqa: F401  (registers every category and family)
from sim.scene import build_scene

TINY_JOB = ["--n-objects", "22", "--n-supports", "10", "--hangs", "2", "--per-row", "2"]


def _non_trivial(path) -> np.ndarray:
    image = np.asarray(Image.open(path).convert("RGB"))
    assert image.shape[0] > 50 and image.shape[1] > 50, image.shape
    colours = np.unique(image.reshape(-1, 3), axis=0)
    assert len(colours) > 20, f"{path} has only {len(colours)} colours"
    return image


def test_job_writes_counts_pictures_and_scene(tmp_path):
    summary = job.main(["--out", str(tmp_path), "--quick", "--no-progress", *TINY_JOB])
    data = json.loads((tmp_path / "assets.json").read_text())
    assert data == json.loads(json.dumps(summary))
    assert sum(data["objects_per_category"].values()) == 22
    assert sum(data["supports_per_family"].values()) == 10
    assert set(data["objects_per_category"]) == set(OBJECT_CATEGORIES)
    assert set(data["supports_per_family"]) == set(SUPPORT_FAMILIES)
    split = data["split"]
    assert split["train"]["objects"] + split["test"]["objects"] == 22
    assert split["train"]["supports"] + split["test"]["supports"] == 10
    dec = data["decomposition"]
    assert set(dec["objects"]) == set(OBJECT_CATEGORIES)
    assert dec["n_needing_coacd"] == 0  # procedural assets are convex parts already
    assert dec["parts_max"] >= dec["parts_mean"] >= 1
    assert {"python", "mujoco", "numpy"} <= set(data["versions"])
    assert {"library", "contact_sheet", "total"} <= set(data["timings_s"])

    hangs = json.loads((tmp_path / "hangs.json").read_text())["pairs"]
    assert len(hangs) == 2
    for pair in hangs:
        assert {"object", "support", "pose", "status", "takeoff"} <= set(pair)
        assert len(pair["pose"]) == 7 and pair["status"] in (
            "stable",
            "fallen",
            "penetrating",
            "diverged",
        )
    assert any(p["stable"] for p in hangs), hangs  # hang proposals find a stable pose

    sheet = _non_trivial(tmp_path / "contact_sheet.png")
    rows = len(OBJECT_CATEGORIES) + len(SUPPORT_FAMILIES)
    assert sheet.shape[0] > rows * 96  # one row of 96-pixel renders per category and family
    _non_trivial(tmp_path / "hangs.png")
    assert (tmp_path / "example_scene" / "scene.xml").exists()


@pytest.mark.parametrize("category", sorted(OBJECT_CATEGORIES))
def test_render_asset_shows_every_object_category(category):
    image = render.render_asset(build_object(category, 0), 64, 64)
    assert image.shape == (64, 64, 3) and image.dtype == np.uint8
    covered = (image < 250).any(axis=2).mean()
    assert 0.03 < covered < 0.95, covered  # the asset is in view, and not clipped to fill it
    assert (image[0, 0] == 255).all()  # background is white


@pytest.mark.parametrize("family", sorted(SUPPORT_FAMILIES))
def test_render_asset_shows_every_support_family(family):
    image = render.render_asset(build_support(family, 0), 64, 64)
    covered = (image < 250).any(axis=2).mean()
    assert 0.01 < covered < 0.95, covered


def test_render_scene_colours_object_and_support_apart():
    obj = build_object(sorted(OBJECT_CATEGORIES)[0], 0)
    support = build_support(sorted(SUPPORT_FAMILIES)[0], 0)
    scene = build_scene(obj, support)
    lo, hi = scene.support_bounds
    pose = np.array([0.5 * (lo[0] + hi[0]), hi[1] + 0.3, 0.5 * (lo[2] + hi[2]), 1, 0, 0, 0])
    image = render.render_scene(scene, pose, 96, 80).reshape(-1, 3).astype(float)

    def share(rgb):  # pixels whose hue is that colour's (any shading)
        rgb = np.asarray(rgb)
        unit = image / np.maximum(np.linalg.norm(image, axis=1, keepdims=True), 1e-9)
        return (unit @ (rgb / np.linalg.norm(rgb)) > 0.995).mean()

    assert share(render.OBJECT_RGB) > 0.005
    assert share(render.SUPPORT_RGB) > 0.005
    assert np.linalg.norm(np.subtract(render.OBJECT_RGB, render.SUPPORT_RGB)) > 0.3


def test_contact_sheet_has_a_row_per_group(tmp_path):
    groups = {"a": [build_object(sorted(OBJECT_CATEGORIES)[0], s) for s in range(2)]}
    groups["b"] = [build_support(sorted(SUPPORT_FAMILIES)[0], 0)]
    sheet = render.contact_sheet(groups, tmp_path / "sheet.png", per_row=3, size=48)
    assert (tmp_path / "sheet.png").exists()
    assert sheet.height >= 2 * 48
