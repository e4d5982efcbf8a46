"""How to hang, evaluated: plan from a start pose in front of the support to a held-out pair's
hanging pose with four collision checkers, and check every returned path with the full meshes.

    python -m experiments.eval_paths --weights weights/collision_fast --pairs 40 \\
        --out out/paths --results results/paths.json --figure docs/img/paths.png
    # nce_geometric: its settings on training validation pairs, then planning
    python -m experiments.eval_paths --weights weights/collision_fast_gpu_near \\
        --select-geometric out/paths_hybrid/selection.json --val-pairs 60
    python -m experiments.eval_paths --weights weights/collision_fast_gpu_near --pairs 40 \\
        --methods nce_geometric --geometric out/paths_hybrid/selection.json --time-limit 15 \\
        --out out/paths_hybrid --results results/paths_hybrid.json
    # the symmetric test (support points behind the observed object surface too): its
    # settings with the one-sided ones fixed, then planning with both
    python -m experiments.eval_paths --weights weights/collision_fast_gpu_near_crop \\
        --select-geometric out/paths_hybrid_sym/selection.json --symmetric
    python -m experiments.eval_paths --weights weights/collision_fast_gpu_near_crop --pairs 40 \\
        --methods nce_geometric --symmetric --geometric out/paths_hybrid_sym/selection.json \\
        --time-limit 30 --out out/paths_hybrid_sym --results results/paths_hybrid_sym_crop_t30.json

Per held-out pair (``DATA/derived/collision/test``, derived on demand: a seeded random sample,
round robin over the object categories) and its first stable pose (the paper's protocol: the dataset's stable
poses as goals; ``--pairs-from RECORDS`` draws the pairs among an ``eval_stage3`` run's and
``--goal answer`` plans to that run's all-stages answer instead, the summary then adding
``goal_statuses`` and ``stable_goals``: the figures over the pairs whose answer hangs), OMPL's
RRT-Connect plans with (``omnihang_jax.planner``):

- ``nce``: the neural collision estimator on the partial clouds;
- ``hce``: the heuristic with normals predicted by the HCE normal net;
- ``hce_true_normals``: the same heuristic with the ray-cast normals;
- ``mesh``: MuJoCo on the full meshes (the paper's "ground truth" planner);
- ``nce_geometric`` (not in the default run; ``--methods nce_geometric``): the NCE OR an
  observed-cloud penetration test (``collision.nce_geometric_collides``: enough object points
  behind the observed support surface), its depth / radius / min points chosen on training
  validation pairs by ``--select-geometric`` (read back with ``--geometric``); with
  ``--symmetric`` the test also counts support points behind the observed object surface
  (``collision.GeometricConfig.symmetric``; ``--select-geometric --symmetric`` chooses that
  side's settings with the one-sided ones fixed);
- ``geometric`` (ablation, not in the default run): that penetration test alone.

Every returned path is interpolated every 2 mm (weighted SE(3) metric) and checked with the
full meshes; a path is collision-free if no state penetrates deeper than 1 mm. Precision =
collision-free paths / paths returned, recall = pairs with a collision-free path / all pairs,
F1; per object category and the mean over categories. Diagnostics: why paths are missing
(time-outs, estimator calls the start invalid) and where returned paths collide.

Writes ``--results`` (keys ``nce``, ``hce``, ``hce_true_normals``, ``mesh``,
``nce_geometric``: precision, recall, f1, per_category, median_planning_s, ...), ``OUT/pairs.jsonl`` (one line per pair and
method, resumable: pairs already there are not planned again), ``OUT/scenes/<pair>/<method>.xml``
(the pair's MJCF with the path as keyframes: ``python -m mujoco.viewer --mjcf=...``) and
with ``--figure`` a strip of frames of a few paths.
"""

from __future__ import annotations

import argparse
import dataclasses
import gzip
import json
import os
import sys
import time
from collections import Counter
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np
from tqdm.auto import tqdm

from experiments.train_collision import (
    SUBSET_SEED_OBJECT,
    SUBSET_SEED_SUPPORT,
    derive_collision_pairs,
    observed_gap,
    record_eyes,
)
from omnihang_jax import approach, collision, planner

METHODS = ("nce", "hce", "hce_true_normals", "mesh")  # the default run
ALL_METHODS = (*METHODS, "nce_geometric", "geometric")
VAL_EVERY = 20  # train_collision --val-every: training pairs kept for the NCE's validation
MINE_GAP = 0.03  # m: mined states whose observed clouds come closer than this are kept
MINE_VERSION = 1


class PairCase(NamedTuple):
    name: str
    meta: dict
    scene: object  # sim.scene.Scene
    object_points: np.ndarray  # [N, 3] object frame (full partial cloud)
    object_normals: np.ndarray  # [N, 3] its ray-cast outward normals
    support_points: np.ndarray  # [M, 3]
    support_normals: np.ndarray  # [M, 3]
    goal: np.ndarray  # [7]
    # --completion (twenty-fifth session): the completion networks' predicted points of each
    # body (object frame / support frame), None without
    predicted_object: np.ndarray | None = None
    predicted_support: np.ndarray | None = None
    wall_y: float | None = None  # the wall's front plane y = wall_y (None: free-standing)


class Answer(NamedTuple):
    """One record's all-stages answer: pose [7], simulated status, (object, support) names."""

    pose: np.ndarray
    status: str
    names: tuple = ()


def read_answers(path: str | os.PathLike) -> dict[int, Answer]:
    """The where-to-hang pipeline's answers as goals: ``pair_index -> Answer`` from an
    ``eval_stage3`` run's per-pair records (``.pairs.jsonl[.gz]``): the all-stages answer
    (``poses_all[answer_index]``) and its simulated status (stable / fallen / penetrating)."""
    opener = gzip.open if str(path).endswith(".gz") else open
    goals = {}
    with opener(path, "rt") as f:
        for line in f:
            if not line.strip():
                continue
            rec = json.loads(line)
            missing = [
                k for k in ("pair_index", "poses_all", "answer_index", "all_stages") if k not in rec
            ]
            if missing:
                raise ValueError(
                    f"{path}: a record without {missing} (not an eval_stage3 pairs file)"
                )
            pose = np.asarray(rec["poses_all"][rec["answer_index"]], float)
            if pose.shape != (7,) or not np.all(np.isfinite(pose)):
                raise ValueError(
                    f"{path}: pair {rec['pair_index']}: answer pose {pose.tolist()} is not 7 finite numbers"
                )
            names = (rec["object"], rec["support"]) if "object" in rec and "support" in rec else ()
            goals[int(rec["pair_index"])] = Answer(pose, str(rec["all_stages"]["status"]), names)
    if not goals:
        raise ValueError(f"{path}: no records")
    return goals


def load_pairs(
    data: str,
    n: int,
    workers: int = 1,
    progress: bool = False,
    records: dict | None = None,
    answer_goals: bool = False,
    split: str = "test",
    names: set[str] | None = None,
) -> list[PairCase]:
    """``n`` held-out pairs (derived on demand) with their scenes, drawn among the pairs of
    ``records`` (:func:`read_answers`) when given; goal = the pair's first stable pose, or with
    ``answer_goals`` the pipeline's answer in ``records`` (``meta["goal_status"]``: its
    simulated status). ``split="train"``: training pairs instead (``--mine``), never one of
    the NCE's validation pairs (``pair_index % VAL_EVERY == 0``) nor a record's. ``names``:
    only the pairs of these names get a case (their scenes built; ``--only-pairs``)."""
    if answer_goals and records is None:
        raise ValueError("answer goals need the pipeline's records")
    if split not in ("test", "train"):
        raise ValueError(f"split must be 'test' or 'train', got {split!r}")
    if split == "train" and records is not None:
        raise ValueError("--pairs-from records are held-out runs: not with training pairs")
    from omnihang_jax import dataset_bridge
    from sim.library import build_library
    from sim.scene import build_scene

    # a seeded random sample of the held-out pairs, round robin over object categories
    only = None if records is None else records.__contains__
    if split == "train":
        only = lambda i: i % VAL_EVERY != 0  # noqa: E731
    files = derive_collision_pairs(data, {split: n}, workers, progress, shuffle_seed=0, only=only)[
        split
    ]
    config = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(data))
    library = build_library(config.library, progress=False)
    if records is not None and len(files) < n:
        raise ValueError(
            f"{len(files)} held-out pairs of the dataset are among the {len(records)} records, "
            f"{n} asked: --pairs-from must be a held-out (test split) eval_stage3 run of this dataset"
        )
    cases = []
    for path in files:
        if names is not None and path.stem not in names:
            continue
        with np.load(path) as f:
            meta = {k: f[k].item() for k in ("pair_index", "object_name", "support_name")}
            meta |= {k: f[k].item() for k in ("object_category", "support_family", "split")}
            if meta["split"] != split:
                raise RuntimeError(f"{path} is not a {split}-split pair")
            obj = library.objects[meta["object_name"]]
            sup = library.supports[meta["support_name"]]
            goal = f["stable_poses"][0].astype(float)
            if answer_goals:
                rec = records[int(meta["pair_index"])]
                if rec.names and rec.names != (meta["object_name"], meta["support_name"]):
                    raise ValueError(
                        f"pair {meta['pair_index']}: the records name {rec.names}, the dataset "
                        f"{(meta['object_name'], meta['support_name'])}: another dataset's run"
                    )
                goal, meta["goal_status"] = rec.pose, rec.status
            cases.append(
                PairCase(
                    name=path.stem,
                    meta=meta,
                    scene=build_scene(obj, sup),
                    object_points=f["object_points"],
                    object_normals=f["object_normals"],
                    support_points=f["support_points"],
                    support_normals=f["support_normals"],
                    goal=goal,
                    wall_y=_wall_of(f),
                )
            )
    return cases


def _wall_of(f) -> float | None:
    """A pair file's wall plane y, None for a free-standing support (stored as NaN)."""
    if "wall_y" not in f.files or not np.isfinite(float(f["wall_y"])):
        return None
    return float(f["wall_y"])


