"""Convex building blocks of every asset, and the watertight mesh they make together.

A procedural asset is a union of convex *parts*. Each part maps one-to-one onto a MuJoCo
geom, so a procedural shape already knows its convex decomposition and never needs CoACD:

- :class:`Capsule`: a tube segment (handles, straps, rings, rods). Chains of capsules
  sharing end points make smooth bent tubes, and capsule collisions are the cheapest and
  smoothest MuJoCo (and MJX) offers.
- :class:`Box`: plates, blocks, mounting plates.
- :class:`ConvexMesh`: any other convex piece (cylinders, domes, blades), kept to at most
  :data:`MAX_HULL_VERTICES` vertices because MJX asks for small hulls.

All lengths are metres. Rotations are 3x3 matrices (numpy) in this module; poses elsewhere
use position + quaternion ``(w, x, y, z)`` as MuJoCo does.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import trimesh

MAX_HULL_VERTICES = 32  # MJX convex collisions scale with vertex count; 32 keeps them cheap.
_CAPSULE_SEGMENTS = 12  # circle resolution of the visual capsule mesh


@dataclasses.dataclass(frozen=True)
class Capsule:
    """A tube segment: all points within ``radius`` of the segment ``p0``-``p1``."""

    p0: np.ndarray  # [3] float64, metres
    p1: np.ndarray  # [3]
    radius: float

    kind = "capsule"

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> Capsule:
        return Capsule(
            rotation @ self.p0 + translation, rotation @ self.p1 + translation, self.radius
        )

    @property
    def volume(self) -> float:
        length = float(np.linalg.norm(self.p1 - self.p0))
        return np.pi * self.radius**2 * length + 4.0 / 3.0 * np.pi * self.radius**3

    def support_points(self) -> np.ndarray:
        """[K, 3] points whose convex hull bounds the part (for AABBs and cameras)."""
        return _sphere_points(self.radius, [self.p0, self.p1])

    def to_trimesh(self) -> trimesh.Trimesh:
        axis = self.p1 - self.p0
        length = float(np.linalg.norm(axis))
        mesh = trimesh.creation.capsule(
            height=max(length, 1e-6),
            radius=self.radius,
            count=[_CAPSULE_SEGMENTS, _CAPSULE_SEGMENTS],
        )
        transform = np.eye(4)
        transform[:3, :3] = _rotation_z_to(axis)
        transform[:3, 3] = 0.5 * (self.p0 + self.p1)
        mesh.apply_transform(transform)
        return mesh


@dataclasses.dataclass(frozen=True)
class Box:
    """An oriented box: ``center`` [3], ``rotation`` [3, 3], ``half_size`` [3]."""

    center: np.ndarray
    rotation: np.ndarray
    half_size: np.ndarray

    kind = "box"

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> Box:
        return Box(rotation @ self.center + translation, rotation @ self.rotation, self.half_size)

    @property
    def volume(self) -> float:
        return float(8.0 * np.prod(self.half_size))

    def support_points(self) -> np.ndarray:
        signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
        return (signs * self.half_size) @ self.rotation.T + self.center

    def to_trimesh(self) -> trimesh.Trimesh:
        transform = np.eye(4)
        transform[:3, :3] = self.rotation
        transform[:3, 3] = self.center
        return trimesh.creation.box(extents=2.0 * np.asarray(self.half_size), transform=transform)


@dataclasses.dataclass(frozen=True)
class ConvexMesh:
    """A convex polytope given by its hull ``vertices`` [V, 3], V <= MAX_HULL_VERTICES."""

    vertices: np.ndarray

    kind = "mesh"

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> ConvexMesh:
        return ConvexMesh(self.vertices @ rotation.T + translation)

    @property
    def volume(self) -> float:
        return float(self.to_trimesh().volume)

    def support_points(self) -> np.ndarray:
        return self.vertices

    def to_trimesh(self) -> trimesh.Trimesh:
        return trimesh.convex.convex_hull(self.vertices)


Part = Capsule | Box | ConvexMesh


# ----------------------------------------------------------------------------- rotations


def _rotation_z_to(direction: np.ndarray) -> np.ndarray:
    """Rotation matrix taking +z onto ``direction`` (any roll)."""
    z = np.asarray(direction, float)
    z = z / max(np.linalg.norm(z), 1e-12)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def rotation_from_axis_angle(axis: Sequence[float], angle: float) -> np.ndarray:
    """[3, 3] rotation of ``angle`` radians about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def frame_from_z(z_axis: Sequence[float], x_hint: Sequence[float] = (1.0, 0.0, 0.0)) -> np.ndarray:
    """Right-handed [3, 3] frame with columns (x, y, z), z along ``z_axis``, x near ``x_hint``."""
    z = np.asarray(z_axis, float)
    z = z / np.linalg.norm(z)
    x = np.asarray(x_hint, float) - np.dot(x_hint, z) * z
    if np.linalg.norm(x) < 1e-6:
        return _rotation_z_to(z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


_SPHERE_DIRS = np.concatenate(
    [
        np.eye(3),
        -np.eye(3),
        np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T / np.sqrt(3),
    ]
)


def _sphere_points(radius: float, centers: Sequence[np.ndarray]) -> np.ndarray:
    """Points of a small octahedron-plus-cube around each centre, bounding a sphere loosely."""
    return np.concatenate([c + radius * _SPHERE_DIRS for c in centers])


# ----------------------------------------------------------------------------- part builders


def capsule(p0: Sequence[float], p1: Sequence[float], radius: float) -> Capsule:
    return Capsule(np.asarray(p0, float), np.asarray(p1, float), float(radius))


def box(
    center: Sequence[float], half_size: Sequence[float], rotation: np.ndarray | None = None
) -> Box:
    rot = np.eye(3) if rotation is None else np.asarray(rotation, float)
    return Box(np.asarray(center, float), rot, np.asarray(half_size, float))


def hull(vertices: np.ndarray) -> ConvexMesh:
    """A convex part from any point set: keeps hull vertices, thinned to MAX_HULL_VERTICES."""
    pts = np.asarray(vertices, float)
    hull_mesh = trimesh.convex.convex_hull(pts)
    verts = np.asarray(hull_mesh.vertices)
    if len(verts) > MAX_HULL_VERTICES:
        verts = _farthest_points(verts, MAX_HULL_VERTICES)
    return ConvexMesh(verts)


def _farthest_points(points: np.ndarray, k: int) -> np.ndarray:
    chosen = [0]
    dist = np.linalg.norm(points - points[0], axis=1)
    for _ in range(k - 1):
        i = int(np.argmax(dist))
        chosen.append(i)
        dist = np.minimum(dist, np.linalg.norm(points - points[i], axis=1))
    return points[chosen]


def tube(points: Sequence[Sequence[float]], radius: float, closed: bool = False) -> list[Capsule]:
    """A bent tube through ``points`` [K, 3] as a chain of capsules (closed: a loop)."""
    pts = np.asarray(points, float)
    segments = [capsule(pts[i], pts[i + 1], radius) for i in range(len(pts) - 1)]
    if closed:
        segments.append(capsule(pts[-1], pts[0], radius))
    return segments


def arc(
    center: Sequence[float],
    u: Sequence[float],
    v: Sequence[float],
    radius: float,
    start: float,
    stop: float,
    num: int,
) -> np.ndarray:
    """[num, 3] points ``center + radius (cos a u + sin a v)`` for a in [start, stop] (radians)."""
    angles = np.linspace(start, stop, num)
    c, uu, vv = (np.asarray(x, float) for x in (center, u, v))
    return c + radius * (np.cos(angles)[:, None] * uu + np.sin(angles)[:, None] * vv)


def ring(center, normal, radius: float, tube_radius: float, segments: int = 10) -> list[Capsule]:
    """A closed torus-like ring of ``segments`` capsules around ``normal``."""
    frame = frame_from_z(normal)
    pts = arc(center, frame[:, 0], frame[:, 1], radius, 0.0, 2 * np.pi, segments + 1)[:-1]
    return tube(pts, tube_radius, closed=True)


def cylinder(p0, p1, radius: float, sides: int = 12) -> ConvexMesh:
    """A solid cylinder hull between ``p0`` and ``p1`` (2 * sides <= MAX_HULL_VERTICES)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    frame = _rotation_z_to(p1 - p0)
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    circle = radius * (np.cos(ang)[:, None] * frame[:, 0] + np.sin(ang)[:, None] * frame[:, 1])
    return ConvexMesh(np.concatenate([p0 + circle, p1 + circle]))


def frustum(p0, p1, r0: float, r1: float, sides: int = 12) -> ConvexMesh:
    """A truncated cone hull with radius ``r0`` at ``p0`` and ``r1`` at ``p1``."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    frame = _rotation_z_to(p1 - p0)
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring_dirs = np.cos(ang)[:, None] * frame[:, 0] + np.sin(ang)[:, None] * frame[:, 1]
    return ConvexMesh(np.concatenate([p0 + r0 * ring_dirs, p1 + r1 * ring_dirs]))


def ellipsoid(
    center, radii, rotation: np.ndarray | None = None, rings: int = 4, sides: int = 6
) -> ConvexMesh:
    """An ellipsoid hull with at most 2 + rings * sides vertices."""
    rot = np.eye(3) if rotation is None else np.asarray(rotation, float)
    pts = [[0, 0, 1], [0, 0, -1]]
    for i in range(1, rings + 1):
        theta = np.pi * i / (rings + 1)
        for j in range(sides):
            phi = 2 * np.pi * (j + 0.5 * (i % 2)) / sides
            pts.append([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    unit = np.asarray(pts) * np.asarray(radii, float)
    return ConvexMesh(unit @ rot.T + np.asarray(center, float))


def prism(
    outline_2d: np.ndarray, thickness: float, frame: np.ndarray | None = None, origin=(0, 0, 0)
) -> ConvexMesh:
    """A flat convex plate: the 2-D convex ``outline_2d`` [K, 2] extruded by ``thickness``.

    The outline lies in the frame's (x, y) plane, the thickness along its z, centred.
    """
    rot = np.eye(3) if frame is None else np.asarray(frame, float)
    o = np.asarray(outline_2d, float)
    top = np.c_[o, np.full(len(o), thickness / 2)]
    bottom = np.c_[o, np.full(len(o), -thickness / 2)]
    return hull(np.concatenate([top, bottom]) @ rot.T + np.asarray(origin, float))


# ----------------------------------------------------------------------------- whole assets


def parts_volume(parts: Sequence[Part]) -> np.ndarray:
    """[P] volume of each part in m^3 (overlaps counted in each part)."""
    return np.array([p.volume for p in parts])


def support_points(parts: Sequence[Part]) -> np.ndarray:
    """[K, 3] points whose hull contains every part (exact for boxes and hulls)."""
    return np.concatenate([p.support_points() for p in parts])


def transform_parts(
    parts: Sequence[Part], rotation: np.ndarray, translation: np.ndarray
) -> list[Part]:
    return [
        p.transformed(np.asarray(rotation, float), np.asarray(translation, float)) for p in parts
    ]


def union_mesh(parts: Sequence[Part]) -> trimesh.Trimesh:
    """The watertight union of all parts (manifold3d boolean), as a trimesh."""
    import manifold3d as m3

    manifolds = []
    for part in parts:
        m = part.to_trimesh()
        manifolds.append(
            m3.Manifold(
                m3.Mesh64(
                    vert_properties=np.asarray(m.vertices, np.float64),
                    tri_verts=np.asarray(m.faces, np.uint64),
                )
            )
        )
    merged = m3.Manifold.batch_boolean(manifolds, m3.OpType.Add).to_mesh64()
    return trimesh.Trimesh(
        np.asarray(merged.vert_properties)[:, :3], np.asarray(merged.tri_verts), process=False
    )
