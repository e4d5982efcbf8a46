"""Issue 13, from the rows of `eval_paths` runs (no planning; forty-fifth session, docs/paths.md):
a run planned in full against the spliced run of the same OMPL seed (on the pairs the spliced run
planned itself and on those it took from its reference run), the outcomes split by whether a
checked route was used, and what refusing slow paths on goals without one would do.

    python scripts/probe_full_runs.py --full results/paths_s45/full_seed1.pairs.jsonl \\
        --spliced results/paths_s41/first_seed1.pairs.jsonl --planned results/paths_s41/plan_first_seed1.txt \\
        --runs results/paths_s45/full_seed1.pairs.jsonl results/paths_s41/first_seed2.pairs.jsonl \\
            results/paths_s43/full_seed3.pairs.jsonl \\
        --out results/paths_s45/full_seed1_and_refusal.json

Outcomes and figures as `scripts/compare_path_runs.py`. The refusal rule: no path is returned on
a goal without a checked route (`approach.route.rank` is None) when planning took more than T
seconds; precision / recall / F1 over the rows of all ``--runs`` together.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from compare_path_runs import figures, outcome  # noqa: E402

THRESHOLDS_S = (10, 15, 20, 25, 30, 40)


def read_rows(path: str, method: str = "nce_geometric") -> dict[str, dict]:
    rows = [json.loads(x) for x in Path(path).read_text().splitlines() if x.strip()]
    rows = {r["pair"]: r for r in rows if r["method"] == method}
    if not rows:
        raise SystemExit(f"{path}: no {method} rows")
    return rows


def routed(row: dict) -> bool:
    """Whether the plan used a checked route off the support (the route rule's first kind)."""
    return ((row.get("approach") or {}).get("route") or {}).get("rank") is not None


def full_against_spliced(full: dict, spliced: dict, planned: set[str]) -> dict:
    missing = set(spliced) - set(full)
    if missing:
        raise SystemExit(f"the full run lacks {len(missing)} of the spliced run's pairs")
    out = {}
    for name, keys in (("planned_by_the_rule", [k for k in spliced if k in planned]),
                       ("reference_rows", [k for k in spliced if k not in planned])):  # fmt: skip
        out[name] = dict(
            spliced=dict(Counter(outcome(spliced[k]) for k in keys)),
            full=dict(Counter(outcome(full[k]) for k in keys)),
            changed=sum(outcome(spliced[k]) != outcome(full[k]) for k in keys),
        )
    for name, rows in (("spliced", spliced), ("full", full)):
        out[name] = figures([outcome(r) for r in rows.values()])
        out[name]["time_outs"] = sum(r["status"] != "Exact solution" for r in rows.values())
        out[name]["by_route"] = {
            kind: dict(Counter(outcome(r) for r in rows.values() if routed(r) == flag))
            for kind, flag in (("checked_route", True), ("no_checked_route", False))
        }
    return out


def refusal(rows: list[dict]) -> dict:
    unrouted = [r for r in rows if r["returned"] and not routed(r)]
    out = dict(
        baseline=figures([outcome(r) for r in rows]),
        planning_s_median_without_route={
            o: float(np.median([r["planning_s"] for r in unrouted if outcome(r) == o]))
            for o in ("free", "colliding")
            if any(outcome(r) == o for r in unrouted)
        },
        refuse_slow=[],
    )
    for t in THRESHOLDS_S:
        refused = {id(r) for r in unrouted if r["planning_s"] > t}
        kept = ["none" if id(r) in refused else outcome(r) for r in rows]
        dropped = [outcome(r) for r in unrouted if id(r) in refused]
        out["refuse_slow"].append(
            dict(threshold_s=t, dropped_free=dropped.count("free"),
                 dropped_colliding=dropped.count("colliding")) | figures(kept)
        )  # fmt: skip
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--full", required=True, help="rows of the run planned in full")
    ap.add_argument("--spliced", required=True, help="rows of the spliced run of the same seed")
    ap.add_argument("--planned", required=True, help="pair names the spliced run planned itself")
    ap.add_argument("--runs", nargs="+", required=True, help="rows for the refusal table")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    planned = {ln.strip() for ln in Path(args.planned).read_text().splitlines() if ln.strip()}
    result = dict(
        settings=vars(args),
        full_against_spliced=full_against_spliced(
            read_rows(args.full), read_rows(args.spliced), planned
        ),
        refusal=refusal([r for p in args.runs for r in read_rows(p).values()]),
    )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
