"""The Stage-3 answer ranked by several value functions, studied after an evaluation run.

    python -m experiments.ensemble_stage3 \\
        --select-on results/validation_where_s11/val_committed.pairs.jsonl.gz --select-split train \\
        --apply-to results/hanging_success_stage3_s10_answer.pairs.jsonl.gz --apply-split test \\
        --value weights/value_small_paper --extra-value weights/value_s12_hardneg \\
        --out results/ensemble_stage3.json

V's ranking among the clear refined candidates is the largest loss of the answer rule (docs/
stage3.md). This scores every refined candidate of a run (the 2K of the answer pool) with the
run's V (``--value``, recomputed and checked against the records: ``v_check``) and with each
``--extra-value`` V, and replaces the final V in the chosen rule (``selection.CHOSEN``,
pooled: the highest score among the candidates with no object point inside the observed
support) by each combination: every V alone, the mean of P(hang) and the mean of log P(hang)
(the geometric mean) over all of them. CEM itself is the run's (on ``--value``): only the
final ranking changes. As in ``experiments.rerank_stage3``, every candidate of an
``eval_stage3`` run was simulated (``stable_all``), so a ranking is scored without a new
simulation; the combination is chosen on --select-on (pairs of validation OBJECTS) and applied
once to --apply-to (held-out pairs). Mean over categories as everywhere.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from experiments import _cli
from experiments.rerank_stage3 import any_refined, pool_indices, proposals_of, read_records
from experiments.smooth_stage3 import POOL, evaluate_scores, record_batches, record_study_parser
from omnihang_jax import refine, selection, stage3


def pool_values(rows, data, split, value_dirs, k, batch, progress) -> np.ndarray:
    """[V, N, P] P(hang) of the pool's candidates under each value function."""
    idx = pool_indices(k, POOL)
    nets = []
    for d in value_dirs:
        config, params = refine.load_value(d)
        value = stage3.make_value(config)
        fn = jax.jit(jax.vmap(
            lambda p, c, poses, value=value, config=config: jnp.exp(
                value.score(p, stage3.subsample_clouds(c, config), poses)),
            in_axes=(None, 0, 0),
        ))  # fmt: skip
        nets.append((fn, params))
    out = [[] for _ in nets]
    for m, chunk, full in record_batches(rows, data, split, batch, "V ensemble", progress):
        poses = jnp.asarray(np.asarray([r["poses_all"] for r in chunk], np.float32)[:, idx])
        for j, (fn, params) in enumerate(nets):
            out[j].append(np.asarray(fn(params, full, poses))[:m])
    return np.stack([np.concatenate(o) for o in out])


def recorded_values(rows, k, extra: int) -> np.ndarray:
    """[1 + extra, N, P] P(hang) of the pool's candidates as the run recorded them: ``v``
    (its CEM's V) and each of its ``v_rank`` networks."""
    missing = [i for i, r in enumerate(rows) if len(r.get("v_rank", [])) != extra]
    if missing:
        raise ValueError(
            f"--from-records: {len(missing)} records hold not {extra} ranking networks' V "
            f"(v_rank; e.g. record {missing[0]}): run eval_stage3 with one --rank-value per "
            "--extra-value, in the same order"
        )
    idx = pool_indices(k, POOL)
    vals = [[r["v"] for r in rows]] + [[r["v_rank"][j] for r in rows] for j in range(extra)]
    return np.asarray(vals, np.float64)[:, :, idx]


def pipeline_sets(n_extra: int) -> list[tuple[int, ...]]:
    """Every set of the other networks the pipeline may rank with, smallest first."""
    return [s for size in range(n_extra + 1)
            for s in itertools.combinations(range(1, n_extra + 1), size)]  # fmt: skip


def pipeline_table(rows, k, values, names) -> list[dict]:
    """The rule's success when the pipeline ranks by the mean log V of the run's V (values[0])
    and each set of the others; ``rank_values`` names the set (``eval_stage3 --rank-value``)."""
    logs = np.log(np.clip(values, 1e-12, 1.0))
    out = []
    for s in pipeline_sets(len(values) - 1):
        score = np.exp(logs[[0, *s]].mean(0))
        label = "rank: " + (" + ".join(names[i] for i in s) if s else "none (the run's V)")
        (row,) = evaluate_scores(rows, k, {label: score})
        out.append({**row, "rank_values": [names[i] for i in s]})
    return out


PESSIMISM = (0.25, 0.5, 1.0)  # lambda of "mean - lambda sd" over the ranking networks


def combinations(values: np.ndarray, names: list[str]) -> dict[str, np.ndarray]:
    """Each V alone, and the mean of P and of log P over all of them ([N, P] each). With two
    or more ranking networks beside the run's V (values[1:], the pipeline's ranking since the
    twentieth session): their mean log P, and pessimistic combinations of their log P (the
    smallest, the median, the mean minus ``lambda`` standard deviations for each of
    :data:`PESSIMISM`): a candidate the networks disagree on ranks lower (twenty-fourth
    session: CEM pushed harder finds poses some networks overrate)."""
    combos = {name: v for name, v in zip(names, values, strict=True)}
    if len(values) > 1:
        combos["mean V"] = values.mean(0)
        combos["mean log V"] = np.exp(np.log(np.clip(values, 1e-12, 1.0)).mean(0))
    if len(values) > 2:
        logs = np.log(np.clip(values[1:], 1e-12, 1.0))
        combos["rankers: mean log V"] = np.exp(logs.mean(0))
        combos["rankers: min log V"] = np.exp(logs.min(0))
        combos["rankers: median log V"] = np.exp(np.median(logs, 0))
        for lam in PESSIMISM:
            combos[f"rankers: mean - {lam} sd log V"] = np.exp(logs.mean(0) - lam * logs.std(0))
    return combos


