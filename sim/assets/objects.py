"""Procedural generators for the 11 object categories of the paper.

Each generator takes a ``numpy.random.Generator`` and returns an :class:`AssetSpec` of convex
parts at real size (metres) plus the :class:`HangLoop` features the object hangs by. Shapes vary
widely within a category (sizes, proportions, hole placement, thickness, style variants); the
recipes and ranges are documented in ``docs/assets_objects.md``.

Hang loops are measured, not guessed: :func:`_fit_loop` takes the opening's plane and a guess
of its centre, moves the centre to the point of largest clearance and records as radius the
distance from that centre to the nearest part (true capsules, boxes and hull faces; never an
overestimate). A rod of radius ``r`` placed at ``center + (radius - r) * u`` for any unit
``u`` in the loop plane therefore at most touches the object.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

from sim import geometry as g
from sim.assets.base import AssetSpec, HangLoop, register_object
from sim.geometry import Box, Capsule, Part

X_AXIS = np.array([1.0, 0.0, 0.0])
Y_AXIS = np.array([0.0, 1.0, 0.0])
Z_AXIS = np.array([0.0, 0.0, 1.0])

MIN_OPENING = 0.0085  # metres; every loop must pass a 7 mm rod with 1.5 mm of clearance


# ----------------------------------------------------------------------------- sampling


def _uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _choice(rng: np.random.Generator, options: list[str]) -> str:
    return options[int(rng.integers(len(options)))]


def _deg(rng: np.random.Generator, lo: float, hi: float) -> float:
    """Uniform angle in degrees, returned in radians."""
    return float(np.deg2rad(rng.uniform(lo, hi)))


# ----------------------------------------------------------------------------- part helpers


def _plane_frame(e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """[3, 3] frame with columns (e1, e2, e1 x e2) for a plane spanned by unit e1, e2."""
    e1 = np.asarray(e1, float)
    e2 = np.asarray(e2, float)
    return np.stack([e1, e2, np.cross(e1, e2)], axis=1)


def _rot_y(angle: float) -> np.ndarray:
    return g.rotation_from_axis_angle(Y_AXIS, angle)


def _rot_z(angle: float) -> np.ndarray:
    return g.rotation_from_axis_angle(Z_AXIS, angle)


def _tube(points, radius: float, closed: bool = False) -> list[Capsule]:
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


def _ellipse(center, e1, e2, a: float, b: float, start: float, stop: float, num: int):
    """[num, 3] points ``center + a cos(t) e1 + b sin(t) e2`` for t in [start, stop]."""
    t = np.linspace(start, stop, num)
    c, u, v = (np.asarray(x, float) for x in (center, e1, e2))
    return c + a * np.cos(t)[:, None] * u + b * np.sin(t)[:, None] * v


def _ellipse_ring(center, e1, e2, a: float, b: float, tube_r: float, segments: int):
    """A closed elliptic ring of ``segments`` capsules; vertex 0 at ``center + a e1``."""
    pts = _ellipse(center, e1, e2, a, b, 0.0, 2 * np.pi, segments + 1)[:-1]
    return _tube(pts, tube_r, closed=True)


def _annulus(
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


def _rect_section(x: float, width: float, thick: float, z: float = 0.0) -> np.ndarray:
    """[4, 3] corners of a rectangle in the plane x = const (width along y, thick along z)."""
    return np.array(
        [[x, sy * width / 2, z + sz * thick / 2] for sy in (-1, 1) for sz in (-1, 1)], float
    )


def _ellipse_section(x: float, half_y: float, half_z: float, z: float = 0.0, sides: int = 8):
    """[sides, 3] points of an ellipse in the plane x = const."""
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False) + np.pi / sides
    return np.stack([np.full(sides, x), half_y * np.cos(ang), z + half_z * np.sin(ang)], axis=1)


def _j_hook(base, up, side, stem: float, bend_r: float, end_angle: float, tube_r: float):
    """A J hook: a stem from ``base`` along ``up``, then an arc of radius ``bend_r`` over to
    the ``side`` and back down, ending ``end_angle`` radians past the horizontal.

    Returns (parts, arc centre, axis normal to the hook plane).
    """
    base, up, side = (np.asarray(v, float) for v in (base, up, side))
    top = base + stem * up
    centre = top + bend_r * side
    segments = 8
    pts = g.arc(centre, side, up, bend_r, np.pi, -end_angle, segments + 1)
    parts = [g.capsule(base, top, tube_r), *_tube(pts, tube_r)]
    return parts, centre, np.cross(side, up)


# ----------------------------------------------------------------------------- hang loops


def _distance_fns(parts: list[Part]):
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


def _fit_loop(parts: list[Part], guess, axis, depth: float, span: float = 0.0) -> HangLoop:
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
    fns = _distance_fns(parts)

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


# ----------------------------------------------------------------------------- categories


@register_object("mug")
def mug(rng: np.random.Generator) -> AssetSpec:
    """A mug: solid (tapered) body and a round-C or squared-D handle tube on its side.

    Hangs by the handle opening (axis = the handle plane's normal, +y).
    """
    radius = _uniform(rng, 0.03, 0.05)
    height = _uniform(rng, 0.07, 0.12)
    taper = _uniform(rng, 0.8, 1.15)  # top radius / bottom radius
    tube_r = _uniform(rng, 0.004, 0.0065)
    reach = _uniform(rng, 0.032, 0.048)  # body wall to handle tube centre line
    handle_h = _uniform(rng, 0.5, 0.75) * height  # vertical span of the handle
    handle_z = _uniform(rng, -0.08, 0.08) * height  # handle centre relative to body centre
    style = _choice(rng, ["round", "square"])
    body = g.frustum([0, 0, -height / 2], [0, 0, height / 2], radius, radius * taper, sides=16)

    def wall_x(z: float) -> float:  # attach half a tube radius inside the wall
        return radius * (1 + (taper - 1) * (z / height + 0.5)) - 0.5 * tube_r

    z_top, z_bot = handle_z + handle_h / 2, handle_z - handle_h / 2
    x_mid = wall_x(handle_z)
    if style == "round":
        ang = np.linspace(np.pi / 2, -np.pi / 2, 9)
        zs = handle_z + handle_h / 2 * np.sin(ang)
        xs = np.array([wall_x(z) for z in zs]) + reach * np.cos(ang)
        pts = np.stack([xs, np.zeros_like(xs), zs], axis=1)
    else:
        chamfer = _uniform(rng, 0.2, 0.45) * min(reach, handle_h / 2)
        x_out = x_mid + reach
        pts = np.array(
            [
                [wall_x(z_top), 0, z_top],
                [x_out - chamfer, 0, z_top],
                [x_out, 0, z_top - chamfer],
                [x_out, 0, z_bot + chamfer],
                [x_out - chamfer, 0, z_bot],
                [wall_x(z_bot), 0, z_bot],
            ]
        )
    parts = [body, *_tube(pts, tube_r)]
    loop = _fit_loop(
        parts, [x_mid + 0.45 * reach, 0.0, handle_z], Y_AXIS, tube_r + 0.004, span=0.5 * reach
    )
    return AssetSpec(
        parts=parts,
        features=[loop],
        params=dict(
            style=style,
            radius=radius,
            height=height,
            taper=taper,
            tube_radius=tube_r,
            handle_reach=reach,
            handle_height=handle_h,
        ),
    )


def _arch(x_half: float, height: float, y: float, z_base: float, num: int) -> np.ndarray:
    """[num, 3] half-ellipse from (-x_half, y, z_base) over the top to (+x_half, y, z_base)."""
    return _ellipse([0.0, y, z_base], X_AXIS, Z_AXIS, x_half, height, np.pi, 0.0, num)


@register_object("bag")
def bag(rng: np.random.Generator) -> AssetSpec:
    """A bag: a trapezoid body with straps forming loops above it.

    Styles: tote (two handles, front and back), messenger (one long strap from side to side,
    front flap), handbag (one short thick handle). Hangs by each strap loop (axis +y).
    """
    style = _choice(rng, ["tote", "messenger", "handbag"])
    width = _uniform(rng, 0.24, 0.42)  # x, at the bottom
    depth = _uniform(rng, 0.07, 0.16)  # y, at the bottom
    if style == "tote":
        height = _uniform(rng, 0.22, 0.38)
        top_w, top_d = width * _uniform(rng, 1.0, 1.15), depth * _uniform(rng, 0.6, 1.0)
    elif style == "messenger":
        height = _uniform(rng, 0.18, 0.3)
        top_w, top_d = width, depth
    else:
        height = _uniform(rng, 0.16, 0.28)
        top_w, top_d = width * _uniform(rng, 0.65, 0.9), depth * _uniform(rng, 0.55, 0.9)
    corners = [
        [sx * w / 2, sy * d / 2, z]
        for (w, d, z) in ((width, depth, 0.0), (top_w, top_d, height))
        for sx in (-1, 1)
        for sy in (-1, 1)
    ]
    parts: list[Part] = [g.hull(np.array(corners))]
    loops_at = []  # (guess, span, strap radius)
    if style == "tote":
        strap_r = _uniform(rng, 0.005, 0.01)
        a = top_w * _uniform(rng, 0.15, 0.3)
        h = _uniform(rng, 0.12, 0.24)
        y0 = top_d / 2 - 1.2 * strap_r
        for y in (y0, -y0):
            parts += _tube(_arch(a, h + 1.5 * strap_r, y, height - 1.5 * strap_r, 7), strap_r)
            loops_at.append(([0.0, y, height + 0.45 * h], 0.9 * min(a, h)))
    elif style == "messenger":
        strap_r = _uniform(rng, 0.006, 0.012)
        a = width / 2 - 0.5 * strap_r
        h = min(_uniform(rng, 0.22, 0.42), 0.76 - height)
        parts += _tube(_arch(a, h + 2 * strap_r, 0.0, height - 2 * strap_r, 11), strap_r)
        flap_h = height * _uniform(rng, 0.4, 0.8)
        parts.append(
            g.box([0, depth / 2 + 0.0015, height - flap_h / 2], [0.49 * width, 0.003, flap_h / 2])
        )
        loops_at.append(([0.0, 0.0, height + 0.4 * h], 0.9 * min(a, h)))
    else:
        strap_r = _uniform(rng, 0.007, 0.014)
        a = top_w * _uniform(rng, 0.2, 0.38)
        h = _uniform(rng, 0.07, 0.15)
        parts += _tube(_arch(a, h + 1.5 * strap_r, 0.0, height - 1.5 * strap_r, 7), strap_r)
        loops_at.append(([0.0, 0.0, height + 0.45 * h], 0.9 * min(a, h)))
    loops = [_fit_loop(parts, c, Y_AXIS, strap_r + 0.003, span) for c, span in loops_at]
    return AssetSpec(
        parts=parts,
        features=loops,
        params=dict(
            style=style, width=width, depth=depth, height=height, strap_radius=strap_r, strap_h=h
        ),
    )


@register_object("cap")
def cap(rng: np.random.Generator) -> AssetSpec:
    """A baseball cap: a crown dome of convex shell panels, a brim plate at the front (+x),
    and a back opening (-x) closed below by a strap arc.

    Hangs by the back opening: a peg enters along x between strap and crown.
    """
    crown_r = _uniform(rng, 0.085, 0.1)
    squash = _uniform(rng, 0.78, 1.0)  # crown height / crown radius
    shell = _uniform(rng, 0.003, 0.006)
    half_open = _deg(rng, 26, 36)  # half-width (azimuth) of the back opening
    open_el = _deg(rng, 34, 46)  # elevation of the opening's top edge
    top_el = _deg(rng, 58, 68)  # elevation where the top panel starts
    n_gores = int(rng.integers(4, 7))  # panels besides the back one
    strap_r = _uniform(rng, 0.004, 0.007)
    brim_len = _uniform(rng, 0.055, 0.085)
    brim_half_angle = _deg(rng, 45, 60)
    brim_tilt = _deg(rng, 0, 18)
    brim_t = _uniform(rng, 0.003, 0.006)

    def sphere_pt(az, el, r):
        return np.array(
            [r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), squash * r * np.sin(el)]
        )

    def panel(az0, az1, el0, el1):
        """A shell patch as one hull: outer grid plus inner corners (a thin convex lens)."""
        ov_az, ov_el = 0.03, 0.02  # overlap neighbours so the union is one solid
        az = np.linspace(az0 - ov_az, az1 + ov_az, 4)
        el = np.linspace(max(el0 - ov_el, 0.0), el1 + ov_el, 3)
        outer = [sphere_pt(a, e, crown_r) for a in az for e in el]
        inner = [sphere_pt(a, e, crown_r - shell) for a in az[[0, -1]] for e in el[[0, -1]]]
        return g.hull(np.array(outer + inner))

    back0, back1 = np.pi - half_open, np.pi + half_open
    bounds = np.linspace(back1, back0 + 2 * np.pi, n_gores + 1)
    parts: list[Part] = [panel(back0, back1, open_el, top_el)]  # above the back opening
    for k in range(n_gores):
        parts.append(panel(bounds[k], bounds[k + 1], 0.0, open_el))
        parts.append(panel(bounds[k], bounds[k + 1], open_el, top_el))
    ring_az = np.linspace(0, 2 * np.pi, 10, endpoint=False)
    top_pts = [sphere_pt(a, top_el - 0.02, r) for a in ring_az for r in (crown_r, crown_r - shell)]
    top_pts += [sphere_pt(a + 0.3, 0.5 * (top_el + np.pi / 2), crown_r) for a in ring_az[::2]]
    top_pts += [sphere_pt(0.0, np.pi / 2, crown_r)]
    parts.append(g.hull(np.array(top_pts)))
    if rng.uniform() < 0.6:  # button on top
        z_top = squash * crown_r
        parts.append(g.cylinder([0, 0, z_top - 0.003], [0, 0, z_top + 0.004], 0.0065, sides=8))
    # Brim: hull of the front rim arc and a half-ellipse reaching brim_len past the crown.
    rim = [
        (crown_r - shell) * np.array([np.cos(a), np.sin(a)])
        for a in np.linspace(-brim_half_angle, brim_half_angle, 5)
    ]
    x_pivot = crown_r * np.cos(brim_half_angle)
    reach = crown_r * (1 - np.cos(brim_half_angle)) + brim_len
    half_w = crown_r * np.sin(brim_half_angle) * _uniform(rng, 1.0, 1.2)
    front = [
        np.array([x_pivot + reach * np.cos(b), half_w * np.sin(b)])
        for b in np.linspace(-np.pi / 2, np.pi / 2, 9)
    ]
    outline = np.array(rim + front) - [x_pivot, 0.0]
    parts.append(g.prism(outline, brim_t, _rot_y(brim_tilt), [x_pivot, 0.0, brim_t / 2]))
    # Strap: a shallow arc along the back rim, ends buried in the neighbouring panels.
    strap_az = np.linspace(back0 - 0.1, back1 + 0.1, 4)
    strap_pts = [sphere_pt(a, 0.0, crown_r - shell / 2) + [0, 0, strap_r] for a in strap_az]
    parts += _tube(np.array(strap_pts), strap_r)
    # The opening, projected along x, is closed by strap (below), panels (sides) and the back
    # panel (above): search the largest inscribed circle over the whole curved opening.
    x_mid = -crown_r * (1 + np.cos(half_open)) / 2
    depth = crown_r * (1 - np.cos(half_open)) / 2 + 0.004
    z_open = squash * crown_r * np.sin(open_el)
    loop = _fit_loop(
        parts,
        [x_mid, 0.0, 0.5 * (2 * strap_r + z_open)],
        X_AXIS,
        depth,
        span=0.8 * crown_r * np.sin(half_open),
    )
    return AssetSpec(
        parts=parts,
        features=[loop],
        params=dict(
            crown_radius=crown_r,
            squash=squash,
            shell=shell,
            opening_half_angle=half_open,
            opening_elevation=open_el,
            gores=n_gores + 1,
            brim_length=brim_len,
            brim_tilt=brim_tilt,
            strap_radius=strap_r,
        ),
    )


@register_object("clothes_hanger")
def clothes_hanger(rng: np.random.Generator) -> AssetSpec:
    """A clothes hanger in the xz-plane with a J hook on top (optionally swivelled about z).

    Styles: wire (triangle of thin wire), wide_shoulder (arched wooden bar of hull segments,
    optional trouser bar), tubular (plastic tube shoulders with a bottom bar). Hangs on a rod
    through the hook's inner curve.
    """
    style = _choice(rng, ["wire", "wide_shoulder", "tubular"])
    width = _uniform(rng, 0.34, 0.46)
    swivel = _deg(rng, -30, 30) if rng.uniform() < 0.4 else 0.0
    side = _rot_z(swivel) @ X_AXIS
    parts: list[Part] = []
    if style == "wire":
        wire_r = _uniform(rng, 0.0018, 0.0028)
        drop = _uniform(rng, 0.1, 0.16)
        left, right, neck = [-width / 2, 0, -drop], [width / 2, 0, -drop], [0.0, 0.0, 0.0]
        parts += [
            g.capsule(neck, left, wire_r),
            g.capsule(left, right, wire_r),
            g.capsule(neck, right, wire_r),
            g.capsule([0, 0, -0.012], [0, 0, 0.012], 1.8 * wire_r),  # twisted neck
        ]
        hook_r, hook_base, stem_extra = wire_r, np.array([0.0, 0.0, 0.0]), 0.012
    elif style == "wide_shoulder":
        arch = _uniform(rng, 0.02, 0.07)  # how far the shoulder tips sit below the centre
        bar_h = _uniform(rng, 0.02, 0.035)  # z
        bar_t = _uniform(rng, 0.008, 0.03)  # y, at the centre
        flare = _uniform(rng, 1.0, 2.0)  # y thickness at the tips / at the centre
        xs = np.linspace(-width / 2, width / 2, 7)

        def section(x, pad):
            s = abs(2 * x / width)
            z = -arch * s**2
            return _rect_section(x + pad, bar_t * (1 + (flare - 1) * s), bar_h, z)

        for x0, x1 in zip(xs[:-1], xs[1:]):
            parts.append(g.hull(np.concatenate([section(x0, -0.002), section(x1, 0.002)])))
        if rng.uniform() < 0.5:  # trouser bar
            bar_r = _uniform(rng, 0.003, 0.006)
            xa = width / 2 * _uniform(rng, 0.55, 0.85)
            za = -arch * (2 * xa / width) ** 2
            zb = za - _uniform(rng, 0.1, 0.16)
            parts += [
                g.capsule([-xa, 0, za], [-xa, 0, zb], bar_r),
                g.capsule([-xa, 0, zb], [xa, 0, zb], bar_r),
                g.capsule([xa, 0, zb], [xa, 0, za], bar_r),
            ]
        hook_r = _uniform(rng, 0.0022, 0.003)
        hook_base = np.array([0.0, 0.0, -0.3 * bar_h])
        stem_extra = 0.8 * bar_h + 0.006  # the stem starts inside the bar, below the ferrule
        parts.append(
            g.cylinder([0, 0, bar_h / 2 - 0.002], [0, 0, bar_h / 2 + 0.006], 2.5 * hook_r, 8)
        )
    else:
        tube_r = _uniform(rng, 0.0035, 0.006)
        drop = _uniform(rng, 0.08, 0.14)
        power = _uniform(rng, 1.2, 2.0)
        for sgn in (-1, 1):
            ks = np.linspace(0, 1, 5)
            pts = np.stack([sgn * width / 2 * ks, np.zeros(5), -drop * ks**power], axis=1)
            tip = pts[-1] + [sgn * 0.004, 0, -_uniform(rng, 0.01, 0.025)]
            parts += _tube(np.concatenate([pts, tip[None]]), tube_r)
        z_bar = -drop - _uniform(rng, 0.0, 0.03)
        ends = [p.p1 for p in parts if abs(p.p1[0]) > width / 2]
        parts.append(g.capsule(ends[0], [ends[0][0], 0, z_bar], tube_r))
        parts.append(g.capsule([ends[0][0], 0, z_bar], [ends[1][0], 0, z_bar], tube_r))
        parts.append(g.capsule([ends[1][0], 0, z_bar], ends[1], tube_r))
        hook_r, hook_base, stem_extra = tube_r, np.array([0.0, 0.0, 0.0]), 0.0
    bend_r = _uniform(rng, max(0.016, hook_r + 0.012), 0.03)
    stem = _uniform(rng, 0.02, 0.05)
    hook, centre, axis = _j_hook(
        hook_base, Z_AXIS, side, stem + stem_extra, bend_r, _deg(rng, 20, 60), hook_r
    )
    parts += hook
    loop = _fit_loop(parts, centre, axis, hook_r + 0.003)
    return AssetSpec(
        parts=parts,
        features=[loop],
        params=dict(
            style=style,
            width=width,
            hook_bend_radius=bend_r,
            hook_wire_radius=hook_r,
            hook_stem=stem,
            swivel=swivel,
        ),
    )


def _end_ring(rng: np.random.Generator, normal: np.ndarray, tube_max: float = 0.0028):
    """A hanging ring whose +x vertex sits 0.5 tube radii past x = 0 (into a handle end).

    Returns (parts, centre): the ring's inner surface stays at x < 0, clear of the handle.
    """
    ring_r = _uniform(rng, 0.013, 0.02)
    wire = _uniform(rng, 0.0015, tube_max)
    centre = np.array([-(ring_r - 0.5 * wire), 0.0, 0.0])
    ring = _ellipse_ring(centre, X_AXIS, np.cross(normal, X_AXIS), ring_r, ring_r, wire, 8)
    return ring, centre, ring_r, wire


@register_object("cooking_utensil")
def cooking_utensil(rng: np.random.Generator) -> AssetSpec:
    """A kitchen utensil along +x: a handle from x = 0 and a head beyond it.

    Heads: spatula (thin bent plate), ladle (deep bowl hull), spoon (flat ellipsoid bowl),
    whisk (wire loops meeting at the tip). Hangs by a hole through the flat handle's end or by
    a hanging ring at the handle end (whisks always by a ring).
    """
    style = _choice(rng, ["spatula", "ladle", "spoon", "whisk"])
    hang = "ring" if style == "whisk" else _choice(rng, ["hole", "ring"])
    parts: list[Part] = []
    if style == "whisk":
        length = _uniform(rng, 0.09, 0.15)
        handle_r = _uniform(rng, 0.01, 0.016)
        parts.append(g.cylinder([0, 0, 0], [length, 0, 0], handle_r, sides=12))
        parts.append(
            g.frustum(
                [length - 0.002, 0, 0], [length + 0.018, 0, 0], handle_r, 0.5 * handle_r, sides=10
            )
        )
        n_loops = int(rng.integers(3, 5))
        head_len = _uniform(rng, 0.12, 0.2)
        head_r = _uniform(rng, 0.022, 0.04)
        wire = _uniform(rng, 0.0008, 0.0015)
        base = np.array([length + 0.012, 0, 0])
        tip = np.array([length + 0.012 + head_len, 0, 0])
        for j in range(n_loops):
            d = np.array([0.0, np.cos(np.pi * j / n_loops), np.sin(np.pi * j / n_loops)])
            # A balloon loop: narrow at the handle, widest near the far end, round at the tip.
            a = base + [0.5 * head_len, 0, 0] + 0.8 * head_r * d
            b = base + [0.85 * head_len, 0, 0] + 0.95 * head_r * d
            a2 = a - 1.6 * head_r * d  # the same wire on the other side of the axis
            b2 = b - 1.9 * head_r * d
            parts += _tube(np.array([base, a, b, tip, b2, a2]), wire, closed=True)
        params = dict(
            handle_radius=handle_r, loops=n_loops, head_length=head_len, head_radius=head_r
        )
    else:
        length = _uniform(rng, 0.2, 0.3) if style == "ladle" else _uniform(rng, 0.13, 0.25)
        handle_w = _uniform(rng, 0.014, 0.026)
        thick = _uniform(rng, 0.006, 0.011) if style == "spoon" else _uniform(rng, 0.004, 0.009)
        tip_w = handle_w * _uniform(rng, 0.5, 0.8)
        params = dict(handle_width=handle_w, handle_thickness=thick)
        if hang == "hole":
            hole_r = _uniform(rng, 0.009, 0.013)
            outer_r = max(hole_r + _uniform(rng, 0.004, 0.008), 0.5 * handle_w + 0.002)
            parts += _annulus([0, 0, 0], np.eye(3), hole_r, outer_r, thick, segments=8)
            x0 = hole_r + 0.3 * (outer_r - hole_r)
        else:
            x0 = 0.0
        parts.append(
            g.hull(
                np.concatenate(
                    [_rect_section(x0, handle_w, thick), _rect_section(length, tip_w, thick)]
                )
            )
        )
        if style == "spatula":
            neck = _uniform(rng, 0.02, 0.05)
            plate_w = _uniform(rng, 0.05, 0.09)
            plate_l = _uniform(rng, 0.06, 0.11)
            plate_t = _uniform(rng, 0.002, 0.004)
            bend = _deg(rng, 0, 25)
            corner = _uniform(rng, 0.005, 0.02)
            start = np.array([length + neck, 0.0, -neck * np.tan(0.5 * bend)])
            parts.append(
                g.hull(
                    np.concatenate(
                        [
                            _rect_section(length - 0.005, tip_w, thick),
                            _rect_section(0.0, 0.4 * plate_w, plate_t) + start,
                        ]
                    )
                )
            )
            outline = np.array(
                [
                    [-0.004, -0.4 * plate_w],
                    [-0.004, 0.4 * plate_w],
                    [plate_l - corner, plate_w / 2],
                    [plate_l, plate_w / 2 - corner],
                    [plate_l, -plate_w / 2 + corner],
                    [plate_l - corner, -plate_w / 2],
                ]
            )
            parts.append(g.prism(outline, plate_t, _rot_y(bend), start))
            params.update(head_width=plate_w, head_length=plate_l, bend=bend)
        elif style == "ladle":
            bowl_r = _uniform(rng, 0.035, 0.05)
            bowl_d = bowl_r * _uniform(rng, 0.6, 1.0)
            drop = _uniform(rng, 0.02, 0.05)
            neck_end = np.array([length + 0.3 * drop, 0, -drop])
            parts.append(g.capsule([length - 0.004, 0, 0], neck_end, max(0.5 * thick, 0.003)))
            centre = neck_end + [0.88 * bowl_r, 0, 0]
            pts = [
                centre + bowl_r * np.array([np.cos(a), np.sin(a), 0])
                for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)
            ]
            for el in (np.pi / 6, np.pi / 3):
                pts += [
                    centre
                    + np.array(
                        [
                            bowl_r * np.cos(el) * np.cos(a),
                            bowl_r * np.cos(el) * np.sin(a),
                            -bowl_d * np.sin(el),
                        ]
                    )
                    for a in np.linspace(0, 2 * np.pi, 8, endpoint=False) + np.pi / 8
                ]
            pts.append(centre - [0, 0, bowl_d])
            parts.append(g.hull(np.array(pts)))
            params.update(head_width=2 * bowl_r, head_length=2 * bowl_r, bowl_depth=bowl_d)
        else:
            bowl_l = _uniform(rng, 0.05, 0.08)
            bowl_w = _uniform(rng, 0.035, 0.055)
            bowl_t = _uniform(rng, 0.006, 0.012)
            drop = _uniform(rng, 0.0, 0.3) * bowl_t
            centre = np.array([length + 0.35 * bowl_l, 0, -drop])
            parts.append(
                g.ellipsoid(centre, [bowl_l / 2, bowl_w / 2, bowl_t / 2], rings=3, sides=8)
            )
            params.update(head_width=bowl_w, head_length=bowl_l)
    if hang == "hole":
        loops = [_fit_loop(parts, [0, 0, 0], Z_AXIS, thick / 2 + 0.003)]
        params["hole_radius"] = hole_r
    else:
        normal = Z_AXIS if rng.uniform() < 0.5 else Y_AXIS
        ring, centre, ring_r, wire = _end_ring(rng, normal)
        parts += ring
        loops = [_fit_loop(parts, centre, normal, wire + 0.003)]
        params["ring_radius"] = ring_r
    params.update(style=style, hang=hang, handle_length=length)
    return AssetSpec(parts=parts, features=loops, params=params)


@register_object("headphone")
def headphone(rng: np.random.Generator) -> AssetSpec:
    """Over-ear headphones in the xz-plane: a headband arc (round tube or flat band of boxes),
    yokes, and two ear cups (cylinders or oval hulls) with cushions facing each other.

    Hangs by the band: a rod through the opening under the band (axis +y) rests at its top.
    """
    head_half = _uniform(rng, 0.062, 0.08)  # cushion face to the middle
    cushion = _uniform(rng, 0.01, 0.025)
    cup_t = _uniform(rng, 0.015, 0.03)
    cup_r = _uniform(rng, 0.03, 0.048)
    yoke = _uniform(rng, 0.008, 0.03)
    tall = _uniform(rng, 1.0, 1.3)  # band height / band half-width
    band_style = _choice(rng, ["round", "flat"])
    cup_style = _choice(rng, ["round", "oval"])
    x_band = head_half + cushion + 0.5 * cup_t
    pts = _ellipse([0, 0, 0], X_AXIS, Z_AXIS, x_band, tall * x_band, 0.0, np.pi, 11)
    parts: list[Part] = []
    if band_style == "round":
        band_r = _uniform(rng, 0.004, 0.008)
        parts += _tube(pts, band_r)
        band_half_y = band_r
    else:
        band_w = _uniform(rng, 0.015, 0.035)
        band_t = _uniform(rng, 0.004, 0.008)
        band_r = band_t / 2
        for p, q in zip(pts[:-1], pts[1:]):
            tangent = (q - p) / np.linalg.norm(q - p)
            rot = _plane_frame(tangent, Y_AXIS)
            half = [np.linalg.norm(q - p) / 2 + 0.002, band_w / 2, band_t / 2]
            parts.append(g.box((p + q) / 2, half, rot))
        band_half_y = band_w / 2
    z_cup = -yoke - cup_r
    yoke_r = _uniform(rng, 0.003, 0.006)
    oval = _uniform(rng, 0.7, 0.9)
    for sgn in (-1, 1):
        parts.append(
            g.capsule([sgn * x_band, 0, 0], [sgn * x_band, 0, z_cup + 0.5 * cup_r], yoke_r)
        )
        x_in, x_out = sgn * (head_half + cushion - 0.001), sgn * (head_half + cushion + cup_t)
        if cup_style == "round":
            parts.append(g.cylinder([x_in, 0, z_cup], [x_out, 0, z_cup], cup_r, sides=12))
        else:
            parts.append(
                g.hull(
                    np.concatenate(
                        [
                            _ellipse_section(x, oval * cup_r, cup_r, z_cup, sides=12)
                            for x in (x_in, x_out)
                        ]
                    )
                )
            )
        pad_r = cup_r * _uniform(rng, 0.8, 0.95)
        half_y, half_z = (pad_r, pad_r) if cup_style == "round" else (oval * pad_r, pad_r)
        parts.append(
            g.hull(
                np.concatenate(
                    [
                        _ellipse_section(sgn * head_half, 0.85 * half_y, 0.85 * half_z, z_cup, 10),
                        _ellipse_section(sgn * (head_half + cushion), half_y, half_z, z_cup, 10),
                    ]
                )
            )
        )
    loop = _fit_loop(
        parts,
        [0, 0, 0.35 * tall * x_band],
        Y_AXIS,
        band_half_y + 0.003,
        span=0.5 * x_band,
    )
    return AssetSpec(
        parts=parts,
        features=[loop],
        params=dict(
            band_style=band_style,
            cup_style=cup_style,
            head_half_width=head_half,
            band_height=tall * x_band,
            cup_radius=cup_r,
            band_radius=band_r,
        ),
    )


@register_object("knife")
def knife(rng: np.random.Generator) -> AssetSpec:
    """A kitchen knife along +x in the xz-plane: a thin blade tapering from spine to edge, an
    oval handle, and an eyelet with a hole at the handle end.

    Styles: chef, utility, bread, cleaver. Hangs by the hole (axis +y).
    """
    style = _choice(rng, ["chef", "utility", "bread", "cleaver"])
    blade_l, blade_h = {
        "chef": (_uniform(rng, 0.15, 0.24), _uniform(rng, 0.035, 0.052)),
        "utility": (_uniform(rng, 0.08, 0.14), _uniform(rng, 0.018, 0.03)),
        "bread": (_uniform(rng, 0.18, 0.25), _uniform(rng, 0.025, 0.035)),
        "cleaver": (_uniform(rng, 0.14, 0.2), _uniform(rng, 0.07, 0.1)),
    }[style]
    spine_t = _uniform(rng, 0.0015, 0.003)
    edge_t = 0.0004
    if style == "cleaver":
        outline = [
            (0, 0),
            (blade_l, 0),
            (blade_l, -0.85 * blade_h),
            (0.93 * blade_l, -blade_h),
            (0, -blade_h),
        ]
    else:
        tip_z = -_uniform(rng, 0.25, 0.55) * blade_h
        power = _uniform(rng, 2.0, 4.0) if style != "bread" else _uniform(rng, 5.0, 8.0)
        outline = [(0, 0), (_uniform(rng, 0.55, 0.8) * blade_l, 0), (blade_l, tip_z)]
        outline += [
            (s * blade_l, -blade_h + (blade_h + tip_z) * s**power) for s in np.linspace(0.93, 0, 7)
        ]
    blade_pts = []
    for x, z in outline:
        t = edge_t + (spine_t - edge_t) * np.clip(1 + z / blade_h, 0, 1)
        blade_pts += [[x, t / 2, z], [x, -t / 2, z]]
    parts: list[Part] = [g.hull(np.array(blade_pts, float))]
    handle_l = _uniform(rng, 0.09, 0.13)
    handle_h = _uniform(rng, 0.02, 0.03)
    handle_w = _uniform(rng, 0.012, 0.02)
    handle_z = -handle_h / 2 + _uniform(rng, -0.004, 0.002)
    flare = _uniform(rng, 1.0, 1.15)
    parts.append(
        g.hull(
            np.concatenate(
                [
                    _ellipse_section(0.012, handle_w / 2, handle_h / 2, handle_z),
                    _ellipse_section(
                        -handle_l, flare * handle_w / 2, flare * handle_h / 2, handle_z
                    ),
                ]
            )
        )
    )
    if rng.uniform() < 0.5:  # bolster
        parts.append(g.box([0.0, 0, handle_z], [0.006, 0.45 * handle_w, 0.55 * handle_h]))
    hole_r = _uniform(rng, 0.009, 0.012)
    outer_r = hole_r + _uniform(rng, 0.004, 0.007)
    eyelet_t = handle_w * _uniform(rng, 0.5, 0.9)
    centre = np.array([-handle_l - hole_r - 0.3 * (outer_r - hole_r), 0.0, handle_z])
    parts += _annulus(centre, _plane_frame(X_AXIS, Z_AXIS), hole_r, outer_r, eyelet_t, segments=8)
    loop = _fit_loop(parts, centre, Y_AXIS, eyelet_t / 2 + 0.003)
    return AssetSpec(
        parts=parts,
        features=[loop],
        params=dict(
            style=style,
            blade_length=blade_l,
            blade_height=blade_h,
            spine_thickness=spine_t,
            handle_length=handle_l,
            hole_radius=hole_r,
        ),
    )


@register_object("racquet")
def racquet(rng: np.random.Generator) -> AssetSpec:
    """A racquet along +z in the xz-plane: capsule head frame, a thin string-bed hull, throat,
    shaft and octagonal handle.

    Styles: tennis and squash (open triangular throat; hangs through it), badminton (T-joint
    and steel shaft; hangs by a wrist loop at the butt). Tennis and squash racquets may carry
    a wrist loop too. Axis of every loop: +y.
    """
    style = _choice(rng, ["tennis", "squash", "badminton"])
    parts: list[Part] = []
    loops: list[HangLoop] = []
    if style == "badminton":
        a, b = _uniform(rng, 0.092, 0.105), _uniform(rng, 0.112, 0.125)
        frame_r = _uniform(rng, 0.0025, 0.0035)
        handle_l = _uniform(rng, 0.15, 0.18)
        handle_r = _uniform(rng, 0.011, 0.013)
        shaft_l = _uniform(rng, 0.2, 0.24)
        parts.append(g.frustum([0, 0, 0], [0, 0, handle_l], handle_r, 0.75 * handle_r, sides=8))
        shaft_top = handle_l + shaft_l
        parts.append(
            g.capsule([0, 0, handle_l - 0.01], [0, 0, shaft_top], _uniform(rng, 0.0035, 0.0045))
        )
        parts.append(g.capsule([0, 0, shaft_top], [0, 0, shaft_top + 0.025], 1.3 * frame_r))
        head_c = np.array([0, 0, shaft_top + 0.025 + b])
        angles = np.linspace(-np.pi / 2, 1.5 * np.pi, 17)[:-1]
        head = head_c + np.stack([a * np.cos(angles), 0 * angles, b * np.sin(angles)], 1)
        throat = 0.0
    else:
        if style == "tennis":
            a, b = _uniform(rng, 0.115, 0.135), _uniform(rng, 0.15, 0.175)
            frame_r = _uniform(rng, 0.006, 0.009)
            handle_l, handle_r = _uniform(rng, 0.17, 0.2), _uniform(rng, 0.013, 0.016)
            throat = _uniform(rng, 0.09, 0.13)
        else:
            a, b = _uniform(rng, 0.095, 0.11), _uniform(rng, 0.135, 0.155)
            frame_r = _uniform(rng, 0.005, 0.007)
            handle_l, handle_r = _uniform(rng, 0.17, 0.2), _uniform(rng, 0.011, 0.014)
            throat = _uniform(rng, 0.12, 0.17)
        phi = _deg(rng, 30, 48)  # where the throat arms meet the head, from its bottom
        parts.append(g.cylinder([0, 0, 0], [0, 0, handle_l], handle_r, sides=8))
        apex = np.array([0, 0, handle_l + 0.005])
        parts.append(g.capsule([0, 0, handle_l - 0.01], apex, 0.8 * handle_r))
        head_c = apex + [0, 0, throat + b * np.cos(phi)]
        # The head: the ellipse above the arms, closed below by a flatter bridge.
        main = np.linspace(-np.pi / 2 + phi, 1.5 * np.pi - phi, 13)
        head_main = head_c + np.stack([a * np.cos(main), 0 * main, b * np.sin(main)], 1)
        right, left = head_main[0], head_main[-1]
        sag = min(_uniform(rng, 0.0, 0.35) * b * (1 - np.cos(phi)), 0.3 * throat)
        s_br = np.linspace(-1, 1, 5)[:-1]
        bridge = np.stack([right[0] * s_br, 0 * s_br, right[2] - sag * (1 - s_br**2)], axis=1)
        head = np.concatenate([bridge, head_main[:-1]])
        arm_r = frame_r * _uniform(rng, 0.9, 1.15)
        parts += [g.capsule(apex, left, arm_r), g.capsule(apex, right, arm_r)]
        throat_guess = (apex + left + right) / 3
        throat_span = 0.25 * np.linalg.norm(right - left)
    parts += _tube(head, frame_r, closed=True)
    # String bed: a 2 mm plate filling the head, its rim inside the frame tube.
    inward = head - head_c
    inward /= np.linalg.norm(inward, axis=1, keepdims=True)
    bed = (head - 0.5 * frame_r * inward)[:, None, :] + np.array([[0, -0.001, 0], [0, 0.001, 0]])
    parts.append(g.hull(bed.reshape(-1, 3)))
    butt_z = -0.006
    parts.append(g.cylinder([0, 0, butt_z], [0, 0, 0.004], 1.1 * handle_r, sides=8))
    if style == "badminton" or rng.uniform() < 0.3:  # wrist loop at the butt
        loop_r = _uniform(rng, 0.018, 0.03)
        wire = _uniform(rng, 0.002, 0.003)
        centre = np.array([0, 0, butt_z + 0.5 * wire - loop_r])
        parts += _ellipse_ring(centre, X_AXIS, Z_AXIS, loop_r, loop_r, wire, 8)
        loops.append(_fit_loop(parts, centre, Y_AXIS, wire + 0.003))
    if style != "badminton":  # the open throat: the largest circle in the triangle
        loops.insert(0, _fit_loop(parts, throat_guess, Y_AXIS, frame_r + 0.003, throat_span))
    return AssetSpec(
        parts=parts,
        features=loops,
        params=dict(
            style=style,
            head_half_width=a,
            head_half_length=b,
            frame_radius=frame_r,
            handle_length=handle_l,
            throat=throat,
        ),
    )


@register_object("scissors")
def scissors(rng: np.random.Generator) -> AssetSpec:
    """Scissors in the xy-plane: two blade plates crossing at a pivot screw (slightly open),
    shanks and two finger rings (round, or one long ring for several fingers).

    Each half lies in its own layer (z = +-0.45 t). Hangs by either finger ring (axis +z).
    """
    blade_l = _uniform(rng, 0.055, 0.12)
    blade_w = _uniform(rng, 0.01, 0.02)
    thick = _uniform(rng, 0.0015, 0.003)
    opening = _deg(rng, 0, 24)
    ring_t = _uniform(rng, 0.0025, 0.004)
    shank = _uniform(rng, 0.012, 0.03)
    gap = _uniform(rng, 0.002, 0.008)
    style = _choice(rng, ["round", "long"])
    small = _uniform(rng, 0.014, 0.018)
    rings = [(small * _uniform(rng, 1.0, 1.15), small)]
    if style == "long":
        rings.append((_uniform(rng, 0.02, 0.032), _uniform(rng, 0.014, 0.017)))
    else:
        rings.append((small * _uniform(rng, 1.0, 1.15), small))
    parts: list[Part] = []
    loops = []
    pivot_r = _uniform(rng, 0.003, 0.0055)
    parts.append(g.cylinder([0, 0, -1.2 * thick], [0, 0, 1.2 * thick], pivot_r, sides=10))
    blade_outline = np.array(
        [
            [-0.012, -blade_w / 2],
            [-0.012, blade_w / 2],
            [0.55 * blade_l, 0.4 * blade_w],
            [blade_l, 0.0015],
            [blade_l, -0.0015],
            [0.8 * blade_l, -0.25 * blade_w],
        ]
    )
    for sgn, (rx, ry) in zip((1, -1), rings):
        rot = _rot_z(-sgn * opening / 2)  # the +y ring's blade turns down: an X
        z = sgn * 0.45 * thick
        frame = rot @ np.diag([1.0, sgn, 1.0])
        parts.append(g.prism(blade_outline, thick, frame, [0, 0, z]))
        local_c = np.array([-shank - rx, sgn * (ry + ring_t + gap / 2), 0.0])
        centre = rot @ local_c + [0, 0, z]
        ring = _ellipse_ring(centre, rot @ X_AXIS, rot @ Y_AXIS, rx, ry, ring_t, 8)
        near = min((p.p0 for p in ring), key=lambda p: np.linalg.norm(p[:2]))
        parts.append(g.capsule([0, 0, z], near, ring_t * 0.9))
        parts += ring
        loops.append(centre)
    features = [_fit_loop(parts, c, Z_AXIS, ring_t + 0.003) for c in loops]
    return AssetSpec(
        parts=parts,
        features=features,
        params=dict(
            style=style,
            blade_length=blade_l,
            blade_width=blade_w,
            thickness=thick,
            opening=opening,
            ring_radii=[list(r) for r in rings],
        ),
    )


@register_object("wrench")
def wrench(rng: np.random.Generator) -> AssetSpec:
    """A spanner in the xy-plane.

    Styles: combination (box ring at x = 0, open jaw at x = L), double_box (two rings of
    different size), adjustable (round head with two jaws, long handle with a hang hole).
    Hangs by a ring hole (axis +z).
    """
    style = _choice(rng, ["combination", "double_box", "adjustable"])
    size = _uniform(rng, 0.017, 0.027)  # nut size across flats
    thick = _uniform(rng, 0.004, 0.008)
    length = size * _uniform(rng, 9.0, 13.0)
    parts: list[Part] = []
    holes = []  # (centre, ring thickness)
    w_near = size * _uniform(rng, 0.45, 0.65)
    w_far = w_near * _uniform(rng, 1.0, 1.3)
    if style in ("combination", "double_box"):
        r_in = 0.51 * size
        r_out = r_in + size * _uniform(rng, 0.3, 0.45)
        ring_t = thick * _uniform(rng, 1.1, 1.4)
        parts += _annulus([0, 0, 0], np.eye(3), r_in, r_out, ring_t, segments=10)
        holes.append((np.zeros(3), ring_t))
        if style == "combination":
            jaw_in = size / 2
            jaw_out = jaw_in + size * _uniform(rng, 0.4, 0.55)
            tilt = _deg(rng, 10, 20)
            frame = _rot_z(tilt)
            centre = np.array([length, 0, 0])
            parts += _annulus(centre, frame, jaw_in, jaw_out, thick, 4, np.pi / 2, 1.5 * np.pi)
            prong = size * _uniform(rng, 0.45, 0.6)
            for sgn in (-1, 1):
                outline = np.array(
                    [
                        [-0.002, sgn * jaw_in],
                        [prong, sgn * jaw_in],
                        [prong, sgn * (jaw_in + 0.6 * (jaw_out - jaw_in))],
                        [-0.002, sgn * jaw_out],
                    ]
                )
                parts.append(g.prism(outline, thick, frame, centre))
            x_far = length - 0.5 * (jaw_in + jaw_out)
        else:
            size2 = size * _uniform(rng, 0.75, 0.92)
            r2_in = 0.51 * size2
            r2_out = r2_in + size2 * _uniform(rng, 0.3, 0.45)
            centre = np.array([length, 0, 0])
            parts += _annulus(centre, np.eye(3), r2_in, r2_out, ring_t, segments=10)
            if r2_in >= MIN_OPENING + 0.0005:
                holes.append((centre, ring_t))
            x_far = length - 0.5 * (r2_in + r2_out)
        x_near = 0.75 * r_out
        params = dict(ring_inner_radius=r_in)
    else:
        head_r = size * _uniform(rng, 0.9, 1.2)
        parts.append(g.cylinder([0, 0, -0.65 * thick], [0, 0, 0.65 * thick], head_r, sides=12))
        jaw_w = size * _uniform(rng, 0.4, 0.55)
        jaw_l = size * _uniform(rng, 0.7, 1.0)
        x0 = np.sqrt(max(head_r**2 - (size / 2) ** 2, 0.0))
        for sgn, shorten in ((1, 1.0), (-1, _uniform(rng, 0.8, 0.95))):
            parts.append(
                g.box(
                    [x0 + 0.5 * shorten * jaw_l - 0.003, sgn * (size / 2 + jaw_w / 2), 0],
                    [0.5 * shorten * jaw_l + 0.003, jaw_w / 2, 0.6 * thick],
                )
            )
        worm_r = 0.3 * size
        parts.append(
            g.cylinder([0.2 * head_r, -head_r, 0], [0.2 * head_r, -0.5 * head_r, 0], worm_r, 8)
        )
        hole_r = _uniform(rng, 0.009, 0.011)
        r_out = max(hole_r + _uniform(rng, 0.004, 0.007), 0.5 * w_far + 0.001)
        centre = np.array([-length - hole_r - 0.3 * (r_out - hole_r), 0, 0])
        parts += _annulus(centre, np.eye(3), hole_r, r_out, thick, segments=8)
        holes.append((centre, thick))
        # Handle runs towards -x: mirror the shaft stations.
        x_near, x_far = -0.5 * head_r, -length
        params = dict(hole_radius=hole_r)
    parts.append(
        g.hull(
            np.concatenate(
                [
                    _rect_section(x_near, w_near, thick),
                    _rect_section(x_far, w_far, thick),
                ]
            )
        )
    )
    features = [_fit_loop(parts, c, Z_AXIS, t / 2 + 0.003) for c, t in holes]
    params.update(style=style, size=size, thickness=thick, length=length)
    return AssetSpec(parts=parts, features=features, params=params)


def _key_ring(rng: np.random.Generator):
    """A split ring (xz-plane) with 1-3 flat keys hanging from its bottom, radially."""
    ring_r = _uniform(rng, 0.012, 0.02)
    wire = _uniform(rng, 0.0012, 0.002)
    parts: list[Part] = list(_ellipse_ring([0, 0, 0], X_AXIS, -Z_AXIS, ring_r, ring_r, wire, 12))
    n_keys = int(rng.integers(1, 4))
    thetas = {1: [90.0], 2: [60.0, 120.0], 3: [60.0, 90.0, 120.0]}[n_keys]
    key_len = 0.0
    for theta in np.deg2rad(thetas):
        radial = np.array([np.cos(theta), 0.0, -np.sin(theta)])
        at = ring_r * radial  # a ring vertex (every 30 degrees)
        bow_r = _uniform(rng, 0.009, 0.014)
        key_t = _uniform(rng, 0.0015, 0.0025)
        blade = _uniform(rng, 0.025, 0.045)
        key_w = _uniform(rng, 0.006, 0.01)
        frame = _plane_frame(radial, Y_AXIS)  # the key's plane holds the radial direction
        bow_c = at + (bow_r - 0.5 * wire) * radial  # the wire runs through the bow's top
        ang = np.linspace(0, 2 * np.pi, 10, endpoint=False)
        parts.append(g.prism(bow_r * np.stack([np.cos(ang), np.sin(ang)], 1), key_t, frame, bow_c))
        outline = np.array(
            [
                [0.6 * bow_r, -key_w / 2],
                [0.6 * bow_r, key_w / 2],
                [bow_r + blade - key_w / 2, key_w / 2],
                [bow_r + blade, 0.0],
                [bow_r + blade - key_w / 2, -key_w / 2],
            ]
        )
        parts.append(g.prism(outline, key_t, frame, bow_c))
        key_len = max(key_len, bow_r + blade)
    loop = _fit_loop(parts, [0, 0, 0], Y_AXIS, wire + 0.003)
    return parts, [loop], dict(ring_radius=ring_r, keys=n_keys, key_length=key_len)


def _towel(rng: np.random.Generator):
    """A folded towel (thin slab, xz-plane) with a fabric loop (tube arch) on its top edge."""
    width = _uniform(rng, 0.25, 0.5)
    height = _uniform(rng, 0.3, 0.6)
    thick = _uniform(rng, 0.004, 0.012)
    loop_a = _uniform(rng, 0.016, 0.03)
    loop_h = _uniform(rng, 0.035, 0.065)
    tube_r = _uniform(rng, 0.002, 0.0035)
    x_loop = 0.0 if rng.uniform() < 0.5 else _uniform(rng, -1, 1) * (width / 2 - loop_a - 0.01)
    parts: list[Part] = [g.box([0, 0, -height / 2], [width / 2, thick / 2, height / 2])]
    arch = _arch(loop_a, loop_h + 1.5 * tube_r, 0.0, -1.5 * tube_r, 9) + [x_loop, 0, 0]
    parts += _tube(arch, tube_r)
    loop = _fit_loop(
        parts,
        [x_loop, 0, 0.45 * loop_h],
        Y_AXIS,
        tube_r + 0.003,
        span=0.9 * min(loop_a, loop_h / 2),
    )
    return parts, [loop], dict(width=width, height=height, thickness=thick, loop_height=loop_h)


def _basket(rng: np.random.Generator):
    """A basket (round frustum or rectangular hull) with a handle arc over its top."""
    height = _uniform(rng, 0.06, 0.14)
    tube_r = _uniform(rng, 0.004, 0.008)
    handle_h = _uniform(rng, 0.08, 0.18)
    if rng.uniform() < 0.5:
        r0 = _uniform(rng, 0.07, 0.14)
        r1 = r0 * _uniform(rng, 1.0, 1.25)
        parts: list[Part] = [g.frustum([0, 0, 0], [0, 0, height], r0, r1, sides=14)]
        z_end = height - 2 * tube_r
        half = r0 + (r1 - r0) * z_end / height - 1.5 * tube_r
        half *= np.cos(np.pi / 14)  # stay inside the 14-gon
        shape = "round"
    else:
        length, depth = _uniform(rng, 0.14, 0.3), _uniform(rng, 0.1, 0.2)
        flare = _uniform(rng, 1.0, 1.15)
        corners = [
            [sx * lx / 2, sy * ly / 2, z]
            for (lx, ly, z) in ((length, depth, 0.0), (flare * length, flare * depth, height))
            for sx in (-1, 1)
            for sy in (-1, 1)
        ]
        parts = [g.hull(np.array(corners))]
        z_end = height - 2 * tube_r
        half = length / 2 - 1.5 * tube_r
        shape = "rectangular"
    parts += _tube(_arch(half, handle_h + 2 * tube_r, 0.0, z_end, 11), tube_r)
    loop = _fit_loop(
        parts, [0, 0, height + 0.4 * handle_h], Y_AXIS, tube_r + 0.003, 0.9 * min(half, handle_h)
    )
    return parts, [loop], dict(shape=shape, height=height, handle_height=handle_h)


def _lanyard(rng: np.random.Generator):
    """A badge card (xz-plane) on a clip, hanging from a long rigid lanyard loop."""
    card_w = _uniform(rng, 0.05, 0.07)
    card_h = _uniform(rng, 0.07, 0.1)
    card_t = _uniform(rng, 0.0015, 0.003)
    clip_h = _uniform(rng, 0.008, 0.015)
    loop_a = _uniform(rng, 0.03, 0.07)
    loop_b = _uniform(rng, 0.1, 0.2)
    wire = _uniform(rng, 0.002, 0.004)
    parts: list[Part] = [
        g.box([0, 0, 0], [card_w / 2, card_t / 2, card_h / 2]),
        g.box([0, 0, card_h / 2 + clip_h / 2 - 0.002], [0.006, 0.003, clip_h / 2 + 0.002]),
    ]
    centre = np.array([0, 0, card_h / 2 + clip_h - 0.5 * wire + loop_b])
    parts += _ellipse_ring(centre, X_AXIS, Z_AXIS, loop_a, loop_b, wire, 12)
    loop = _fit_loop(parts, centre, Y_AXIS, wire + 0.003)
    return parts, [loop], dict(card_height=card_h, loop_width=2 * loop_a, loop_length=2 * loop_b)


def _umbrella(rng: np.random.Generator):
    """A closed stick umbrella along +z: shaft, folded canopy hulls, tip, J crook below."""
    shaft_l = _uniform(rng, 0.4, 0.55)
    shaft_r = _uniform(rng, 0.004, 0.007)
    canopy_r = _uniform(rng, 0.025, 0.045)
    z0 = shaft_l * _uniform(rng, 0.15, 0.3)  # where the gathered canopy starts
    z1 = z0 + 0.25 * (shaft_l - z0)  # its widest section
    tip = _uniform(rng, 0.02, 0.05)
    parts: list[Part] = [
        g.capsule([0, 0, -0.01], [0, 0, shaft_l], shaft_r),
        g.frustum([0, 0, z0], [0, 0, z1], 1.2 * shaft_r, canopy_r, sides=10),
        g.frustum([0, 0, z1 - 0.001], [0, 0, shaft_l], canopy_r, 1.5 * shaft_r, sides=10),
        g.capsule([0, 0, shaft_l], [0, 0, shaft_l + tip], 0.6 * shaft_r),
    ]
    crook_r = _uniform(rng, 0.028, 0.045)
    tube_r = _uniform(rng, 0.008, 0.013)
    hook, centre, axis = _j_hook(
        [0, 0, 0], -Z_AXIS, X_AXIS, _uniform(rng, 0.01, 0.03), crook_r, _deg(rng, 0, 40), tube_r
    )
    parts += hook
    loop = _fit_loop(parts, centre, axis, tube_r + 0.003)
    return parts, [loop], dict(length=shaft_l + tip, canopy_radius=canopy_r, crook_radius=crook_r)


_DAILY_OBJECTS = {
    "key_ring": _key_ring,
    "towel": _towel,
    "basket": _basket,
    "lanyard": _lanyard,
    "umbrella": _umbrella,
}


@register_object("others")
def others(rng: np.random.Generator) -> AssetSpec:
    """Daily objects (the paper's "others"), one kind drawn per seed: a key ring with keys, a
    towel with a hanging loop, a basket with a handle arc, a badge on a lanyard loop, or a
    stick umbrella with a J crook. Each hangs by its loop, handle or crook.
    """
    kind = _choice(rng, list(_DAILY_OBJECTS))
    parts, loops, params = _DAILY_OBJECTS[kind](rng)
    return AssetSpec(parts=parts, features=loops, params=dict(kind=kind, **params))
