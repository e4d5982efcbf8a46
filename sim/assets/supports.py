"""Procedural generators for supporting-item families, mounted as in real homes.

Wall-mounted items have a backplate whose back face is the wall (the lowest y of all parts)
and reach out towards +y; free-standing items stand on a base at their lowest z.
"""

from __future__ import annotations

import numpy as np

from sim import geometry as g
from sim.assets.base import AssetSpec, Peg, register_support


def _backplate(rng: np.random.Generator, width: float, height: float, thick: float):
    return g.box([0.0, thick / 2, 0.0], [width / 2, thick / 2, height / 2])


@register_support("single_rod_hook")
def single_rod_hook(rng: np.random.Generator) -> AssetSpec:
    """One rod out of a wall plate: straight, angled up, or with an upturned J tip."""
    style = rng.choice(["straight", "angled", "j_tip"])
    thick = rng.uniform(0.008, 0.015)
    plate = _backplate(rng, rng.uniform(0.03, 0.06), rng.uniform(0.05, 0.1), thick)
    rod_r = rng.uniform(0.003, 0.007)
    length = rng.uniform(0.08, 0.16)
    tilt = np.deg2rad(rng.uniform(10, 35)) if style == "angled" else np.deg2rad(rng.uniform(0, 6))
    base = np.array([0.0, thick, 0.0])
    tip = base + length * np.array([0.0, np.cos(tilt), np.sin(tilt)])
    parts = [plate, g.capsule(base, tip, rod_r)]
    if style == "j_tip":
        up = rng.uniform(0.015, 0.03)
        parts.append(g.capsule(tip, tip + [0.0, 0.005, up], rod_r))
    return AssetSpec(
        parts=parts,
        features=[Peg(base, tip, rod_r)],
        params=dict(
            style=str(style), rod_radius=rod_r, length=length, tilt_deg=float(np.rad2deg(tilt))
        ),
    )
