"""Splice planned rows into a reference run: every pair's row from ``--new`` where it has one,
else from ``--reference`` (each row marked ``spliced_from``), for ``compare_path_runs.py``.
For a probe that changes the planner on a known set of pairs only (thirty-ninth session: the
oracle two-move approach on the 17 goals that need two moves off the support); an approach
*rule* has its own checked splice (``approach_decisions.py``).

    python scripts/splice_rows.py --reference results/paths80_device_s37_rule_seed3.pairs.jsonl \\
        --new results/paths_s39/planned_device_two_moves_seed3.pairs.jsonl --out F.pairs.jsonl
"""

from __future__ import annotations

import argparse
import json

from experiments import eval_paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reference", required=True)
    ap.add_argument("--new", required=True)
    ap.add_argument("--method", default="nce_geometric")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)

    ref = eval_paths.read_rows(args.reference, args.method)
    new = eval_paths.read_rows(args.new, args.method)
    stray = sorted(set(new) - set(ref))
    if stray:
        raise SystemExit(f"{len(stray)} new pair(s) the reference lacks, e.g. {stray[0]!r}")
    with open(args.out, "w") as f:
        for pair, row in ref.items():
            src = args.new if pair in new else args.reference
            f.write(json.dumps(dict(new.get(pair, row), spliced_from=src)) + "\n")
    print(f"{len(ref)} rows ({len(new)} from {args.new}) -> {args.out}")
    return len(ref)


if __name__ == "__main__":
    main()
