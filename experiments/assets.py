"""Asset and physics showcase: the library's numbers, a contact sheet and a few known hangs.

Usage::

    python -m experiments.assets --out out/assets            # the paper's 340 + 72 assets
    python -m experiments.assets --out /tmp/assets --quick   # 22 + 10 assets, small pictures

Writes into ``--out``:

- ``assets.json``: assets per category / family, train/test split sizes, decomposition
  figures (parts per asset, part kinds, hull sizes, CoACD use, build time), versions and
  the wall-clock time of every step;
- ``manifest.json``: the library manifest (one record per asset, :mod:`sim.library`);
- ``contact_sheet.png``: a few renders of every object category and support family;
- ``hangs.png`` / ``hangs.json``: for a handful of (object, support) pairs from different
  categories and families, a stable pose found by simulation (hang proposals ->
  stability -> take-off), rendered, beside the partial clouds at that pose coloured by
  their soft contact maps;
- ``example_scene/scene.xml``: the first shown hang as a MuJoCo scene
  (``python -m mujoco.viewer --mjcf=<out>/example_scene/scene.xml``).

Everything renders on the CPU by ray casting (:mod:`sim.render`); no OpenGL or display.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import hashlib
import json
import os
import pickle
import platform
import time
from collections.abc import Sequence
from pathlib import Path

import matplotlib

from experiments import _cli

matplotlib.use("Agg")  # headless: never look for a display

import matplotlib.pyplot as plt  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

from sim import annotate, camera, kernels, proposals, render  # noqa: E402
from sim.assets.base import Asset, HangLoop, Peg  # noqa: E402
from sim.geometry import ConvexMesh  # noqa: E402
from sim.library import Library, LibraryConfig, build_library  # noqa: E402
from sim.scene import build_scene, write_scene  # noqa: E402


@dataclasses.dataclass(frozen=True)
class AssetsJobConfig:
    n_objects: int = 340  # the paper's dataset size
    n_supports: int = 72  # the paper's number of supporting items
    seed: int = 0  # library seed (assets and split) and the job's own sampling
    hangs: int = 6  # (object, support) pairs shown in hangs.png
    per_row: int = 6  # renders per category / family in the contact sheet
    render_size: int = 160  # pixels per contact-sheet cell
    scene_size: tuple[int, int] = (360, 300)  # (width, height) of each hang render
    candidates: int = 64  # hang proposals simulated per pair (most penetrate or fall)
    max_attempts: int = 6  # (object, support) pairs tried per shown hang before giving up
    view_tries: int = 4  # camera pairs tried; keep the one seeing the most contact mass
    cloud_width: int = 320  # depth camera for the partial clouds (original 640 x 480)
    cloud_height: int = 240
    cloud_points: int = 2048  # points per partial cloud in the figure (original 4096)
    cache_dir: str | None = None  # built library + union meshes (None: <out>/cache)
    progress: bool = True


QUICK = AssetsJobConfig(
    n_objects=22,
    n_supports=10,
    hangs=2,
    per_row=3,
    render_size=96,
    scene_size=(200, 160),
    candidates=32,
    max_attempts=4,
    view_tries=2,
    cloud_width=160,
    cloud_height=120,
    cloud_points=512,
)


# ----------------------------------------------------------------------------- library


LIBRARY_SOURCES = (
    "sim/geometry.py",
    "sim/assets/base.py",
    "sim/assets/objects.py",
    "sim/assets/supports.py",
    "sim/library.py",
)


def load_or_build_library(
    config: LibraryConfig, cache_dir: Path, progress: bool = True
) -> tuple[Library, bool]:
    """The library of ``config``, from ``cache_dir`` if this exact config and generator code
    built it before (key: SHA-256 of the config and of :data:`LIBRARY_SOURCES`), else built
    and stored there. Returns (library, loaded_from_cache)."""
    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256(json.dumps(dataclasses.asdict(config), sort_keys=True).encode())
    for rel in LIBRARY_SOURCES:
        h.update((root / rel).read_bytes())
    path = cache_dir / f"library-{h.hexdigest()[:20]}.pkl"
    if path.exists():
        try:
            with path.open("rb") as f:
                library = pickle.load(f)
            library.cache_dir = cache_dir
            return library, True
        except Exception as exc:  # stale or corrupt: rebuild below
            print(f"ignoring unreadable library cache {path}: {exc}")
    library = build_library(config, cache_dir=cache_dir, progress=progress)
    cache_dir.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".tmp{os.getpid()}")
    with tmp.open("wb") as f:
        pickle.dump(library, f, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(tmp, path)  # atomic: a killed run never leaves half a cache file
    for old in cache_dir.glob("library-*.pkl"):  # libraries of older code or configs
        if old != path:
            old.unlink(missing_ok=True)
    return library, False


def library_figures(library: Library, build_seconds: float) -> dict:
    """Counts, split sizes and decomposition figures of ``library`` (JSON-able)."""
    manifest = library.manifest()
    records = manifest["objects"] + manifest["supports"]

    def per_group(recs):
        groups = collections.defaultdict(list)
        for r in recs:
            groups[r["category"]].append(r)
        out = {}
        for name in sorted(groups):
            rs = groups[name]
            parts = np.array([r["n_parts"] for r in rs])
            kinds = collections.Counter()
            for r in rs:
                kinds.update(r["part_kinds"])
            out[name] = dict(
                n=len(rs),
                parts_mean=round(float(parts.mean()), 2),
                parts_max=int(parts.max()),
                part_kinds=dict(kinds),
                max_hull_vertices=max(r["max_hull_vertices"] for r in rs),
                n_features_min=min(r["n_features"] for r in rs),
            )
        return out

    kinds = collections.Counter()
    for r in records:
        kinds.update(r["part_kinds"])
    parts = np.array([r["n_parts"] for r in records])
    return dict(
        objects_per_category=library.objects_per_category(),
        supports_per_family=library.supports_per_family(),
        n_objects=len(library.objects),
        n_supports=len(library.supports),
        split={s: {g: len(v) for g, v in groups.items()} for s, groups in library.split.items()},
        decomposition=dict(
            objects=per_group(manifest["objects"]),
            supports=per_group(manifest["supports"]),
            parts_mean=round(float(parts.mean()), 2),
            parts_max=int(parts.max()),
            part_kinds=dict(kinds),
            max_hull_vertices=max(r["max_hull_vertices"] for r in records),
            # procedural assets are built from convex parts; only user meshes go through CoACD
            n_needing_coacd=sum(r["source"] != "procedural" for r in records),
            build_seconds=round(build_seconds, 3),  # or load time, see library_from_cache
        ),
        wall_supports=sum(r.get("wall", False) for r in manifest["supports"]),
    )


def sheet_groups(library: Library, per_row: int) -> dict[str, list[Asset]]:
    """Up to ``per_row`` assets of every category, then of every family, spread over the
    index range (so the sheet shows the variety, not just the first seeds)."""
    groups: dict[str, list[Asset]] = {}
    for table in (library.objects, library.supports):
        by: dict[str, list[Asset]] = collections.defaultdict(list)
        for a in table.values():
            by[a.category].append(a)
        for name in sorted(by):
            assets = by[name]
            idx = np.unique(np.linspace(0, len(assets) - 1, min(per_row, len(assets))).round())
            groups[name] = [assets[int(i)] for i in idx]
    return groups


# ----------------------------------------------------------------------------- hangs


def _candidates(obj: Asset, support: Asset, n: int, rng: np.random.Generator) -> np.ndarray:
    has_loops = any(isinstance(f, HangLoop) for f in obj.features)
    has_pegs = any(isinstance(f, Peg) for f in support.features)
    if has_loops and has_pegs:
        return proposals.hang_poses(obj, support, n, rng)
    return proposals.uniform_poses(obj, support, 4 * n, rng)  # the original's low-yield sampler


def pick_pairs(library: Library, n: int, attempts: int) -> list[list[tuple[Asset, Asset]]]:
    """For each of ``n`` shown pairs, the (object, support) attempts to simulate in order
    until one hangs. Pair ``i`` starts at category ``i`` and family ``i`` (cycling), so the
    shown pairs differ in both; attempts 2k and 2k+1 try two objects of the category on a
    support of family ``i + k``."""
    cats = collections.defaultdict(list)
    for a in library.objects.values():
        cats[a.category].append(a)
    fams = collections.defaultdict(list)
    for a in library.supports.values():
        fams[a.category].append(a)
    cat_names, fam_names = sorted(cats), sorted(fams)
    plans = []
    for i in range(n):
        objs = cats[cat_names[i % len(cat_names)]]
        round_ = i // max(len(cat_names), len(fam_names))  # later rounds: other assets
        plan = []
        for a in range(max(1, attempts)):
            sups = fams[fam_names[(i + a // 2) % len(fam_names)]]
            plan.append((objs[(round_ + a) % len(objs)], sups[round_ % len(sups)]))
        plans.append(plan)
    return plans


def simulate_hang(
    obj: Asset, support: Asset, config: AssetsJobConfig, rng: np.random.Generator
) -> dict:
    """Propose, simulate and take-off-test one pair; returns the record of its best pose
    (stable and removable if any, else stable, else the first candidate)."""
    scene = build_scene(obj, support)
    poses = _candidates(obj, support, config.candidates, rng)
    stab = kernels.stability(scene, poses)
    stable = np.flatnonzero(stab.stable)
    takeoff = None
    best = int(stable[0]) if len(stable) else 0
    if len(stable):
        tested = stable[:8]
        takeoff = kernels.takeoff(scene, stab.settled_pose[tested])
        removable = np.flatnonzero(takeoff.removable)
        k = int(removable[0]) if len(removable) else 0
        best = int(tested[k])
        takeoff = dict(
            removable=bool(takeoff.removable[k]),
            first_direction=int(takeoff.direction[k]),
            removed_per_direction=takeoff.removed[k].tolist(),
            frame=kernels.TakeoffConfig().frame,
            n_tested=len(tested),
            n_removable=len(removable),
        )
    counts = np.bincount(stab.status, minlength=len(kernels.STATUS_NAMES))
    return dict(
        scene=scene,
        object=obj.name,
        support=support.name,
        object_category=obj.category,
        support_family=support.category,
        n_candidates=len(poses),
        status_counts={name: int(c) for name, c in zip(kernels.STATUS_NAMES, counts)},
        status=kernels.STATUS_NAMES[int(stab.status[best])],
        stable=bool(stab.stable[best]),
        initial_pose=poses[best].tolist(),
        pose=stab.settled_pose[best].tolist(),
        settle_time_s=float(stab.sim_time[best]),
        takeoff=takeoff,
    )


def annotate_hang(scene, pose: np.ndarray, config: AssetsJobConfig, rng: np.random.Generator):
    """Partial clouds of both bodies and their soft contact maps at ``pose``.

    Like the original, several camera pairs are tried and the one whose clouds carry the
    most contact-map mass is kept. Returns (object cloud, support cloud, annotation,
    contact result)."""
    contacts = kernels.contact_query(scene, pose[None])
    mask = contacts.mask[0]
    cam = camera.CameraConfig(
        width=config.cloud_width, height=config.cloud_height, n_points=config.cloud_points
    )
    best = None
    for _ in range(max(1, config.view_tries)):
        obj_eye, sup_eye = camera.default_eyes(scene, rng, cam)
        try:
            obj_cloud = camera.partial_cloud(scene, "object", obj_eye, rng, cam)
            sup_cloud = camera.partial_cloud(scene, "support", sup_eye, rng, cam)
        except ValueError:  # this camera saw nothing of one body
            continue
        ann = annotate.annotate(
            contacts.object_points[0][mask],
            contacts.support_points[0][mask],
            pose,
            obj_cloud,
            sup_cloud,
        )
        mass = float(ann.object_map.sum() + ann.support_map.sum())
        if best is None or mass > best[0]:
            best = (mass, obj_cloud, sup_cloud, ann)
    if best is None:
        raise RuntimeError(f"no camera saw both bodies of {scene.obj.name} x {scene.support.name}")
    return best[1], best[2], best[3], contacts


def _blend(base, hot, weights: np.ndarray) -> np.ndarray:
    """[N, 4] RGBA: ``base`` colour where the contact map is 0, ``hot`` where it is 1."""
    w = np.clip(weights, 0.0, 1.0)[:, None]
    rgb = (1 - w) * np.asarray(base) + w * np.asarray(hot)
    return np.concatenate([rgb, np.full((len(w), 1), 1.0)], axis=1)


def _view_angles(view_dir) -> tuple[float, float]:
    v = np.asarray(view_dir, float) / np.linalg.norm(view_dir)
    return float(np.degrees(np.arcsin(v[2]))), float(np.degrees(np.arctan2(v[1], v[0])))


def draw_hangs(records: Sequence[dict], path: Path, config: AssetsJobConfig) -> None:
    """hangs.png: per pair, the rendered scene and the contact-coloured partial clouds."""
    n = len(records)
    fig = plt.figure(figsize=(10, 4.2 * max(n, 1)), dpi=90)
    elev, azim = _view_angles(render.SCENE_VIEW)
    pale_obj = 0.45 * np.asarray(render.OBJECT_RGB) + 0.55
    pale_sup = 0.45 * np.asarray(render.SUPPORT_RGB) + 0.55
    hot = (0.85, 0.0, 0.1)
    for i, rec in enumerate(records):
        ax = fig.add_subplot(n, 2, 2 * i + 1)
        ax.imshow(rec["image"])
        ax.set_axis_off()
        to = rec["takeoff"]
        takeoff = "-" if to is None else ("removable" if to["removable"] else "NOT removable")
        ax.set_title(
            f"{rec['object']} on {rec['support']}\n{rec['status']} "
            f"({rec['status_counts']['stable']}/{rec['n_candidates']} stable), take-off: {takeoff}",
            fontsize=9,
        )
        ax3 = fig.add_subplot(n, 2, 2 * i + 2, projection="3d")
        pose = np.asarray(rec["pose"])
        rot = Rotation.from_quat(np.roll(pose[3:], -1)).as_matrix()
        obj_pts = rec["object_cloud"].points @ rot.T + pose[:3]
        sup_pts = rec["support_cloud"].points
        ann = rec["annotation"]
        # frame on the object and the contacts; matplotlib's 3-D axes do not clip, so the
        # support's cloud is cropped to the frame
        lo, hi = obj_pts.min(0), obj_pts.max(0)
        if len(ann.support_points):
            lo = np.minimum(lo, ann.support_points.min(0))
            hi = np.maximum(hi, ann.support_points.max(0))
        centre, half = 0.5 * (lo + hi), 0.6 * float((hi - lo).max())
        inside = np.all(np.abs(sup_pts - centre) <= half, axis=1)
        sup_c = _blend(pale_sup, hot, ann.support_map)
        ax3.scatter(*sup_pts[inside].T, s=1.5, c=sup_c[inside], depthshade=False)
        ax3.scatter(*obj_pts.T, s=1.5, c=_blend(pale_obj, hot, ann.object_map), depthshade=False)
        if len(ann.support_points):
            ax3.scatter(*ann.support_points.T, s=16, c="k", marker="x", depthshade=False)
        for setter, c in zip((ax3.set_xlim, ax3.set_ylim, ax3.set_zlim), centre):
            setter(c - half, c + half)
        ax3.set_box_aspect((1, 1, 1))
        ax3.view_init(elev=elev, azim=azim)
        ax3.tick_params(labelsize=6)
        ax3.set_title(
            f"partial clouds at the pose; contact maps in red, contacts (x): {len(ann.pairs)}",
            fontsize=9,
        )
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run_hangs(library: Library, out: Path, config: AssetsJobConfig):
    """Simulate, annotate and draw ``config.hangs`` pairs into ``out/hangs.png``.

    Returns (JSON-able records, timings, full records with scenes, clouds and maps)."""
    rng = np.random.default_rng(config.seed)
    records = []
    t0 = time.perf_counter()
    plans = pick_pairs(library, config.hangs, config.max_attempts)
    for plan in tqdm(plans, desc="hangs", disable=not config.progress):
        rec = None
        for attempt, (obj, support) in enumerate(plan):
            rec = simulate_hang(obj, support, config, rng)
            rec["attempts"] = attempt + 1
            if rec["stable"]:
                break
        records.append(rec)
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    for rec in records:
        pose = np.asarray(rec["pose"])
        rec["image"] = render.render_scene(rec["scene"], pose, *config.scene_size)
        oc, sc, ann, contacts = annotate_hang(rec["scene"], pose, config, rng)
        rec.update(object_cloud=oc, support_cloud=sc, annotation=ann)
        rec["contacts"] = dict(
            penetration_m=float(contacts.penetration[0]),
            distance_m=float(contacts.distance[0]),
            n_contacts=int(contacts.mask[0].sum()),
            n_annotated=len(ann.pairs),
            object_map_mass=round(float(ann.object_map.sum()), 3),
            support_map_mass=round(float(ann.support_map.sum()), 3),
        )
    t_ann = time.perf_counter() - t0
    t0 = time.perf_counter()
    draw_hangs(records, out / "hangs.png", config)
    t_draw = time.perf_counter() - t0
    skip = {"scene", "image", "object_cloud", "support_cloud", "annotation"}
    clean = [{k: v for k, v in r.items() if k not in skip} for r in records]
    return (
        clean,
        dict(
            hangs_simulate=round(t_sim, 3),
            hangs_render_annotate=round(t_ann, 3),
            hangs_draw=round(t_draw, 3),
        ),
        records,
    )


# ----------------------------------------------------------------------------- the job


def versions() -> dict:
    import scipy
    import trimesh

    return dict(
        python=platform.python_version(),
        mujoco=mujoco.__version__,
        numpy=np.__version__,
        scipy=scipy.__version__,
        trimesh=trimesh.__version__,
        matplotlib=matplotlib.__version__,
        platform=platform.platform(),
    )


def _write_json(path: Path, obj) -> None:
    path.write_text(json.dumps(obj, indent=1))


def run(out_dir: str | Path, config: AssetsJobConfig = AssetsJobConfig()) -> dict:
    """Run the whole job into ``out_dir``; returns the content of ``assets.json``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    t_start = time.perf_counter()

    t0 = time.perf_counter()
    lib_config = LibraryConfig(
        n_objects=config.n_objects, n_supports=config.n_supports, seed=config.seed
    )
    cache = Path(config.cache_dir) if config.cache_dir else out / "cache"
    library, cached = load_or_build_library(lib_config, cache, progress=config.progress)
    timings["library"] = round(time.perf_counter() - t0, 3)
    library.save_manifest(out / "manifest.json")
    figures = library_figures(library, timings["library"])
    figures["decomposition"]["library_from_cache"] = cached

    t0 = time.perf_counter()
    groups = sheet_groups(library, config.per_row)
    render.contact_sheet(
        groups,
        out / "contact_sheet.png",
        per_row=config.per_row,
        size=config.render_size,
        progress=config.progress,
    )
    timings["contact_sheet"] = round(time.perf_counter() - t0, 3)

    hang_json, hang_times, hang_records = run_hangs(library, out, config)
    timings.update(hang_times)
    _write_json(out / "hangs.json", dict(pairs=hang_json, config=_config_json(config)))

    t0 = time.perf_counter()
    shown = next(
        (r for r in hang_records if r["stable"]), hang_records[0] if hang_records else None
    )
    example = None
    if shown is not None:
        example = write_scene(
            shown["scene"].obj, shown["scene"].support, out / "example_scene", pose=shown["pose"]
        )
        example = str(example.relative_to(out))
    timings["example_scene"] = round(time.perf_counter() - t0, 3)
    timings["total"] = round(time.perf_counter() - t_start, 3)

    summary = dict(
        **figures,
        hangs=dict(
            shown=len(hang_json),
            stable=sum(r["stable"] for r in hang_json),
            removable=sum(bool(r["takeoff"] and r["takeoff"]["removable"]) for r in hang_json),
        ),
        example_scene=example,
        files=["assets.json", "manifest.json", "contact_sheet.png", "hangs.png", "hangs.json"]
        + ([example] if example else []),
        config=_config_json(config),
        versions=versions(),
        timings_s=timings,
        n_convex_mesh_parts=sum(
            isinstance(p, ConvexMesh) for a in library.assets() for p in a.parts
        ),
    )
    _write_json(out / "assets.json", summary)
    return summary


