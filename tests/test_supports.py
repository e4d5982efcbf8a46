"""Supporting-item families: one watertight body at real size, pegs on capsule axes, mounts.

Parametrised over every registered family, so a new family is tested once registered.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from scipy.spatial import ConvexHull

import sim.assets.supports  # noqa: F401  (registers the families)
from sim import geometry as g
from sim.assets.base import SUPPORT_FAMILIES, Asset, build_support

FAMILIES = sorted(SUPPORT_FAMILIES)
MESH_SEEDS = range(8)  # seeds whose union mesh is built (about 10-30 ms each)
SEEDS = range(32)  # seeds checked on their parts only
AXIS_TOL = 1e-6  # metres: a peg lies on its capsule's axis up to rounding
FREE_PROBE = 0.01  # metres beyond an open peg's tip that must be empty space
MOUNT_PROBE = 0.001  # metres either side of a peg's base: inside the mount / free rod
MAX_PARTS = 12  # static supports stay cheap to collide
MAX_TILT_DEG = 40.0

# Real sizes: rod radius, free peg length, bounding-box extent ranges (metres, per axis or None).
SIZES = {
    "single_rod_hook": dict(radius=(0.0025, 0.008), length=(0.04, 0.20)),
    "two_rod_hook": dict(radius=(0.0025, 0.008), length=(0.04, 0.20)),
    "towel_bar": dict(radius=(0.0025, 0.010), length=(0.15, 0.60), x=(0.25, 0.60)),
    "mug_tree": dict(radius=(0.0025, 0.008), length=(0.04, 0.20), z=(0.25, 0.45)),
    "pegboard_hook": dict(radius=(0.002, 0.004), length=(0.04, 0.20)),
    "coat_rack_knob": dict(radius=(0.004, 0.006), length=(0.04, 0.10), x=(0.10, 0.60)),
}
DEFAULT_SIZE = dict(radius=(0.002, 0.012), length=(0.04, 0.60))


@functools.cache
def _asset(family: str, seed: int) -> Asset:
    return build_support(family, seed)


def _segment_distance(points: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """[N] distance of ``points`` [N, 3] to the segment p0-p1."""
    axis = p1 - p0
    t = np.clip((points - p0) @ axis / max(axis @ axis, 1e-30), 0.0, 1.0)
    return np.linalg.norm(points - (p0 + t[:, None] * axis), axis=1)


def _inside_part(part: g.Part, point: np.ndarray) -> bool:
    """Whether ``point`` [3] lies strictly inside the exact (not tessellated) part."""
    if isinstance(part, g.Capsule):
        return bool(_segment_distance(point[None], part.p0, part.p1)[0] < part.radius)
    if isinstance(part, g.Box):
        local = part.rotation.T @ (point - part.center)
        return bool(np.all(np.abs(local) < part.half_size))
    eq = ConvexHull(part.vertices).equations
    return bool(np.all(eq[:, :3] @ point + eq[:, 3] < 0.0))


def _peg_capsule(asset: Asset, peg) -> int:
    """Index of a capsule part of the peg's radius whose axis holds the whole peg, or -1."""
    probes = peg.base + np.linspace(0.0, 1.0, 11)[:, None] * (peg.tip - peg.base)
    for i, part in enumerate(asset.parts):
        if isinstance(part, g.Capsule) and abs(part.radius - peg.radius) < 1e-12:
            if _segment_distance(probes, part.p0, part.p1).max() < AXIS_TOL:
                return i
    return -1


def _direction(peg) -> np.ndarray:
    d = peg.tip - peg.base
    return d / np.linalg.norm(d)


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("seed", MESH_SEEDS)
def test_single_watertight_body(family, seed):
    mesh = _asset(family, seed).mesh
    assert mesh.is_watertight
    assert mesh.body_count == 1
    assert mesh.volume > 0.0


@pytest.mark.parametrize("family", FAMILIES)
def test_parts_small_and_finite(family):
    for seed in SEEDS:
        asset = _asset(family, seed)
        assert 1 <= len(asset.parts) <= MAX_PARTS, (seed, len(asset.parts))
        for part in asset.parts:
            arrays = [np.asarray(v, float) for v in vars(part).values()]
            assert all(np.all(np.isfinite(a)) for a in arrays), (seed, part)
            if isinstance(part, g.ConvexMesh):
                assert len(part.vertices) <= g.MAX_HULL_VERTICES
            if isinstance(part, g.Capsule):
                assert part.radius > 0.0
        assert asset.features, seed
        for peg in asset.features:
            assert np.all(np.isfinite(peg.base)) and np.all(np.isfinite(peg.tip))
        assert np.all(np.isfinite(asset.bounds()))


@pytest.mark.parametrize("family", FAMILIES)
def test_real_sizes(family):
    size = SIZES.get(family, DEFAULT_SIZE)
    for seed in SEEDS:
        asset = _asset(family, seed)
        for peg in asset.features:
            lo, hi = size["radius"]
            assert lo - 1e-12 <= peg.radius <= hi + 1e-12, (seed, peg.radius)
            length = float(np.linalg.norm(peg.tip - peg.base))
            lo, hi = size["length"]
            assert lo <= length <= hi, (seed, length)
            tilt = np.rad2deg(np.arcsin(_direction(peg)[2]))
            assert -1e-6 <= tilt <= MAX_TILT_DEG + 1e-6, (seed, tilt)
        for axis, name in enumerate("xyz"):
            if name in size:
                lo, hi = size[name]
                assert lo <= asset.extents[axis] <= hi, (seed, name, asset.extents)
        assert asset.extents.max() < 0.65


