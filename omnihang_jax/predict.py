"""Batched "where to hang" inference: Stage 1 proposals refined by Stage 2.

``make_predict(stage1_config, stage2_config)`` returns a pure function (jit it, with
``num_proposals`` static); ``load_predictor(folder)`` rebuilds both stages from a training
folder (``out/stage1`` and ``out/stage2b``) and returns a ``Predictor`` that validates its inputs
on the host (NaN clouds raise ValueError here, not inside jit) and calls the jitted function.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from omnihang_jax.data import check_point_clouds
from omnihang_jax.poses import pose6_to_pose7
from omnihang_jax.stage1 import make_stage1
from omnihang_jax.stage2 import Stage2Config, make_stage2
from omnihang_jax.train import restore_stage

__all__ = ["Prediction", "make_predict", "Predictor", "load_predictor"]


class Prediction(NamedTuple):
    """Output for B pairs and K proposals each (K3 = Stage2Config.k_pairs).

    stage1_poses: [B, K, 7] rough poses (xyz metres + quaternion wxyz, object in support frame).
    stage2_poses: [B, K, 7] Stage-2 poses (Stage-1 rotation, translation from contacts).
    object_indices, support_indices: [B, K, K3] int32 chosen contact points (cloud indices).
    probability: [B, K, K3] float32 pair probabilities; weight: [B, K, K3] 1 = used for t.
    """

    stage1_poses: Any
    stage2_poses: Any
    object_indices: Any
    support_indices: Any
    probability: Any
    weight: Any


def mix_counts(num_proposals: int, networks: int) -> tuple[int, ...]:
    """Proposals of each Stage-1 network of a mix: K split evenly, the first networks take
    the remainder (16 over 2 -> (8, 8); 5 over 2 -> (3, 2))."""
    if networks < 1 or num_proposals < networks:
        raise ValueError(f"{num_proposals} proposals cannot be split over {networks} networks")
    base, extra = divmod(num_proposals, networks)
    return tuple(base + (i < extra) for i in range(networks))


def make_predict(stage1_config, stage2_config: Stage2Config) -> Callable:
    """``predict(stage1_params, stage2_params, object_points [B,N,3], support_points [B,M,3],
    key, num_proposals, support_normals=None [B,M,3]) -> Prediction``. Pure and un-jitted;
    ``num_proposals`` is static. The support normals serve only Stage 2's clearance
    (``Stage2Config.clearance``; without them Stage 2 estimates them).

    A Stage-1 mix (seventeenth session, issue 12): ``stage1_config`` a tuple of Stage1Configs
    and ``stage1_params`` the tuple of their params; the K proposals are split over the
    networks (:func:`mix_counts`), network 0's first (its noise drawn with ``key`` itself, as
    a single network's; network i's with ``fold_in(key, i)``), and Stage 2 refines them all."""
    mixed = isinstance(stage1_config, (tuple, list))
    networks = [make_stage1(c) for c in (stage1_config if mixed else (stage1_config,))]
    stage2 = make_stage2(stage2_config)

    def propose(stage1_params, object_points, support_points, key, k):
        params = tuple(stage1_params) if mixed else (stage1_params,)
        if len(params) != len(networks):
            raise ValueError(f"{len(networks)} Stage-1 configs, {len(params)} params")
        parts = [
            net.propose(p, object_points, support_points, key if i == 0 else jax.random.fold_in(key, i), n)
            for i, (net, p, n) in enumerate(zip(networks, params, mix_counts(k, len(networks))))
        ]  # fmt: skip
        return parts[0] if len(parts) == 1 else jnp.concatenate(parts, axis=1)

    def predict(
        stage1_params,
        stage2_params,
        object_points,
        support_points,
        key,
        num_proposals,
        support_normals=None,
    ):
        batch, n, _ = object_points.shape
        m = support_points.shape[1]
        k = num_proposals
        pose6 = propose(stage1_params, object_points, support_points, key, k)  # [B, K, 6]

        def tile(x, size):  # [B, size, 3] -> [B*K, size, 3]
            return jnp.broadcast_to(x[:, None], (batch, k, size, 3)).reshape(batch * k, size, 3)

        def unflat(x):  # [B*K, ...] -> [B, K, ...]
            return x.reshape((batch, k) + x.shape[1:])

        out = stage2.refine(
            stage2_params,
            tile(object_points, n),
            tile(support_points, m),
            pose6.reshape(-1, 6),
            None if support_normals is None else tile(support_normals, m),
        )
        return Prediction(
            stage1_poses=pose6_to_pose7(pose6),
            stage2_poses=pose6_to_pose7(unflat(out.pose6)),
            object_indices=unflat(out.object_indices),
            support_indices=unflat(out.support_indices),
            probability=unflat(out.probability),
            weight=unflat(out.weight),
        )

    return predict


class Predictor:
    """Host-side wrapper: validated inputs, one jitted call, numpy outputs.

    predictor(object_points [B,N,3], support_points [B,M,3], key=None, num_proposals=None,
    support_normals=None [B,M,3]) -> Prediction of numpy arrays. Unbatched [N,3] / [M,3]
    clouds are accepted too (B = 1). ``support_normals`` only matter for a Stage-2 clearance.
    """

    def __init__(self, stage1_config, stage1_params, stage2_config, stage2_params, seed: int = 0,
                 mix: tuple = ()):  # fmt: skip
        self.stage1_config = stage1_config  # network 0's (of a mix: the first)
        self.stage2_config = stage2_config
        self.stage1_params = stage1_params
        self.stage2_params = stage2_params
        # more Stage-1 networks ((config, params), ...) whose proposals join network 0's
        self.stage1_mix = tuple(mix)
        self._key = jax.random.key(seed)
        self._calls = 0
        self._predict = jax.jit(
            make_predict(self.stage1_spec[0], stage2_config), static_argnames="num_proposals"
        )

    @property
    def stage1_configs(self) -> tuple:
        """Every Stage-1 network's config, network 0's first."""
        return (self.stage1_config,) + tuple(c for c, _ in self.stage1_mix)

    @property
    def stage1_spec(self) -> tuple:
        """(config, params) for ``make_predict`` / ``stage3.make_hang_pipeline``: network 0's,
        or with a mix the tuples of all networks' configs and params."""
        if not self.stage1_mix:
            return self.stage1_config, self.stage1_params
        return self.stage1_configs, (self.stage1_params,) + tuple(p for _, p in self.stage1_mix)

    @property
    def num_points(self) -> int:
        """Points per cloud the Stage-1 networks were designed for (of a mix: the most)."""
        return max(
            max(c.encoder.num_points, c.encoder.sa_levels[0].npoint) for c in self.stage1_configs
        )

    def __call__(
        self,
        object_points,
        support_points,
        key=None,
        num_proposals: int | None = None,
        support_normals=None,
    ):
        object_points = np.asarray(object_points, np.float32)
        support_points = np.asarray(support_points, np.float32)
        if support_normals is not None:
            support_normals = np.asarray(support_normals, np.float32)
            if support_normals.ndim == 2:
                support_normals = support_normals[None]
        if object_points.ndim == 2 and support_points.ndim == 2:
            object_points, support_points = object_points[None], support_points[None]
        check_point_clouds(object_points, support_points)
        if support_normals is not None and (
            support_normals.shape != support_points.shape
            or not np.all(np.isfinite(support_normals))
        ):
            raise ValueError(
                f"support_normals must be finite and shaped like the support cloud "
                f"{support_points.shape}, got {support_normals.shape}"
            )
        if object_points.shape[0] != support_points.shape[0]:
            raise ValueError(
                f"batch sizes differ: {object_points.shape[0]} objects, "
                f"{support_points.shape[0]} supports"
            )
        if key is None:
            key = jax.random.fold_in(self._key, self._calls)
            self._calls += 1
        k = num_proposals or self.stage1_config.num_eval_samples
        out = self._predict(
            self.stage1_spec[1], self.stage2_params, object_points, support_points, key,
            num_proposals=k, support_normals=support_normals,
        )  # fmt: skip
        return Prediction(*(np.asarray(x) for x in out))


