"""Procedural generators for supporting-item families, mounted as in real homes.

Frames (construction frame; :func:`sim.assets.base.build_support` re-centres on the bounding
box afterwards): z up. Wall-mounted items have a backplate whose back face lies in the wall
plane ``y = 0``, the lowest y of all parts, and reach out towards +y; every rod starts inside
its mount at ``y >= radius + 0.5 mm`` so that no part pokes through the wall. Free-standing
items stand on a base whose bottom face is the floor ``z = 0``.

Every rod an object can hang on is recorded as a :class:`~sim.assets.base.Peg` lying exactly
on the axis of one capsule part of the same radius: ``base`` where the rod leaves its mount
(plate, collar, pole or standoff), ``tip`` its free end. Stops beyond the tip (ball knobs,
upturned or curled J ends) are extra parts; a ball is centred on the tip, a J starts at the
tip, and both leave the point 1 cm beyond the tip along the rod free. Towel bars are fixed at
both ends (``closed=True``): base and tip are the two ends of the free span between the
standoffs.

Families: ``single_rod_hook``, ``two_rod_hook``, ``towel_bar``, ``mug_tree``,
``pegboard_hook``, ``coat_rack_knob`` (``docs/assets_supports.md`` lists their randomised
ranges).
"""

from __future__ import annotations

import numpy as np

from sim import geometry as g
from sim.assets.base import AssetSpec, Peg, register_support
from sim.geometry import Part

_UP = np.array([0.0, 0.0, 1.0])
_WALL_CLEARANCE = 0.0005  # metres between a rod's buried end cap and the wall plane
_PEGBOARD_PITCH = 0.0254  # hole spacing of standard (1 inch) pegboard, metres
_MAX_BALL_RADIUS = 0.009  # a ball stop stays under 1 cm so the rod's tip region stays open
# Frame of a plate lying on the wall: outline x -> world x, outline y -> world z, thickness
# along world -y (right-handed).
_WALL_FRAME = np.stack([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], axis=1)


# ----------------------------------------------------------------------------- helpers


def _rod_direction(tilt: float, yaw: float = 0.0) -> np.ndarray:
    """[3] unit direction of a rod leaving a wall (+y), raised by ``tilt`` and turned by ``yaw``
    about z (radians)."""
    return np.array([np.sin(yaw) * np.cos(tilt), np.cos(yaw) * np.cos(tilt), np.sin(tilt)])


def _rounded_rect(half_w: float, half_h: float, corner: float, per_corner: int = 4) -> np.ndarray:
    """[4 * per_corner, 2] convex outline of a rounded rectangle (corner radius ``corner``)."""
    corner = min(corner, half_w, half_h)
    pts = []
    for cx, cy, a0 in [(1, 1, 0.0), (-1, 1, 0.5 * np.pi), (-1, -1, np.pi), (1, -1, 1.5 * np.pi)]:
        ang = np.linspace(a0, a0 + 0.5 * np.pi, per_corner)
        centre = np.array([cx * (half_w - corner), cy * (half_h - corner)])
        pts.append(centre + corner * np.stack([np.cos(ang), np.sin(ang)], axis=1))
    return np.concatenate(pts)


def _wall_plate(
    shape: str, width: float, height: float, thick: float, x: float = 0.0, z: float = 0.0
) -> Part:
    """A mounting plate on the wall: back face at y = 0, front face at y = ``thick``.

    ``shape``: "rect" (box), "rounded" (rounded-rectangle prism) or "round" (a disk of
    diameter ``min(width, height)``).
    """
    if shape == "rect":
        return g.box([x, thick / 2, z], [width / 2, thick / 2, height / 2])
    if shape == "round":
        radius = 0.5 * min(width, height)
        return g.cylinder([x, 0.0, z], [x, thick, z], radius, sides=16)
    outline = _rounded_rect(width / 2, height / 2, 0.3 * min(width, height))
    return g.prism(outline, thick, _WALL_FRAME, origin=(x, thick / 2, z))


