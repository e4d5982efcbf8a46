"""``hang --heldout N``: the default answer on held-out library pairs, judged on the true meshes,
beside the rate ``experiments.evaluate where`` measured."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from omnihang_jax.hang_inputs import HangConfig, HangInputError, _say
from omnihang_jax.hang_outputs import _replace_folder

# ----------------------------------------------------------------------------- held-out pairs

HELDOUT_RESULTS = "results/hanging_success.json"  # the rate quoted beside a demo run


def heldout_pairs(n: int, dataset_dir: str | os.PathLike = "datasets/paper", seed: int = 0):
    """``n`` held-out (object, support) library names: pairs of the dataset's "test" split
    with labelled stable poses, spread over support families (round robin), and within a
    family over object categories and supports (the least used first, ties at random)."""
    import collections

    from omnihang_jax.dataset_bridge import read_recipe
    from sim import dataset

    recipe = read_recipe(dataset_dir)
    pairs = recipe["pairs"]
    labelled = {
        int(r["pair_index"]) for r in dataset.load_records(dataset_dir) if len(r["stable_poses"])
    }
    by_family: dict[str, list[tuple[str, str]]] = collections.defaultdict(list)
    for i, (o, s, split) in enumerate(pairs):
        if split == "test" and i in labelled:
            by_family[s.rsplit("_", 1)[0]].append((o, s))
    rng = np.random.default_rng(seed)
    families = sorted(by_family)
    rng.shuffle(families)
    used: collections.Counter = collections.Counter()
    chosen: list[tuple[str, str]] = []
    for k in range(min(n, sum(map(len, by_family.values())))):
        options = [p for p in by_family[families[k % len(families)]] if p not in chosen]
        if not options:
            continue
        cost = [used[p[0].rsplit("_", 1)[0]] + used[p[1]] + rng.random() for p in options]
        pick = options[int(np.argmin(cost))]
        used[pick[0].rsplit("_", 1)[0]] += 1
        used[pick[1]] += 1
        chosen.append(pick)
    return chosen


def heldout_rates(rows: list[dict]) -> dict:
    """Per support family and per object category: pairs, answers that hang, pairs where
    some candidate hangs."""
    import collections

    out: dict[str, dict] = {"per_support_family": {}, "per_object_category": {}}
    for key, field in (("per_support_family", "support"), ("per_object_category", "object")):
        table: dict = collections.defaultdict(lambda: [0, 0, 0])
        for r in rows:
            entry = table[r[field].rsplit("_", 1)[0]]
            entry[0] += 1
            entry[1] += int(r["answer"] == "stable")
            entry[2] += int(r["hung"])
        out[key] = {k: dict(pairs=v[0], answer_hangs=v[1], some_candidate_hangs=v[2])
                    for k, v in sorted(table.items())}  # fmt: skip
    return out


def expected_heldout(path: str | os.PathLike = HELDOUT_RESULTS, where: str = "default"):
    """The held-out rate of the answer ``where`` (``results/hanging_success.json``: all stages,
    mean over categories, %): the ``experiments.evaluate where`` entry of that config, else
    (the default answer) the figure of record; None when neither is there."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    entry = data.get(where)
    if isinstance(entry, dict) and "all_stages" in entry:
        return dict(all_stages=entry["all_stages"]["mean"], pairs=entry["pairs"],
                    seeds=entry["seeds"], source=entry["command"])  # fmt: skip
    record = data.get("all_stages") if where == "default" else None
    if isinstance(record, dict) and "mean" in record:
        return dict(all_stages=record["mean"], pairs=record.get("pairs"), seeds=record.get("seeds"),
                    source=record.get("command") or f"measured at {record.get('measured_at_commit')}")  # fmt: skip
    return None


def run_heldout(
    n: int,
    out: str | os.PathLike,
    config: HangConfig = HangConfig(),
    dataset_dir: str | os.PathLike = "datasets/paper",
    log: Callable[[str], None] | None = print,
    outputs: bool = True,
) -> dict:
    """:func:`hang` on ``n`` held-out pairs (:func:`heldout_pairs`), one output folder each,
    and ``OUT/heldout.json``. Per pair: ``answer``, the status on the true meshes of the answer
    from the clouds alone (the ranked candidates checked on the observed clouds, as the
    evaluation's ``all_stages``), and ``hung``, whether some candidate hangs (the answer ``hang``
    gives with meshes); beside them the rate ``experiments.evaluate where`` measured. The folder
    is written whole or not at all; ``outputs=False`` writes only heldout.json."""
    from tqdm.auto import tqdm

    from omnihang_jax.hang import hang, network_sizes, observed_check, where_config
    from sim.kernels import STATUS_NAMES

    out = Path(out)
    if out.exists() and not (out / "heldout.json").exists() and any(out.iterdir()):
        raise HangInputError(f"{out}: folder exists and is not a previous held-out run")
    network_sizes(config.stage12_folder())
    wc = where_config(config)
    pairs = heldout_pairs(n, dataset_dir, config.seed)
    _say(log, f"{len(pairs)} held-out pairs over {len({s.rsplit('_', 1)[0] for _, s in pairs})} "
              f"support families and {len({o.rsplit('_', 1)[0] for o, _ in pairs})} object categories")  # fmt: skip
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp-"))
    tmp.chmod(0o755)
    rows = []
    t0 = time.perf_counter()
    try:
        for i, (o, s) in enumerate(tqdm(pairs, desc="held-out pairs", disable=log is None)):
            folder = tmp / f"{i:02d}_{o}__{s}" if outputs else None
            r = hang(o, s, folder, config, log=None)
            pick = 0
            if wc.check > 0 and config.value != "off":
                pick, _, _ = observed_check(r.object, r.support, r.support.asset,
                                            r.candidates.poses, wc.check, None)  # fmt: skip
            rows.append(dict(
                object=o, support=s, answer=STATUS_NAMES[int(r.status[pick])], hung=r.hung,
                stable_candidates=int((r.status == 0).sum()), candidates=len(r.status),
                seconds=round(sum(r.timings.values()), 2),
            ))  # fmt: skip
        answers = sum(r["answer"] == "stable" for r in rows)
        summary = dict(
            pairs=len(rows), answer_hangs=answers, answer_rate=answers / max(1, len(rows)),
            some_candidate_hangs=sum(r["hung"] for r in rows), where=config.where,
            seconds=round(time.perf_counter() - t0, 1), **heldout_rates(rows),
        )  # fmt: skip
        record = dict(
            summary=summary,
            expected=expected_heldout(where=config.where),
            definition=(
                "answer: the answer from the clouds alone (the ranked candidates dropped on the "
                "observed clouds, the first that stays), simulated on the true meshes; hung: some "
                "candidate stays hanging (the answer hang gives with meshes). One rendered view "
                "per body (sim.camera.default_eyes), the evaluation protocol "
                "(omnihang_jax.evaluate.protocol_stability)."
            ),
            dataset=os.fspath(dataset_dir),
            pairs=rows,
        )
        (tmp / "heldout.json").write_text(json.dumps(record, indent=1))
        _replace_folder(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return record
