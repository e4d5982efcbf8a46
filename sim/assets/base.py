"""Asset records and the registry of procedural categories (objects) and families (supports).

Frames
------
- Object frame: origin at the centre of the object's axis-aligned bounding box (as the
  original code centred its meshes), axes as the generator built them.
- Support frame (= world frame in every scene): z up. Wall-mounted items have their wall
  in the plane ``y = wall_y`` and reach out towards +y; free-standing items stand with
  their base on ``z = floor_z``. The origin is the centre of the item's bounding box.

Hang features
-------------
Generators also record *where* a shape hangs, which drives the hang-pose proposals
(:mod:`sim.proposals`) and the physics tests:

- :class:`HangLoop` (objects): an opening a rod can pass through (handle, strap, ring,
  hole, J-hook, headband), by its centre, the axis a rod would follow through it, and the
  free radius of the opening.
- :class:`Peg` (supports): a straight rod segment an object can hang on, by its base and
  tip and its radius; ``closed`` marks rods fixed at both ends (towel bars), which an
  object cannot slide off.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
import trimesh

from sim import geometry
from sim.geometry import Part


@dataclasses.dataclass(frozen=True)
class HangLoop:
    center: np.ndarray  # [3] object frame, metres
    axis: np.ndarray  # [3] unit, direction a rod passes through the opening
    radius: float  # free radius of the opening (rod radius must be smaller)


@dataclasses.dataclass(frozen=True)
class Peg:
    base: np.ndarray  # [3] support frame, where the rod leaves its mount
    tip: np.ndarray  # [3] free end (or the other mount for closed rods)
    radius: float
    closed: bool = False  # fixed at both ends: objects cannot be slid off


@dataclasses.dataclass(frozen=True)
class AssetSpec:
    """What a generator returns: parts and features in its own construction frame."""

    parts: list[Part]
    features: list  # list[HangLoop] for objects, list[Peg] for supports
    params: dict  # the sampled shape parameters (for the record and for tests)
    ground_parts: tuple[int, ...] = ()  # support parts that count as the ground (stand bases)
    wall: bool = True  # supports: mounted on a wall (a wall slab is added in scenes)


@dataclasses.dataclass
class Asset:
    """One object or supporting item of the library, centred on its bounding-box centre."""

    name: str  # unique id, e.g. "mug_0007"
    kind: str  # "object" | "support"
    category: str  # object category or support family
    seed: int
    parts: list[Part]
    features: list
    params: dict
    ground_parts: tuple[int, ...] = ()
    wall_y: float | None = None  # supports on a wall: plane of the wall
    floor_z: float = 0.0  # height of the ground plane in this asset's frame
    source: str = "procedural"  # or the path of a user mesh
    _mesh: trimesh.Trimesh | None = dataclasses.field(default=None, repr=False)

    @property
    def mesh(self) -> trimesh.Trimesh:
        """Watertight visual mesh, the union of the convex parts (built on first use)."""
        if self._mesh is None:
            self._mesh = geometry.union_mesh(self.parts)
        return self._mesh

    @property
    def extents(self) -> np.ndarray:
        pts = geometry.support_points(self.parts)
        return pts.max(0) - pts.min(0)

    @property
    def scale(self) -> float:
        """Half of the bounding-box diagonal, metres (the camera distance unit)."""
        return float(0.5 * np.linalg.norm(self.extents))

    def bounds(self) -> np.ndarray:
        """[2, 3] axis-aligned bounds (min, max) of the parts, metres."""
        pts = geometry.support_points(self.parts)
        return np.stack([pts.min(0), pts.max(0)])


ObjectGenerator = Callable[[np.random.Generator], AssetSpec]
OBJECT_CATEGORIES: dict[str, ObjectGenerator] = {}
SUPPORT_FAMILIES: dict[str, ObjectGenerator] = {}


def register_object(category: str):
    def wrap(fn: ObjectGenerator) -> ObjectGenerator:
        OBJECT_CATEGORIES[category] = fn
        return fn

    return wrap


def register_support(family: str):
    def wrap(fn: ObjectGenerator) -> ObjectGenerator:
        SUPPORT_FAMILIES[family] = fn
        return fn

    return wrap


FLOOR_GAP = 0.8  # metres from a wall item's lowest point to the floor: room to dangle.


def _centre(spec: AssetSpec) -> tuple[np.ndarray, list[Part], list]:
    pts = geometry.support_points(spec.parts)
    centre = 0.5 * (pts.min(0) + pts.max(0))
    eye = np.eye(3)
    parts = geometry.transform_parts(spec.parts, eye, -centre)
    feats = []
    for f in spec.features:
        if isinstance(f, HangLoop):
            feats.append(
                HangLoop(np.asarray(f.center, float) - centre, _unit(f.axis), float(f.radius))
            )
        else:
            feats.append(
                Peg(
                    np.asarray(f.base, float) - centre,
                    np.asarray(f.tip, float) - centre,
                    float(f.radius),
                    f.closed,
                )
            )
    return centre, parts, feats


def _unit(v: Sequence[float]) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def build_object(category: str, seed: int, index: int | None = None) -> Asset:
    """Generate object ``category`` deterministically from ``seed``."""
    spec = OBJECT_CATEGORIES[category](np.random.default_rng(seed))
    _, parts, feats = _centre(spec)
    name = f"{category}_{seed if index is None else index:04d}"
    return Asset(name, "object", category, seed, parts, feats, spec.params)


def build_support(family: str, seed: int, index: int | None = None) -> Asset:
    """Generate supporting item ``family`` deterministically from ``seed``."""
    spec = SUPPORT_FAMILIES[family](np.random.default_rng(seed))
    centre, parts, feats = _centre(spec)
    pts = geometry.support_points(parts)
    wall_y = float(pts[:, 1].min()) if spec.wall else None
    floor_z = float(pts[:, 2].min()) - (FLOOR_GAP if spec.wall else 0.0)
    name = f"{family}_{seed if index is None else index:04d}"
    return Asset(
        name,
        "support",
        family,
        seed,
        parts,
        feats,
        spec.params,
        tuple(spec.ground_parts),
        wall_y,
        floor_z,
    )
