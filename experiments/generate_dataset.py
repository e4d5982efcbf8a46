"""Generate (or resume) the hanging dataset.

    python -m experiments.generate_dataset --preset demo --out out/dataset_demo
    python -m experiments.generate_dataset --preset paper --out datasets/paper --workers 0
    python -m experiments.generate_dataset --preset paper --out datasets/paper --part 1/2

Shards already on disk are never redone; kill the job at any time and run the same command
again. The dataset card is written at the end (DIR/dataset_card.json and .md).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import sys
from concurrent.futures.process import BrokenProcessPool

from experiments import _cli
from sim import dataset


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--preset", choices=sorted(dataset.PRESETS), default="demo", help="dataset size preset"
    )
    parser.add_argument("--out", required=True, help="output directory (resumed if it exists)")
    parser.add_argument("--backend", choices=["cpu", "mjx"], default="cpu", help="physics backend")
    parser.add_argument(
        "--max-pairs-per-category", type=int, default=None, help="override: objects per category"
    )
    parser.add_argument(
        "--max-pairs",
        type=int,
        default=None,
        help="a seeded random subset of N pairs (to measure rates)",
    )
    parser.add_argument("--seed", type=int, default=None, help="override the dataset seed")
    parser.add_argument(
        "--workers",
        type=int,
        default=1,
        help="processes, one shard each at a time (CPU backend; 0 = one per core); with "
        "--backend mjx: processes for the per-pair CPU stage",
    )
    parser.add_argument(
        "--part",
        default="0/1",
        help="I/N: do only shards k with k %% N == I (split one dataset over machines; "
        "merge by copying shards/ into one DIR and rerunning)",
    )
    parser.add_argument(
        "--stop-after",
        type=float,
        default=None,
        metavar="SECONDS",
        help="start no new shard after this many seconds (for jobs on a time limit)",
    )
    parser.add_argument(
        "--shards-per-call",
        type=int,
        default=1,
        metavar="N",
        help="--backend mjx: label N shards in one device model (fewer compilations, fuller "
        "GPU); --workers then sets the processes for the per-pair CPU stage, which runs "
        "for one group while the GPU labels the next",
    )
    parser.add_argument(
        "--max-shards",
        type=int,
        default=None,
        metavar="N",
        help="do at most N of the shards left, then write the card (bounded chunks of work)",
    )
    parser.add_argument(
        "--card-only",
        action="store_true",
        help="generate nothing: (re)write DIR/dataset_card.json/.md from the shards present "
        "(safe while another job is generating into DIR)",
    )
    parser.add_argument("--no-progress", action="store_true", help="disable progress bars")
    args = parser.parse_args(argv)
    config = dataset.PRESETS[args.preset]
    if args.max_pairs_per_category is not None:
        config = dataclasses.replace(config, max_objects_per_category=args.max_pairs_per_category)
    if args.max_pairs is not None:
        config = dataclasses.replace(config, max_pairs=args.max_pairs)
    if args.seed is not None:
        config = dataclasses.replace(config, seed=args.seed)
    try:
        i_part, n_part = (int(x) for x in args.part.split("/"))
    except ValueError:
        parser.error(f"--part must look like I/N (e.g. 0/2), got {args.part!r}")
    # SIGTERM (a job scheduler's or `timeout`'s stop) ends the run like Ctrl-C: finished
    # shards stay, the run is logged in DIR/runs.jsonl as interrupted
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    workers = 1 if args.card_only else (args.workers or len(os.sched_getaffinity(0)))
    try:
        card = _generate(args, config, workers, i_part, n_part)
    except KeyboardInterrupt:
        print(
            f"interrupted: finished shards are kept in {args.out}/shards and the run is logged "
            "in runs.jsonl; run the same command again to resume",
            file=sys.stderr,
        )
        raise SystemExit(130) from None
    except BrokenProcessPool as e:  # a worker was killed (out of memory?): nothing is lost
        print(
            f"a worker process died ({e}); finished shards are kept in {args.out}/shards and "
            "the run is logged in runs.jsonl; check memory (fewer --workers) and run the same "
            "command again to resume",
            file=sys.stderr,
        )
        raise SystemExit(1) from None
    except Exception as e:
        if args.backend != "mjx" or "Failed to allocate" not in str(e):
            raise
        # MuJoCo Warp allocates scratch memory inside the jitted step; after a few device
        # models in one process that fails although the GPU has memory to spare (upstream:
        # mujoco_warp issues 926 and 1385). A fresh process starts clean.
        print(
            f"MuJoCo Warp could not allocate GPU memory in this process ({str(e)[-160:]}); "
            f"finished shards are kept in {args.out}/shards and the run is logged in "
            "runs.jsonl; run again (a new process) to resume, e.g. with --max-shards equal "
            "to --shards-per-call for one device model per process",
            file=sys.stderr,
        )
        raise SystemExit(3) from None
    return _report(args, card)


def _generate(args, config, workers: int, i_part: int, n_part: int) -> dict:
    return dataset.generate(
        config,
        args.out,
        preset=args.preset,
        backend=args.backend,
        progress=not args.no_progress,
        workers=workers,
        part=(i_part, n_part),
        stop_after_s=0.0 if args.card_only else args.stop_after,
        shards_per_call=args.shards_per_call,
        max_shards=args.max_shards,
    )


def _report(args, card: dict) -> dict:
    summary = {
        k: card[k]
        for k in (
            "pairs_done",
            "pairs_with_stable_poses",
            "train_pairs",
            "test_pairs",
            "stable_yield",
        )
    }
    print(json.dumps(summary, indent=1))
    rate = (
        f"pairs/min this run: {card['timings']['pairs_per_min_this_run']:.1f}"
        if card["timings"].get("pairs_this_run")
        else "nothing generated in this run"
    )
    print(f"{rate}; card: {args.out}/dataset_card.md")
    return card


if __name__ == "__main__":
    _cli.run(main)
