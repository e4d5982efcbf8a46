"""Measure how many candidate poses of each sampler hang stably, per object category.

    python -m experiments.proposal_yield --out results/proposal_yield.json

For every category, ``--objects`` objects of the library, each paired with a support drawn
at random from all families, get ``--hang`` hang-threading candidates
(``sim.proposals.hang_poses``) and ``--uniform`` candidates of the original uniform sampler;
the CPU stability kernel labels them. Writes the fractions per category and their mean.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from experiments import _cli
from sim import kernels, proposals
from sim.library import LibraryConfig, build_library
from sim.scene import build_scene


def measure(
    objects: int = 3, hang: int = 32, uniform: int = 128, seed: int = 0, progress: bool = True
) -> dict:
    library = build_library(LibraryConfig(), progress=False)
    rng = np.random.default_rng(seed)
    supports = sorted(library.supports)
    by_cat: dict[str, list[str]] = {}
    for name in sorted(library.objects):
        by_cat.setdefault(library.objects[name].category, []).append(name)
    rows = {}
    t0 = time.time()
    for cat, names in tqdm(sorted(by_cat.items()), desc="categories", disable=not progress):
        counts = {"hang": [0, 0], "uniform": [0, 0]}
        for name in names[:objects]:
            support = library.supports[supports[rng.integers(len(supports))]]
            obj = library.objects[name]
            scene = build_scene(obj, support)
            for sampler, n, fn in (
                ("hang", hang, proposals.hang_poses),
                ("uniform", uniform, proposals.uniform_poses),
            ):
                if n == 0:
                    continue
                res = kernels.stability(scene, fn(obj, support, n, rng))
                counts[sampler][0] += int(res.stable.sum())
                counts[sampler][1] += n
        rows[cat] = {k: v[0] / max(v[1], 1) for k, v in counts.items()}
    return {
        "per_category": rows,
        "mean": {k: float(np.mean([r[k] for r in rows.values()])) for k in ("hang", "uniform")},
        "settings": {
            "objects_per_category": objects,
            "hang": hang,
            "uniform": uniform,
            "seed": seed,
        },
        "seconds": time.time() - t0,
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", default="results/proposal_yield.json", help="JSON to write")
    parser.add_argument("--objects", type=int, default=3, help="objects per category")
    parser.add_argument("--hang", type=int, default=32, help="hang-threading candidates per object")
    parser.add_argument("--uniform", type=int, default=128, help="uniform candidates per object")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    result = measure(args.objects, args.hang, args.uniform, args.seed)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    for cat, r in result["per_category"].items():
        print(f"{cat:16s} hang {100 * r['hang']:5.1f}%  uniform {100 * r['uniform']:5.1f}%")
    print(
        f"{'mean':16s} hang {100 * result['mean']['hang']:5.1f}%  uniform {100 * result['mean']['uniform']:5.1f}%"
    )
    return result


if __name__ == "__main__":
    _cli.run(main)
