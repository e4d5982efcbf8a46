"""Held-out hanging success of the where-to-hang answer, end to end (docs/evaluation.md).

One run of :func:`omnihang_jax.where.load_where` per batch of pairs gives every answer the
figures need; each is simulated on the pair's TRUE meshes with the evaluation protocol
(``omnihang_jax.evaluate.protocol_stability``: 1 s from rest, > 3 mm initial penetration
fails). Success is "stable"; a figure is the mean over object categories of the per-category
success.

The answers of a pair (:data:`ANSWERS`):

* ``stage1_network``: the network's first Stage-1 proposal as predicted (the paper's reading);
* ``stage1``: the least penetrating of the K proposals, released ``stage1.ANSWER_LIFT`` up;
* ``stage1_2``: the least penetrating of the K Stage-2 poses, released ``stage2.ANSWER_LIFT`` up;
* ``stage1_3``: the rule's best candidate refined from a Stage-1 proposal (configs that refine
  from Stage 1 only);
* ``all_stages_unchecked``: the rule's best candidate;
* ``all_stages``: the answer after the observed-cloud check (= unchecked when the check is off).

The check and the simulations run in worker processes (each holding the asset library) while
the networks run the next batch. Records are one JSON line per pair, appended as pairs finish:
a killed run resumes where it stopped.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from omnihang_jax import where as where_mod
from omnihang_jax.refine import label_job, library_pool

__all__ = ["ANSWERS", "evaluate_where", "pair_files", "read_records", "summarise"]

ANSWERS = (
    "stage1_network",
    "stage1",
    "stage1_2",
    "stage1_3",
    "all_stages_unchecked",
    "all_stages",
)
VALIDATION_FRACTION = 0.1  # the trainers' validation objects (data.validation_objects)


def pair_files(data: str | os.PathLike, split: str, pairs: int | None = None) -> list[Path]:
    """The derived pair files of ``split``: "test" (held-out objects and supports),
    "validation" (the training split's validation objects, never trained on) or "train" (the
    training split less those). ``pairs``: at most this many, taken round robin over the object
    categories (a balanced prefix)."""
    from omnihang_jax import data as data_mod
    from omnihang_jax import dataset_bridge

    if split not in ("test", "validation", "train"):
        raise ValueError(f"split must be 'test', 'validation' or 'train', got {split!r}")
    _, derived = dataset_bridge.resolve_dataset_dir(data)
    files = dataset_bridge.derived_files(derived, "test" if split == "test" else "train")
    if split != "test":
        names = [data_mod.object_name_of(os.fspath(f)) for f in files]
        fit, val = data_mod.split_by_object(names, VALIDATION_FRACTION)
        files = [files[i] for i in (val if split == "validation" else fit)]
    by_cat: dict[str, list[Path]] = {}
    for f in files:
        obj = f.name.split("__")[0].split("_", 1)[1]
        by_cat.setdefault(obj.rsplit("_", 1)[0], []).append(f)
    groups = list(by_cat.values())
    order = [g[i] for i in range(max(map(len, groups), default=0)) for g in groups if i < len(g)]
    return order if pairs is None else order[:pairs]


def judge_pair(job: dict) -> dict:
    """Worker: the observed-cloud check of one pair, then its answers simulated on the true
    meshes. ``job``: object, support, clouds, ranked [C, 7], answers {name: [7]}, check (reach)."""
    from omnihang_jax.refine import worker_library
    from sim import kernels, observed

    lib = worker_library()
    support = lib.supports[job["support"]]
    pick, tried, note = 0, 0, None
    if job["check"] > 0:
        try:
            pick, status = observed.first_staying(
                job["clouds"], job["ranked"], support.floor_z, support.wall_y, job["check"]
            )
            tried = int((status != -2).sum())
        except ValueError as err:  # a malformed cloud: the check is skipped, said in the record
            note = f"check skipped: {err}"
    answers = dict(job["answers"])
    answers["all_stages"] = job["ranked"][pick]
    names = list(answers)
    poses = np.stack([np.asarray(answers[n], np.float64) for n in names])
    status, _ = label_job((job["object"], job["support"], poses))
    return dict(
        check_pick=int(pick), check_tried=tried, check_note=note,
        status={n: kernels.STATUS_NAMES[int(s)] for n, s in zip(names, status, strict=True)},
        poses={n: np.round(p, 6).tolist() for n, p in zip(names, poses, strict=True)},
    )  # fmt: skip


def read_records(path: str | os.PathLike) -> list[dict]:
    """The per-pair records of a run (a torn last line, from a kill, is dropped)."""
    rows = []
    if Path(path).exists():
        for line in Path(path).read_text().splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return rows


def evaluate_where(
    config: where_mod.WhereConfig,
    files: Sequence[str | os.PathLike],
    records_path: str | os.PathLike,
    seed: int = 0,
    batch: int = 8,
    workers: int = 0,
    progress: bool = True,
    dataset_dir: str | os.PathLike | None = None,
) -> list[dict]:
    """Run the answer on every pair file not yet in ``records_path`` and append its record;
    returns all records of the file (earlier ones included). ``workers`` > 0: that many
    processes check and simulate while the networks run; 0: in this process."""
    from tqdm.auto import tqdm

    from omnihang_jax import dataset_bridge, stage3

    files = [Path(f) for f in files]
    if not files:
        return read_records(records_path)
    if dataset_dir is None:
        dataset_dir, _ = dataset_bridge.resolve_dataset_dir(files[0].parent.parent)
    records_path = Path(records_path)
    records_path.parent.mkdir(parents=True, exist_ok=True)
    done = {int(r["pair_index"]) for r in read_records(records_path) if r.get("seed") == seed}
    todo = [f for f in files if _pair_index(f) not in done]
    if not todo:
        return read_records(records_path)
    where = where_mod.load_where(config)
    starts = config.pipeline.starts
    pool = library_pool(dataset_dir, workers)
    pending: list = []
    bar = tqdm(total=len(todo), desc=f"where ({len(done)} done)", disable=not progress)

    def drain(all_: bool) -> None:
        with records_path.open("a") as out:
            while pending and (all_ or not pool or pending[0][1].done()):
                meta, result = pending.pop(0)
                row = {**meta, **(result.result() if pool else result)}
                row["success"] = {n: s == "stable" for n, s in row["status"].items()}
                out.write(json.dumps(row) + "\n")
                out.flush()
                bar.update(1)

    try:
        for i in range(0, len(todo), batch):
            chunk = todo[i : i + batch]
            loaded = [dataset_bridge.load_pair_file(f) for f in chunk]
            padded = loaded + [loaded[0]] * (batch - len(chunk))  # one compiled shape
            clouds = stage3.stack_clouds([s for s, _ in padded])
            ids = [m["pair_index"] for _, m in padded]
            out = where.answer(clouds, ids, seed)
            for b, (sample, meta) in enumerate(loaded):
                pair = dict(object_points=np.asarray(sample.object_points),
                            object_normals=np.asarray(sample.object_normals),
                            support_points=np.asarray(sample.support_points),
                            support_normals=np.asarray(sample.support_normals))  # fmt: skip
                answers = {
                    "stage1_network": out.stage1[b, 0],
                    "stage1": where_mod.stage1_answer(
                        pair["object_points"], pair["support_points"], pair["support_normals"],
                        out.stage1[b],
                    ),
                    "stage1_2": where_mod.stage1_2_answer(
                        pair["object_points"], pair["support_points"], pair["support_normals"],
                        out.stage2[b],
                    ),
                }  # fmt: skip
                if "stage1" in starts:
                    answers["stage1_3"] = out.ranked[b][out.start[b] == "stage1"][0]
                answers["all_stages_unchecked"] = out.ranked[b, 0]
                job = dict(object=meta["object_name"], support=meta["support_name"], clouds=pair,
                           ranked=out.ranked[b], answers=answers, check=config.check)  # fmt: skip
                info = dict(
                    pair_index=int(meta["pair_index"]), seed=int(seed),
                    object=str(meta["object_name"]), support=str(meta["support_name"]),
                    category=str(meta["object_category"]), family=str(meta["support_family"]),
                )  # fmt: skip
                pending.append((info, pool.submit(judge_pair, job) if pool else judge_pair(job)))
            drain(all_=False)
        drain(all_=True)
    finally:
        bar.close()
        if pool is not None:
            pool.__exit__(None, None, None)
    return read_records(records_path)


def _pair_index(path: Path) -> int:
    return int(path.name.split("_", 1)[0])


def summarise(records: Sequence[dict]) -> dict:
    """Per answer: ``mean`` (over object categories, %), ``per_category``, ``pairs``; with
    several seeds also ``per_seed`` and ``std_over_seeds``."""
    seeds = sorted({int(r["seed"]) for r in records})
    out = {}
    for name in ANSWERS:
        rows = [r for r in records if name in r["success"]]
        if not rows:
            continue
        per_seed = {s: _category_mean([r for r in rows if r["seed"] == s], name) for s in seeds}
        per_seed = {s: v for s, v in per_seed.items() if v is not None}
        cats = sorted({r["category"] for r in rows})
        per_cat = {c: round(100 * float(np.mean([r["success"][name] for r in rows
                                                  if r["category"] == c])), 2)
                   for c in cats}  # fmt: skip
        entry = dict(
            mean=round(float(np.mean([v["mean"] for v in per_seed.values()])), 2),
            per_category=per_cat,
            pairs=len({r["pair_index"] for r in rows}),
        )
        if len(per_seed) > 1:
            entry["per_seed"] = {str(s): round(v["mean"], 2) for s, v in per_seed.items()}
            entry["std_over_seeds"] = round(
                float(np.std([v["mean"] for v in per_seed.values()])), 2
            )
        out[name] = entry
    return out


def _category_mean(rows: Sequence[dict], name: str) -> dict | None:
    if not rows:
        return None
    cats = sorted({r["category"] for r in rows})
    means = [np.mean([r["success"][name] for r in rows if r["category"] == c]) for c in cats]
    return dict(mean=100 * float(np.mean(means)))


def timing_note(t0: float, pairs: int) -> dict:
    """Wall seconds and pairs per second of a run since ``t0``."""
    dt = time.time() - t0
    return dict(wall_s=round(dt, 1), pairs_per_s=round(pairs / dt, 3) if dt > 0 else None)