class Estimators(NamedTuple):
    """Jitted ``collides`` functions and their parameters, loaded from a weights folder."""

    nce_config: collision.NCEConfig
    nce_params: dict
    normal_config: collision.NormalNetConfig
    normal_params: dict
    true_threshold: float
    nce: object
    heuristic: object
    normals: object
    nce_far_threshold: float | None = None  # see collision.goal_ball_collides
    nce_goal_ball: float = 0.0
    geometric: collision.GeometricConfig = collision.GeometricConfig()
    nce_geometric: object = None  # jitted collision.nce_geometric_collides
    geometric_alone: object = None  # jitted collision.geometric_collides (ablation)
    test_goal_ball: float = 0.0  # m: the hybrid's test is off this near the goal (ablation)
    # m: with far_ball > 0, the hybrid (and the NCE) first require this clearance between the
    # observed clouds beyond far_ball of the goal (planner.ClearanceFarFromGoal)
    far_clearance: float = 0.0
    far_ball: float = 0.0
    # with --completion: where the completed clouds replace the observed ones ("clear": the
    # returned path's clearing, "far": the clearance far from the goal)
    completion_in: tuple[str, ...] = ()
    # twenty-eighth session: a second NCE (config, params, jitted collides) asked only beyond
    # far_nce_ball of the goal, after the hybrid (eval_paths --far-nce: the completion-aware
    # NCE, which sees the hidden backs the transit collisions are made of)
    far_nce: tuple | None = None
    far_nce_ball: float = 0.0
    # twenty-ninth session: the observed object cloud kept this far in front of the known wall
    # plane (planner.WallChecker, first in the cascade); None: the wall is not checked
    wall_margin: float | None = None
    # thirtieth session: when a plan times out, plan again for fallback_time s with the NCE's
    # far threshold (beyond nce_goal_ball) raised to fallback_far_threshold (nce_fallback: the
    # jitted collision.goal_ball_collides with it); None: no second plan
    fallback_far_threshold: float | None = None
    fallback_time: float = 0.0
    nce_fallback: object = None
    # thirty-fourth session, a probe: the straight retreat (--retreat) chosen by the full meshes
    # (the oracle approach over the goal's last centimetres), the search by the estimators
    oracle_retreat: bool = False
    # thirty-fifth session: the straight retreat's directions ranked by the approach network
    # (approach.ApproachPredictor on the observed clouds; those at its threshold or above, best
    # first); approach_check "none": the best one is taken as free, "method": the first the
    # method's checker calls free
    approach: object = None
    approach_check: str = "none"
    # and with approach_open_side, none towards a wall-mounted support's wall (-y): a pre-goal
    # behind the object, between it and the wall, is a narrow place to plan to (device, OMPL
    # seed 3: the 10 pairs whose best direction was -y planned no free path, 9 timed out)
    approach_open_side: bool = False
    # thirty-sixth session: the replan after a time-out with the same approach ("same") or the
    # plain plan ("plain"): a time-out with an approach may mean its pre-goal is out of reach
    # (seed 1, open side: 8 time-outs used an approach, the plain plan had 2 of them free);
    # thirty-eighth session: "next", the second usable direction (plain when there is none)
    approach_replan: str = "same"
    # thirty-ninth session, a probe: on goals no straight move takes off the support but two do
    # (on the full meshes, >= 1 cm clear), the approach is that two-move route (the oracle);
    # elsewhere the approach network's rule as configured
    oracle_two_moves: bool = False
    # and, with oracle_lattice > 0 (m), on threaded goals (no one- or two-move way off) the
    # shortest lattice route of that step off the support (planner.lattice_retreat, meshes)
    oracle_lattice: float = 0.0
    # fortieth session: a route network (approach.ApproachPredictor with first_lengths: one or
    # two straight moves ending off the support) at its threshold; routes_mode "fill": asked
    # only where the straight approach rule gives none, "first": asked first; "only" (forty-third
    # session): asked first, and where it gives no route the plan is plain (no straight approach)
    routes: object = None
    routes_mode: str = "fill"
    # forty-first session: the route is asked of the planner's own observed clouds first:
    # routes_check "checker" takes the first confident route (best first, at most routes_tries)
    # whose states the method's checker calls free and whose end the observed clouds show at
    # least routes_end_gap (m) clear ("none": the best route, taken as free)
    routes_check: str = "none"
    routes_end_gap: float = 0.0
    routes_tries: int = 10


def with_fallback(est: Estimators, far_threshold: float, seconds: float) -> Estimators:
    """``est`` with a second plan after a time-out: the NCE beyond its goal ball at
    ``far_threshold`` (laxer than ``est.nce_far_threshold``, or equal: a replan with the same
    checker, OMPL's random stream continuing, so a fresh search) for ``seconds``. Thirtieth
    session: the time-outs' true paths are blocked far from the goal by NCE calls of 0.6-0.9
    (scripts/probe_timeouts.py). Thirty-third session: pooling the best hybrid's runs under
    three OMPL seeds, a replan after a time-out would return ~5 more paths of 80 at the same
    precision (scripts/probe_portfolio.py)."""
    if est.nce_far_threshold is None:
        raise ValueError("a fallback far threshold needs the goal-ball NCE (--nce-goal-ball > 0)")
    if not (far_threshold >= est.nce_far_threshold and seconds > 0):
        raise ValueError(
            f"the fallback's far threshold ({far_threshold}) must be laxer than the plan's "
            f"({est.nce_far_threshold}) or equal to it, and its time > 0 (got {seconds})"
        )
    fn = collision.goal_ball_collides(est.nce_config, far_threshold, est.nce_goal_ball)
    return est._replace(fallback_far_threshold=float(far_threshold),
                        fallback_time=float(seconds), nce_fallback=jax.jit(fn))  # fmt: skip


def load_estimators(
    weights: str,
    nce_threshold: float | None = None,
    nce_far_threshold: float | None = None,
    nce_goal_ball: float = 0.0,
    geometric: collision.GeometricConfig = collision.GeometricConfig(),
) -> Estimators:
    """The estimators of a weights folder; ``nce_threshold`` overrides the NCE's threshold;
    ``nce_far_threshold`` with ``nce_goal_ball`` > 0: ``collision.goal_ball_collides``;
    ``geometric``: the penetration test of ``nce_geometric`` (the NCE with its own
    threshold OR the test)."""
    nce_cfg, nce_params, _ = collision.load_estimator(Path(weights, "nce"))
    if nce_threshold is not None:
        nce_cfg = dataclasses.replace(nce_cfg, threshold=nce_threshold)
    normal_cfg, normal_params, _ = collision.load_estimator(Path(weights, "hce_normals"))
    true_json = Path(weights, "hce_true_normals.json")
    if not true_json.exists():
        raise FileNotFoundError(f"{true_json} not found: train with experiments.train_collision")
    true_threshold = float(json.loads(true_json.read_text())["threshold"])
    net = collision.make_normal_net(normal_cfg)
    return Estimators(
        nce_cfg,
        nce_params,
        normal_cfg,
        normal_params,
        true_threshold,
        jax.jit(
            collision.nce_collides(nce_cfg)
            if nce_far_threshold is None or nce_goal_ball <= 0
            else collision.goal_ball_collides(nce_cfg, nce_far_threshold, nce_goal_ball)
        ),
        jax.jit(collision.heuristic_score),
        jax.jit(lambda params, pts: net.apply(params, pts[None])[0]),
        nce_far_threshold if nce_goal_ball > 0 else None,
        nce_goal_ball,
        geometric,
        jax.jit(collision.nce_geometric_collides(nce_cfg, geometric)),
        jax.jit(collision.geometric_collides(geometric)),
    )


# ----------------------------------------------------------------------------------------------
# nce_geometric: the observed-cloud penetration test's settings, chosen on validation pairs

SELECT_DEPTHS = (0.0005, 0.001, 0.0015, 0.002, 0.003, 0.004)  # m
SELECT_RADII = (0.002, 0.003, 0.004, 0.006, 0.01)  # m
SELECT_MIN_POINTS = (0, 1, 2, 3, 5, 8, 12)


def _geometric_grid(
    data, pair_rows, poses, geo: collision.GeometricConfig, depths, radii, symmetric=False
):
    """Inside counts [L, D, R] of ``poses`` [L, 7] of pairs ``pair_rows`` [L] for every
    (depth, radius), one support lookup table per pair: object points inside the observed
    support, or with ``symmetric`` support points (all of them) inside the observed object
    (one lookup table over the object cloud per pair, object frame)."""
    import jax.numpy as jnp

    def counts(grid, cloud, poses):
        if symmetric:  # support points into the object frame
            moved = collision.inverse_transform_points(poses, cloud)
        else:
            moved = collision.transform_points(poses, cloud)
        along, length, ok = collision.grid_offsets(grid, moved)
        along = jnp.where(ok, along, 0.0)
        return jnp.stack(
            [
                jnp.stack([collision.inside_points(along, length, d, r) for r in radii], -1)
                for d in depths
            ],
            -2,
        )

    counts = jax.jit(counts)
    out = np.zeros((len(pair_rows), len(depths), len(radii)), np.int32)
    for p in np.unique(pair_rows):
        rows = np.flatnonzero(pair_rows == p)
        if symmetric:  # (with geo.sym_solid_only: solid-backed object points only)
            grid = collision.object_grid(data.object_points[p], data.object_normals[p], geo)
            cloud = data.support_points[p]  # the planner's: the support table's points
        else:
            grid = collision.support_grid(
                data.support_points[p],
                data.support_normals[p],
                geo.voxel,
                geo.max_voxels,
                geo.margin,
            )
            cloud = collision.subsample_cloud(
                data.object_points[p], geo.object_points, SUBSET_SEED_OBJECT
            )
        for a in range(0, len(rows), 256):
            r = rows[a : a + 256]
            padded = np.concatenate([poses[r], np.repeat(poses[r[:1]], 256 - len(r), 0)])
            out[r] = np.asarray(counts(grid, cloud, padded))[: len(r)]
    return out


def collision_validation_pairs(data: str, val_pairs: int):
    """The planner's TRAINING validation pairs (``pair_index % 20 == 0``, never trained on;
    ``train_collision --val-every 20``) with their near-contact poses and mesh labels, derived
    if missing: where :func:`select_geometric` and :func:`hce_goal_pass_thresholds` choose."""
    from experiments.train_collision import load_collision_data

    files = derive_collision_pairs(
        data, {"train": val_pairs}, 1, False, only=lambda i: i % 20 == 0
    )["train"]
    val = load_collision_data(files)
    if any(m["split"] != "train" or m["pair_index"] % 20 for m in val.meta):
        raise RuntimeError("validation pairs must be training-split pairs with index % 20 == 0")
    return val


def hce_goal_pass_thresholds(
    data: str, weights: str, val_pairs: int = 60, goal_pass: float = 0.95
) -> dict:
    """The two HCEs' thresholds chosen by the NCE's own rule (thirty-first session): on the
    TRAINING validation pairs of :func:`select_geometric` (``pair_index % 20 == 0``, never
    trained on), the lowest score at which at least ``goal_pass`` of the dataset's stable
    poses are called free (``train_collision.goal_pass_threshold``'s rule; the contact NCE's
    0.56 came from it). The default HCE thresholds maximise balanced accuracy on labels that
    are ~80 % colliding, and a stable hang touches the support, so they call most goals
    colliding (27-32 of 40 held-out goals, sixteenth session) and the planner cannot finish:
    the baseline would be judged on a threshold no planner could use.

    Returns per method (``hce``, ``hce_true_normals``) the chosen and the balanced threshold
    with, at each, the goal pass and the near-contact recall / precision / free precision of
    the moved near poses (mesh labels, deeper than 1 mm)."""
    from experiments.train_collision import (
        NEAR_STABLE,
        NEAR_TRANSIT,
        hce_score_fn,
        score_poses,
        true_normals_score_fn,
    )

    if not 0.0 < goal_pass <= 1.0:
        raise ValueError(f"goal_pass must be in (0, 1], got {goal_pass}")
    val = collision_validation_pairs(data, val_pairs)
    if val.near_poses is None:
        raise RuntimeError("the validation pairs hold no near-contact poses (derive them again)")
    est = load_estimators(weights)
    nce_cfg = est.nce_config
    n_obj, n_sup = nce_cfg.object_points, est.normal_config.points
    stable = val.near_kind == NEAR_STABLE
    moved = ~stable & (val.near_kind != NEAR_TRANSIT)
    fns = {
        "hce": (hce_score_fn(est.normal_config, est.normal_params), est.normal_config.threshold),
        "hce_true_normals": (true_normals_score_fn(val, n_sup), est.true_threshold),
    }
    out = dict(validation_pairs=len(val.meta), stable_poses=int(stable.sum()),
               near_poses=int(moved.sum()), goal_pass_target=goal_pass)  # fmt: skip
    for name, (fn, balanced) in fns.items():
        s = score_poses(val, val.near_pair, val.near_poses, fn, n_obj, n_sup)
        if not np.all(np.isfinite(s)):
            raise RuntimeError(f"{name}: non-finite heuristic scores on the validation poses")
        chosen = float(np.quantile(s[stable], goal_pass, method="higher"))

        def at(t, s=s):
            called = s > t
            m = collision.binary_metrics(called[moved], val.near_labels[moved])
            return dict(threshold=float(t), goal_pass=float(np.mean(~called[stable])),
                        near_recall=m["recall"], near_precision=m["precision"],
                        free_precision=m["free_precision"])  # fmt: skip

        out[name] = dict(chosen=at(chosen), balanced=at(balanced))
    return out


