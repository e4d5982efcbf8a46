"""Where to hang the external objects (``datasets/external``: public meshes in their authors'
frames, none used in training) on held-out library supports, through the `hang` command's own
code path.

    python -m experiments.external                       # every object x one held-out support
                                                         # of every family, seed 0
    python -m experiments.external --objects mug_pybullet,scissors_cc0scissors --families \\
        single_rod_hook,mug_tree --out out/external      # a few

Per (object, support) it runs :func:`omnihang_jax.hang.hang` with the mesh and the support's
library name (where to hang on the rendered clouds, then every candidate simulated on the meshes;
no planner) and records two answers, both judged on the meshes:

- ``meshes``: the command's verified answer (the first candidate that stays hanging in MuJoCo);
- ``clouds``: the clouds-only answer (the first candidate that stays on the observed clouds,
  ``hang.observed_check``, as the command answers when it only has clouds).

Records (one JSON line per pair, resumable) go to ``--records``; the summary (per object, per
category, the means) to ``--results`` under the config's name.
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path

import numpy as np

from experiments import _cli

MANIFEST = "datasets/external/manifest.json"


def heldout_supports(families: list[str] | None) -> list[str]:
    """The first held-out support of every support family (or of ``families``)."""
    from omnihang_jax import refine

    lib = refine.worker_library()
    first: dict[str, str] = {}
    for name in sorted(lib.split["test"]["supports"]):
        first.setdefault(lib.supports[name].category, name)
    if families:
        unknown = sorted(set(families) - set(first))
        if unknown:
            raise ValueError(
                f"--families: no held-out support of {unknown}; one of {sorted(first)}"
            )
        return [first[f] for f in families]
    return [first[f] for f in sorted(first)]


def read_objects(manifest: str | Path, names: list[str] | None) -> list[dict]:
    path = Path(manifest)
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: the external object set (datasets/external)")
    entries = json.loads(path.read_text())["objects"]
    if names:
        known = {e["name"] for e in entries}
        unknown = sorted(set(names) - known)
        if unknown:
            raise ValueError(f"--objects: {unknown} not in {path}")
        entries = [e for e in entries if e["name"] in names]
    return entries


def judge(entry: dict, support: str, config, predictor, root: Path) -> dict:
    """One pair through the hang command; both answers judged on the meshes."""
    from omnihang_jax import hang as hang_mod
    from omnihang_jax.refine import worker_library
    from sim import kernels

    t = time.perf_counter()
    res = hang_mod.hang(str(root / entry["file"]), support, config=config, predictor=predictor,
                        log=None)  # fmt: skip
    row = dict(object=entry["name"], category=entry["category"], support=support,
               seed=config.seed, candidates=int(len(res.candidates.poses)))  # fmt: skip
    if res.status is None:
        return dict(row, error="not verified: " + res.steps.get("check", ""))
    stable = res.status == kernels.STABLE
    if not len(stable):
        return dict(row, error="no candidates")
    # the answer the command gives from clouds alone: the observed-cloud check's pick
    sup_asset = worker_library().supports[support]
    top = hang_mod.where_config(config).check
    pick, _, _ = hang_mod.observed_check(res.object, res.support, sup_asset, res.candidates.poses,
                                         top, None)  # fmt: skip
    return dict(row, hanging=int(stable.sum()), meshes=res.verdict == "stable",
                clouds=bool(stable[pick]), clouds_pick=int(pick),
                seconds=round(time.perf_counter() - t, 1))  # fmt: skip


def summarise(rows: list[dict]) -> dict:
    ok = [r for r in rows if "error" not in r]
    per_object: dict[str, dict] = {}
    for r in ok:
        o = per_object.setdefault(r["object"], dict(category=r["category"], pairs=0, meshes=0,
                                                     clouds=0))  # fmt: skip
        o["pairs"] += 1
        o["meshes"] += r["meshes"]
        o["clouds"] += r["clouds"]
    for o in per_object.values():
        o["meshes"] = round(100 * o["meshes"] / o["pairs"], 1)
        o["clouds"] = round(100 * o["clouds"] / o["pairs"], 1)
    per_category: dict[str, dict] = {}
    for c in sorted({o["category"] for o in per_object.values()}):
        objs = [o for o in per_object.values() if o["category"] == c]
        per_category[c] = {k: round(float(np.mean([o[k] for o in objs])), 1)
                           for k in ("meshes", "clouds")}  # fmt: skip
    return dict(
        pairs=len(ok), errors=len(rows) - len(ok), objects=len(per_object),
        meshes=round(100 * float(np.mean([r["meshes"] for r in ok])), 1) if ok else None,
        clouds=round(100 * float(np.mean([r["clouds"] for r in ok])), 1) if ok else None,
        per_category=per_category, per_object=per_object,
    )  # fmt: skip


def main(argv=None) -> dict:
    from omnihang_jax import hang as hang_mod
    from omnihang_jax import predict, refine, where

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("--manifest", default=MANIFEST)
    p.add_argument("--objects", default=None, help="comma-separated names (default: all)")
    p.add_argument("--families", default=None,
                   help="comma-separated support families (default: every family)")  # fmt: skip
    p.add_argument("--where", default="default", choices=sorted(where.CONFIGS))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--data", default="datasets/paper", help="the dataset whose library holds "
                   "the held-out supports")  # fmt: skip
    p.add_argument("--records", default="out/external/records.jsonl")
    p.add_argument("--results", default="results/external_objects.json")
    args = p.parse_args(argv)
    entries = read_objects(args.manifest, args.objects.split(",") if args.objects else None)
    refine.library_pool(args.data, 0)
    supports = heldout_supports(args.families.split(",") if args.families else None)
    config = hang_mod.HangConfig(where=args.where, seed=args.seed, plan=False)
    predictor = predict.load_predictor(where.CONFIGS[args.where].stage12, seed=args.seed)
    records = Path(args.records)
    records.parent.mkdir(parents=True, exist_ok=True)
    rows = [json.loads(x) for x in records.read_text().splitlines()] if records.exists() else []
    done = {(r["object"], r["support"], r["seed"]) for r in rows}
    root = Path(args.manifest).parent
    todo = [(e, s) for e in entries for s in supports if (e["name"], s, args.seed) not in done]
    print(f"external: {len(entries)} objects x {len(supports)} supports; {len(todo)} to go")
    for i, (entry, support) in enumerate(todo, 1):
        try:
            row = judge(entry, support, config, predictor, root)
        except hang_mod.HangInputError as exc:  # said and kept: the object is reported, not lost
            row = dict(object=entry["name"], category=entry["category"], support=support,
                       seed=args.seed, error=str(exc))  # fmt: skip
        with records.open("a") as f:
            f.write(json.dumps(row) + "\n")
        rows.append(row)
        print(f"  {i}/{len(todo)} {entry['name']} on {support}: "
              + (row.get("error") or f"meshes {row['meshes']}, clouds {row['clouds']} "
                 f"({row['hanging']} of {row['candidates']} hang, {row['seconds']} s)"),
              flush=True)  # fmt: skip
    names = {e["name"] for e in entries}
    mine = [r for r in rows if r["object"] in names and r["support"] in supports
            and r["seed"] == args.seed]  # fmt: skip
    summary = dict(where=args.where, seed=args.seed, supports=supports,
                   date=datetime.date.today().isoformat(),
                   command="python -m experiments.external " + " ".join(sys.argv[1:] if argv is None else argv),
                   **summarise(mine))  # fmt: skip
    if args.results:
        from experiments.evaluate import merge_results

        merge_results(args.results, args.where, summary)
    print(json.dumps({k: v for k, v in summary.items() if k != "per_object"}, indent=1))
    return summary


if __name__ == "__main__":
    _cli.run(main)
