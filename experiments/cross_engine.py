"""Do MuJoCo and PyBullet agree on what hangs? A seeded sample of a dataset's stable poses
and near misses re-judged by both engines under named set-ups (sim.judges).

    python -m experiments.cross_engine --data datasets/paper --stable 1100 --near-miss 1100 \
        --bullet original,matched --mujoco scene --workers 2 \
        --out results/cross_engine.json --items out/cross_engine/items.jsonl \
        --export out/cross_engine/cases --figure docs/img/cross_engine.png

    # one setting at a time, on a smaller sample of the four categories that disagree most
    python -m experiments.cross_engine --data datasets/paper --stable 240 --near-miss 240 \
        --categories cap,racquet,scissors,clothes_hanger --bullet all --mujoco all \
        --out results/cross_engine_ablation.json

The sample is balanced over (object category, support family) cells (sim.judges.
sample_dataset). Stable poses are simulated with the dataset's stability protocol (2 s);
near misses with its near-miss rollout (0.5 s: a miss falls, diverges or moves > 0.3 m).
For every PyBullet set-up the results compare it with MuJoCo's scene ("mujoco:scene"), and
every MuJoCo variant with PyBullet's matched set-up: agreement overall, per category and
per family, in both directions (sim.judges.agreement). --export writes up to
--export-per-category disagreeing cases per category of the first-vs-last PyBullet set-up
comparison as OBJ + pose (sim.dataset_io.export_sample); --figure pictures the agreement and
a few of those cases. --items keeps one JSON line per judged pose (verdict and status
under every set-up).
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from omnihang_jax import dataset_bridge
from sim import dataset, dataset_io, judges, kernels

_STATE: dict = {}


def _init(data: str) -> None:
    from sim.library import build_library

    recipe = dataset_bridge.read_recipe(data)
    config = dataset_bridge.dataset_config_from_recipe(recipe)
    _STATE.update(
        recipe=recipe,
        config=config,
        library=build_library(config.library, progress=False),
    )


def _job(args) -> tuple[list[int], dict]:
    from sim.scene import build_scene

    indices, pair_index, kind, poses, bullet_names, mujoco_names = args
    recipe, config, library = _STATE["recipe"], _STATE["config"], _STATE["library"]
    obj, sup, _ = recipe["pairs"][pair_index]
    scene = build_scene(library.objects[obj], library.supports[sup])
    out = judges.judge_pair(
        scene,
        kind,
        np.asarray(poses, float),
        config.stability,
        config,
        {n: judges.bullet_variant(n) for n in bullet_names},
        {n: judges.MUJOCO_VARIANTS[n] for n in mujoco_names},
    )
    return indices, out


def run(
    data: str,
    n_stable: int,
    n_near_miss: int,
    bullet_names: list[str],
    mujoco_names: list[str],
    seed: int = 0,
    workers: int = 1,
    categories: list[str] | None = None,
    progress: bool = True,
) -> tuple[list, dict, dict]:
    """Sample, judge, and return (items, verdicts {judge: [N] bool}, statuses {judge: [N]})."""
    _init(data)
    recipe, config, library = _STATE["recipe"], _STATE["config"], _STATE["library"]
    records = dataset.load_records(dataset_bridge.resolve_dataset_dir(data)[0])
    if categories:
        known = {a.category for a in library.objects.values()}
        bad = sorted(set(categories) - known)
        if bad:
            raise SystemExit(f"unknown categories {bad}; known: {sorted(known)}")
        records = [
            r
            for r in records
            if library.objects[recipe["pairs"][int(r["pair_index"])][0]].category in categories
        ]
    items = judges.sample_dataset(records, recipe, library, config, n_stable, n_near_miss, seed)
    groups: dict[tuple[int, str], list[int]] = {}
    for i, it in enumerate(items):
        groups.setdefault((it.pair_index, it.kind), []).append(i)
    jobs = [
        (idx, p, kind, [items[i].pose for i in idx], bullet_names, mujoco_names)
        for (p, kind), idx in sorted(groups.items())
    ]
    n = len(items)
    names = [f"mujoco:{m}" for m in mujoco_names] + [f"pybullet:{b}" for b in bullet_names]
    verdicts = {k: np.zeros(n, bool) for k in names}
    statuses = {k: np.zeros(n, np.int8) for k in names}
    bar = tqdm(total=n, desc="cross-engine", unit="pose", disable=not progress)

    def collect(indices, out):
        for k, v in out.items():
            verdicts[k][indices] = v["hangs"]
            statuses[k][indices] = v["status"]
        bar.update(len(indices))

    if workers <= 1:
        for job in jobs:
            collect(*_job(job))
    else:
        from sim import workers as workers_mod

        with (
            workers_mod.worker_environment(),
            cf.ProcessPoolExecutor(workers, initializer=_init, initargs=(data,)) as pool,
        ):
            for fut in cf.as_completed([pool.submit(_job, job) for job in jobs]):
                collect(*fut.result())
    bar.close()
    statuses["behind_wall_m"] = np.array(
        [
            judges.behind_wall_depth(
                library.objects[recipe["pairs"][it.pair_index][0]],
                np.asarray(it.pose)[None],
                library.supports[recipe["pairs"][it.pair_index][1]].wall_y,
            )[0]
            for it in items
        ]
    )
    return items, verdicts, statuses


def summarize(items, verdicts, statuses, bullet_names, mujoco_names) -> dict:
    """The comparisons: each PyBullet set-up vs MuJoCo's scene, each MuJoCo variant vs
    PyBullet matched (when both were run), and the dataset's own labels vs MuJoCo now."""
    ref_mj = f"mujoco:{mujoco_names[0]}"
    ref_pb = f"pybullet:{bullet_names[-1]}"
    label = {"dataset": np.array([it.kind == "stable" for it in items])}
    comps = {
        "dataset_vs_" + ref_mj: judges.agreement(items, {**label, **verdicts}, "dataset", ref_mj)
    }
    for b in bullet_names:
        comps[f"{ref_mj}_vs_pybullet:{b}"] = judges.agreement(
            items, verdicts, ref_mj, f"pybullet:{b}"
        )
    for m in mujoco_names[1:]:
        comps[f"mujoco:{m}_vs_{ref_pb}"] = judges.agreement(items, verdicts, f"mujoco:{m}", ref_pb)
        comps[f"{ref_mj}_vs_mujoco:{m}"] = judges.agreement(items, verdicts, ref_mj, f"mujoco:{m}")
    behind = statuses["behind_wall_m"] > 0.001
    kinds = np.array([it.kind for it in items])
    through_wall = {
        kind: {
            "poses_reaching_behind_the_wall_plane_over_1mm": int((behind & (kinds == kind)).sum()),
            "of": int((kinds == kind).sum()),
        }
        for kind in ("stable", "near_miss")
    }
    status_counts = {
        k: {
            kind: {
                kernels.STATUS_NAMES[s]: int(
                    ((v == s) & np.array([it.kind == kind for it in items])).sum()
                )
                for s in range(4)
            }
            for kind in ("stable", "near_miss")
        }
        for k, v in statuses.items()
        if k != "behind_wall_m"
    }
    return {"comparisons": comps, "status_counts": status_counts, "through_wall": through_wall}


