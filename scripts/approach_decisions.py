"""The cheap paired protocol for approach rules (issue 13, thirty-eighth session).

Runs of one OMPL seed nearly repeat (thirty-seventh session: 37 of 37 pairs identical across two
machines; 4 of 59 and 3 of 47 swaps between two rules on the pairs where they decide alike).
A paired comparison of a new approach rule against a planned reference run is therefore decided
by the pairs where the two rules' first plans decide differently (another direction, or an
approach against none). This script finds them without planning, and splices the new rule's run:

``diff``: the new rule's first-plan decision on every pair the reference runs planned (the
approach network on the pair's observed clouds, exactly as ``eval_paths.learned_approach``); a
pair is covered by the first reference that decided it the same way; the others are written as
a pair list for ``eval_paths --only-pairs``:

    python scripts/approach_decisions.py diff --reference results/paths80_device_s37_rule_seed3.pairs.jsonl \\
        --approach weights/approach_s37_8k --threshold 0.8 --open-side --views 4 --out out/s38/differ_seed3.txt

``splice``: the covering references' rows plus the new rows planned on the other pairs: an
estimate of the new rule's full run under the same seed (rows marked ``"spliced_from"``), for
``scripts/compare_path_runs.py``.

    python scripts/approach_decisions.py splice --decisions out/s38/differ_seed3.json \\
        --new out/s38/new_seed3/pairs.jsonl --out out/s38/spliced_seed3.pairs.jsonl
"""

from __future__ import annotations

import argparse
import json
import types
from pathlib import Path

from experiments.eval_paths import read_rows  # noqa: F401  (its splice reads runs so)
from omnihang_jax import approach


def decision(record: dict | None):
    """A row's ``approach`` record -> the first plan's direction (a tuple), its route
    (("route", first direction index, first length, last direction index); fortieth session,
    ``eval_paths --routes``) or None."""
    route = (record or {}).get("route") or {}
    if "waypoints" in route:
        return ("route", *route["best"])
    first = (record or {}).get("first_tried")
    return None if first is None else tuple(round(float(x), 3) for x in first)


def diff(args) -> dict:
    """The new rule's decision on every pair some reference planned; a pair is *covered* when a
    reference (first match in the given order) decided it the same way, else it is to plan."""
    from experiments import eval_paths

    refs = {str(r): read_rows(r) for r in args.reference}
    names = set().union(*refs.values())
    records = eval_paths.read_answers(args.pairs_from)
    cases = eval_paths.load_pairs(args.data, args.pairs, 1, False, records, False, names=names)
    lost = sorted(names - {c.name for c in cases})
    if lost:
        raise SystemExit(f"diff: {len(lost)} reference pair(s) are not among the --pairs "
                         f"{args.pairs} of --pairs-from (e.g. {lost[0]!r})")  # fmt: skip
    est = types.SimpleNamespace(
        approach=approach.load_predictor(args.approach, args.threshold, args.views),
        approach_open_side=args.open_side,
        approach_check="none",
        routes=approach.load_predictor(args.routes, args.routes_threshold, args.routes_views)
        if args.routes
        else None,
    )
    est.routes_check, est.routes_end_gap = args.routes_check, args.routes_end_gap
    est.routes_tries = args.routes_tries
    planner_est = None
    if args.routes_check == "checker":  # the best planner's own checker, as eval_paths builds it
        from omnihang_jax import planner

        geo = planner.HybridSettings.from_selection(args.geometric, 0.0, 0.0).geometric
        planner_est = eval_paths.load_estimators(
            args.weights, args.nce_threshold, args.nce_far_threshold, args.nce_goal_ball, geo
        )
    pairs = {}
    for case in cases:
        directions, _, record = eval_paths.learned_approach(case, est)
        if est.routes is not None and (args.routes_mode != "fill" or not len(directions)):
            check = None
            if planner_est is not None:
                check = eval_paths.checkers_for(
                    case, planner_est, 0.001, ("nce_geometric",), warm=False
                )["nce_geometric"]
            found, record["route"] = eval_paths.learned_route(case, est, check)
            if found is None and args.routes_mode == "only":
                eval_paths.drop_straight(record, directions)
        new = decision(record)
        cover = next((r for r, rows in refs.items() if case.name in rows
                      and decision(rows[case.name].get("approach")) == new), None)  # fmt: skip
        pairs[case.name] = dict(new=new, best_p=record["best_p"], covered_by=cover)
    differ = [p for p, d in pairs.items() if d["covered_by"] is None]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("".join(p + "\n" for p in differ))
    summary = dict(
        references=list(refs),
        rule=dict(
            weights=args.approach,
            threshold=args.threshold,
            open_side=args.open_side,
            views=args.views,
            routes=args.routes,
            routes_threshold=None if est.routes is None else est.routes.config.threshold,
            routes_mode=args.routes_mode,
            routes_views=args.routes_views,
            routes_check=args.routes_check,
            routes_end_gap=args.routes_end_gap,
            routes_tries=args.routes_tries,
        ),  # fmt: skip
        pairs=len(pairs),
        used_new=sum(d["new"] is not None for d in pairs.values()),
        used_route=sum(d["new"] is not None and d["new"][0] == "route" for d in pairs.values()),
        covered={r: sum(d["covered_by"] == r for d in pairs.values()) for r in refs},
        differ=len(differ),
        differ_pairs=differ,
        decisions=pairs,
    )
    Path(args.out).with_suffix(".json").write_text(json.dumps(summary, indent=1) + "\n")
    print(f"{len(pairs)} pairs: the new rule uses an approach on {summary['used_new']}; covered "
          f"{summary['covered']}; {len(differ)} to plan -> {args.out}")  # fmt: skip
    return summary


