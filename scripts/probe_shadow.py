"""Issue 12 probe (forty-fifth session): does the solid behind each observed surface, as each
camera saw it, show the penetrations the answer rule cannot see?

The answer rule counts object points behind the nearest observed support point's surface
(along its normal, within a radius sideways). A rod or a hook is solid for its whole diameter
behind what its camera saw, and a penetrating candidate's object often crosses that hidden half
(docs/stage3.md: ~9 % of held-out pairs pick a penetrating candidate while another hangs; the
observed clouds show no object point inside). This probe measures the other test: along the
ray from the support's camera, how far behind the observed support surface each posed object
point lies (``omnihang_jax.completion.depth_map``, the carving depth map), counting the points
in a slab ``lo < behind < hi`` (a stable hang touches the back of a rod at about its diameter,
so ``hi`` must stay below the thinnest rod's). ``support``: observed object points in the
support's slab; ``object``: observed support points in the object's slab (the object's hidden
back, from its own camera, in the object frame); ``both``: their sum.

Rules, choice and reading as ``scripts/probe_symmetry.py`` (the default union's key minus
``lambda x count`` or lexicographic with a limit; chosen on the validation objects' records of
three CEM keys, read once on the held-out records). No network, no simulation: every pooled
candidate of the records was simulated.

    python -m experiments.derive_dataset --data datasets/paper --split train --pairs-from VAL.jsonl --clouds-only
    python -m experiments.derive_dataset --data datasets/paper --split test --pairs-from TEST.jsonl --clouds-only
    python scripts/probe_shadow.py --out results/probe_shadow_s45.json      # ~15 min on 2 cores
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from probe_symmetry import (  # noqa: E402
    HELDOUT,
    MAX_POINTS,
    VALIDATION,
    finish,
    key_runs,
    separation,
    table,
)

from experiments.rerank_stage3 import read_records  # noqa: E402
from omnihang_jax import collision, completion  # noqa: E402

SLABS = tuple((lo, hi) for lo in (0.001, 0.002, 0.003) for hi in (0.004, 0.006, 0.01))
VARIANTS = ("support", "object", "both")
N_OBJECT = 1024  # observed object points posed (the rule's subset size)
N_SUPPORT = 2048  # observed support points taken into the object frame


def slab_counts(behind: np.ndarray) -> np.ndarray:
    """behind [P, N] -> [S, P] points in each slab of :data:`SLABS`."""
    return np.stack([((behind > lo) & (behind < hi)).sum(1) for lo, hi in SLABS]).astype(np.int32)


def pair_counts(eyes, clouds: dict, poses: np.ndarray) -> dict:
    """part -> [S, P] counts for the candidate poses [P, 7] of one pair (object eye in the
    object frame, support eye in the support frame: the dataset's records)."""
    obj = np.asarray(clouds["object_points"], float)
    sup = np.asarray(clouds["support_points"], float)
    obj = obj[collision.subsample_indices(len(obj), N_OBJECT, 0)]
    sub_s = sup[collision.subsample_indices(len(sup), N_SUPPORT, 0)]
    poses = np.asarray(poses, float)
    behind_s = completion.depth_map(sup, eyes[1])
    posed = np.asarray(collision.posed_points(poses, obj), float)  # [P, N, 3] support frame
    behind_o = completion.depth_map(np.asarray(clouds["object_points"], float), eyes[0])
    local = np.asarray(collision.inverse_transform_points(poses, sub_s), float)  # object frame
    p = len(poses)
    return {
        "support": slab_counts(behind_s(posed.reshape(-1, 3)).reshape(p, -1)),
        "object": slab_counts(behind_o(local.reshape(-1, 3)).reshape(p, -1)),
    }


def combine(c: dict, variant: str) -> np.ndarray:
    return c["support"] + c["object"] if variant == "both" else c[variant]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--keys", type=int, default=3, help="CEM keys read (1-3)")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    from sim import dataset

    t0 = time.perf_counter()
    data, progress = Path(args.data), not args.no_progress
    eyes = {int(r["pair_index"]): (np.asarray(r["object_eye"], float),
                                   np.asarray(r["support_eye"], float))
            for r in dataset.load_records(data)}  # fmt: skip

    def counts_fn(row, clouds, poses):
        return pair_counts(eyes[int(row["pair_index"])], clouds, poses)

    result = dict(settings=vars(args), slabs=[list(x) for x in SLABS], max_points=list(MAX_POINTS))
    tables = {}
    g = SLABS.index((0.002, 0.006))
    for split, runs in (("validation", VALIDATION), ("heldout", HELDOUT)):
        parts = [
            key_runs([read_records(p) for p in key], data, 0.0, progress, counts_fn, VARIANTS, combine)
            for key in runs[: args.keys]
        ]  # fmt: skip
        tables[split] = table(parts, progress, VARIANTS, SLABS, ("behind_from", "behind_to"))
        result[f"separation_{split}"] = separation(parts, VARIANTS, g) | {"slab": list(SLABS[g])}
        print(f"{split}: {len(tables[split])} rules, {time.perf_counter() - t0:.0f} s", flush=True)
    return finish(result, tables, ("variant", "behind_from", "behind_to", "rule", "value"),
                  args.out, t0)  # fmt: skip


if __name__ == "__main__":
    main()
