"""The Stage-3 answer picked by a smoothed V, studied after an evaluation run.

    python -m experiments.smooth_stage3 \\
        --select-on results/validation_where_s11/val_committed.pairs.jsonl.gz --select-split train \\
        --apply-to results/hanging_success_stage3_s10.pairs.jsonl.gz --apply-split test \\
        --out results/smooth_stage3.json

CEM maximises V, so a refined candidate may sit on a narrow peak of V. This scores every refined
candidate of a run (the 2K of the answer pool, Stages 1+3 and all stages) by V averaged over
``--samples`` poses around it (``stage3.make_smoothed_value``: Gaussian actions about the
candidate's contact pivot, the same actions for every candidate of a pair), for a grid of
(translation, rotation) widths and two averages (of P(hang), of log P(hang)), and replaces the
final V in the chosen rule (``selection.CHOSEN``, pooled: the highest score among the candidates
with no object point inside the observed support). As in ``experiments.rerank_stage3``, every
candidate of an ``eval_stage3`` run was simulated (``stable_all``), so a rule is scored without a
new simulation; the width is chosen on --select-on (pairs of validation OBJECTS) and applied
once to --apply-to (held-out pairs). The clouds come from the pair files the records name
(``DATA/derived/<split>/``); as a check, V of the unperturbed candidates is recomputed and
compared with the recorded one (``v_check``). Mean over categories as everywhere.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from experiments import _cli
from experiments.rerank_stage3 import (
    any_refined,
    pool_indices,
    proposals_of,
    read_records,
    successes,
)
from omnihang_jax import dataset_bridge, refine, selection, stage3

POOL = "stage1_2"
DEFAULT_WIDTHS = "0.001:0.02,0.001:0.05,0.002:0.02,0.002:0.05,0.002:0.1,0.004:0.05,0.004:0.1"


def parse_widths(text: str) -> list[tuple[float, float]]:
    out = []
    for item in text.split(","):
        t, _, r = item.partition(":")
        if not r:
            raise ValueError(f"--widths: {item!r} is not TRANSLATION:ROTATION (m:rad)")
        out.append((float(t), float(r)))
    return out


def record_batches(rows, data, split, batch, desc, progress):
    """The records in batches of ``batch`` (the last padded with its first record: one
    compilation) -> (m real records, the padded records, their full clouds as one batched
    PairClouds of device arrays), from the pair files the records name
    (``DATA/derived/<split>/``)."""
    folder = os.path.join(data, "derived", split)
    for i in tqdm(range(0, len(rows), batch), desc=f"{desc} ({split})", disable=not progress):
        chunk = rows[i : i + batch]
        m = len(chunk)
        chunk = chunk + [chunk[0]] * (batch - m)
        clouds = []
        for r in chunk:
            path = os.path.join(folder, r["file"])
            if not os.path.exists(path):
                raise FileNotFoundError(
                    f"{path}: the pair file of a record is missing; derive it "
                    f"(experiments.derive_dataset --split {split} --pairs-from RECORDS)"
                )
            sample, _ = dataset_bridge.load_pair_file(path)
            clouds.append(sample)
        yield m, chunk, jax.tree.map(jnp.asarray, stage3.stack_clouds(clouds))


def smoothed_scores(rows, data, split, value_dir, k, widths, samples, batch, seed, progress):
    """Per width: ([N, P] mean P(hang), [N, P] mean log P(hang)) of the pool's candidates, and
    [N, P] the recomputed plain V (the check against the records)."""
    value_config, params = refine.load_value(value_dir)
    idx = pool_indices(k, POOL)
    fns = {
        w: jax.jit(jax.vmap(
            stage3.make_smoothed_value(value_config, samples, w[0], w[1]),
            in_axes=(None, 0, 0, 0),
        ))
        for w in widths
    }  # fmt: skip
    value = stage3.make_value(value_config)
    plain_fn = jax.jit(
        jax.vmap(lambda p, c, poses: jnp.exp(value.score(p, c, poses)), in_axes=(None, 0, 0))
    )
    out = {w: ([], []) for w in widths}
    plain = []
    key = jax.random.key(seed)
    for m, chunk, full in record_batches(rows, data, split, batch, "smoothed V", progress):
        small = stage3.subsample_clouds(full, value_config)
        poses = jnp.asarray(np.asarray([r["poses_all"] for r in chunk], np.float32)[:, idx])
        # per pair a key of its own (folded with its pair index): reproducible, batch-free
        keys = jax.vmap(lambda n: jax.random.fold_in(key, n))(
            jnp.asarray([int(r["pair_index"]) for r in chunk])
        )
        plain.append(np.asarray(plain_fn(params, small, poses))[:m])
        for w, fn in fns.items():
            mean_v, mean_log = fn(params, keys, small, poses)
            out[w][0].append(np.asarray(mean_v)[:m])
            out[w][1].append(np.asarray(mean_log)[:m])
    result = {w: (np.concatenate(a), np.concatenate(b)) for w, (a, b) in out.items()}
    return result, np.concatenate(plain)


def with_scores(rows, k, scores):
    """The records with the pool candidates' ``v`` replaced by ``scores`` [N, P]."""
    idx = pool_indices(k, POOL)
    out = []
    for r, s in zip(rows, scores, strict=True):
        v = list(r["v"])
        for j, c in enumerate(idx):
            v[c] = float(s[j])
        out.append({**r, "v": v})
    return out


def evaluate_scores(rows, k, scores: dict) -> list[dict]:
    """The chosen rule's success with each named score [N, P] of the pool's candidates in
    place of the recorded V, one table row each (``score``: the name)."""
    return [{"score": name, **successes(with_scores(rows, k, s), k, POOL, selection.CHOSEN)}
            for name, s in scores.items()]  # fmt: skip


