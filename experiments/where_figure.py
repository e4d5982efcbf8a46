"""Figure of predicted hangs: what the "where to hang" model did on a few held-out pairs.

    python -m experiments.where_figure --pairs results/hanging_success.pairs.jsonl \
        --data datasets/paper --out docs/img/hanging_success.png [--n 8]

Input: the per-pair JSONL of ``experiments.eval_where`` (``omnihang_jax.evaluate``: per pair the
chosen candidate's Stage-1 and Stage-1+2 poses, their simulated status and pose errors) and the
dataset it was evaluated on (rebuilds the asset library from the dataset's recipe for the
meshes; the ground-truth stable poses come from the derived pair file, or from the shard
record when the pair was never derived). Nothing of the model is re-run.

One row per pair, three panels: (a) the ground-truth stable pose nearest to the Stage-1 pose
(the pose its translation error is measured to; simulated here with the evaluation protocol),
(b) the Stage-1 pose and (c) the Stage-1+2 pose, as predicted (before simulation), each
ray-cast like ``experiments/assets.py``'s hangs (:func:`sim.render.render_scene`: object
orange, support blue). Titles give the pair, the simulated outcome (STABLE / FALLEN /
PENETRATING / DIVERGED) and the translation / rotation error. The partial point clouds the
network saw are overlaid faintly (object cloud moved to the panel's pose). Pairs are picked
deterministically (:func:`select_pairs`): round robin over object categories, alternating
successes and failures, spreading support families.
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import matplotlib

from experiments import _cli

matplotlib.use("Agg")  # headless

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

__all__ = ["read_pairs_jsonl", "select_pairs", "draw_where_figure", "main"]

PANEL_PX = (300, 240)  # (width, height) of each rendered panel
DPI = 100
TITLE_IN = 0.38  # inches of title above each panel
ROW_HEAD_IN = 0.25  # inches of the row heading (the pair)
STAGES = (("stage1", "(b) Stage 1"), ("stage1_2", "(c) Stage 1+2"))
OK_COLOUR, BAD_COLOUR = "#1a7f37", "#c62828"


def read_pairs_jsonl(path: str | os.PathLike) -> list[dict]:
    """The rows of a per-pair JSONL written by ``omnihang_jax.evaluate.evaluate_where``
    (``.jsonl`` or gzipped ``.jsonl.gz``, as the archived results are)."""
    opener = gzip.open if os.fspath(path).endswith(".gz") else open
    with opener(path, "rt") as f:
        return [json.loads(line) for line in f if line.strip()]


def _success(row: dict) -> bool:
    return bool(row["stage1"]["success"] or row["stage1_2"]["success"])


def select_pairs(rows: Sequence[dict], n: int) -> list[dict]:
    """``n`` rows, deterministic: round robin over the object categories (sorted); the wanted
    outcome (success of Stage 1 or 1+2 / failure of both) alternates over categories and
    rounds, falling back to the other outcome where a category has none left; within a
    category the least-shown support family first, then the lowest pair index. Returned
    sorted by (category, pair index)."""
    by_cat: dict[str, list[dict]] = collections.defaultdict(list)
    for r in sorted(rows, key=lambda r: int(r["pair_index"])):
        by_cat[r["category"]].append(r)
    cats = sorted(by_cat)
    chosen: list[dict] = []
    taken: set[int] = set()
    families: collections.Counter = collections.Counter()
    rnd = 0
    while len(chosen) < min(n, len(rows)):
        for ci, cat in enumerate(cats):
            if len(chosen) >= n:
                break
            pool = [r for r in by_cat[cat] if int(r["pair_index"]) not in taken]
            if not pool:
                continue
            want = (rnd + ci) % 2 == 0
            match = [r for r in pool if _success(r) == want] or pool
            pick = min(match, key=lambda r: (families[r["family"]], int(r["pair_index"])))
            chosen.append(pick)
            taken.add(int(pick["pair_index"]))
            families[pick["family"]] += 1
        rnd += 1
    return sorted(chosen, key=lambda r: (r["category"], int(r["pair_index"])))


def _pair_data(row: dict, derived_dir: Path, records: dict, recipe: dict, config, library, clouds):
    """(ground-truth stable poses [D, 7], object cloud [N, 3] (object frame) or None, support
    cloud [M, 3] (support frame) or None) of one pair: from its derived file when there is
    one, else from the shard record (clouds derived in memory by ``sim.dataset.derive_pair``
    when ``clouds``; nothing is written)."""
    from omnihang_jax import dataset_bridge
    from sim import dataset

    index = int(row["pair_index"])
    if index >= len(recipe["pairs"]) or list(recipe["pairs"][index][:2]) != [
        row["object"],
        row["support"],
    ]:
        raise ValueError(
            f"pair {index} ({row['object']} x {row['support']}) is not in this dataset's recipe: "
            "the pairs file comes from another dataset"
        )
    found = sorted(derived_dir.glob(f"*/{row['file']}")) if row.get("file") else []
    if found:
        sample, _ = dataset_bridge.load_pair_file(found[0])
        poses = np.asarray(sample.stable_poses, float)[np.asarray(sample.pose_mask, bool)]
        return poses, np.asarray(sample.object_points), np.asarray(sample.support_points)
    if index not in records:
        raise ValueError(f"pair {index} has no shard record in the dataset")
    record = records[index]
    poses = np.asarray(record["stable_poses"], float).reshape(-1, 7)
    if not clouds:
        return poses, None, None
    derived = dataset.derive_pair(
        library.objects[row["object"]], library.supports[row["support"]], record, config
    )
    return poses, derived["object_points"], derived["support_points"]


def _rotation(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _finite_pose(pose) -> np.ndarray | None:
    pose = np.asarray(pose, float)
    if pose.shape != (7,) or not np.isfinite(pose).all() or np.linalg.norm(pose[3:]) < 1e-6:
        return None
    return np.concatenate([pose[:3], pose[3:] / np.linalg.norm(pose[3:])])


def _camera(bounds: np.ndarray):
    """(eye, target) of :func:`sim.render.render_scene`'s framing of world ``bounds`` [2, 3]."""
    from sim import render

    center = 0.5 * (bounds[0] + bounds[1])
    radius = 0.5 * float(np.linalg.norm(bounds[1] - bounds[0]))
    return render._eye_for(center, radius, render.SCENE_VIEW, render.RenderConfig()), center


