"""Which rule should pick the approach direction from the approach network's probabilities
(issue 13, thirty-sixth session)? A probe on labels only, no planning.

For the validation objects' goals (the training run's whole-object split) and the path
benchmark's held-out goals, every rule below is scored by how often it *uses* an approach and
how often a used one is *free* on the full meshes (the planner's straight 4.5-cm segment):

- ``argmax t``: the best direction when its probability reaches t (the thirty-fifth session's);
- ``order t``: the first direction in the planner's fixed order (upward first, the oracle's
  order) whose probability reaches t;
- each with ``open`` (no direction towards a wall-mounted support's wall, ``--approach-open-side``).

    python scripts/probe_approach_rule.py --weights weights/approach_s35 weights/approach_s35_6k \
        --out results/approach_rule_s36.json

Thirty-eighth session: ``--views N`` also scores each network on N subsets of the clouds
(``local_from`` points drawn with seeds 0..N-1; the planner uses seed 0) averaged (``W@N``), and
``--ensemble`` the mean of all the given networks' probabilities (``ensemble@N``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from experiments import eval_paths, train_approach, train_collision
from omnihang_jax import approach

THRESHOLDS = (0.3, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95)


def walls(files: list[Path]) -> np.ndarray:
    """[P] bool: the pair's support is wall-mounted."""
    out = []
    for f in files:
        with np.load(f) as z:
            out.append(eval_paths._wall_of(z) is not None)
    return np.array(out)


def choose(prob: np.ndarray, wall: np.ndarray, rule: str, t: float, open_side: bool) -> np.ndarray:
    """[R] the chosen direction per goal (``prob`` [R, 26] in ``approach.DIRECTIONS`` order),
    -1 when none is used; what may be used is the planner's own rule (``approach.usable``)."""
    ok = np.stack([approach.usable(approach.DIRECTIONS, p, t, w, open_side)
                   for p, w in zip(prob, wall)])  # fmt: skip
    if rule == "argmax":
        masked = np.where(ok, prob, -1.0)
        best = masked.argmax(1)
        return np.where(ok.any(1), best, -1)
    first = ok.argmax(1)  # the fixed order: the first that passes
    return np.where(ok.any(1), first, -1)


def table(prob, labels, wall) -> list[dict]:
    rows = []
    for open_side in (False, True):
        for rule in ("argmax", "order"):
            for t in THRESHOLDS:
                c = choose(prob, wall, rule, t, open_side)
                used = c >= 0
                free = labels[np.flatnonzero(used), c[used]]
                rows.append(dict(rule=rule, threshold=t, open_side=open_side,
                                 used=round(float(used.mean()), 4),
                                 used_free=round(float(free.mean()), 4) if used.any() else None,
                                 used_blocked=int((~free).sum()), goals=int(len(c))))  # fmt: skip
    return rows


def family_of(path: Path) -> str:
    """The support family of a derived pair file (``<index>_<object>__<family>_<nnnn>.npz``)."""
    return Path(path).stem.split("__")[1].rsplit("_", 1)[0]


