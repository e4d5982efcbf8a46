"""Benchmark of the observed-physics answer check (``sim.observed.first_staying``) on the CPU.

Per pair of evenly spaced validation records (three views, CEM key 0), side by side in one run: the lazy
check (the rule's candidates dropped one at a time until one stays, at most ``--top``, the
default's 60), the lazy check with a shorter reach (``--short``, 8) and the eager one at that
reach (all 8 simulated, the same answer as the lazy one), each on one core. Prints
and writes per-pair wall times (mean, median, p90), the candidates simulated, their ratio,
the machine and the versions.

    python scripts/bench_observed_check.py --pairs 100 --out results/bench_observed_check_cpu.json
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]
from experiments.observed_check import union  # noqa: E402
from experiments.rerank_completed import load_clouds  # noqa: E402
from experiments.union_views import VALIDATION_RECORDS as VALIDATION  # noqa: E402
from sim import kernels, observed  # noqa: E402


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def stats(x) -> dict:
    x = np.asarray(x, float) * 1e3
    return dict(mean_ms=round(float(x.mean()), 1), median_ms=round(float(np.median(x)), 1),
                p90_ms=round(float(np.percentile(x, 90)), 1))  # fmt: skip


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=100)
    p.add_argument("--top", type=int, default=observed.ANSWER_TOP, help="the lazy check's reach")
    p.add_argument("--short", type=int, default=8, help="a shorter reach, lazy and eager")
    p.add_argument("--radius", type=float, default=observed.ObservedConfig.radius)
    p.add_argument("--data", default="datasets/paper")
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    import mujoco

    from omnihang_jax import dataset_bridge
    from sim.library import build_library

    cfg = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(a.data))
    library = build_library(cfg.library, progress=False)
    u = union(VALIDATION[0])
    config = observed.ObservedConfig(radius=a.radius)
    times = {"lazy": [], "lazy_short": [], "eager_short": []}
    tried = {"lazy": [], "lazy_short": []}
    same = 0
    picks = np.unique(np.linspace(0, len(u["rows"]) - 1, min(a.pairs, len(u["rows"]))).astype(int))
    rows = [u["rows"][i] for i in picks]  # evenly spaced: every category (rows are by category)
    for i, r in zip(picks, rows, strict=True):
        sup = library.supports[r["support"]]
        clouds = load_clouds(Path(a.data), r)
        poses = u["poses"][i, np.argsort(-u["keys"][i], kind="stable")]
        args = (clouds, poses, sup.floor_z, sup.wall_y)
        for name, top in (("lazy", a.top), ("lazy_short", a.short)):
            t = time.perf_counter()
            idx, status = observed.first_staying(*args, top, config)
            times[name].append(time.perf_counter() - t)
            tried[name].append(int((status != -2).sum()))
        t = time.perf_counter()
        every = observed.observed_stability(
            clouds, poses[: a.short], sup.floor_z, sup.wall_y, config
        )
        times["eager_short"].append(time.perf_counter() - t)
        stays = np.flatnonzero(every == kernels.STABLE)
        same += int((stays[0] if len(stays) else 0) == idx)  # idx: the lazy short check's
    out = {}
    for name, x in times.items():
        out[name] = stats(x) | {
            "top": a.top if name == "lazy" else a.short,
            "candidates_simulated_mean": round(float(np.mean(tried[name])), 2)
            if name in tried else float(a.short),
        }  # fmt: skip
    result = dict(
        pairs=len(rows), radius_m=a.radius, records=VALIDATION[0], **out,
        lazy_over_lazy_short=round(float(np.mean(times["lazy"]) / np.mean(times["lazy_short"])), 2),
        eager_short_over_lazy_short=round(
            float(np.mean(times["eager_short"]) / np.mean(times["lazy_short"])), 2),
        same_answer_lazy_and_eager_short=same,
        machine=dict(cpu=cpu_name(), cores_used=1, platform=platform.platform()),
        versions=dict(mujoco=mujoco.__version__, numpy=np.__version__,
                      python=platform.python_version()),  # fmt: skip
    )  # fmt: skip
    print(json.dumps(result, indent=1))
    if a.out:
        Path(a.out).write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
