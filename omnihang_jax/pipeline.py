"""Stages 1-3 as one pure function: ``make_hang_pipeline`` and its :class:`PipelineConfig`.

``hang(params, key, clouds [B, ...]) -> HangOutput`` runs Stage 1's K proposals, their Stage-2
refinements, CEM on the value function V (:mod:`omnihang_jax.stage3`) from the configured starts
on every view of the clouds, the ranking networks and the answer rule, in one XLA program.
:data:`ANSWER_PIPELINE` is the default answer's (``omnihang_jax.where.DEFAULT``);
``PipelineConfig()`` is the paper's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from omnihang_jax import selection
from omnihang_jax.poses import (
    box_centre,
    move_origin,
    pose6_to_pose7,
    quaternion_to_matrix,
    reframe,
    super_fibonacci,
)
from omnihang_jax.stage3 import (
    CEMConfig,
    PairClouds,
    ValueConfig,
    cem_keys,
    make_refiner,
    make_value,
    subset_clouds,
)

__all__ = ["ANSWER_PIPELINE", "HangOutput", "PipelineConfig", "make_ensemble_score",
           "make_hang_pipeline"]  # fmt: skip


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Stages 1-3 in one call. ``starts``: the proposals CEM refines: "stage2" (all stages,
    the paper's pipeline) and/or "stage1" (the Stages 1+3 ablation). ``select``: how the
    answer is picked among each start's refined candidates (``omnihang_jax.selection``;
    default the paper's highest V). ``ANSWER_PIPELINE`` is the default answer's
    (``omnihang_jax.where``)."""

    num_proposals: int = 5  # K Stage-1 proposals per pair (facts: 5 at evaluation)
    cem: CEMConfig = CEMConfig()
    starts: tuple[str, ...] = ("stage2",)
    select: selection.SelectConfig = selection.SelectConfig()
    # True: the answer is picked among the refined candidates of ALL starts (with starts
    # ("stage2", "stage1"): 2K candidates), not only the first start's
    pool_starts: bool = False
    # ours: R more value networks (params["rank_values"], a list of R
    # value params of the same ValueConfig) rank the refined candidates: their final score is
    # the mean of log V over the CEM's V and these (a geometric-mean ensemble); CEM itself
    # searches on params["value"] alone. 0: the CEM's V ranks (the paper's)
    rank_values: int = 0
    # ours: False: the R networks rank alone (the mean log V over them,
    # without the CEM's V), e.g. a ranker trained on the pipeline's own refined candidates
    # (experiments.train_ranker); only with rank_values > 0
    rank_with_value: bool = True
    # ours: the subsamples (j, T) of the clouds the pipeline runs on
    # (stage3.subset_clouds); with several, CEM and the ranking run once per view (same keys)
    # and the answer is picked among every view's candidates (their K axes concatenated)
    views: tuple[tuple[int, int], ...] = ((0, 1),)
    # ours: one CEM over every view and start (their candidates
    # stacked on the pair axis, each with the key it had in its own CEM) and one ranking pass
    # over every view: the same candidates as False, up to float rounding, with one sequence of
    # CEM iterations instead of one per view and start (latency at batch 1; peak memory grows
    # with views x starts). False: each view and start its own CEM, one after the other.
    # None (default): fused on a GPU, one after the other on the CPU, where fusing measured
    # slower (two views at batch 1: 82.0 s fused against 66.3 s on 2 cores; 119.0 against
    # 179.6 ms on one H100)
    fuse: bool | None = None
    # ours, for objects in any frame: Stage 1 runs on the object cloud turned into this many
    # frames (:func:`frame_hypotheses`: a super-Fibonacci set of SO(3) turned by one random
    # turn per pair), every proposal is turned back, V (which reads the object posed in the
    # support frame, so it does not depend on the object's frame) picks the K best as the
    # Stage-1 starts, and Stage 2 refines each in its own frame (:func:`make_frame_starts`).
    # 0: Stages 1-2 read the cloud as given.
    frames: int = 0
    # ours, for objects in any frame: the object-frame network (``omnihang_jax.canon``,
    # params["canon"]) gives H more hypotheses, each the transform that writes the object as
    # the library does, read as ``frames``' are (before them). False: none.
    canon: bool = False