def _wall_rod(exit_point: np.ndarray, direction: np.ndarray, length: float, radius: float):
    """A rod leaving a mount face at ``exit_point`` along ``direction`` for ``length`` metres.

    Returns (capsule, base, tip). The capsule starts inside the mount, on the same axis, with
    its end cap ``_WALL_CLEARANCE`` in front of the wall plane y = 0.
    """
    start_y = radius + _WALL_CLEARANCE
    back = (exit_point[1] - start_y) / direction[1]
    p0 = exit_point - back * direction
    tip = exit_point + length * direction
    return g.capsule(p0, tip, radius), exit_point.copy(), tip


def _upward_normal(direction: np.ndarray) -> np.ndarray:
    """[3] unit vector perpendicular to ``direction`` in its vertical plane, pointing up."""
    n = _UP - np.dot(_UP, direction) * direction
    return n / np.linalg.norm(n)


def _bent_end(
    tip: np.ndarray,
    direction: np.ndarray,
    radius: float,
    bend_deg: list[float],
    lengths: list[float],
) -> list[Part]:
    """Capsules continuing a rod from ``tip``, each turned ``bend_deg`` (from the rod direction,
    towards up) and ``lengths`` long: one entry is an upturn, several a curled J."""
    n = _upward_normal(direction)
    pts = [tip]
    for angle, length in zip(bend_deg, lengths):
        a = np.deg2rad(angle)
        pts.append(pts[-1] + length * (np.cos(a) * direction + np.sin(a) * n))
    return g.tube(pts, radius)


def _tip_stop(
    rng: np.random.Generator,
    style: str,
    tip: np.ndarray,
    direction: np.ndarray,
    radius: float,
    max_rise: float = 0.035,
) -> list[Part]:
    """The stop beyond a rod's free ``tip``.

    - "plain": none (the capsule's round end).
    - "ball": a knob centred on the tip, radius <= 9 mm.
    - "upturn": one capsule bent 60-90 deg up from the rod, 1.2-3 cm long.
    - "j": a curled J of 2-3 capsules, bending 40-60 deg first, then 30-45 deg more each.

    Bends keep the point 1 cm beyond the tip outside the stop for rods up to 8 mm ("upturn")
    and 5 mm ("j") radius; ``max_rise`` caps the stop's height above the tip.
    """
    tilt = np.rad2deg(np.arcsin(np.clip(direction[2], -1.0, 1.0)))
    if style == "ball":
        ball_r = min(rng.uniform(1.5, 2.0) * radius, _MAX_BALL_RADIUS)
        return [g.ellipsoid(tip, [ball_r] * 3, g.frame_from_z(direction), rings=4, sides=6)]
    if style == "upturn":
        bend = rng.uniform(60.0, max(60.0, min(90.0, 100.0 - tilt)))
        rise = np.sin(np.deg2rad(tilt + bend))
        length = min(rng.uniform(0.012, 0.03), max_rise / max(rise, 0.5))
        return _bent_end(tip, direction, radius, [bend], [length])
    if style == "j":
        n_seg = int(rng.integers(2, 4))
        bends = [rng.uniform(40.0, 60.0)]
        for _ in range(n_seg - 1):
            bends.append(bends[-1] + rng.uniform(30.0, 45.0))
        bends = [min(b, 150.0 - tilt) for b in bends]  # curl back, never hang down
        chord = min(rng.uniform(0.009, 0.014), max_rise / n_seg)
        return _bent_end(tip, direction, radius, bends, [chord] * n_seg)
    return []


def _leave_distance(
    a0: np.ndarray, da: np.ndarray, b0: np.ndarray, db: np.ndarray, radius: float
) -> float:
    """Arc length s >= 0 at which the axis point ``a0 + s da`` is ``radius`` from the line
    ``b0 + u db`` (two diverging rods; unit directions)."""
    w = a0 - b0
    # |w + s da|^2 - ((w + s da) . db)^2 = radius^2, a quadratic in s.
    qa = 1.0 - np.dot(da, db) ** 2
    qb = 2.0 * (np.dot(w, da) - np.dot(w, db) * np.dot(da, db))
    qc = np.dot(w, w) - np.dot(w, db) ** 2 - radius**2
    if qc >= 0.0:
        return 0.0
    return float((-qb + np.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa))


def _pick(rng: np.random.Generator, options: list[str], p: list[float] | None = None) -> str:
    return str(rng.choice(options, p=p))