def export_disagreements(items, verdicts, a, b, out_dir, per_category: int) -> list[dict]:
    """Write up to ``per_category`` items per (category, kind) whose verdicts under ``a`` and
    ``b`` differ as OBJ + pose folders; returns their descriptions."""
    recipe, library = _STATE["recipe"], _STATE["library"]
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows, count = [], {}
    for i, it in enumerate(items):
        if verdicts[a][i] == verdicts[b][i]:
            continue
        key = (it.category, it.kind)
        if count.get(key, 0) >= per_category:
            continue
        count[key] = count.get(key, 0) + 1
        name = f"{i:05d}_{it.kind}_{recipe['pairs'][it.pair_index][0]}__{recipe['pairs'][it.pair_index][1]}"
        record = {"pair_index": it.pair_index, "stable_poses": np.asarray([it.pose])}
        dataset_io.export_sample(library, record, recipe["pairs"], out_dir / name, 0)
        rows.append(
            {
                "item": i,
                "folder": name,
                "kind": it.kind,
                "category": it.category,
                "family": it.family,
                "pair_index": it.pair_index,
                "pose_index": it.pose_index,
                a: bool(verdicts[a][i]),
                b: bool(verdicts[b][i]),
            }
        )
    (out_dir / "cases.json").write_text(json.dumps(rows, indent=1))
    return rows


