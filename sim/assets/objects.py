"""Procedural generators for the 11 object categories of the paper.

Each generator takes a ``numpy.random.Generator`` and returns an :class:`AssetSpec` of convex
parts at real size (metres) plus the :class:`HangLoop` features the object hangs by. Shapes vary
widely within a category (sizes, proportions, hole placement, thickness).
"""

from __future__ import annotations

import numpy as np

from sim import geometry as g
from sim.assets.base import AssetSpec, HangLoop, register_object


@register_object("mug")
def mug(rng: np.random.Generator) -> AssetSpec:
    """A mug: solid body (cylinder or tapered) and a C-shaped handle tube on its side.

    Hangs by the handle opening (axis = the handle plane's normal, +y).
    """
    radius = rng.uniform(0.03, 0.05)
    height = rng.uniform(0.07, 0.12)
    taper = rng.uniform(0.8, 1.1)  # top radius / bottom radius
    tube_r = rng.uniform(0.004, 0.007)
    handle_reach = rng.uniform(0.025, 0.04)  # how far the handle sticks out of the body
    handle_h = rng.uniform(0.45, 0.75) * height  # vertical span of the handle
    handle_z = rng.uniform(-0.1, 0.1) * height  # handle centre height relative to body centre
    body = g.frustum([0, 0, -height / 2], [0, 0, height / 2], radius, radius * taper, sides=14)
    x_wall = radius * (1 + taper) / 2 - 0.5 * tube_r  # attach slightly inside the body wall
    # C-shaped handle: a half-ellipse from the top attachment to the bottom one, in the xz-plane.
    ang = np.linspace(np.pi / 2, -np.pi / 2, 7)
    pts = np.stack(
        [
            x_wall + handle_reach * np.cos(ang),
            np.zeros_like(ang),
            handle_z + handle_h / 2 * np.sin(ang),
        ],
        axis=1,
    )
    handle = g.tube(pts, tube_r)
    free = min(handle_reach, handle_h / 2) - tube_r
    loop_centre = [x_wall + 0.5 * handle_reach, 0.0, handle_z]
    return AssetSpec(
        parts=[body, *handle],
        features=[
            HangLoop(
                np.array(loop_centre),
                np.array([0.0, 1.0, 0.0]),
                0.5 * free + 0.5 * (handle_reach - tube_r) * 0.5,
            )
        ],
        params=dict(
            radius=radius, height=height, taper=taper, tube_radius=tube_r, handle_reach=handle_reach
        ),
    )
