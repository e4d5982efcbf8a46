"""Issue 13 probe (forty-first session): the route network's choice checked on the observed
clouds before it is taken, against the truth on the full meshes.

The fortieth session's route rule takes the route network's best route when its probability
reaches a threshold, as free. This asks, for the network's candidate routes (probability >=
0.3, best first, at most ``--tries``), two questions the planner can answer itself from the
observed clouds:

- ``checker``: does the best planner's own checker (the hybrid: the observed-cloud penetration
  test, then the contact NCE, lenient within 2 cm of the goal) call every state of the route
  free (``planner.route_states`` at the planner's 5-mm resolution)?
- ``end gap``: is the route's end at least ``g`` clear between the observed clouds
  (``collision.cloud_gap``)? Observed points lie on the true surfaces, so the true clearance
  is never larger than the observed one: a route whose observed end gap is under the label's
  1 cm cannot truly end off the support.

A rule takes the first candidate at or above the threshold that passes its checks (``none``
is the fortieth session's rule: the best route, if confident). Per rule and threshold, in
``fill`` mode (only where the straight approach rule gives none) and ``first`` mode: goals
given a route and how many of those routes are truly good (free on the meshes and ending >= 1
cm off the support and the wall: ``approach.route_labels``). The rule is chosen on the
validation objects' goals (``--validation P``: never trained on by the route network; the
contact NCE did train on those pairs, so the ``checker`` rows are optimistic there), then read
once on the 80 held-out goals of the path benchmark.

    python scripts/probe_route_check.py --routes weights/approach_routes_s40_8k --validation 8000 \\
        --out results/paths_s41/route_check_validation.json      # ~10 min, CPU (969 goals)
    python scripts/probe_route_check.py --routes weights/approach_routes_s40_8k \\
        --out results/paths_s41/route_check_heldout.json         # ~1 min
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import types
from collections import Counter
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
import probe_route_rule  # noqa: E402

from experiments import eval_paths  # noqa: E402
from omnihang_jax import approach, collision, planner  # noqa: E402

THRESHOLDS = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8)
END_GAPS = (0.0, 0.005, 0.01)
FLOOR = 0.3  # the lowest probability a candidate route is looked at


def hybrid_settings(geometric_file: str, near: float, far: float, ball: float):
    """The best planner's checker settings (docs/paths.md: the hybrid with the NCE lenient near
    the goal): the observed-cloud test of ``geometric_file``'s chosen row."""
    settings = planner.HybridSettings.from_selection(geometric_file, near, ball)
    return settings._replace(far_threshold=far)


def add_planner_args(ap: argparse.ArgumentParser) -> None:
    """The best planner's straight approach rule and checker settings, as flags (defaults: the
    adopted planner's; shared with ``probe_checked_lattice.py``)."""
    ap.add_argument("--approach", default="weights/approach_s37_8k")
    ap.add_argument("--approach-threshold", type=float, default=0.8)
    ap.add_argument("--weights", default="weights/collision_s18_contact", help="the contact NCE")
    ap.add_argument("--geometric", default="results/paths_hybrid_s18_joint95_selection.json")
    ap.add_argument("--nce-threshold", type=float, default=0.99, help="within the goal ball")
    ap.add_argument("--nce-far-threshold", type=float, default=0.56)
    ap.add_argument("--nce-goal-ball", type=float, default=0.02)
    ap.add_argument("--resolution", type=float, default=planner.PlannerConfig().resolution)


def candidate_rows(case, probs, labels, routes_cfg, checker, tries: int, resolution: float,
                   floor: float = FLOOR):  # fmt: skip
    """Per candidate route (probability >= ``floor``, best first, at most ``tries``): its index,
    probability, truth, whether ``checker`` calls all its states free, its observed end gap."""
    order = np.argsort(-probs, kind="stable")
    order = order[probs[order] >= floor][:tries]
    if not len(order):
        return []
    tree = cKDTree(np.asarray(case.support_points, float))
    states = [planner.route_states(case.goal, routes_cfg.routes[r], routes_cfg.length, resolution)
              for r in order]  # fmt: skip
    flat = np.concatenate(states)
    flags = np.asarray(checker(flat), bool)
    ends = np.stack([s[-1] for s in states])
    gaps = collision.cloud_gap(case.object_points, tree, ends, upper=0.05)
    out, at = [], 0
    for r, s, gap in zip(order, states, gaps, strict=True):
        out.append(dict(route=int(r), p=round(float(probs[r]), 4), good=bool(labels[r]),
                        free=not bool(flags[at:at + len(s)].any()),
                        end_gap=round(float(min(gap, 0.05)), 4)))  # fmt: skip
        at += len(s)
    return out


def choose(cands: list[dict], threshold: float, check: str, end_gap: float):
    """The rule's route among a goal's candidates: the first (best first) at or above
    ``threshold`` passing ``check`` ("none", "checker") and the end gap; None: no route."""
    for c in cands:
        if c["p"] < threshold:
            break
        if check == "checker" and not c["free"]:
            continue
        if c["end_gap"] < end_gap:
            continue
        return c
    return None


def sweep(rows: list[dict], mode: str, thresholds=THRESHOLDS, end_gaps=END_GAPS) -> list[dict]:
    """Per rule (check, end gap) and threshold: goals given a route, how many truly good."""
    out = []
    pool = [r for r in rows if mode == "first" or not r["straight_used"]]
    for check in ("none", "checker"):
        for gap in end_gaps:
            for t in thresholds:
                picks = [(r, choose(r["candidates"], t, check, gap)) for r in pool]
                used = [(r, c) for r, c in picks if c is not None]
                good = sum(c["good"] for _, c in used)
                kinds = Counter(r["kind"] for r, _ in used)
                good_kinds = Counter(r["kind"] for r, c in used if c["good"])
                out.append(dict(check=check, end_gap=gap, threshold=t, used=len(used), good=good,
                                used_good=round(good / len(used), 4) if used else None,
                                by_kind={k: [good_kinds[k], n] for k, n in sorted(kinds.items())}))  # fmt: skip
    return out


