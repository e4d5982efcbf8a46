"""Bridge from the dataset engine (``sim.dataset``: labels in shards) to the networks'
``HangSample`` files (``omnihang_jax.data.load_hang_dataset``).

``derive_dataset(dataset_dir)`` reads ``DIR/recipe.json`` + ``DIR/shards/*.npz``, rebuilds the
asset library from the recipe, and for every pair with at least one stable pose writes::

    DIR/derived/<split>/<pair_index:05d>_<object>__<support>.npz

whose keys are the ``HangSample`` fields (unbatched: object cloud in the OBJECT frame, support
cloud in the SUPPORT frame = the scene's world frame, stable poses = object frame in support
frame, xyz + quaternion wxyz) plus metadata used by the evaluation (``pair_index``,
``object_name``, ``support_name``, ``object_category``, ``support_family``, ``split``).
The split is the recipe's pair list's (a pair is "test" when its object or its support is
held out). Files are written to a temporary name and renamed, so an existing file is
complete and is skipped on a rerun (resumable). ``DIR/derived/derived.json`` summarises the
run (counts per split, pairs skipped for lack of stable poses, the source dataset).

This module imports both sides (``sim`` for physics and ray casting, ``omnihang_jax.data``
for the contract); neither side imports it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from omnihang_jax.config import config_from_dict
from omnihang_jax.data import HangSample, make_hang_sample

__all__ = [
    "DERIVED_DIRNAME",
    "META_KEYS",
    "dataset_config_from_recipe",
    "read_recipe",
    "pair_file_name",
    "derive_dataset",
    "load_pair_file",
    "derived_files",
    "resolve_dataset_dir",
]

DERIVED_DIRNAME = "derived"
META_KEYS = (
    "pair_index",
    "object_name",
    "support_name",
    "object_category",
    "support_family",
    "split",
)


def read_recipe(dataset_dir: str | os.PathLike) -> dict:
    """The dataset's ``recipe.json``; FileNotFoundError with the expected layout if absent."""
    path = Path(dataset_dir) / "recipe.json"
    if not path.exists():
        raise FileNotFoundError(
            f"{path} not found: {os.fspath(dataset_dir)!r} is not a generated dataset "
            "(expected recipe.json + shards/shard_*.npz, written by "
            "`python -m experiments.generate_dataset --preset demo --out DIR`)"
        )
    return json.loads(path.read_text())


def dataset_config_from_recipe(recipe: dict):
    """Rebuild the ``sim.dataset.DatasetConfig`` the dataset was generated with.

    Raises ValueError if the rebuilt config does not serialise back to the recipe's (a field
    was renamed or added since the dataset was made), so derived arrays never silently come
    from different camera or library settings.
    """
    from sim import dataset, dataset_io

    saved = dataset_io.upgrade_config_json(recipe["config"])  # fields added since: defaults
    config = config_from_dict(dataset.DatasetConfig, saved)
    diff = dataset_io.config_differences(dataset_io.config_json(config), saved)
    if diff:
        raise ValueError(f"recipe config does not round-trip through DatasetConfig: fields {diff}")
    return config


def pair_file_name(pair_index: int, object_name: str, support_name: str) -> str:
    return f"{pair_index:05d}_{object_name}__{support_name}.npz"


def interleave_by_category(jobs: list[tuple[dict, str]], pairs) -> list[tuple[dict, str]]:
    """``jobs`` (record, path) reordered round robin over the records' object categories
    (each category in pair-index order; categories alphabetically within a round)."""
    by_cat: dict[str, list] = {}
    for job in jobs:
        obj_name = pairs[int(job[0]["pair_index"])][0]
        by_cat.setdefault(obj_name.rsplit("_", 1)[0], []).append(job)
    queues = [by_cat[c] for c in sorted(by_cat)]
    return [q[i] for i in range(max(map(len, queues), default=0)) for q in queues if i < len(q)]


def _records(dataset_dir: Path) -> list[dict]:
    from sim import dataset

    shards = sorted((dataset_dir / "shards").glob("shard_*.npz"))
    if not shards:
        raise FileNotFoundError(
            f"no shards in {dataset_dir / 'shards'}: generate (or resume) the dataset first "
            f"(`python -m experiments.generate_dataset --out {dataset_dir}`)"
        )
    return dataset.load_records(dataset_dir)


_WORKER: dict = {}


def scaled_config(config, camera_scale: float = 1.0):
    """The dataset config with the depth camera's resolution scaled (same field of view,
    same resampled point count): ``camera_scale`` 0.5 renders 320 x 240 instead of 640 x 480,
    ~4x fewer rays. The clouds are the same visible surface sampled on a coarser pixel grid
    (2.2 instead of 1.1 mm between rays at 0.5 m, against ~5 mm between the 4096 resampled
    points)."""
    if camera_scale == 1.0:
        return config
    if not 0.1 <= camera_scale <= 1.0:
        raise ValueError(f"camera_scale must be in [0.1, 1], got {camera_scale}")
    cam = config.camera
    cam = dataclasses.replace(
        cam, width=round(cam.width * camera_scale), height=round(cam.height * camera_scale)
    )
    return dataclasses.replace(config, camera=cam)


