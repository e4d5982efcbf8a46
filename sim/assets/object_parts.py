"""The parts and measurements the object generators (:mod:`sim.assets.objects`,
:mod:`sim.assets.objects_tools`) are built from: random draws, tubes, rings, annuli, sections,
and the hang-loop fit.

Hang loops are measured, not guessed: :func:`fit_loop` takes the opening's plane and a guess
of its centre, moves the centre to the point of largest clearance and records as radius the
distance from that centre to the nearest part (true capsules, boxes and hull faces; never an
overestimate). A rod of radius ``r`` placed at ``center + (radius - r) * u`` for any unit
``u`` in the loop plane therefore at most touches the object.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

from sim import geometry as g
from sim.assets.base import HangLoop
from sim.geometry import Box, Capsule, Part

X_AXIS = np.array([1.0, 0.0, 0.0])
Y_AXIS = np.array([0.0, 1.0, 0.0])
Z_AXIS = np.array([0.0, 0.0, 1.0])

MIN_OPENING = 0.0085  # metres; every loop must pass a 7 mm rod with 1.5 mm of clearance


# ----------------------------------------------------------------------------- sampling


def uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def choice(rng: np.random.Generator, options: list[str]) -> str:
    return options[int(rng.integers(len(options)))]


def deg(rng: np.random.Generator, lo: float, hi: float) -> float:
    """Uniform angle in degrees, returned in radians."""
    return float(np.deg2rad(rng.uniform(lo, hi)))


# ----------------------------------------------------------------------------- part helpers


def plane_frame(e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """[3, 3] frame with columns (e1, e2, e1 x e2) for a plane spanned by unit e1, e2."""
    e1 = np.asarray(e1, float)
    e2 = np.asarray(e2, float)
    return np.stack([e1, e2, np.cross(e1, e2)], axis=1)


def rot_y(angle: float) -> np.ndarray:
    return g.rotation_from_axis_angle(Y_AXIS, angle)


def rot_z(angle: float) -> np.ndarray:
    return g.rotation_from_axis_angle(Z_AXIS, angle)


def tube(points, radius: float, closed: bool = False) -> list[Capsule]:
    """A bent tube through ``points`` [K, 3] as a chain of capsules, like ``geometry.tube``.

    At interior joints each capsule stops 0.3 radii short of the shared point: the two end
    spheres then overlap instead of coinciding, which keeps the tube solid but makes the
    manifold union several times cheaper (nearly coincident spheres are its worst case).
    """
    pts = np.asarray(points, float)
    k = len(pts)
    pairs = [(i, i + 1) for i in range(k - 1)] + ([(k - 1, 0)] if closed else [])
    caps = []
    for n, (i, j) in enumerate(pairs):
        p0, p1 = pts[i], pts[j]
        seg = p1 - p0
        length = float(np.linalg.norm(seg))
        pull = min(0.3 * radius, 0.2 * length) * seg / max(length, 1e-12)
        start = p0 + pull if (closed or n > 0) else p0
        stop = p1 - pull if (closed or n < len(pairs) - 1) else p1
        caps.append(g.capsule(start, stop, radius))
    return caps


def ellipse(center, e1, e2, a: float, b: float, start: float, stop: float, num: int):
    """[num, 3] points ``center + a cos(t) e1 + b sin(t) e2`` for t in [start, stop]."""
    t = np.linspace(start, stop, num)
    c, u, v = (np.asarray(x, float) for x in (center, e1, e2))
    return c + a * np.cos(t)[:, None] * u + b * np.sin(t)[:, None] * v


def ellipse_ring(center, e1, e2, a: float, b: float, tube_r: float, segments: int):
    """A closed elliptic ring of ``segments`` capsules; vertex 0 at ``center + a e1``."""
    pts = ellipse(center, e1, e2, a, b, 0.0, 2 * np.pi, segments + 1)[:-1]
    return tube(pts, tube_r, closed=True)


def annulus(
    center,
    frame: np.ndarray,
    r_in: float,
    r_out: float,
    thickness: float,
    segments: int = 8,
    start: float = 0.0,
    stop: float = 2 * np.pi,
) -> list[g.ConvexMesh]:
    """A flat washer (or a sector of one) as ``segments`` convex prism sectors.

    It lies in the frame's (x, y) plane, thickness along the frame's z. The inner polygon's
    vertices sit at ``r_in / cos(half sector angle)``, so its inscribed circle -- the free
    radius of the hole -- is exactly ``r_in``. Neighbouring sectors overlap a little at the
    outer edge so the union is one solid.
    """
    step = (stop - start) / segments
    ri = r_in / np.cos(step / 2)
    overlap = 0.15 * step
    sectors = []
    for k in range(segments):
        a0, a1 = start + k * step, start + (k + 1) * step
        b0, b1 = a0 - overlap, a1 + overlap
        if abs(stop - start - 2 * np.pi) > 1e-9:  # open sector: keep its ends flush
            b0, b1 = max(b0, start), min(b1, stop)
        outline = np.array(
            [
                [ri * np.cos(a0), ri * np.sin(a0)],
                [ri * np.cos(a1), ri * np.sin(a1)],
                [r_out * np.cos(b1), r_out * np.sin(b1)],
                [r_out * np.cos(b0), r_out * np.sin(b0)],
            ]
        )
        sectors.append(g.prism(outline, thickness, frame, center))
    return sectors


def rect_section(x: float, width: float, thick: float, z: float = 0.0) -> np.ndarray:
    """[4, 3] corners of a rectangle in the plane x = const (width along y, thick along z)."""
    return np.array(
        [[x, sy * width / 2, z + sz * thick / 2] for sy in (-1, 1) for sz in (-1, 1)], float
    )


def ellipse_section(x: float, half_y: float, half_z: float, z: float = 0.0, sides: int = 8):
    """[sides, 3] points of an ellipse in the plane x = const."""
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False) + np.pi / sides
    return np.stack([np.full(sides, x), half_y * np.cos(ang), z + half_z * np.sin(ang)], axis=1)


def j_hook(base, up, side, stem: float, bend_r: float, end_angle: float, tube_r: float):
    """A J hook: a stem from ``base`` along ``up``, then an arc of radius ``bend_r`` over to
    the ``side`` and back down, ending ``end_angle`` radians past the horizontal.

    Returns (parts, arc centre, axis normal to the hook plane).
    """
    base, up, side = (np.asarray(v, float) for v in (base, up, side))
    top = base + stem * up
    centre = top + bend_r * side
    segments = 8
    pts = g.arc(centre, side, up, bend_r, np.pi, -end_angle, segments + 1)
    parts = [g.capsule(base, top, tube_r), *tube(pts, tube_r)]
    return parts, centre, np.cross(side, up)


# ----------------------------------------------------------------------------- hang loops


def distance_fns(parts: list[Part]):
    """Per part, a function [N, 3] points -> [N] distance lower bound (negative inside)."""
    fns = []
    for part in parts:
        if isinstance(part, Capsule):

            def fn(p, a=part.p0, b=part.p1, r=part.radius):
                ab = b - a
                t = np.clip((p - a) @ ab / max(float(ab @ ab), 1e-18), 0.0, 1.0)
                return np.linalg.norm(p - (a + t[:, None] * ab), axis=1) - r

        elif isinstance(part, Box):

            def fn(p, c=part.center, rot=part.rotation, h=part.half_size):
                q = np.abs((p - c) @ rot) - h
                return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(1), 0.0)

        else:
            planes = ConvexHull(part.vertices).equations  # [F, 4]: n . x + d <= 0 inside
            normals, offsets = planes[:, :3], -planes[:, 3]

            # Largest face-plane distance: exact on faces, an underestimate near edges.
            def fn(p, n=normals, o=offsets):
                return (p @ n.T - o).max(1)

        fns.append(fn)
    return fns


def fit_loop(parts: list[Part], guess, axis, depth: float, span: float = 0.0) -> HangLoop:
    """The hang loop of an opening: centre, rod axis, and measured free radius.

    ``guess`` lies in the opening's plane (normal ``axis``). The clearance of a centre is the
    smallest distance from the rod's axis -- sampled over ``[-depth, depth]`` along ``axis``
    -- to any part. With ``span > 0`` a compass search moves the centre (at most ``span``
    along each in-plane direction) to a local maximum of clearance: the centre of the largest
    circle inscribed in a closed opening. Open hooks (J shapes) use ``span = 0``.
    """
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    guess = np.asarray(guess, float)
    plane = g.frame_from_z(axis)[:, :2]  # [3, 2] in-plane directions
    samples = max(3, 2 * int(np.ceil(depth / 0.0015)) + 1)
    ts = np.linspace(-depth, depth, samples)
    fns = distance_fns(parts)

    def clearance(offsets: np.ndarray) -> np.ndarray:  # [M, 2] -> [M]
        centres = guess + offsets @ plane.T
        pts = (centres[:, None, :] + ts[None, :, None] * axis).reshape(-1, 3)
        dist = np.min([fn(pts) for fn in fns], axis=0)
        return dist.reshape(len(offsets), samples).min(1)

    best_off = np.zeros(2)
    best = float(clearance(best_off[None])[0])
    if span > 0:
        dirs = np.array(
            [[np.cos(a), np.sin(a)] for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
        )
        step = span / 4
        for _ in range(200):
            if step < 2e-4:
                break
            cand = np.clip(best_off + step * dirs, -span, span)
            vals = clearance(cand)
            i = int(np.argmax(vals))
            if vals[i] > best + 1e-7:
                best, best_off = float(vals[i]), cand[i]
            else:
                step *= 0.5
    return HangLoop(guess + plane @ best_off, axis, best)


def arch(x_half: float, height: float, y: float, z_base: float, num: int) -> np.ndarray:
    """[num, 3] half-ellipse from (-x_half, y, z_base) over the top to (+x_half, y, z_base)."""
    return ellipse([0.0, y, z_base], X_AXIS, Z_AXIS, x_half, height, np.pi, 0.0, num)