def _config_json(config: AssetsJobConfig) -> dict:
    return {
        k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(config).items()
    }


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    d = AssetsJobConfig()
    p = argparse.ArgumentParser(
        prog="python -m experiments.assets",
        description="Build the asset library and write its numbers (assets.json), a contact "
        "sheet of every category and family, a figure of simulated hangs with contact maps "
        "and one example MuJoCo scene. Headless, CPU only.",
    )
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument("--n-objects", type=int, default=None, help=f"objects (default {d.n_objects})")
    p.add_argument(
        "--n-supports", type=int, default=None, help=f"supporting items (default {d.n_supports})"
    )
    p.add_argument("--seed", type=int, default=d.seed, help="library and sampling seed")
    p.add_argument(
        "--hangs", type=int, default=None, help=f"pairs shown in hangs.png (default {d.hangs})"
    )
    p.add_argument(
        "--per-row", type=int, default=None, help=f"renders per row of the sheet ({d.per_row})"
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="smoke-test settings: 22 objects, 10 supports, 2 hangs, small pictures "
        "(explicit --n-objects/--n-supports/--hangs/--per-row still win)",
    )
    p.add_argument(
        "--cache-dir",
        default=None,
        help="where the built library (and union meshes) are kept between runs (default OUT/cache)",
    )
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    return p.parse_args(argv)


def config_from_args(args: argparse.Namespace) -> AssetsJobConfig:
    config = QUICK if args.quick else AssetsJobConfig()
    chosen = dict(
        n_objects=args.n_objects, n_supports=args.n_supports, hangs=args.hangs, per_row=args.per_row
    )
    return dataclasses.replace(
        config,
        **{k: v for k, v in chosen.items() if v is not None},
        seed=args.seed,
        cache_dir=args.cache_dir,
        progress=not args.no_progress,
    )


def main(argv: Sequence[str] | None = None) -> dict:
    args = parse_args(argv)
    config = config_from_args(args)
    summary = run(args.out, config)
    t = summary["timings_s"]
    steps = ", ".join(f"{k} {v:.1f} s" for k, v in t.items() if k != "total")
    print(f"wrote {args.out}: {', '.join(summary['files'])}")
    print(f"timings: {steps}; total {t['total']:.1f} s")
    return summary


if __name__ == "__main__":
    _cli.run(main)