def _worker_init(
    recipe: dict, clouds_only: bool = False, camera_scale: float = 1.0, view: int = 0
) -> None:
    from sim.library import build_library

    config = scaled_config(dataset_config_from_recipe(recipe), camera_scale)
    library = build_library(config.library, progress=False)
    _WORKER.update(
        library=library, config=config, pairs=recipe["pairs"], clouds_only=clouds_only, view=view
    )


def _derive_one(job: tuple[dict, str]) -> None:
    from sim import dataset

    record, path = job
    w = _WORKER
    contacts = not w.get("clouds_only", False)
    obj_name, sup_name, split = w["pairs"][int(record["pair_index"])]
    obj, sup = w["library"].objects[obj_name], w["library"].supports[sup_name]
    derived = dataset.derive_pair(
        obj, sup, record, w["config"], contacts=contacts, view=w.get("view", 0)
    )
    sample = make_hang_sample(**derived, stable_poses=record["stable_poses"])
    meta = dict(
        contact_maps=np.bool_(contacts),
        pair_index=np.int64(int(record["pair_index"])),
        object_name=np.str_(obj_name),
        support_name=np.str_(sup_name),
        object_category=np.str_(obj.category),
        support_family=np.str_(sup.category),
        split=np.str_(split),
    )
    from sim import atomic

    atomic.savez(path, **sample._asdict(), **meta)


def pairs_per_object(pairs: list, split: str, n: int, seed: int = 0) -> set[int]:
    """At most ``n`` pair indices of every object of ``split`` (drawn at random, seeded), from
    the recipe's pair list [(object, support, split), ...]: a derive that covers every object
    at a fraction of the pairs (inputs that read the object alone, e.g. the object-frame
    network's)."""
    import random

    by_object: dict[str, list[int]] = {}
    for index, (obj, _, s) in enumerate(pairs):
        if s == split:
            by_object.setdefault(obj, []).append(index)
    rng = random.Random(seed)
    chosen: set[int] = set()
    for obj in sorted(by_object):
        chosen.update(rng.sample(by_object[obj], min(n, len(by_object[obj]))))
    return chosen


