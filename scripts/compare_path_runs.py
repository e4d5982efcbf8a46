"""Pair-by-pair comparison of eval_paths runs planned with the same OMPL seed (twenty-fifth
session): for each pair both runs planned, the outcome (free / colliding / time-out) as planned
(the rows' ``raw_*`` keys where the run cleared its paths) and as returned, and the transitions.

    python scripts/compare_path_runs.py results/paths80_goal_stable_s24_keep45.pairs.jsonl \\
        out/paths80_s25_compclear/pairs.jsonl [--out results/....json]
"""

import argparse
import json
from collections import Counter
from pathlib import Path


def load(path):
    rows = {}
    for line in Path(path).read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            rows[(r["pair"], r["method"])] = r  # a resumed run: the last row counts
    return rows


def outcome(r, raw):
    if not r["returned"]:
        return "time-out"
    free = r.get("raw_collision_free", r["collision_free"]) if raw else r["collision_free"]
    return "free" if free else "colliding"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("base")
    ap.add_argument("new")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    a, b = load(args.base), load(args.new)
    common = sorted(set(a) & set(b))
    out = dict(base=args.base, new=args.new, pairs=len(common))
    for raw in (True, False):
        key = "as_planned" if raw else "as_returned"
        trans = Counter(f"{outcome(a[k], raw)} -> {outcome(b[k], raw)}" for k in common)
        out[key] = dict(
            base=dict(Counter(outcome(a[k], raw) for k in common)),
            new=dict(Counter(outcome(b[k], raw) for k in common)),
            changed={
                t: n for t, n in sorted(trans.items()) if t.split(" -> ")[0] != t.split(" -> ")[1]
            },
        )
    print(json.dumps(out, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
