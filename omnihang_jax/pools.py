"""Pools: the answer pipeline's own refined candidates of training pairs, each simulated.

The answer's rankers (``weights/rankers/*``, ``experiments.train_ranker``) learn to order what
the pipeline gives them: the candidates CEM refines. A pool is those candidates of one pair,
made by the product's code, :func:`omnihang_jax.where.load_where` with :data:`POOL_CONFIG`
(the default pipeline, K = 10 proposals from Stages 1 and 2 on three views: 60 candidates,
ranked by V alone, no observed-cloud check), and every candidate simulated on the pair's TRUE
meshes with the evaluation protocol (``evaluate.protocol_stability``). Per pair, [C] each:

* ``poses`` [C, 7]: object frame in the support frame (xyz m + wxyz), in the rule's order;
* ``keys``: the rule's key with V (``selection.select_key`` of log V): candidate 0 is the
  pool's own answer, what the rankers have to beat;
* ``counts``: observed object points inside the observed support (``selection.inside_counts``
  at the rule's depth and radius, full clouds); *clear*: at most the rule's ``max_points``;
* ``status`` (``sim.kernels.STATUS_NAMES``) and ``stable``: the simulation's outcome;
* ``start`` (index into ``starts``) and ``proposal``: where each candidate comes from.

Pairs (:func:`pair_files`): the training split's derived pair files of TRAINING objects
("train": never one of the validation objects of ``data.split_by_object`` at
``where_eval.VALIDATION_FRACTION``), or of the validation objects ("validation": the rankers'
validation), a balanced prefix over object categories. :func:`build_pools` writes them as
compact npz shards (``shard_NNNNN.npz``, pairs stacked); pairs already in a shard of the folder
are skipped, so a killed run resumes. The simulations run in worker processes while the
networks answer the next batch. :func:`read_pools` stacks shards back into one table.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from omnihang_jax import refine, selection
from omnihang_jax import where as where_mod

__all__ = [
    "FIELDS",
    "POOL_CONFIG",
    "RULE",
    "build_pools",
    "category_means",
    "pair_files",
    "pooled_pairs",
    "read_pools",
    "rule_success",
    "write_shard",
]

# the default pipeline's candidates, ranked by V (no rankers), no observed-cloud check
POOL_CONFIG = dataclasses.replace(where_mod.DEFAULT, rankers=(), check=0)
RULE = where_mod.DEFAULT.pipeline.select  # the answer rule the rankers rank for
# per-candidate arrays of a shard ([pairs, C, ...]) and per-pair ones ([pairs])
FIELDS = ("poses", "keys", "counts", "status", "stable", "start", "proposal")
PAIR_FIELDS = ("pair_index", "pair_file", "category", "object", "support")


def pair_files(data: str | os.PathLike, split: str, pairs: int | None = None) -> list[Path]:
    """Derived pair files of the training split: "train" (training objects) or "validation"
    (the validation objects), round robin over the categories (``where_eval.pair_files``)."""
    from omnihang_jax import where_eval

    if split not in ("train", "validation"):
        raise ValueError(f"split must be 'train' or 'validation', got {split!r}")
    return where_eval.pair_files(data, split, pairs)


def _pair_index(path: Path) -> int:
    return int(Path(path).name.split("_", 1)[0])


# ----------------------------------------------------------------------------------------------
# Shards


def write_shard(path: str | os.PathLike, table: dict, starts: Sequence[str], seed: int,
                config: where_mod.WhereConfig) -> None:  # fmt: skip
    """One shard (atomic): ``table`` holds :data:`FIELDS` [n, C, ...] and :data:`PAIR_FIELDS`
    [n]; the pipeline's ``starts``, the seed and the config travel with it."""
    from sim import atomic

    n = len(table["pair_index"])
    arrays = {f: np.asarray(table[f]) for f in (*FIELDS, *PAIR_FIELDS)}
    for f in FIELDS:
        if arrays[f].shape[0] != n:
            raise ValueError(f"shard {path}: {f} holds {arrays[f].shape[0]} pairs, not {n}")
    arrays["poses"] = arrays["poses"].astype(np.float32)
    arrays["keys"] = arrays["keys"].astype(np.float32)
    arrays["counts"] = np.minimum(arrays["counts"], np.iinfo(np.int16).max).astype(np.int16)
    arrays["status"] = arrays["status"].astype(np.int8)
    arrays["stable"] = arrays["stable"].astype(bool)
    arrays["start"] = arrays["start"].astype(np.uint8)
    arrays["proposal"] = arrays["proposal"].astype(np.uint8)
    arrays["pair_index"] = arrays["pair_index"].astype(np.int64)
    for f in PAIR_FIELDS[1:]:
        arrays[f] = arrays[f].astype(str)
    atomic.savez(os.fspath(path), starts=np.asarray(list(starts)), seed=np.asarray(seed),
                 config=np.asarray(json.dumps(dataclasses.asdict(config))), **arrays)  # fmt: skip


