"""The paper's refinement-learning experiment: RL success against steps, from Stage 2 vs uniform.

Example (CPU smoke run, needs derived training pairs):

    python -m experiments.refinement_learning --pairs 8 --max-steps 160 --steps-per-round 80 \\
        --preset tiny --out out/refinement_learning.json

The committed figure (results/refinement_learning.json, docs/img/refinement_learning.png)
is the GPU run of scripts/device_stage3.sh (mode ``curve``): 100 pairs, 10,000 steps.
"""

from __future__ import annotations

import argparse
import dataclasses
import json

from experiments import _cli
from experiments.train_stage3 import PRESETS
from omnihang_jax.rl import learning_curve


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", default="datasets/paper")
    parser.add_argument("--weights", default="weights/stage12")
    parser.add_argument("--out", required=True, help="JSON (the PNG goes beside it)")
    parser.add_argument("--preset", choices=sorted(PRESETS), default="paper")
    parser.add_argument("--pairs", type=int, default=100)
    parser.add_argument("--max-steps", type=int, default=10_000)
    parser.add_argument("--steps-per-round", type=int, default=1_000)
    parser.add_argument("--train-steps", type=int, default=200, help="V steps per round")
    parser.add_argument("--workers", type=int, default=0)
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    config = dataclasses.replace(PRESETS[args.preset], workers=args.workers)
    result = learning_curve(
        args.data, args.weights, args.out, num_pairs=args.pairs, max_steps=args.max_steps,
        steps_per_round=args.steps_per_round, train_steps=args.train_steps, config=config,
        progress=not args.no_progress,
    )  # fmt: skip
    brief = {s: [round(r["success"], 3) for r in rows] for s, rows in result["curves"].items()}
    print(json.dumps(brief))
    return result


if __name__ == "__main__":
    _cli.run(main)