def _tilt(rng: np.random.Generator, lo: float = 0.0, hi: float = 40.0) -> float:
    """Upward tilt in radians: a third of the items level-ish (<= 5 deg), the rest in [lo, hi]."""
    if rng.uniform() < 1.0 / 3.0:
        return float(np.deg2rad(rng.uniform(lo, min(hi, lo + 5.0))))
    return float(np.deg2rad(rng.uniform(lo, hi)))


def _hook_tip_style(rng: np.random.Generator, radius: float) -> str:
    """Tip of a wall hook rod; balls and curled Js only on thin rods (as real ones are)."""
    options = ["plain", "upturn"] + (["ball", "j"] if radius <= 0.005 else [])
    return _pick(rng, options)


# ----------------------------------------------------------------------------- wall hooks


@register_support("single_rod_hook")
def single_rod_hook(rng: np.random.Generator) -> AssetSpec:
    """One rod out of a wall plate, level or tilted up to 40 deg, optionally through a collar,
    ending plain, in a ball, an upturn or a curled J."""
    rod_r = rng.uniform(0.0025, 0.008)
    length = rng.uniform(0.05, 0.18)
    tilt = _tilt(rng)
    tip_style = _hook_tip_style(rng, rod_r)
    plate_shape = _pick(rng, ["rect", "rounded", "round"])
    # Thick rods sit in thick plates: the rod's full section must clear the plate face.
    thick = rng.uniform(max(0.006, 1.7 * rod_r + 0.001), max(0.015, 1.7 * rod_r + 0.005))
    width = rng.uniform(max(0.025, 5 * rod_r), 0.06)
    height = width if plate_shape == "round" else rng.uniform(max(0.04, width), 0.10)
    # The rod leaves the plate around or above its middle, inside the plate's outline.
    exit_z = rng.uniform(-0.1, 0.15 if plate_shape == "round" else 0.3) * height
    plate = _wall_plate(plate_shape, width, height, thick)
    parts: list[Part] = [plate]
    direction = _rod_direction(tilt)
    exit_point = np.array([0.0, thick, exit_z])
    collar_len = 0.0
    if tilt <= np.deg2rad(12.0) and rng.uniform() < 0.5:  # a round collar between plate and rod
        collar_len = rng.uniform(0.004, 0.012)
        # The collar sticks straight out of the plate; its front face still holds the whole
        # (slightly tilted) rod.
        front_r = rod_r + collar_len * np.tan(tilt) + 0.0005
        back_r = max(rng.uniform(1.6, 2.2) * rod_r, front_r + 0.001)
        parts.append(
            g.frustum(
                [0.0, thick - 0.001, exit_z],
                [0.0, thick + collar_len, exit_z],
                back_r,
                front_r,
                sides=12,
            )
        )
        exit_point = exit_point + collar_len / direction[1] * direction
    rod, base, tip = _wall_rod(exit_point, direction, length, rod_r)
    parts.append(rod)
    parts += _tip_stop(rng, tip_style, tip, direction, rod_r)
    return AssetSpec(
        parts=parts,
        features=[Peg(base, tip, rod_r)],
        params=dict(
            rod_radius=rod_r,
            length=length,
            tilt_deg=float(np.rad2deg(tilt)),
            tip=tip_style,
            plate=plate_shape,
            plate_thickness=thick,
            collar_length=collar_len,
        ),
    )


