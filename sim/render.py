"""Headless CPU pictures of assets and scenes, by ray casting (no OpenGL, no display).

Every pixel casts one ray through :func:`sim.camera.cast` (``mujoco.mj_multiRay``), which
returns the first geom hit and its surface normal (pixels on a boundary between geoms cast
``supersample``^2 rays, averaged: adaptive anti-aliasing); a hit is shaded Lambertian::

    colour = base * (AMBIENT + KEY * max(0, n . l_key) + HEAD * max(0, -n . ray))

with a key light from above the camera's left shoulder and a weak head light (so
faces turned from the key light are never black). Misses are white. The camera is the
pinhole of :mod:`sim.camera` at the distance where the body's bounding sphere fits the
field of view (:func:`sim.camera.camera_distance`), so a picture never clips its subject.

- :func:`render_asset`: one object or supporting item alone, coloured by its category.
- :func:`render_scene`: a pair scene at an object pose: object, supporting item, and the
  wall and floor faint (geom groups of :mod:`sim.scene`).
- :func:`contact_sheet`: a labelled grid PNG, one row per category / family.

A 160 x 160 picture costs about 25,600 rays plus ~9 per boundary pixel: 10-50 ms on one CPU
core for our assets (the most for the caps' many hulls).
"""

from __future__ import annotations

import colorsys
import dataclasses
import hashlib
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import mujoco
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from sim import camera
from sim.assets.base import Asset
from sim.geometry import ConvexMesh
from sim.scene import ENV_GROUP, OBJECT_GROUP, PARK_HEIGHT, SUPPORT_GROUP, Scene, _geom_xml

OBJECT_RGB = (0.86, 0.42, 0.12)  # orange: the object in scene renders
SUPPORT_RGB = (0.22, 0.42, 0.78)  # blue: the supporting item
ENV_RGB = (0.93, 0.93, 0.91)  # wall and floor: faint, behind everything
SUPPORT_VIEW = (0.55, 1.0, 0.45)  # front (+y, away from the wall), right and above
SCENE_VIEW = (0.75, 1.0, 0.35)


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    fovy_deg: float = 40.0  # narrower than the depth camera's 60: less perspective distortion
    fit_margin: float = 1.05  # bounding sphere / field of view
    supersample: int = 3  # rays per pixel side on geom boundaries (adaptive anti-aliasing)
    ambient: float = 0.35  # light every surface gets
    key: float = 0.55  # key light weight (direction relative to the camera: KEY_LIGHT)
    head: float = 0.25  # head light weight (along the view ray)


# Direction towards the key light in the camera frame (right, down, forward): upper left,
# on the camera's side of the subject.
KEY_LIGHT = (-0.5, -0.8, -0.6)


# Distinct, mid-saturation colours for the rows of a contact sheet (Tableau 10, then more).
PALETTE = (
    (0.12, 0.47, 0.71),
    (1.00, 0.50, 0.05),
    (0.17, 0.63, 0.17),
    (0.84, 0.15, 0.16),
    (0.58, 0.40, 0.74),
    (0.55, 0.34, 0.29),
    (0.89, 0.47, 0.76),
    (0.50, 0.50, 0.50),
    (0.74, 0.74, 0.13),
    (0.09, 0.75, 0.81),
    (0.60, 0.35, 0.60),
    (0.30, 0.60, 0.55),
    (0.95, 0.70, 0.20),
    (0.40, 0.45, 0.80),
    (0.80, 0.35, 0.45),
    (0.45, 0.65, 0.30),
    (0.25, 0.30, 0.45),
    (0.85, 0.55, 0.40),
)


def category_colour(name: str) -> tuple[float, float, float]:
    """A stable, saturated RGB in [0, 1] for a category or family name (hash -> hue)."""
    hue = int.from_bytes(hashlib.sha256(name.encode()).digest()[:2], "little") / 65536.0
    return colorsys.hsv_to_rgb(hue, 0.55, 0.85)


# ----------------------------------------------------------------------------- models


def asset_model(asset: Asset) -> mujoco.MjModel:
    """A static MjModel holding just ``asset``'s convex parts (one geom each, group 1)."""
    mesh_ref: dict[str, str] = {}
    meshes, geoms = [], []
    for i, part in enumerate(asset.parts):
        name = f"part_{i}"
        if isinstance(part, ConvexMesh):
            mesh_ref[name] = f"{name}_mesh"
            verts = " ".join(f"{x:.7g}" for x in np.ravel(part.vertices))
            meshes.append(f'<mesh name="{name}_mesh" vertex="{verts}"/>')
        # the part -> geom mapping of the physics scenes, so pictures show what is simulated
        geoms.append(_geom_xml(part, name, OBJECT_GROUP, "", mesh_ref))
    xml = f"""<mujoco model="{asset.name}">
  <asset>{"".join(meshes)}</asset>
  <worldbody>{"".join(geoms)}</worldbody>
</mujoco>"""
    return mujoco.MjModel.from_xml_string(xml)


