"""Procedural generators of the tool categories: cooking utensil, knife, scissors, wrench
(the other object categories: :mod:`sim.assets.objects`, which imports this module)."""

from __future__ import annotations

import numpy as np

from sim import geometry as g
from sim.assets import object_parts as op
from sim.assets.base import AssetSpec, register_object
from sim.assets.object_parts import MIN_OPENING, X_AXIS, Y_AXIS, Z_AXIS
from sim.geometry import Part

# ----------------------------------------------------------------------------- categories


def _end_ring(rng: np.random.Generator, normal: np.ndarray, tube_max: float = 0.0028):
    """A hanging ring whose +x vertex sits 0.5 tube radii past x = 0 (into a handle end).

    Returns (parts, centre): the ring's inner surface stays at x < 0, clear of the handle.
    """
    ring_r = op.uniform(rng, 0.013, 0.02)
    wire = op.uniform(rng, 0.0015, tube_max)
    centre = np.array([-(ring_r - 0.5 * wire), 0.0, 0.0])
    ring = op.ellipse_ring(centre, X_AXIS, np.cross(normal, X_AXIS), ring_r, ring_r, wire, 8)
    return ring, centre, ring_r, wire


@register_object("cooking_utensil")
def cooking_utensil(rng: np.random.Generator) -> AssetSpec:
    """A kitchen utensil along +x: a handle from x = 0 and a head beyond it.

    Heads: spatula (thin bent plate), ladle (deep bowl hull), spoon (flat ellipsoid bowl),
    whisk (wire loops meeting at the tip). Hangs by a hole through the flat handle's end or by
    a hanging ring at the handle end (whisks always by a ring).
    """
    style = op.choice(rng, ["spatula", "ladle", "spoon", "whisk"])
    hang = "ring" if style == "whisk" else op.choice(rng, ["hole", "ring"])
    parts: list[Part] = []
    if style == "whisk":
        length = op.uniform(rng, 0.09, 0.15)
        handle_r = op.uniform(rng, 0.01, 0.016)
        parts.append(g.cylinder([0, 0, 0], [length, 0, 0], handle_r, sides=12))
        parts.append(
            g.frustum(
                [length - 0.002, 0, 0], [length + 0.018, 0, 0], handle_r, 0.5 * handle_r, sides=10
            )
        )
        n_loops = int(rng.integers(3, 5))
        head_len = op.uniform(rng, 0.12, 0.2)
        head_r = op.uniform(rng, 0.022, 0.04)
        wire = op.uniform(rng, 0.0008, 0.0015)
        base = np.array([length + 0.012, 0, 0])
        tip = np.array([length + 0.012 + head_len, 0, 0])
        for j in range(n_loops):
            d = np.array([0.0, np.cos(np.pi * j / n_loops), np.sin(np.pi * j / n_loops)])
            # A balloon loop: narrow at the handle, widest near the far end, round at the tip.
            a = base + [0.5 * head_len, 0, 0] + 0.8 * head_r * d
            b = base + [0.85 * head_len, 0, 0] + 0.95 * head_r * d
            a2 = a - 1.6 * head_r * d  # the same wire on the other side of the axis
            b2 = b - 1.9 * head_r * d
            parts += op.tube(np.array([base, a, b, tip, b2, a2]), wire, closed=True)
        params = dict(
            handle_radius=handle_r, loops=n_loops, head_length=head_len, head_radius=head_r
        )
    else:
        length = op.uniform(rng, 0.2, 0.3) if style == "ladle" else op.uniform(rng, 0.13, 0.25)
        handle_w = op.uniform(rng, 0.014, 0.026)
        thick = op.uniform(rng, 0.006, 0.011) if style == "spoon" else op.uniform(rng, 0.004, 0.009)
        tip_w = handle_w * op.uniform(rng, 0.5, 0.8)
        params = dict(handle_width=handle_w, handle_thickness=thick)
        if hang == "hole":
            hole_r = op.uniform(rng, 0.009, 0.013)
            outer_r = max(hole_r + op.uniform(rng, 0.004, 0.008), 0.5 * handle_w + 0.002)
            parts += op.annulus([0, 0, 0], np.eye(3), hole_r, outer_r, thick, segments=8)
            x0 = hole_r + 0.3 * (outer_r - hole_r)
        else:
            x0 = 0.0
        parts.append(
            g.hull(
                np.concatenate(
                    [op.rect_section(x0, handle_w, thick), op.rect_section(length, tip_w, thick)]
                )
            )
        )
        if style == "spatula":
            neck = op.uniform(rng, 0.02, 0.05)
            plate_w = op.uniform(rng, 0.05, 0.09)
            plate_l = op.uniform(rng, 0.06, 0.11)
            plate_t = op.uniform(rng, 0.002, 0.004)
            bend = op.deg(rng, 0, 25)
            corner = op.uniform(rng, 0.005, 0.02)
            start = np.array([length + neck, 0.0, -neck * np.tan(0.5 * bend)])
            parts.append(
                g.hull(
                    np.concatenate(
                        [
                            op.rect_section(length - 0.005, tip_w, thick),
                            op.rect_section(0.0, 0.4 * plate_w, plate_t) + start,
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
            parts.append(g.prism(outline, plate_t, op.rot_y(bend), start))
            params.update(head_width=plate_w, head_length=plate_l, bend=bend)
        elif style == "ladle":
            bowl_r = op.uniform(rng, 0.035, 0.05)
            bowl_d = bowl_r * op.uniform(rng, 0.6, 1.0)
            drop = op.uniform(rng, 0.02, 0.05)
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
            bowl_l = op.uniform(rng, 0.05, 0.08)
            bowl_w = op.uniform(rng, 0.035, 0.055)
            bowl_t = op.uniform(rng, 0.006, 0.012)
            drop = op.uniform(rng, 0.0, 0.3) * bowl_t
            centre = np.array([length + 0.35 * bowl_l, 0, -drop])
            parts.append(
                g.ellipsoid(centre, [bowl_l / 2, bowl_w / 2, bowl_t / 2], rings=3, sides=8)
            )
            params.update(head_width=bowl_w, head_length=bowl_l)
    if hang == "hole":
        loops = [op.fit_loop(parts, [0, 0, 0], Z_AXIS, thick / 2 + 0.003)]
        params["hole_radius"] = hole_r
    else:
        normal = Z_AXIS if rng.uniform() < 0.5 else Y_AXIS
        ring, centre, ring_r, wire = _end_ring(rng, normal)
        parts += ring
        loops = [op.fit_loop(parts, centre, normal, wire + 0.003)]
        params["ring_radius"] = ring_r
    params.update(style=style, hang=hang, handle_length=length)
    return AssetSpec(parts=parts, features=loops, params=params)


@register_object("knife")
def knife(rng: np.random.Generator) -> AssetSpec:
    """A kitchen knife along +x in the xz-plane: a thin blade tapering from spine to edge, an
    oval handle, and an eyelet with a hole at the handle end.

    Styles: chef, utility, bread, cleaver. Hangs by the hole (axis +y).
    """
    style = op.choice(rng, ["chef", "utility", "bread", "cleaver"])
    blade_l, blade_h = {
        "chef": (op.uniform(rng, 0.15, 0.24), op.uniform(rng, 0.035, 0.052)),
        "utility": (op.uniform(rng, 0.08, 0.14), op.uniform(rng, 0.018, 0.03)),
        "bread": (op.uniform(rng, 0.18, 0.25), op.uniform(rng, 0.025, 0.035)),
        "cleaver": (op.uniform(rng, 0.14, 0.2), op.uniform(rng, 0.07, 0.1)),
    }[style]
    spine_t = op.uniform(rng, 0.0015, 0.003)
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
        tip_z = -op.uniform(rng, 0.25, 0.55) * blade_h
        power = op.uniform(rng, 2.0, 4.0) if style != "bread" else op.uniform(rng, 5.0, 8.0)
        outline = [(0, 0), (op.uniform(rng, 0.55, 0.8) * blade_l, 0), (blade_l, tip_z)]
        outline += [
            (s * blade_l, -blade_h + (blade_h + tip_z) * s**power) for s in np.linspace(0.93, 0, 7)
        ]
    blade_pts = []
    for x, z in outline:
        t = edge_t + (spine_t - edge_t) * np.clip(1 + z / blade_h, 0, 1)
        blade_pts += [[x, t / 2, z], [x, -t / 2, z]]
    parts: list[Part] = [g.hull(np.array(blade_pts, float))]
    handle_l = op.uniform(rng, 0.09, 0.13)
    handle_h = op.uniform(rng, 0.02, 0.03)
    handle_w = op.uniform(rng, 0.012, 0.02)
    handle_z = -handle_h / 2 + op.uniform(rng, -0.004, 0.002)
    flare = op.uniform(rng, 1.0, 1.15)
    parts.append(
        g.hull(
            np.concatenate(
                [
                    op.ellipse_section(0.012, handle_w / 2, handle_h / 2, handle_z),
                    op.ellipse_section(
                        -handle_l, flare * handle_w / 2, flare * handle_h / 2, handle_z
                    ),
                ]
            )
        )
    )
    if rng.uniform() < 0.5:  # bolster
        parts.append(g.box([0.0, 0, handle_z], [0.006, 0.45 * handle_w, 0.55 * handle_h]))
    hole_r = op.uniform(rng, 0.009, 0.012)
    outer_r = hole_r + op.uniform(rng, 0.004, 0.007)
    eyelet_t = handle_w * op.uniform(rng, 0.5, 0.9)
    centre = np.array([-handle_l - hole_r - 0.3 * (outer_r - hole_r), 0.0, handle_z])
    parts += op.annulus(
        centre, op.plane_frame(X_AXIS, Z_AXIS), hole_r, outer_r, eyelet_t, segments=8
    )
    loop = op.fit_loop(parts, centre, Y_AXIS, eyelet_t / 2 + 0.003)
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


@register_object("scissors")
def scissors(rng: np.random.Generator) -> AssetSpec:
    """Scissors in the xy-plane: two blade plates crossing at a pivot screw (slightly open),
    shanks and two finger rings (round, or one long ring for several fingers).

    Each half lies in its own layer (z = +-0.45 t). Hangs by either finger ring (axis +z).
    """
    blade_l = op.uniform(rng, 0.055, 0.12)
    blade_w = op.uniform(rng, 0.01, 0.02)
    thick = op.uniform(rng, 0.0015, 0.003)
    opening = op.deg(rng, 0, 24)
    ring_t = op.uniform(rng, 0.0025, 0.004)
    shank = op.uniform(rng, 0.012, 0.03)
    gap = op.uniform(rng, 0.002, 0.008)
    style = op.choice(rng, ["round", "long"])
    small = op.uniform(rng, 0.014, 0.018)
    rings = [(small * op.uniform(rng, 1.0, 1.15), small)]
    if style == "long":
        rings.append((op.uniform(rng, 0.02, 0.032), op.uniform(rng, 0.014, 0.017)))
    else:
        rings.append((small * op.uniform(rng, 1.0, 1.15), small))
    parts: list[Part] = []
    loops = []
    pivot_r = op.uniform(rng, 0.003, 0.0055)
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
        rot = op.rot_z(-sgn * opening / 2)  # the +y ring's blade turns down: an X
        z = sgn * 0.45 * thick
        frame = rot @ np.diag([1.0, sgn, 1.0])
        parts.append(g.prism(blade_outline, thick, frame, [0, 0, z]))
        local_c = np.array([-shank - rx, sgn * (ry + ring_t + gap / 2), 0.0])
        centre = rot @ local_c + [0, 0, z]
        ring = op.ellipse_ring(centre, rot @ X_AXIS, rot @ Y_AXIS, rx, ry, ring_t, 8)
        near = min((p.p0 for p in ring), key=lambda p: np.linalg.norm(p[:2]))
        parts.append(g.capsule([0, 0, z], near, ring_t * 0.9))
        parts += ring
        loops.append(centre)
    features = [op.fit_loop(parts, c, Z_AXIS, ring_t + 0.003) for c in loops]
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
    style = op.choice(rng, ["combination", "double_box", "adjustable"])
    size = op.uniform(rng, 0.017, 0.027)  # nut size across flats
    thick = op.uniform(rng, 0.004, 0.008)
    length = size * op.uniform(rng, 9.0, 13.0)
    parts: list[Part] = []
    holes = []  # (centre, ring thickness)
    w_near = size * op.uniform(rng, 0.45, 0.65)
    w_far = w_near * op.uniform(rng, 1.0, 1.3)
    if style in ("combination", "double_box"):
        r_in = 0.51 * size
        r_out = r_in + size * op.uniform(rng, 0.3, 0.45)
        ring_t = thick * op.uniform(rng, 1.1, 1.4)
        parts += op.annulus([0, 0, 0], np.eye(3), r_in, r_out, ring_t, segments=10)
        holes.append((np.zeros(3), ring_t))
        if style == "combination":
            jaw_in = size / 2
            jaw_out = jaw_in + size * op.uniform(rng, 0.4, 0.55)
            tilt = op.deg(rng, 10, 20)
            frame = op.rot_z(tilt)
            centre = np.array([length, 0, 0])
            parts += op.annulus(centre, frame, jaw_in, jaw_out, thick, 4, np.pi / 2, 1.5 * np.pi)
            prong = size * op.uniform(rng, 0.45, 0.6)
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
            size2 = size * op.uniform(rng, 0.75, 0.92)
            r2_in = 0.51 * size2
            r2_out = r2_in + size2 * op.uniform(rng, 0.3, 0.45)
            centre = np.array([length, 0, 0])
            parts += op.annulus(centre, np.eye(3), r2_in, r2_out, ring_t, segments=10)
            if r2_in >= MIN_OPENING + 0.0005:
                holes.append((centre, ring_t))
            x_far = length - 0.5 * (r2_in + r2_out)
        x_near = 0.75 * r_out
        params = dict(ring_inner_radius=r_in)
    else:
        head_r = size * op.uniform(rng, 0.9, 1.2)
        parts.append(g.cylinder([0, 0, -0.65 * thick], [0, 0, 0.65 * thick], head_r, sides=12))
        jaw_w = size * op.uniform(rng, 0.4, 0.55)
        jaw_l = size * op.uniform(rng, 0.7, 1.0)
        x0 = np.sqrt(max(head_r**2 - (size / 2) ** 2, 0.0))
        for sgn, shorten in ((1, 1.0), (-1, op.uniform(rng, 0.8, 0.95))):
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
        hole_r = op.uniform(rng, 0.009, 0.011)
        r_out = max(hole_r + op.uniform(rng, 0.004, 0.007), 0.5 * w_far + 0.001)
        centre = np.array([-length - hole_r - 0.3 * (r_out - hole_r), 0, 0])
        parts += op.annulus(centre, np.eye(3), hole_r, r_out, thick, segments=8)
        holes.append((centre, thick))
        # Handle runs towards -x: mirror the shaft stations.
        x_near, x_far = -0.5 * head_r, -length
        params = dict(hole_radius=hole_r)
    parts.append(
        g.hull(
            np.concatenate(
                [
                    op.rect_section(x_near, w_near, thick),
                    op.rect_section(x_far, w_far, thick),
                ]
            )
        )
    )
    features = [op.fit_loop(parts, c, Z_AXIS, t / 2 + 0.003) for c, t in holes]
    params.update(style=style, size=size, thickness=thick, length=length)
    return AssetSpec(parts=parts, features=features, params=params)
