"""Issue 12 probe (fiftieth session): what the SUPPORT's true surface gives the answer rule, a bound
on completing the support, beside the object's true hidden side.

The forty-eighth session's bound (``scripts/probe_true_surface.py``) tested the object's true hidden
side against the OBSERVED support and added a penalty to the default's key: +2.0 held out, about
half of a perfect penetration test (+4.4). This probe asks where the other half is. It REPLACES the
default's inside test (``selection.CHOSEN``: no object point 0.5 mm behind the support's surface
within 5 mm sideways; ``experiments.rerank_stage3.rule_keys``) by the same test on other clouds:

- ``committed``: the record's own counts (the default, a check);
- ``observed``: the observed object points against the observed support cloud, recounted here
  with :func:`experiments.rerank_completed.inside_grid` (a check that the recount agrees);
- ``support_true``: the observed object points against the support's whole true surface (its union
  mesh sampled ~1 mm apart, with the faces' outward normals): a perfect support completion;
- ``object_true``: the observed object points and the object's true hidden side (as the s48 bound)
  against the observed support;
- ``both_true``: both: the observed points and the true hidden side against the true support.

The union of the three views and the ranking networks' key are the default's; only the inside
counts change. It is an oracle (meshes, no simulation, the records' simulated outcomes). Reads the
three validation keys' first key and held-out key 0 (``--keys``, ``--heldout-keys``).

    python scripts/probe_support_surface.py --out results/probe_support_surface_s50.json
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))

from probe_symmetry import HELDOUT, VALIDATION  # noqa: E402
from probe_true_surface import MARGIN, support_surface  # noqa: E402

from experiments.rerank_completed import inside_grid, load_clouds  # noqa: E402
from experiments.rerank_stage3 import (  # noqa: E402
    category_means,
    pool_indices,
    proposals_of,
    read_records,
)
from omnihang_jax import collision, selection  # noqa: E402

VARIANTS = ("committed", "observed", "support_true", "object_true", "both_true")
N_POINTS = 1024  # object points (observed, and hidden) posed per candidate
MAX_DIST = 0.03  # m: a point this far from every support point is outside (no part is 6 cm thick)
NEW = 0.003  # m: a true surface point farther than this from every observed one is hidden

_W: dict = {}


def _init(data: str, cache: str) -> None:
    from omnihang_jax import dataset_bridge
    from sim.library import build_library

    cfg = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(data))
    with np.load(cache) as z:
        true = {str(n): s for n, s in zip(z["names"], z["surfaces"], strict=True)}
    _W.update(data=Path(data), library=build_library(cfg.library, progress=False), true=true,
              supports={})  # fmt: skip


def pair_counts(job: tuple[dict, np.ndarray]) -> dict:
    """(record row, [P, 7] poses) -> variant -> [P] inside counts at the CHOSEN depth / radius."""
    row, poses = job
    grid = ((selection.CHOSEN.depth, selection.CHOSEN.radius),)
    clouds = load_clouds(_W["data"], row)
    obs = np.asarray(clouds["object_points"], float)
    pick = collision.subsample_indices
    obs = obs[pick(len(obs), N_POINTS, 0)] if len(obs) > N_POINTS else obs
    surf = np.asarray(_W["true"][row["object"]], float)
    hidden = surf[cKDTree(obs).query(surf, k=1)[0] > NEW]
    hidden = hidden[pick(len(hidden), N_POINTS, 0)] if len(hidden) > N_POINTS else hidden
    name = row["support"]
    if name not in _W["supports"]:
        _W["supports"][name] = support_surface(_W["library"].supports[name])
    sp, sn = _W["supports"][name]
    op, on = (np.asarray(clouds[k], float) for k in ("support_points", "support_normals"))

    def count(points, s, n):
        if len(points) == 0:
            return np.zeros(len(poses), np.int64)
        posed = collision.posed_points(poses, points)
        return inside_grid(posed, s, n, margin=MARGIN, grid=grid, max_dist=MAX_DIST)[0]

    c_obs, c_sup = count(obs, op, on), count(obs, sp, sn)
    c_hid_obs, c_hid_sup = count(hidden, op, on), count(hidden, sp, sn)
    fit = float(np.median(cKDTree(sp).query(op, k=1)[0]))
    return dict(observed=c_obs, support_true=c_sup, object_true=c_obs + c_hid_obs,
                both_true=c_sup + c_hid_sup, fit=fit)  # fmt: skip


def split_success(
    keys_runs: list, data: str, cache: str, workers: int, progress: bool, limit: int | None = None
) -> dict:
    """One split's keys (each a list of three views' record files) -> variant -> per-key means."""
    out: dict[str, list] = {v: [] for v in VARIANTS}
    fits = []
    ctx = multiprocessing.get_context("spawn")  # the parent holds JAX's threads: no fork
    with ProcessPoolExecutor(workers, ctx, initializer=_init, initargs=(data, cache)) as ex:
        for key in keys_runs:
            keys = {v: [] for v in VARIANTS}
            stable = []
            rows0 = None
            for path in key:
                rows = read_records(path)[:limit]
                rows0 = rows0 or rows
                k = proposals_of(rows)
                idx = pool_indices(k, "stage1_2")
                grid = selection.grid_key(selection.CHOSEN.depth, selection.CHOSEN.radius)
                jobs = [(r, np.asarray(r["poses_all"], float)[idx]) for r in rows]
                counts = list(tqdm(ex.map(pair_counts, jobs, chunksize=4), total=len(jobs),
                                   desc=Path(path).name, disable=not progress))  # fmt: skip
                fits += [c["fit"] for c in counts]
                score = np.stack([
                    np.log(np.clip(np.asarray(r.get("v_rank") or [r["v"]], float)[:, idx],
                                   1e-12, 1.0)).mean(0)
                    for r in rows])  # fmt: skip
                stable.append(np.stack([np.asarray(r["stable_all"], bool)[idx] for r in rows]))
                for v in VARIANTS:
                    c = (np.stack([np.asarray(r["inside_counts"][grid], np.int64)[idx] for r in rows])
                         if v == "committed" else np.stack([x[v] for x in counts]))  # fmt: skip
                    keys[v].append(np.asarray(selection.select_key(score, c, selection.CHOSEN)))
            st = np.concatenate(stable, 1)
            n = np.arange(len(rows0))
            for v in VARIANTS:
                kk = np.concatenate(keys[v], 1)
                out[v].append(category_means(rows0, st[n, kk.argmax(1)]))
    result = {
        v: dict(per_key=[round(m["mean"], 3) for m in ms],
                mean=round(float(np.mean([m["mean"] for m in ms])), 3),
                per_category={c: round(float(np.mean([m["per_category"][c] for m in ms])), 2)
                              for c in ms[0]["per_category"]})
        for v, ms in out.items()
    }  # fmt: skip
    result["median_observed_support_to_true_mm"] = round(1e3 * float(np.median(fits)), 3)
    return result


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--cache", default="out/s48/true_surfaces.npz",
                    help="the objects' true surfaces (scripts/probe_true_surface.py writes it)")  # fmt: skip
    ap.add_argument("--keys", type=int, default=1, help="CEM keys read on validation (0-3)")
    ap.add_argument("--heldout-keys", type=int, default=1, help="... and held out")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--limit", type=int, default=None, help="the first N pairs only (a quick look)")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    if not Path(args.cache).exists():
        raise SystemExit(f"{args.cache} missing: run scripts/probe_true_surface.py once (it renders "
                         "and caches the objects' true surfaces)")  # fmt: skip
    t0 = time.perf_counter()
    result: dict = dict(settings=vars(args), depth=selection.CHOSEN.depth,
                        radius=selection.CHOSEN.radius)  # fmt: skip
    for split, runs, n in (("validation", VALIDATION, args.keys),
                           ("heldout", HELDOUT, args.heldout_keys)):  # fmt: skip
        if n == 0:  # a split not read (--keys 0: held out only)
            continue
        result[split] = split_success(runs[:n], args.data, args.cache, args.workers,
                                      not args.no_progress, args.limit)  # fmt: skip
        print(split, {v: result[split][v]["mean"] for v in VARIANTS}, flush=True)
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    result["seconds"] = round(time.perf_counter() - t0, 1)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
