"""Held-out hanging success of Stages 1, 1+2, 1+3 and all stages (protocol: docs/evaluation.md).

Example (after deriving held-out pairs and training V):

    python -m experiments.derive_dataset --data datasets/paper --split test --limit 16
    python -m experiments.eval_stage3 --value weights/value_s16_hardneg --limit 16 \\
        --out out/hanging_success_stage3.json

``--pairs-from results/hanging_success.pairs.jsonl`` evaluates exactly the pairs of an earlier
run (the committed figures use the 1,814 pairs of results/hanging_success.json).

One run evaluates the pipeline on one view of the clouds (``--view``). The default pipeline
(``stage3.ANSWER_PIPELINE``, twenty-seventh session) answers with the best candidate of two
views, (0, 1) and (1, 2): its figure is the union of two runs with the same key,

    python -m experiments.eval_stage3 ... --out out/v0.json
    python -m experiments.eval_stage3 ... --view 1/2 --out out/v1.json
    python -m experiments.union_views --runs out/v0.pairs.jsonl out/v1.pairs.jsonl

(every candidate of both views is simulated; the union picks as the fused pipeline does).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from experiments import _cli
from omnihang_jax import dataset_bridge, eval_pipeline, evaluate, refine, selection, stage3
from omnihang_jax.stage3 import CEMConfig


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", default="datasets/paper", help="dataset with derived/test")
    parser.add_argument("--weights", default="weights/where_small_paper", help="Stages 1-2")
    parser.add_argument(
        "--value",
        default=stage3.CEM_VALUE,
        help="V that CEM searches on (Stage 3; default stage3.CEM_VALUE)",
    )
    parser.add_argument("--out", required=True, help="summary JSON (pairs go to .pairs.jsonl)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--pairs-from", default=None, help="evaluate the pairs of this JSONL")
    parser.add_argument("--limit", type=int, default=None, help="first N pairs")
    parser.add_argument("--per-category", type=int, default=None, help="N pairs per category")
    parser.add_argument(
        "--proposals", type=int, default=stage3.ANSWER_PIPELINE.num_proposals,
        help=f"K (default {stage3.ANSWER_PIPELINE.num_proposals}: the answer pipeline's; "
        "the facts' 5 with --proposals 5)",
    )  # fmt: skip
    parser.add_argument("--rounds", type=int, default=1, help="CEM rounds (1 = facts)")
    parser.add_argument(
        "--cem-iterations", type=int, default=stage3.CEMConfig().iterations, metavar="N",
        help="CEM iterations a round (default 10: the facts'); fewer leave latency for more views "
        "(forty-third session: CEM has not converged at 10, docs/stage3.md)",
    )  # fmt: skip
    parser.add_argument(
        "--stage1-rounds", type=int, default=None, metavar="N",
        help="CEM rounds of the Stage-1 starts only (default: --rounds); e.g. 2 widens the "
        "Stage-1 starts' reach to +-4 cm while the Stage-2 starts keep one round",
    )  # fmt: skip
    parser.add_argument("--batch", type=int, default=16, help="pairs per network call")
    parser.add_argument("--workers", type=int, default=0, help="simulation processes")
    parser.add_argument(
        "--stage2-clearance", type=float, default=None, metavar="M",
        help="Stage 2 moves its pose M metres along the observed support normal at its chosen "
        "contacts (Stage2Config.clearance; default: the model's own)",
    )  # fmt: skip
    parser.add_argument(
        "--select", choices=selection.RULES, default=selection.CHOSEN.rule,
        help="the answer among the refined candidates: 'value' = the highest V (paper); "
        "'value_clear' = the highest V among candidates with at most --select-max-points "
        "object points inside the observed support (omnihang_jax.selection); the defaults "
        "are selection.CHOSEN, chosen on validation objects",
    )  # fmt: skip
    parser.add_argument("--select-depth", type=float, default=selection.CHOSEN.depth, metavar="M")
    parser.add_argument("--select-radius", type=float, default=selection.CHOSEN.radius, metavar="M")
    parser.add_argument(
        "--select-max-points", type=int, default=selection.CHOSEN.max_points, metavar="N"
    )
    parser.add_argument(
        "--pool-starts", action=argparse.BooleanOptionalAction, default=True,
        help="the all-stages answer among the candidates refined from Stages 1 AND 2 (default, "
        "stage3.ANSWER_PIPELINE); --no-pool-starts --select value: the paper's answer (it is "
        "also reported as all_stages_paper either way)",
    )  # fmt: skip
    parser.add_argument(
        "--rank-value", action="append", default=None, metavar="DIR",
        help="a value folder that ranks CEM's refined candidates beside --value (mean log V "
        "over them; repeat for more; default stage3.RANK_VALUES); --rank-value none: the "
        "CEM's V alone",
    )  # fmt: skip
    parser.add_argument(
        "--rank-with-value", action=argparse.BooleanOptionalAction,
        default=stage3.RANK_WITH_CEM_VALUE,
        help="the CEM's V ranks beside the --rank-value networks (mean log V over all); "
        "--no-rank-with-value: they rank alone (default: stage3.RANK_WITH_CEM_VALUE)",
    )  # fmt: skip
    parser.add_argument(
        "--rank-subsets", type=int, default=stage3.ANSWER_PIPELINE.rank_subsets, metavar="T",
        help="each ranking network scores every candidate on T evenly spaced subsets of the "
        "clouds, the mean log V ranks (stage3.subset_clouds; default "
        "stage3.ANSWER_PIPELINE.rank_subsets)",
    )  # fmt: skip
    parser.add_argument(
        "--view", default="0/1", metavar="J/T",
        help="CEM's V and the ranking networks see subset J of T evenly spaced subsets of the "
        "clouds (stage3.subset_clouds; 0/1: the first view; the default pipeline answers on "
        f"{list(stage3.ANSWER_PIPELINE.views)}: run each and join them with "
        "experiments.union_views)",
    )  # fmt: skip
    parser.add_argument(
        "--seed", type=int, default=0,
        help="the key of Stage 1's noise and CEM's samples (0: every committed run); other "
        "seeds measure the figure's spread",
    )  # fmt: skip
    parser.add_argument("--label", default="")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.rounds < 1 or (args.stage1_rounds is not None and args.stage1_rounds < 1):
        parser.error("--rounds and --stage1-rounds must be >= 1")
    if args.cem_iterations < 1:
        parser.error(f"--cem-iterations {args.cem_iterations}: must be >= 1")
    if args.rank_subsets < 1:
        parser.error("--rank-subsets must be >= 1")
    parts = args.view.split("/")
    view = tuple(int(x) for x in parts) if all(x.strip().isdigit() for x in parts) else ()
    if len(view) != 2 or not 0 <= view[0] < view[1]:
        parser.error(f"--view {args.view}: expected J/T with 0 <= J < T")
    if view != (0, 1) and args.rank_subsets > 1:
        parser.error("--view and --rank-subsets > 1 do not go together")
    dataset_dir, derived_dir = dataset_bridge.resolve_dataset_dir(args.data)
    files = dataset_bridge.derived_files(derived_dir, args.split)
    if args.pairs_from:
        wanted = [json.loads(x)["file"] for x in Path(args.pairs_from).read_text().splitlines()]
        have = {Path(f).name: f for f in files}
        missing = [w for w in wanted if w not in have]
        if missing:
            raise FileNotFoundError(
                f"{len(missing)} of {len(wanted)} pairs of {args.pairs_from} are not derived"
                f" under {derived_dir}/{args.split} (first: {missing[0]}); derive them first"
            )
        files = [have[w] for w in wanted]
    if args.per_category:
        files = evaluate.spread_per_category(files, args.per_category)
    if args.limit:
        files = files[: args.limit]
    if not files:
        raise FileNotFoundError(f"no derived {args.split} pairs under {derived_dir}")
    select = selection.SelectConfig(
        args.select, args.select_depth, args.select_radius, args.select_max_points
    )
    rank_values = list(stage3.RANK_VALUES) if args.rank_value is None else [
        v for v in args.rank_value if v.lower() != "none"]  # fmt: skip
    for v in rank_values:
        if not (Path(v) / "params.msgpack").exists():
            parser.error(f"--rank-value {v}: not a value folder (config.json + params.msgpack)")
    records, timings = eval_pipeline.evaluate_pipeline(
        files, args.weights, args.value, dataset_dir, num_proposals=args.proposals,
        cem=CEMConfig(rounds=args.rounds, iterations=args.cem_iterations), batch=args.batch,
        workers=args.workers,
        progress=not args.no_progress, stage2_clearance=args.stage2_clearance, select=select,
        pool_starts=args.pool_starts, rank_value_dirs=rank_values, seed=args.seed,
        rank_with_value=args.rank_with_value,
        cem_stage1=None if args.stage1_rounds is None else CEMConfig(
            rounds=args.stage1_rounds, iterations=args.cem_iterations),
        rank_subsets=args.rank_subsets, view=view,
    )  # fmt: skip
    summary = eval_pipeline.summarize_pipeline(records, args.proposals)
    summary.update(label=args.label, timings=timings, weights=args.weights, value=args.value,
                   cem_rounds=args.rounds, cem_rounds_stage1=args.stage1_rounds,
                   cem_iterations=args.cem_iterations,
                   num_proposals=args.proposals, seed=args.seed,
                   stage2_clearance_m=args.stage2_clearance,
                   select=dataclasses.asdict(select),
                   pool_starts=args.pool_starts, rank_values=rank_values,
                   rank_with_value=args.rank_with_value,
                   rank_subsets=args.rank_subsets, view=list(view))  # fmt: skip
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    refine.write_json(out, summary)
    pairs = out.with_name(out.name.removesuffix(".json") + ".pairs.jsonl")
    pairs.write_text("".join(json.dumps(r) + "\n" for r in records))
    brief = {
        s: round(summary[s]["mean"], 1)
        for s in eval_pipeline.STAGES + eval_pipeline.VARIANTS
        if s in summary
    }
    brief.update(pairs=len(records), ranker=summary["ranker"], ceiling=summary["ceiling"])
    print(json.dumps(brief, indent=1))
    return summary


if __name__ == "__main__":
    _cli.run(main)