def read_pair_names(path: str | Path) -> list[str]:
    """Pair names of an ``--only-pairs`` file: one per line, or a JSON list."""
    text = Path(path).read_text()
    return json.loads(text) if text.lstrip().startswith("[") else text.split()


def only_pairs(cases: list, path: str | Path) -> list:
    """The ``cases`` named in ``path`` (:func:`read_pair_names`), in their order; a name that
    is not among the cases is a clear error (another --pairs or goal)."""
    names = read_pair_names(path)
    have = {c.name for c in cases}
    unknown = sorted(set(names) - have)
    if unknown:
        raise ValueError(f"--only-pairs {path}: {len(unknown)} pair(s) not among the pairs "
                         f"loaded (e.g. {unknown[0]!r}); check --pairs and --pairs-from")  # fmt: skip
    keep = set(names)
    return [c for c in cases if c.name in keep]


def select_geometric(
    data: str,
    weights: str,
    val_pairs: int = 60,
    goal_pass: float = 0.9,
    geo: collision.GeometricConfig = collision.GeometricConfig(),
    depths=SELECT_DEPTHS,
    radii=SELECT_RADII,
    min_points=SELECT_MIN_POINTS,
    symmetric: bool = False,
    nce_thresholds=None,
) -> dict:
    """The penetration test's (depth, radius, min_points) for ``nce_geometric``, on TRAINING
    validation pairs (``pair_index % 20 == 0``, never trained on; ``train_collision
    --val-every 20``), with their near-contact poses and mesh labels (colliding: deeper than
    1 mm on the full meshes): among the settings at which the hybrid (NCE OR test) still
    calls at least ``goal_pass`` of the stable poses free, the one with the highest
    precision of "free" on the moved near-contact poses (ties: higher specificity).

    ``symmetric``: the one-sided test fixed at ``geo``'s depth / radius / min points, the
    same grid and rule choose the symmetric side's ``sym_depth`` / ``sym_radius`` /
    ``sym_min_points`` (the hybrid: NCE OR one-sided OR symmetric); ``chosen`` is None when
    no setting keeps the goal pass (then the symmetric side stays off).

    ``nce_thresholds``: the NCE's threshold is searched too (eighteenth session), jointly with
    the test's settings under the same rule; rows and ``chosen`` then carry ``nce_threshold``,
    which ``--geometric`` applies (unless ``--nce-threshold`` is given)."""
    from experiments.train_collision import (
        NEAR_APPROACH,
        NEAR_JITTER,
        NEAR_LIFT,
        NEAR_STABLE,
        NEAR_TRANSIT,
        nce_score_fn,
        score_poses,
    )

    val = collision_validation_pairs(data, val_pairs)
    t0 = time.time()
    cfg, params, _ = collision.load_estimator(Path(weights, "nce"))
    nce_fn = nce_score_fn(cfg, params)
    prob = score_poses(
        val, val.near_pair, val.near_poses, nce_fn, cfg.object_input, cfg.support_input
    )
    nce_s = time.time() - t0
    fixed = np.zeros(len(prob), bool)
    if symmetric:  # the one-sided hybrid, fixed
        one = _geometric_grid(val, val.near_pair, val.near_poses, geo, [geo.depth], [geo.radius])
        fixed = one[:, 0, 0] > geo.min_points
    thresholds = [cfg.threshold] if nce_thresholds is None else list(nce_thresholds)
    nce_calls = {t: (prob > t) | fixed for t in thresholds}
    counts = _geometric_grid(val, val.near_pair, val.near_poses, geo, depths, radii, symmetric)
    stable = val.near_kind == NEAR_STABLE
    transit = val.near_kind == NEAR_TRANSIT  # reported, not in the rule (near version 2)
    moved = ~stable & ~transit
    label = val.near_labels

    def metrics(called):
        m = collision.binary_metrics(called[moved], label[moved])
        kinds = {"jitter": NEAR_JITTER, "approach": NEAR_APPROACH, "lift": NEAR_LIFT}
        return dict(
            goal_pass=float(np.mean(~called[stable])),
            near_recall=m["recall"], near_precision=m["precision"],
            free_precision=m["free_precision"], specificity=m["specificity"],
            **{f"{k}_" + ("recall" if k == "jitter" else "specificity"): (
                collision.binary_metrics(called[val.near_kind == v], label[val.near_kind == v])[
                    "recall" if k == "jitter" else "specificity"
                ]
            ) for k, v in kinds.items()},
            **({} if not transit.any() else {
                "transit_recall": collision.binary_metrics(called[transit], label[transit])[
                    "recall"],
                "transit_free_precision": collision.binary_metrics(
                    called[transit], label[transit])["free_precision"],
            }),
        )  # fmt: skip

    table, best = [], None
    for threshold, by_nce in nce_calls.items():
        for i, d in enumerate(depths):
            for j, r in enumerate(radii):
                for m in min_points:
                    by_test = counts[:, i, j] > m
                    setting = dict(depth=d, radius=r, min_points=m)
                    if symmetric:
                        setting = dict(
                            depth=geo.depth, radius=geo.radius, min_points=geo.min_points,
                            sym_depth=d, sym_radius=r, sym_min_points=m,
                        )  # fmt: skip
                    if nce_thresholds is not None:
                        setting["nce_threshold"] = float(threshold)
                    row = dict(**setting, **metrics(by_nce | by_test))
                    row["test_alone"] = metrics(by_test)
                    table.append(row)
                    ok = row["goal_pass"] >= goal_pass
                    key = (row["free_precision"], row["specificity"])
                    if ok and (best is None or key > (best["free_precision"], best["specificity"])):
                        best = row
    by_nce = (prob > cfg.threshold) | fixed  # the NCE's own row, at its own threshold
    out = dict(
        validation_pairs=len(val.meta),
        near_poses=int(moved.sum()),
        stable_poses=int(stable.sum()),
        colliding_fraction=float(label[moved].mean()),
        goal_pass_target=goal_pass,
        rule="max free precision (moved near poses) at hybrid goal pass >= target",
        geometric=dataclasses.asdict(geo),
        nce=dict(weights=weights, threshold=cfg.threshold, **metrics(by_nce)),
        chosen=best,
        table=table,
        nce_s=round(nce_s, 1),
        wall_s=round(time.time() - t0, 1),
    )
    if symmetric:  # the "nce" row is then the one-sided hybrid (NCE OR the fixed test)
        out["symmetric"] = True
        if geo.sym_solid_only:
            out["rule"] += " (solid-backed object points only)"
        out["nce"] |= dict(depth=geo.depth, radius=geo.radius, min_points=geo.min_points)
        out["rule"] += " (symmetric side; one-sided test fixed)"
    return out


WALL_POINTS = 512  # object points of planner.WallChecker (--wall-margin)
FAR_CLEARANCE_POINTS = 512  # object points of planner.ClearanceFarFromGoal (--far-clearance)


def completed(case: PairCase, n_observed: int) -> tuple[np.ndarray, np.ndarray]:
    """(object, support) clouds for the clearance tests with --completion
    (``completion.clearance_clouds``, the planner's object seed)."""
    from omnihang_jax import completion

    return completion.clearance_clouds(case.object_points, case.support_points,
                                       case.predicted_object, case.predicted_support,
                                       n_observed, SUBSET_SEED_OBJECT)  # fmt: skip


def add_completion(cases: list[PairCase], folder: str, carve_with: str | None = None):
    """The cases with the completion networks' predicted points (``omnihang_jax.completion``);
    with ``carve_with`` (a dataset folder), less the points each body's camera would have seen
    (``completion.carve``, the cameras of the dataset's records)."""
    from omnihang_jax import completion

    nets = completion.load_nets(folder)
    eyes = {}
    if carve_with is not None:
        eyes = record_eyes(carve_with, [c.meta["pair_index"] for c in cases])
    out = []
    for case in cases:
        po, ps = completion.predict_points(nets, case.object_points, case.support_points,
                                           eyes.get(int(case.meta["pair_index"])))  # fmt: skip
        out.append(case._replace(predicted_object=po, predicted_support=ps))
    return out


def nce_clouds(case: PairCase, config: collision.NCEConfig) -> tuple[np.ndarray, np.ndarray]:
    """(object, support) clouds the NCE is given before its fixed subsets: the observed ones,
    or for an NCE trained on completed clouds (``config.input_clouds``, twenty-eighth session)
    ``completion.completed_cloud`` of each, as in its training (``train_collision
    --completion``). Raises ``ValueError`` when that NCE has no predicted points to use."""
    if config.input_clouds == "observed":
        return case.object_points, case.support_points
    if case.predicted_object is None or case.predicted_support is None:
        raise ValueError(
            f"pair {case.name}: this NCE was trained on completed clouds: pass --completion "
            "FOLDER --completion-carve (the networks it was trained with)"
        )
    from omnihang_jax import completion

    return (completion.completed_cloud(case.object_points, case.predicted_object),
            completion.completed_cloud(case.support_points, case.predicted_support))  # fmt: skip