def splice(args) -> int:
    """The new rule's estimated run: each pair's row from the reference that covers it (``diff``'s
    decisions), else from the new run; rows marked ``spliced_from``."""
    decisions = json.loads(Path(args.decisions).read_text())["decisions"]
    new = read_rows(args.new) if args.new else {}
    missing = [p for p, d in decisions.items() if d["covered_by"] is None and p not in new]
    if missing:
        raise SystemExit(f"splice: {len(missing)} pair(s) to plan have no new row, e.g. "
                         f"{missing[0]!r}: plan them first (eval_paths --only-pairs)")  # fmt: skip
    wrong = [p for p, d in decisions.items() if d["covered_by"] is None
             and decision(new[p].get("approach")) != (None if d["new"] is None else tuple(d["new"]))]  # fmt: skip
    if wrong:
        raise SystemExit(f"splice: {len(wrong)} new row(s) decided otherwise than diff's rule, "
                         f"e.g. {wrong[0]!r}: --new is another rule's or seed's run")  # fmt: skip
    refs = {r: read_rows(r) for r in {d["covered_by"] for d in decisions.values()} - {None}}
    with open(args.out, "w") as f:
        for pair, d in decisions.items():
            src = d["covered_by"] or str(args.new)
            row = refs[src][pair] if d["covered_by"] else new[pair]
            f.write(json.dumps(dict(row, spliced_from=src)) + "\n")
    planned = sum(d["covered_by"] is None for d in decisions.values())
    print(f"{len(decisions)} rows ({planned} newly planned) -> {args.out}")
    return len(decisions)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("diff", help="the pairs where a new rule decides differently")
    d.add_argument(
        "--reference",
        nargs="+",
        required=True,
        help="planned runs' pairs.jsonl of the same OMPL seed and machine kind",
    )
    d.add_argument("--approach", nargs="+", required=True, help="approach weights (several: mean)")
    d.add_argument("--threshold", type=float, required=True)
    d.add_argument("--open-side", action="store_true")
    d.add_argument("--views", type=int, default=1, help="cloud subsets averaged")
    d.add_argument("--routes", help="a route network (eval_paths --routes)")
    d.add_argument("--routes-threshold", type=float)
    d.add_argument("--routes-mode", choices=("fill", "first", "only"), default="fill")
    d.add_argument("--routes-views", type=int, default=1)
    d.add_argument("--routes-check", choices=("none", "checker"), default="none",
                   help="eval_paths --routes-check (checker: the best planner's hybrid, below)")  # fmt: skip
    d.add_argument("--routes-end-gap", type=float, default=0.0)
    d.add_argument("--routes-tries", type=int, default=10)
    d.add_argument("--weights", default="weights/collision_s18_contact",
                   help="with --routes-check checker: the planner's NCE (eval_paths --weights)")  # fmt: skip
    d.add_argument("--geometric", default="results/paths_hybrid_s18_joint95_selection.json")
    d.add_argument("--nce-threshold", type=float, default=0.99)
    d.add_argument("--nce-far-threshold", type=float, default=0.56)
    d.add_argument("--nce-goal-ball", type=float, default=0.02)
    d.add_argument("--data", default="datasets/paper")
    d.add_argument("--pairs", type=int, default=80)
    d.add_argument("--pairs-from", default="out/paths_records.jsonl.gz")
    d.add_argument("--out", required=True, help="the pair list (and OUT.json, the decisions)")
    s = sub.add_parser("splice", help="reference rows + the new rows on the differing pairs")
    s.add_argument("--decisions", required=True, help="diff's OUT.json")
    s.add_argument("--new", default=None, help="the run planned on diff's pair list")
    s.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    return diff(args) if args.cmd == "diff" else splice(args)


if __name__ == "__main__":
    main()