def _shards(path: str | os.PathLike) -> list[Path]:
    path = Path(path)
    if path.is_dir():
        return sorted(path.glob("shard_*.npz"))
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such pool shard or folder")
    return [path]


def pooled_pairs(folder: str | os.PathLike) -> set[int]:
    """Pair indices already in the shards of ``folder``."""
    if not Path(folder).is_dir():
        return set()
    done: set[int] = set()
    for shard in _shards(folder):
        with np.load(shard) as z:
            done.update(int(i) for i in z["pair_index"])
    return done


def read_pools(paths: Sequence[str | os.PathLike] | str | os.PathLike) -> dict:
    """Shards (files, or folders of ``shard_*.npz``) -> one table: :data:`FIELDS` [N, C, ...],
    :data:`PAIR_FIELDS` [N] and ``starts``. Refuses pools of different sizes C, a pair twice,
    non-finite poses."""
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    shards = [s for p in paths for s in _shards(p)]
    if not shards:
        raise FileNotFoundError(f"no pool shards in {[os.fspath(p) for p in paths]}")
    parts, starts = [], None
    for shard in shards:
        with np.load(shard) as z:
            parts.append({f: z[f] for f in (*FIELDS, *PAIR_FIELDS)})
            starts = [str(s) for s in z["starts"]] if starts is None else starts
    sizes = {p["poses"].shape[1] for p in parts}
    if len(sizes) != 1:
        raise ValueError(f"pools of different sizes {sorted(sizes)}: pools of one pipeline only")
    table = {f: np.concatenate([p[f] for p in parts]) for f in (*FIELDS, *PAIR_FIELDS)}
    index, count = np.unique(table["pair_index"], return_counts=True)
    if (count > 1).any():
        raise ValueError(f"pair {int(index[count > 1][0])} is in more than one shard")
    if not np.all(np.isfinite(table["poses"])):
        raise ValueError("non-finite candidate poses in the pools")
    table["starts"] = np.asarray(starts)
    return table


# ----------------------------------------------------------------------------------------------
# Scores


def category_means(categories: Sequence[str], outcomes) -> dict:
    """Per pair a success -> ``mean`` over object categories (the figure everywhere),
    ``pair_mean``, ``per_category`` (percent) and ``pairs``."""
    by_cat: dict[str, list[bool]] = {}
    for c, ok in zip(categories, np.asarray(outcomes, bool), strict=True):
        by_cat.setdefault(str(c), []).append(bool(ok))
    per_cat = {c: 100.0 * float(np.mean(x)) for c, x in sorted(by_cat.items())}
    return {
        "mean": float(np.mean(list(per_cat.values()))) if per_cat else float("nan"),
        "pair_mean": 100.0 * float(np.mean([x for xs in by_cat.values() for x in xs])),
        "per_category": per_cat,
        "pairs": sum(len(x) for x in by_cat.values()),
    }


def rule_success(pools: dict, scores, rule: selection.SelectConfig = RULE) -> dict:
    """The answer rule's success when ``scores`` [N, C] (e.g. log P(hang)) rank the pools:
    the best-scored clear candidate, else the one with the fewest inside points."""
    picks = np.asarray(selection.select(np.asarray(scores, np.float32), pools["counts"], rule))
    return category_means(pools["category"], pools["stable"][np.arange(len(picks)), picks])


# ----------------------------------------------------------------------------------------------
# Building


def simulate(job: tuple[str, str, np.ndarray]) -> np.ndarray:
    """Worker: (object, support, poses [C, 7]) -> [C] int8 statuses on the true meshes."""
    return refine.label_job(job)[0]