def checkers_for(
    case: PairCase, est: Estimators, tolerance: float, methods=METHODS, warm: bool = True
) -> dict:
    """The checkers of one pair. The HCEs' support normals do not depend on the pose:
    predicted once per pair (``collision.hce_collides`` computes the same per call); nor does
    ``nce_geometric``'s support lookup table (built once per pair, outside the planning
    clock, only when that method is asked for). ``warm``: every padded batch size compiled
    and run once here, outside a planner's clock (off for a caller that times nothing)."""
    sub = collision.subsample_cloud
    n_obj, n_sup = est.nce_config.object_points, est.nce_config.support_input
    n_nce_obj = est.nce_config.object_input  # the contact NCE is given more (NCEConfig)
    nce_params = est.nce_params
    if est.nce_far_threshold is not None:  # collision.goal_ball_collides
        weight = np.float32(planner.object_radius(case.scene))
        nce_params = (est.nce_params, np.asarray(case.goal, np.float32), weight)
    nce_object, nce_support = nce_clouds(case, est.nce_config)
    nce = planner.EstimatorChecker(
        est.nce,
        nce_params,
        sub(nce_object, n_nce_obj, SUBSET_SEED_OBJECT),
        sub(nce_support, n_sup, SUBSET_SEED_SUPPORT),
    )
    h_sup = est.normal_config.points
    oc = sub(case.object_points, n_obj, SUBSET_SEED_OBJECT)
    sc = sub(case.support_points, h_sup, SUBSET_SEED_SUPPORT)
    predicted = np.asarray(est.normals(est.normal_params, sc))
    true = sub(case.support_normals, h_sup, SUBSET_SEED_SUPPORT)

    def heuristic(normals, threshold):
        def collides(params, object_cloud, support_cloud, poses):
            return est.heuristic(object_cloud, support_cloud, params, poses) > threshold

        return planner.EstimatorChecker(collides, normals, oc, sc)

    checkers = {
        "nce": nce,
        "hce": heuristic(predicted, est.normal_config.threshold),
        "hce_true_normals": heuristic(true, est.true_threshold),
        "mesh": planner.MeshChecker(case.scene, tolerance),
    }
    if "nce_geometric" in methods or "geometric" in methods:
        geo = est.geometric
        grid = collision.support_grid(
            case.support_points, case.support_normals, geo.voxel, geo.max_voxels, geo.margin
        )
        geo_object = sub(case.object_points, geo.object_points, SUBSET_SEED_OBJECT)
        object_grid, alone = None, grid
        if geo.symmetric:  # the object cloud's table too (object frame), also outside the clock
            object_grid = collision.object_grid(case.object_points, case.object_normals, geo)
            alone = collision.GeometricGrids(grid, object_grid)
        # the penetration test alone (ablation): no NCE, ~20x cheaper a check
        checkers["geometric"] = planner.EstimatorChecker(
            est.geometric_alone, alone, geo_object, grid.points
        )
        # the hybrid: the test first, the NCE only where it says free, and not at all for an
        # edge it blocks (planner.CascadeChecker; the same calls as the one jitted
        # collision.nce_geometric_collides, est.nce_geometric, at about half the NCE queries)
        test = checkers["geometric"]
        if est.test_goal_ball > 0:  # the NCE alone decides near the goal
            weight = planner.object_radius(case.scene)
            test = planner.ExemptNearGoal(test, case.goal, est.test_goal_ball, weight)
        checkers["nce_geometric"] = planner.CascadeChecker(test, nce)
    if est.far_ball > 0 and est.far_clearance > 0:  # the clearance first, far from the goal
        obj, sup = (
            sub(case.object_points, FAR_CLEARANCE_POINTS, SUBSET_SEED_OBJECT),
            case.support_points,
        )
        if "far" in est.completion_in and case.predicted_object is not None:
            obj, sup = completed(case, FAR_CLEARANCE_POINTS)
        clear = planner.ClearanceFarFromGoal(
            obj, sup, case.goal, est.far_ball, est.far_clearance, planner.object_radius(case.scene)
        )
        for name in ("nce", "nce_geometric"):
            if name in checkers:
                checkers[name] = planner.CascadeChecker(clear, checkers[name])
    if est.far_nce is not None:  # the second NCE far from the goal, on what the hybrid passes
        far_cfg, far_params, far_fn = est.far_nce
        far_object, far_support = nce_clouds(case, far_cfg)
        far = planner.EstimatorChecker(
            far_fn,
            far_params,
            sub(far_object, far_cfg.object_input, SUBSET_SEED_OBJECT),
            sub(far_support, far_cfg.support_input, SUBSET_SEED_SUPPORT),
        )
        far = planner.ExemptNearGoal(
            far, case.goal, est.far_nce_ball, planner.object_radius(case.scene)
        )
        for name in ("nce", "nce_geometric"):
            if name in checkers:
                checkers[name] = planner.CascadeChecker(checkers[name], far)
    if est.wall_margin is not None and case.wall_y is not None:  # the known wall, first
        wall = planner.WallChecker(
            sub(case.object_points, WALL_POINTS, SUBSET_SEED_OBJECT), case.wall_y, est.wall_margin
        )
        for name in ("nce", "nce_geometric"):
            if name in checkers:
                checkers[name] = planner.CascadeChecker(wall, checkers[name])
    for name in set(methods) - {"mesh"} if warm else ():  # compiled outside the planning clock
        checkers[name].warm_up()
    return checkers


def learned_approach(case: PairCase, est: Estimators):
    """(directions [K, 3] to try in order, their checker or None for the method's, a row
    record) from the approach network on the pair's observed clouds: the directions whose
    probability reaches the network's threshold, best first (none: the plain plan)."""
    t0 = time.perf_counter()
    directions, probs = est.approach.order(case.object_points, case.support_points, case.goal)
    keep = approach.usable(directions, probs, est.approach.config.threshold,
                           case.wall_y is not None, est.approach_open_side)  # fmt: skip
    if est.approach_check == "none":
        keep &= np.cumsum(keep) == 1  # the best one kept only, taken as free
    seconds = time.perf_counter() - t0
    record = dict(best=directions[0].round(3).tolist(), best_p=round(float(probs[0]), 4),
                  tried=int(keep.sum()), seconds=round(seconds, 4))  # fmt: skip
    if keep.any():
        record["first_tried"] = directions[keep][0].round(3).tolist()
    checker = approach.never_colliding if est.approach_check == "none" else None
    return directions[keep], checker, record


TWO_MOVE_FIRSTS = (0.015, 0.03, 0.045)  # m: the first move's lengths (scripts/probe_dogleg.py)
TWO_MOVE_CLEAR = 0.01  # m: the end must be this clear of the support on the meshes


def route_oracle(case: PairCase, mesh, config: planner.PlannerConfig, bounds, lattice: float):
    """(kind, retreat) of the oracle route off the support on the full meshes (ending
    ``TWO_MOVE_CLEAR`` clear; thirty-ninth session): ("two_moves", ...) where one straight move
    does not take the object off but two do (``planner.find_two_move_retreat``; 17 of the 80
    benchmark goals); ("lattice", ...) where neither does and ``lattice`` > 0, the shortest
    lattice route of that step (``planner.lattice_retreat``, at most 20,000 nodes); (None, None)
    where one move does (the approach rule's case) or none is found."""
    off = lambda pose: float(mesh.clearance(pose)[0]) >= TWO_MOVE_CLEAR  # noqa: E731
    length = config.retreat_lengths[0]
    found = planner.find_two_move_retreat(
        mesh, case.goal, TWO_MOVE_FIRSTS, length, config.resolution, bounds, off
    )
    if found is not None:
        return ("two_moves", found) if len(found.via) else (None, None)
    if lattice > 0:
        found, _ = planner.lattice_retreat(mesh, case.goal, lattice, off, 20_000, bounds)
        if found is not None:
            return "lattice", found
    return None, None


def drop_straight(record: dict, directions: np.ndarray) -> np.ndarray:
    """``--routes-mode only`` (forty-third session) where no checked route is found: the plain
    plan, not the straight rule's approach (its direction kept in the record as
    ``straight_dropped``; ``first_tried`` removed, so the row reads as planned without one).
    Over the adopted planner's three seeds, straight approaches on goals without a route were
    9 free / 6 colliding / 9 without a path, on threaded goals 3 / 6 / 9: a straight 4.5-cm move
    that is free says nothing of leaving the support."""
    first = record.pop("first_tried", None)
    if first is not None:
        record["straight_dropped"] = first
    return directions[:0]


def learned_route(
    case: PairCase, est, check=None, resolution: float = planner.PlannerConfig().resolution
):
    """(retreat or None, record) from the route network on the observed clouds
    (``approach.checked_route``): its best route when its probability reaches the network's
    threshold (``planner.route_retreat``, the corner in ``via``; taken as free, like the
    straight rule's best direction). With ``est.routes_check`` "checker" (forty-first session)
    the first confident route, best first and at most ``est.routes_tries``, that ``check`` (the
    method's own checker) calls free at every state (at ``resolution``) and whose end is
    ``est.routes_end_gap`` clear between the observed clouds."""
    t0 = time.perf_counter()
    mode = getattr(est, "routes_check", "none")
    if mode == "checker" and check is None:
        raise ValueError("routes_check 'checker' needs the method's checker")
    choice = approach.checked_route(
        est.routes, case.object_points, case.support_points, case.goal,
        check if mode == "checker" else None, float(getattr(est, "routes_end_gap", 0.0)),
        int(getattr(est, "routes_tries", 10)), resolution,
    )  # fmt: skip
    best = choice.best if choice.route is None else choice.route
    record = dict(best=[int(best[0]), round(float(best[1]), 4), int(best[2])],
                  best_p=round(choice.probability, 4))  # fmt: skip
    if mode != "none":
        record |= dict(check=mode, tried=choice.tried, rank=choice.rank)
    found = None
    if choice.route is not None:
        found = planner.route_retreat(case.goal, choice.route, est.routes.config.length)
        record["waypoints"] = len(found.via) + 1
    record["seconds"] = round(time.perf_counter() - t0, 4)
    return found, record


def next_approach(case: PairCase, est) -> np.ndarray:
    """[0 or 1, 3]: the second usable direction of the approach network (at its threshold, open
    side as configured), for ``--approach-replan next`` (with ``--approach-check none``, whose
    first plan used the first usable direction): a time-out of the first plan may mean
    that the first direction's pre-goal is out of reach (thirty-eighth session). Empty: none
    passes, and the replan plans plainly to the goal."""
    directions, probs = est.approach.order(case.object_points, case.support_points, case.goal)
    keep = approach.usable(directions, probs, est.approach.config.threshold,
                           case.wall_y is not None, est.approach_open_side)  # fmt: skip
    return directions[keep][1:2]