def derive_dataset(
    dataset_dir: str | os.PathLike,
    out_dir: str | os.PathLike | None = None,
    splits: tuple[str, ...] = ("train", "test"),
    limit: int | None = None,
    progress: bool = True,
    workers: int = 1,
    pair_indices: set[int] | None = None,
    clouds_only: bool = False,
    camera_scale: float = 1.0,
    view: int = 0,
) -> dict:
    """Write one HangSample ``.npz`` per pair with stable poses (see module docstring).

    ``pair_indices``: derive only these pairs (e.g. the pairs of an earlier evaluation).

    ``clouds_only``: clouds, normals and stable poses without contact maps / pairs (zeros,
    ``contact_maps=False`` in the file; ~1.7x less CPU per pair), written to ``<split>_clouds/`` so they
    never mix with the full files: enough for Stage 1, V and the NCE, not for Stage 2.

    ``camera_scale`` < 1 renders the clouds at that fraction of the recipe's resolution
    (``scaled_config``; only with ``clouds_only``, into ``<split>_clouds_r<percent>/``): a
    cheaper derive of training inputs (the ray casting is most of a clouds-only derive);
    held-out pairs keep the recipe's camera.

    ``view`` k >= 1 renders each pair from another of its candidate views (``sim.dataset.
    derive_pair``; only with ``clouds_only``, into ``<split>_clouds[_r<percent>]_v<k>/``): more
    views of the same training pairs.

    ``workers`` > 1 derives pairs in that many processes (ray casting and contact maps are
    single-threaded NumPy/MuJoCo; the files are identical either way).

    dataset_dir: a generated dataset (recipe.json + shards/). out_dir: default
    ``dataset_dir/derived``. splits: which splits to derive. limit: at most this many new
    files (smoke runs). Returns the summary also written to ``out_dir/derived.json``.
    """
    from sim.library import build_library

    dataset_dir = Path(dataset_dir)
    recipe = read_recipe(dataset_dir)
    if camera_scale != 1.0 and not clouds_only:
        raise ValueError("camera_scale != 1 is only for clouds-only derives (training inputs)")
    if view and not clouds_only:
        raise ValueError("view >= 1 is only for clouds-only derives (training inputs)")
    config = scaled_config(dataset_config_from_recipe(recipe), camera_scale)

    def folder(split: str) -> str:  # e.g. train, train_clouds, train_clouds_r50_v1
        name = f"{split}_clouds" if clouds_only else split
        name += f"_r{round(camera_scale * 100)}" if camera_scale != 1.0 else ""
        return name + (f"_v{view}" if view else "")

    out = Path(out_dir) if out_dir is not None else dataset_dir / DERIVED_DIRNAME
    records = _records(dataset_dir)
    pairs = recipe["pairs"]

    t0 = time.time()
    written = skipped_existing = 0
    no_stable: list[int] = []
    counts = {s: 0 for s in splits}
    jobs: list[tuple[dict, str]] = []
    for record in records:
        index = int(record["pair_index"])
        obj_name, sup_name, split = pairs[index]
        if recipe["objects"][int(record["object_id"])] != obj_name or (
            recipe["supports"][int(record["support_id"])] != sup_name
        ):
            raise ValueError(f"shard record {index} does not match the recipe's pair list")
        if split not in splits or (pair_indices is not None and index not in pair_indices):
            continue
        if len(record["stable_poses"]) == 0:
            no_stable.append(index)
            continue
        path = out / folder(split) / pair_file_name(index, obj_name, sup_name)
        counts[split] += 1
        if path.exists():
            skipped_existing += 1
            continue
        jobs.append((record, os.fspath(path)))
    # round robin over object categories, so a derive cut short (a time budget, --limit)
    # still covers every category present instead of the alphabetically first ones
    jobs = interleave_by_category(jobs, pairs)
    if limit is not None:
        jobs = jobs[:limit]
    bar = tqdm(total=len(jobs), desc="derive", unit="pair", disable=not progress)
    if workers <= 1 and jobs:
        library = build_library(config.library, progress=False)
        _WORKER.update(
            library=library, config=config, pairs=pairs, clouds_only=clouds_only, view=view
        )
        for job in jobs:
            _derive_one(job)
            written += 1
            bar.update(1)
    elif jobs:
        from sim.workers import spawn_pool

        with spawn_pool(workers, _worker_init, (recipe, clouds_only, camera_scale, view)) as pool:
            for _ in pool.imap_unordered(_derive_one, jobs, chunksize=4):
                written += 1
                bar.update(1)
    bar.close()
    summary = {
        "source": os.fspath(dataset_dir.resolve()),
        "preset": recipe.get("preset"),
        "pairs_in_shards": len(records),
        "pairs_planned": len(pairs),
        "files_per_split": {folder(k): v for k, v in counts.items()},
        "clouds_only": clouds_only,
        "camera_resolution": [config.camera.width, config.camera.height],
        "view": view,
        "written_this_run": written,
        "skipped_existing": skipped_existing,
        "pairs_without_stable_poses": len(no_stable),
        "points_per_cloud": config.camera.n_points,
        "derive_s_this_run": round(time.time() - t0, 2),
        "workers": workers,
    }
    out.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out, prefix=".tmp_")
    with os.fdopen(fd, "w") as fh:
        json.dump(summary, fh, indent=1)
    os.replace(tmp, out / "derived.json")
    return summary


def load_pair_file(path: str | os.PathLike) -> tuple[HangSample, dict]:
    """One derived pair: (unbatched HangSample, metadata dict with the ``META_KEYS``)."""
    from omnihang_jax.data import _load_npz_sample

    sample = _load_npz_sample(os.fspath(path))
    with np.load(path) as f:
        missing = [k for k in META_KEYS if k not in f.files]
        if missing:
            raise ValueError(f"{path}: no pair metadata {missing}; derive it with derive_dataset")
        meta = {k: f[k].item() for k in META_KEYS}
    meta["pair_index"] = int(meta["pair_index"])
    return sample, meta


def resolve_dataset_dir(data: str | os.PathLike) -> tuple[Path, Path]:
    """(dataset_dir with recipe.json, derived_dir) from either of the two folders."""
    data = Path(data)
    if (data / "recipe.json").exists():
        return data, data / DERIVED_DIRNAME
    summary = data / "derived.json"
    if summary.exists():
        return Path(json.loads(summary.read_text())["source"]), data
    raise FileNotFoundError(
        f"{os.fspath(data)!r} is neither a generated dataset (recipe.json) nor a derived folder "
        "(derived.json): run `python -m experiments.derive_dataset --data DIR` first"
    )


def derived_files(derived_dir: str | os.PathLike, split: str) -> list[Path]:
    """Sorted pair files of one split; FileNotFoundError if there are none."""
    files = sorted(Path(derived_dir, split).glob("*.npz"))
    if not files:
        raise FileNotFoundError(
            f"no derived pairs in {Path(derived_dir, split)}: run "
            "`python -m experiments.derive_dataset --data DIR` first"
        )
    return files