def draw_figure(summary: dict, items, verdicts, comps: list[str], cases, png) -> None:
    """Agreement per category (stable poses and near misses) for ``comps``, and renders of up
    to eight disagreeing cases."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim.render import render_scene
    from sim.scene import build_scene

    recipe, library = _STATE["recipe"], _STATE["library"]
    shown = cases[:8]
    fig = plt.figure(figsize=(16, 7.4 if shown else 4.4))
    grid = fig.add_gridspec(2 if shown else 1, 8, height_ratios=[1.6, 1] if shown else [1])
    for col, kind in enumerate(("stable", "near_miss")):
        ax = fig.add_subplot(grid[0, 4 * col : 4 * col + 4])
        cats = sorted(summary["comparisons"][comps[0]][kind]["per_category"])
        width = 0.8 / len(comps)
        for j, c in enumerate(comps):
            table = summary["comparisons"][c][kind]["per_category"]
            ax.bar(
                np.arange(len(cats)) + j * width,
                [100 * (table[k]["agree"] or 0) for k in cats],
                width,
                label=c.replace("_vs_", " vs "),
            )
        ax.axhline(95, color="k", lw=0.8, ls="--")
        ax.set_xticks(np.arange(len(cats)) + 0.4 - width / 2)
        ax.set_xticklabels(cats, rotation=35, ha="right", fontsize=8)
        ax.set_ylim(0, 102)
        ax.set_ylabel("verdicts agreeing (%)")
        n = summary["comparisons"][comps[0]][kind]["overall"]["n"]
        ax.set_title(f"{kind.replace('_', ' ')} poses ({n}), per object category")
        ax.legend(fontsize=7, loc="lower left")
    for j, case in enumerate(shown):
        it = items[case["item"]]
        obj, sup, _ = recipe["pairs"][it.pair_index]
        scene = build_scene(library.objects[obj], library.supports[sup])
        img = render_scene(scene, np.asarray(it.pose), 240, 180)
        ax = fig.add_subplot(grid[1, j])
        ax.imshow(img)
        ax.set_axis_off()
        verdict = ", ".join(
            f"{k.split(':')[0]} {'hangs' if v else 'falls'}" for k, v in list(case.items())[-2:]
        )
        ax.set_title(f"{it.kind} {obj}\n{sup}\n{verdict}", fontsize=6)
    fig.tight_layout()
    Path(png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", default="datasets/paper", help="dataset (recipe + shards)")
    parser.add_argument("--stable", type=int, default=1100, help="stable poses in the sample")
    parser.add_argument("--near-miss", type=int, default=1100, help="near misses in the sample")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--bullet",
        default="original,matched",
        help=f"comma-separated PyBullet set-ups, or 'all' ({', '.join(judges.BULLET_VARIANT_NAMES)})",
    )
    parser.add_argument(
        "--mujoco",
        default="scene",
        help=f"comma-separated MuJoCo variants (first = reference), or 'all' ({', '.join(judges.MUJOCO_VARIANTS)})",
    )
    parser.add_argument("--categories", default=None, help="comma-separated object categories")
    parser.add_argument("--workers", type=int, default=1, help="processes (one core each)")
    parser.add_argument("--out", default="results/cross_engine.json")
    parser.add_argument("--items", default=None, help="per-pose JSONL")
    parser.add_argument("--export", default=None, help="folder for disagreeing cases")
    parser.add_argument("--export-per-category", type=int, default=3)
    parser.add_argument("--figure", default=None, help="PNG")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument(
        "--redraw",
        metavar="ITEMS_JSONL",
        default=None,
        help="only redraw --figure from an earlier run's --items and --out files",
    )
    parser.add_argument(
        "--wall-census",
        action="store_true",
        help="only count the dataset's stable poses that reach behind the wall plane "
        "(sim.judges.wall_census), written to --out",
    )
    args = parser.parse_args(argv)
    cli = list(argv) if argv is not None else sys.argv[1:]
    if args.wall_census:
        _init(args.data)
        records = dataset.load_records(dataset_bridge.resolve_dataset_dir(args.data)[0])
        census = judges.wall_census(records, _STATE["recipe"], _STATE["library"])
        census["command"] = "python -m experiments.cross_engine " + " ".join(cli)
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(census, indent=1) + "\n")
        print(json.dumps({k: v for k, v in census.items() if not k.startswith("per_")}))
        return census
    if args.redraw:
        if not args.figure:
            parser.error("--redraw needs --figure")
        _init(args.data)
        rows = [json.loads(line) for line in Path(args.redraw).read_text().splitlines()]
        items = [
            judges.SampleItem(
                r["pair_index"], r["kind"], r["pose_index"], tuple(r["pose"]), r["category"],
                r["family"],
            )
            for r in rows
        ]  # fmt: skip
        verdicts = {k: np.array([r["hangs"][k] for r in rows]) for k in rows[0]["hangs"]}
        result = json.loads(Path(args.out).read_text())
        comps = [c for c in result["comparisons"] if not c.startswith("dataset_vs")]
        comps = [
            c
            for c in comps
            if not c.startswith(f"mujoco:{list(result['mujoco_variants'])[0]}_vs_mujoco")
        ]
        a, b = result["before_after"]["after"]["comparison"].split("_vs_")
        shown = [
            {"item": int(i), a: bool(verdicts[a][i]), b: bool(verdicts[b][i])}
            for i in np.flatnonzero(verdicts[a] != verdicts[b])[:8]
        ]
        draw_figure(result, items, verdicts, comps, shown, args.figure)
        print(f"wrote {args.figure}")
        return result
    bullet = list(judges.BULLET_VARIANT_NAMES) if args.bullet == "all" else args.bullet.split(",")
    mujoco = list(judges.MUJOCO_VARIANTS) if args.mujoco == "all" else args.mujoco.split(",")
    for b in bullet:
        judges.bullet_variant(b)  # unknown names fail here, not in a worker
    bad = [m for m in mujoco if m not in judges.MUJOCO_VARIANTS]
    if bad:
        parser.error(f"unknown MuJoCo variants {bad}; known: {list(judges.MUJOCO_VARIANTS)}")
    if args.stable < 0 or args.near_miss < 0 or args.stable + args.near_miss == 0:
        parser.error("--stable and --near-miss must be >= 0, not both 0")
    t0 = time.time()
    items, verdicts, statuses = run(
        args.data,
        args.stable,
        args.near_miss,
        bullet,
        mujoco,
        args.seed,
        args.workers,
        args.categories.split(",") if args.categories else None,
        not args.no_progress,
    )
    seconds = time.time() - t0
    summary = summarize(items, verdicts, statuses, bullet, mujoco)
    import pybullet

    result = {
        "what": "MuJoCo vs PyBullet verdicts on a seeded sample of the dataset's stable poses "
        "(2 s stability protocol) and near misses (0.5 s rollout: a miss falls, diverges or "
        "moves > 0.3 m); 'hangs' = stable / not a miss (sim.judges, docs/judges.md)",
        "command": "python -m experiments.cross_engine " + " ".join(cli),
        "data": args.data,
        "seed": args.seed,
        "sample": {
            "stable": int(sum(it.kind == "stable" for it in items)),
            "near_miss": int(sum(it.kind == "near_miss" for it in items)),
            "pairs": len({it.pair_index for it in items}),
            "categories": sorted({it.category for it in items}),
            "families": sorted({it.family for it in items}),
        },
        "bullet_setups": {b: dataclasses.asdict(judges.bullet_variant(b)) for b in bullet},
        "mujoco_variants": {m: judges.MUJOCO_VARIANTS[m] for m in mujoco},
        **summary,
        "seconds": round(seconds, 1),
        "poses_per_second_all_setups": round(len(items) / seconds, 2),
        "workers": args.workers,
        "machine": f"{platform.machine()} {os.cpu_count()} cpus",
        "versions": {"pybullet": pybullet.getAPIVersion(), "python": platform.python_version()},
    }
    if args.items:
        path = Path(args.items)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "w") as f:
            for i, it in enumerate(items):
                row = dataclasses.asdict(it)
                row["hangs"] = {k: bool(v[i]) for k, v in verdicts.items()}
                row["status"] = {
                    k: kernels.STATUS_NAMES[v[i]]
                    for k, v in statuses.items()
                    if k != "behind_wall_m"
                }
                row["behind_wall_m"] = round(float(statuses["behind_wall_m"][i]), 5)
                f.write(json.dumps(row) + "\n")
    first, last = f"pybullet:{bullet[0]}", f"pybullet:{bullet[-1]}"
    ref, fixed = f"mujoco:{mujoco[0]}", f"mujoco:{mujoco[-1]}"
    # before: MuJoCo's scene vs the first PyBullet set-up; after: the last of each
    stages = {"before": (ref, first), "after": (fixed, last)}
    result["before_after"] = {
        stage: {
            "comparison": f"{a}_vs_{b}",
            **{
                kind: {
                    "overall": summary["comparisons"][f"{a}_vs_{b}"][kind]["overall"]["agree"],
                    "per_category": {
                        c: t["agree"]
                        for c, t in summary["comparisons"][f"{a}_vs_{b}"][kind][
                            "per_category"
                        ].items()
                    },
                    "per_family": {
                        f: t["agree"]
                        for f, t in summary["comparisons"][f"{a}_vs_{b}"][kind][
                            "per_family"
                        ].items()
                    },
                }
                for kind in ("stable", "near_miss")
            },
        }
        for stage, (a, b) in stages.items()
    }
    cases = {}
    if args.export:
        for stage, (a, b) in stages.items():
            cases[stage] = export_disagreements(
                items, verdicts, a, b, Path(args.export) / stage, args.export_per_category
            )
        result["exported"] = {
            stage: {
                "folder": str(Path(args.export) / stage),
                "against": list(stages[stage]),
                "cases": len(rows),
            }
            for stage, rows in cases.items()
        }
    if args.figure:
        comps = [f"{ref}_vs_pybullet:{b}" for b in bullet] + [
            f"mujoco:{m}_vs_{last}" for m in mujoco[1:]
        ]
        a, b = stages["after"]
        shown = cases.get("after") or [
            {"item": int(i), a: bool(verdicts[a][i]), b: bool(verdicts[b][i])}
            for i in np.flatnonzero(verdicts[a] != verdicts[b])[:8]
        ]
        draw_figure(summary, items, verdicts, comps, shown, args.figure)
        result["figure"] = args.figure
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    brief = {
        c: {k: v[k]["overall"]["agree"] for k in ("stable", "near_miss")}
        for c, v in summary["comparisons"].items()
    }
    print(json.dumps({"seconds": result["seconds"], "agreement": brief}, indent=1))
    return result


if __name__ == "__main__":
    main()
