"""Every figure of the README, end to end: ``where`` (hanging success) and ``paths`` (P / R / F1).

    python -m experiments.evaluate where                    # default answer, all held-out pairs, seeds 0 1 2
    python -m experiments.evaluate where --config paper     # the paper's pipeline
    python -m experiments.evaluate where --split validation --pairs 345 --seed 0
    python -m experiments.evaluate where --frame any        # each object in a random frame
    python -m experiments.evaluate paths                    # default planner, 300 held-out pairs
    python -m experiments.evaluate paths --config paper_nce

Per-pair records go to ``out/evaluate/<figure>_<config>_<split>.jsonl`` (``--records``); a run
resumes from them. The summary is merged into ``results/hanging_success.json`` or
``results/paths.json`` under the config's name (``--results``; held-out split only unless
given), with the command and settings that made it. Needs the derived pairs:
``python -m experiments.derive_dataset --data datasets/paper --split test``.
The protocol behind each number: docs/evaluation.md.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import sys
import time
from pathlib import Path

from experiments import _cli

RESULTS = {"where": "results/hanging_success.json", "paths": "results/paths.json"}


def _versions() -> dict:
    import jax
    import mujoco

    return dict(python=platform.python_version(), jax=jax.__version__, mujoco=mujoco.__version__,
                device=str(jax.devices()[0].device_kind), backend=jax.default_backend(),
                host=f"{platform.machine()} x{os.cpu_count()}")  # fmt: skip


def merge_results(path: str | os.PathLike, key: str, entry: dict) -> dict:
    """Write ``entry`` under ``key`` of the JSON file at ``path`` (other keys kept; written to a
    temporary file and renamed, so a crash never leaves half a file)."""
    path = Path(path)
    data = json.loads(path.read_text()) if path.exists() else {}
    data[key] = entry
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(tmp, path)
    return data


def promotes(args, entry: dict) -> bool:
    """Whether a run becomes the figures of record: the default answer on the held-out split,
    on every held-out pair or at least the record sample (``where_eval.RECORD_PAIRS`` pairs),
    with three seeds or more."""
    from omnihang_jax.where_eval import RECORD_PAIRS

    return (args.figure == "where" and args.config == "default" and args.split == "test"
            and not args.depth_noise and not args.dropout
            and (args.pairs is None or entry["pairs"] >= RECORD_PAIRS)
            and len(args.seed) >= 3)  # fmt: skip


def promote(path: str | os.PathLike, entry: dict, suffix: str = "") -> None:
    """A run that :func:`promotes` becomes the figures of record: the top-level
    ``stage1`` (with ``network_first_pose``), ``stage1_2``, ``stage1_3`` and ``all_stages``
    (``suffix`` "_any_frame": ``stage1_any_frame`` ... of the any-frame protocol)."""
    for name in ("stage1", "stage1_2", "stage1_3", "all_stages"):
        if name not in entry:
            continue
        figure = dict(entry[name], seeds=entry["seeds"], command=entry["command"],
                      date=entry["date"])  # fmt: skip
        if name == "stage1" and "stage1_network" in entry:
            figure["network_first_pose"] = entry["stage1_network"]["mean"]
        if name == "all_stages" and "all_stages_unchecked" in entry:
            figure["unchecked"] = entry["all_stages_unchecked"]["mean"]
        merge_results(path, name + suffix, figure)


def run_where(args) -> dict:
    from omnihang_jax import where, where_eval

    config = where.CONFIGS[args.config]
    files = where_eval.pair_files(args.data, args.split, args.pairs)
    records = Path(args.records or f"out/evaluate/where_{_key(args)}_{args.split}.jsonl")
    before = len(where_eval.read_records(records))
    t0 = time.time()
    rows = []
    for seed in args.seed:
        rows = where_eval.evaluate_where(
            config, files, records, seed=seed, batch=args.batch, workers=args.workers,
            progress=not args.no_progress, frame=args.frame,
            depth_noise=args.depth_noise / 1000, dropout=args.dropout,
        )  # fmt: skip
    wanted = {int(where_eval._pair_index(f)) for f in files}
    rows = [r for r in rows if r["pair_index"] in wanted and r["seed"] in args.seed]
    summary = where_eval.summarise(rows)
    entry = dict(
        config=args.config, split=args.split, frame=args.frame, seeds=list(args.seed),
        depth_noise_mm=args.depth_noise, dropout=args.dropout,
        pairs=len(files), command=_command(), date=datetime.date.today().isoformat(),
        versions=_versions(),
        timing=where_eval.timing_note(t0, len(where_eval.read_records(records)) - before),
        **summary,
    )  # fmt: skip
    return entry


def run_paths(args) -> dict:
    from omnihang_jax import paths, paths_eval

    config = paths.CONFIGS[args.config]
    records = Path(args.records or f"out/evaluate/paths_{_key(args)}_{args.split}.jsonl")
    t0 = time.time()
    summary = paths_eval.evaluate_paths(
        config, data=args.data, split=args.split, pairs=args.pairs, seeds=list(args.seed),
        workers=args.workers, records_path=records, progress=not args.no_progress,
        frame=args.frame,
    )  # fmt: skip
    return dict(
        config=args.config, split=args.split, frame=args.frame, command=_command(),
        date=datetime.date.today().isoformat(), versions=_versions(),
        wall_s=round(time.time() - t0, 1), **summary,
    )  # fmt: skip


def _key(args, entry: dict | None = None) -> str:
    """The results key: the config's name, + "_any_frame" under the any-frame protocol,
    + "_noise<mm>mm" / "_dropout<percent>" with degraded clouds, + "_pairs<N>" for a `where` run
    on fewer pairs than the record sample (so a short run never replaces a whole one)."""
    from omnihang_jax.where_eval import RECORD_PAIRS

    key = args.config + ("_any_frame" if getattr(args, "frame", "library") == "any" else "")
    if getattr(args, "depth_noise", 0):
        key += f"_noise{args.depth_noise:g}mm"
    if getattr(args, "dropout", 0):
        key += f"_dropout{100 * args.dropout:g}"
    if args.figure == "where" and entry is not None and entry["pairs"] < RECORD_PAIRS:
        key += f"_pairs{entry['pairs']}"
    return key


def _command() -> str:
    return "python -m experiments.evaluate " + " ".join(shlex.quote(a) for a in sys.argv[1:])


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("figure", choices=["where", "paths"])
    parser.add_argument("--config", default="default",
                        help="where: default | paper | frames | canon; paths: default | paper_nce | paper_hce | mesh")  # fmt: skip
    parser.add_argument("--split", choices=["test", "validation"], default="test",
                        help="test: the held-out objects and supports (default)")  # fmt: skip
    parser.add_argument("--seed", type=int, nargs="+", default=None,
                        help="where: CEM / Stage-1 keys (default 0 1 2); paths: OMPL seeds (default 1)")  # fmt: skip
    parser.add_argument("--pairs", type=int, default=None,
                        help="at most this many pairs, round robin over the object categories "
                        "(where default: all; paths default: 300)")  # fmt: skip
    parser.add_argument("--data", default="datasets/paper", help="dataset (recipe.json + derived/)")
    parser.add_argument("--batch", type=int, default=8, help="where: pairs per network call")
    parser.add_argument("--workers", type=int, default=None,
                        help="processes that simulate / plan (default: the cores, less one)")  # fmt: skip
    parser.add_argument("--records", default=None, help="per-pair JSONL (resumable)")
    parser.add_argument("--results", default=None,
                        help="summary file (default results/hanging_success.json or "
                        "results/paths.json for the test split; none for validation)")  # fmt: skip
    parser.add_argument("--frame", choices=["library", "any"], default="library",
                        help="'any' hands each pair's object over in a random frame (any "
                        "rotation and shift); where also turns free-standing supports about z, "
                        "paths plan from the clouds alone; answers and paths are turned back "
                        "and judged on the true meshes")  # fmt: skip
    parser.add_argument("--depth-noise", type=float, default=0.0, metavar="MM",
                        help="where: Gaussian noise (std, mm) along each camera ray, normals "
                        "re-estimated from the noisy clouds")  # fmt: skip
    parser.add_argument(
        "--dropout",
        type=float,
        default=0.0,
        metavar="FRACTION",
        help="where: this share of each cloud's points lost at random",
    )
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.figure == "where":
        from omnihang_jax import where

        if args.config not in where.CONFIGS:
            raise ValueError(f"--config {args.config!r}: where takes {sorted(where.CONFIGS)}")
        args.seed = args.seed if args.seed is not None else [0, 1, 2]
    else:
        from omnihang_jax import paths

        if args.config not in paths.CONFIGS:
            raise ValueError(f"--config {args.config!r}: paths takes {sorted(paths.CONFIGS)}")
        args.seed = args.seed if args.seed is not None else [1]
        args.pairs = args.pairs if args.pairs is not None else 300
    if args.figure == "paths" and (args.depth_noise or args.dropout):
        raise ValueError("--depth-noise and --dropout are protocols of `where`")
    if args.pairs is not None and args.pairs < 1:
        raise ValueError(f"--pairs must be >= 1, got {args.pairs}")
    if args.workers is None:
        args.workers = max(1, (os.cpu_count() or 2) - 1)
    entry = run_where(args) if args.figure == "where" else run_paths(args)
    results = args.results or (RESULTS[args.figure] if args.split == "test" else None)
    if results:
        merge_results(results, _key(args, entry), entry)
        if promotes(args, entry):
            promote(results, entry, "_any_frame" if args.frame == "any" else "")
    print(json.dumps(entry, indent=1))
    return entry


if __name__ == "__main__":
    _cli.run(main)