def evaluate_pair(
    case: PairCase,
    est: Estimators,
    config: planner.PlannerConfig,
    methods,
    clearance: planner.ClearanceConfig | None = None,
    mine: tuple[Path, int] | None = None,
):
    """Plan with each method and densely check what comes back. Returns (rows, paths).
    ``mine`` = (folder, cap): the estimator methods' checkers are recorded
    (``planner.RecordingChecker``) and what they judged near the support, with the returned
    path's dense states, is labelled by the meshes into ``folder`` (:func:`save_mined`).
    ``clearance``: each estimator's returned path is moved away from the observed support
    (``planner.clear_path`` with that method's checker) and the moved path is the one
    returned; the path as planned is checked too (the row's ``raw_*`` keys)."""
    scene = case.scene
    weight = planner.object_radius(scene)
    bounds = planner.default_bounds(scene)
    goal = case.goal
    start = planner.start_pose(scene, goal)
    mesh = planner.MeshChecker(scene, config.penetration_tolerance)
    checkers = checkers_for(case, est, config.penetration_tolerance, methods)
    if mine is not None and est.nce_fallback is not None:
        raise ValueError("a fallback plan is for the evaluation: mining records the first plan's "
                         "checker only")  # fmt: skip
    fallbacks = {}
    if est.nce_fallback is not None:  # built (and compiled) outside the planning clock
        lax = est._replace(nce=est.nce_fallback, nce_fallback=None)
        names = tuple(m for m in methods if m in ("nce", "nce_geometric"))
        if names:
            fallbacks = checkers_for(case, lax, config.penetration_tolerance, names)
    base = dict(
        pair=case.name,
        **case.meta,
        start=start.round(5).tolist(),
        goal=goal.round(5).tolist(),
        start_penetration=float(mesh.penetration(start[None])[0]),
        goal_penetration=float(mesh.penetration(goal[None])[0]),
    )
    rows, paths = [], {}
    for name in methods:
        check = checkers[name]
        if mine is not None and name != "mesh":
            check = planner.RecordingChecker(
                check, cap=20 * mine[1], seed=int(case.meta["pair_index"])
            )
        directions, retreat_checker, ranked = planner.RETREAT_DIRECTIONS, None, None
        two = None
        if est.oracle_retreat and name != "mesh":
            retreat_checker = mesh
        elif est.approach is not None and name != "mesh":
            directions, retreat_checker, ranked = learned_approach(case, est)
            if est.routes is not None and (est.routes_mode != "fill" or not len(directions)):
                found, ranked["route"] = learned_route(case, est, check, config.resolution)
                ranked["seconds"] = round(ranked["seconds"] + ranked["route"]["seconds"], 4)
                if found is not None:  # the replan after a time-out stays as configured
                    two, directions = found, found.direction[None]
                elif est.routes_mode == "only":
                    directions = drop_straight(ranked, directions)
            if est.oracle_two_moves:
                kind, two = route_oracle(case, mesh, config, bounds, est.oracle_lattice)
                if two is not None:  # the replan after a time-out stays plain
                    directions = two.direction[None]
                    ranked[kind] = dict(
                        waypoints=len(two.via) + 1,
                        corner=np.asarray(two.via[-1][:3] - goal[:3]).round(4).tolist(),
                        last=two.direction.round(3).tolist(),
                        search_s=round(two.seconds, 3),
                    )  # fmt: skip
        res, retreat = planner.plan_with_retreat(
            check, start, goal, bounds, weight, config, retreat_checker=retreat_checker,
            retreat_directions=directions, retreat=two,
        )  # fmt: skip
        if ranked is not None:
            res = res._replace(planning_s=res.planning_s + ranked["seconds"])
        start_colliding = bool(check(start[None])[0])
        goal_colliding = bool(check(goal[None])[0])
        fallback = None
        if res.path is None and name in fallbacks:  # the second plan, laxer far from the goal
            lax_check = fallbacks[name]
            used = ranked is not None and len(directions) > 0  # an approach was planned to
            plain = used and est.approach_replan == "plain"
            replan_directions = directions[:0] if plain else directions
            if used and est.approach_replan == "next":
                t_next = time.perf_counter()
                replan_directions = next_approach(case, est)
                res = res._replace(planning_s=res.planning_s + time.perf_counter() - t_next)
                plain = len(replan_directions) == 0
            second, second_retreat = planner.plan_with_retreat(
                lax_check, start, goal, bounds, weight,
                dataclasses.replace(config, time_limit=est.fallback_time, retreat_after=0.0),
                retreat_checker=retreat_checker,
                retreat_directions=replan_directions,
            )  # fmt: skip
            fallback = dict(far_threshold=est.fallback_far_threshold, status=second.status,
                            planning_s=round(second.planning_s, 3),
                            returned=second.path is not None)  # fmt: skip
            if used:
                kind = "next" if est.approach_replan == "next" else "same"
                fallback["approach"] = "plain" if plain else kind
                if kind == "next" and not plain:
                    fallback["approach_direction"] = replan_directions[0].round(3).tolist()
                retreat = second_retreat  # the path's end is the second plan's
            res = second._replace(
                planning_s=res.planning_s + second.planning_s,
                states_checked=res.states_checked + second.states_checked,
                checker_calls=res.checker_calls + second.checker_calls,
            )
            if second.path is not None:
                check = lax_check  # its clearing keeps to what the fallback's checker allows
        row = dict(
            base,
            method=name,
            status=res.status,
            planning_s=round(res.planning_s, 3),
            states_checked=res.states_checked,
            checker_calls=res.checker_calls,
            start_called_colliding=start_colliding,
            goal_called_colliding=goal_colliding,
            returned=res.path is not None,
        )
        if fallback is not None:
            row["fallback"] = fallback
        if config.retreat_lengths:
            row["retreat"] = None if retreat is None else dict(
                direction=retreat.direction.round(3).tolist(), length_m=retreat.length,
                search_s=round(retreat.seconds, 3), states=retreat.states_checked,
            )  # fmt: skip
        if ranked is not None:
            row["approach"] = ranked
        if res.path is not None and clearance is not None and name != "mesh":
            free, deepest, _ = planner.dense_check(mesh, res.path, config.dense_resolution, weight)
            obj, sup, cfg = case.object_points, case.support_points, clearance
            if "clear" in est.completion_in and case.predicted_object is not None:
                obj, sup = completed(case, clearance.object_points)
                cfg = dataclasses.replace(clearance, object_points=len(obj))
            cleared = planner.clear_path(
                res.path, check, obj, sup, goal, weight, bounds, config.resolution, cfg,
                config.goal_radius,
            )  # fmt: skip
            row |= dict(
                raw_collision_free=free, raw_deepest_m=round(deepest, 5),
                raw_waypoints=len(res.path), clear_gap_before_m=round(cleared.gap_before, 5),
                clear_gap_after_m=round(cleared.gap_after, 5), clear_moves=cleared.moves,
                clear_removed=cleared.removed, clear_states=cleared.states_checked,
                clear_s=round(cleared.seconds, 3),
            )  # fmt: skip
            res = res._replace(path=cleared.path)
        if res.path is not None:
            free, deepest, n = planner.dense_check(mesh, res.path, config.dense_resolution, weight)
            # would a denser check by the same estimator have caught it? (estimator misses
            # vs states skipped between the planner's checks)
            dense = planner.interpolate_path(res.path, config.dense_resolution, weight)
            flags = np.asarray(check(dense), bool)
            row |= dict(
                collision_free=free, deepest_m=round(deepest, 5), dense_states=n,
                waypoints=len(res.path), estimator_dense_flags=int(flags.sum()),
            )  # fmt: skip
            paths[name] = res.path
        else:
            row |= dict(collision_free=False)
        if mine is not None and name != "mesh":
            row["mined"] = save_mined(case, check, mesh, res.path, name, config, mine)
        rows.append(row)
    return rows, paths