def by_family(prob, labels, wall, families, t: float) -> dict:
    """Per support family at ``argmax t`` with the open side (the planner's rule): goals, the
    share with any free direction, the share used and the used ones' free share."""
    c = choose(prob, wall, "argmax", t, True)
    out = {}
    for fam in sorted(set(families)):
        m = np.array([f == fam for f in families])
        used = m & (c >= 0)
        free = labels[np.flatnonzero(used), c[used]]
        out[fam] = dict(goals=int(m.sum()), any_free=round(float(labels[m].any(1).mean()), 3),
                        used=round(float(used.sum() / max(m.sum(), 1)), 3),
                        used_free=round(float(free.mean()), 3) if used.any() else None)  # fmt: skip
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--weights", nargs="+", required=True)
    ap.add_argument("--pairs", type=int, default=1600, help="the training run's pairs")
    ap.add_argument("--val-mod", type=int, default=7)
    ap.add_argument("--test-pairs", type=int, default=80)
    ap.add_argument(
        "--pairs-from", default="results/hanging_success_stage3_s14_cemv.pairs.jsonl.gz"
    )
    ap.add_argument("--views", type=int, default=1, help="also average N cloud subsets")
    ap.add_argument("--ensemble", action="store_true", help="also the networks' mean")
    ap.add_argument(
        "--family-thresholds",
        type=float,
        nargs="*",
        default=[],
        help="also break argmax-open down by support family at these thresholds",
    )
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    files = train_collision.derive_collision_pairs(
        args.data, {"train": args.pairs}, 1, False, shuffle_seed=0,
        only=lambda i: i % eval_paths.VAL_EVERY != 0,
    )["train"]  # fmt: skip
    labels = train_approach.label_pairs(args.data, files, approach.ApproachConfig(), 1, False)
    data = train_approach.ApproachData.from_files(files, labels)
    is_val = train_approach.object_split(data.object_names, args.val_mod)
    val_idx = np.flatnonzero(is_val)
    val = data.subset(val_idx)
    val_files = [files[i] for i in val_idx]
    val_wall = walls(val_files)
    records = eval_paths.read_answers(args.pairs_from)
    test_files = train_collision.derive_collision_pairs(
        args.data, {"test": args.test_pairs}, 1, False, shuffle_seed=0, only=records.__contains__,
    )["test"]  # fmt: skip
    test = train_approach.ApproachData.from_files(
        test_files,
        train_approach.label_pairs(args.data, test_files, approach.ApproachConfig(), 1, False),
    )
    test_wall = walls(test_files)
    out = dict(val_pairs=len(val_idx), test_pairs=len(test_files), views=args.views, weights={})
    sets = dict(validation_first_goal=(val, val_wall), held_out_first_goal=(test, test_wall))
    probs = {}  # (weights, set) -> [views, R, 26]
    for w in args.weights:
        config, params, _ = approach.load(w)
        for name, (d, _) in sets.items():
            probs[w, name] = np.stack([train_approach.score_rows(config, params, d, d.first_row, seed=s)
                                       for s in range(args.views)])  # fmt: skip
    entries = {w: {n: probs[w, n][:1] for n in sets} for w in args.weights}
    if args.views > 1:
        entries.update({f"{w}@{args.views}": {n: probs[w, n] for n in sets} for w in args.weights})
    if args.ensemble:
        entries[f"ensemble@{args.views}"] = {
            n: np.concatenate([probs[w, n] for w in args.weights]) for n in sets
        }
    for key, by_set in entries.items():
        res = {}
        for name, (d, wall) in sets.items():
            rows = d.first_row
            res[name] = table(by_set[name].mean(0), d.labels[rows], wall[d.pair[rows]])
            res[name + "_any_free"] = round(float(d.labels[rows].any(1).mean()), 4)
            fams = [
                family_of(f) for f in (val_files if name.startswith("validation") else test_files)
            ]
            fams = [fams[i] for i in d.pair[rows]]
            for t in args.family_thresholds:
                res.setdefault(name + "_by_family", {})[f"{t:g}"] = by_family(
                    by_set[name].mean(0), d.labels[rows], wall[d.pair[rows]], fams, t
                )
        out["weights"][key] = res
        print(key, flush=True)
        for v, h in zip(res["validation_first_goal"], res["held_out_first_goal"]):
            print(f"  {v['rule']:6s} t={v['threshold']:.2f} open={int(v['open_side'])}  val used "
                  f"{v['used']:.3f} free {v['used_free']}  | held-out used {h['used']:.3f} free "
                  f"{h['used_free']} blocked {h['used_blocked']}")  # fmt: skip
        for name in sets:
            for t, fams in res.get(name + "_by_family", {}).items():
                print(f"  {name} argmax open t={t}")
                for fam, r in fams.items():
                    print(f"    {fam:16s} {r}")
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return out


if __name__ == "__main__":
    main()
