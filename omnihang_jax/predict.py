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


def make_predict(stage1_config, stage2_config: Stage2Config) -> Callable:
    """``predict(stage1_params, stage2_params, object_points [B,N,3], support_points [B,M,3],
    key, num_proposals, support_normals=None [B,M,3]) -> Prediction``. Pure and un-jitted;
    ``num_proposals`` is static. The support normals serve only Stage 2's clearance
    (``Stage2Config.clearance``; without them Stage 2 estimates them)."""
    stage1 = make_stage1(stage1_config)
    stage2 = make_stage2(stage2_config)

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
        pose6 = stage1.propose(stage1_params, object_points, support_points, key, k)  # [B, K, 6]

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

    def __init__(self, stage1_config, stage1_params, stage2_config, stage2_params, seed: int = 0):
        self.stage1_config = stage1_config
        self.stage2_config = stage2_config
        self.stage1_params = stage1_params
        self.stage2_params = stage2_params
        self._key = jax.random.key(seed)
        self._calls = 0
        self._predict = jax.jit(
            make_predict(self.stage1_spec[0], stage2_config), static_argnames="num_proposals"
        )

    @property
    def stage1_spec(self) -> tuple:
        """(config, params) of Stage 1, for ``make_predict`` / ``pipeline.make_hang_pipeline``."""
        return self.stage1_config, self.stage1_params

    @property
    def num_points(self) -> int:
        """Points per cloud the Stage-1 network was designed for."""
        enc = self.stage1_config.encoder
        return max(enc.num_points, enc.sa_levels[0].npoint)

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
    folder: str | os.PathLike,
    seed: int = 0,
    stage2_overrides: dict | None = None,
    stage1_folder: str | os.PathLike | None = None,
) -> Predictor:
    """Rebuild the predictor from a training folder holding ``stage1/`` and ``stage2b/``
    (each with config.json + checkpoints/), as written by ``train.train_where``.
    ``stage2_overrides``: inference-only ``Stage2Config`` fields to replace, e.g.
    ``{"clearance": 0.004}``. ``stage1_folder``: read ``stage1/`` from there instead."""
    folder = os.fspath(folder)
    stages = {}
    for stage in ("stage1", "stage2b"):
        base = os.fspath(stage1_folder) if stage == "stage1" and stage1_folder else folder
        path = os.path.join(base, stage)
        if not os.path.exists(os.path.join(path, "config.json")):
            raise FileNotFoundError(
                f"{path}/config.json not found: train it first "
                f"(python -m experiments.train_where --out {folder} --stage all)"
            )
        stages[stage] = restore_stage(path)
    (config1, params1, _), (config2, params2, _) = stages["stage1"], stages["stage2b"]
    stage2_config = dataclasses.replace(config2.stage2, **(stage2_overrides or {}))
    return Predictor(config1.stage1, params1, stage2_config, params2, seed=seed)


def load_rank_values(folders) -> tuple:
    """``(configs, params)``: the config and params of each value folder that ranks the
    refined candidates (beside the CEM's V or alone); each scores its own subsample of the
    clouds, so configs may differ (e.g. near points, ``ValueConfig.support_near``)."""
    from omnihang_jax import refine

    loaded = [refine.load_value(folder) for folder in folders or ()]
    return tuple(c for c, _ in loaded), [p for _, p in loaded]
