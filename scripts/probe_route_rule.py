"""Issue 13 probe (fortieth session): what a route network would decide on the path
benchmark's held-out goals, before planning, against the truth on the full meshes.

For each of the 80 held-out first goals: the adopted straight approach rule's decision
(``--approach`` at ``--approach-threshold``, open side), the route network's best route and its
probability, whether that route is truly free and ends off the support on the meshes
(``approach.route_labels``), whether any route of the network's set is, and the goal's kind
(off in one straight move / two moves / threaded: ``scripts/probe_dogleg.py``'s table). Per
threshold, for ``fill`` (only where the straight rule gives none) and ``first`` (the route
network first): how many goals take a route and how many of those routes are truly good.

    python scripts/probe_route_rule.py --routes weights/approach_routes_s40 \\
        --out results/paths_s40/route_rule_heldout.json      # ~1 min, CPU

``--validation P``: instead, the first goals of the validation objects among the route
network's P training pairs (its whole-object split, never trained on; labels from its label
files): the rule's threshold is chosen there, the lowest whose ``fill`` routes are >= ``--target``
good (0.85: the goals ``fill`` acts on plan at ~75 % precision without an approach, and "good" asks
more than the straight rule's 90 %-free label: free *and* off the support).
"""

from __future__ import annotations

import argparse
import json
import time
import types
from collections import Counter
from pathlib import Path

import numpy as np

from experiments import eval_paths, train_approach
from omnihang_jax import approach, dataset_bridge

THRESHOLDS = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)


def validation_cases(data: str, pairs: int, config, val_mod: int = 7, workers: int = 1,
                     progress: bool = False):  # fmt: skip
    """(cases, labels [P, R]) of the validation objects' first goals among the first ``pairs``
    training pairs (``train_approach``'s pair order and whole-object split); the validation
    objects' pair files are derived where missing (``workers`` processes), the others never."""
    from experiments import train_collision

    names = dataset_bridge.read_recipe(data)["pairs"]

    def validation(index: int) -> bool:
        return bool(train_approach.object_split([names[index][0]], val_mod)[0])

    files = train_collision.derive_collision_pairs(
        data, {"train": pairs}, workers, progress, shuffle_seed=0,
        only=lambda i: i % eval_paths.VAL_EVERY != 0, derive_only=validation,
    )["train"]  # fmt: skip
    # the pair index leads the file name (dataset_bridge.pair_file_name)
    files = [f for f in files
             if validation(int(f.stem.split("_", 1)[0])) and train_collision.is_complete(f)]  # fmt: skip
    labels = train_approach.label_pairs(data, files, config, workers, progress, goals=3)
    cases, out = [], []
    for f, lf in zip(files, labels):
        with np.load(f) as z:
            wall = float(z["wall_y"]) if "wall_y" in z.files else float("nan")
            cases.append(types.SimpleNamespace(
                name=f.stem, meta=dict(support_family=z["support_family"].item()),
                object_points=z["object_points"], support_points=z["support_points"],
                support_normals=z["support_normals"],
                goal=z["stable_poses"][0].astype(np.float64),
                wall_y=wall if np.isfinite(wall) else None,
            ))  # fmt: skip
        with np.load(lf) as zl:
            out.append(zl["labels"][0])
    return cases, np.array(out)


def sweep(rows: list[dict], mode: str, thresholds=THRESHOLDS) -> list[dict]:
    """Per threshold: goals given a route (``used``), of those truly good (``good``), split by
    goal kind, under ``mode`` "fill" (only goals without a straight approach) or "first"."""
    out = []
    for t in thresholds:
        pool = [r for r in rows if mode == "first" or not r["straight_used"]]
        used = [r for r in pool if r["route_p"] >= t]
        by_kind = Counter(r["kind"] for r in used)
        good_kind = Counter(r["kind"] for r in used if r["route_good"])
        good = sum(r["route_good"] for r in used)
        out.append(dict(threshold=t, used=len(used), good=good,
                        used_free=round(good / len(used), 4) if used else None,
                        by_kind={k: [good_kind[k], n] for k, n in sorted(by_kind.items())}))  # fmt: skip
    return out