# The default pipeline (``omnihang_jax.where.DEFAULT``): K = 10 proposals, CEM from both the
# Stage-1 and the Stage-2 proposals on three subsamples of the clouds (views), the ranking
# networks alone score the candidates, and the answer is picked among all of them by the
# observed-cloud rule (selection.CHOSEN). Every choice was made on the validation objects
# (docs/where.md). ``PipelineConfig()`` is the paper's: K = 5, Stage-2 starts, highest V.
ANSWER_PIPELINE = PipelineConfig(
    num_proposals=10,
    starts=("stage2", "stage1"),
    select=selection.CHOSEN,
    pool_starts=True,
    rank_with_value=False,
    views=((0, 1), (1, 2), (3, 4)),
)


def frame_hypotheses(key: jax.Array, n: int) -> jax.Array:
    """[n, 3, 3] the frames the object cloud is read in: ``super_fibonacci(n)`` turned by one
    uniform random rotation (drawn from ``key``), so that no frame is favoured."""
    turn = quaternion_to_matrix(jax.random.normal(key, (4,)))
    return quaternion_to_matrix(jnp.asarray(super_fibonacci(n), jnp.float32)) @ turn


def make_frame_starts(stage1_config, stage2_config, value, config: PipelineConfig,
                      value_config: ValueConfig, canon_config=None) -> Callable:  # fmt: skip
    """``starts(params, key, clouds [B, ...]) -> (stage1 [B, K, 7], stage2 [B, K, 7], pool
    [B, M*K, 7])``: Stage 1 on M copies of the object cloud, each written in one frame
    hypothesis (points ``H p + s``), its M x K proposals turned back (the pool); the K that V
    scores highest (on the first view) are the Stage-1 starts, and Stage 2 refines each in the
    frame it came from (so Stage 2 runs K times a pair, as without frames).

    The hypotheses: with ``config.canon`` the object-frame network's H transforms
    (``omnihang_jax.canon``, ``params["canon"]``; ``canon_config`` its CanonConfig), then
    ``config.frames`` more from :func:`frame_hypotheses` (no shift)."""
    from omnihang_jax.stage1 import make_stage1
    from omnihang_jax.stage2 import make_stage2

    stage1, stage2 = make_stage1(stage1_config), make_stage2(stage2_config)
    k = config.num_proposals
    view = tuple(int(x) for x in config.views[0])
    if config.canon and canon_config is None:
        raise ValueError("PipelineConfig.canon needs the object-frame network's config")
    canon = None
    if config.canon:
        from omnihang_jax.canon import make_canon

        canon = make_canon(canon_config)

    def hypotheses(params, key, points):  # -> [B, M, 3, 3], [B, M, 3]
        b = points.shape[0]
        rots, shifts = [], []
        if canon is not None:  # the network reads the cloud about its box centre c
            centre = jax.vmap(box_centre)(points)
            rot, shift, _ = canon.frames(params["canon"], points - centre[:, None])
            rots.append(rot.astype(points.dtype))
            shift = shift - jnp.einsum("bhij,bj->bhi", rot, centre)  # R (p - c) + t
            shifts.append(shift.astype(points.dtype))
        if config.frames:
            fib = jnp.broadcast_to(frame_hypotheses(key, config.frames), (b, config.frames, 3, 3))
            rots.append(fib.astype(points.dtype))
            shifts.append(jnp.zeros((b, config.frames, 3), points.dtype))
        return jnp.concatenate(rots, 1), jnp.concatenate(shifts, 1)

    def back(pose7, rot, shift):  # poses of the cloud H p + s -> of the cloud p
        return reframe(move_origin(pose7, shift), rot)

    def starts(params, key, clouds: PairClouds):
        kf, kp = jax.random.split(key)
        b, n, _ = clouds.object_points.shape
        rot, shift = hypotheses(params, kf, clouds.object_points)  # [B, M, 3, 3], [B, M, 3]
        m = rot.shape[1]
        obj = jnp.einsum("bmij,bnj->mbni", rot, clouds.object_points) + jnp.moveaxis(
            shift, 1, 0)[:, :, None]  # fmt: skip
        sup = jnp.broadcast_to(clouds.support_points[None], (m, *clouds.support_points.shape))
        pose6 = stage1.propose(params["stage1"], obj.reshape(m * b, n, 3),
                               sup.reshape(m * b, -1, 3), kp, k)  # fmt: skip
        pose6 = jnp.moveaxis(pose6.reshape(m, b, k, 6), 0, 1).reshape(b, m * k, 6)
        of = jnp.repeat(jnp.arange(m), k)  # the frame of each pool member
        pool = back(pose6_to_pose7(pose6), rot[:, of], shift[:, of])  # [B, M*K, 7]
        small = subset_clouds(clouds, value_config, *view)
        score = jax.vmap(value.score, in_axes=(None, 0, 0))(params["value"], small, pool)
        top = jnp.argsort(-score, axis=1)[:, :k]  # [B, K]
        first = jnp.take_along_axis(pool, top[:, :, None], axis=1)
        # Stage 2 on each chosen proposal, in its own frame
        h = jnp.take_along_axis(rot, of[top][:, :, None, None], axis=1)  # [B, K, 3, 3]
        hs = jnp.take_along_axis(shift, of[top][:, :, None], axis=1)  # [B, K, 3]
        seen = jnp.einsum("bkij,bnj->bkni", h, clouds.object_points) + hs[:, :, None]

        def tile(x):  # [B, ...] -> [B*K, ...]
            return jnp.broadcast_to(x[:, None], (b, k, *x.shape[1:])).reshape(b * k, *x.shape[1:])

        chosen = jnp.take_along_axis(pose6, top[:, :, None], axis=1).reshape(b * k, 6)
        out = stage2.refine(params["stage2"], seen.reshape(b * k, n, 3), tile(clouds.support_points),
                            chosen, tile(clouds.support_normals))  # fmt: skip
        second = back(pose6_to_pose7(out.pose6).reshape(b, k, 7), h, hs)
        return first, second, pool

    return starts