@pytest.mark.parametrize("family", FAMILIES)
def test_deterministic_from_seed(family):
    for seed in (0, 7):
        a, b = build_support(family, seed), build_support(family, seed)
        assert a.params == b.params
        assert len(a.parts) == len(b.parts)
        for pa, pb in zip(a.parts, b.parts):
            assert type(pa) is type(pb)
            for va, vb in zip(vars(pa).values(), vars(pb).values()):
                np.testing.assert_array_equal(va, vb)
        for fa, fb in zip(a.features, b.features):
            np.testing.assert_array_equal(fa.base, fb.base)
            np.testing.assert_array_equal(fa.tip, fb.tip)


@pytest.mark.parametrize("family", FAMILIES)
def test_variety_over_seeds(family):
    assets = [_asset(family, seed) for seed in SEEDS]
    extents = np.stack([a.extents for a in assets])
    assert np.all(extents.std(0) > 1e-3), extents.std(0)
    for key in assets[0].params:
        values = {repr(a.params.get(key)) for a in assets}
        assert len(values) >= 2, (key, values)
    assert len({len(a.parts) for a in assets}) >= 2


@pytest.mark.parametrize("family", FAMILIES)
def test_pegs_on_capsule_axes(family):
    for seed in SEEDS:
        asset = _asset(family, seed)
        for peg in asset.features:
            assert _peg_capsule(asset, peg) >= 0, (seed, peg)


@pytest.mark.parametrize("family", FAMILIES)
def test_peg_base_at_mount_and_open_tips_free(family):
    """Just behind the base is mount, just after it free rod; 1 cm past an open tip is empty."""
    for seed in SEEDS:
        asset = _asset(family, seed)
        for peg in asset.features:
            own = _peg_capsule(asset, peg)
            others = [p for i, p in enumerate(asset.parts) if i != own]
            d = _direction(peg)
            ends = [(peg.base, d)] + ([(peg.tip, -d)] if peg.closed else [])
            for end, inward in ends:
                behind, ahead = end - MOUNT_PROBE * inward, end + MOUNT_PROBE * inward
                assert any(_inside_part(p, behind) for p in others), (seed, "base not mounted")
                assert not any(_inside_part(p, ahead) for p in others), (seed, "rod not free")
            if not peg.closed:
                beyond = peg.tip + FREE_PROBE * d
                assert not any(_inside_part(p, beyond) for p in asset.parts), (seed, "tip")


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("seed", MESH_SEEDS)
def test_pegs_against_mesh(family, seed):
    """The union mesh holds the peg's middle and leaves 1 cm past an open tip empty."""
    asset = _asset(family, seed)
    probes, expected = [], []
    for peg in asset.features:
        probes.append(0.5 * (peg.base + peg.tip))
        expected.append(True)
        if not peg.closed:
            probes.append(peg.tip + FREE_PROBE * _direction(peg))
            expected.append(False)
    np.testing.assert_array_equal(asset.mesh.contains(np.array(probes)), expected)


@pytest.mark.parametrize("family", FAMILIES)
def test_mounting(family):
    """Wall items: flat backplate on the wall plane, nothing behind it, rods clear of the wall,
    open pegs reaching out. Free-standing items: the ground parts hold the lowest z."""
    for seed in SEEDS:
        asset = _asset(family, seed)
        spec_wall = asset.wall_y is not None
        if spec_wall:
            assert not asset.ground_parts
            wall_y = asset.wall_y
            on_wall = 0
            for part in asset.parts:
                pts = part.support_points()
                assert pts[:, 1].min() >= wall_y - 1e-9, (seed, "behind the wall")
                if isinstance(part, g.Capsule):
                    assert pts[:, 1].min() > wall_y + 1e-4, (seed, "rod touches the wall")
                elif np.sum(np.abs(pts[:, 1] - wall_y) < 1e-9) >= 3:
                    on_wall += 1
            assert on_wall >= 1, (seed, "no flat backplate on the wall")
            assert asset.floor_z < asset.bounds()[0, 2]
            for peg in asset.features:
                if not peg.closed:
                    assert peg.tip[1] - peg.base[1] > 0.02, (seed, "peg does not reach out")
        else:
            assert asset.ground_parts
            low = asset.bounds()[0, 2]
            assert abs(asset.floor_z - low) < 1e-12
            for i, part in enumerate(asset.parts):
                part_low = part.support_points()[:, 2].min()
                if i in asset.ground_parts:
                    assert abs(part_low - low) < 1e-9, (seed, "ground part off the floor")
                else:
                    assert part_low > low + 1e-4, (seed, i, "non-ground part on the floor")
            for peg in asset.features:
                assert peg.tip[2] > low + 0.05


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("seed", MESH_SEEDS)
def test_mesh_on_the_wall(family, seed):
    asset = _asset(family, seed)
    bounds = asset.mesh.bounds
    if asset.wall_y is not None:
        assert abs(bounds[0, 1] - asset.wall_y) < 1e-6
    else:
        assert abs(bounds[0, 2] - asset.floor_z) < 1e-6