# ----------------------------------------------------------------------------- ray tracing


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _pixel_rays(eye, target, width: int, height: int, fovy_deg: float, u, v) -> np.ndarray:
    """[R, 3] unit world rays through the pixel coordinates ``u`` (column) and ``v`` (row),
    [R] floats with pixel centres at ``i + 0.5``: the pinhole of
    :func:`sim.camera.camera_rays`, at arbitrary (sub-pixel) positions."""
    f = 0.5 * height / np.tan(np.deg2rad(fovy_deg) / 2)
    local = np.stack([(u - width / 2) / f, (v - height / 2) / f, np.ones_like(u)], axis=1)
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    return local @ camera.look_at(eye, target).T


def _shade(model, data, eye, dirs, to_light, groups, config: RenderConfig):
    """Geom ids [R] (-1: miss) and Lambertian intensities [R] of the rays ``dirs`` [R, 3]."""
    geomid, _, n = camera.cast(model, data, eye, dirs, groups, True, 1e3)
    facing = np.sum(n * dirs, axis=1)
    n = np.where((facing > 0)[:, None], -n, n)  # seen from inside a hull: light the face we see
    shade = (
        config.ambient
        + config.key * np.clip(n @ to_light, 0.0, None)
        + config.head * np.abs(facing)
    )
    return geomid, shade


def _raytrace(model, data, eye, target, width, height, groups, colour_fn, config: RenderConfig):
    """[height, width, 3] uint8 image; ``colour_fn(geomid [R], shade [R]) -> rgb [R, 3]`` in
    [0, 1] colours each ray (white for misses).

    Anti-aliasing is adaptive: one ray per pixel, then ``supersample``^2 rays for the pixels
    on a boundary between geoms (or geom and background) only, averaged. Boundaries are a
    small fraction of the pixels, so this costs little more than one ray per pixel.
    """
    to_light = camera.look_at(eye, target) @ _unit(KEY_LIGHT)
    v, u = np.mgrid[0:height, 0:width] + 0.5
    dirs = _pixel_rays(eye, target, width, height, config.fovy_deg, u.ravel(), v.ravel())
    geomid, shade = _shade(model, data, eye, dirs, to_light, groups, config)
    rgb = colour_fn(geomid, shade).reshape(height, width, 3)
    s = int(config.supersample)
    if s > 1:
        g = geomid.reshape(height, width)
        edge = np.zeros_like(g, dtype=bool)
        dx, dy = g[:, 1:] != g[:, :-1], g[1:, :] != g[:-1, :]
        edge[:, 1:] |= dx
        edge[:, :-1] |= dx
        edge[1:, :] |= dy
        edge[:-1, :] |= dy
        ys, xs = np.nonzero(edge)
        if len(ys):
            offs = (np.arange(s) + 0.5) / s
            su = np.broadcast_to(xs[:, None, None] + offs[None, None, :], (len(xs), s, s))
            sv = np.broadcast_to(ys[:, None, None] + offs[None, :, None], (len(ys), s, s))
            sub = _pixel_rays(eye, target, width, height, config.fovy_deg, su.ravel(), sv.ravel())
            sub_id, sub_shade = _shade(model, data, eye, sub, to_light, groups, config)
            rgb[ys, xs] = colour_fn(sub_id, sub_shade).reshape(len(ys), s * s, 3).mean(axis=1)
    return np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)


def _eye_for(center: np.ndarray, radius: float, view_dir, config: RenderConfig) -> np.ndarray:
    cam = camera.CameraConfig(
        width=1, height=1, fovy_deg=config.fovy_deg, fit_margin=config.fit_margin
    )
    return center + camera.camera_distance(radius, cam) * _unit(view_dir)


def default_view(asset: Asset) -> np.ndarray:
    """A 3/4 view: supports from the front (away from the wall); objects looking mostly
    along their thinnest axis (flat tools and loops show their outline and opening)."""
    if asset.kind == "support":
        return _unit(SUPPORT_VIEW)
    ext = asset.extents
    thin = int(np.argmin(ext))
    view = np.full(3, 0.35)
    view[thin] = 1.0
    if thin != 2:
        view[2] = 0.5  # and a little from above
    return _unit(view)


def render_asset(
    asset: Asset,
    width: int = 160,
    height: int = 160,
    view_dir=None,
    rgb: Sequence[float] | None = None,
    config: RenderConfig = RenderConfig(),
    model: mujoco.MjModel | None = None,
) -> np.ndarray:
    """[height, width, 3] uint8 picture of ``asset`` alone on white.

    ``view_dir`` [3]: direction from the asset's centre towards the camera (asset frame);
    None picks :func:`default_view`. ``rgb``: base colour in [0, 1] (default: the
    category's colour). ``model``: a prebuilt :func:`asset_model` to skip compiling.
    """
    model = asset_model(asset) if model is None else model
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    lo, hi = asset.bounds()
    center = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    view = default_view(asset) if view_dir is None else view_dir
    eye = _eye_for(center, radius, view, config)
    base = np.asarray(category_colour(asset.category) if rgb is None else rgb, float)

    def colour(geomid, shade):
        return np.where((geomid >= 0)[:, None], shade[:, None] * base, 1.0)

    return _raytrace(model, data, eye, center, width, height, (OBJECT_GROUP,), colour, config)


