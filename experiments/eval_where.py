"""Hanging success of the "where to hang" networks on the held-out pairs (paper protocol).

    python -m experiments.eval_where --model runs/where --data data/paper \
        --out results/hanging_success.json --errors results/pose_errors.json

For every derived pair of --split (default test): Stage 1 proposes K poses, Stage 2 refines
them; proposal 0 (Stages 1 and 1+2) is loaded at rest and simulated for 1 s
(omnihang_jax.evaluate: failure if it penetrates > 3 mm at the start, leaves the support's
bounding box, touches the ground or diverges). The answers carry what the validation objects
chose: Stage 1 is released --stage1-lift (stage1.ANSWER_LIFT, 7.5 mm) above the network's pose,
Stage 1+2 moved --stage2-clearance (stage2.ANSWER_CLEARANCE, 4 mm) along the observed support
normal, and of each stage's K proposals the one least inside the observed support is the answer
(--select penetration, evaluate.ANSWER_SELECT); the chosen Stages 1+2 pose is then released
--stage2-lift (stage2.ANSWER_LIFT, 5 mm) higher. `--select first --stage1-lift 0
--stage2-clearance 0 --stage2-lift 0` gives the paper's: the network's first proposal as predicted. Writes OUT (success per stage: mean over
categories and per category, %), ERRORS (pose errors to the nearest ground-truth stable pose)
and OUT with suffix .pairs.jsonl (one line per pair). --model ground_truth evaluates the
dataset's own stable poses instead (a check of the protocol).

--figure [PNG] also draws predicted hangs of --figure-pairs held-out pairs (ground truth,
Stage 1, Stage 1+2; default PNG: OUT with suffix .png; experiments.where_figure). Redraw it
later from the per-pair JSONL without the model:

    python -m experiments.eval_where --figure-from results/hanging_success.pairs.jsonl \
        --data data/paper --figure results/hanging_success.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from experiments import _cli
from omnihang_jax import evaluate, stage1, stage2


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model", help="folder written by train_where, or 'ground_truth'")
    parser.add_argument("--data", required=True, help="generated dataset (or its derived/ folder)")
    parser.add_argument("--out", help="results JSON")
    parser.add_argument("--errors", default=None, help="pose-error JSON (default beside --out)")
    parser.add_argument(
        "--pairs-out", default=None, help="per-pair JSONL (default OUT.pairs.jsonl)"
    )
    parser.add_argument("--split", default="test", help="split of the derived pairs")
    parser.add_argument("--proposals", type=int, default=None, help="K (default: Stage-1 eval Z)")
    parser.add_argument("--candidate", type=int, default=0, help="proposal that is evaluated")
    parser.add_argument(
        "--select",
        choices=evaluate.SELECTS,
        default=evaluate.ANSWER_SELECT,
        help="which proposal of each stage is evaluated: the one whose object cloud least "
        "enters the observed support cloud (omnihang_jax.heuristics; default "
        "evaluate.ANSWER_SELECT, chosen on validation objects), or the first drawn (the "
        "paper's: with --stage1-lift 0 --stage2-clearance 0 --stage2-lift 0 the network's own "
        "first proposal)",
    )
    parser.add_argument(
        "--separate",
        action="store_true",
        help="back every proposal out of the observed support cloud along its outward "
        "normal before it is scored (omnihang_jax.heuristics.separate; before --select)",
    )
    parser.add_argument(
        "--stage2-lift",
        type=float,
        default=stage2.ANSWER_LIFT,
        metavar="M",
        help="release the chosen Stage-2 pose M metres higher, after the clearance and the "
        "selection (default stage2.ANSWER_LIFT, 0.005: the Stages 1+2 answer, chosen on "
        "validation objects; 0: no release height)",
    )
    parser.add_argument(
        "--stage1-lift",
        type=float,
        default=stage1.ANSWER_LIFT,
        metavar="M",
        help="release the Stage-1 proposals M metres above the predicted pose (+z of the "
        "support frame, rotation kept; default stage1.ANSWER_LIFT, 0.0075: the Stage-1 answer, "
        "chosen on validation objects; 0: the network's pose, the paper's Stage 1)",
    )
    parser.add_argument(
        "--stage2-clearance",
        type=float,
        default=stage2.ANSWER_CLEARANCE,
        metavar="M",
        help="Stage-2 clearance in metres (default stage2.ANSWER_CLEARANCE, 0.004: the Stages "
        "1+2 answer, chosen on validation objects; 0: the paper's, the trained model's own): the "
        "Stage-2 pose moves M along the mean outward normal of the observed support cloud (the "
        "pair's support_normals) at its chosen support contact points",
    )
    parser.add_argument("--backend", choices=["cpu", "mjx"], default="cpu")
    parser.add_argument(
        "--judge",
        choices=["mujoco", "pybullet", "both"],
        default="mujoco",
        help="who judges success (sim.judges): MuJoCo, PyBullet with MuJoCo's physics, or "
        "both (success only if both say it hangs; per-judge rates in 'by_judge')",
    )
    parser.add_argument("--seed", type=int, default=0, help="Stage-1 noise seed")
    parser.add_argument("--label", default="", help="free text stored in the results")
    parser.add_argument("--limit", type=int, default=None, help="first N pairs only (smoke runs)")
    parser.add_argument(
        "--per-category",
        type=int,
        default=None,
        metavar="N",
        help="at most N pairs per object category, evenly spaced (a balanced subset)",
    )
    parser.add_argument("--no-reference", action="store_true", help="skip the ground-truth check")
    parser.add_argument("--no-progress", action="store_true", help="disable progress bars")
    parser.add_argument(
        "--stage2-only",
        metavar="STAGE_DIR",
        default=None,
        help="only the Stage-2-from-ground-truth diagnostic of this trained stage folder "
        "(MODEL/stage2b or MODEL/stage2a), written to --out; no simulation",
    )
    parser.add_argument(
        "--figure",
        nargs="?",
        const="",
        default=None,
        metavar="PNG",
        help="also draw predicted hangs into PNG (default: OUT with suffix .png)",
    )
    parser.add_argument("--figure-pairs", type=int, default=8, help="pairs in the figure (8)")
    parser.add_argument(
        "--figure-from",
        metavar="PAIRS_JSONL",
        default=None,
        help="only draw the figure from an earlier run's per-pair JSONL (needs --data)",
    )
    args = parser.parse_args(argv)
    if args.figure_from is not None:
        from experiments import where_figure

        src = Path(args.figure_from)
        png = args.figure or (
            src.with_name(src.name[: -len(".pairs.jsonl")] + ".png")
            if src.name.endswith(".pairs.jsonl")
            else src.with_suffix(".png")
        )
        rows = where_figure.draw_where_figure(src, args.data, png, args.figure_pairs)
        print(json.dumps({"figure": str(png), "rows": rows}, indent=1))
        return {"figure": str(png), "rows": rows}
    if args.model is None or args.out is None:
        parser.error("--model and --out are required (unless --figure-from)")
    if args.stage2_only is not None:
        diag = evaluate.stage2_diagnostics(
            args.stage2_only, args.data, args.split, args.limit, args.seed
        )
        diag["label"] = args.label
        with open(args.out, "w") as f:
            json.dump(diag, f, indent=1)
        print(json.dumps({k: diag[k] for k in ("exact", "noisy")}, indent=1))
        return diag
    config = evaluate.EvalConfig(
        num_proposals=args.proposals,
        candidate=args.candidate,
        select=args.select,
        separate=args.separate,
        # ground truth is no prediction: it is evaluated where it is
        stage1_lift=0.0 if args.model == "ground_truth" else args.stage1_lift,
        backend=args.backend,
        judge=args.judge,
        seed=args.seed,
        split=args.split,
        # ground truth runs no Stage 2: no clearance to record
        stage2_clearance=None if args.model == "ground_truth" else args.stage2_clearance,
        stage2_lift=0.0 if args.model == "ground_truth" else args.stage2_lift,
    )
    results = evaluate.evaluate_where(
        None if args.model == "ground_truth" else args.model,
        args.data,
        args.out,
        errors_path=args.errors,
        pairs_path=args.pairs_out,
        config=config,
        label=args.label,
        reference=not args.no_reference,
        limit=args.limit,
        per_category=args.per_category,
        progress=not args.no_progress,
    )
    brief = {k: results[k] for k in ("stage1", "stage1_2", "pairs")}
    if "by_judge" in results:
        brief["by_judge"] = {
            e: {st: v[st]["mean"] for st in ("stage1", "stage1_2")}
            for e, v in results["by_judge"].items()
        }
    if "ground_truth_reference" in results:
        brief["ground_truth_reference"] = results["ground_truth_reference"]["mean"]
    if args.figure is not None:
        from experiments import where_figure

        png = args.figure or Path(args.out).with_suffix(".png")
        pairs = args.pairs_out or Path(args.out).with_suffix(".pairs.jsonl")
        where_figure.draw_where_figure(pairs, args.data, png, args.figure_pairs)
        brief["figure"] = str(png)
    print(json.dumps(brief, indent=1))
    return results


if __name__ == "__main__":
    _cli.run(main)