def chosen_rule(table: list[dict], target: float) -> dict | None:
    """The validation rule: among the rows whose routes are >= ``target`` good, the one giving
    the most goals a route (ties: the lower threshold, then the simpler check)."""
    ok = [r for r in table if r["used"] and r["used_good"] >= target]
    if not ok:
        return None
    return max(ok, key=lambda r: (r["used"], -r["threshold"], r["check"] == "none", -r["end_gap"]))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--routes", required=True, help="the route network's folder")
    add_planner_args(ap)
    ap.add_argument("--tries", type=int, default=10, help="candidate routes looked at a goal")
    ap.add_argument("--kinds", default="results/paths_s39/dogleg_heldout.json")
    ap.add_argument("--pairs-from", default="out/paths_records.jsonl.gz")
    ap.add_argument("--pairs", type=int, default=80)
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--target", type=float, default=0.85)
    ap.add_argument("--validation", type=int, default=0, metavar="P",
                    help="the validation objects' first goals of P training pairs instead")  # fmt: skip
    ap.add_argument("--rule", default=None, metavar="JSON",
                    help="a validation run's output: its chosen rule is read off here too")  # fmt: skip
    ap.add_argument(
        "--thresholds",
        type=float,
        nargs="+",
        default=list(THRESHOLDS),
        help="the rules' probability thresholds (the lowest is the candidates' floor)",
    )
    ap.add_argument("--end-gaps", type=float, nargs="+", default=list(END_GAPS), metavar="M")
    ap.add_argument(
        "--workers",
        type=int,
        default=1,
        help="processes deriving the validation pairs' files where missing",
    )
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    floor = min(args.thresholds)
    if floor <= 0 or max(args.thresholds) >= 1 or min(args.end_gaps) < 0:
        ap.error("thresholds must lie in (0, 1) and end gaps be >= 0")

    est = types.SimpleNamespace(
        approach=approach.load_predictor(args.approach, args.approach_threshold),
        approach_open_side=True, approach_check="none",
        routes=approach.load_predictor(args.routes),
    )  # fmt: skip
    routes_cfg = est.routes.config
    nce_cfg, nce_params, _ = collision.load_estimator(Path(args.weights, "nce"))
    settings = hybrid_settings(args.geometric, args.nce_threshold, args.nce_far_threshold,
                               args.nce_goal_ball)  # fmt: skip
    kinds = {}
    if not args.validation:
        kinds = probe_route_rule.goal_kinds(args.kinds)
        cases = eval_paths.load_pairs(
            args.data, args.pairs, records=eval_paths.read_answers(args.pairs_from)
        )
        known = None
    else:
        cases, known = probe_route_rule.validation_cases(
            args.data,
            args.validation,
            routes_cfg,
            workers=args.workers,
            progress=not args.no_progress,
        )
    rows, t0 = [], time.perf_counter()
    for k, case in enumerate(tqdm(cases, desc="goals", disable=args.no_progress)):
        directions, _, _ = eval_paths.learned_approach(case, est)
        probs = est.routes.probabilities(case.object_points, case.support_points, case.goal)
        if known is not None:
            labels = known[k]
        else:
            labels = approach.route_labels(case.scene, case.goal[None], routes_cfg)[0]
        checker = None
        if probs.max() >= floor:  # built (its support table, its NCE calls) only when asked
            weight = 0.5 * float(np.ptp(case.object_points, axis=0).max())
            checker = planner.hybrid_checker(
                nce_cfg, nce_params, case.object_points, case.support_points,
                case.support_normals, settings, case.goal, weight,
            )  # fmt: skip
        rows.append(dict(
            pair=case.name, family=case.meta["support_family"],
            kind=kinds.get(case.name) or probe_route_rule.label_kind(labels, routes_cfg),
            straight_used=bool(len(directions)), any_good=bool(labels.any()),
            candidates=candidate_rows(case, probs, labels, routes_cfg, checker, args.tries,
                                      args.resolution, floor),
        ))  # fmt: skip
    fill = sweep(rows, "fill", args.thresholds, args.end_gaps)
    first = sweep(rows, "first", args.thresholds, args.end_gaps)
    result = dict(
        settings=vars(args), seconds=round(time.perf_counter() - t0, 1), goals=len(rows),
        kinds=dict(Counter(r["kind"] for r in rows)),
        straight_used=sum(r["straight_used"] for r in rows),
        chosen_fill=chosen_rule(fill, args.target), chosen_first=chosen_rule(first, args.target),
        fill=fill, first=first, rows=rows,
    )  # fmt: skip
    if args.rule:
        rule = json.loads(Path(args.rule).read_text())
        for mode, table in (("fill", fill), ("first", first)):
            pick = rule.get(f"chosen_{mode}")
            result[f"validation_rule_{mode}"] = pick and next(
                r for r in table if all(r[k] == pick[k] for k in ("check", "end_gap", "threshold"))
            )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    show = {
        k: result[k] for k in ("goals", "kinds", "straight_used", "chosen_fill", "chosen_first")
    }
    for k in ("validation_rule_fill", "validation_rule_first"):
        if k in result:
            show[k] = result[k]
    print(json.dumps(show, indent=1))
    return result


if __name__ == "__main__":
    main()
