"""Held-out hanging success of the whole where-to-hang pipeline (Stages 1, 1+2, 1+3, 1-3).

The protocol is ``omnihang_jax.evaluate``'s (module docstring there): one candidate per pair
is simulated for 1 s under ``protocol_stability``; success = STABLE; the score is the mean over
object categories. What differs is only which candidate counts:

* ``stage1`` / ``stage1_2``: the first of the K proposals (no score to rank by);
* ``stage1_3``: CEM on V from each Stage-1 proposal, the candidate with the best final V;
* ``all_stages``: CEM on V from each Stage-2 proposal, the best final V (facts: "the
  candidate with the best final Stage-3 score is evaluated").

All 4K candidates of a pair are simulated (one batched job per pair in a process pool) so the
same run also reports: any-of-K per stage, V as a ranker of the *unrefined* Stage-2
proposals (best initial V against any-of-K), CEM's gain per proposal, V's accuracy on every
simulated candidate, and the ceiling of CEM's box (a ground-truth stable pose within +-2 cm
and 0.5 rad of some proposal).
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from omnihang_jax import dataset_bridge, refine, selection, stage3
from omnihang_jax.evaluate import pose_errors, summarize_success

__all__ = ["STAGES", "evaluate_pipeline", "within_box", "summarize_pipeline"]

STAGES = ("stage1", "stage1_2", "stage1_3", "all_stages")
# training-free variant of the answer: the all-stages pose backed out of the observed support
# along its normals (omnihang_jax.heuristics.separate; 703 of 1,814 answers of the first
# evaluation failed by > 3 mm of penetration)
VARIANTS = ("all_stages_separated", "all_stages_paper")
# all_stages_paper: the paper's answer (highest final V among the Stage-2 starts' refined
# candidates) recorded beside the configured one (``select`` / ``pool_starts``)
PAPER = {"stage1": 36.0, "stage1_2": 34.2, "stage1_3": 56.2, "all_stages": 68.3}


class _Truth(NamedTuple):
    """What ``pose_errors`` reads of a HangSample."""

    stable_poses: np.ndarray
    pose_mask: np.ndarray


def within_box(poses: np.ndarray, targets: np.ndarray, translation: float, rotation: float):
    """[K] bool: some target pose lies within +-``translation`` per axis and ``rotation``
    rad of geodesic angle of each pose (the reach of one CEM run)."""
    from scipy.spatial.transform import Rotation

    if len(targets) == 0:
        return np.zeros(len(poses), bool)
    dt = np.abs(poses[:, None, :3] - targets[None, :, :3]).max(-1)  # [K, D]
    rp = Rotation.from_quat(np.roll(poses[:, 3:], -1, axis=1))
    rt = Rotation.from_quat(np.roll(targets[:, 3:], -1, axis=1))
    ang = np.stack([(rp[i].inv() * rt).magnitude() for i in range(len(poses))])  # [K, D]
    return np.any((dt <= translation) & (ang <= rotation), axis=1)


def evaluate_pipeline(
    files: Sequence[str | os.PathLike],
    weights: str | os.PathLike,
    value_dir: str | os.PathLike,
    dataset_dir: str | os.PathLike,
    num_proposals: int = 5,
    cem: stage3.CEMConfig = stage3.CEMConfig(),
    batch: int = 16,
    workers: int = 0,
    seed: int = 0,
    progress: bool = True,
    stage2_clearance: float | None = None,
    select: selection.SelectConfig = selection.SelectConfig(),
    pool_starts: bool = False,
    rank_value_dirs: Sequence[str | os.PathLike] = (),
    rank_with_value: bool = True,
    cem_stage1: stage3.CEMConfig | None = None,
    rank_subsets: int = 1,
    view: tuple[int, int] = (0, 1),
) -> tuple[list[dict], dict]:
    """Run Stages 1-3 on every pair file and simulate every candidate. Returns (records,
    timings). ``stage2_clearance`` (m): replaces the model's ``Stage2Config.clearance`` (None:
    the model's own); Stage 2 gets each pair's observed support normals either way. ``select``:
    the rule that picks the Stages 1+3 and all-stages answers among the refined candidates
    (``omnihang_jax.selection``; default the paper's highest V); ``pool_starts``: the
    all-stages answer is picked among the 2K candidates refined from Stages 1 and 2 (as
    ``stage3.ANSWER_PIPELINE``), not only the Stage-2 starts'; the paper's answer is recorded
    beside it either way (``all_stages_paper``). Every record also holds
    every candidate's V (``v``) and observed-cloud inside counts (``inside_counts``, for each
    (depth, radius) of ``selection.INSIDE_GRID``): rules can be studied after the run
    (``experiments.rerank_stage3``). ``rank_value_dirs``: more value folders; the refined
    candidates are then ranked by the mean log V over the CEM's V and these
    (``stage3.make_ensemble_score``, as ``PipelineConfig.rank_values``), and each record also
    holds every candidate's V under each of them (``v_rank``); ``v`` stays the CEM's V and
    ``all_stages_paper`` its highest V. ``rank_with_value=False``: the ``rank_value_dirs``
    rank alone, without the CEM's V (``PipelineConfig.rank_with_value``). ``cem_stage1``: the
    CEM of the Stage-1 starts when it differs from ``cem`` (e.g. more rounds there only).
    ``rank_subsets``: each ranking network scores on that many evenly spaced subsets of the
    clouds (``PipelineConfig.rank_subsets``); ``v_rank`` then holds each network's geometric
    mean over them. ``view`` = (j, T): CEM's V, every V recorded and the ranking networks see
    subset j of T of the clouds (``stage3.subset_clouds``) instead of subset 0: the same
    pipeline on another subsample (twenty-sixth session)."""
    from omnihang_jax.predict import load_predictor, load_rank_values
    from sim import kernels

    t0 = time.time()
    overrides = None if stage2_clearance is None else {"clearance": float(stage2_clearance)}
    predictor = load_predictor(weights, stage2_overrides=overrides)
    value_config, value_params = refine.load_value(value_dir)
    refine_fn = jax.jit(stage3.make_refiner(value_config, cem))
    refine_fn1 = refine_fn
    if cem_stage1 is not None and cem_stage1 != cem:
        refine_fn1 = jax.jit(stage3.make_refiner(value_config, cem_stage1))
    value_fn = jax.jit(stage3.make_value(value_config).value)
    rank_configs, rank_params = load_rank_values(rank_value_dirs)
    view = tuple(view)
    ensemble_fn = jax.jit(
        stage3.make_ensemble_score(rank_configs, rank_with_value, rank_subsets, view)
    )
    rank_views = [(j, rank_subsets) for j in range(rank_subsets)] if rank_subsets > 1 else [view]
    jits = {c: jax.jit(stage3.make_value(c).value) for c in set(rank_configs)}  # one per config
    rank_value_fns = [jits[c] for c in rank_configs]

    @jax.jit
    def separate_fn(full, poses):  # [B, ...] clouds, [B, 7] -> [B, 7], one pair at a time
        from omnihang_jax.heuristics import separate

        def one(args):
            op, sp, sn, pose = args
            return separate(op, sp, sn, pose)[0]

        return jax.lax.map(one, (full.object_points, full.support_points,
                                 full.support_normals, poses))  # fmt: skip

    grid = selection.INSIDE_GRID
    if (select.depth, select.radius) not in grid:
        grid = grid + ((select.depth, select.radius),)
    g_select = grid.index((select.depth, select.radius))

    @jax.jit
    def counts_fn(full, poses):  # [B, ...] full clouds, [B, P, 7] -> [B, G, P] int32
        def one(args):
            op, sp, sn, p = args
            return selection.inside_counts_grid(op, sp, sn, p, grid)

        return jax.lax.map(one, (full.object_points, full.support_points,
                                 full.support_normals, poses))  # fmt: skip

    key = jax.random.key(seed)
    k = num_proposals
    records, jobs, cands = [], [], []
    t_net = 0.0
    bar = tqdm(range(0, len(files), batch), desc="stages 1-3", disable=not progress)
    for i in bar:
        chunk = list(files[i : i + batch])
        m = len(chunk)
        loaded = [dataset_bridge.load_pair_file(f) for f in chunk]
        loaded += [loaded[0]] * (batch - m)  # pad: one compilation
        samples = [s for s, _ in loaded]
        full = stage3.stack_clouds(samples)
        tn = time.time()
        pred = predictor(full.object_points, full.support_points,
                         key=jax.random.fold_in(key, i), num_proposals=k,
                         support_normals=full.support_normals)  # fmt: skip
        small = stage3.subset_clouds(jax.tree.map(jnp.asarray, full), value_config, *view)
        r2 = refine_fn(value_params, jax.random.fold_in(key, 2 * i + 1), small,
                       jnp.asarray(pred.stage2_poses))  # fmt: skip
        r1 = refine_fn1(value_params, jax.random.fold_in(key, 2 * i + 2), small,
                       jnp.asarray(pred.stage1_poses))  # fmt: skip
        # the answers: the rule over the refined candidates' final V and inside counts
        fullj = jax.tree.map(jnp.asarray, full)
        cand = jnp.concatenate([jnp.asarray(pred.stage1_poses), jnp.asarray(pred.stage2_poses),
                                r1.poses, r2.poses], axis=1)  # [B, 4K, 7]  # fmt: skip
        counts = counts_fn(fullj, cand)  # [B, G, 4K]
        f1, f2 = r1.scores, r2.scores  # the final scores that rank: the CEM's V or the ensemble
        if rank_params:
            f1 = ensemble_fn(r1.scores, rank_params, fullj, r1.poses)
            f2 = ensemble_fn(r2.scores, rank_params, fullj, r2.poses)
        best1 = selection.select(f1, counts[:, g_select, 2 * k : 3 * k], select)
        best2 = selection.select(f2, counts[:, g_select, 3 * k :], select)
        if pool_starts:  # the answer among all 2K refined candidates (stage3.ANSWER_PIPELINE)
            keys = jnp.concatenate(
                [selection.select_key(f1, counts[:, g_select, 2 * k : 3 * k], select),
                 selection.select_key(f2, counts[:, g_select, 3 * k :], select)], axis=1,
            )  # fmt: skip
            answer = 2 * k + jnp.argmax(keys, axis=1)  # index into the 4K candidates
        else:
            answer = 3 * k + best2
        # V of the unrefined Stage-2 proposals is r2.initial_scores; V of every candidate:
        chosen = jnp.take_along_axis(cand, answer[:, None, None], axis=1)[:, 0]
        separated = separate_fn(fullj, chosen)
        allp = jnp.concatenate([cand, separated[:, None]], axis=1)  # [B, 4K+1, 7]
        tiled = jax.tree.map(lambda x: jnp.repeat(x, 4 * k + 1, axis=0), small)
        v_all = value_fn(value_params, tiled, allp.reshape(-1, 7)).reshape(batch, 4 * k + 1)
        v_rank = []  # each ranking network on its own subsample of the clouds
        for fn, c, p in zip(rank_value_fns, rank_configs, rank_params, strict=True):
            vs = []
            for j, of in rank_views:
                tiled_rank = jax.tree.map(lambda x: jnp.repeat(x, 4 * k + 1, axis=0),
                                          stage3.subset_clouds(fullj, c, j, of))  # fmt: skip
                vs.append(fn(p, tiled_rank, allp.reshape(-1, 7)).reshape(batch, 4 * k + 1))
            if len(vs) > 1:  # the geometric mean over the subsets, as the ensemble ranks
                vs = [jnp.exp(jnp.mean(jnp.log(jnp.clip(jnp.stack(vs), 1e-12, 1.0)), axis=0))]
            v_rank.append(np.asarray(vs[0]))
        jax.block_until_ready(v_all)
        t_net += time.time() - tn
        allp, v_all, counts = np.asarray(allp), np.asarray(v_all), np.asarray(counts)
        best1, best2, best_v = np.asarray(best1), np.asarray(best2), np.asarray(r2.best)
        answer = np.asarray(answer)
        for j in range(m):
            sample, meta = loaded[j]
            records.append({
                "pair_index": int(meta["pair_index"]),
                "object": str(meta["object_name"]),
                "support": str(meta["support_name"]),
                "category": str(meta["object_category"]),
                "family": str(meta["support_family"]),
                "file": os.path.basename(os.fspath(chunk[j])),
                "best_stage1_3": int(best1[j]),
                "best_all_stages": int(best2[j]),
                "best_all_stages_value": int(best_v[j]),  # the paper's rule (highest V)
                "answer_index": int(answer[j]),  # the all-stages answer in the 4K+1 candidates
                "best_initial_v": int(np.argmax(np.asarray(r2.initial_scores[j]))),
                "v": v_all[j].tolist(),
                **({"v_rank": [v[j].tolist() for v in v_rank]} if rank_params else {}),
                # every candidate [4K+1, 7] (Stage 1, 1+2, 1+3, all stages, separated): for
                # selection rules studied after the run (experiments.rerank_stage3)
                "poses_all": np.round(allp[j], 6).tolist(),
                # object points inside the observed support, candidates 0..4K-1, per setting
                "inside_counts": {selection.grid_key(d, r): counts[j, g].tolist()
                                  for g, (d, r) in enumerate(grid)},  # fmt: skip
                # the ground truth only: the clouds of 1,814 pairs need not stay in memory
                "_truth": _Truth(np.asarray(sample.stable_poses), np.asarray(sample.pose_mask)),
            })  # fmt: skip
            jobs.append((str(meta["object_name"]), str(meta["support_name"]), allp[j]))
            cands.append(allp[j])
    labeller = refine.Labeller(dataset_dir, workers)
    ts = time.time()
    try:
        results = labeller(jobs, progress=progress)
    finally:
        labeller.close()
    t_sim = time.time() - ts
    for rec, (status, pen), poses in zip(records, results, cands, strict=True):
        sample = rec.pop("_truth")
        ok = status == kernels.STABLE
        names = kernels.STATUS_NAMES
        gt = np.asarray(sample.stable_poses)[np.asarray(sample.pose_mask, bool)]
        sl = {"stage1": slice(0, k), "stage1_2": slice(k, 2 * k),
              "stage1_3": slice(2 * k, 3 * k),
              "all_stages": slice(2 * k if pool_starts else 3 * k, 4 * k),
              "all_stages_separated": slice(4 * k, 4 * k + 1),
              "all_stages_paper": slice(3 * k, 4 * k)}  # fmt: skip
        pick = {"stage1": 0, "stage1_2": 0, "stage1_3": rec["best_stage1_3"],
                "all_stages": rec["answer_index"] - sl["all_stages"].start,
                "all_stages_separated": 0,
                "all_stages_paper": rec["best_all_stages_value"]}  # fmt: skip
        for stage, s in sl.items():
            c = pick[stage]
            err = pose_errors(poses[s], sample)
            rec[stage] = {
                "success": bool(ok[s][c]),
                "status": names[status[s][c]],
                "any_of_k": bool(ok[s].any()),
                "statuses": [names[x] for x in status[s]],
                "initial_penetration_m": float(pen[s][c]),
                "pose": poses[s][c].tolist(),
                **{key: float(v[c]) for key, v in err.items()},
            }
        rec["ranker_initial_v_success"] = bool(ok[k : 2 * k][rec["best_initial_v"]])
        rec["ceiling_stage1"] = bool(within_box(poses[:k], gt, cem.clip_translation,
                                                cem.clip_rotation).any())  # fmt: skip
        rec["ceiling_stage2"] = bool(within_box(poses[k : 2 * k], gt, cem.clip_translation,
                                                cem.clip_rotation).any())  # fmt: skip
        rec["stable_all"] = ok.tolist()
    timings = {"pairs": len(records), "network_s": t_net, "simulation_s": t_sim,
               "wall_s": time.time() - t0}  # fmt: skip
    return records, timings


def _pct(x) -> float:
    x = np.asarray(x, float)
    return float(100 * x.mean()) if len(x) else float("nan")


def summarize_pipeline(records: Sequence[dict], k: int) -> dict:
    """The four stages' success (mean over categories, per category), any-of-K, V as a ranker,
    CEM gain, V's accuracy on all simulated candidates, the box ceiling, status counts."""
    stages = STAGES + tuple(v for v in VARIANTS if records and v in records[0])
    out = {s: summarize_success(records, s) for s in stages}
    for s in stages:
        out[s]["any_of_k"] = summarize_success(records, s, "any_of_k")["mean"]
        out[s]["statuses"] = {}
        for r in records:
            out[s]["statuses"][r[s]["status"]] = out[s]["statuses"].get(r[s]["status"], 0) + 1
    by_cat: dict[str, list] = {}
    for r in records:
        by_cat.setdefault(r["category"], []).append(r)

    def cat_mean(fn):
        return float(np.mean([_pct([fn(r) for r in rs]) for rs in by_cat.values()]))

    ok = np.array([r["stable_all"][: 4 * k] for r in records], bool)  # [n, 4K]
    v = np.array([r["v"][: 4 * k] for r in records], float)
    out["ranker"] = {
        "note": "V picks one of the K unrefined Stage-2 proposals (best initial V) vs the first"
        " proposal and vs any of K (a perfect ranker)",
        "best_initial_v": cat_mean(lambda r: r["ranker_initial_v_success"]),
        "first": out["stage1_2"]["mean"],
        "any_of_k": out["stage1_2"]["any_of_k"],
    }
    out["cem_gain"] = {
        "note": "success rate over all K proposals of every pair, before and after CEM",
        "stage1_before": _pct(ok[:, :k]),
        "stage1_after": _pct(ok[:, 2 * k : 3 * k]),
        "stage2_before": _pct(ok[:, k : 2 * k]),
        "stage2_after": _pct(ok[:, 3 * k :]),
    }
    out["value_accuracy"] = refine.classification_metrics(v.reshape(-1), ok.reshape(-1))
    out["ceiling"] = {
        "note": "a ground-truth stable pose within +-2 cm per axis and 0.5 rad of some proposal",
        "stage1": cat_mean(lambda r: r["ceiling_stage1"]),
        "stage2": cat_mean(lambda r: r["ceiling_stage2"]),
    }
    if records and "inside_counts" in records[0]:
        out["answer_failures"] = answer_failures(records, k)
    out["pairs"] = len(records)
    out["paper"] = PAPER
    return out


