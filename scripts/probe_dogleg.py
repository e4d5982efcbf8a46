"""Issue 13 probe (thirty-ninth session): does a goal have a way *off* the support in one or
two straight moves, on the full meshes?

The approach network's label (``approach.approach_labels``) asks whether a straight 4.5-cm
move from the goal is free. On a pegboard's long wire arm that is often a slide along the arm:
free, but still threaded on the hook, so the planner's pre-goal is as hard to reach as the goal.
This probe asks, per goal (the first stable pose of the path benchmark's held-out pairs):

- ``straight``: some straight move of ``--length`` is free (the network's label);
- ``straight_off``: ... and ends with the object at least ``--clear`` from the support and the
  wall (MuJoCo's ``mj_geomDistance`` between every object and support part);
- ``dogleg_off``: some first move (lengths ``--first``, 26 directions) then a second straight
  move of ``--length`` (26 directions), both free, ending at least ``--clear`` away.

    python scripts/probe_dogleg.py --out results/paths_s39/dogleg_heldout.json   # ~1 min, CPU

``--runs F ...`` (planned runs' pairs.jsonl) splits their outcomes by the goal's kind.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from experiments import eval_paths
from omnihang_jax import collision, planner


def search(case, length: float, firsts, clear: float, resolution: float) -> dict:
    """The three answers for one case: the first free straight move's direction, and the
    first one-move / two-move route off the support (``planner.find_two_move_retreat``, the
    planner's direction order) as [first direction, first length, second direction] or None."""
    mesh = collision.MeshChecker(case.scene, 1e-3)
    lo, hi = planner.default_bounds(case.scene)
    bounds = (np.asarray(lo, float), np.asarray(hi, float))
    goal = np.asarray(case.goal, float)
    off = lambda pose: float(mesh.clearance(pose)[0]) >= clear  # noqa: E731
    free = planner.free_retreats(mesh, goal, length, resolution, bounds)
    out = dict(
        straight=planner.RETREAT_DIRECTIONS[free][0].round(3).tolist() if free.any() else None
    )

    def route(found):
        if found is None:
            return None
        if not len(found.via):
            return [found.direction.round(3).tolist(), found.length, None]
        first = found.via[0, :3] - goal[:3]
        size = float(np.linalg.norm(first))
        return [(first / size).round(3).tolist(), round(size, 4), found.direction.round(3).tolist()]

    # one search: the one-move routes come first, so a route without a corner is one move
    found = planner.find_two_move_retreat(mesh, goal, firsts, length, resolution, bounds, off)
    out["straight_off"] = route(found) if found is not None and not len(found.via) else None
    out["dogleg_off"] = route(found)
    return out


def kind_of(row: dict) -> str:
    """A goal's kind: a straight way off, off in two moves, or threaded (neither)."""
    if row["straight_off"] is not None:
        return "off_straight"
    return "off_two_moves" if row["dogleg_off"] is not None else "threaded"


def split_runs(rows: list[dict], runs: list[str]) -> dict:
    """The runs' outcomes (free / colliding / no path) pooled by goal kind, pegboards apart."""
    kinds = {r["pair"]: (kind_of(r), r["support_family"]) for r in rows}
    out = defaultdict(lambda: dict(pair_plans=0, free=0, colliding=0, no_path=0))
    for run in runs:
        for line in Path(run).read_text().splitlines():
            if not line.strip():
                continue
            r = json.loads(line)
            if r.get("method", "nce_geometric") != "nce_geometric" or r["pair"] not in kinds:
                continue
            kind, fam = kinds[r["pair"]]
            outcome = (
                "free" if r["collision_free"] else ("colliding" if r["returned"] else "no_path")
            )
            for key in (kind, f"{kind}/{'pegboard' if fam == 'pegboard_hook' else 'other'}"):
                out[key]["pair_plans"] += 1
                out[key][outcome] += 1
    for v in out.values():
        ret = v["free"] + v["colliding"]
        v["precision"] = round(100 * v["free"] / max(ret, 1), 1)
        v["recall"] = round(100 * v["free"] / max(v["pair_plans"], 1), 1)
    goals = defaultdict(int)
    for kind, _ in kinds.values():
        goals[kind] += 1
    return dict(files=runs, goals=dict(goals), by_kind=dict(sorted(out.items())))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs-from", default="out/paths_records.jsonl.gz")
    ap.add_argument("--pairs", type=int, default=80)
    ap.add_argument("--split", default="test", choices=["test", "train"],
                    help="train: training pairs' first goals (the label statistics of a "
                    "learned route; never the NCE's validation pairs)")  # fmt: skip
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--length", type=float, default=0.045, help="m, the straight move")
    ap.add_argument("--first", type=float, nargs="+", default=[0.015, 0.03, 0.045])
    ap.add_argument("--clear", type=float, default=0.01, help="m from the support at the end")
    ap.add_argument("--resolution", type=float, default=0.002)
    ap.add_argument("--runs", nargs="*", default=[],
                    help="eval_paths pairs.jsonl files to split by goal kind (off straight / "
                    "off in two moves / threaded)")  # fmt: skip
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    if args.runs and Path(args.out).exists():  # the goals are measured: only split the runs
        result = json.loads(Path(args.out).read_text())
        result["runs"] = split_runs(result["pairs"], args.runs)
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
        print(json.dumps(result["runs"]["by_kind"], indent=1))
        return result
    if args.split == "train":  # training pairs are derived on demand (a few s each)
        cases = eval_paths.load_pairs(args.data, args.pairs, split="train", workers=2)
    else:
        cases = eval_paths.load_pairs(
            args.data, args.pairs, records=eval_paths.read_answers(args.pairs_from)
        )
    rows = []
    t0 = time.perf_counter()
    for case in cases:
        r = search(case, args.length, args.first, args.clear, args.resolution)
        rows.append(dict(pair=case.name, support_family=case.meta["support_family"], **r))
        print(case.name, {k: r[k] for k in ("straight", "straight_off", "dogleg_off")},
              f"{time.perf_counter() - t0:.0f}s", flush=True)  # fmt: skip
    fam = defaultdict(lambda: dict(goals=0, straight=0, straight_off=0, dogleg_off=0))
    for r in rows:
        for key in (r["support_family"], "all"):
            f = fam[key]
            f["goals"] += 1
            for k in ("straight", "straight_off", "dogleg_off"):
                f[k] += r[k] is not None
    result = dict(settings=vars(args), by_family=dict(fam), pairs=rows)
    if args.runs:
        result["runs"] = split_runs(rows, args.runs)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(dict(fam), indent=1))
    return result


if __name__ == "__main__":
    main()