def load_predictor(
    folder: str | os.PathLike, seed: int = 0, stage2_overrides: dict | None = None
) -> Predictor:
    """Rebuild the predictor from a training folder holding ``stage1/`` and ``stage2b/``
    (each with config.json + checkpoints/), as written by ``train.train_where``.
    ``stage2_overrides``: inference-only ``Stage2Config`` fields to replace, e.g.
    ``{"clearance": 0.004}``. ``"A+B"``: a Stage-1 mix (:func:`make_predict`): Stage 2 and
    the first Stage 1 from folder A, more Stage-1 networks from B (``B/stage1``), ..."""
    folder = os.fspath(folder)
    if "+" in folder:
        first, *more = folder.split("+")
        base = load_predictor(first, seed=seed, stage2_overrides=stage2_overrides)
        mix = []
        for other in more:
            path = os.path.join(other, "stage1")
            if not os.path.exists(os.path.join(path, "config.json")):
                raise FileNotFoundError(
                    f"{path}/config.json not found (the Stage-1 mix {folder!r})"
                )
            config, params, _ = restore_stage(path)
            mix.append((config.stage1, params))
        return Predictor(base.stage1_config, base.stage1_params, base.stage2_config,
                         base.stage2_params, seed=seed, mix=tuple(mix))  # fmt: skip
    stages = {}
    for stage in ("stage1", "stage2b"):
        path = os.path.join(folder, stage)
        if not os.path.exists(os.path.join(path, "config.json")):
            raise FileNotFoundError(
                f"{path}/config.json not found: train it first "
                f"(python -m experiments.train_where --out {folder} --stage all)"
            )
        stages[stage] = restore_stage(path)
    (config1, params1, _), (config2, params2, _) = stages["stage1"], stages["stage2b"]
    stage2_config = dataclasses.replace(config2.stage2, **(stage2_overrides or {}))
    return Predictor(config1.stage1, params1, stage2_config, params2, seed=seed)