def _render(scene, pose, bounds: np.ndarray, width: int, height: int) -> np.ndarray:
    """:func:`sim.render.render_scene` of ``scene`` at ``pose`` (None: object parked), framed
    on ``bounds`` instead of the pose's own box, so the three panels of a row share one camera
    (same colours, lights and anti-aliasing)."""
    import mujoco

    from sim import render
    from sim.scene import ENV_GROUP, OBJECT_GROUP, PARK_HEIGHT, SUPPORT_GROUP

    model = scene.model
    data = mujoco.MjData(model)
    data.qpos[:7] = [0, 0, PARK_HEIGHT, 1, 0, 0, 0] if pose is None else pose
    mujoco.mj_kinematics(model, data)
    eye, center = _camera(bounds)
    palette = np.ones((max(4, ENV_GROUP + 1), 3))
    palette[OBJECT_GROUP] = render.OBJECT_RGB
    palette[SUPPORT_GROUP] = render.SUPPORT_RGB
    palette[ENV_GROUP] = render.ENV_RGB

    def colour(geomid, shade):  # as render_scene: wall and floor faint
        group = np.where(geomid >= 0, model.geom_group[np.maximum(geomid, 0)], -1)
        shade = np.where(group == ENV_GROUP, 0.85 + 0.15 * np.clip(shade, 0, 1), shade)
        rgb = shade[:, None] * palette[np.maximum(group, 0)]
        return np.where((group >= 0)[:, None], rgb, 1.0)

    groups = (OBJECT_GROUP, SUPPORT_GROUP, ENV_GROUP)
    return render._raytrace(
        model, data, eye, center, width, height, groups, colour, render.RenderConfig()
    )