class HangOutput(NamedTuple):
    """B pairs, K proposals. Poses [B, K, 7] (xyz + wxyz, object in support frame).

    stage1_poses, stage2_poses: Stages 1 and 2. refined: {start: [B, K, 7]} CEM results from
    each start; scores: {start: [B, K]} final log V (with ``PipelineConfig.rank_values``: the
    mean log V of CEM's V and the ranking networks); initial_scores: {start: [B, K]} log V of
    the unrefined proposal. best: {start: [B]} index of the best final V (the pipeline's
    answer, facts: "the candidate with the best final Stage-3 score"); pose: [B, 7] the answer
    of the first start.
    """

    stage1_poses: Any
    stage2_poses: Any
    refined: Any
    scores: Any
    initial_scores: Any
    best: Any
    pose: Any
    # the answer's pool in the rule's order, best first: [B, C, 7] poses, [B, C] rule keys and
    # [B, C] int the index in ``PipelineConfig.starts`` each candidate was refined from; the pool
    # is every start's refined candidates with ``pool_starts``, else the first start's
    ranked: Any = None
    ranked_keys: Any = None
    ranked_start: Any = None
    ranked_proposal: Any = None  # [B, C] the Stage-1 draw each candidate descends from


def make_ensemble_score(
    rank_configs,
    with_first: bool = True,
    view: tuple[int, int] = (0, 1),
    stacked: tuple[tuple[int, int], ...] | None = None,
) -> Callable:
    """``ensemble(scores [B, P], extra_params [R value params], clouds [B, ...] the observed
    clouds, poses [B, P, 7]) -> [B, P]``: the mean of log V over the first V (its final
    scores, as CEM returns them) and the R other value networks on the same poses, network i of
    config ``rank_configs[i]`` scoring its own subsample of the clouds (configs may differ from
    each other and from the CEM's V, e.g. near points; one ``ValueConfig``: all R share it): a
    geometric-mean ensemble that ranks CEM's candidates (``PipelineConfig.rank_values``,
    ``omnihang_jax.where``). ``with_first=False``: the mean
    over the R networks alone (``PipelineConfig.rank_with_value``). ``view`` = (j, T): every
    network sees subset j of T instead of subset 0 (the pipeline's views). ``stacked`` V
    views (j, T): scores [V*B, P] and poses [V*B, P, 7] hold V views' candidates, view-major,
    of the B pairs of ``clouds``; rows of view v are scored on its subset, every view in one
    pass of each network (``PipelineConfig.fuse``). Pure, un-jitted."""
    if stacked is not None and (tuple(view) != (0, 1) or not stacked):
        raise ValueError("stacked views go with no view")
    views = [tuple(view)]

    def view_clouds(clouds, config, i, of):
        if stacked is None:
            return subset_clouds(clouds, config, i, of)
        subs = [subset_clouds(clouds, config, *v) for v in stacked]
        return jax.tree.map(lambda *x: jnp.concatenate(x, axis=0), *subs)

    def per_pair(config):
        value = make_value(config)
        return jax.vmap(lambda p, c, poses: value.score(p, c, poses), in_axes=(None, 0, 0))

    def ensemble(scores, extra_params, clouds: PairClouds, poses):
        configs = (
            (rank_configs,) * len(extra_params)
            if isinstance(rank_configs, ValueConfig)
            else tuple(rank_configs)
        )
        if len(configs) != len(extra_params):
            raise ValueError(f"{len(extra_params)} ranking networks, {len(configs)} configs")
        # networks of one config run as one network over stacked parameters (jax.vmap over
        # the network axis): one pass a config, not one a network (fewer kernels at batch 1)
        groups: dict = {}
        for c, p in zip(configs, extra_params, strict=True):
            groups.setdefault(c, []).append(p)
        logs, count = [], 0
        for c, ps in groups.items():
            score = per_pair(c)
            together = jax.tree.map(lambda *x: jnp.stack(x), *ps) if len(ps) > 1 else None
            total = 0.0
            for i, of in views:
                sub = view_clouds(clouds, c, i, of)
                if together is None:
                    total = total + score(ps[0], sub, poses)
                else:
                    each = jax.vmap(score, in_axes=(0, None, None))(together, sub, poses)
                    total = total + jnp.sum(each, axis=0)
            logs.append(total)
            count += len(ps)
        if with_first or not logs:
            logs, count = [scores] + logs, count + 1
        return sum(logs) / count

    return ensemble


