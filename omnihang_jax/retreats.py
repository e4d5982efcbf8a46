"""The end of a plan: straight retreats and routes of one or two straight moves from the goal.

A hang is an insertion; its last centimetres are the reverse of taking the object off. A
:class:`Retreat` is such a way off the support (its far end the pre-goal); the planner plans
to the pre-goal and ends straight in (:func:`plan_with_retreat`). The approach and route
networks (:mod:`omnihang_jax.approach`) are trained on :func:`free_retreats` and
:func:`route_table` of the full meshes and choose one at planning time.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from omnihang_jax.planner import (
    PlannerConfig,
    PlanResult,
    any_colliding,
    interpolate_segment,
    plan,
)

# A hang is an insertion; its approach is the reverse of taking the object off. The retreat
# directions (support frame, z up): the 26 of {-1, 0, 1}^3 minus zero, normalised, upward ones
# first (a hung object usually comes off by lifting), then in a fixed order: deterministic.
RETREAT_DIRECTIONS = (
    np.array(
        sorted(
            (d for d in np.ndindex(3, 3, 3) if d != (1, 1, 1)),
            key=lambda d: (-(d[2] - 1), sum(abs(x - 1) for x in d), d),
        ),
        float,
    )
    - 1.0
)
RETREAT_DIRECTIONS /= np.linalg.norm(RETREAT_DIRECTIONS, axis=1, keepdims=True)


class Retreat(NamedTuple):
    pregoal: np.ndarray  # [7] the goal moved back along ``direction`` by ``length``
    direction: np.ndarray  # [3] unit, support frame
    length: float  # m
    states_checked: int
    seconds: float
    # waypoints between the pre-goal and the goal, in approach order (the corner of a
    # two-move route); empty: straight in
    via: np.ndarray = np.zeros((0, 7))


def find_retreat(
    checker: Callable[[np.ndarray], np.ndarray],
    goal: np.ndarray,
    lengths,
    resolution: float,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    directions: np.ndarray = RETREAT_DIRECTIONS,
) -> Retreat | None:
    """The first straight, orientation-keeping retreat from ``goal`` that ``checker`` calls
    free on every state at ``resolution`` (the goal itself excluded, as in :func:`plan`):
    lengths in the given order (shortest first is sensible), for each the directions in
    order; within ``bounds`` when given. None when every one is blocked."""
    t0 = time.perf_counter()
    goal = np.asarray(goal, float)
    checked = 0
    for length in lengths:
        for d in directions:
            end, states = _retreat_states(goal, d, float(length), resolution, bounds)
            if states is None:
                continue
            checked += len(states)
            if not any_colliding(checker, states):
                return Retreat(end, np.asarray(d, float), float(length), checked,
                               time.perf_counter() - t0)  # fmt: skip
    return None


def move_routes(firsts, directions: np.ndarray = RETREAT_DIRECTIONS) -> np.ndarray:
    """[R, 3] the routes of at most two straight moves a route network scores, rows (first direction index or -1, first length m or 0, last direction index):
    the one-move routes first (one per direction), then for each first length in ``firsts``
    every pair of directions that does not go back the way it came (cosine >= -0.5): 26 + 506 routes for one first length."""
    rows = [(-1, 0.0, j) for j in range(len(directions))]
    for first in firsts:
        for i, d1 in enumerate(directions):
            for j, d2 in enumerate(directions):
                if np.dot(d1, d2) >= -0.5:
                    rows.append((i, float(first), j))
    return np.array(rows, float).reshape(-1, 3)


def route_table(
    checker: Callable[[np.ndarray], np.ndarray],
    goal: np.ndarray,
    routes: np.ndarray,
    length: float,
    resolution: float,
    bounds: tuple[np.ndarray, np.ndarray] | None,
    off: Callable[[np.ndarray], bool],
    directions: np.ndarray = RETREAT_DIRECTIONS,
) -> np.ndarray:
    """[R] bool: is each route of :func:`move_routes` free on ``checker`` (every state of both
    moves at ``resolution``, inside ``bounds``) and does ``off`` accept its end? The last move
    is ``length`` long. Each straight segment is checked once (a shared first move, an end's
    ``off``). A route network's labels (``approach.route_labels``)."""
    goal = np.asarray(goal, float)
    segments: dict = {}

    def free_end(start_key, a, j, L):
        key = (start_key, j, round(float(L), 6))
        if key not in segments:
            end, states = _retreat_states(a, directions[j], float(L), resolution, bounds)
            segments[key] = None if states is None or any_colliding(checker, states) else end
        return segments[key]

    ends_off: dict = {}
    out = np.zeros(len(routes), bool)
    for r, (i, first, j) in enumerate(np.asarray(routes, float)):
        i, j = int(i), int(j)
        start_key, start = "goal", goal
        if i >= 0:
            start = free_end("goal", goal, i, first)
            if start is None:
                continue
            start_key = (i, round(float(first), 6))
        end = free_end(start_key, start, j, length)
        if end is None:
            continue
        key = (start_key, j)
        if key not in ends_off:
            ends_off[key] = bool(off(end))
        out[r] = ends_off[key]
    return out