@register_support("two_rod_hook")
def two_rod_hook(rng: np.random.Generator) -> AssetSpec:
    """Two rods from one wall plate: side by side ("parallel"), fanned out from one point
    ("v_spread"), or a coat hook with a long steep upper and a short lower rod ("stacked")."""
    layout = _pick(rng, ["parallel", "v_spread", "stacked"])
    rod_r = rng.uniform(0.0025, 0.007)
    thick = rng.uniform(max(0.006, 1.7 * rod_r + 0.001), max(0.014, 1.7 * rod_r + 0.005))
    plate_shape = _pick(rng, ["rect", "rounded"] + (["round"] if layout == "v_spread" else []))
    rods: list[tuple[np.ndarray, np.ndarray, float, str, float]] = []  # exit, dir, len, tip, rise
    params: dict = dict(layout=layout, rod_radius=rod_r, plate=plate_shape, plate_thickness=thick)
    if layout == "parallel":
        spacing = rng.uniform(0.025, 0.10)
        tilt = _tilt(rng)
        length = rng.uniform(0.04, 0.15)
        tip = _hook_tip_style(rng, rod_r)
        width = spacing + rng.uniform(0.02, 0.04)
        height = rng.uniform(0.03, 0.08)
        exit_z = rng.uniform(-0.1, 0.2) * height
        for x in (-spacing / 2, spacing / 2):
            rods.append((np.array([x, thick, exit_z]), _rod_direction(tilt), length, tip, 0.035))
        params.update(spacing=spacing, tilt_deg=float(np.rad2deg(tilt)), length=length, tip=tip)
    elif layout == "v_spread":
        half_angle = np.deg2rad(rng.uniform(10.0, 30.0))
        tilt = _tilt(rng)
        length = rng.uniform(0.05, 0.15)
        tip = _pick(rng, ["plain", "ball"] if rod_r <= 0.005 else ["plain"])
        gap = rng.uniform(0.0, 0.015)  # the two rods leave the plate this far apart in x
        width = rng.uniform(max(0.03, gap + 6 * rod_r), 0.06)
        height = width if plate_shape == "round" else rng.uniform(max(0.04, width), 0.09)
        exit_z = rng.uniform(-0.1, 0.15) * height
        exits = [np.array([sign * gap / 2, thick, exit_z]) for sign in (-1.0, 1.0)]
        dirs = [_rod_direction(tilt, sign * half_angle) for sign in (-1.0, 1.0)]
        # Each Peg starts where its rod's axis leaves the other rod, so the whole Peg is free.
        clear = _leave_distance(exits[0], dirs[0], exits[1], dirs[1], rod_r)
        for exit_point, direction in zip(exits, dirs):
            rods.append((exit_point + clear * direction, direction, length, tip, 0.035))
        params.update(
            spread_deg=float(np.rad2deg(2 * half_angle)),
            tilt_deg=float(np.rad2deg(tilt)),
            length=length,
            tip=tip,
            exit_gap=gap,
            free_from=clear,
        )
    else:  # stacked coat hook: upper rod steeper than the lower one, so the two diverge
        spacing = rng.uniform(0.025, 0.05)
        tilt_lo = np.deg2rad(rng.uniform(0.0, 20.0))
        tilt_hi = tilt_lo + np.deg2rad(rng.uniform(10.0, 20.0))
        len_lo = rng.uniform(0.04, 0.08)
        len_hi = len_lo + rng.uniform(0.03, 0.08)
        tip_lo = _hook_tip_style(rng, rod_r)
        tip_hi = _pick(rng, ["plain", "ball"] if rod_r <= 0.005 else ["plain"])
        width = rng.uniform(max(0.025, 5 * rod_r), 0.05)
        height = spacing + rng.uniform(0.03, 0.06)
        z_lo = -spacing / 2
        rods.append(
            (np.array([0.0, thick, z_lo]), _rod_direction(tilt_lo), len_lo, tip_lo, 0.6 * spacing)
        )
        rods.append(
            (np.array([0.0, thick, z_lo + spacing]), _rod_direction(tilt_hi), len_hi, tip_hi, 0.0)
        )
        params.update(
            spacing=spacing,
            tilt_deg=float(np.rad2deg(tilt_lo)),
            upper_tilt_deg=float(np.rad2deg(tilt_hi)),
            length=len_lo,
            upper_length=len_hi,
            tip=tip_lo,
            upper_tip=tip_hi,
        )
    params.update(plate_width=width, plate_height=height)
    parts: list[Part] = [_wall_plate(plate_shape, width, height, thick)]
    pegs = []
    for exit_point, direction, length, tip_style, max_rise in rods:
        rod, base, tip = _wall_rod(exit_point, direction, length, rod_r)
        parts.append(rod)
        parts += _tip_stop(rng, tip_style, tip, direction, rod_r, max_rise=max_rise)
        pegs.append(Peg(base, tip, rod_r))
    return AssetSpec(parts=parts, features=pegs, params=params)


# ----------------------------------------------------------------------------- towel bar


