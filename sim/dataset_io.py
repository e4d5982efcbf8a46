"""The dataset's files: the shard format, the recipe's config as JSON, the dataset card and
one pose exported for other engines.

Format (version :data:`FORMAT`)
-------------------------------
``DIR/recipe.json``         the config, library config, versions: everything needed to rebuild.
``DIR/shards/shard_NNNNN.npz``  labels of ``shard_size`` consecutive pairs (compressed):
    ``pair_index [P]``, ``object_id [P]``, ``support_id [P]`` (indices into the recipe's
    name lists), ``pair_seed [P] uint64``, ``mass [P]``, ``friction [P]``,
    ``object_eye [P, 3]``, ``support_eye [P, 3]`` (chosen camera positions, float32),
    ``n_candidates``, ``n_penetrating``, ``n_fallen``, ``n_stable_raw``, ``n_takeoff_rejected``
    ``[P]`` (counts), ``stable_offsets [P + 1]`` + ``stable_poses`` (quantised, below),
    ``negative_offsets [P + 1]`` + ``negative_kept`` (which of the pair's
    ``sim.dataset.negative_candidates`` are near misses), ``collision_offsets [P + 1]`` +
    ``collision_kept`` + ``collision_label`` (colliding) for the pair's
    ``sim.dataset.collision_poses``; all three as packed bits (``np.packbits``). Negative and
    collision candidates are *not* stored but regenerated from ``pair_seed`` (and, for the
    negatives, the stored stable poses).
    Poses are position (m) + quaternion (w, x, y, z) of the object frame in the support
    frame, stored quantised (``stable_position [S, 3] int16`` in 0.1 mm steps,
    ``stable_quaternion [S, 4] int16`` of q x 32767) so the paper-scale labels fit well under
    50 MB; :func:`unpack` returns float32 ``stable_poses`` [S, 7]. Every shard is written to a temporary file and renamed, so a shard that exists is
    complete; a killed job loses at most the shard in progress.
Heavy arrays (partial clouds, contact maps, contact pairs) are derived from the labels by
``sim.dataset.derive_pair`` (deterministic ray casting on the CPU) and cached by the caller.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import os
import platform
from pathlib import Path

import numpy as np

from sim import atomic, kernels
from sim.library import Library

FORMAT = 2
POSITION_STEP = 1e-4  # m: stored positions are int16 multiples of 0.1 mm (range +-3.27 m)
QUAT_SCALE = 32767  # stored quaternions are int16 of q * 32767 (error < 3e-5)


def quantise_poses(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[S, 7] float poses -> (positions [S, 3] int16, quaternions [S, 4] int16)."""
    poses = np.asarray(poses, np.float64).reshape(-1, 7)
    steps = np.round(poses[:, :3] / POSITION_STEP)
    if np.abs(steps).max(initial=0) > np.iinfo(np.int16).max:
        raise ValueError(
            f"pose position beyond +-3.27 m cannot be stored: {np.abs(poses[:, :3]).max():.3f} m"
        )
    pos = steps.astype(np.int16)
    quat = poses[:, 3:] / np.maximum(np.linalg.norm(poses[:, 3:], axis=1, keepdims=True), 1e-12)
    return pos, np.round(quat * QUAT_SCALE).astype(np.int16)