def load_hang_pipeline(where_folder: str | os.PathLike, value_folder: str | os.PathLike,
                       config=None, stage2_overrides: dict | None = None,
                       rank_value_folders=None):  # fmt: skip
    """(hang, params): the jitted Stages 1-3 pipeline (``stage3.make_hang_pipeline``) and its
    parameters, from the Stage 1/2 weights and a value folder (``refine.save_value``).
    ``stage2_overrides``: as in :func:`load_predictor`, e.g. ``{"clearance": 0.008}`` (the
    pipeline takes the support normals from its clouds). ``config``: a
    ``stage3.PipelineConfig``, default ``stage3.ANSWER_PIPELINE`` (both starts refined, the
    answer by the observed-cloud rule chosen on validation objects; ``PipelineConfig()`` is
    the paper's). ``rank_value_folders``: more value folders whose mean log V with the first
    ranks CEM's candidates (``PipelineConfig.rank_values``; None: ``stage3.RANK_VALUES``
    when the config picks by the chosen rule ``selection.CHOSEN`` as the default does, none
    for the paper's highest V; () for none).

    ``hang(params, key, clouds: stage3.PairClouds [B, ...]) -> stage3.HangOutput``."""
    from omnihang_jax import refine, selection, stage3

    where = load_predictor(where_folder, stage2_overrides=stage2_overrides)
    value_config, value_params = refine.load_value(value_folder)
    config = config or stage3.ANSWER_PIPELINE
    if rank_value_folders is None:
        rank_value_folders = stage3.RANK_VALUES if config.select == selection.CHOSEN else ()
    rank_configs, extra = load_rank_values(rank_value_folders)
    config = dataclasses.replace(config, rank_values=len(extra))
    stage1_config, stage1_params = where.stage1_spec
    hang = jax.jit(
        stage3.make_hang_pipeline(
            stage1_config, where.stage2_config, value_config, config, rank_configs
        )
    )
    params = {"stage1": stage1_params, "stage2": where.stage2_params, "value": value_params}
    if extra:
        params["rank_values"] = extra
    return hang, params


def load_rank_values(folders) -> tuple:
    """``(configs, params)``: the config and params of each value folder that ranks the
    refined candidates (beside the CEM's V or alone); each scores its own subsample of the
    clouds, so configs may differ (e.g. near points, ``ValueConfig.support_near``)."""
    from omnihang_jax import refine

    loaded = [refine.load_value(folder) for folder in folders or ()]
    return tuple(c for c, _ in loaded), [p for _, p in loaded]
