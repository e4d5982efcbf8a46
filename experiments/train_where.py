"""Train the "where to hang" networks: Stage 1 (rough pose), Stage 2a (contact scores),
Stage 2b (contact correspondences).

    python -m experiments.train_where --data synthetic --out runs/where_tiny --preset tiny --steps 200
    python -m experiments.train_where --data datasets/paper/derived --out runs/where --stage all

Each stage trains into OUT/stage<name>/ (config.json, orbax checkpoints, metrics.jsonl,
loss.png) and resumes from its latest checkpoint: run the same command again to continue or
raise --steps. Stage 2b starts from Stage 2a's parameters. --data synthetic trains on generated
ring-on-peg pairs (a dry run of the whole pipeline); a directory is read with
omnihang_jax.data.load_hang_dataset (one .npz per pair, keys = HangSample fields), or, if it
holds a pack.json, as a packed split (experiments.pack_dataset; the fast path on a GPU).

Pairs of a fixed 10 % of the training OBJECTS are held out for validation (--val-fraction):
val_metrics.jsonl every --eval-every steps, the best parameters under stage<name>/best/;
--export DIR writes the small weights folder (--export-which best|latest). The learning
rate warms up and decays (cosine) over --steps, so give the run's total steps.
"""

from __future__ import annotations

import argparse
import dataclasses

from experiments import _cli
from omnihang_jax import train

STAGE_CHOICES = {
    "1": ("1",),
    "2a": ("2a",),
    "2b": ("2b",),
    "2": ("2a", "2b"),
    "all": train.STAGES,
    "canon": ("canon",),  # the object-frame network (omnihang_jax.canon)
}