def evaluate(rows, k, smoothed, plain):
    """Success of the chosen rule with the recorded V and with each smoothed score."""
    idx = pool_indices(k, POOL)
    recorded = np.asarray([r["v"] for r in rows], np.float32)[:, idx]
    table = [{"score": "recorded V", **successes(rows, k, POOL, selection.CHOSEN)}]
    for (t, r), (mean_v, mean_log) in smoothed.items():
        for name, s in (("mean V", mean_v), ("mean log V", mean_log)):
            res = successes(with_scores(rows, k, s), k, POOL, selection.CHOSEN)
            table.append({"score": name, "sigma_translation_m": t, "sigma_rotation_rad": r, **res})
    check = {"max_abs_diff": float(np.max(np.abs(plain - recorded))),
             "mean_abs_diff": float(np.mean(np.abs(plain - recorded)))}  # fmt: skip
    return table, check


def record_study_parser(doc: str) -> argparse.ArgumentParser:
    """The arguments every study that recomputes V on an evaluation's records shares
    (this module, ``experiments.ensemble_stage3``): the runs, their pair files, their V, K."""
    parser = argparse.ArgumentParser(
        description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--select-on", required=True, help="validation run's .pairs.jsonl[.gz]")
    parser.add_argument("--select-split", default="train", help="derived split of its pairs")
    parser.add_argument("--apply-to", default=None, help="held-out run's .pairs.jsonl[.gz]")
    parser.add_argument("--apply-split", default="test")
    parser.add_argument("--data", default="datasets/paper", help="dataset with derived/<split>")
    parser.add_argument(
        "--value",
        required=True,
        help="V of the runs (the CEM's V they recorded: weights/value_small_paper until the "
        "thirteenth session, stage3.CEM_VALUE since)",
    )
    parser.add_argument(
        "--proposals", type=int, default=None,
        help="K of the runs, checked against their records (default: read from them)",
    )  # fmt: skip
    return parser


def main(argv=None) -> dict:
    parser = record_study_parser(__doc__)
    parser.add_argument("--widths", default=DEFAULT_WIDTHS,
                        help="comma-separated TRANSLATION:ROTATION sigmas (m:rad)")  # fmt: skip
    parser.add_argument("--samples", type=int, default=16, help="poses per average")
    parser.add_argument("--batch", type=int, default=16, help="pairs per call")
    parser.add_argument("--limit", type=int, default=None, help="first N records of each run")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="JSON")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.samples < 1 or args.batch < 1:
        parser.error("--samples and --batch must be >= 1")
    widths = parse_widths(args.widths)
    common = dict(value_dir=args.value, samples=args.samples, batch=args.batch, seed=args.seed,
                  progress=not args.no_progress)  # fmt: skip

    val = read_records(args.select_on)[: args.limit]
    k = proposals_of(val, args.proposals)
    smoothed, plain = smoothed_scores(val, args.data, args.select_split, k=k, widths=widths,
                                      **common)  # fmt: skip
    table, check = evaluate(val, k, smoothed, plain)
    best = max(table, key=lambda row: row["mean"])
    result = {
        "select_on": args.select_on,
        "select_on_pairs": len(val),
        "pool": POOL,
        "rule": {"rule": selection.CHOSEN.rule, "depth_m": selection.CHOSEN.depth,
                 "radius_m": selection.CHOSEN.radius, "max_points": selection.CHOSEN.max_points},
        "samples": args.samples,
        "seed": args.seed,
        "v_check_select_on": check,
        "any_refined_select_on": any_refined(val, k, POOL),
        "chosen": {x: best[x] for x in best if x != "per_category"},
        "table": [{x: row[x] for x in row if x != "per_category"} for row in table],
        "device": str(jax.devices()[0]),
    }  # fmt: skip
    print(f"validation ({len(val)} pairs): recorded V {table[0]['mean']:.1f} %, best "
          f"{best['mean']:.1f} % ({_label(best)}); V check {check}")  # fmt: skip
    if args.apply_to:
        held = read_records(args.apply_to)[: args.limit]
        kh = proposals_of(held, args.proposals)
        # only the chosen width (none when the recorded V won: V is still recomputed, the check)
        chosen = [(best["sigma_translation_m"], best["sigma_rotation_rad"])] if (
            "sigma_translation_m" in best) else []  # fmt: skip
        sm, pl = smoothed_scores(held, args.data, args.apply_split, k=kh, widths=chosen, **common)
        htable, hcheck = evaluate(held, kh, sm, pl)
        pick = next(r for r in htable if _setting(r) == _setting(best))
        result["apply_to"] = args.apply_to
        result["held_out"] = {
            "pairs": len(held),
            "recorded_v": htable[0],
            "chosen": pick,
            "any_refined": any_refined(held, kh, POOL),
            "v_check": hcheck,
            "table": [{x: row[x] for x in row if x != "per_category"} for row in htable],
        }
        print(f"held-out ({len(held)} pairs): recorded V {htable[0]['mean']:.1f} %, chosen "
              f"{pick['mean']:.1f} % ({_label(pick)}); V check {hcheck}")  # fmt: skip
    refine.write_json(Path(args.out), result)
    return result


def _setting(row: dict) -> tuple:
    return row["score"], row.get("sigma_translation_m"), row.get("sigma_rotation_rad")


def _label(row: dict) -> str:
    if "sigma_translation_m" not in row:
        return row["score"]
    return f"{row['score']}, {1000 * row['sigma_translation_m']:g} mm / {row['sigma_rotation_rad']:g} rad"


if __name__ == "__main__":
    _cli.run(main)
