"""Issue 12 probe (forty-third session): how much do CEM's last iterations still find?

The default pipeline spends 88 % of its 97.1-ms latency in CEM (10 iterations of 32 poses from
every start of every view; docs/stage3.md "Thirty-second session"), and a fourth view of the
clouds does not fit under the 100-ms aim at 10 iterations. This runs the pipeline's CEM
(``stage3.make_cem`` on ``stage3.CEM_VALUE``, the facts' settings) from the recorded starts of
validation-object pairs (the Stage-1 and Stage-2 proposals of a three-view default run's view-0
records, ``poses_all[:2K]``) and reads each candidate's ``history`` (the best log V after every
iteration): how often, and by how much, iterations t+1..10 beat the best of the first t, and how
often the candidate with the best final V is already the best after t. A cheap reading of what
fewer iterations would lose, not a success rate (that needs the simulation: eval_stage3).

    python -m experiments.derive_dataset --data datasets/paper --split train \\
        --pairs-from out/s43/cem_pairs.jsonl --clouds-only          # the pairs' clouds first
    python scripts/probe_cem_iterations.py --pairs 40 --out results/stage3_s43/cem_iterations.json
"""

from __future__ import annotations

import argparse
import gzip
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from omnihang_jax import dataset_bridge, refine, stage3  # noqa: E402


def read_records(path: str, n: int) -> list[dict]:
    """``n`` records evenly spaced over the file (the records run object by object)."""
    opener = gzip.open if path.endswith(".gz") else open
    with opener(path, "rt") as f:
        rows = [json.loads(line) for line in f if line.strip()]
    pick = np.unique(np.linspace(0, len(rows) - 1, min(n, len(rows))).round().astype(int))
    return [rows[i] for i in pick]


def summarise(histories: np.ndarray, upto=(5, 6, 7, 8, 9)) -> dict:
    """histories [P, C, T] best log V after each iteration (P pairs, C candidates)."""
    final = histories[..., -1]
    v_final = np.exp(final)
    best_final = np.argmax(final, axis=1)
    out = {}
    for t in upto:
        at = histories[..., t - 1]
        gain = np.exp(final) - np.exp(at)  # in V (probability), >= 0
        out[str(t)] = dict(
            candidates_improved_after=round(float((final > at + 1e-6).mean()), 4),
            mean_gain_in_v=round(float(gain.mean()), 5),
            p90_gain_in_v=round(float(np.quantile(gain, 0.9)), 5),
            same_best_candidate=round(float((np.argmax(at, axis=1) == best_final).mean()), 4),
            best_candidate_gain_in_v=round(
                float(np.mean(v_final.max(axis=1) - np.exp(at).max(axis=1))), 5
            ),
        )
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--records", default="results/validation_where_s27/val_k10_v0.pairs.jsonl.gz")
    ap.add_argument("--derived", default="datasets/paper/derived/train_clouds")
    ap.add_argument("--value", default=stage3.CEM_VALUE)
    ap.add_argument("--pairs", type=int, default=40)
    ap.add_argument("--proposals", type=int, default=10, help="K of the records")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--list", default=None, help="write the pairs' list for derive_dataset and stop"
    )
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)

    records = read_records(args.records, args.pairs)
    if args.list:
        Path(args.list).parent.mkdir(parents=True, exist_ok=True)
        Path(args.list).write_text("".join(
            json.dumps(dict(pair_index=r["pair_index"], file=r["file"])) + "\n" for r in records
        ))  # fmt: skip
        print(f"{len(records)} pairs -> {args.list}")
        return {}
    config, params = refine.load_value(args.value)
    cem_config = stage3.CEMConfig()
    value = stage3.make_value(config)
    cem = stage3.make_cem(lambda poses, p, c: value.score(p, c, poses), cem_config)

    def one(key, start, clouds, p):
        return cem(key, start, stage3.contact_pivot(clouds, start), p, clouds).history

    run = jax.jit(jax.vmap(one, in_axes=(0, 0, None, None)))
    k2 = 2 * args.proposals
    histories, t0 = [], time.perf_counter()
    for i, rec in enumerate(tqdm(records, desc="pairs", disable=args.no_progress)):
        path = Path(args.derived, rec["file"])
        if not path.exists():
            raise SystemExit(f"{path} is missing: derive the pairs first (see --list)")
        sample, _ = dataset_bridge.load_pair_file(path)
        full = stage3.stack_clouds([sample])
        small = stage3.subset_clouds(jax.tree.map(jnp.asarray, full), config, 0, 1)
        small = jax.tree.map(lambda x: x[0], small)
        starts = jnp.asarray(np.asarray(rec["poses_all"], np.float32)[:k2])
        keys = jax.random.split(jax.random.fold_in(jax.random.key(args.seed), i), k2)
        histories.append(np.asarray(run(keys, starts, small, params)))
    histories = np.stack(histories)  # [P, 2K, T]
    result = dict(
        settings=vars(args),
        cem=dict(population=cem_config.population, iterations=cem_config.iterations,
                 elites=cem_config.elites),  # fmt: skip
        pairs=len(records), candidates_per_pair=k2,
        seconds=round(time.perf_counter() - t0, 1),
        mean_best_v_by_iteration=np.exp(histories).mean(axis=(0, 1)).round(5).tolist(),
        after_iteration=summarise(histories),
    )  # fmt: skip
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: result[k] for k in ("pairs", "seconds", "mean_best_v_by_iteration",
                                             "after_iteration")}, indent=1))  # fmt: skip
    return result


if __name__ == "__main__":
    main()