@register_support("towel_bar")
def towel_bar(rng: np.random.Generator) -> AssetSpec:
    """A horizontal bar held at both ends by two standoffs (rosette + post) on the wall.

    With the wall the bar forms a closed loop: its Peg is ``closed`` and spans the free bar
    between the posts. A third of the items carry a second, outer bar ("double").
    """
    bar_r = rng.uniform(0.005, 0.009)
    centres = rng.uniform(0.22, 0.52)  # post centre to post centre
    overhang = rng.uniform(0.0, 0.025) if rng.uniform() < 0.5 else 0.0  # bar past the posts
    standoff = rng.uniform(0.045, 0.085)  # wall to bar axis
    double = bool(rng.uniform() < 1.0 / 3.0)
    outer_gap = rng.uniform(0.03, 0.05) if double else 0.0
    post_r = bar_r + rng.uniform(0.002, 0.005)
    post_shape = _pick(rng, ["round", "square"])
    rosette_shape = _pick(rng, ["round", "rect", "rounded"])
    rosette_thick = rng.uniform(post_r + 0.002, post_r + 0.008)
    rosette_size = rng.uniform(max(0.035, 2 * post_r + 0.012), 0.07)
    parts: list[Part] = []
    bar_ys = [standoff] + ([standoff + outer_gap] if double else [])
    outer_y = bar_ys[-1]
    for x in (-centres / 2, centres / 2):
        parts.append(_wall_plate(rosette_shape, rosette_size, rosette_size, rosette_thick, x=x))
        if post_shape == "round":  # its round end cap wraps the outer bar's end
            parts.append(g.capsule([x, post_r + _WALL_CLEARANCE, 0.0], [x, outer_y, 0.0], post_r))
        else:
            y0, y1 = rosette_thick / 2, outer_y + bar_r + 0.003
            parts.append(g.box([x, 0.5 * (y0 + y1), 0.0], [post_r, 0.5 * (y1 - y0), post_r]))
    pegs = []
    end = centres / 2 + overhang
    for y in bar_ys:
        parts.append(g.capsule([-end, y, 0.0], [end, y, 0.0], bar_r))
        span = centres / 2 - post_r
        pegs.append(Peg(np.array([-span, y, 0.0]), np.array([span, y, 0.0]), bar_r, closed=True))
    return AssetSpec(
        parts=parts,
        features=pegs,
        params=dict(
            bar_radius=bar_r,
            post_spacing=centres,
            overhang=overhang,
            standoff=standoff,
            double=double,
            outer_gap=outer_gap,
            post_radius=post_r,
            post=post_shape,
            rosette=rosette_shape,
            rosette_size=rosette_size,
        ),
    )


# ----------------------------------------------------------------------------- mug tree