def make_hang_pipeline(stage1_config, stage2_config, value_config: ValueConfig,
                       config: PipelineConfig = PipelineConfig(),
                       rank_configs=None, canon_config=None) -> Callable:  # fmt: skip
    """``hang(params, key, clouds: PairClouds [B, ...]) -> HangOutput``; params =
    ``{"stage1", "stage2", "value"}`` (+ ``"rank_values"``). Pure and un-jitted:
    ``jax.jit(hang)`` runs Stages 1, 2 and CEM on V in one XLA program, batched over pairs.
    The observed support normals (``clouds.support_normals``) reach Stage 2 for its clearance
    (``Stage2Config.clearance``; 0 leaves them unused). ``rank_configs``: the ranking
    networks' configs, one each or one for all (default ``value_config``; e.g. with near
    points), each scoring its own subsample of the clouds (``make_ensemble_score``)."""
    from omnihang_jax.predict import make_predict

    predict = make_predict(stage1_config, stage2_config)
    refine = make_refiner(value_config, config.cem)
    views = tuple(tuple(int(x) for x in v) for v in config.views)
    if not views or any(not 0 <= j < t for j, t in views):
        raise ValueError(f"PipelineConfig.views {config.views}: need (j, T) with 0 <= j < T")
    ranks = {
        v: make_ensemble_score(
            value_config if rank_configs is None else rank_configs, config.rank_with_value, v,
        )
        for v in views
    }  # fmt: skip
    fused_rank = make_ensemble_score(
        value_config if rank_configs is None else rank_configs, config.rank_with_value,
        stacked=views,
    )  # fmt: skip
    rule = config.select
    fuse = jax.default_backend() != "cpu" if config.fuse is None else config.fuse
    frame_starts = None
    if config.frames or config.canon:
        frame_starts = make_frame_starts(stage1_config, stage2_config, make_value(value_config),
                                         config, value_config, canon_config)  # fmt: skip

    def fused_views(params, k3, clouds, starts):
        """Every view's and start's CEM as one CEM over V * B rows of S * K starts (each
        start's key as in ``one_view``), then one ranking pass: per start {name: [B, V*K]}."""
        b = clouds.object_points.shape[0]
        names = config.starts
        width = [starts[n].shape[1] for n in names]
        keys = jnp.concatenate(
            [cem_keys(jax.random.fold_in(k3, i), b, w) for i, w in enumerate(width)], axis=1
        )
        tile = lambda x: jnp.concatenate([x] * len(views), axis=0)  # noqa: E731
        subs = [subset_clouds(clouds, value_config, *v) for v in views]
        small = jax.tree.map(lambda *x: jnp.concatenate(x, axis=0), *subs)  # [V*B, ...]
        res = refine(params["value"], None, small,
                     tile(jnp.concatenate([starts[n] for n in names], axis=1)), keys=tile(keys))  # fmt: skip
        scores = res.scores
        if config.rank_values:
            extra = params["rank_values"]
            if len(extra) != config.rank_values:
                raise ValueError(f"params['rank_values'] holds {len(extra)} value "
                                 f"networks, PipelineConfig.rank_values {config.rank_values}")  # fmt: skip
            scores = fused_rank(scores, extra, clouds, res.poses)
        cut = list(np.cumsum(width)[:-1])

        def per_start(x):  # [V*B, S*K, ...] -> {name: [B, V*K, ...]}
            parts = [jnp.split(v, cut, axis=1) for v in jnp.split(x, len(views), axis=0)]
            return {n: jnp.concatenate([p[i] for p in parts], axis=1) for i, n in enumerate(names)}

        return per_start(res.poses), per_start(scores), per_start(res.initial_scores)

    def one_view(params, k3, clouds, starts, view):
        """CEM and the ranking on one subsample: per start (poses, scores, initial)."""
        small = subset_clouds(clouds, value_config, *view)
        refined, scores, initial = {}, {}, {}
        for i, name in enumerate(config.starts):
            res = refine(params["value"], jax.random.fold_in(k3, i), small, starts[name])
            refined[name], scores[name], initial[name] = res.poses, res.scores, res.initial_scores
        if config.rank_values:  # static: the ensemble's mean log V ranks the candidates
            extra = params["rank_values"]
            if len(extra) != config.rank_values:
                raise ValueError(f"params['rank_values'] holds {len(extra)} value "
                                 f"networks, PipelineConfig.rank_values {config.rank_values}")  # fmt: skip
            # every start's candidates in one pass of each network ([B, S*K])
            width = [refined[n].shape[1] for n in config.starts]
            ranked = ranks[view](
                jnp.concatenate([scores[n] for n in config.starts], axis=1), extra, clouds,
                jnp.concatenate([refined[n] for n in config.starts], axis=1),
            )  # fmt: skip
            parts = jnp.split(ranked, list(np.cumsum(width)[:-1]), axis=1)
            scores = dict(zip(config.starts, parts, strict=True))
        return refined, scores, initial

    def hang(params, key, clouds: PairClouds) -> HangOutput:
        k1, k3 = jax.random.split(key)
        if frame_starts is not None:
            stage1_poses, stage2_poses, _ = frame_starts(params, k1, clouds)
        else:
            pred = predict(
                params["stage1"], params["stage2"], clouds.object_points, clouds.support_points,
                k1, config.num_proposals, support_normals=clouds.support_normals,
            )  # fmt: skip
            stage1_poses, stage2_poses = pred.stage1_poses, pred.stage2_poses
        starts = {"stage1": stage1_poses, "stage2": stage2_poses}
        if fuse:
            refined, scores, initial = fused_views(params, k3, clouds, starts)
        else:
            per_view = [one_view(params, k3, clouds, starts, v) for v in views]
            # the views' candidates side by side: [B, V*K] per start
            refined, scores, initial = (
                {n: jnp.concatenate([pv[j][n] for pv in per_view], axis=1)
                 for n in config.starts}
                for j in range(3)
            )  # fmt: skip
        best, keys_of = {}, {}
        for name in config.starts:
            final = scores[name]
            best[name] = jnp.argmax(final, axis=1)
            keys_of[name] = final
            if rule.rule != "value":  # static: the paper's rule traces today's function
                counts = jax.vmap(selection.inside_counts, in_axes=(0, 0, 0, 0, None, None))(
                    clouds.object_points, clouds.support_points, clouds.support_normals,
                    refined[name], rule.depth, rule.radius,
                )  # fmt: skip
                keys_of[name] = selection.select_key(final, counts, rule)
                best[name] = jnp.argmax(keys_of[name], axis=1)
        first = config.starts[0]
        pose = jnp.take_along_axis(refined[first], best[first][:, None, None], axis=1)[:, 0]
        pooled = config.starts if config.pool_starts else config.starts[:1]
        cands = jnp.concatenate([refined[n] for n in pooled], axis=1)  # [B, C, 7]
        keys = jnp.concatenate([keys_of[n] for n in pooled], axis=1)  # [B, C]
        start = np.concatenate(
            [np.full(refined[n].shape[1], config.starts.index(n), np.int32) for n in pooled]
        )
        # views are laid side by side, K candidates each: position % K is the proposal
        proposal = np.concatenate([np.arange(refined[n].shape[1]) for n in pooled])
        proposal = proposal % config.num_proposals
        if config.pool_starts and len(config.starts) > 1:
            pick = jnp.argmax(keys, axis=1)
            pose = jnp.take_along_axis(cands, pick[:, None, None], axis=1)[:, 0]
        order = jnp.argsort(-keys, axis=1, stable=True)
        ranked = jnp.take_along_axis(cands, order[:, :, None], axis=1)
        return HangOutput(
            stage1_poses, stage2_poses, refined, scores, initial, best, pose,
            ranked, jnp.take_along_axis(keys, order, axis=1), jnp.asarray(start)[order],
            jnp.asarray(proposal)[order],
        )  # fmt: skip

    return hang