@functools.lru_cache(maxsize=2)
def _counter(depth: float, radius: float):
    import jax

    def one(o, s, n, poses):
        return selection.inside_counts(o, s, n, poses, depth, radius)

    return jax.jit(jax.vmap(one))


def build_pools(
    files: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    config: where_mod.WhereConfig = POOL_CONFIG,
    seed: int = 0,
    batch: int = 8,
    workers: int = 0,
    shard_pairs: int = 64,
    progress: bool = True,
    dataset_dir: str | os.PathLike | None = None,
) -> dict:
    """The pools of every pair file not yet in ``out``'s shards (module docstring): the answer
    of ``config`` in batches of ``batch`` pairs, its candidates simulated by ``workers``
    processes (0: in this process), a shard written every ``shard_pairs`` pairs. Returns
    ``{"pairs": written now, "skipped": already pooled, "shards": written now}``."""
    import jax.numpy as jnp
    from tqdm.auto import tqdm

    from omnihang_jax import dataset_bridge, stage3

    files = [Path(f) for f in files]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    done = pooled_pairs(out)
    todo = [f for f in files if _pair_index(f) not in done]
    summary = {"pairs": 0, "skipped": len(files) - len(todo), "shards": 0}
    if not todo:
        return summary
    if dataset_dir is None:
        dataset_dir, _ = dataset_bridge.resolve_dataset_dir(todo[0].parent.parent)
    where = where_mod.load_where(config)
    starts = list(config.pipeline.starts)
    count = _counter(RULE.depth, RULE.radius)
    pool = refine.library_pool(dataset_dir, workers)
    shard_no = max((int(s.stem.split("_")[1]) + 1 for s in _shards(out)), default=0)
    rows: list[dict] = []
    pending: list = []  # (row without status, future or status)
    bar = tqdm(total=len(todo), desc=f"pools ({len(done)} done)", disable=not progress)

    def flush(force: bool) -> None:
        nonlocal rows, shard_no
        while rows and (force or len(rows) >= shard_pairs):
            part, rows = rows[:shard_pairs], rows[shard_pairs:]
            table = {f: np.stack([r[f] for r in part]) for f in (*FIELDS, *PAIR_FIELDS)}
            write_shard(out / f"shard_{shard_no:05d}.npz", table, starts, seed, config)
            shard_no += 1
            summary["shards"] += 1
            summary["pairs"] += len(part)

    def drain(all_: bool) -> None:
        while pending and (all_ or pool is None or pending[0][1].done()):
            row, status = pending.pop(0)
            status = np.asarray(status.result() if pool is not None else status, np.int8)
            rows.append({**row, "status": status, "stable": status == 0})  # kernels.STABLE
            bar.update(1)
        flush(force=False)

    try:
        for i in range(0, len(todo), batch):
            chunk = todo[i : i + batch]
            loaded = [dataset_bridge.load_pair_file(f) for f in chunk]
            padded = loaded + [loaded[0]] * (batch - len(chunk))  # one compiled shape
            clouds = jax_tree(jnp.asarray, stage3.stack_clouds([s for s, _ in padded]))
            answer = where.answer(clouds, [m["pair_index"] for _, m in padded], seed)
            counts = np.asarray(count(clouds.object_points, clouds.support_points,
                                      clouds.support_normals,
                                      jnp.asarray(answer.ranked, jnp.float32)))  # fmt: skip
            for b, ((_, meta), f) in enumerate(zip(loaded, chunk, strict=True)):
                row = dict(
                    poses=answer.ranked[b], keys=answer.keys[b], counts=counts[b],
                    start=np.asarray([starts.index(s) for s in answer.start[b]]),
                    proposal=answer.proposal[b], pair_index=int(meta["pair_index"]),
                    pair_file=f.name, category=str(meta["object_category"]),
                    object=str(meta["object_name"]), support=str(meta["support_name"]),
                )  # fmt: skip
                job = (row["object"], row["support"], answer.ranked[b])
                pending.append((row, pool.submit(simulate, job) if pool else simulate(job)))
            drain(all_=False)
        drain(all_=True)
        flush(force=True)
    finally:
        bar.close()
        if pool is not None:
            pool.__exit__(None, None, None)
    return summary


def jax_tree(fn, tree):
    import jax

    return jax.tree.map(fn, tree)