def _project(bounds: np.ndarray, points: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixel coordinates [P, 2] (column, row; NaN behind the camera) of world ``points`` in
    the pictures of :func:`_render` framed on ``bounds`` (same pinhole)."""
    from sim import camera, render

    eye, center = _camera(bounds)
    local = (points - eye) @ camera.look_at(eye, center)  # columns: right, down, forward
    f = 0.5 * height / np.tan(np.deg2rad(render.RenderConfig().fovy_deg) / 2)
    z = np.where(local[:, 2] > 1e-6, local[:, 2], np.nan)
    return np.stack([f * local[:, 0] / z + width / 2, f * local[:, 1] / z + height / 2], 1)


def draw_where_figure(
    pairs_jsonl_rows: Sequence[dict] | str | os.PathLike,
    dataset_dir: str | os.PathLike,
    out_png: str | os.PathLike,
    n: int = 8,
    clouds: bool = False,
    simulate_ground_truth: bool = True,
    title: str | None = None,
    progress: bool = False,
) -> list[dict]:
    """Draw the predicted-hangs figure (module docstring) of ``n`` pairs into ``out_png``.

    pairs_jsonl_rows: the rows of an evaluation's per-pair JSONL (or its path).
    dataset_dir: the dataset they were evaluated on (recipe.json + shards/, or its derived/
    folder). Returns one summary dict per drawn row (pair, statuses, errors).
    """
    from tqdm.auto import tqdm

    from omnihang_jax import dataset_bridge, evaluate
    from sim import dataset, kernels, render
    from sim.library import build_library
    from sim.scene import build_scene

    if isinstance(pairs_jsonl_rows, (str, os.PathLike)):
        pairs_jsonl_rows = read_pairs_jsonl(pairs_jsonl_rows)
    rows = select_pairs(list(pairs_jsonl_rows), n)
    if not rows:
        raise ValueError("no pairs to draw")
    data_dir, derived_dir = dataset_bridge.resolve_dataset_dir(dataset_dir)
    recipe = dataset_bridge.read_recipe(data_dir)
    config = dataset_bridge.dataset_config_from_recipe(recipe)
    library = build_library(config.library, progress=False)
    records = {int(r["pair_index"]): r for r in dataset.load_records(data_dir)}
    stability = evaluate.protocol_stability()

    w_px, h_px = PANEL_PX
    panel_w, panel_h = w_px / DPI, h_px / DPI
    header = 0.62
    row_h = panel_h + TITLE_IN + ROW_HEAD_IN
    fig = plt.figure(figsize=(3 * panel_w, len(rows) * row_h + header), dpi=DPI)
    fig_h = fig.get_figheight()
    summary = []
    for i, row in enumerate(tqdm(rows, desc="where figure", disable=not progress)):
        gt_poses, obj_cloud, sup_cloud = _pair_data(
            row, derived_dir, records, recipe, config, library, clouds
        )
        if not len(gt_poses):
            raise ValueError(f"pair {row['pair_index']} has no ground-truth stable pose")
        scene = build_scene(library.objects[row["object"]], library.supports[row["support"]])
        s1 = _finite_pose(row["stage1"]["pose"])
        ref = s1 if s1 is not None else gt_poses[0]
        gt = gt_poses[int(np.argmin(np.linalg.norm(gt_poses[:, :3] - ref[:3], axis=1)))]
        gt = _finite_pose(gt)
        gt_status = None
        if simulate_ground_truth:
            res = kernels.stability(scene, gt[None], stability)
            gt_status = kernels.STATUS_NAMES[int(res.status[0])]
        panels = [("(a) ground truth", gt, gt_status, None, None)]
        for stage, label in STAGES:
            rec = row[stage]
            panels.append(
                (
                    label,
                    _finite_pose(rec["pose"]),
                    rec["status"],
                    rec.get("translation_error_m"),
                    rec.get("rotation_error_deg"),
                )
            )
        # one camera per row: framed on the support and the object at all three poses
        boxes = [render.scene_view_bounds(scene, p) for _, p, *_ in panels if p is not None]
        bounds = np.stack([np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0)])
        top = fig_h - header - i * (panel_h + TITLE_IN + ROW_HEAD_IN)
        fig.text(
            0.5,
            (top - 0.04) / fig_h,
            f"{row['object']} on {row['support']}   (pair {int(row['pair_index'])}: "
            f"{row['category']} / {row['family']})",
            ha="center",
            va="top",
            fontsize=9,
            weight="bold",
        )
        entry = {
            "pair_index": int(row["pair_index"]),
            "pair": f"{row['object']} on {row['support']}",
            "category": row["category"],
        }
        for j, (label, pose, status, dt, dr) in enumerate(panels):
            bottom = top - (panel_h + TITLE_IN + ROW_HEAD_IN)
            ax = fig.add_axes(
                [j / 3, bottom / fig_h, 1 / 3, panel_h / fig_h],
                frame_on=False,
                xticks=[],
                yticks=[],
            )
            ax.imshow(_render(scene, pose, bounds, w_px, h_px))
            if clouds and pose is not None:
                obj_world = obj_cloud @ _rotation(pose[3:]).T + pose[:3]
                for pts, colour in ((sup_cloud, "#0b2a66"), (obj_world, "#7a2e00")):
                    uv = _project(bounds, np.asarray(pts, float), w_px, h_px)
                    ax.scatter(*uv.T, s=0.4, c=colour, alpha=0.35, linewidths=0)
            ax.set_xlim(0, w_px)
            ax.set_ylim(h_px, 0)
            line = label
            if status is not None:
                line += f": {status.upper()}"
            if pose is None:
                line += " (non-finite pose)"
            if dt is not None and np.isfinite(dt):
                line += f"\n$\\Delta t$ = {100 * dt:.1f} cm, $\\Delta r$ = {dr:.0f}°"
            elif j == 0:
                line += "\n(the one nearest to the Stage-1 pose)"
            colour = (
                "black" if status is None else (OK_COLOUR if status == "stable" else BAD_COLOUR)
            )
            ax.text(0.5, 1.01, line, transform=ax.transAxes, ha="center", va="bottom",
                    fontsize=8.5, color=colour)  # fmt: skip
            key = ("ground_truth", "stage1", "stage1_2")[j]
            entry[key] = {"status": status, "translation_error_m": dt}
        summary.append(entry)
    n_ok = {
        k: sum(e[k]["status"] == "stable" for e in summary)
        for k in ("ground_truth", "stage1", "stage1_2")
    }
    head = title or "Predicted hangs on held-out pairs"
    fig.text(
        0.5,
        1 - 0.1 / fig_h,
        f"{head}\nSTABLE after 1 s of simulation: ground truth {n_ok['ground_truth']}/{len(rows)}, "
        f"Stage 1 {n_ok['stage1']}/{len(rows)}, Stage 1+2 {n_ok['stage1_2']}/{len(rows)}. "
        "Object (orange) at the pose, before simulation;\n$\\Delta t$: distance to the nearest "
        "ground-truth stable position, $\\Delta r$: rotation to that pose"
        + ("; dots: the partial clouds the network saw" if clouds else ""),
        ha="center",
        va="top",
        fontsize=8.5,
    )
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=DPI)
    plt.close(fig)
    return summary


def main(argv: Iterable[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--pairs", required=True, help="per-pair JSONL of eval_where")
    parser.add_argument("--data", required=True, help="the dataset it was evaluated on")
    parser.add_argument("--out", required=True, help="PNG to write")
    parser.add_argument("--n", type=int, default=8, help="pairs (rows) shown (default 8)")
    parser.add_argument(
        "--clouds", action="store_true", help="overlay the partial clouds (faint dots)"
    )
    parser.add_argument(
        "--no-gt-sim", action="store_true", help="do not simulate the ground-truth poses"
    )
    parser.add_argument("--title", default=None, help="figure heading")
    args = parser.parse_args(None if argv is None else list(argv))
    summary = draw_where_figure(
        args.pairs,
        args.data,
        args.out,
        args.n,
        clouds=args.clouds,
        simulate_ground_truth=not args.no_gt_sim,
        title=args.title,
        progress=True,
    )
    print(json.dumps({"out": args.out, "rows": summary}, indent=1))
    return summary


if __name__ == "__main__":
    _cli.run(main)
