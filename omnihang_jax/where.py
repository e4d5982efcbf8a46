"""Where to hang: one config, one factory, one answer for the command and the evaluation.

:class:`WhereConfig` names the weights and the pipeline; :data:`DEFAULT` is the answer of
record and :data:`PAPER` the paper's pipeline. :func:`load_where` builds both from the same
code::

    where = load_where(DEFAULT)
    out = where.answer(clouds, pair_ids, seed)   # jitted, batched over pairs (device)
    pick, status = where.check(out, b, clouds_of_pair_b, floor_z, wall_y)   # host MuJoCo

``answer`` runs Stages 1-3 in one XLA program (``pipeline.make_hang_pipeline``): K Stage-1
proposals, their Stage-2 refinements, CEM on the value function V from the configured starts on
every view of the clouds, the ranking networks and the answer rule; it returns every pooled
candidate in the rule's order. Each pair runs under its own key, ``fold_in(key(seed), pair_id)``,
so a pair's answer does not depend on the batch it came in. ``check`` is the observed-cloud
check (``sim.observed.first_staying``): the ranked candidates are dropped one at a time on the
partial clouds (as spheres, the dataset's stability protocol) and the answer is the first that
stays; the rule's first candidate when none does or the check is off.

The Stage-1 and Stages 1+2 answers (the ablations) come from the same call:
:func:`stage1_answer` and :func:`stage1_2_answer` pick the least penetrating proposal and release
it a few millimetres up, as chosen on the validation objects (docs/where.md).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any, NamedTuple

import numpy as np

from omnihang_jax import pipeline, poses, selection, sharding, stage3

__all__ = [
    "CANON",
    "CONFIGS",
    "DEFAULT",
    "FRAMES",
    "PAPER",
    "Where",
    "WhereConfig",
    "WhereOutput",
    "load_where",
    "stage1_answer",
    "stage1_2_answer",
]


@dataclasses.dataclass(frozen=True)
class WhereConfig:
    """What the where-to-hang answer is made of. Paths are relative to the checkout."""

    stage12: str = "weights/stage12"  # Stage 1 + Stage 2 networks (predict.load_predictor)
    stage1: str | None = None  # a folder whose stage1/ replaces stage12's Stage 1
    # the object-frame network (a folder holding stagecanon/, ``omnihang_jax.canon``): with
    # ``pipeline.canon`` Stages 1-2 read the object in its hypotheses of the library's frame
    canon: str | None = None
    value: str = "weights/value"  # the value function V that CEM searches on
    # networks whose mean log V ranks CEM's candidates (() : V ranks, the paper's)
    rankers: tuple[str, ...] = (
        "weights/rankers/listwise",
        "weights/rankers/listwise_big",
        "weights/rankers/near",
    )
    pipeline: pipeline.PipelineConfig = pipeline.ANSWER_PIPELINE
    # the observed-cloud check's reach: the first of the best ``check`` candidates that stays
    # on the partial clouds (60 = the default's whole pool, chosen on the validation objects);
    # 0: off, the rule's first candidate is the answer
    check: int = 60

    def __post_init__(self):
        if self.check < 0:
            raise ValueError(f"WhereConfig.check must be >= 0, got {self.check}")
        if self.pipeline.num_proposals < 1:
            raise ValueError("WhereConfig.pipeline.num_proposals must be >= 1")
        if self.pipeline.canon and not self.canon:
            raise ValueError(
                "WhereConfig.pipeline.canon needs WhereConfig.canon (a weights folder)"
            )


DEFAULT = WhereConfig()
# The paper's pipeline: K = 5 proposals, CEM from the Stage-2 proposals on one view, the
# highest final V is the answer, no check.
PAPER = WhereConfig(rankers=(), pipeline=pipeline.PipelineConfig(), check=0)
# The answer for objects in any frame: Stage 1 reads the object cloud about its box centre in 32
# frames, V picks the K best of every frame's proposals and Stage 2 refines them, each in its
# frame (pipeline.PipelineConfig.frames); the rest reads the object posed in the support frame.
# Its Stage 1 is trained for that (weights/stage1_frames: `train_where --augment-object-turn 32`).
FRAMES = dataclasses.replace(
    DEFAULT,
    stage1="weights/stage1_frames",
    pipeline=dataclasses.replace(DEFAULT.pipeline, frames=32),
)
# The answer for objects in any frame with the object-frame network (``omnihang_jax.canon``):
# Stages 1-2 (the default's, trained in the library's frame) read the object in each of the
# network's H hypotheses of the library's frame, V picks the K best proposals as for FRAMES.
CANON = dataclasses.replace(
    DEFAULT,
    canon="weights/canon",
    pipeline=dataclasses.replace(DEFAULT.pipeline, canon=True),
)
CONFIGS = {"default": DEFAULT, "paper": PAPER, "frames": FRAMES, "canon": CANON}


class WhereOutput(NamedTuple):
    """B pairs, K proposals, C pooled candidates (numpy, on the host).

    stage1, stage2: [B, K, 7] the proposals and their Stage-2 refinements; ranked: [B, C, 7]
    the pool in the rule's order; keys: [B, C] the rule's keys (higher is better); start: [B, C]
    "stage1" or "stage2", the proposal each candidate was refined from; proposal: [B, C] which
    of the K draws. Poses are the object frame in the support frame, xyz (m) + wxyz."""

    stage1: np.ndarray
    stage2: np.ndarray
    ranked: np.ndarray
    keys: np.ndarray
    start: np.ndarray
    proposal: np.ndarray


class Where(NamedTuple):
    """A loaded :class:`WhereConfig`: ``answer(clouds, pair_ids, seed) -> WhereOutput`` and
    ``check(output, b, clouds, floor_z, wall_y) -> (index into ranked[b], statuses)``."""

    config: WhereConfig
    answer: Any
    check: Any
    params: Any


def _normalise(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, np.float64).copy()
    poses[..., 3:] /= np.maximum(np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True), 1e-12)
    return poses


def load_where(config: WhereConfig = DEFAULT, stage2_overrides: dict | None = None) -> Where:
    """Load the networks of ``config`` and compile its answer (once per process and config)."""
    return _load(config, None if not stage2_overrides else tuple(sorted(stage2_overrides.items())))


@functools.lru_cache(maxsize=4)
def _load(config: WhereConfig, overrides) -> Where:
    import jax

    from omnihang_jax import predict, refine

    folders = (
        config.stage12,
        *([config.stage1] if config.stage1 else []),
        *([config.canon] if config.canon else []),
        config.value,
        *config.rankers,
    )
    for folder in folders:
        if not os.path.exists(folder):
            raise FileNotFoundError(
                f"{folder} not found: the where-to-hang weights are looked up from the checkout's "
                "root (run from there, or give WhereConfig absolute paths)"
            )
    nets = predict.load_predictor(config.stage12, stage2_overrides=dict(overrides or ()),
                                  stage1_folder=config.stage1)  # fmt: skip
    value_config, value_params = refine.load_value(config.value)
    rank_configs, rank_params = predict.load_rank_values(config.rankers)
    pipe = dataclasses.replace(config.pipeline, rank_values=len(rank_params))
    stage1_config, stage1_params = nets.stage1_spec
    canon_config = None
    params = {"stage1": stage1_params, "stage2": nets.stage2_params, "value": value_params}
    if pipe.canon:
        from omnihang_jax import train

        canon_nets, params["canon"], _ = train.restore_stage(
            os.path.join(config.canon, "stagecanon")
        )
        canon_config = canon_nets.canon
    hang = pipeline.make_hang_pipeline(
        stage1_config, nets.stage2_config, value_config, pipe, rank_configs or None, canon_config
    )
    if rank_params:
        params["rank_values"] = rank_params

    def one(params, key, clouds):  # one pair, its own key: a batch of one inside
        framed = pipe.frames or pipe.canon
        if framed:  # the object read about its own box centre, wherever its origin is
            centre = poses.box_centre(clouds.object_points)
            clouds = clouds._replace(object_points=clouds.object_points - centre)
        out = hang(params, key, jax.tree.map(lambda x: x[None], clouds))
        out = jax.tree.map(lambda x: x[0], (out.stage1_poses, out.stage2_poses, out.ranked,
                                            out.ranked_keys, out.ranked_start,
                                            out.ranked_proposal))  # fmt: skip
        if framed:  # poses of the centred cloud -> of the cloud as given
            out = tuple(poses.move_origin(x, -centre) for x in out[:3]) + out[3:]
        return out

    batched = jax.jit(jax.vmap(one, in_axes=(None, 0, 0)))
    starts = np.array(pipe.starts)
    # data parallel over every visible device: parameters replicated, pairs split (one device:
    # as they are)
    mesh = sharding.data_mesh()
    params = sharding.replicate(params, mesh)

    def answer(clouds: stage3.PairClouds, pair_ids, seed: int = 0) -> WhereOutput:
        """Stages 1-3 on B pairs: ``clouds`` [B, N, 3] each (object frame / support frame),
        ``pair_ids`` [B] ints that, with ``seed``, fix each pair's random draws. With several
        devices the pairs are split over them (padded to a multiple of the device count)."""
        ids = np.asarray(pair_ids, np.int64).reshape(-1)
        n = len(ids)
        if n != np.shape(clouds.object_points)[0]:
            raise ValueError(f"{n} pair ids for {np.shape(clouds.object_points)[0]} pairs")
        size = sharding.padded_size(n, mesh)
        if size != n:  # copies of the first pair, dropped below
            pad = np.zeros(size - n, np.int64)
            ids = np.concatenate([ids, ids[pad]])
            clouds = jax.tree.map(lambda x: np.concatenate([x, np.asarray(x)[pad]]), clouds)
        base = jax.random.key(int(seed))
        keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(jax.numpy.asarray(ids, np.uint32))
        keys, clouds = sharding.shard_batch((keys, clouds), mesh)
        out = batched(params, keys, clouds)
        s1, s2, ranked, keys_, start, proposal = (np.asarray(x)[:n] for x in out)
        return WhereOutput(
            _normalise(s1), _normalise(s2), _normalise(ranked), np.asarray(keys_, np.float64),
            starts[np.asarray(start)], np.asarray(proposal),
        )  # fmt: skip

    def check(output: WhereOutput, b: int, clouds: dict, floor_z: float, wall_y: float | None,
              nthread: int = 1) -> tuple[int, np.ndarray]:  # fmt: skip
        """The observed-cloud check of pair ``b``: (index into ``output.ranked[b]``, [C]
        statuses on the observed clouds, -2 where not tried). ``clouds``: the pair's
        ``object_points``/``object_normals``/``support_points``/``support_normals``."""
        from sim import observed

        ranked = output.ranked[b]
        if config.check == 0:
            return 0, np.full(len(ranked), -2, np.int8)
        return observed.first_staying(
            clouds, ranked, floor_z, wall_y, top=config.check, nthread=nthread
        )

    return Where(config, answer, check, params)


def stage1_answer(object_points, support_points, support_normals, stage1_poses) -> np.ndarray:
    """The Stage-1 answer of one pair: the proposal [K, 7] whose object cloud least enters the
    observed support cloud, released ``stage1.ANSWER_LIFT`` up (+z)."""
    from omnihang_jax.stage1 import ANSWER_LIFT

    return _least_penetrating(object_points, support_points, support_normals, stage1_poses,
                              ANSWER_LIFT)  # fmt: skip


def stage1_2_answer(object_points, support_points, support_normals, stage2_poses) -> np.ndarray:
    """The Stages 1+2 answer of one pair: the least penetrating Stage-2 pose [K, 7], released
    ``stage2.ANSWER_LIFT`` up (+z)."""
    from omnihang_jax.stage2 import ANSWER_LIFT

    return _least_penetrating(object_points, support_points, support_normals, stage2_poses,
                              ANSWER_LIFT)  # fmt: skip


def _least_penetrating(object_points, support_points, support_normals, poses, lift: float):
    from omnihang_jax.heuristics import rank_by_penetration

    obj = np.asarray(object_points, np.float32)[::4]  # every 4th object point: the rule's
    order, _ = rank_by_penetration(
        obj, np.asarray(support_points, np.float32), np.asarray(support_normals, np.float32),
        np.asarray(poses, np.float32),
    )  # fmt: skip
    pose = np.array(poses[int(np.asarray(order)[0])], np.float64)
    pose[2] += lift
    return pose


def rule_inside_counts(object_points, support_points, support_normals, poses) -> np.ndarray:
    """[P] observed object points inside the observed support at each pose, as the default
    answer rule counts them (``selection.CHOSEN``)."""
    rule = selection.CHOSEN
    return np.asarray(selection.inside_counts(object_points, support_points, support_normals,
                                              np.asarray(poses, np.float32), rule.depth,
                                              rule.radius))  # fmt: skip
