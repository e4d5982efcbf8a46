"""Procedural generators for the 11 object categories of the paper: mug, bag, cap, clothes
hanger, headphone, racquet and "others" here; the tools (cooking utensil, knife, scissors,
wrench) in :mod:`sim.assets.objects_tools`, registered when this module is imported.

Each generator takes a ``numpy.random.Generator`` and returns an :class:`AssetSpec` of convex
parts at real size (metres) plus the :class:`HangLoop` features the object hangs by. Shapes vary
widely within a category (sizes, proportions, hole placement, thickness, style variants); the
recipes and ranges are documented in ``docs/library.md``. Hang loops are measured, not guessed
(:func:`sim.assets.object_parts.fit_loop`).
"""

from __future__ import annotations

import numpy as np

from sim import geometry as g
from sim.assets import object_parts as op
from sim.assets import objects_tools  # noqa: F401  (registers the tool categories)
from sim.assets.base import AssetSpec, HangLoop, register_object
from sim.assets.object_parts import X_AXIS, Y_AXIS, Z_AXIS
from sim.geometry import Part

# ----------------------------------------------------------------------------- categories


@register_object("mug")
def mug(rng: np.random.Generator) -> AssetSpec:
    """A mug: solid (tapered) body and a round-C or squared-D handle tube on its side.

    Hangs by the handle opening (axis = the handle plane's normal, +y).
    """
    radius = op.uniform(rng, 0.03, 0.05)
    height = op.uniform(rng, 0.07, 0.12)
    taper = op.uniform(rng, 0.8, 1.15)  # top radius / bottom radius
    tube_r = op.uniform(rng, 0.004, 0.0065)
    reach = op.uniform(rng, 0.032, 0.048)  # body wall to handle tube centre line
    handle_h = op.uniform(rng, 0.5, 0.75) * height  # vertical span of the handle
    handle_z = op.uniform(rng, -0.08, 0.08) * height  # handle centre relative to body centre
    style = op.choice(rng, ["round", "square"])
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
        chamfer = op.uniform(rng, 0.2, 0.45) * min(reach, handle_h / 2)
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
    parts = [body, *op.tube(pts, tube_r)]
    loop = op.fit_loop(
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


@register_object("bag")
def bag(rng: np.random.Generator) -> AssetSpec:
    """A bag: a trapezoid body with straps forming loops above it.

    Styles: tote (two handles, front and back), messenger (one long strap from side to side,
    front flap), handbag (one short thick handle). Hangs by each strap loop (axis +y).
    """
    style = op.choice(rng, ["tote", "messenger", "handbag"])
    width = op.uniform(rng, 0.24, 0.42)  # x, at the bottom
    depth = op.uniform(rng, 0.07, 0.16)  # y, at the bottom
    if style == "tote":
        height = op.uniform(rng, 0.22, 0.38)
        top_w, top_d = width * op.uniform(rng, 1.0, 1.15), depth * op.uniform(rng, 0.6, 1.0)
    elif style == "messenger":
        height = op.uniform(rng, 0.18, 0.3)
        top_w, top_d = width, depth
    else:
        height = op.uniform(rng, 0.16, 0.28)
        top_w, top_d = width * op.uniform(rng, 0.65, 0.9), depth * op.uniform(rng, 0.55, 0.9)
    corners = [
        [sx * w / 2, sy * d / 2, z]
        for (w, d, z) in ((width, depth, 0.0), (top_w, top_d, height))
        for sx in (-1, 1)
        for sy in (-1, 1)
    ]
    parts: list[Part] = [g.hull(np.array(corners))]
    loops_at = []  # (guess, span, strap radius)
    if style == "tote":
        strap_r = op.uniform(rng, 0.005, 0.01)
        a = top_w * op.uniform(rng, 0.15, 0.3)
        h = op.uniform(rng, 0.12, 0.24)
        y0 = top_d / 2 - 1.2 * strap_r
        for y in (y0, -y0):
            parts += op.tube(op.arch(a, h + 1.5 * strap_r, y, height - 1.5 * strap_r, 7), strap_r)
            loops_at.append(([0.0, y, height + 0.45 * h], 0.9 * min(a, h)))
    elif style == "messenger":
        strap_r = op.uniform(rng, 0.006, 0.012)
        a = width / 2 - 0.5 * strap_r
        h = min(op.uniform(rng, 0.22, 0.42), 0.76 - height)
        parts += op.tube(op.arch(a, h + 2 * strap_r, 0.0, height - 2 * strap_r, 11), strap_r)
        flap_h = height * op.uniform(rng, 0.4, 0.8)
        parts.append(
            g.box([0, depth / 2 + 0.0015, height - flap_h / 2], [0.49 * width, 0.003, flap_h / 2])
        )
        loops_at.append(([0.0, 0.0, height + 0.4 * h], 0.9 * min(a, h)))
    else:
        strap_r = op.uniform(rng, 0.007, 0.014)
        a = top_w * op.uniform(rng, 0.2, 0.38)
        h = op.uniform(rng, 0.07, 0.15)
        parts += op.tube(op.arch(a, h + 1.5 * strap_r, 0.0, height - 1.5 * strap_r, 7), strap_r)
        loops_at.append(([0.0, 0.0, height + 0.45 * h], 0.9 * min(a, h)))
    loops = [op.fit_loop(parts, c, Y_AXIS, strap_r + 0.003, span) for c, span in loops_at]
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
    crown_r = op.uniform(rng, 0.085, 0.1)
    squash = op.uniform(rng, 0.78, 1.0)  # crown height / crown radius
    shell = op.uniform(rng, 0.003, 0.006)
    half_open = op.deg(rng, 26, 36)  # half-width (azimuth) of the back opening
    open_el = op.deg(rng, 34, 46)  # elevation of the opening's top edge
    top_el = op.deg(rng, 58, 68)  # elevation where the top panel starts
    n_gores = int(rng.integers(4, 7))  # panels besides the back one
    strap_r = op.uniform(rng, 0.004, 0.007)
    brim_len = op.uniform(rng, 0.055, 0.085)
    brim_half_angle = op.deg(rng, 45, 60)
    brim_tilt = op.deg(rng, 0, 18)
    brim_t = op.uniform(rng, 0.003, 0.006)

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
    half_w = crown_r * np.sin(brim_half_angle) * op.uniform(rng, 1.0, 1.2)
    front = [
        np.array([x_pivot + reach * np.cos(b), half_w * np.sin(b)])
        for b in np.linspace(-np.pi / 2, np.pi / 2, 9)
    ]
    outline = np.array(rim + front) - [x_pivot, 0.0]
    parts.append(g.prism(outline, brim_t, op.rot_y(brim_tilt), [x_pivot, 0.0, brim_t / 2]))
    # Strap: a shallow arc along the back rim, ends buried in the neighbouring panels.
    strap_az = np.linspace(back0 - 0.1, back1 + 0.1, 4)
    strap_pts = [sphere_pt(a, 0.0, crown_r - shell / 2) + [0, 0, strap_r] for a in strap_az]
    parts += op.tube(np.array(strap_pts), strap_r)
    # The opening, projected along x, is closed by strap (below), panels (sides) and the back
    # panel (above): search the largest inscribed circle over the whole curved opening.
    x_mid = -crown_r * (1 + np.cos(half_open)) / 2
    depth = crown_r * (1 - np.cos(half_open)) / 2 + 0.004
    z_open = squash * crown_r * np.sin(open_el)
    loop = op.fit_loop(
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
    style = op.choice(rng, ["wire", "wide_shoulder", "tubular"])
    width = op.uniform(rng, 0.34, 0.46)
    swivel = op.deg(rng, -30, 30) if rng.uniform() < 0.4 else 0.0
    side = op.rot_z(swivel) @ X_AXIS
    parts: list[Part] = []
    if style == "wire":
        wire_r = op.uniform(rng, 0.0018, 0.0028)
        drop = op.uniform(rng, 0.1, 0.16)
        left, right, neck = [-width / 2, 0, -drop], [width / 2, 0, -drop], [0.0, 0.0, 0.0]
        parts += [
            g.capsule(neck, left, wire_r),
            g.capsule(left, right, wire_r),
            g.capsule(neck, right, wire_r),
            g.capsule([0, 0, -0.012], [0, 0, 0.012], 1.8 * wire_r),  # twisted neck
        ]
        hook_r, hook_base, stem_extra = wire_r, np.array([0.0, 0.0, 0.0]), 0.012
    elif style == "wide_shoulder":
        arch = op.uniform(rng, 0.02, 0.07)  # how far the shoulder tips sit below the centre
        bar_h = op.uniform(rng, 0.02, 0.035)  # z
        bar_t = op.uniform(rng, 0.008, 0.03)  # y, at the centre
        flare = op.uniform(rng, 1.0, 2.0)  # y thickness at the tips / at the centre
        xs = np.linspace(-width / 2, width / 2, 7)

        def section(x, pad):
            s = abs(2 * x / width)
            z = -arch * s**2
            return op.rect_section(x + pad, bar_t * (1 + (flare - 1) * s), bar_h, z)

        for x0, x1 in zip(xs[:-1], xs[1:]):
            parts.append(g.hull(np.concatenate([section(x0, -0.002), section(x1, 0.002)])))
        if rng.uniform() < 0.5:  # trouser bar
            bar_r = op.uniform(rng, 0.003, 0.006)
            xa = width / 2 * op.uniform(rng, 0.55, 0.85)
            za = -arch * (2 * xa / width) ** 2
            zb = za - op.uniform(rng, 0.1, 0.16)
            parts += [
                g.capsule([-xa, 0, za], [-xa, 0, zb], bar_r),
                g.capsule([-xa, 0, zb], [xa, 0, zb], bar_r),
                g.capsule([xa, 0, zb], [xa, 0, za], bar_r),
            ]
        hook_r = op.uniform(rng, 0.0022, 0.003)
        hook_base = np.array([0.0, 0.0, -0.3 * bar_h])
        stem_extra = 0.8 * bar_h + 0.006  # the stem starts inside the bar, below the ferrule
        parts.append(
            g.cylinder([0, 0, bar_h / 2 - 0.002], [0, 0, bar_h / 2 + 0.006], 2.5 * hook_r, 8)
        )
    else:
        tube_r = op.uniform(rng, 0.0035, 0.006)
        drop = op.uniform(rng, 0.08, 0.14)
        power = op.uniform(rng, 1.2, 2.0)
        for sgn in (-1, 1):
            ks = np.linspace(0, 1, 5)
            pts = np.stack([sgn * width / 2 * ks, np.zeros(5), -drop * ks**power], axis=1)
            tip = pts[-1] + [sgn * 0.004, 0, -op.uniform(rng, 0.01, 0.025)]
            parts += op.tube(np.concatenate([pts, tip[None]]), tube_r)
        z_bar = -drop - op.uniform(rng, 0.0, 0.03)
        ends = [p.p1 for p in parts if abs(p.p1[0]) > width / 2]
        parts.append(g.capsule(ends[0], [ends[0][0], 0, z_bar], tube_r))
        parts.append(g.capsule([ends[0][0], 0, z_bar], [ends[1][0], 0, z_bar], tube_r))
        parts.append(g.capsule([ends[1][0], 0, z_bar], ends[1], tube_r))
        hook_r, hook_base, stem_extra = tube_r, np.array([0.0, 0.0, 0.0]), 0.0
    bend_r = op.uniform(rng, max(0.016, hook_r + 0.012), 0.03)
    stem = op.uniform(rng, 0.02, 0.05)
    hook, centre, axis = op.j_hook(
        hook_base, Z_AXIS, side, stem + stem_extra, bend_r, op.deg(rng, 20, 60), hook_r
    )
    parts += hook
    loop = op.fit_loop(parts, centre, axis, hook_r + 0.003)
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


@register_object("headphone")
def headphone(rng: np.random.Generator) -> AssetSpec:
    """Over-ear headphones in the xz-plane: a headband arc (round tube or flat band of boxes),
    yokes, and two ear cups (cylinders or oval hulls) with cushions facing each other.

    Hangs by the band: a rod through the opening under the band (axis +y) rests at its top.
    """
    head_half = op.uniform(rng, 0.062, 0.08)  # cushion face to the middle
    cushion = op.uniform(rng, 0.01, 0.025)
    cup_t = op.uniform(rng, 0.015, 0.03)
    cup_r = op.uniform(rng, 0.03, 0.048)
    yoke = op.uniform(rng, 0.008, 0.03)
    tall = op.uniform(rng, 1.0, 1.3)  # band height / band half-width
    band_style = op.choice(rng, ["round", "flat"])
    cup_style = op.choice(rng, ["round", "oval"])
    x_band = head_half + cushion + 0.5 * cup_t
    pts = op.ellipse([0, 0, 0], X_AXIS, Z_AXIS, x_band, tall * x_band, 0.0, np.pi, 11)
    parts: list[Part] = []
    if band_style == "round":
        band_r = op.uniform(rng, 0.004, 0.008)
        parts += op.tube(pts, band_r)
        band_half_y = band_r
    else:
        band_w = op.uniform(rng, 0.015, 0.035)
        band_t = op.uniform(rng, 0.004, 0.008)
        band_r = band_t / 2
        for p, q in zip(pts[:-1], pts[1:]):
            tangent = (q - p) / np.linalg.norm(q - p)
            rot = op.plane_frame(tangent, Y_AXIS)
            half = [np.linalg.norm(q - p) / 2 + 0.002, band_w / 2, band_t / 2]
            parts.append(g.box((p + q) / 2, half, rot))
        band_half_y = band_w / 2
    z_cup = -yoke - cup_r
    yoke_r = op.uniform(rng, 0.003, 0.006)
    oval = op.uniform(rng, 0.7, 0.9)
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
                            op.ellipse_section(x, oval * cup_r, cup_r, z_cup, sides=12)
                            for x in (x_in, x_out)
                        ]
                    )
                )
            )
        pad_r = cup_r * op.uniform(rng, 0.8, 0.95)
        half_y, half_z = (pad_r, pad_r) if cup_style == "round" else (oval * pad_r, pad_r)
        parts.append(
            g.hull(
                np.concatenate(
                    [
                        op.ellipse_section(
                            sgn * head_half, 0.85 * half_y, 0.85 * half_z, z_cup, 10
                        ),
                        op.ellipse_section(sgn * (head_half + cushion), half_y, half_z, z_cup, 10),
                    ]
                )
            )
        )
    loop = op.fit_loop(
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


@register_object("racquet")
def racquet(rng: np.random.Generator) -> AssetSpec:
    """A racquet along +z in the xz-plane: capsule head frame, a thin string-bed hull, throat,
    shaft and octagonal handle.

    Styles: tennis and squash (open triangular throat; hangs through it), badminton (T-joint
    and steel shaft; hangs by a wrist loop at the butt). Tennis and squash racquets may carry
    a wrist loop too. Axis of every loop: +y.
    """
    style = op.choice(rng, ["tennis", "squash", "badminton"])
    parts: list[Part] = []
    loops: list[HangLoop] = []
    if style == "badminton":
        a, b = op.uniform(rng, 0.092, 0.105), op.uniform(rng, 0.112, 0.125)
        frame_r = op.uniform(rng, 0.0025, 0.0035)
        handle_l = op.uniform(rng, 0.15, 0.18)
        handle_r = op.uniform(rng, 0.011, 0.013)
        shaft_l = op.uniform(rng, 0.2, 0.24)
        parts.append(g.frustum([0, 0, 0], [0, 0, handle_l], handle_r, 0.75 * handle_r, sides=8))
        shaft_top = handle_l + shaft_l
        parts.append(
            g.capsule([0, 0, handle_l - 0.01], [0, 0, shaft_top], op.uniform(rng, 0.0035, 0.0045))
        )
        parts.append(g.capsule([0, 0, shaft_top], [0, 0, shaft_top + 0.025], 1.3 * frame_r))
        head_c = np.array([0, 0, shaft_top + 0.025 + b])
        angles = np.linspace(-np.pi / 2, 1.5 * np.pi, 17)[:-1]
        head = head_c + np.stack([a * np.cos(angles), 0 * angles, b * np.sin(angles)], 1)
        throat = 0.0
    else:
        if style == "tennis":
            a, b = op.uniform(rng, 0.115, 0.135), op.uniform(rng, 0.15, 0.175)
            frame_r = op.uniform(rng, 0.006, 0.009)
            handle_l, handle_r = op.uniform(rng, 0.17, 0.2), op.uniform(rng, 0.013, 0.016)
            throat = op.uniform(rng, 0.09, 0.13)
        else:
            a, b = op.uniform(rng, 0.095, 0.11), op.uniform(rng, 0.135, 0.155)
            frame_r = op.uniform(rng, 0.005, 0.007)
            handle_l, handle_r = op.uniform(rng, 0.17, 0.2), op.uniform(rng, 0.011, 0.014)
            throat = op.uniform(rng, 0.12, 0.17)
        phi = op.deg(rng, 30, 48)  # where the throat arms meet the head, from its bottom
        parts.append(g.cylinder([0, 0, 0], [0, 0, handle_l], handle_r, sides=8))
        apex = np.array([0, 0, handle_l + 0.005])
        parts.append(g.capsule([0, 0, handle_l - 0.01], apex, 0.8 * handle_r))
        head_c = apex + [0, 0, throat + b * np.cos(phi)]
        # The head: the ellipse above the arms, closed below by a flatter bridge.
        main = np.linspace(-np.pi / 2 + phi, 1.5 * np.pi - phi, 13)
        head_main = head_c + np.stack([a * np.cos(main), 0 * main, b * np.sin(main)], 1)
        right, left = head_main[0], head_main[-1]
        sag = min(op.uniform(rng, 0.0, 0.35) * b * (1 - np.cos(phi)), 0.3 * throat)
        s_br = np.linspace(-1, 1, 5)[:-1]
        bridge = np.stack([right[0] * s_br, 0 * s_br, right[2] - sag * (1 - s_br**2)], axis=1)
        head = np.concatenate([bridge, head_main[:-1]])
        arm_r = frame_r * op.uniform(rng, 0.9, 1.15)
        parts += [g.capsule(apex, left, arm_r), g.capsule(apex, right, arm_r)]
        throat_guess = (apex + left + right) / 3
        throat_span = 0.25 * np.linalg.norm(right - left)
    parts += op.tube(head, frame_r, closed=True)
    # String bed: a 2 mm plate filling the head, its rim inside the frame tube.
    inward = head - head_c
    inward /= np.linalg.norm(inward, axis=1, keepdims=True)
    bed = (head - 0.5 * frame_r * inward)[:, None, :] + np.array([[0, -0.001, 0], [0, 0.001, 0]])
    parts.append(g.hull(bed.reshape(-1, 3)))
    butt_z = -0.006
    parts.append(g.cylinder([0, 0, butt_z], [0, 0, 0.004], 1.1 * handle_r, sides=8))
    if style == "badminton" or rng.uniform() < 0.3:  # wrist loop at the butt
        loop_r = op.uniform(rng, 0.018, 0.03)
        wire = op.uniform(rng, 0.002, 0.003)
        centre = np.array([0, 0, butt_z + 0.5 * wire - loop_r])
        parts += op.ellipse_ring(centre, X_AXIS, Z_AXIS, loop_r, loop_r, wire, 8)
        loops.append(op.fit_loop(parts, centre, Y_AXIS, wire + 0.003))
    if style != "badminton":  # the open throat: the largest circle in the triangle
        loops.insert(0, op.fit_loop(parts, throat_guess, Y_AXIS, frame_r + 0.003, throat_span))
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


def _key_ring(rng: np.random.Generator):
    """A split ring (xz-plane) with 1-3 flat keys hanging from its bottom, radially."""
    ring_r = op.uniform(rng, 0.012, 0.02)
    wire = op.uniform(rng, 0.0012, 0.002)
    parts: list[Part] = list(op.ellipse_ring([0, 0, 0], X_AXIS, -Z_AXIS, ring_r, ring_r, wire, 12))
    n_keys = int(rng.integers(1, 4))
    thetas = {1: [90.0], 2: [60.0, 120.0], 3: [60.0, 90.0, 120.0]}[n_keys]
    key_len = 0.0
    for theta in np.deg2rad(thetas):
        radial = np.array([np.cos(theta), 0.0, -np.sin(theta)])
        at = ring_r * radial  # a ring vertex (every 30 degrees)
        bow_r = op.uniform(rng, 0.009, 0.014)
        key_t = op.uniform(rng, 0.0015, 0.0025)
        blade = op.uniform(rng, 0.025, 0.045)
        key_w = op.uniform(rng, 0.006, 0.01)
        frame = op.plane_frame(radial, Y_AXIS)  # the key's plane holds the radial direction
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
    loop = op.fit_loop(parts, [0, 0, 0], Y_AXIS, wire + 0.003)
    return parts, [loop], dict(ring_radius=ring_r, keys=n_keys, key_length=key_len)


def _towel(rng: np.random.Generator):
    """A folded towel (thin slab, xz-plane) with a fabric loop (tube arch) on its top edge."""
    width = op.uniform(rng, 0.25, 0.5)
    height = op.uniform(rng, 0.3, 0.6)
    thick = op.uniform(rng, 0.004, 0.012)
    loop_a = op.uniform(rng, 0.016, 0.03)
    loop_h = op.uniform(rng, 0.035, 0.065)
    tube_r = op.uniform(rng, 0.002, 0.0035)
    x_loop = 0.0 if rng.uniform() < 0.5 else op.uniform(rng, -1, 1) * (width / 2 - loop_a - 0.01)
    parts: list[Part] = [g.box([0, 0, -height / 2], [width / 2, thick / 2, height / 2])]
    arch = op.arch(loop_a, loop_h + 1.5 * tube_r, 0.0, -1.5 * tube_r, 9) + [x_loop, 0, 0]
    parts += op.tube(arch, tube_r)
    loop = op.fit_loop(
        parts,
        [x_loop, 0, 0.45 * loop_h],
        Y_AXIS,
        tube_r + 0.003,
        span=0.9 * min(loop_a, loop_h / 2),
    )
    return parts, [loop], dict(width=width, height=height, thickness=thick, loop_height=loop_h)


def _basket(rng: np.random.Generator):
    """A basket (round frustum or rectangular hull) with a handle arc over its top."""
    height = op.uniform(rng, 0.06, 0.14)
    tube_r = op.uniform(rng, 0.004, 0.008)
    handle_h = op.uniform(rng, 0.08, 0.18)
    if rng.uniform() < 0.5:
        r0 = op.uniform(rng, 0.07, 0.14)
        r1 = r0 * op.uniform(rng, 1.0, 1.25)
        parts: list[Part] = [g.frustum([0, 0, 0], [0, 0, height], r0, r1, sides=14)]
        z_end = height - 2 * tube_r
        half = r0 + (r1 - r0) * z_end / height - 1.5 * tube_r
        half *= np.cos(np.pi / 14)  # stay inside the 14-gon
        shape = "round"
    else:
        length, depth = op.uniform(rng, 0.14, 0.3), op.uniform(rng, 0.1, 0.2)
        flare = op.uniform(rng, 1.0, 1.15)
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
    parts += op.tube(op.arch(half, handle_h + 2 * tube_r, 0.0, z_end, 11), tube_r)
    loop = op.fit_loop(
        parts, [0, 0, height + 0.4 * handle_h], Y_AXIS, tube_r + 0.003, 0.9 * min(half, handle_h)
    )
    return parts, [loop], dict(shape=shape, height=height, handle_height=handle_h)


def _lanyard(rng: np.random.Generator):
    """A badge card (xz-plane) on a clip, hanging from a long rigid lanyard loop."""
    card_w = op.uniform(rng, 0.05, 0.07)
    card_h = op.uniform(rng, 0.07, 0.1)
    card_t = op.uniform(rng, 0.0015, 0.003)
    clip_h = op.uniform(rng, 0.008, 0.015)
    loop_a = op.uniform(rng, 0.03, 0.07)
    loop_b = op.uniform(rng, 0.1, 0.2)
    wire = op.uniform(rng, 0.002, 0.004)
    parts: list[Part] = [
        g.box([0, 0, 0], [card_w / 2, card_t / 2, card_h / 2]),
        g.box([0, 0, card_h / 2 + clip_h / 2 - 0.002], [0.006, 0.003, clip_h / 2 + 0.002]),
    ]
    centre = np.array([0, 0, card_h / 2 + clip_h - 0.5 * wire + loop_b])
    parts += op.ellipse_ring(centre, X_AXIS, Z_AXIS, loop_a, loop_b, wire, 12)
    loop = op.fit_loop(parts, centre, Y_AXIS, wire + 0.003)
    return parts, [loop], dict(card_height=card_h, loop_width=2 * loop_a, loop_length=2 * loop_b)


def _umbrella(rng: np.random.Generator):
    """A closed stick umbrella along +z: shaft, folded canopy hulls, tip, J crook below."""
    shaft_l = op.uniform(rng, 0.4, 0.55)
    shaft_r = op.uniform(rng, 0.004, 0.007)
    canopy_r = op.uniform(rng, 0.025, 0.045)
    z0 = shaft_l * op.uniform(rng, 0.15, 0.3)  # where the gathered canopy starts
    z1 = z0 + 0.25 * (shaft_l - z0)  # its widest section
    tip = op.uniform(rng, 0.02, 0.05)
    parts: list[Part] = [
        g.capsule([0, 0, -0.01], [0, 0, shaft_l], shaft_r),
        g.frustum([0, 0, z0], [0, 0, z1], 1.2 * shaft_r, canopy_r, sides=10),
        g.frustum([0, 0, z1 - 0.001], [0, 0, shaft_l], canopy_r, 1.5 * shaft_r, sides=10),
        g.capsule([0, 0, shaft_l], [0, 0, shaft_l + tip], 0.6 * shaft_r),
    ]
    crook_r = op.uniform(rng, 0.028, 0.045)
    tube_r = op.uniform(rng, 0.008, 0.013)
    hook, centre, axis = op.j_hook(
        [0, 0, 0], -Z_AXIS, X_AXIS, op.uniform(rng, 0.01, 0.03), crook_r, op.deg(rng, 0, 40), tube_r
    )
    parts += hook
    loop = op.fit_loop(parts, centre, axis, tube_r + 0.003)
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
    kind = op.choice(rng, list(_DAILY_OBJECTS))
    parts, loops, params = _DAILY_OBJECTS[kind](rng)
    return AssetSpec(parts=parts, features=loops, params=dict(kind=kind, **params))