def answer_failures(records: Sequence[dict], k: int,
                    rule: selection.SelectConfig = selection.CHOSEN) -> dict:  # fmt: skip
    """Why the all-stages answers that fail do (pairs): among the 2K refined candidates
    (indices 2K..4K of ``stable_all``), "clear" = at most ``rule.max_points`` observed object
    points more than ``rule.depth`` inside the observed support (``inside_counts``):
    ``ranking`` (another clear candidate hangs: the score picked wrong), ``no_hanging``
    (no refined candidate hangs: proposals and CEM), ``only_inside_hang`` (only candidates the
    rule sets back hang), ``no_clear`` (no clear candidate at all)."""
    key = selection.grid_key(rule.depth, rule.radius)
    out = {"failed": 0, "ranking": 0, "no_hanging": 0, "only_inside_hang": 0, "no_clear": 0}
    for r in records:
        if r["all_stages"]["success"]:
            continue
        out["failed"] += 1
        ok = np.asarray(r["stable_all"][2 * k : 4 * k], bool)
        clear = np.asarray(r["inside_counts"][key][2 * k : 4 * k]) <= rule.max_points
        if not clear.any():
            out["no_clear"] += 1
        elif not ok.any():
            out["no_hanging"] += 1
        elif (ok & clear).any():
            out["ranking"] += 1
        else:
            out["only_inside_hang"] += 1
    out["note"] = (f"failed all-stages answers by cause; clear = at most {rule.max_points} "
                   f"observed object points > {rule.depth * 1e3:g} mm inside the observed "
                   f"support within {rule.radius * 1e3:g} mm (the answer rule's test)")  # fmt: skip
    return out