def stage2_overrides(stage2, items, flag: str = "--stage2"):
    """Apply ``FIELD=VALUE`` strings to a Stage2Config (or Stage1Config; values cast to the
    field's type)."""
    fields = {f.name: f for f in dataclasses.fields(stage2)}
    changes = {}
    for item in items:
        name, _, value = item.partition("=")
        if name not in fields or not _:
            raise SystemExit(f"{flag} {item!r}: expected FIELD=VALUE, FIELD one of {list(fields)}")
        current = getattr(stage2, name)
        if isinstance(current, bool):
            changes[name] = value.lower() in ("1", "true", "yes")
        elif isinstance(current, (int, float, str)):
            changes[name] = type(current)(value)
        else:
            raise SystemExit(f"{flag} {name}: not settable from the command line")
    return dataclasses.replace(stage2, **changes)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--data",
        default="synthetic",
        help="'synthetic' (generated ring-on-peg pairs) or a dataset directory of per-pair .npz",
    )
    parser.add_argument("--out", required=True, help="output folder (resumed if it exists)")
    parser.add_argument(
        "--stage", choices=sorted(STAGE_CHOICES), default="all", help="stage(s) to train"
    )
    parser.add_argument(
        "--steps", type=int, default=None, help="total steps per stage (default: preset's)"
    )
    parser.add_argument(
        "--preset",
        choices=sorted(train.PRESETS),
        default="original",
        help="network sizes: 'original' (paper, 4096-point clouds), 'small' (real objects on "
        "2048-point clouds, CPU in minutes) or 'tiny' (tests)",
    )
    parser.add_argument("--batch", type=int, default=None, help="pairs per step (default 32)")
    parser.add_argument("--seed", type=int, default=None, help="seed for init, data and noise")
    parser.add_argument("--lr-stage1", type=float, default=None, help="Adam lr, Stage 1")
    parser.add_argument("--lr-stage2", type=float, default=None, help="Adam lr, Stages 2a/2b")
    parser.add_argument(
        "--synthetic-pairs",
        type=int,
        default=None,
        help="size of the generated pool with --data synthetic (default: preset's)",
    )
    parser.add_argument(
        "--stage2",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a Stage2Config field, e.g. --stage2 contact_loss=bce "
        "--stage2 train_selection=predicted (repeatable)",
    )
    parser.add_argument(
        "--stage1",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a Stage1Config field, e.g. --stage1 rotation=6d --stage1 "
        "set_loss_mean=true --stage1 num_train_samples=16 (repeatable)",
    )
    parser.add_argument(
        "--time-budget",
        default=None,
        metavar="STAGE=SECONDS,...",
        help="stop a stage after this many seconds (checkpointed; rerun to continue), "
        "e.g. 1=300,2a=90,2b=60",
    )
    parser.add_argument(
        "--data-on-device",
        action="store_true",
        help="keep every pair in device memory and gather batches there (GPU; ~1.8 MB per "
        "paper-scale pair) instead of stacking batches on the host",
    )
    parser.add_argument(
        "--schedule", choices=["cosine", "constant"], default=None, help="lr schedule"
    )
    parser.add_argument("--warmup", type=int, default=None, help="lr warm-up steps")
    parser.add_argument("--clip-norm", type=float, default=None, help="0 = no clipping")
    parser.add_argument(
        "--augment-jitter",
        type=float,
        default=None,
        metavar="M",
        help="Stage 1: Gaussian noise (m) on every training point (omnihang_jax.augment)",
    )
    parser.add_argument(
        "--augment-yaw",
        type=float,
        default=None,
        metavar="RAD",
        help="Stage 1: turn each training pair about the vertical by U(-RAD, RAD)",
    )
    parser.add_argument(
        "--augment-object-turn",
        type=int,
        nargs="?",
        const=1,
        default=None,
        metavar="M",
        help="Stages 1-2: each training object read about its box centre in the frame that the "
        "nearest of M frame hypotheses leaves of a uniform random frame (where.FRAMES: 32; "
        "no M: any frame), its stable poses the same placements",
    )
    parser.add_argument(
        "--val-fraction", type=float, default=None, help="fraction of objects held out (0.1)"
    )
    parser.add_argument("--eval-every", type=int, default=None, help="steps between val checks")
    parser.add_argument("--checkpoint-every", type=int, default=None)
    parser.add_argument("--export", default=None, metavar="DIR", help="export weights here")
    parser.add_argument("--export-which", choices=["best", "latest"], default="best")
    parser.add_argument(
        "--init-from",
        default=None,
        metavar="WEIGHTS",
        help="start stages without a checkpoint from these weights (e.g. "
        "weights/stage12; same preset): fine-tuning with a fresh schedule",
    )
    parser.add_argument("--no-progress", action="store_true", help="disable progress bars")
    args = parser.parse_args(argv)
    budget = None
    if args.time_budget:
        try:
            budget = {
                k.strip(): float(v) for k, v in (x.split("=") for x in args.time_budget.split(","))
            }
        except ValueError:
            parser.error(f"--time-budget must look like 1=300,2a=90, got {args.time_budget!r}")
        unknown = set(budget) - set(train.ALL_STAGES)
        if unknown:
            parser.error(f"--time-budget: unknown stages {sorted(unknown)}; use {train.ALL_STAGES}")

    if args.augment_object_turn is not None and args.augment_object_turn < 1:
        parser.error(f"--augment-object-turn M needs M >= 1 frame hypotheses (1: any frame), "
                     f"got {args.augment_object_turn}")  # fmt: skip
    config = train.PRESETS[args.preset]
    overrides = {}
    if args.batch is not None:
        overrides["batch_size"] = args.batch
    if args.seed is not None:
        overrides["seed"] = args.seed
    if args.lr_stage1 is not None:
        overrides["lr_stage1"] = args.lr_stage1
    if args.lr_stage2 is not None:
        overrides["lr_stage2"] = args.lr_stage2
    if args.synthetic_pairs is not None:
        overrides["synthetic_pairs"] = args.synthetic_pairs
    for name, value in (
        ("schedule", args.schedule),
        ("warmup_steps", args.warmup),
        ("clip_norm", args.clip_norm),
        ("val_fraction", args.val_fraction),
        ("eval_every", args.eval_every),
        ("checkpoint_every", args.checkpoint_every),
        ("augment_jitter", args.augment_jitter),
        ("augment_yaw", args.augment_yaw),
        ("augment_object_turn", args.augment_object_turn),
    ):
        if value is not None:
            overrides[name] = value
    config = dataclasses.replace(config, train=dataclasses.replace(config.train, **overrides))
    if args.stage2:
        config = dataclasses.replace(config, stage2=stage2_overrides(config.stage2, args.stage2))
    if args.stage1:
        config = dataclasses.replace(
            config, stage1=stage2_overrides(config.stage1, args.stage1, "--stage1")
        )
    states = train.train_where(
        args.data,
        args.out,
        stages=STAGE_CHOICES[args.stage],
        config=config,
        steps=args.steps,
        progress=not args.no_progress,
        time_budget_s=budget,
        data_on_device=args.data_on_device,
        init_from=args.init_from,
    )
    summary = {stage: int(state.step) for stage, state in states.items()}
    print(f"trained steps per stage: {summary}; outputs in {args.out}")
    if args.export:
        exported = train.export_weights(
            args.out, args.export, STAGE_CHOICES[args.stage], which=args.export_which
        )
        print(f"exported ({args.export_which}) {exported} to {args.export}")
    return summary


if __name__ == "__main__":
    _cli.run(main)
