"""The answer check on the OBSERVED clouds, read from an evaluation's records.

The default answer rule (``experiments.rerank_stage3.rule_keys``: the rankers' mean log P,
no observed object point inside the observed support) picks a candidate that falls or
penetrates in ~17 % of held-out pairs, most of them while another candidate hangs. This
simulates the rule's top ``--top`` candidates of every pair on the observed clouds alone
(``sim.observed``: the partial clouds as spheres, the dataset's stability protocol by default)
and reads the rules that skip a candidate the observed physics drops:

- ``first_of_M``: the first of the rule's top M candidates that stays on the observed clouds,
  else the rule's own answer (``sim.observed.first_staying``, M = ``ANSWER_TOP``);

chosen on the validation records (three views, CEM keys 0-2), read once on the held-out ones.
No network runs: every candidate of the records was already simulated on the true meshes, so
each rule's success is exact. The observed clouds come from ``experiments.derive_dataset
--clouds-only``; the observed statuses are cached (``--cache``), so a killed run resumes.

    python -m experiments.observed_check --split validation --key 0        # ~2 min, 2 cores
    python -m experiments.observed_check --split heldout --key 0 --out results/observed_check_s51/heldout_k0.json
    python -m experiments.observed_check --runs A.pairs.jsonl.gz B.pairs.jsonl.gz   # any records
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from experiments import _cli
from experiments.rerank_completed import load_clouds
from experiments.rerank_stage3 import (
    category_means,
    pool_indices,
    proposals_of,
    read_records,
    rule_keys,
)
from experiments.union_views import HELDOUT_RECORDS, VALIDATION_RECORDS
from sim import kernels, observed

FIRST_OF = (2, 3, 4, 5, 8, 10)
FIRST_OF_EXTENDED = (15, 20, 30, 40, 60)  # with --extend: where none of the top 10 stays
_W: dict = {}


def union(files: list[str]) -> dict:
    """The three views' records of one key as one pool per pair: rows (of the first view),
    [N, P] rule keys, [N, P] simulated stable, [N, P] statuses, [N, P, 7] poses."""
    runs = [read_records(f) for f in files]
    keys, stable, status, poses = [], [], [], []
    for rows in runs:
        if [r["pair_index"] for r in rows] != [r["pair_index"] for r in runs[0]]:
            raise ValueError(f"{files}: the views' records list different pairs")
        k = proposals_of(rows)
        idx = pool_indices(k, "stage1_2")
        kk, st = rule_keys(rows, k)
        keys.append(kk)
        stable.append(st)
        status.append([r["all_stages"]["statuses"] for r in rows])  # the 2K pooled candidates
        poses.append([np.asarray(r["poses_all"], float)[idx] for r in rows])
    return dict(rows=runs[0], keys=np.concatenate(keys, 1), stable=np.concatenate(stable, 1),
                status=np.concatenate(status, 1), poses=np.concatenate(poses, 1))  # fmt: skip


def _stability(protocol: str, max_penetration: float | None = None):
    """The stability protocol of the observed check: the evaluation's (1 s, > 3 mm initial
    penetration fails) or the dataset's (``sim.kernels.StabilityConfig``: 2 s, > 1 mm), with
    another initial-penetration limit when ``max_penetration`` is given."""
    from omnihang_jax.evaluate import protocol_stability

    config = protocol_stability() if protocol == "eval" else kernels.StabilityConfig()
    if max_penetration is not None:
        config = dataclasses.replace(config, max_penetration=float(max_penetration))
    return config


def _init(data: str, config: dict, protocol: str = "dataset", scene: str = "known",
          max_penetration: float | None = None) -> None:  # fmt: skip
    from omnihang_jax import dataset_bridge
    from sim.library import build_library

    cfg = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(data))
    _W.update(data=Path(data), library=build_library(cfg.library, progress=False),
              config=observed.ObservedConfig(**config), stability=_stability(protocol, max_penetration),
              scene=scene)  # fmt: skip


def simulate(job: tuple[dict, np.ndarray]) -> tuple[int, np.ndarray, float]:
    """(record row, [M, 7] poses) -> (pair index, [M] observed statuses, seconds)."""
    row, poses = job
    t = time.perf_counter()
    support = _W["library"].supports[row["support"]]
    clouds = load_clouds(_W["data"], row)
    floor_z, wall_y = support.floor_z, support.wall_y
    if _W["scene"] == "clouds":  # what a clouds-only input knows: no wall, no floor
        floor_z, wall_y = observed.unknown_environment(clouds["support_points"])
    try:
        status = observed.observed_stability(
            clouds, poses, floor_z, wall_y, _W["config"], _W["stability"]
        )
    except ValueError as err:  # a malformed cloud: say so, count the pair as unchecked
        print(f"pair {row['pair_index']}: {err}", file=sys.stderr)
        status = np.full(len(poses), -1, np.int8)
    return int(row["pair_index"]), status, time.perf_counter() - t


def observed_statuses(u: dict, top: int, cache: Path, data: str, config: dict, workers: int,
                      progress: bool = True, protocol: str = "dataset", scene: str = "known",
                      max_penetration: float | None = None,
                      extend: int | None = None) -> np.ndarray:  # fmt: skip
    """[N, P] observed status of each pooled candidate (-2 where not simulated): the rule's
    top ``top`` of every pair, then, where none of them stays, the rest of the top ``extend``
    (so ``first_of_M`` is exact for every M up to ``extend``); cached in ``cache``
    (resumable)."""
    have: dict[int, np.ndarray] = {}
    if cache.exists():
        with np.load(cache) as z:
            have = {int(i): s for i, s in zip(z["pair"], z["status"], strict=True)}
    n, p = u["keys"].shape
    order = np.argsort(-u["keys"], axis=1, kind="stable")
    where = {int(r["pair_index"]): i for i, r in enumerate(u["rows"])}
    seconds = []

    def save():
        pairs = np.array(sorted(have), np.int64)
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_suffix(".tmp.npz")
        np.savez(tmp, pair=pairs, status=np.stack([have[q] for q in pairs]) if len(pairs)
                 else np.zeros((0, p), np.int8))  # fmt: skip
        tmp.replace(cache)

    def run(cols: dict[int, np.ndarray], label: str) -> None:
        """Simulate, per row index i, the candidates ``cols[i]`` not simulated yet."""
        jobs = []
        for i, c in cols.items():
            pi = int(u["rows"][i]["pair_index"])
            done = have.get(pi)
            if done is None or (done[c] == -2).any():
                jobs.append((u["rows"][i], u["poses"][i, c]))
        if not jobs:
            return
        with ProcessPoolExecutor(
            workers, initializer=_init, initargs=(data, config, protocol, scene, max_penetration)
        ) as pool:
            bar = tqdm(total=len(jobs), desc=f"observed physics, {label} ({cache.stem})",
                       disable=not progress)  # fmt: skip
            for k, (pi, status, sec) in enumerate(pool.map(simulate, jobs, chunksize=4), 1):
                i = where[pi]
                row = have.get(pi, np.full(p, -2, np.int8)).copy()
                row[cols[i]] = status
                have[pi] = row
                seconds.append(sec)
                bar.update()
                if k % 50 == 0:
                    save()
            bar.close()
        save()
        print(f"{label}: simulated {len(jobs)} pairs, {np.mean(seconds):.2f} s a pair (one core)")

    run({i: order[i, :top] for i in range(n)}, f"top {top}")
    if extend and extend > top:
        none = [i for i in range(n)
                if not (have[int(u["rows"][i]["pair_index"])][order[i, :top]] == kernels.STABLE).any()]  # fmt: skip
        run(
            {i: order[i, top:extend] for i in none},
            f"{len(none)} pairs, candidates {top + 1}-{extend}",
        )
    out = np.full((n, p), -2, np.int8)
    for i, r in enumerate(u["rows"]):
        out[i] = have[int(r["pair_index"])]
    return out


def rules(u: dict, obs: np.ndarray, extend: int | None = None) -> dict:
    """Rule name -> the category means of its answers (``first_of_M`` beyond ``--top`` only
    up to ``extend``, where the statuses reach)."""
    keys, stable = u["keys"], u["stable"]
    order = np.argsort(-keys, axis=1, kind="stable")
    n = len(keys)
    out = {"default": category_means(u["rows"], stable[np.arange(n), order[:, 0]])}
    for m in [*FIRST_OF, *(m for m in FIRST_OF_EXTENDED if extend and m <= extend)]:
        picks = []
        for i in range(n):
            stays = [j for j in order[i, :m] if obs[i, j] == kernels.STABLE]
            picks.append(stays[0] if stays else order[i, 0])
        out[f"first_of_{m}"] = category_means(u["rows"], stable[np.arange(n), picks])
        out[f"first_of_{m}"]["changed"] = int(np.sum(np.asarray(picks) != order[:, 0]))
    out["some_candidate"] = category_means(u["rows"], stable.any(1))
    return out


def confusion(u: dict, obs: np.ndarray) -> dict:
    """True status -> observed status counts over the simulated candidates, overall and for
    the rule's own answers."""
    names = kernels.STATUS_NAMES
    out = {}
    n = len(obs)
    first = np.argsort(-u["keys"], axis=1, kind="stable")[:, 0]
    for label, mask in (("top", obs != -2), ("answer", np.zeros_like(obs, bool))):
        if label == "answer":
            mask[np.arange(n), first] = True
        c = Counter()
        for t, o in zip(u["status"][mask], obs[mask], strict=True):
            c[(str(t), "unchecked" if o < 0 else names[o])] += 1
        out[label] = {f"{t} -> {o}": v for (t, o), v in sorted(c.items())}
    return out


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--split",
        choices=("validation", "heldout"),
        default="validation",
        help="the default pipeline's committed records of these pairs",
    )
    p.add_argument("--key", type=int, default=0, help="CEM key of the records (0-2)")
    p.add_argument(
        "--runs",
        nargs="+",
        default=None,
        help="other records (eval_stage3 per-pair JSONL, the same pairs in each), "
        "pooled as one pipeline's views; overrides --split / --key",
    )
    p.add_argument("--top", type=int, default=10, help="candidates simulated per pair")
    p.add_argument(
        "--extend",
        type=int,
        default=None,
        metavar="N",
        help="where none of the top stays, simulate on down to the N-th candidate "
        "(first_of_N exact; default: none)",
    )
    p.add_argument("--data", default="datasets/paper")
    p.add_argument("--radius", type=float, default=observed.ObservedConfig.radius)
    p.add_argument("--crop", type=float, default=observed.ObservedConfig.crop)
    p.add_argument("--voxel", type=float, default=observed.ObservedConfig.voxel)
    p.add_argument(
        "--protocol",
        choices=("dataset", "eval"),
        default="dataset",
        help="stability protocol of the check: the dataset's (2 s, > 1 mm penetration "
        "fails) or the evaluation's (1 s, > 3 mm)",
    )
    p.add_argument(
        "--scene",
        choices=("known", "clouds"),
        default="known",
        help="known: the support's floor and wall (an observer sees both); clouds: "
        "neither (a clouds-only input: the floor 1 m below the support, no wall)",
    )
    p.add_argument(
        "--max-penetration",
        type=float,
        default=None,
        metavar="M",
        help="initial penetration (m) past which a candidate fails on the observed "
        "clouds (default: the protocol's, 1 mm / 3 mm)",
    )
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--limit", type=int, default=None, help="first N pairs only (a smoke run)")
    p.add_argument(
        "--cache",
        default=None,
        help="statuses cache (default out/observed_check/<records>_<config>.npz)",
    )
    p.add_argument("--out", default=None, help="JSON of the figures")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    if a.top < max(FIRST_OF):
        p.error(f"--top must be at least {max(FIRST_OF)} (the widest rule)")
    files = a.runs or (VALIDATION_RECORDS if a.split == "validation" else HELDOUT_RECORDS)[a.key]
    u = union(files)
    if a.limit:
        u = {k: v[: a.limit] for k, v in u.items()}
    config = dict(radius=a.radius, crop=a.crop, voxel=a.voxel)
    name = f"{a.split}_k{a.key}" if not a.runs else Path(a.runs[0]).name.split(".")[0]
    tag = f"{name}_r{a.radius * 1e3:g}_c{a.crop * 1e3:g}_v{a.voxel * 1e3:g}"
    tag += ("_eval" if a.protocol == "eval" else "") + ("_clouds" if a.scene == "clouds" else "")
    tag += f"_p{a.max_penetration * 1e3:g}" if a.max_penetration is not None else ""
    cache = Path(a.cache or f"out/observed_check/{tag}.npz")
    t = time.perf_counter()
    obs = observed_statuses(
        u, a.top, cache, a.data, config, a.workers, not a.no_progress, a.protocol, a.scene,
        a.max_penetration, a.extend,
    )  # fmt: skip
    result = dict(
        split=a.split, key=a.key, pairs=len(u["rows"]), top=a.top, extend=a.extend, records=files,
        protocol=dataclasses.asdict(_stability(a.protocol, a.max_penetration)), scene=a.scene,
        config=dataclasses.asdict(observed.ObservedConfig(**config)) | {"physics": None},
        seconds=round(time.perf_counter() - t, 1), rules=rules(u, obs, a.extend), confusion=confusion(u, obs),
    )  # fmt: skip
    for name, r in result["rules"].items():
        print(f"{name:>16}: {r['mean']:.2f} % ({r['pair_mean']:.2f} over pairs)"
              + (f", {r['changed']} answers changed" if "changed" in r else ""))  # fmt: skip
    print(json.dumps(result["confusion"], indent=1))
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    _cli.run(main)
