"""Benchmark of the stability kernel: labelled candidate poses per second, one protocol.

Engines, in one run on one machine: MJX (``sim.mjx_kernels``, on the default JAX device),
MuJoCo C through ``mujoco.rollout`` on all CPU cores (``sim.kernels``, the reference) and
PyBullet on one core (``sim.pybullet_ref``, the paper's engine). Also the agreement of the
MJX labels (stable; removable for poses stable on the reference) with the reference on a
fixed set of pairs and poses, and the number of MJX compilations.

    python -m experiments.bench_sim --out DIR [--pairs 20 --poses 100 --repeat 8]

Writes DIR/bench_sim.json and prints a markdown table row set for docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from experiments import _cli
from sim import kernels, proposals
from sim.assets import objects, supports  # noqa: F401  (registers the generators)
from sim.assets.base import OBJECT_CATEGORIES, SUPPORT_FAMILIES, build_object, build_support
from sim.scene import build_scene


def pair_set(n_pairs: int, categories=None, families=None):
    """``n_pairs`` scenes cycling over object categories and support families."""
    cats = list(categories or OBJECT_CATEGORIES)
    fams = list(families or SUPPORT_FAMILIES)
    return [
        build_scene(
            build_object(cats[i % len(cats)], 1000 + i // len(cats)),
            build_support(fams[i % len(fams)], 2000 + i // len(fams)),
        )
        for i in range(n_pairs)
    ]


def pose_set(scenes, per_pair: int, seed: int):
    """Jittered hang proposals: [N] pair index and [N, 7] poses."""
    rng = np.random.default_rng(seed)
    pair = np.repeat(np.arange(len(scenes)), per_pair)
    poses = np.concatenate([proposals.hang_poses(s.obj, s.support, per_pair, rng) for s in scenes])
    return pair, poses


def by_pair(fn, scenes, pair, poses, *args):
    """Run a single-pair kernel per pair and scatter the results back into pose order."""
    out = {}
    for p in np.unique(pair):
        idx = np.flatnonzero(pair == p)
        res = fn(scenes[p], poses[idx], *args)
        for name, value in res._asdict().items():
            out.setdefault(name, np.zeros((len(poses), *value.shape[1:]), value.dtype))[idx] = value
    return out


def groups(scenes):
    """Pairs sharing a template: {template key: [pair indices]}."""
    from sim import mjx_kernels

    g = defaultdict(list)
    for i, s in enumerate(scenes):
        g[mjx_kernels.template_for(s)].append(i)
    return dict(g)


def merged_groups(scenes, k: int):
    """``k`` templates: pairs sorted by slot count, cut into k runs; each run is padded to
    the largest slot counts among its pairs (one compilation per run and function)."""
    from sim import mjx_kernels

    size = [sum(map(sum, mjx_kernels.template_for(s))) for s in scenes]
    order = np.argsort(size, kind="stable")
    return {i: sorted(c.tolist()) for i, c in enumerate(np.array_split(order, k)) if len(c)}


def mjx_many(kind, scenes, pair, poses, config, settings, templates):
    """Run the MJX kernel over all pairs: one batch per template (0: one per bucket)."""
    from sim import mjx_kernels

    fn = {"stability": mjx_kernels.stability_many, "takeoff": mjx_kernels.takeoff_many}[kind]
    if settings.impl == "warp":  # one union model for every pair
        parts = {0: list(range(len(scenes)))}
    else:
        parts = merged_groups(scenes, templates) if templates else groups(scenes)
    out = {}
    for members in parts.values():
        sub = [scenes[i] for i in members]
        local = {g: k for k, g in enumerate(members)}
        idx = np.flatnonzero(np.isin(pair, members))
        if len(idx) == 0:
            continue
        res = fn(sub, np.array([local[p] for p in pair[idx]]), poses[idx], config, settings)
        for name, value in res._asdict().items():
            out.setdefault(name, np.zeros((len(poses), *value.shape[1:]), value.dtype))[idx] = value
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--pairs", type=int, default=20)
    ap.add_argument("--poses", type=int, default=100, help="agreement poses per pair")
    ap.add_argument("--repeat", type=int, default=8, help="throughput set = poses x repeat")
    ap.add_argument("--lanes", type=int, default=4096)
    ap.add_argument("--iterations", type=int, default=None, help="MJX Newton cap")
    ap.add_argument("--ls-iterations", type=int, default=None)
    ap.add_argument("--pybullet-poses", type=int, default=60)
    ap.add_argument("--templates", type=int, default=4, help="0: one per slot bucket")
    ap.add_argument("--categories", default=None, help="comma list of object categories")
    ap.add_argument("--no-takeoff", action="store_true")
    ap.add_argument("--wait-for", default=None, help="file to wait for before CPU timings")
    ap.add_argument("--wait-max", type=int, default=900, help="seconds to wait for --wait-for")
    ap.add_argument("--impl", default="jax", choices=("jax", "warp"), help="MJX implementation")
    ap.add_argument("--contacts-per-world", type=int, default=48, help="warp contact pool")
    ap.add_argument(
        "--cpu-poses", type=int, default=0, help="MuJoCo C throughput slice (0: whole set)"
    )
    args = ap.parse_args(argv)

    import jax
    import mujoco

    from sim import mjx_kernels

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cats = args.categories.split(",") if args.categories else None
    scenes = pair_set(args.pairs, cats)
    pair, poses = pose_set(scenes, args.poses, seed=0)
    cfg = kernels.StabilityConfig()
    settings = mjx_kernels.MJXSettings(
        lanes=args.lanes,
        iterations=args.iterations,
        ls_iterations=args.ls_iterations,
        chunk=min(args.lanes, 4096),
        impl=args.impl,
        contacts_per_world=args.contacts_per_world,
    )
    timings, log = {}, print
    partial = {"impl": args.impl, "lanes": args.lanes, "pairs": len(scenes), "timings_s": timings}

    def dump(**kw):  # partial results after each stage: a run cut short still reports
        partial.update(kw)
        partial["compilations"] = dict(mjx_kernels.COMPILES)
        (out / "bench_sim.partial.json").write_text(json.dumps(partial, indent=2, default=str))
        log(json.dumps({k: v for k, v in kw.items() if k != "disagreements"}, default=str))

    # --- compilation, measured apart: one pose per pair, twice (compile + run, then run)
    first = np.unique(pair, return_index=True)[1]
    for label in ("mjx_warmup_first_s", "mjx_warmup_second_s"):
        t = time.perf_counter()
        mjx_many("stability", scenes, pair[first], poses[first], cfg, settings, args.templates)
        timings[label] = time.perf_counter() - t
    timings["mjx_compile_s"] = timings["mjx_warmup_first_s"] - timings["mjx_warmup_second_s"]
    dump(stage="compiled")

    # --- agreement set: reference labels, then MJX (first call pays the compilations)
    t = time.perf_counter()
    ref = by_pair(kernels.stability, scenes, pair, poses, cfg)
    timings["cpu_agreement_s"] = time.perf_counter() - t
    t = time.perf_counter()
    mj = mjx_many("stability", scenes, pair, poses, cfg, settings, args.templates)
    timings["mjx_first_call_s"] = time.perf_counter() - t
    log(
        f"agreement set: cpu {timings['cpu_agreement_s']:.1f}s mjx {timings['mjx_first_call_s']:.1f}s"
    )
    stable_ref, stable_mjx = ref["stable"], mj["stable"]
    stab_agree = stable_ref == stable_mjx
    rem_ref = np.zeros(len(poses), bool)
    rem_mjx = np.zeros(len(poses), bool)
    if not args.no_takeoff:
        both = np.flatnonzero(stable_ref)
        tcfg = kernels.TakeoffConfig()
        settled = ref["settled_pose"][both]
        t = time.perf_counter()
        rem_ref[both] = by_pair(kernels.takeoff, scenes, pair[both], settled, tcfg)["removable"]
        timings["cpu_takeoff_s"] = time.perf_counter() - t
        t = time.perf_counter()
        rem_mjx[both] = mjx_many(
            "takeoff", scenes, pair[both], settled, tcfg, settings, args.templates
        )["removable"]
        timings["mjx_takeoff_s"] = time.perf_counter() - t
    dump(
        stage="agreement",
        agreement_stable=float(stab_agree.mean()),
        status_counts_cpu=np.bincount(ref["status"], minlength=4).tolist(),
        status_counts_mjx=np.bincount(mj["status"], minlength=4).tolist(),
    )
    label_ref = np.stack([stable_ref, rem_ref], 1)
    label_mjx = np.stack([stable_mjx, rem_mjx], 1)
    agree = (label_ref == label_mjx).all(1)
    names = kernels.STATUS_NAMES
    disagreements = [
        {
            "pose": int(i),
            "pair": f"{scenes[pair[i]].obj.name} x {scenes[pair[i]].support.name}",
            "cpu": names[ref["status"][i]],
            "mjx": names[mj["status"][i]],
            "removable_cpu": bool(rem_ref[i]),
            "removable_mjx": bool(rem_mjx[i]),
            "penetration_cpu": float(ref["initial_penetration"][i]),
            "penetration_mjx": float(mj["initial_penetration"][i]),
        }
        for i in np.flatnonzero(~agree)
    ]

    # --- throughput set: the agreement poses jittered `repeat` times
    rng = np.random.default_rng(1)
    tp_pair = np.tile(pair, args.repeat)
    tp_poses = np.concatenate(
        [poses]
        + [
            np.stack([proposals.jitter_pose(p, rng, 0.05, 0.002) for p in poses])
            for _ in range(args.repeat - 1)
        ]
    )
    t = time.perf_counter()
    mj_tp = mjx_many("stability", scenes, tp_pair, tp_poses, cfg, settings, args.templates)
    mjx_s = time.perf_counter() - t
    dump(stage="mjx_throughput", mjx_poses_per_s=len(tp_poses) / mjx_s, mjx_s=mjx_s)
    if args.wait_for:  # e.g. a PyBullet build running beside the GPU part
        for _ in range(args.wait_max):
            if os.path.exists(args.wait_for):
                break
            time.sleep(1)
    cpu_take = np.arange(len(tp_poses))
    if args.cpu_poses and args.cpu_poses < len(tp_poses):
        cpu_take = np.linspace(0, len(tp_poses) - 1, args.cpu_poses).astype(int)
    t = time.perf_counter()
    by_pair(kernels.stability, scenes, tp_pair[cpu_take], tp_poses[cpu_take], cfg)
    cpu_s = time.perf_counter() - t
    dump(stage="cpu_throughput", cpu_poses_per_s=len(cpu_take) / cpu_s, cpu_s=cpu_s)
    # PyBullet, one core: a slice of the throughput set over all pairs
    take = np.linspace(0, len(tp_poses) - 1, args.pybullet_poses).astype(int)
    pb, pb_s, pb_skipped = {"status": np.zeros(0, int)}, float("nan"), []
    try:
        from sim import pybullet_ref
    except ImportError as err:  # e.g. the PyBullet build beside the GPU part failed
        log(f"no PyBullet: {err}")
        take = take[:0]
    if len(take):
        t = time.perf_counter()
        status, kept = [], []
        for p in np.unique(tp_pair[take]):
            idx = take[tp_pair[take] == p]
            try:
                status.append(pybullet_ref.stability(scenes[p], tp_poses[idx], cfg).status)
                kept.append(idx)
            except Exception as err:  # some mesh parts fail to load in PyBullet
                pb_skipped.append(f"{scenes[p].obj.name} x {scenes[p].support.name}: {err}")
        pb_s = time.perf_counter() - t
        take = np.concatenate(kept) if kept else take[:0]
        pb = {"status": np.concatenate(status) if status else np.zeros(0, int)}
    n = len(tp_poses)
    rates = {"mjx": n / mjx_s, "mujoco_cpu": len(cpu_take) / cpu_s, "pybullet": len(take) / pb_s}
    mix = {
        k: np.bincount(v, minlength=4).tolist()
        for k, v in (("mjx", mj_tp["status"]), ("pybullet", pb["status"]))
    }
    result = {
        "poses_per_s": rates,
        "ratios": {
            "mjx_over_mujoco_cpu": rates["mjx"] / rates["mujoco_cpu"],
            "mjx_over_pybullet": rates["mjx"] / rates["pybullet"],
            "mujoco_cpu_over_pybullet": rates["mujoco_cpu"] / rates["pybullet"],
        },
        "agreement": float(agree.mean()),
        "agreement_stable": float(stab_agree.mean()),
        "agreement_removable_on_ref_stable": float(
            (rem_ref == rem_mjx)[stable_ref].mean() if stable_ref.any() else 1.0
        ),
        "agreement_poses": len(poses),
        "pairs": len(scenes),
        "categories": sorted({s.obj.category for s in scenes}),
        "families": sorted({s.support.category for s in scenes}),
        "stable_fraction_cpu": float(stable_ref.mean()),
        "status_counts_cpu": np.bincount(ref["status"], minlength=4).tolist(),
        "status_counts_mjx": np.bincount(mj["status"], minlength=4).tolist(),
        "status_counts_throughput": mix,
        "disagreements": disagreements,
        "compilations": dict(mjx_kernels.COMPILES),
        "compilations_total": int(sum(mjx_kernels.COMPILES.values())),
        "templates": 1 if args.impl == "warp" else (args.templates or len(groups(scenes))),
        "slot_buckets": len(groups(scenes)),
        "throughput_poses": n,
        "cpu_throughput_poses": len(cpu_take),
        "impl": args.impl,
        "contacts_per_world": args.contacts_per_world if args.impl == "warp" else None,
        "pybullet_poses": len(take),
        "pybullet_skipped_pairs": pb_skipped,
        "lanes": args.lanes,
        "mjx_iterations": args.iterations,
        "mjx_ls_iterations": args.ls_iterations,
        "timings_s": {**timings, "cpu": cpu_s, "mjx": mjx_s, "pybullet": pb_s},
        "device": str(jax.devices()[0].device_kind) if jax.devices() else "none",
        "jax_backend": jax.default_backend(),
        "warp_device": _warp_device() if args.impl == "warp" else None,
        "cpu_cores": len(os.sched_getaffinity(0)),
        "versions": {
            "jax": jax.__version__,
            "mujoco": mujoco.__version__,
            "mujoco_mjx": _version("mujoco-mjx"),
            "pybullet": _version("pybullet"),
            "warp_lang": _version("warp-lang"),
            "python": platform.python_version(),
        },
    }
    (out / "bench_sim.json").write_text(json.dumps(result, indent=2))
    log(json.dumps({k: v for k, v in result.items() if k != "disagreements"}, indent=2))
    return result


def _warp_device() -> str:
    """Where MuJoCo Warp runs: Warp's preferred device (``cuda:0`` on a GPU, else ``cpu``)."""
    try:
        import warp

        return str(warp.get_preferred_device())
    except Exception as err:  # noqa: BLE001
        return f"unknown ({err})"


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "missing"


if __name__ == "__main__":
    _cli.run(main)