def dequantise_poses(pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Inverse of :func:`quantise_poses`: [S, 7] float32 with unit quaternions."""
    q = quat.astype(np.float64) / QUAT_SCALE
    q /= np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    return np.concatenate([pos.astype(np.float64) * POSITION_STEP, q], axis=1).astype(np.float32)


def pack_shard(records: list[dict], indices: list[int], ids: list[tuple[int, int, int]]) -> dict:
    out: dict[str, np.ndarray] = {
        "pair_index": np.asarray(indices, np.int64),
        "object_id": np.asarray([i[0] for i in ids], np.int32),
        "support_id": np.asarray([i[1] for i in ids], np.int32),
        "pair_seed": np.asarray([i[2] for i in ids], np.uint64),
    }
    for key in ("n_candidates", "n_penetrating", "n_fallen", "n_stable_raw", "n_takeoff_rejected"):
        out[key] = np.asarray([r[key] for r in records], np.int32)
    for key in ("mass", "friction"):
        out[key] = np.asarray([r[key] for r in records], np.float32)
    for key in ("object_eye", "support_eye"):
        out[key] = np.stack([r[key] for r in records]).astype(np.float32)
    poses = [np.asarray(r["stable_poses"]).reshape(-1, 7) for r in records]
    out["stable_offsets"] = np.concatenate([[0], np.cumsum([len(p) for p in poses])]).astype(
        np.int64
    )
    stacked = np.concatenate(poses) if poses else np.zeros((0, 7))
    out["stable_position"], out["stable_quaternion"] = quantise_poses(stacked)
    for name, fields in (
        ("negative", ("negative_kept",)),
        ("collision", ("collision_kept", "collision_label")),
    ):
        lengths = [len(r[fields[0]]) for r in records]
        out[f"{name}_offsets"] = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
        for f in fields:  # one bit per label
            out[f] = np.packbits(np.concatenate([np.asarray(r[f], bool) for r in records]))
    return out


def unpack(shard: dict) -> list[dict]:
    """Per-pair records from a loaded shard (``np.load`` result or dict)."""
    scalars = (
        "pair_index",
        "object_id",
        "support_id",
        "pair_seed",
        "mass",
        "friction",
        "object_eye",
        "support_eye",
        "n_candidates",
        "n_penetrating",
        "n_fallen",
        "n_stable_raw",
        "n_takeoff_rejected",
    )
    groups = {
        "negative_kept": "negative",
        "collision_kept": "collision",
        "collision_label": "collision",
    }
    bits = {
        f: np.unpackbits(shard[f], count=int(shard[f"{g}_offsets"][-1])).astype(bool)
        for f, g in groups.items()
    }
    recs = []
    for i in range(len(shard["pair_index"])):
        r = {k: shard[k][i] for k in scalars}
        a, b = shard["stable_offsets"][i], shard["stable_offsets"][i + 1]
        r["stable_poses"] = dequantise_poses(
            shard["stable_position"][a:b], shard["stable_quaternion"][a:b]
        )
        for f, g in groups.items():
            a, b = shard[f"{g}_offsets"][i], shard[f"{g}_offsets"][i + 1]
            r[f] = bits[f][a:b]
        recs.append(r)
    return recs


def config_json(config) -> dict:
    """The config as the JSON-able dict stored in ``recipe.json``."""
    return json.loads(json.dumps(dataclasses.asdict(config), default=str))


def upgrade_config_json(saved: dict, defaults: dict | None = None) -> dict:
    """A recipe's config with fields added to :class:`DatasetConfig` since it was written
    filled in with their defaults (recursively), so older datasets stay resumable and
    derivable. Fields that no longer exist are kept, so a comparison still fails on them."""
    if defaults is None:
        from sim.dataset import DatasetConfig

        defaults = config_json(DatasetConfig())
    out = dict(saved)
    for key, value in defaults.items():
        if key not in out:
            out[key] = value
        elif isinstance(value, dict) and isinstance(out[key], dict):
            out[key] = upgrade_config_json(out[key], value)
    return out


def config_differences(a: dict, b: dict, prefix: str = "") -> list[str]:
    """Dotted names of the fields where two config dicts differ."""
    diff = []
    for key in sorted(set(a) | set(b)):
        va, vb = a.get(key, "<missing>"), b.get(key, "<missing>")
        if isinstance(va, dict) and isinstance(vb, dict):
            diff += config_differences(va, vb, f"{prefix}{key}.")
        elif va != vb:
            diff.append(f"{prefix}{key}")
    return diff


def device_name() -> str:
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"{platform.processor() or platform.machine()} x{cores} ({platform.node()})"


def dataset_card(
    out: Path,
    library: Library,
    pairs,
    rec: dict,
    timings: dict,
    backend: str,
    new_pairs: int,
    records: list[dict],
    runs: list[dict],
) -> dict:

    by_index = {int(r["pair_index"]): r for r in records}
    n_stable = {i: len(r["stable_poses"]) for i, r in by_index.items()}
    with_stable = [i for i, n in n_stable.items() if n > 0]
    train_pairs = [i for i in with_stable if pairs[i][2] == "train"]
    test_pairs = [i for i in with_stable if pairs[i][2] == "test"]
    train_objects = sorted({pairs[i][0] for i in train_pairs})
    test_objects = sorted(
        {pairs[i][0] for i in test_pairs if library.split_of(pairs[i][0]) == "test"}
    )
    leaked = set(train_objects) & {n for n in library.objects if library.split_of(n) == "test"}
    if leaked:
        raise AssertionError(f"test objects leaked into training pairs: {sorted(leaked)[:5]}")
    per_cat: dict[str, dict] = {}
    per_fam: dict[str, dict] = {}
    for i, r in by_index.items():
        o, s, _ = pairs[i]
        for table, key in (
            (per_cat, library.objects[o].category),
            (per_fam, library.supports[s].category),
        ):
            e = table.setdefault(
                key, dict(pairs=0, pairs_with_stable_poses=0, stable_poses=0, candidates=0)
            )
            e["pairs"] += 1
            e["pairs_with_stable_poses"] += int(n_stable[i] > 0)
            e["stable_poses"] += n_stable[i]
            e["candidates"] += int(r["n_candidates"])
    tot = lambda k: int(sum(int(r[k]) for r in records))  # noqa: E731
    device = platform.processor() or platform.machine()
    card = {
        "format": FORMAT,
        "labels_version": rec.get("labels_version", 1),
        "preset": rec["preset"],
        "pairs_total": len(pairs),
        "pairs_done": len(records),
        "pairs_with_stable_poses": len(with_stable),
        "train_pairs": len(train_pairs),
        "test_pairs": len(test_pairs),
        "train_objects": train_objects,
        "test_objects": test_objects,
        "objects": len({p[0] for p in pairs}),
        "supports": len({p[1] for p in pairs}),
        "stable_poses": int(sum(n_stable.values())),
        "negative_poses": int(sum(int(r["negative_kept"].sum()) for r in records)),
        "collision_labels": int(sum(int(r["collision_kept"].sum()) for r in records)),
        "colliding_fraction": float(
            sum(int(r["collision_label"].sum()) for r in records)
            / max(1, sum(int(r["collision_kept"].sum()) for r in records))
        ),
        "candidates": tot("n_candidates"),
        "stable_yield": tot("n_stable_raw") / max(1, tot("n_candidates")),
        "penetrating_fraction": tot("n_penetrating") / max(1, tot("n_candidates")),
        "takeoff_rejections": tot("n_takeoff_rejected"),
        "per_category": per_cat,
        "per_family": per_fam,
        "timings": {
            **timings,
            "pairs_this_run": new_pairs,
            "pairs_per_min_this_run": 60 * new_pairs / max(timings["generate_s"], 1e-9),
        },
        "runs": runs,
        # seconds per stage of generate_pair, summed over the logged runs (CPU-seconds of
        # all workers): where generation time goes
        "time_per_stage_s": _sum_stage_seconds(runs),
        "backend": backend,
        "mujoco_warnings_this_run": dict(
            kernels.MUJOCO_WARNINGS
        ),  # diverged worlds, labelled failures
        "device": f"{device} x{os.cpu_count()} ({platform.platform()})",
        "versions": rec["versions"],
    }
    atomic.write_text(out / "dataset_card.json", json.dumps(card, indent=1))
    atomic.write_text(out / "dataset_card.md", card_markdown(card))
    return card


def _sum_stage_seconds(runs: list[dict]) -> dict:
    total: collections.Counter = collections.Counter()
    for r in runs:
        total.update(r.get("stage_seconds", {}))
    return {k: round(v, 1) for k, v in sorted(total.items())}


def card_markdown(card: dict) -> str:
    lines = [
        f"# Dataset card ({card['preset']})",
        "",
        f"- pairs with stable poses: {card['pairs_with_stable_poses']} of {card['pairs_done']} generated ({card['pairs_total']} planned)",
        f"- train / test pairs: {card['train_pairs']} / {card['test_pairs']}",
        f"- objects / supports: {card['objects']} / {card['supports']}",
        f"- stable poses kept: {card['stable_poses']}; negatives: {card['negative_poses']}; collision labels: {card['collision_labels']} ({100 * card['colliding_fraction']:.1f}% colliding)",
        f"- candidates: {card['candidates']}; stable yield {100 * card['stable_yield']:.2f}%; penetrating {100 * card['penetrating_fraction']:.1f}%; take-off rejections {card['takeoff_rejections']}",
        (
            f"- last run: backend {card['backend']} on {card['device']}, "
            f"{card['timings']['pairs_per_min_this_run']:.1f} pairs/min"
            if card["timings"].get("pairs_this_run")
            else f"- last run generated nothing (card rewritten on {card['device']}); "
            "the runs that made the shards are listed below"
        ),
        "- time per stage (CPU-s over logged runs): "
        + (", ".join(f"{k} {v:.0f}" for k, v in card.get("time_per_stage_s", {}).items()) or "-"),
        "",
        "| run | pairs | minutes | pairs/min | backend | workers | part | device |",
        "|---|---|---|---|---|---|---|---|",
        *(
            f"| {r['date']} | {r['pairs']} | {r['seconds'] / 60:.1f} | {r['pairs_per_min']:.1f} | {r.get('backend', 'cpu')} | {r['workers']} | {'/'.join(map(str, r['part']))} | {r['device']} |"
            for r in card.get("runs", [])
        ),
        "",
        "| category | pairs | with stable poses | stable poses | candidates |",
        "|---|---|---|---|---|",
    ]
    for name, e in sorted(card["per_category"].items()):
        lines.append(
            f"| {name} | {e['pairs']} | {e['pairs_with_stable_poses']} | {e['stable_poses']} | {e['candidates']} |"
        )
    lines += [
        "",
        "| support family | pairs | with stable poses | stable poses | candidates |",
        "|---|---|---|---|---|",
    ]
    for name, e in sorted(card["per_family"].items()):
        lines.append(
            f"| {name} | {e['pairs']} | {e['pairs_with_stable_poses']} | {e['stable_poses']} | {e['candidates']} |"
        )
    return "\n".join(lines) + "\n"


def export_sample(
    library: Library, record: dict, pairs, out_dir: str | os.PathLike, pose_index: int = 0
) -> Path:
    """Write one stable pose as ``object.obj`` (object frame), ``support.obj`` (support frame)
    and ``pose.json``, so other engines can check it.

    Convention: the pose maps object-frame points into the support frame,
    ``p_support = R @ p_object + t``; ``quaternion_wxyz`` is scalar-first (MuJoCo order),
    ``quaternion_xyzw`` scalar-last (PyBullet/SciPy order), metres throughout.
    """
    from scipy.spatial.transform import Rotation

    obj_name, sup_name, split = pairs[int(record["pair_index"])]
    pose = np.asarray(record["stable_poses"][pose_index], float)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    library.objects[obj_name].mesh.export(out / "object.obj")
    library.supports[sup_name].mesh.export(out / "support.obj")
    rot = Rotation.from_quat(np.roll(pose[3:], -1))
    matrix = np.eye(4)
    matrix[:3, :3] = rot.as_matrix()
    matrix[:3, 3] = pose[:3]
    meta = {
        "object": obj_name,
        "support": sup_name,
        "split": split,
        "convention": "p_support = T @ p_object (homogeneous); metres; quaternion_wxyz scalar-first",
        "matrix_4x4": matrix.tolist(),
        "position": pose[:3].tolist(),
        "quaternion_wxyz": pose[3:].tolist(),
        "quaternion_xyzw": np.roll(pose[3:], -1).tolist(),
        "wall_y": library.supports[sup_name].wall_y,
        "floor_z": library.supports[sup_name].floor_z,
    }
    (out / "pose.json").write_text(json.dumps(meta, indent=1))
    return out
