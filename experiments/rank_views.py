"""The default pipeline's answer from its records, re-ranked: new ranking networks, sets of
rankers chosen over several CEM keys, and two probes of the pooled candidates.

    # 1. a ranker's log P(hang) for every pooled candidate of a key's two view runs (CPU or GPU)
    python -m experiments.rank_views score --ranker out/s31/rk/ctl/value --name ctl \\
        --key val0 results/validation_where_s27/val_k10_v0.pairs.jsonl.gz \\
        results/validation_where_s27/val_k10_v1of2.pairs.jsonl.gz \\
        --clouds datasets/paper/derived/train --out out/s31/scores
    # 2. every set of the committed rankers and the scored ones, chosen on the validation keys
    python -m experiments.rank_views sets --runs runs.json --scores out/s31/scores \\
        --names ctl dn d384 --out results/ranker_s31/sets.json
    # 3. the probes (no network): cross-view consensus, and four half-size runs
    python -m experiments.rank_views probes --runs runs.json --out results/ranker_s31/probes.json

``runs.json`` maps a key name to its view runs: ``{"val0": [VIEW0, VIEW1of2], ...}``, or the
three of the default pipeline (views 0, 1/2, 3/4: ``VIEW_SETS``, forty-seventh session);
names starting with ``val`` are validation-object runs (the choice is made on their mean),
``held`` held-out runs (reported). Thirty-first session (issue 12, docs/stage3.md).

The answer key is ``experiments.rerank_stage3.rule_keys``' (the rankers' mean log P from each
candidate's own view, observed inside points first), pooled over the two views as
``experiments.union_views`` does; with the committed rankers' recorded scores it reproduces the
records' answer exactly. A new ranker scores the candidates of view J/2 on subset J of 2 of
the observed clouds (``stage3.subset_clouds`` with the ranker's own config), as the pipeline
does.
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from pathlib import Path

import numpy as np

from experiments import _cli
from experiments.rerank_stage3 import (
    category_means,
    pool_indices,
    proposals_of,
    read_records,
    rule_keys,
)
from omnihang_jax import selection

COMMITTED = ("s20", "big1", "near")  # stage3.RANK_VALUES, in v_rank's order
# a key's view runs, in order: the twenty-seventh session's two views, the default's three
VIEW_SETS = {2: ((0, 1), (1, 2)), 3: ((0, 1), (1, 2), (3, 4))}


def load_key(runs: list[str]) -> dict:
    """The view runs of one key (``VIEW_SETS``) -> arrays over the pooled candidates: keys /
    clear / stable [N, V, 2K], poses [N, V, 2K, 7], ranks [N, V, R, 2K] (the committed rankers'
    recorded P), category, files, views."""
    if len(runs) not in VIEW_SETS:
        raise ValueError(
            f"a key needs its view runs ({' or '.join(map(str, VIEW_SETS))}: view 0, view 1/2"
            f"[, view 3/4]), got {len(runs)}"
        )
    rows = [read_records(p) for p in runs]
    order = [r["pair_index"] for r in rows[0]]
    if any([r["pair_index"] for r in rr] != order for rr in rows[1:]):
        raise ValueError(f"{runs}: the view runs hold different pairs")
    k = proposals_of(rows[0])
    idx = pool_indices(k, "stage1_2")
    parts = [rule_keys(rr, k) for rr in rows]
    grid = selection.grid_key(selection.CHOSEN.depth, selection.CHOSEN.radius)
    counts = np.stack(
        [np.asarray([np.asarray(r["inside_counts"][grid])[idx] for r in rr]) for rr in rows], 1
    )
    return dict(
        keys=np.stack([p[0] for p in parts], 1),
        clear=counts <= selection.CHOSEN.max_points,  # the rule ranks these by log P
        stable=np.stack([p[1] for p in parts], 1),
        poses=np.stack(
            [np.asarray([np.asarray(r["poses_all"])[idx] for r in rr], np.float32) for rr in rows],
            1,
        ),  # fmt: skip
        ranks=np.stack(
            [np.asarray([np.asarray(r["v_rank"])[:, idx] for r in rr]) for rr in rows], 1
        ),
        category=[r["category"] for r in rows[0]],
        files=[r["file"] for r in rows[0]],
        views=np.asarray(VIEW_SETS[len(runs)], np.int64),
    )


def pack(d: dict, path: str | Path) -> None:
    """What :func:`score` reads of a key (files, poses, views) -> one ``.npz``."""
    np.savez_compressed(path, files=np.asarray(d["files"]), poses=d["poses"], views=d["views"])


def load_pack(path: str | Path) -> dict:
    with np.load(path) as z:
        d = {"files": [str(f) for f in z["files"]], "poses": z["poses"], "views": z["views"]}
    if d["poses"].shape[:2] != (len(d["files"]), len(d["views"])):
        raise ValueError(f"{path}: poses {d['poses'].shape} for {len(d['files'])} pairs")
    return d


def category_mean(category, ok) -> float:
    """The figure everywhere: the mean over object categories (percent)."""
    return category_means([{"category": c} for c in category], ok)["mean"]


def answer(d: dict, score: np.ndarray) -> float:
    """The rule's success (mean over categories) with ``score`` [N, V, 2K] (log P) ranking the
    clear candidates; the non-clear ones keep their recorded key."""
    n = len(d["category"])
    key = np.where(d["clear"], score, d["keys"]).reshape(n, -1)
    return category_mean(d["category"], d["stable"].reshape(n, -1)[np.arange(n), key.argmax(1)])


def committed_scores(d: dict) -> dict:
    return {
        name: np.log(np.clip(d["ranks"][:, :, i], 1e-12, 1.0)) for i, name in enumerate(COMMITTED)
    }


# ----------------------------------------------------------------------------------------------


def score(ranker: str, d: dict, clouds_dir: str, batch: int = 8) -> np.ndarray:
    """[N, V, 2K] log P(hang) of every pooled candidate by the ranker in ``ranker``."""
    from types import SimpleNamespace

    from experiments.rank_subsets import load_clouds
    from experiments.train_ranker import make_scorer, score_table
    from omnihang_jax import refine, stage3
    from omnihang_jax.stage3 import PairClouds

    full = load_clouds(Path(clouds_dir), d["files"])
    stacked = PairClouds(*(np.stack([c[f] for c in full]) for f in range(4)))
    config, params = refine.load_value(ranker)
    scorer = make_scorer(config)
    out = np.zeros(d["poses"].shape[:3], np.float32)
    for v, (j, t) in enumerate(d["views"]):
        bank = SimpleNamespace(clouds=stage3.subset_clouds(stacked, config, int(j), int(t)))
        t0 = time.time()
        table = {"files": d["files"], "poses": d["poses"][:, v]}
        out[:, v] = score_table(scorer, params, bank, table, batch)
        print(f"view {j}/{t}: {len(d['files'])} pairs in {time.time() - t0:.0f} s", flush=True)
    if not np.all(np.isfinite(out)):
        raise RuntimeError(f"{ranker}: non-finite scores")
    return out


def sets(keys: dict[str, dict], extra: dict[str, dict[str, np.ndarray]]) -> dict:
    """Every non-empty set of the committed and the extra rankers scored on every key ->
    per set its success on each key, the validation mean and the held-out mean; ``chosen``:
    the best validation mean (ties: the smaller set)."""
    names = list(COMMITTED) + list(extra)
    table = []
    for r in range(1, len(names) + 1):
        for combo in itertools.combinations(names, r):
            row = {"set": "+".join(combo), "keys": {}}
            for key, d in keys.items():
                s = committed_scores(d) | {n: extra[n][key] for n in extra if key in extra[n]}
                if all(c in s for c in combo):
                    row["keys"][key] = answer(d, np.mean([s[c] for c in combo], 0))
            for part in ("val", "held"):
                got = [v for k, v in row["keys"].items() if k.startswith(part)]
                row[part] = float(np.mean(got)) if got else None
            table.append(row)
    ranked = sorted((r for r in table if r["val"] is not None), key=lambda r: -r["val"])
    committed = next(r for r in table if r["set"] == "+".join(COMMITTED))
    return {"committed": committed, "chosen": ranked[0] if ranked else None, "table": ranked}


def consensus_probe(d: dict, translation: float, rotation: float, cross_only: bool, lam: float):
    """The key plus ``lam`` x log(1 + the candidate's neighbours among the pooled candidates
    within ``translation`` m and ``rotation`` rad; ``cross_only``: of the other view only)."""
    n = len(d["category"])
    p = d["poses"].reshape(n, -1, 7)
    nv = d["poses"].shape[1]
    view = np.repeat(np.arange(nv), p.shape[1] // nv)
    dt = np.linalg.norm(p[:, :, None, :3] - p[:, None, :, :3], axis=-1)
    dot = np.abs(np.sum(p[:, :, None, 3:] * p[:, None, :, 3:], -1)).clip(0, 1)
    near = (dt < translation) & (2 * np.arccos(dot) < rotation)
    near &= (view[:, None] != view[None, :]) if cross_only else ~np.eye(p.shape[1], dtype=bool)
    score = np.mean(list(committed_scores(d).values()), 0)
    return answer(d, score + lam * np.log1p(near.sum(-1)).reshape(score.shape))


def half_runs_probe(a: dict, b: dict) -> dict:
    """Four runs of half the proposals (two keys x two views, the first K/2 Stage-1 and Stage-2
    starts of each) against the default's two runs of K: the same number of candidates."""
    k2 = a["keys"].shape[2] // 2
    half = np.r_[0 : k2 // 2, k2 : k2 + k2 // 2]
    keys = np.concatenate([a["keys"][:, :, half], b["keys"][:, :, half]], 1)
    stable = np.concatenate([a["stable"][:, :, half], b["stable"][:, :, half]], 1)
    n = len(a["category"])
    pick = keys.reshape(n, -1).argmax(1)
    full = a["keys"].reshape(n, -1).argmax(1)
    return {
        "four_half_runs": category_mean(a["category"], stable.reshape(n, -1)[np.arange(n), pick]),
        "default_first_key": category_mean(a["category"], a["stable"].reshape(n, -1)[np.arange(n), full]),
    }  # fmt: skip


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    sc = sub.add_parser("score", help="a ranker's log P of one key's pooled candidates (.npy)")
    sc.add_argument("--ranker", required=True, help="a value folder (config.json, params)")
    sc.add_argument("--name", required=True)
    sc.add_argument("--key", nargs="+", metavar="X",
                    help="KEY_NAME VIEW0_RECORDS VIEW1of2_RECORDS [VIEW3of4_RECORDS]")  # fmt: skip
    sc.add_argument(
        "--table",
        nargs="+",
        metavar="NPZ",
        help="instead of --key: pack's KEY_NAME.npz files (the key named by the file)",
    )
    sc.add_argument("--clouds", required=True, help="folder of the pairs' derived files")
    sc.add_argument("--out", required=True, help="folder: NAME_KEY.npy")
    pk = sub.add_parser("pack", help="every key's candidates as KEY.npz (for score --table)")
    pk.add_argument("--runs", required=True, help="JSON: key name -> its view runs' records")
    pk.add_argument("--out", required=True, help="folder")
    se = sub.add_parser("sets", help="sets of rankers chosen on the validation keys")
    pr = sub.add_parser("probes", help="cross-view consensus; four half-size runs")
    for p in (se, pr):
        p.add_argument("--runs", required=True, help="JSON: key name -> [view 0, view 1/2] records")
        p.add_argument("--out", required=True, help="JSON")
    se.add_argument("--scores", required=True, help="the score command's folder")
    se.add_argument("--names", nargs="*", default=[], help="scored rankers to add")
    args = ap.parse_args(argv)

    if args.command == "score":
        if bool(args.key) == bool(args.table):
            raise SystemExit("score: give --key KEY RUNS... or --table NPZ...")
        todo = [(args.key[0], lambda: load_key(args.key[1:]))] if args.key else [
            (Path(t).stem, lambda t=t: load_pack(t)) for t in args.table]  # fmt: skip
        outs = []
        for name_key, load in todo:
            out = Path(args.out) / f"{args.name}_{name_key}.npy"
            out.parent.mkdir(parents=True, exist_ok=True)
            np.save(out, score(args.ranker, load(), args.clouds))
            print(f"wrote {out}", flush=True)
            outs.append(str(out))
        return {"out": outs}

    runs = json.loads(Path(args.runs).read_text())
    if args.command == "pack":
        Path(args.out).mkdir(parents=True, exist_ok=True)
        for name, paths in runs.items():
            pack(load_key(paths), Path(args.out) / f"{name}.npz")
            print(f"packed {name}", flush=True)
        return {"out": args.out}
    keys = {name: load_key(paths) for name, paths in runs.items()}
    if args.command == "sets":
        extra = {}
        for n in args.names:
            extra[n] = {}
            for key in keys:
                f = Path(args.scores) / f"{n}_{key}.npy"
                if f.exists():
                    extra[n][key] = np.load(f)
        res = {"runs": runs, **sets(keys, extra)}
        for row in [res["committed"], *res["table"][:10]]:
            keys_txt = " ".join(f"{k} {v:.2f}" for k, v in row["keys"].items())
            print(f"{row['set']:<28} val {row['val'] or float('nan'):.2f} "
                  f"held {row['held'] or float('nan'):.2f}  {keys_txt}")  # fmt: skip
    else:
        grid = itertools.product(
            (0.005, 0.01, 0.02), (0.1, 0.2, 0.4), (True, False), (0.1, 0.3, 1.0)
        )
        rows = []
        for t, r, cross, lam in grid:
            row = dict(translation=t, rotation=r, cross_only=cross, lam=lam,
                       keys={k: consensus_probe(d, t, r, cross, lam) for k, d in keys.items()})  # fmt: skip
            for part in ("val", "held"):
                got = [v for k, v in row["keys"].items() if k.startswith(part)]
                row[part] = float(np.mean(got)) if got else None
            rows.append(row)
        base = {
            k: answer(d, np.mean(list(committed_scores(d).values()), 0)) for k, d in keys.items()
        }
        half = {}
        for part in ("val", "held"):
            names = [k for k in keys if k.startswith(part)]
            for a, b in itertools.combinations(names, 2):
                half[f"{a}+{b}"] = half_runs_probe(keys[a], keys[b])
        res = {"runs": runs, "default": base, "consensus": rows, "half_runs": half}
        best = max(rows, key=lambda r: r["val"] or -1)
        print(f"default {base}\nconsensus, best on validation: {best}\nhalf runs: {half}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    return res


if __name__ == "__main__":
    _cli.run(main)