def save_mined(case: PairCase, recorder, mesh, path, method: str, config, mine) -> dict:
    """The states a planner's checker judged on a (training) pair, labelled by the meshes:
    hard examples for the NCE from where the planner actually goes (twenty-ninth session).
    Kept: the recorded states whose observed clouds come within ``MINE_GAP`` (elsewhere
    nothing is near), at most ``cap`` of them, half called colliding and half called free
    where there are that many, plus every dense state (``config.dense_resolution``) of the
    returned path within the gap. Written to ``folder/<pair file>.npz`` (``poses`` [K, 7],
    ``penetration`` [K] m by :class:`planner.MeshChecker`, ``called`` [K] the checker's
    verdict, ``gap`` [K] m, ``goal_distance`` [K] (planner metric), ``source`` [K] 0
    recorded / 1 returned path). Returns counts for the row."""
    from sim import atomic

    folder, cap = mine
    rng = np.random.default_rng(int(case.meta["pair_index"]))
    weight = planner.object_radius(case.scene)
    poses, called = recorder.poses.astype(float), recorder.called
    gap = observed_gap(case.object_points, case.support_points, poses, MINE_GAP)
    near = np.flatnonzero(gap < MINE_GAP)
    pick = []
    for verdict in (True, False):
        rows = near[called[near] == verdict]
        other = len(near) - len(rows)
        n = min(len(rows), max(cap // 2, cap - other))
        pick.append(rng.choice(rows, n, replace=False) if n < len(rows) else rows)
    pick = np.sort(np.concatenate(pick)).astype(int)
    poses, called, gap = poses[pick], called[pick], gap[pick]
    source = np.zeros(len(pick), np.int8)
    if path is not None:
        dense = planner.interpolate_path(path, config.dense_resolution, weight)
        d_gap = observed_gap(case.object_points, case.support_points, dense, MINE_GAP)
        keep = d_gap < MINE_GAP
        d_called = np.asarray(recorder.checker(dense[keep]), bool)
        poses = np.concatenate([poses, dense[keep]])
        called = np.concatenate([called, d_called])
        gap = np.concatenate([gap, d_gap[keep]])
        source = np.concatenate([source, np.ones(int(keep.sum()), np.int8)])
    penetration = mesh.penetration(poses) if len(poses) else np.zeros(0)
    folder.mkdir(parents=True, exist_ok=True)
    atomic.savez(
        folder / f"{case.name}.npz",
        poses=poses.astype(np.float32),
        penetration=penetration.astype(np.float32),
        called=called.astype(bool),
        gap=gap.astype(np.float32),
        goal_distance=planner.goal_distances(poses, case.goal, weight).astype(np.float32),
        source=source,
        method=np.array(method),
        mine_version=np.array(MINE_VERSION),
        **{k: np.array(v) for k, v in case.meta.items()},
    )
    colliding = penetration > config.penetration_tolerance
    return dict(
        recorded=int(recorder.seen), kept=int(len(poses)),
        colliding=int(colliding.sum()), missed=int((colliding & ~called).sum()),
        false_alarms=int((~colliding & called).sum()),
    )  # fmt: skip


def read_rows(path: str | Path, method: str = "nce_geometric") -> dict[str, dict]:
    """A run's ``pairs.jsonl`` (this module's ``--out``) -> pair -> its last row of ``method``
    (a resumed run: the last row counts); rows planned to another goal than the first stable
    pose are refused (a run of another protocol). The scripts that compare or splice runs
    read them so (``scripts/approach_decisions.py``, ``splice_rows.py``, ``probe_path_gaps.py``)."""
    rows = {}
    for line in Path(path).read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            if r.get("goal_kind", "stable") != "stable":
                raise ValueError(f"{path}: a row planned to {r['goal_kind']!r}, not a stable pose")
            if r.get("method", method) == method:
                rows[r["pair"]] = r
    return rows


def summarise(rows: list[dict], methods=METHODS) -> dict:
    """precision / recall / F1 per method, per object category and their mean."""
    out = {}
    pairs = sorted({r["pair"] for r in rows})
    for m in methods:
        mine = [r for r in rows if r["method"] == m]
        if not mine:
            continue

        def prf(sel):
            returned = sum(r["returned"] for r in sel)
            free = sum(r["collision_free"] for r in sel)
            precision = free / returned if returned else 0.0
            recall = free / len(sel) if sel else 0.0
            f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
            return dict(
                pairs=len(sel), returned=returned, collision_free=free,
                precision=round(100 * precision, 1), recall=round(100 * recall, 1),
                f1=round(100 * f1, 1),
            )  # fmt: skip

        per_cat = {
            c: prf([r for r in mine if r["object_category"] == c])
            for c in sorted({r["object_category"] for r in mine})
        }
        entry = prf(mine)
        entry["mean_over_categories"] = {
            k: round(float(np.mean([v[k] for v in per_cat.values()])), 1)
            for k in ("precision", "recall", "f1")
        }
        times = np.array([r["planning_s"] for r in mine])
        entry |= dict(
            per_category=per_cat,
            median_planning_s=round(float(np.median(times)), 3),
            p90_planning_s=round(float(np.quantile(times, 0.9)), 3),
            planning_s=[r["planning_s"] for r in mine],
            # OMPL reports a time-out with a partial tree as "Approximate solution"
            timeouts=sum(planner.timed_out(r["status"]) for r in mine),
            invalid_start_or_goal=sum(
                r["status"] in ("Invalid start", "Invalid goal") for r in mine
            ),
            start_called_colliding=sum(r["start_called_colliding"] for r in mine),
            goal_called_colliding=sum(r["goal_called_colliding"] for r in mine),
            deepest_penetration_of_colliding_paths_m=sorted(
                r["deepest_m"] for r in mine if r["returned"] and not r["collision_free"]
            ),
            median_states_checked=float(np.median([r["states_checked"] for r in mine])),
        )
        if (
            mine
            and all("raw_collision_free" in r for r in mine if r["returned"])
            and any("raw_collision_free" in r for r in mine)
        ):  # --clear-path: the same plans as returned by the planner, before clearing
            raw = [r | dict(collision_free=r.get("raw_collision_free", False)) for r in mine]
            entry["as_planned"] = {
                k: v
                for k, v in prf(raw).items()
                if k in ("returned", "collision_free", "precision", "recall", "f1")
            }
            moved = [r for r in mine if r["returned"]]
            entry["clearing"] = dict(
                became_free=sum(r["collision_free"] and not r["raw_collision_free"] for r in moved),
                became_colliding=sum(
                    r["raw_collision_free"] and not r["collision_free"] for r in moved
                ),
                median_gap_before_m=float(np.median([r["clear_gap_before_m"] for r in moved])),
                median_gap_after_m=float(np.median([r["clear_gap_after_m"] for r in moved])),
                median_s=float(np.median([r["clear_s"] for r in moved])),
            )
        tried = [r for r in mine if r.get("fallback")]
        if tried:  # --fallback-far-threshold: the second plans after a time-out
            entry["fallback"] = dict(
                tried=len(tried),
                returned=sum(r["fallback"]["returned"] for r in tried),
                collision_free=sum(
                    r["fallback"]["returned"] and r["collision_free"] for r in tried
                ),
                # the same run with the first plans alone (each fallback pair a time-out)
                without=prf(
                    [
                        r | dict(returned=False, collision_free=False) if r.get("fallback") else r
                        for r in mine
                    ]
                ),  # fmt: skip
            )
        bad = [r for r in mine if r["returned"] and not r["collision_free"]]
        if bad and all("estimator_dense_flags" in r for r in bad):
            # colliding paths whose states at the dense (ground-truth) spacing the estimator
            # itself flags: a finer planner resolution would have rejected those edges
            entry["colliding_paths_flagged_when_dense"] = sum(
                r["estimator_dense_flags"] > 0 for r in bad
            )
        out[m] = entry
    out["pairs"] = len(pairs)
    if rows and all("goal_status" in r for r in rows):
        # goals from the pipeline: the figures again over the pairs whose answer hangs (a path
        # to a penetrating answer cannot be collision-free), and the answers' statuses
        stable = [r for r in rows if r["goal_status"] == "stable"]
        by_pair = {r["pair"]: r["goal_status"] for r in rows}
        out["goal_statuses"] = dict(sorted(Counter(by_pair.values()).items()))
        if stable and len(stable) < len(rows):
            out["stable_goals"] = {
                m: {
                    k: v
                    for k, v in e.items()
                    if k in ("pairs", "returned", "collision_free", "precision", "recall", "f1")
                }
                for m, e in summarise(stable, methods).items()
                if m in methods
            }
    return out


# ----------------------------------------------------------------------------------------------
# Figure and scenes


def strip_figure(cases_paths: list[tuple[PairCase, str, np.ndarray]], path: str, frames=6):
    """One row per (pair, label, path): the support cloud and the object cloud at ``frames``
    states along the path (start ... goal), seen from the side (y-z: the wall on the left,
    the start in front on the right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = len(cases_paths)
    fig, axes = plt.subplots(rows, frames, figsize=(2.2 * frames, 2.4 * rows), squeeze=False)
    for r, (case, method, waypoints) in enumerate(cases_paths):
        weight = planner.object_radius(case.scene)
        dense = planner.interpolate_path(waypoints, 0.005, weight)
        idx = np.linspace(0, len(dense) - 1, frames).round().astype(int)
        sup = collision.subsample_cloud(case.support_points, 1500, 1)
        obj = collision.subsample_cloud(case.object_points, 800, 0)
        posed_all = [np.asarray(collision.transform_points(dense[i : i + 1], obj))[0] for i in idx]
        allpts = np.concatenate([sup, *posed_all])
        lo, hi = allpts.min(0), allpts.max(0)
        for c, (i, posed) in enumerate(zip(idx, posed_all)):
            ax = axes[r, c]
            # side view: y right (away from the wall), z up
            ax.scatter(sup[:, 1], sup[:, 2], s=0.5, c="0.5")
            ax.scatter(posed[:, 1], posed[:, 2], s=0.5, c="tab:orange")
            ax.plot(dense[:, 1], dense[:, 2], lw=0.6, c="tab:blue")
            ax.set_xlim(lo[1] - 0.02, hi[1] + 0.02)
            ax.set_ylim(lo[2] - 0.02, hi[2] + 0.02)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            frac = i / max(len(dense) - 1, 1)
            ax.set_title(f"{frac:.0%}", fontsize=7)
        axes[r, 0].set_ylabel(
            f"{case.meta['object_name']}\n{case.meta['support_name']}\n{method}", fontsize=6
        )
    fig.suptitle(
        "Planned paths (side view, y-z; wall left): support cloud grey, object cloud orange, "
        "path of the object's centre blue",
        fontsize=9,
    )
    fig.tight_layout()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _label(row: dict) -> str:
    if row["collision_free"]:
        return f"{row['method']}: free"
    return f"{row['method']}: {1e3 * row['deepest_m']:.1f} mm deep"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", default="datasets/paper")
    parser.add_argument("--weights", required=True, help="train_collision output folder")
    parser.add_argument("--pairs", type=int, default=20, help="held-out pairs")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--time-limit", type=float, default=20.0, help="s per plan")
    parser.add_argument(
        "--planner-seed", type=int, default=planner.PlannerConfig.seed,
        help="OMPL's random seed (once per process; > 0): repeat a run with other seeds to "
        "see the planner's run-to-run spread",
    )  # fmt: skip
    parser.add_argument(
        "--pairs-from",
        default=None,
        metavar="PAIRS_JSONL",
        help="draw the pairs among those of an eval_stage3 run's per-pair records (e.g. "
        "results/hanging_success_stage3_s14_cemv.pairs.jsonl.gz); default: all held-out pairs",
    )
    parser.add_argument(
        "--goal", choices=["stable", "answer"], default="stable",
        help="stable: each pair's first stable pose (the paper's protocol); answer: the "
        "where-to-hang pipeline's all-stages answer from --pairs-from (Stages 1-3 then plan)",
    )  # fmt: skip
    parser.add_argument(
        "--resolution", type=float, default=planner.PlannerConfig.resolution,
        help="m: spacing of the states the estimator checks along an edge",
    )  # fmt: skip
    parser.add_argument(
        "--goal-radius", type=float, default=1e-6, help="m: states this near the goal unchecked"
    )
    parser.add_argument(
        "--nce-threshold", type=float, default=None, help="override the NCE's own threshold"
    )
    parser.add_argument(
        "--nce-far-threshold",
        type=float,
        default=None,
        help="with --nce-goal-ball: the NCE threshold farther than the ball from the goal",
    )
    parser.add_argument(
        "--nce-goal-ball",
        type=float,
        default=0.0,
        help="m (planner metric): within it the NCE's threshold, beyond it --nce-far-threshold",
    )
    parser.add_argument(
        "--test-goal-ball", type=float, default=0.0, metavar="M",
        help="nce_geometric: the observed-cloud test is off within M (planner metric) of the "
        "goal, the NCE alone decides there (ablation; the test's false alarms on the last "
        "millimetres of the approach)",
    )  # fmt: skip
    parser.add_argument(
        "--far-clearance", type=float, default=0.0, metavar="M",
        help="nce and nce_geometric: farther than --far-ball from the goal, a state is "
        "colliding when the observed object cloud comes within M of the observed support "
        "cloud (planner.ClearanceFarFromGoal; the unobserved side of a support lies behind "
        "what is seen); 0: off",
    )  # fmt: skip
    parser.add_argument(
        "--far-ball", type=float, default=0.10, metavar="R",
        help="m (planner metric): with --far-clearance, the clearance is required only "
        "farther than R from the goal",
    )  # fmt: skip
    parser.add_argument(
        "--far-nce", default=None, metavar="FOLDER",
        help="a second NCE (FOLDER/nce; twenty-eighth session: weights/collision_s28_completed, "
        "trained on completed clouds) asked after the NCE / hybrid, only farther than "
        "--far-nce-ball from the goal",
    )  # fmt: skip
    parser.add_argument(
        "--far-nce-threshold", type=float, default=None,
        help="--far-nce's threshold (default: its own, chosen on its validation pairs)",
    )  # fmt: skip
    parser.add_argument(
        "--far-nce-ball", type=float, default=0.045, metavar="R",
        help="m (planner metric): --far-nce is asked only farther than R from the goal",
    )  # fmt: skip
    parser.add_argument(
        "--retreat", default="", metavar="M,M,...",
        help="lengths (m) of a straight retreat from the goal tried first (planner."
        "plan_with_retreat: the first retreat the method's checker calls free, upward "
        "directions first; RRT-Connect to its end, then straight in); empty: off",
    )  # fmt: skip
    parser.add_argument(
        "--oracle-retreat", action="store_true",
        help="a probe, not a planner: with --retreat, the retreat's direction is chosen by the "
        "full meshes (the oracle approach), the search to its end by the method's checker",
    )  # fmt: skip
    parser.add_argument(
        "--routes", metavar="DIR",
        help="with --approach: a route network (train_approach --first-lengths): its best route "
        "of one or two straight moves, when confident, is the approach (see --routes-mode)",
    )  # fmt: skip
    parser.add_argument("--routes-threshold", type=float, metavar="P",
                        help="with --routes: its best route's probability needed (default: its own)")  # fmt: skip
    parser.add_argument("--routes-views", type=int, default=1, metavar="N",
                        help="with --routes: its probabilities averaged over N cloud subsets")  # fmt: skip
    parser.add_argument(
        "--routes-mode", choices=("fill", "first", "only"), default="fill",
        help="with --routes: 'fill' asks it only where the straight approach rule gives none, "
        "'first' asks it first (the straight rule where it is not confident), 'only' asks it "
        "first and plans plainly where it gives no route (no straight approach)",
    )  # fmt: skip
    parser.add_argument(
        "--routes-check", choices=("none", "checker"), default="none",
        help="with --routes: 'checker' takes the first confident route (best first) that the "
        "method's own checker calls free and whose end is --routes-end-gap clear between the "
        "observed clouds; 'none' the best route, taken as free",
    )  # fmt: skip
    parser.add_argument("--routes-end-gap", type=float, default=0.0, metavar="M",
                        help="with --routes-check checker: the observed clearance its end needs")  # fmt: skip
    parser.add_argument("--routes-tries", type=int, default=10, metavar="N",
                        help="with --routes-check checker: confident routes asked at most")  # fmt: skip
    parser.add_argument(
        "--oracle-two-moves", action="store_true",
        help="a probe, not a planner: with --approach, on goals that no straight move takes off "
        "the support but two moves do (full meshes, 1 cm clear), plan to that two-move route",
    )  # fmt: skip
    parser.add_argument(
        "--oracle-lattice", type=float, default=0.0, metavar="STEP",
        help="a probe, with --oracle-two-moves: on goals neither one nor two moves take off the "
        "support, plan to the shortest lattice route of STEP m off it (full meshes)",
    )  # fmt: skip
    parser.add_argument(
        "--approach", metavar="DIR", nargs="+",
        help="with --retreat: the retreat's directions ranked by the approach network in DIR "
        "(experiments.train_approach) on the observed clouds; several DIRs: their mean "
        "probability",
    )  # fmt: skip
    parser.add_argument(
        "--approach-views", type=int, default=1, metavar="N",
        help="with --approach: the probabilities averaged over N subsets of the clouds (seeds "
        "0..N-1; thirty-eighth session)",
    )  # fmt: skip
    parser.add_argument(
        "--approach-threshold", type=float, metavar="P",
        help="with --approach: only directions of probability >= P (default: the network's)",
    )  # fmt: skip
    parser.add_argument(
        "--approach-open-side", action="store_true",
        help="with --approach: no direction towards the wall of a wall-mounted support (-y): "
        "the pre-goal stays on the open side",
    )  # fmt: skip
    parser.add_argument(
        "--approach-check", choices=("none", "method"), default="none",
        help="with --approach: 'none' takes the best direction as free; 'method' tries them "
        "best first and takes the first the method's checker calls free",
    )  # fmt: skip
    parser.add_argument(
        "--approach-replan", choices=("same", "plain", "next"), default="same",
        help="with --approach and --fallback-far-threshold: the replan after a time-out keeps "
        "the approach ('same') or plans plainly to the goal ('plain': the approach's pre-goal "
        "may be what was out of reach) or tries the second usable direction ('next', plain when "
        "there is none)",
    )  # fmt: skip
    parser.add_argument(
        "--retreat-after", type=float, default=0.0, metavar="S",
        help="with --retreat: the plain plan first for S seconds, the retreat only when it "
        "finds no path (PlannerConfig.retreat_after; 0: the retreat first)",
    )  # fmt: skip
    parser.add_argument(
        "--clear-path", type=float, default=0.0, metavar="M",
        help="move each estimator's returned path away from the observed support, towards an "
        "observed clearance of M where its checker allows (planner.clear_path; the path as "
        "planned is checked too: the summary's as_planned); 0: off",
    )  # fmt: skip
    parser.add_argument(
        "--clear-keep-ball", type=float, default=planner.ClearanceConfig.keep_ball, metavar="R",
        help="with --clear-path: waypoints within R (planner metric) of the goal stay",
    )  # fmt: skip
    parser.add_argument(
        "--completion", default=None, metavar="FOLDER",
        help="shape-completion networks (FOLDER/object, FOLDER/support; experiments."
        "train_completion): their predicted points are added to the observed clouds where "
        "--completion-in says",
    )  # fmt: skip
    parser.add_argument(
        "--completion-in", default="clear", metavar="WHERE",
        help="with --completion, comma- (or plus-) separated: clear (the returned path's clearing, "
        "--clear-path), far (the clearance far from the goal, --far-clearance); none: neither "
        "(the predicted points only for an NCE trained on completed clouds)",
    )  # fmt: skip
    parser.add_argument(
        "--completion-carve", action="store_true",
        help="with --completion: drop the predicted points each body's camera would have seen "
        "(omnihang_jax.completion.carve; the cameras of the dataset's records)",
    )  # fmt: skip
    parser.add_argument(
        "--select-geometric",
        default=None,
        metavar="JSON",
        help="choose nce_geometric's depth / radius / min points on --val-pairs training "
        "validation pairs, write them to JSON and stop (no planning)",
    )
    parser.add_argument("--val-pairs", type=int, default=60, help="for --select-geometric")
    parser.add_argument(
        "--select-goal-pass", type=float, default=0.9,
        help="--select-geometric: the hybrid goal pass the chosen setting must keep",
    )  # fmt: skip
    parser.add_argument(
        "--hce-goal-pass", type=float, default=None, metavar="P",
        help="choose both HCE thresholds as the NCE's was: the lowest score that calls at "
        "least P of the validation pairs' stable poses free (hce_goal_pass_thresholds); "
        "default: the balanced-accuracy thresholds saved with the weights",
    )  # fmt: skip
    parser.add_argument(
        "--select-nce-thresholds", default=None, metavar="T1,T2,...",
        help="--select-geometric: search the NCE's threshold too, jointly with the test",
    )  # fmt: skip
    parser.add_argument(
        "--symmetric",
        action="store_true",
        help="the penetration test also counts support points behind the observed object "
        "surface (collision.GeometricConfig.symmetric); with --select-geometric: choose that "
        "side's settings, the one-sided ones fixed (those of --geometric, else the defaults)",
    )
    parser.add_argument(
        "--sym-solid",
        action="store_true",
        help="with --symmetric: only behind solid-backed object points (both faces observed; "
        "collision.GeometricConfig.sym_solid_only)",
    )
    parser.add_argument(
        "--geometric",
        default=None,
        metavar="JSON",
        help="nce_geometric's settings: a --select-geometric file (its 'chosen' row); "
        "default collision.GeometricConfig()",
    )
    parser.add_argument("--out", default="out/paths")
    parser.add_argument("--results", default=None, help="summary JSON (default OUT/paths.json)")
    parser.add_argument("--figure", default=None, help="strip-of-frames PNG")
    parser.add_argument("--figure-paths", type=int, default=4)
    parser.add_argument("--workers", type=int, default=1, help="derive processes")
    parser.add_argument(
        "--summary-only", action="store_true",
        help="plan nothing: the summary of the rows already in OUT/pairs.jsonl (after --shard "
        "runs; pairs without rows are left out and counted as missing_pairs)",
    )  # fmt: skip
    parser.add_argument(
        "--only-pairs", default=None, metavar="FILE",
        help="plan and summarise only these of the --pairs pairs (FILE: pair names, one per line, "
        "or a JSON list; thirty-eighth session: a paired comparison of two rules plans only the "
        "pairs where they decide differently, scripts/approach_decisions.py)",
    )  # fmt: skip
    parser.add_argument(
        "--shard", default=None, metavar="I/N",
        help="plan only every N-th pair from the I-th (0-based) into OUT/pairs.jsonl and write "
        "no summary: N processes plan one run together (scripts/device_paths.sh); a run "
        "without --shard afterwards plans nothing new and writes the summary",
    )  # fmt: skip
    parser.add_argument(
        "--wall-margin", type=float, default=None, metavar="M",
        help="the estimators' checkers also call a state colliding where an observed object "
        "point comes closer than M (m; 0: behind it) to the known wall plane (planner.WallChecker); "
        "default: the wall is not checked",
    )  # fmt: skip
    parser.add_argument(
        "--split", default="test", choices=("test", "train"),
        help="plan on held-out pairs (the evaluation) or on training pairs (with --mine; never "
        "the NCE's validation pairs, pair_index %% 20 == 0)",
    )  # fmt: skip
    parser.add_argument(
        "--mine", default=None, metavar="DIR",
        help="record the states each estimator's checker judged, label those near the support "
        "with the meshes and write DIR/<pair>.npz (hard examples for train_collision --mined)",
    )  # fmt: skip
    parser.add_argument(
        "--mine-cap", type=int, default=6000,
        help="recorded states kept a pair (half called colliding, half free), besides the "
        "returned path's",
    )  # fmt: skip
    parser.add_argument(
        "--fallback-far-threshold", type=float, default=None, metavar="T",
        help="nce / nce_geometric with --nce-goal-ball: when a plan times out, plan again for "
        "--fallback-time s with the NCE's threshold beyond the goal ball raised to T (laxer; "
        "T equal to --nce-far-threshold: a replan with the same checker, a fresh search); "
        "default: no second plan",
    )  # fmt: skip
    parser.add_argument("--fallback-time", type=float, default=15.0, metavar="S",
                        help="s: the second plan's time limit")  # fmt: skip
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.fallback_far_threshold is not None and args.mine:
        parser.error("--fallback-far-threshold is for the evaluation, not with --mine")
    if args.split == "train" and not args.mine:
        parser.error("--split train is for --mine: the evaluation plans on held-out pairs")
    if args.mine_cap < 2:
        parser.error("--mine-cap must be >= 2")
    if args.wall_margin is not None and not args.wall_margin >= 0:
        parser.error("--wall-margin must be >= 0")
    geo = collision.GeometricConfig()
    if args.geometric:
        chosen = json.loads(Path(args.geometric).read_text())["chosen"]
        if chosen is None:
            parser.error(
                f"--geometric {args.geometric}: no setting was chosen (none kept the goal pass)"
            )
        keys = ("depth", "radius", "min_points")
        if args.symmetric and not args.select_geometric:
            keys += tuple(k for k in ("sym_depth", "sym_radius", "sym_min_points") if k in chosen)
        geo = dataclasses.replace(geo, **{k: chosen[k] for k in keys})
        if "nce_threshold" in chosen and args.nce_threshold is None:  # a joint selection
            args.nce_threshold = float(chosen["nce_threshold"])
    if args.sym_solid:
        if not args.symmetric:
            parser.error("--sym-solid needs --symmetric")
        geo = dataclasses.replace(geo, sym_solid_only=True)
    if args.select_geometric:
        thresholds = None
        if args.select_nce_thresholds:
            thresholds = [float(t) for t in args.select_nce_thresholds.split(",") if t]
        sel = select_geometric(
            args.data, args.weights, args.val_pairs, goal_pass=args.select_goal_pass, geo=geo,
            symmetric=args.symmetric, nce_thresholds=thresholds,
        )  # fmt: skip
        Path(args.select_geometric).parent.mkdir(parents=True, exist_ok=True)
        Path(args.select_geometric).write_text(json.dumps(sel, indent=1))
        print(json.dumps({"nce": sel["nce"], "chosen": sel["chosen"]}, indent=1))
        return sel
    methods = tuple(m for m in args.methods.split(",") if m)
    bad = [m for m in methods if m not in ALL_METHODS]
    if bad:
        raise SystemExit(f"unknown methods {bad}; choose from {ALL_METHODS}")
    if args.goal == "answer" and not args.pairs_from:
        parser.error("--goal answer needs --pairs-from (an eval_stage3 run's per-pair records)")
    if not args.resolution > 0:
        parser.error("--resolution must be > 0")
    if args.planner_seed < 1:
        parser.error("--planner-seed must be >= 1 (OMPL does not take 0)")
    try:
        retreat = tuple(float(x) for x in args.retreat.split(",") if x.strip())
    except ValueError:
        parser.error(f"--retreat {args.retreat!r}: comma-separated lengths in metres")
    if any(not x > 0 for x in retreat):
        parser.error("--retreat lengths must be > 0")
    if args.far_clearance < 0 or (args.far_clearance > 0 and not args.far_ball > 0):
        parser.error("--far-clearance must be >= 0, and with it --far-ball > 0")
    if not 0 <= args.retreat_after < args.time_limit:
        parser.error("--retreat-after must be in [0, --time-limit)")
    shard = None
    if args.shard is not None:
        try:
            shard = tuple(int(x) for x in args.shard.split("/"))
            assert len(shard) == 2 and 0 <= shard[0] < shard[1]
        except (ValueError, AssertionError):
            parser.error(f"--shard {args.shard!r}: I/N with 0 <= I < N")
    if args.clear_path < 0 or args.clear_keep_ball < 0:
        parser.error("--clear-path and --clear-keep-ball must be >= 0")
    completion_in = (
        tuple(x for x in args.completion_in.replace("+", ",").split(",") if x and x != "none")
        if args.completion
        else ()
    )
    if set(completion_in) - {"clear", "far"}:
        parser.error(f"--completion-in {args.completion_in!r}: clear and/or far")
    clearance = None
    if args.clear_path > 0:
        clearance = planner.ClearanceConfig(target=args.clear_path, keep_ball=args.clear_keep_ball)
    config = planner.PlannerConfig(
        time_limit=args.time_limit, goal_radius=args.goal_radius, resolution=args.resolution,
        retreat_lengths=retreat, retreat_after=args.retreat_after, seed=args.planner_seed,
    )  # fmt: skip
    out = Path(args.out)
    (out / "scenes").mkdir(parents=True, exist_ok=True)
    if args.symmetric:
        geo = dataclasses.replace(geo, symmetric=True)
    est = load_estimators(
        args.weights, args.nce_threshold, args.nce_far_threshold, args.nce_goal_ball, geo
    )._replace(
        test_goal_ball=args.test_goal_ball,
        far_clearance=args.far_clearance,
        far_ball=args.far_ball if args.far_clearance > 0 else 0.0,
        completion_in=completion_in,
        wall_margin=args.wall_margin,
    )
    hce_selection = None
    if args.hce_goal_pass is not None:
        if not 0.0 < args.hce_goal_pass <= 1.0:
            parser.error("--hce-goal-pass must be in (0, 1]")
        if not {"hce", "hce_true_normals"} & set(methods):
            parser.error("--hce-goal-pass needs --methods with hce or hce_true_normals")
        hce_selection = hce_goal_pass_thresholds(
            args.data, args.weights, args.val_pairs, args.hce_goal_pass
        )
        est = est._replace(
            normal_config=dataclasses.replace(
                est.normal_config, threshold=hce_selection["hce"]["chosen"]["threshold"]
            ),
            true_threshold=hce_selection["hce_true_normals"]["chosen"]["threshold"],
        )
        print(json.dumps(hce_selection, indent=1))
    if args.fallback_far_threshold is not None:
        try:
            est = with_fallback(est, args.fallback_far_threshold, args.fallback_time)
        except ValueError as e:
            parser.error(str(e))
    if args.routes and not args.approach:
        parser.error("--routes needs --approach (the straight rule it fills in or precedes)")
    if args.routes_check != "none" and not args.routes:
        parser.error("--routes-check needs --routes (the route network whose routes it checks)")
    if args.routes_end_gap < 0 or args.routes_tries < 1:
        parser.error("--routes-end-gap must be >= 0 and --routes-tries >= 1")
    if args.routes and args.oracle_two_moves:
        parser.error("--routes and --oracle-two-moves both choose the route: one of them")
    if args.oracle_retreat:
        if not retreat:
            parser.error("--oracle-retreat needs --retreat LENGTHS")
        est = est._replace(oracle_retreat=True)
    if args.approach:
        if not retreat or args.oracle_retreat:
            parser.error("--approach needs --retreat LENGTHS (and not --oracle-retreat)")
        predictor = approach.load_predictor(
            args.approach, args.approach_threshold, args.approach_views
        )
        predictor.warm_up()  # compiled outside the planning clock
        if args.approach_replan == "next" and args.approach_check != "none":
            parser.error("--approach-replan next needs --approach-check none (with 'method' the "
                         "first plan may already have used the second direction)")  # fmt: skip
        est = est._replace(approach=predictor, approach_check=args.approach_check,
                           approach_open_side=args.approach_open_side,
                           approach_replan=args.approach_replan,
                           oracle_two_moves=args.oracle_two_moves,
                           oracle_lattice=args.oracle_lattice)  # fmt: skip
        if args.oracle_lattice and not args.oracle_two_moves:
            parser.error("--oracle-lattice needs --oracle-two-moves")
    elif args.oracle_two_moves:
        parser.error("--oracle-two-moves needs --approach (elsewhere its rule plans)")
    if args.routes:
        routes = approach.load_predictor(args.routes, args.routes_threshold, args.routes_views)
        if not routes.config.first_lengths:
            parser.error(f"--routes {args.routes}: a straight approach network, not a route "
                         "network (experiments.train_approach --first-lengths)")  # fmt: skip
        routes.warm_up()
        est = est._replace(routes=routes, routes_mode=args.routes_mode,
                           routes_check=args.routes_check, routes_end_gap=args.routes_end_gap,
                           routes_tries=args.routes_tries)  # fmt: skip
    if args.far_nce:
        far_cfg, far_params, _ = collision.load_estimator(Path(args.far_nce, "nce"))
        if args.far_nce_threshold is not None:
            far_cfg = dataclasses.replace(far_cfg, threshold=args.far_nce_threshold)
        est = est._replace(far_nce=(far_cfg, far_params, jax.jit(collision.nce_collides(far_cfg))),
                           far_nce_ball=args.far_nce_ball)  # fmt: skip
    nce_configs = [est.nce_config] + ([est.far_nce[0]] if est.far_nce else [])
    if any(c.input_clouds == "completed" for c in nce_configs) and not (
        args.completion and args.completion_carve
    ):
        parser.error("an NCE given (--weights / --far-nce) was trained on completed, carved "
                     "clouds: pass --completion FOLDER --completion-carve")  # fmt: skip
    records = read_answers(args.pairs_from) if args.pairs_from else None
    cases = load_pairs(
        args.data, args.pairs, args.workers, not args.no_progress, records, args.goal == "answer",
        split=args.split, names=set(read_pair_names(args.only_pairs)) if args.only_pairs else None,
    )  # fmt: skip
    if args.only_pairs:
        cases = only_pairs(cases, args.only_pairs)
    if args.completion:
        cases = add_completion(cases, args.completion, args.data if args.completion_carve else None)
    jsonl = out / "pairs.jsonl"
    rows = [json.loads(x) for x in jsonl.read_text().splitlines()] if jsonl.exists() else []
    # a resumed run reuses only rows planned to the same kind of goal (older rows: stable)
    kind = args.goal if args.goal == "stable" else f"answer:{args.pairs_from}"
    rows = [r for r in rows if r.get("goal_kind", "stable") == kind]
    done = {(r["pair"], r["method"]) for r in rows}
    figure_items = []
    t0 = time.time()
    mine = cases if shard is None else cases[shard[0] :: shard[1]]
    if args.summary_only:
        mine = []
    for case in tqdm(mine, desc="plan", unit="pair", disable=args.no_progress):
        todo = [m for m in methods if (case.name, m) not in done]
        if not todo:
            continue
        mined = None if not args.mine else (Path(args.mine), args.mine_cap)
        new_rows, paths = evaluate_pair(case, est, config, todo, clearance, mined)
        for row in new_rows:
            row["goal_kind"] = kind
        with open(jsonl, "a") as f:
            for row in new_rows:
                f.write(json.dumps(row) + "\n")
        rows += new_rows
        for method, path in paths.items():
            dense = planner.interpolate_path(path, 0.01, planner.object_radius(case.scene))
            xml = planner.path_scene_xml(case.scene, dense)  # <= 100 keys, 1 cm or more apart
            (out / "scenes" / case.name).mkdir(exist_ok=True)
            (out / "scenes" / case.name / f"{method}.xml").write_text(xml)
            np.save(out / "scenes" / case.name / f"{method}_path.npy", path)
    if shard is not None:
        print(f"shard {args.shard}: {len(mine)} of {len(cases)} pairs planned into {jsonl}")
        return {}
    names = {c.name for c in cases}
    latest = {(r["pair"], r["method"]): r for r in rows}  # a resumed run: the last row counts
    rows = [r for r in latest.values() if r["pair"] in names and r["method"] in methods]
    summary = summarise(rows, methods)
    missing = sorted(names - {r["pair"] for r in rows})
    if missing:  # only with --summary-only (or --shard runs cut short): say so
        print(f"{len(missing)} of {len(names)} pairs have no rows in {jsonl}: left out")
        summary["missing_pairs"] = missing
    summary["settings"] = dict(
        planner=dataclasses.asdict(config),
        weights=args.weights,
        nce_config=est.nce_config.__dict__,
        normal_config=est.normal_config.__dict__,
        hce_true_normals_threshold=est.true_threshold,
        hce_goal_pass_selection=hce_selection,
        geometric=dataclasses.asdict(est.geometric)
        if {"nce_geometric", "geometric"} & set(methods)
        else None,
        geometric_settings_from=args.geometric,
        nce_far_threshold=est.nce_far_threshold,
        nce_goal_ball_m=est.nce_goal_ball,
        test_goal_ball_m=est.test_goal_ball,
        far_clearance_m=est.far_clearance,
        far_ball_m=est.far_ball,
        completion=args.completion,
        completion_in=list(completion_in),
        completion_carve=bool(args.completion and args.completion_carve),
        wall_margin_m=est.wall_margin,
        fallback=None
        if est.fallback_far_threshold is None
        else dict(far_threshold=est.fallback_far_threshold, seconds=est.fallback_time),
        far_nce=None
        if est.far_nce is None
        else dict(
            weights=args.far_nce, config=dataclasses.asdict(est.far_nce[0]), ball_m=est.far_nce_ball
        ),
        retreat_lengths_m=list(config.retreat_lengths),
        oracle_retreat=est.oracle_retreat,
        oracle_two_moves=est.oracle_two_moves,
        oracle_lattice=est.oracle_lattice,
        routes=None
        if est.routes is None
        else dict(
            weights=args.routes,
            threshold=est.routes.config.threshold,
            first_lengths_m=list(est.routes.config.first_lengths),
            clear_m=est.routes.config.clear,
            mode=est.routes_mode,
            views=est.routes.views,
            check=est.routes_check,
            end_gap_m=est.routes_end_gap,
            tries=est.routes_tries,
        ),  # fmt: skip
        approach=None
        if est.approach is None
        else dict(
            weights=args.approach[0] if len(args.approach) == 1 else args.approach,
            views=est.approach.views,
            threshold=est.approach.config.threshold,
            check=est.approach_check,
            open_side=est.approach_open_side,
            replan=est.approach_replan,
        ),  # fmt: skip
        clear_path=None if clearance is None else dataclasses.asdict(clearance),
        goal="first stable pose of each held-out pair"
        if args.goal == "stable"
        else f"the where-to-hang pipeline's all-stages answer ({args.pairs_from})",
        pairs_from=args.pairs_from,
        device=str(jax.devices()[0]),
        host_cores=os.cpu_count(),
        wall_s_this_run=round(time.time() - t0, 1),
        only_pairs=args.only_pairs,
        command="python -m experiments.eval_paths "
        + " ".join(sys.argv[1:] if argv is None else argv),
    )
    results = Path(args.results) if args.results else out / "paths.json"
    results.parent.mkdir(parents=True, exist_ok=True)
    results.write_text(json.dumps(summary, indent=1))
    if args.figure:
        by_name = {c.name: c for c in cases}
        for r in rows:
            if len(figure_items) >= args.figure_paths:
                break
            p = out / "scenes" / r["pair"] / f"{r['method']}_path.npy"
            if r["method"] == "nce" and r["returned"] and p.exists():
                figure_items.append((by_name[r["pair"]], _label(r), np.load(p)))
        for r in rows:  # fill up with other methods' paths
            if len(figure_items) >= args.figure_paths:
                break
            p = out / "scenes" / r["pair"] / f"{r['method']}_path.npy"
            if r["method"] != "nce" and r["returned"] and p.exists():
                figure_items.append((by_name[r["pair"]], _label(r), np.load(p)))
        if figure_items:
            strip_figure(figure_items, args.figure)
    for m in methods:
        if m in summary:
            s = summary[m]
            print(
                f"{m}: precision {s['precision']} recall {s['recall']} F1 {s['f1']} "
                f"({s['returned']} returned, {s['collision_free']} free of {s['pairs']}); "
                f"median {s['median_planning_s']} s, {s['timeouts']} time-outs"
            )
    return summary


if __name__ == "__main__":
    main()