def route_retreat(goal: np.ndarray, route, length: float,
                  directions: np.ndarray = RETREAT_DIRECTIONS) -> Retreat:  # fmt: skip
    """The :class:`Retreat` of one route of :func:`move_routes` (its corner in ``via``), for
    ``plan_with_retreat(retreat=...)``; no check is made (a route network's choice)."""
    goal = np.asarray(goal, float)
    i, first, j = (int(route[0]), float(route[1]), int(route[2]))
    mid = goal.copy()
    via = np.zeros((0, 7))
    if i >= 0:
        mid[:3] += first * directions[i]
        via = mid[None].copy()
    end = mid.copy()
    end[:3] += length * directions[j]
    return Retreat(end, np.asarray(directions[j], float), float(length), 0, 0.0, via=via)


def route_states(goal: np.ndarray, route, length: float, resolution: float,
                 directions: np.ndarray = RETREAT_DIRECTIONS) -> np.ndarray:  # fmt: skip
    """[n, 7] the states of one route of :func:`move_routes` from ``goal`` at ``resolution``
    (the first move, if any, then the last; orientation kept; the goal itself excluded, the
    route's end last): what a planner's own checker is asked before it takes a route
    network's choice."""
    goal = np.asarray(goal, float)
    i, first, j = (int(route[0]), float(route[1]), int(route[2]))
    parts, start = [], goal
    if i >= 0:
        start, states = _retreat_states(goal, directions[i], first, resolution, None)
        parts.append(states)
    _, states = _retreat_states(start, directions[j], float(length), resolution, None)
    parts.append(states)
    return np.concatenate(parts)


def _retreat_states(goal, direction, length: float, resolution: float, bounds):
    """(far end [7], the straight retreat's states from ``goal`` [n, 7]); states None when
    the far end leaves ``bounds``."""
    end = goal.copy()
    end[:3] = goal[:3] + length * np.asarray(direction, float)
    if bounds is not None and not (np.all(bounds[0] <= end[:3]) and np.all(end[:3] <= bounds[1])):
        return end, None
    return end, interpolate_segment(goal, end, max(1, int(np.ceil(length / resolution))))


def free_retreats(
    checker: Callable[[np.ndarray], np.ndarray],
    goal: np.ndarray,
    length: float,
    resolution: float,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    directions: np.ndarray = RETREAT_DIRECTIONS,
) -> np.ndarray:
    """[D] bool: which straight, orientation-keeping retreats of ``length`` from ``goal``
    ``checker`` calls free (as :func:`find_retreat` judges one; False when leaving ``bounds``).
    The approach network's labels (``approach.approach_labels``)."""
    goal = np.asarray(goal, float)
    out = np.zeros(len(directions), bool)
    for i, d in enumerate(directions):
        _, states = _retreat_states(goal, d, float(length), resolution, bounds)
        out[i] = states is not None and not any_colliding(checker, states)
    return out


def plan_with_retreat(
    checker: Callable[[np.ndarray], np.ndarray],
    start: np.ndarray,
    goal: np.ndarray,
    bounds: tuple[np.ndarray, np.ndarray],
    rotation_weight: float,
    config: PlannerConfig = PlannerConfig(),
    retreat_checker: Callable[[np.ndarray], np.ndarray] | None = None,
    retreat_directions: np.ndarray = RETREAT_DIRECTIONS,
    retreat: Retreat | None = None,
) -> tuple[PlanResult, Retreat | None]:
    """RRT-Connect to a pre-goal, then straight in: :func:`find_retreat` (lengths
    ``config.retreat_lengths``) and, when a retreat is free, :func:`plan` from ``start`` to its
    pre-goal with what is left of the time limit, the path ending pre-goal -> goal. Without a
    free retreat (or with ``retreat_lengths`` empty) the plain plan to the goal. The search's
    time and states count in the result. ``retreat_checker``: the retreat's checker when not
    ``checker`` (``approach.never_colliding``: a network's choice taken as free).
    ``retreat_directions``: those tried, in order (the approach network's ranking; empty: the
    plain plan)."""
    lo, hi = np.asarray(bounds[0], float), np.asarray(bounds[1], float)
    spent_s, spent_states, spent_calls = 0.0, 0, 0
    found = retreat
    if found is None and config.retreat_lengths:
        found = find_retreat(retreat_checker or checker, goal, config.retreat_lengths,
                             config.resolution, (lo, hi), retreat_directions)  # fmt: skip
    if found is None:
        res = plan(checker, start, goal, bounds, rotation_weight, config)
        return PlanResult(res.path, res.status, res.planning_s + spent_s,
                          res.states_checked + spent_states, res.checker_calls + spent_calls), None  # fmt: skip
    left = dataclasses.replace(config, time_limit=max(config.time_limit - found.seconds, 0.01))
    res = plan(checker, start, found.pregoal, bounds, rotation_weight, left)
    path = None
    if res.path is not None:
        path = np.concatenate([res.path, np.asarray(found.via, float).reshape(-1, 7),
                               np.asarray(goal, float)[None]])  # fmt: skip
    return PlanResult(path, res.status, res.planning_s + found.seconds + spent_s,
                      res.states_checked + found.states_checked + spent_states,
                      res.checker_calls + spent_calls), found  # fmt: skip