@register_support("mug_tree")
def mug_tree(rng: np.random.Generator) -> AssetSpec:
    """A free-standing mug tree: base (disk, square or dome), vertical pole (optional ball
    finial) and 3-8 arms tilted 10-40 deg up around the pole at one or two heights."""
    height = rng.uniform(0.25, 0.45)
    base_shape = _pick(rng, ["disk", "square", "dome"])
    base_r = rng.uniform(0.06, 0.10)
    base_thick = rng.uniform(0.012, 0.025)
    pole_r = rng.uniform(0.008, 0.014)
    n_arms = int(rng.integers(3, 9))
    levels = 2 if n_arms >= 4 and rng.uniform() < 0.5 else 1
    arm_r = rng.uniform(0.003, 0.006)
    arm_len = rng.uniform(0.06, 0.12)
    tilt = np.deg2rad(rng.uniform(10.0, 40.0))
    finial = bool(rng.uniform() < 0.5)
    # Ball knobs on the arm tips only where the part budget (<= 12) allows.
    tip_style = _pick(rng, ["plain", "ball"]) if n_arms <= 4 else "plain"

    if base_shape == "disk":
        base = g.cylinder([0, 0, 0], [0, 0, base_thick], base_r, sides=16)
    elif base_shape == "square":
        half = base_r / np.sqrt(2.0) * 1.15
        base = g.box([0, 0, base_thick / 2], [half, half, base_thick / 2])
    else:
        base = g.frustum([0, 0, 0], [0, 0, base_thick], base_r, 0.55 * base_r, sides=16)
    parts: list[Part] = [base]
    top = height - (rng.uniform(1.3, 1.8) * pole_r if finial else pole_r)
    pole_start = max(base_thick, pole_r + 0.001)  # round end buried in the base, off the floor
    parts.append(g.capsule([0, 0, pole_start], [0, 0, top], pole_r))
    if finial:
        parts.append(g.ellipsoid([0, 0, top], [height - top] * 3, rings=4, sides=6))

    finial_r = height - top if finial else 0.0
    # Upper arms: tips (with their knobs) stay below the top, and arms leave the pole's
    # straight part below the finial.
    stop_r = _MAX_BALL_RADIUS if tip_style == "ball" else arm_r
    rise = (pole_r / np.cos(tilt) + arm_len) * np.sin(tilt) + stop_r
    z_hi = min(
        rng.uniform(0.72, 0.88) * height,
        height - 0.005 - rise,
        top - finial_r - pole_r * np.tan(tilt) - arm_r - 0.002,
    )
    z_lo = min(rng.uniform(0.45, 0.60) * height, z_hi - 0.04)
    per_level = [n_arms] if levels == 1 else [n_arms - n_arms // 2, n_arms // 2]
    heights = [z_hi] if levels == 1 else [z_lo, z_hi]
    phase = rng.uniform(0, 2 * np.pi)
    pegs = []
    for level, (count, z) in enumerate(zip(per_level, heights)):
        offset = phase + (np.pi / count if level == 1 else 0.0)  # stagger the upper level
        for k in range(count):
            az = offset + 2 * np.pi * k / count
            d = np.array([np.cos(az) * np.cos(tilt), np.sin(az) * np.cos(tilt), np.sin(tilt)])
            centre = np.array([0.0, 0.0, z])
            base_pt = centre + pole_r / np.cos(tilt) * d  # where the arm's axis leaves the pole
            tip = base_pt + arm_len * d
            parts.append(g.capsule(centre, tip, arm_r))
            parts += _tip_stop(rng, tip_style, tip, d, arm_r)
            pegs.append(Peg(base_pt, tip, arm_r))
    return AssetSpec(
        parts=parts,
        features=pegs,
        params=dict(
            height=height,
            base=base_shape,
            base_radius=base_r,
            base_thickness=base_thick,
            pole_radius=pole_r,
            n_arms=n_arms,
            levels=levels,
            arm_radius=arm_r,
            arm_length=arm_len,
            tilt_deg=float(np.rad2deg(tilt)),
            finial=finial,
            tip=tip_style,
        ),
        ground_parts=(0,),
        wall=False,
    )


# ----------------------------------------------------------------------------- pegboard hook


@register_support("pegboard_hook")
def pegboard_hook(rng: np.random.Generator) -> AssetSpec:
    """A wire hook in a pegboard panel section (the panel is the backplate, holes not modelled).

    The wire (radius 2-4 mm) runs up the panel face one hole pitch (1 inch) from its arm to a
    prong in the upper hole; "double" hooks have two legs joined by a top cross wire and two
    parallel arms one or two pitches apart. Arms end straight (L-shaped), upturned, or curled
    into a J.
    """
    wire_r = rng.uniform(0.002, 0.004)
    panel_thick = rng.uniform(0.0055, 0.0065)  # 1/4 inch hardboard
    double = bool(rng.uniform() < 0.4)
    spacing = _PEGBOARD_PITCH * int(rng.integers(1, 3)) if double else 0.0
    arm_len = rng.uniform(0.05, 0.20)
    tilt = np.deg2rad(rng.uniform(0.0, 30.0))
    tip_style = _pick(rng, ["plain", "upturn", "j"])
    shape = "L" if tip_style == "plain" else "J"
    holes_w = int(rng.integers(4, 12))  # panel size in hole pitches
    holes_h = int(rng.integers(4, 12))
    # Where the hook sits on the panel, in whole hole pitches from the panel centre.
    off_x = _PEGBOARD_PITCH * int(rng.integers(-(holes_w // 4), holes_w // 4 + 1))
    off_z = _PEGBOARD_PITCH * int(rng.integers(-(holes_h // 4), holes_h // 4 + 1))
    width = _PEGBOARD_PITCH * holes_w + spacing
    height = _PEGBOARD_PITCH * holes_h
    panel = g.box([off_x, panel_thick / 2, off_z], [width / 2, panel_thick / 2, height / 2])
    parts: list[Part] = [panel]
    wire_y = panel_thick + 0.6 * wire_r  # the wire lies on the face, sunk 0.4 r into it
    z_arm, z_top = 0.0, _PEGBOARD_PITCH
    xs = [-spacing / 2, spacing / 2] if double else [0.0]
    if double:
        parts.append(g.capsule([xs[0], wire_y, z_top], [xs[1], wire_y, z_top], wire_r))
    else:  # the top prong bends into the upper hole
        parts.append(g.capsule([0, wire_y, z_top], [0, wire_r + _WALL_CLEARANCE, z_top], wire_r))
    direction = _rod_direction(tilt)
    pegs = []
    for x in xs:
        parts.append(g.capsule([x, wire_y, z_arm], [x, wire_y, z_top], wire_r))
        # The arm comes out of the lower hole; its Peg starts in front of the wire leg.
        hole = np.array([x, panel_thick, z_arm])
        exit_point = hole + (wire_y + wire_r - panel_thick) / direction[1] * direction
        rod, base, tip = _wall_rod(exit_point, direction, arm_len, wire_r)
        parts.append(rod)
        parts += _tip_stop(rng, tip_style, tip, direction, wire_r)
        pegs.append(Peg(base, tip, wire_r))
    return AssetSpec(
        parts=parts,
        features=pegs,
        params=dict(
            wire_radius=wire_r,
            panel_thickness=panel_thick,
            panel_width=width,
            panel_height=height,
            double=double,
            spacing=spacing,
            length=arm_len,
            tilt_deg=float(np.rad2deg(tilt)),
            tip=tip_style,
            shape=shape,
        ),
    )


# ----------------------------------------------------------------------------- coat rack


@register_support("coat_rack_knob")
def coat_rack_knob(rng: np.random.Generator) -> AssetSpec:
    """A wall rail (coat rack board) with 2-5 evenly spaced knob pegs, Shaker style: a thick
    short shaft tilted 0-25 deg up, ending plain or in a ball knob."""
    n_pegs = int(rng.integers(2, 6))
    peg_r = rng.uniform(0.004, 0.006)  # knob heads (<= 9 mm) stay 1.5x the shaft
    peg_len = rng.uniform(0.04, 0.09)
    tilt = np.deg2rad(rng.uniform(0.0, 25.0))
    tip_style = _pick(rng, ["ball", "ball", "plain"])
    pitch = rng.uniform(0.08, 0.14)  # peg centre to peg centre
    margin = rng.uniform(0.03, 0.07)  # rail beyond the outer pegs
    width = min((n_pegs - 1) * pitch + 2 * margin, 0.58)
    pitch = min(pitch, (width - 2 * margin) / (n_pegs - 1))
    height = rng.uniform(0.06, 0.12)
    thick = rng.uniform(max(0.015, 1.7 * peg_r + 0.001), max(0.022, 1.7 * peg_r + 0.004))
    rail_shape = _pick(rng, ["rect", "rounded"])
    exit_z = rng.uniform(-0.15, 0.1) * height
    parts: list[Part] = [_wall_plate(rail_shape, width, height, thick)]
    direction = _rod_direction(tilt)
    pegs = []
    for k in range(n_pegs):
        x = (k - 0.5 * (n_pegs - 1)) * pitch
        rod, base, tip = _wall_rod(np.array([x, thick, exit_z]), direction, peg_len, peg_r)
        parts.append(rod)
        parts += _tip_stop(rng, tip_style, tip, direction, peg_r)
        pegs.append(Peg(base, tip, peg_r))
    return AssetSpec(
        parts=parts,
        features=pegs,
        params=dict(
            n_pegs=n_pegs,
            peg_radius=peg_r,
            length=peg_len,
            tilt_deg=float(np.rad2deg(tilt)),
            tip=tip_style,
            pitch=pitch,
            rail=rail_shape,
            rail_width=width,
            rail_height=height,
            rail_thickness=thick,
        ),
    )