def scene_view_bounds(scene: Scene, pose: np.ndarray) -> np.ndarray:
    """[2, 3] world bounds of the supporting item together with the object at ``pose``."""
    from sim.kernels import object_boxes  # kernels import scipy; keep render import light

    box = object_boxes(scene, np.asarray(pose, float)[None])[0]
    sb = scene.support_bounds
    return np.stack([np.minimum(box[0], sb[0]), np.maximum(box[1], sb[1])])


def render_scene(
    scene: Scene,
    pose: np.ndarray | None,
    width: int = 320,
    height: int = 240,
    view_dir=SCENE_VIEW,
    config: RenderConfig = RenderConfig(),
    object_rgb: Sequence[float] = OBJECT_RGB,
    support_rgb: Sequence[float] = SUPPORT_RGB,
    env_rgb: Sequence[float] = ENV_RGB,
) -> np.ndarray:
    """[height, width, 3] uint8 picture of the pair scene with the object at ``pose`` [7]
    (None: parked out of view), framed on the supporting item and the object.

    The object is ``object_rgb``, the supporting item ``support_rgb``, wall and floor
    ``env_rgb`` with a flat, faint shading.
    """
    model = scene.model
    data = mujoco.MjData(model)
    data.qpos[:7] = [0, 0, PARK_HEIGHT, 1, 0, 0, 0] if pose is None else pose
    mujoco.mj_kinematics(model, data)
    bounds = scene.support_bounds if pose is None else scene_view_bounds(scene, pose)
    center = 0.5 * (bounds[0] + bounds[1])
    radius = 0.5 * float(np.linalg.norm(bounds[1] - bounds[0]))
    eye = _eye_for(center, radius, view_dir, config)
    groups = (OBJECT_GROUP, SUPPORT_GROUP, ENV_GROUP)
    palette = np.ones((max(4, ENV_GROUP + 1), 3))
    palette[OBJECT_GROUP] = object_rgb
    palette[SUPPORT_GROUP] = support_rgb
    palette[ENV_GROUP] = env_rgb

    def colour(geomid, shade):
        group = np.where(geomid >= 0, model.geom_group[np.maximum(geomid, 0)], -1)
        # wall and floor: only a hint of shading, so they read as background
        shade = np.where(group == ENV_GROUP, 0.85 + 0.15 * np.clip(shade, 0, 1), shade)
        rgb = shade[:, None] * palette[np.maximum(group, 0)]
        return np.where((group >= 0)[:, None], rgb, 1.0)

    return _raytrace(model, data, eye, center, width, height, groups, colour, config)


# ----------------------------------------------------------------------------- sheets


def _font(size: int) -> ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1 has only the fixed bitmap font
        return ImageFont.load_default()


def contact_sheet(
    assets_by_group: Mapping[str, Sequence[Asset]],
    path: str | os.PathLike,
    per_row: int = 6,
    size: int = 160,
    config: RenderConfig = RenderConfig(),
    progress: bool = False,
) -> Image.Image:
    """Write a labelled grid PNG to ``path``: one row per group (object category or support
    family, in the mapping's order) with up to ``per_row`` renders of ``size`` pixels.

    Each cell is captioned with the asset's name; the row label gives the group and its
    kind. Rows take the colours of :data:`PALETTE` in turn. Returns the PIL image.
    """
    from tqdm.auto import tqdm

    groups = [(g, list(a)[:per_row]) for g, a in assets_by_group.items()]
    label_w, caption_h, pad = 150, 16, 4
    cell_w, cell_h = size + pad, size + caption_h + pad
    sheet = Image.new(
        "RGB", (label_w + per_row * cell_w + pad, max(1, len(groups)) * cell_h + pad), "white"
    )
    draw = ImageDraw.Draw(sheet)
    label_font, caption_font = _font(15), _font(11)
    total = sum(len(a) for _, a in groups)
    bar = tqdm(total=total, desc="contact sheet", disable=not progress)
    for r, (group, assets) in enumerate(groups):
        y = pad + r * cell_h
        kind = assets[0].kind if assets else ""
        draw.text((6, y + size // 2 - 16), group, fill=(0, 0, 0), font=label_font)
        draw.text((6, y + size // 2 + 2), kind, fill=(110, 110, 110), font=caption_font)
        rgb = PALETTE[r % len(PALETTE)]
        for c, asset in enumerate(assets):
            x = label_w + c * cell_w
            image = render_asset(asset, size, size, rgb=rgb, config=config)
            sheet.paste(Image.fromarray(image), (x, y))
            draw.text((x + 2, y + size + 1), asset.name, fill=(60, 60, 60), font=caption_font)
            bar.update()
        if r:  # thin separator between rows
            draw.line([(4, y - pad // 2), (sheet.width - 4, y - pad // 2)], fill=(225, 225, 225))
    bar.close()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(path)
    return sheet