def goal_kinds(path) -> dict[str, str]:
    """pair -> its goal's kind ("off_straight", "off_two_moves", "threaded") from a
    ``probe_dogleg.py`` output (thirty-ninth session)."""
    return {
        r["pair"]: "off_straight" if r["straight_off"] is not None
        else "off_two_moves" if r["dogleg_off"] is not None else "threaded"
        for r in json.loads(Path(path).read_text())["pairs"]
    }  # fmt: skip


def label_kind(labels: np.ndarray, config) -> str:
    """A goal's kind from its route labels (validation goals have no probe_dogleg row)."""
    if labels[config.routes[:, 0] < 0].any():
        return "off_straight"
    return "off_two_moves" if labels.any() else "neither"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--routes", required=True, help="the route network's folder")
    ap.add_argument("--approach", default="weights/approach_s37_8k")
    ap.add_argument("--approach-threshold", type=float, default=0.8)
    ap.add_argument("--kinds", default="results/paths_s39/dogleg_heldout.json")
    ap.add_argument("--pairs-from", default="out/paths_records.jsonl.gz")
    ap.add_argument("--pairs", type=int, default=80)
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--views", type=int, default=1,
                    help="the route network's probabilities averaged over N cloud subsets")  # fmt: skip
    ap.add_argument(
        "--target",
        type=float,
        default=0.85,
        help="the rule: lowest threshold whose fill routes are this share good",
    )
    ap.add_argument("--validation", type=int, default=0, metavar="P",
                    help="the validation objects' first goals of P training pairs instead")  # fmt: skip
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)

    kinds = {} if args.validation else goal_kinds(args.kinds)
    est = types.SimpleNamespace(
        approach=approach.load_predictor(args.approach, args.approach_threshold),
        approach_open_side=True, approach_check="none",
        routes=approach.load_predictor(args.routes, views=args.views),
    )  # fmt: skip
    config = est.routes.config
    if args.validation:
        cases, known = validation_cases(args.data, args.validation, config)
    else:
        cases = eval_paths.load_pairs(
            args.data, args.pairs, records=eval_paths.read_answers(args.pairs_from)
        )
    rows, t0 = [], time.perf_counter()
    for k, case in enumerate(cases):
        directions, _, _ = eval_paths.learned_approach(case, est)
        probs = est.routes.probabilities(case.object_points, case.support_points, case.goal)
        if args.validation:
            labels = known[k]
        else:
            labels = approach.route_labels(case.scene, case.goal[None], config)[0]
        best = int(np.argmax(probs))
        route = config.routes[best]
        rows.append(dict(
            pair=case.name, family=case.meta["support_family"],
            kind=kinds.get(case.name) or label_kind(labels, config),
            straight_used=bool(len(directions)), route=[int(route[0]), float(route[1]), int(route[2])],
            route_p=round(float(probs[best]), 4), route_two_moves=bool(route[0] >= 0), route_good=bool(labels[best]),
            any_good=bool(labels.any()),
        ))  # fmt: skip
    result = dict(
        settings=vars(args) | dict(routes_config=dict(first_lengths=list(config.first_lengths),
                                                      clear=config.clear, outputs=config.outputs)),
        seconds=round(time.perf_counter() - t0, 1),
        goals=len(rows),
        kinds=dict(Counter(r["kind"] for r in rows)),
        rule_threshold=train_approach.rule_threshold(sweep(rows, "fill"), args.target),
        rule_target=args.target,
        any_good_by_kind={k: sum(r["any_good"] for r in rows if r["kind"] == k)
                          for k in sorted({r["kind"] for r in rows})},
        straight_used=sum(r["straight_used"] for r in rows),
        fill=sweep(rows, "fill"),
        first=sweep(rows, "first"),
        rows=rows,
    )  # fmt: skip
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: result[k] for k in ("goals", "kinds", "any_good_by_kind",
                                             "straight_used", "fill", "first")}, indent=1))  # fmt: skip
    return result


if __name__ == "__main__":
    main()
