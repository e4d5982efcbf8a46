"""Issue 13 probe (thirty-ninth session): how far is a threaded goal from being off its
support, moving the object by translations only?

For each benchmark goal that neither one nor two straight moves take off the support
(``probe_dogleg.py``'s *threaded* goals), a breadth-first search on a lattice of ``--step``
translations (26 directions, orientation kept) from the goal, every edge checked on the full
meshes at 2 mm, until a node is ``--clear`` off the support (``MeshChecker.clearance``) or
``--max-nodes`` are expanded. Reported: the route's length in steps and metres (None: no
translation-only way off found within the cap: a rotation is needed, or the goal is locked, as a
ring on a closed bar).

    python scripts/probe_route_bfs.py --dogleg results/paths_s39/dogleg_heldout.json \\
        --out results/paths_s39/route_bfs_threaded.json        # a few min, CPU
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

import numpy as np

from experiments import eval_paths
from omnihang_jax import collision, planner


def bfs_route(
    mesh, goal, step: float, clear: float, max_nodes: int, bounds
) -> tuple[list | None, int]:
    """(the lattice route off the support as lattice offsets [k][3] from the goal, goal first,
    or None; nodes expanded): ``planner.lattice_retreat`` with "``clear`` off" as its end."""
    found, expanded = planner.lattice_retreat(
        mesh, goal, step, lambda pose: float(mesh.clearance(pose)[0]) >= clear, max_nodes, bounds
    )
    if found is None:
        return None, expanded
    pts = [np.asarray(goal, float)[:3], *[v[:3] for v in found.via[::-1]], found.pregoal[:3]]
    return [np.rint((p - pts[0]) / step).astype(int).tolist() for p in pts], expanded


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dogleg", required=True, help="probe_dogleg.py's JSON of the same goals")
    ap.add_argument("--pairs-from", default="out/paths_records.jsonl.gz")
    ap.add_argument("--pairs", type=int, default=80)
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--step", type=float, default=0.015)
    ap.add_argument("--clear", type=float, default=0.01)
    ap.add_argument("--max-nodes", type=int, default=3000)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    kinds = {r["pair"]: r for r in json.loads(Path(args.dogleg).read_text())["pairs"]}
    threaded = {
        p for p, r in kinds.items() if r["straight_off"] is None and r["dogleg_off"] is None
    }
    cases = eval_paths.load_pairs(args.data, args.pairs,
                                  records=eval_paths.read_answers(args.pairs_from), names=threaded)  # fmt: skip
    rows = []
    for case in cases:
        t0 = time.perf_counter()
        mesh = collision.MeshChecker(case.scene, 1e-3)
        lo, hi = planner.default_bounds(case.scene)
        route, expanded = bfs_route(mesh, case.goal, args.step, args.clear, args.max_nodes,
                                    (np.asarray(lo), np.asarray(hi)))  # fmt: skip
        length = None
        if route is not None:
            pts = args.step * np.asarray(route, float)
            length = round(float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()), 3)
        rows.append(dict(pair=case.name, support_family=case.meta["support_family"],
                         steps=None if route is None else len(route) - 1, length_m=length,
                         route=route, expanded=expanded,
                         seconds=round(time.perf_counter() - t0, 1)))  # fmt: skip
        print({k: v for k, v in rows[-1].items() if k != "route"}, flush=True)
    found = [r for r in rows if r["steps"] is not None]
    summary = dict(threaded=len(rows), off_by_translation=len(found),
                   by_family={f: dict(goals=n, off=sum(r["support_family"] == f for r in found))
                              for f, n in Counter(r["support_family"] for r in rows).items()},
                   median_length_m=float(np.median([r["length_m"] for r in found])) if found else None)  # fmt: skip
    result = dict(settings=vars(args), summary=summary, pairs=rows)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(summary, indent=1))
    return result


if __name__ == "__main__":
    main()