def study(rows, k, values, names, recorded_name):
    """Table of the chosen rule's success per combination, and the recorded-V check."""
    idx = pool_indices(k, POOL)
    recorded = np.asarray([r["v"] for r in rows], np.float32)[:, idx]
    table = evaluate_scores(rows, k, combinations(values, names))
    for row in table:
        row["v_names"] = names if row["score"].startswith("mean") else [row["score"]]
    check = {"value": recorded_name,
             "max_abs_diff": float(np.max(np.abs(values[0] - recorded))),
             "mean_abs_diff": float(np.mean(np.abs(values[0] - recorded)))}  # fmt: skip
    return table, check


def main(argv=None) -> dict:
    parser = record_study_parser(__doc__)
    parser.add_argument("--extra-value", action="append", required=True,
                        help="another V folder (repeat for more)")  # fmt: skip
    parser.add_argument("--batch", type=int, default=16, help="pairs per call")
    parser.add_argument(
        "--from-records",
        action="store_true",
        help="each V as the runs recorded it (v, v_rank) instead of recomputed",
    )
    parser.add_argument("--limit", type=int, default=None, help="first N records of each run")
    parser.add_argument("--out", required=True, help="JSON")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.batch < 1:
        parser.error("--batch must be >= 1")
    dirs = [args.value, *args.extra_value]
    for d in dirs:
        if not args.from_records and not (Path(d) / "params.msgpack").exists():
            parser.error(f"{d}: not a value folder (config.json + params.msgpack)")
    names = [str(d) for d in dirs]
    common = dict(value_dirs=dirs, batch=args.batch, progress=not args.no_progress)

    def values_of(rows, split, k):  # [V, N, P]: as the run recorded them, or recomputed
        if args.from_records:
            return recorded_values(rows, k, len(args.extra_value))
        return pool_values(rows, args.data, split, k=k, **common)

    val = read_records(args.select_on)[: args.limit]
    k = proposals_of(val, args.proposals)
    values = values_of(val, args.select_split, k)
    table, check = study(val, k, values, names, args.value)
    best = max(table, key=lambda row: row["mean"])
    ptable = pipeline_table(val, k, values, names)
    pbest = max(ptable, key=lambda row: row["mean"])  # first of the ties: the smaller set
    strip = lambda row: {x: row[x] for x in row if x != "per_category"}  # noqa: E731
    result = {
        "select_on": args.select_on,
        "select_on_pairs": len(val),
        "pool": POOL,
        "values": names,
        "rule": {"rule": selection.CHOSEN.rule, "depth_m": selection.CHOSEN.depth,
                 "radius_m": selection.CHOSEN.radius, "max_points": selection.CHOSEN.max_points},
        "v_check_select_on": check,
        "any_refined_select_on": any_refined(val, k, POOL),
        "chosen": strip(best),
        "table": [strip(row) for row in table],
        "v_source": "records" if args.from_records else "recomputed",
        "pipeline_table": [strip(row) for row in ptable],
        "chosen_rank_values": pbest["rank_values"],
        "device": str(jax.devices()[0]),
    }  # fmt: skip
    print(f"validation ({len(val)} pairs): run's V {table[0]['mean']:.1f} %, best "
          f"{best['mean']:.1f} % ({best['score']}); the pipeline's ranking: {pbest['score']} "
          f"{pbest['mean']:.1f} %; V check {check}")  # fmt: skip
    if args.apply_to:
        held = read_records(args.apply_to)[: args.limit]
        kh = proposals_of(held, args.proposals)
        hvalues = values_of(held, args.apply_split, kh)
        htable, hcheck = study(held, kh, hvalues, names, args.value)
        pick = next(r for r in htable if r["score"] == best["score"])
        hptable = pipeline_table(held, kh, hvalues, names)
        result["apply_to"] = args.apply_to
        result["held_out"] = {
            "pairs": len(held),
            "run_v": htable[0],
            "chosen": pick,
            "any_refined": any_refined(held, kh, POOL),
            "v_check": hcheck,
            "table": [strip(row) for row in htable],
            "pipeline_table": [strip(row) for row in hptable],
            "pipeline_chosen": next(r for r in hptable if r["score"] == pbest["score"]),
        }
        print(f"held-out ({len(held)} pairs): run's V {htable[0]['mean']:.1f} %, chosen "
              f"{pick['mean']:.1f} % ({pick['score']}); V check {hcheck}")  # fmt: skip
    refine.write_json(Path(args.out), result)
    return result


if __name__ == "__main__":
    _cli.run(main)
