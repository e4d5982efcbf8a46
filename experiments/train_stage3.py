"""Train Stage 3 (value function V + CEM) with simulated rewards; resumable.

Example (CPU, a few minutes on 2 cores, needs derived training pairs):

    python -m experiments.derive_dataset --data datasets/paper --split train --limit 24
    python -m experiments.train_stage3 --preset tiny --out runs/stage3_tiny

On a GPU machine the ``paper`` preset is the job of scripts/device_stage3.sh. Rerunning the
same command resumes from ``OUT`` (buffer, V checkpoint, round counter).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import signal
import sys

from experiments import _cli
from omnihang_jax import stage3
from omnihang_jax.rl import RLConfig, train_stage3
from omnihang_jax.stage3 import CEMConfig

PRESETS = {
    # tests and CPU smoke runs: tiny network, few pairs, a couple of rounds
    "tiny": RLConfig(
        value=stage3.VALUE_TINY,
        cem=CEMConfig(population=8, iterations=3, elites=3),
        num_proposals=2,
        max_pairs=12,
        perturb_wide=4,
        perturb_tight=4,
        pretrain_steps=30,
        rounds=2,
        round_pairs=6,
        round_steps=20,
        val_every=1,
        val_pairs=4,
        eval_every=20,
        val_fraction=0.25,
    ),
    # the GPU job: every derived training pair, the small PointNet++ preset
    "paper": RLConfig(workers=15, time_budget=0.0),
    # the device job (scripts/chain/stage3.sh): every training pair, derived
    # while the job runs (ingested every 3 rounds), a lighter seed (8 + 8 perturbations per
    # pair), then hard-negative rounds: CEM's answers + the 8 best-scored members of every
    # final population labelled by the physics, a quarter of each batch from those hard cases
    "hardneg": RLConfig(
        workers=4,
        perturb_wide=8,
        perturb_tight=8,
        pretrain_steps=6000,
        rounds=60,
        round_pairs=256,
        round_steps=400,
        val_every=3,
        keep_top=8,
        hard_fraction=0.25,
        min_pairs=200,
        ingest_every=3,
        ingest_min=200,
        seed_chunk=1500,
        seed_share=0.5,
        bank_capacity=16384,
        cem_batch=16,
    ),
    # the same at CPU scale (tests, CHAIN_TINY=1)
    "hardneg_tiny": RLConfig(
        value=stage3.VALUE_TINY,
        cem=CEMConfig(population=8, iterations=3, elites=3),
        num_proposals=2,
        max_pairs=24,
        perturb_wide=4,
        perturb_tight=4,
        pretrain_steps=30,
        rounds=3,
        round_pairs=6,
        round_steps=20,
        val_every=1,
        val_pairs=4,
        eval_every=20,
        val_fraction=0.25,
        keep_top=4,
        hard_fraction=0.25,
        ingest_every=1,
        seed_chunk=8,
        bank_capacity=32,
    ),
}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--preset", choices=sorted(PRESETS), default="tiny")
    parser.add_argument("--out", required=True, help="job folder (created; resumed if present)")
    parser.add_argument(
        "--data", default="datasets/paper", help="dataset with derived/ (default datasets/paper)"
    )
    parser.add_argument(
        "--weights",
        default="weights/stage12",
        help="Stage 1/2 weights (default weights/stage12)",
    )
    parser.add_argument("--max-pairs", type=int, default=None, help="training pairs (0 = all)")
    parser.add_argument("--pretrain-steps", type=int, default=None)
    parser.add_argument("--rounds", type=int, default=None)
    parser.add_argument("--round-pairs", type=int, default=None)
    parser.add_argument("--round-steps", type=int, default=None)
    parser.add_argument("--batch", type=int, default=None, help="V training batch")
    parser.add_argument("--workers", type=int, default=None, help="simulation processes")
    parser.add_argument("--time-budget", type=float, default=None, help="seconds for the job")
    parser.add_argument(
        "--keep-top", type=int, default=None,
        help="hard-negative rounds: label the N best members of each final CEM population",
    )  # fmt: skip
    parser.add_argument(
        "--hard-fraction", type=float, default=None, help="share of a batch from the hard cases"
    )
    parser.add_argument("--val-every", type=int, default=None, help="rounds between val checks")
    parser.add_argument("--perturb-wide", type=int, default=None)
    parser.add_argument("--perturb-tight", type=int, default=None)
    parser.add_argument("--init-value", default=None, help="start V from this value/ folder")
    parser.add_argument("--min-pairs", type=int, default=None, help="wait for this many pairs")
    parser.add_argument("--cem-batch", type=int, default=None, help="pairs per jitted CEM call")
    parser.add_argument(
        "--seed-share", type=float, default=None, help="of the budget a run may spend seeding"
    )
    parser.add_argument(
        "--round-start", choices=("stage2", "stage1", "alternate"), default=None,
        help="proposals CEM refines in the RL rounds (alternate: Stage 2 odd, Stage 1 even rounds)",
    )  # fmt: skip
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    config = PRESETS[args.preset]
    over = {
        "max_pairs": args.max_pairs,
        "pretrain_steps": args.pretrain_steps,
        "rounds": args.rounds,
        "round_pairs": args.round_pairs,
        "round_steps": args.round_steps,
        "workers": args.workers,
        "time_budget": args.time_budget,
        "keep_top": args.keep_top,
        "hard_fraction": args.hard_fraction,
        "val_every": args.val_every,
        "perturb_wide": args.perturb_wide,
        "perturb_tight": args.perturb_tight,
        "init_value": args.init_value,
        "min_pairs": args.min_pairs,
        "cem_batch": args.cem_batch,
        "round_start": args.round_start,
        "seed_share": args.seed_share,
    }
    config = dataclasses.replace(config, **{k: v for k, v in over.items() if v is not None})
    if args.batch:
        config = dataclasses.replace(
            config, value=dataclasses.replace(config.value, batch_size=args.batch)
        )
    # a guard timeout's SIGTERM ends the job through its `finally` (the simulation pool closed)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    # a missing dataset or weights folder is a user error: one line + exit 2 (experiments._cli)
    summary = train_stage3(config, args.out, args.data, args.weights, progress=not args.no_progress)
    print(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    _cli.run(main)
