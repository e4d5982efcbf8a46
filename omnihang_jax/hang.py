"""``hang``: a user's object and supporting item in, a hanging pose (checked in MuJoCo) out.

The front door of the project: one call from inputs to an answer, callable from a notebook
(``omnihang_jax.hang.hang``) and from the terminal (``python -m experiments.hang``).

Inputs (each of the object and the support, independently):

* a mesh file (OBJ, STL, PLY with faces, GLB/GLTF), read and checked by
  :func:`sim.meshio.load_user_mesh`, decomposed by CoACD (:mod:`sim.decompose`, cached in
  ``HangConfig.cache_dir``); its partial cloud is rendered the way the dataset renders one:
  one depth view (:func:`sim.camera.default_eyes`: any side of the object, the front side of
  a wall-mounted support), optional depth noise, resampled to the networks' 4,096 points;
* a point cloud file (``.npy`` / ``.npz`` / ``.ply`` without faces): ``[N, 3]`` points or
  ``[N, 6]`` points + normals, used as it is (resampled to 4,096 points);
* the name of a library asset (``mug_0016``, ``single_rod_hook_0001``: ``sim.library``);
* nothing: the built-in default (:data:`DEFAULT_OBJECT` on :data:`DEFAULT_SUPPORT`, a
  held-out mug on a held-out hook: neither was seen in training).

Frames (docs/architecture.md): lengths in metres (``scale`` converts, a millimetre file is
detected from its extent and refused with a hint). The object's cloud or mesh is in the
OBJECT frame, origin at its bounding-box centre (meshes are centred on loading); the
support's in the SUPPORT frame = world: z up; a wall-mounted support has its back on the
wall at its lowest y and reaches towards +y; a free-standing one stands on its lowest z.
The answer is the object frame in the support frame: ``p_support = R p_object + t``, given as
a 4x4 matrix and as xyz + quaternion wxyz (MuJoCo's order).

Steps (each pluggable: ``where`` and ``how`` arguments):

1. *where to hang*: the answer of ``omnihang_jax.where`` named by ``HangConfig.where``
   (:data:`omnihang_jax.where.DEFAULT`: Stages 1-3 on three views of the clouds, the rankers,
   the answer rule), its pooled candidates in the rule's order, then the unrefined proposals;
   ``value="off"``: Stages 1-2 alone, ranked by the observed-cloud clearance.
2. *check* (meshes only): every candidate is simulated with the evaluation protocol
   (``omnihang_jax.evaluate.protocol_stability``: 1 s from rest, > 3 mm initial penetration
   fails); the answer is the best-ranked candidate that stays hanging. From clouds alone the
   true shapes cannot be simulated: the candidates are dropped on the observed clouds instead
   (:func:`observed_check`, ``sim.observed``) and the answer is the first that stays there,
   marked "unverified".
3. *how to hang* (a collision-free path from a start pose above and in front of the support
   to the answer): ``omnihang_jax.paths.make_planner`` (``HangConfig.checker``).
4. *search* (``HangConfig.search``, meshes only): the data engine's sampler finds
   simulated stable poses directly (hang-feature threading when both assets know their hang
   features, else uniform poses around the support), the reference the learned answer is
   compared with.

:func:`write_outputs` writes ``result.json``, ``scene.xml`` (+ meshes), ``hang.png`` and
``viewer.html`` into a temporary folder beside ``out`` and renames it: the output folder is
complete or absent.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from omnihang_jax.hang_inputs import (  # noqa: F401  (re-exported)
    CLOUD_FORMATS,
    DEFAULT_MODEL,
    DEFAULT_OBJECT,
    DEFAULT_SUPPORT,
    FAR_FROM_ORIGIN,
    MAX_EXTENT,
    MESH_FORMATS,
    MIN_EXTENT,
    MIN_PROTRUSION,
    NORMAL_NEIGHBOURS,
    SEARCH_ENOUGH,
    SEARCH_KEEP,
    TRAINED_EXTENT,
    WALL_CONTACT_AREA,
    WALL_TOLERANCE,
    Body,
    Candidates,
    HangConfig,
    HangInputError,
    HangResult,
    PathPlan,
    _check_extent,
    _check_stl,
    _check_training_domain,
    _cli_hint,
    _estimate_normals,
    _face_area_on_plane,
    _library_asset,
    _mesh_kind,
    _mount_ratio,
    _ply_has_faces,
    _read_cloud,
    _say,
    cache_dir,
    check_support_mesh,
    cloud_body,
    decompose_mesh,
    load_body,
    read_mesh,
    render_body,
)
from omnihang_jax.hang_outputs import _check_out, result_json, write_outputs  # noqa: F401

__all__ = [
    "DEFAULT_OBJECT",
    "DEFAULT_SUPPORT",
    "DEFAULT_MODEL",
    "HangInputError",
    "HangConfig",
    "Body",
    "Candidates",
    "PathPlan",
    "HangResult",
    "load_body",
    "stages_where",
    "available_steps",
    "search_stable_poses",
    "hang",
    "write_outputs",
]

# ----------------------------------------------------------------------------- steps


WhereFn = Callable[[Body, Body, int], Candidates]
HowFn = Callable[[Any, Body, Body, np.ndarray], "PathPlan | None"]


def _clearance_scores(obj: Body, sup: Body, poses: np.ndarray) -> np.ndarray:
    """[C] 1 - share of the object cloud inside the observed support cloud at each pose."""
    from omnihang_jax.heuristics import rank_by_penetration

    _, pen = rank_by_penetration(
        obj.points[::4], sup.points, sup.normals, np.asarray(poses, np.float32)
    )
    return 1.0 - np.asarray(pen, np.float64)


def compile_cache(folder: str | None = None) -> Path | None:
    """Keep JAX's compiled programs on disk so that a second run loads the networks' programs
    instead of compiling them again (minutes on a 2-core CPU). ``folder``: None for the default,
    ``$OMNIHANG_CACHE/jax`` else ``$XDG_CACHE_HOME/omnihang/jax`` else ``~/.cache/omnihang/jax``;
    "off" for none. A ``JAX_COMPILATION_CACHE_DIR`` set by the caller wins. Call it before the
    first compile of the process; returns the folder in use (None: off)."""
    import jax

    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return Path(os.environ["JAX_COMPILATION_CACHE_DIR"])
    if folder == "off":
        return None
    if folder is None:
        root = os.environ.get("OMNIHANG_CACHE") or os.path.join(
            os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "omnihang"
        )
        folder = os.path.join(root, "jax")
    path = Path(folder).expanduser()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HangInputError(f"--compile-cache {folder}: cannot create it ({exc})") from exc
    jax.config.update("jax_compilation_cache_dir", os.fspath(path))
    # programs that took at least this long to compile are kept (the networks take tens of s)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    return path


def where_config(config: HangConfig):
    """The ``omnihang_jax.where.WhereConfig`` of ``config``: the named answer (``--where``)
    with the overrides of ``--model``, ``--num-proposals`` and ``--observed-check``."""
    from omnihang_jax import where

    if config.where not in where.CONFIGS:
        raise HangInputError(
            f"--where must be one of {sorted(where.CONFIGS)}, got {config.where!r}"
        )
    wc = where.CONFIGS[config.where]
    if config.model is not None:
        wc = dataclasses.replace(wc, stage12=config.model)
    if config.num_proposals is not None:
        wc = dataclasses.replace(
            wc, pipeline=dataclasses.replace(wc.pipeline, num_proposals=config.num_proposals)
        )
    if config.observed_check is not None:
        wc = dataclasses.replace(wc, check=config.observed_check)
    return wc


def describe_where(wc) -> str:
    """One sentence on a ``WhereConfig``."""
    pipe = wc.pipeline
    views = ", ".join(f"{j}/{t}" for j, t in pipe.views)
    rank = (f"ranked by the mean log V of {', '.join(wc.rankers)}" if wc.rankers
            else "ranked by V")  # fmt: skip
    return (
        f"Stages 1-2 ({wc.stage12}), K = {pipe.num_proposals} proposals and their Stage-2 "
        f"refinements; CEM on {wc.value} from the {' and '.join(pipe.starts)} proposals on "
        f"{len(pipe.views)} view(s) of the clouds ({views}), {rank}, the answer by the "
        f"rule {pipe.select.rule}"
    )


def stages_where(wc) -> WhereFn:
    """The where-to-hang step of ``omnihang_jax.where`` on one pair: its pooled candidates in
    the rule's order (stage "stage1_3" from a Stage-1 proposal, "stage3" from a Stage-2 one),
    then the unrefined proposals ranked by the observed-cloud clearance."""
    from omnihang_jax import stage3, where

    loaded = where.load_where(wc)

    def fn(obj: Body, sup: Body, seed: int) -> Candidates:
        clouds = stage3.PairClouds(obj.points[None], obj.normals[None], sup.points[None],
                                   sup.normals[None])  # fmt: skip
        out = loaded.answer(clouds, [0], seed)
        ranked = out.ranked[0]
        stage = np.where(out.start[0] == "stage1", "stage1_3", "stage3")
        unrefined = _stages12_candidates(obj, sup, out.stage1[0], out.stage2[0])
        return Candidates(
            np.concatenate([ranked, unrefined.poses]), np.concatenate([stage, unrefined.stage]),
            np.concatenate([out.proposal[0], unrefined.proposal]),
            np.concatenate([out.keys[0], unrefined.score - 1e9]), "rule key",
        )  # fmt: skip

    return fn


def _stages12_candidates(obj: Body, sup: Body, stage1, stage2) -> Candidates:
    k = len(stage1)
    poses = np.concatenate([stage1, stage2]).astype(np.float64)
    poses[:, 3:] /= np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
    stage = np.array(["stage1"] * k + ["stage1_2"] * k)
    proposal = np.concatenate([np.arange(k), np.arange(k)])
    score = _clearance_scores(obj, sup, poses)
    order = np.argsort(-score, kind="stable")
    return Candidates(poses[order], stage[order], proposal[order], score[order],
                      "observed_clearance")  # fmt: skip


def stages12_where(predictor, num_proposals: int) -> WhereFn:
    """Stages 1-2 alone (``--value off``): K proposals and their Stage-2 refinements ranked by
    the observed-cloud clearance (the share of the object cloud outside the support cloud)."""
    import jax

    def fn(obj: Body, sup: Body, seed: int) -> Candidates:
        out = predictor(
            obj.points[None], sup.points[None], key=jax.random.key(seed),
            num_proposals=num_proposals, support_normals=sup.normals[None],
        )  # fmt: skip
        return _stages12_candidates(obj, sup, out.stage1_poses[0], out.stage2_poses[0])

    return fn


def _planner(config: HangConfig):
    """(how, description) of the planner of ``config.checker`` (``omnihang_jax.paths``), or
    (None, the reason)."""
    from omnihang_jax import paths

    planner_config = paths.for_hang(config.checker, config.plan_time, config.replan_time)
    why = paths.missing(planner_config)
    if why is not None:
        return None, why
    planner = paths.make_planner(planner_config)
    return functools.partial(planner, free_standing=config.free_standing), planner.description


def available_steps() -> dict:
    """Which steps exist in this checkout: {"stage3": reason, "planner": reason}."""
    from omnihang_jax import paths

    config = paths.for_hang()
    try:
        s3 = describe_where(where_config(HangConfig()))
    except HangInputError as err:
        s3 = str(err)
    return {"stage3": s3, "planner": paths.missing(config) or paths.describe(config)}


def search_stable_poses(obj_asset, sup_asset, n: int, rng, scene=None, progress=None) -> dict:
    """Simulated stable poses found directly (at most ``n`` candidates in batches of 512,
    stopping once SEARCH_ENOUGH are stable) (the data engine's sampler and stability
    protocol, :func:`sim.dataset.draw_candidates` / ``sim.kernels.StabilityConfig``): hang-
    feature threading for 75 % of the candidates when both assets know their features,
    else uniform poses around the support. Returns poses [S, 7] (settled), counts, the
    sampler used and seconds."""
    from sim import kernels
    from sim.dataset import DatasetConfig, draw_candidates
    from sim.scene import build_scene

    t0 = time.perf_counter()
    scene = scene if scene is not None else build_scene(obj_asset, sup_asset)
    config = DatasetConfig()
    featured = bool(obj_asset.features) and bool(sup_asset.features)
    stable, statuses, done = [], np.zeros(4, int), 0
    batch = 512
    while done < n and len(stable) < SEARCH_ENOUGH:
        size = min(batch, n - done)
        cand = draw_candidates(obj_asset, sup_asset, rng, size, config)
        res = kernels.stability(scene, cand, config.stability)
        stable.extend(res.settled_pose[res.stable])
        statuses += np.bincount(res.status, minlength=4)
        done += size
        if progress is not None:
            progress(size)
    poses = np.asarray(stable, np.float64).reshape(-1, 7)
    return dict(
        sampler="hang features (75 %) + uniform" if featured else "uniform (no known features)",
        candidates=done,
        stable=len(poses),
        status_counts={k: int(v) for k, v in zip(kernels.STATUS_NAMES, statuses)},
        poses=poses,
        seconds=time.perf_counter() - t0,
    )


def pose_matrix(pose: np.ndarray) -> np.ndarray:
    """[4, 4] homogeneous matrix of a pose [7] (xyz + quaternion wxyz)."""
    from scipy.spatial.transform import Rotation

    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(np.roll(np.asarray(pose[3:7], float), -1)).as_matrix()
    m[:3, 3] = pose[:3]
    return m


def pose_distance(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (deg) between pose ``a`` [7] and each of ``b`` [S, 7]."""
    qa = np.asarray(a[3:7], float)
    qb = np.asarray(b, float)[:, 3:7]
    dot = np.abs(qb @ qa) / (np.linalg.norm(qb, axis=1) * np.linalg.norm(qa))
    angle = np.degrees(2 * np.arccos(np.clip(dot, -1.0, 1.0)))
    return np.linalg.norm(np.asarray(b)[:, :3] - a[:3], axis=1), angle


# ----------------------------------------------------------------------------- the pipeline


def observed_check(obj: Body, sup: Body, sup_asset, poses: np.ndarray, top: int, log):
    """The clouds-only answer check (``sim.observed.first_staying``): the candidates in
    ranking order dropped on the observed clouds (as spheres, the dataset's stability
    protocol) until one stays, at most ``top``. The floor and wall are the support mesh's when
    it is known, else unknown (no wall, the floor 1 m below the support cloud: a fall is the
    object leaving the support). -> (chosen index, a sentence, a JSON record)."""
    from sim import kernels, observed

    if sup_asset is not None:
        floor_z, wall_y, where = float(sup_asset.floor_z), sup_asset.wall_y, "the support mesh's"
    else:
        (floor_z, wall_y), where = (
            observed.unknown_environment(sup.points),
            "unknown: no wall, no floor",
        )
    clouds = dict(object_points=obj.points, object_normals=obj.normals,
                  support_points=sup.points, support_normals=sup.normals)  # fmt: skip
    _say(log, f"dropping the best {min(top, len(poses))} candidates on the observed clouds")
    chosen, status = observed.first_staying(clouds, poses, floor_z, wall_y, top)
    tried = int((status != -2).sum())
    stays = status[chosen] == kernels.STABLE
    text = (
        f"the observed clouds as spheres (sim.observed): candidate {chosen} is the first of "
        f"the best {tried} to stay on them" if stays else
        f"the observed clouds as spheres (sim.observed): none of the best {tried} stays on "
        "them, the answer is the best-ranked candidate"
    ) + "; unverified on the true shapes"  # fmt: skip
    record = dict(
        top=int(top), chosen=int(chosen), stays=bool(stays), floor_and_wall=where,
        floor_z=floor_z, wall_y=None if wall_y is None else float(wall_y),
        status=[kernels.STATUS_NAMES[int(x)] if x >= 0 else "not simulated" for x in status],
    )  # fmt: skip
    return int(chosen), text, record


def hang(
    object=None,
    support=None,
    out: str | os.PathLike | None = None,
    config: HangConfig = HangConfig(),
    *,
    where: WhereFn | None = None,
    how: HowFn | None = None,
    predictor=None,
    log: Callable[[str], None] | None = print,
) -> HangResult:
    """Where (and how) to hang ``object`` on ``support``; see the module docstring.

    Args:
      object, support: None (the built-in default), a library asset name, a mesh or cloud
        file path, or a cloud array [N, 3] / [N, 6] (metres, object / support frame).
      out: folder for result.json, scene.xml, hang.png, viewer.html (None: nothing written).
      config: :class:`HangConfig`.
      where: replaces the where-to-hang step (``where(object_body, support_body, seed) ->
        Candidates``); default :func:`stages_where` on ``config.model``.
      how: replaces the planner (``how(scene, object_body, support_body, pose) -> PathPlan``).
      predictor: an already loaded ``omnihang_jax.predict.Predictor`` (saves ~3 s per call).
      log: progress messages (None: silent).

    Raises:
      HangInputError: bad input, with a one-line message naming the file and the problem.
    """
    timings: dict[str, float] = {}
    warnings: list[str] = []
    steps: dict[str, str] = {}
    t = time.perf_counter()
    rng = np.random.default_rng([config.seed, 11])
    if config.num_proposals is not None and config.num_proposals < 1:
        raise HangInputError(f"--num-proposals must be >= 1, got {config.num_proposals}")
    if config.observed_check is not None and config.observed_check < 0:
        raise HangInputError(f"--observed-check must be >= 0, got {config.observed_check}")
    if config.value not in (None, "on", "off"):
        raise HangInputError(f"--value must be 'on' or 'off', got {config.value!r}")
    if not config.plan_time > 0:
        raise HangInputError(f"--plan-time must be > 0 s, got {config.plan_time}")
    if config.replan_time is not None and not config.replan_time >= 0:
        raise HangInputError(f"--replan-time must be >= 0 s, got {config.replan_time}")
    if config.checker not in ("auto", "nce", "hce", "mesh"):
        raise HangInputError(
            f"--checker must be 'auto', 'nce', 'hce' or 'mesh', got {config.checker!r}"
        )
    from sim.decompose import PRESETS

    if config.coacd not in PRESETS:
        raise HangInputError(f"--coacd must be one of {sorted(PRESETS)}, got {config.coacd!r}")
    if config.up not in ("z", "y"):
        raise HangInputError(f"--up must be 'z' or 'y', got {config.up!r}")
    for name in ("scale", "object_scale", "support_scale"):
        value = getattr(config, name)
        if value is not None and not (np.isfinite(value) and value > 0):
            raise HangInputError(
                f"--{name.replace('_', '-')} must be a positive number, got {value}"
            )
    if out is not None:
        _check_out(Path(out))
    if predictor is not None:
        n_points, min_points = _predictor_sizes(predictor)
    elif where is None:
        n_points, min_points = network_sizes(config.stage12_folder())
    else:  # a user where-step: the dataset's cloud size, the small encoder's first level
        n_points, min_points = 4096, 128

    # ---- inputs: every check before anything slow (CoACD, the networks)
    t = time.perf_counter()
    _say(log, "reading the inputs")
    loaded = {
        kind: load_body(spec, kind, config, n_points, min_points, rng)
        for kind, spec in (("object", object), ("support", support))
    }
    meshes = {k: v[2][0] for k, v in loaded.items() if not isinstance(v, Body) and v[0] == "mesh"}
    if "support" in meshes:
        check = check_support_mesh(
            meshes["support"], not config.free_standing, meshes.get("object"), str(support)
        )
        loaded["support"][2][1]["checks"] = check
    if meshes:
        _say(log, f"CoACD decompositions are cached in {cache_dir(config)} (--cache to move)")
    for kind in meshes:
        _, spec, (_, report) = loaded[kind]
        _say(log, f"decomposing the {kind} mesh {spec} (CoACD)")
        asset, report = decompose_mesh(spec, kind, config, report)
        loaded[kind] = ("asset", asset, report)
    timings["read_inputs"] = time.perf_counter() - t

    t = time.perf_counter()
    wc = where_config(config)
    if where is None and config.value == "off" and predictor is None:
        from omnihang_jax.predict import load_predictor

        _say(log, f"loading the Stage 1 + 2 networks from {wc.stage12}")
        predictor = load_predictor(wc.stage12, seed=config.seed)
    timings["load_model"] = time.perf_counter() - t
    obj_asset, sup_asset = (
        None if isinstance(loaded[k], Body) else loaded[k][1] for k in ("object", "support")
    )
    scene = None
    t = time.perf_counter()
    bodies: dict[str, Body] = {}
    if obj_asset is not None or sup_asset is not None:
        from sim import camera
        from sim.scene import build_scene

        # A body without a mesh is rendered in a scene only to give the other one its
        # camera; with both meshes known the scene is also the one simulated below.
        if obj_asset is not None and sup_asset is not None:
            scene = build_scene(obj_asset, sup_asset)
        for kind, asset in (("object", obj_asset), ("support", sup_asset)):
            if asset is None:
                continue
            partner = _partner(kind, obj_asset, sup_asset)
            sc = scene or build_scene(*((asset, partner) if kind == "object" else (partner, asset)))
            eyes = camera.default_eyes(sc, rng, camera.CameraConfig())
            eye = eyes[0] if kind == "object" else eyes[1]
            cloud = render_body(sc, kind, eye, rng, config, n_points)
            report = dict(loaded[kind][2])
            report.update(
                rendered=dict(
                    eye=[float(x) for x in eye],
                    pixels_visible=int(cloud.n_visible),
                    image=[config.image_width, config.image_height],
                    depth_noise_m=config.depth_noise,
                )
            )
            label = report.get("path") or asset.name
            warnings += _check_training_domain(asset, kind, label)
            bodies[kind] = Body(
                kind,
                asset.name,
                report["source"],
                report.get("path"),
                cloud.points,
                cloud.normals,
                asset,
                np.asarray(eye),
                report,
            )
    for kind in ("object", "support"):
        if kind not in bodies:
            body = loaded[kind]
            warnings += _check_training_domain(body, kind, body.path or body.name)
            bodies[kind] = body
    obj, sup = bodies["object"], bodies["support"]
    timings["clouds"] = time.perf_counter() - t
    for w in warnings:
        _say(log, f"warning: {w}")

    # ---- where
    t = time.perf_counter()
    if where is None and config.value == "off":
        k = wc.pipeline.num_proposals
        where = stages12_where(predictor, k)
        steps["stage3"] = "switched off (--value off)"
        steps["where"] = (f"Stages 1-2 ({wc.stage12}), {k} proposals + their Stage-2 "
                          "refinements, ranked by observed-cloud clearance")  # fmt: skip
    elif where is None:
        _say(log, f"loading and compiling the where-to-hang answer ({config.where})")
        where = stages_where(wc)
        steps["stage3"] = f"the {config.where!r} answer (omnihang_jax.where)"
        steps["where"] = describe_where(wc)
    else:
        steps["where"] = f"user function {getattr(where, '__name__', repr(where))}"
    _say(log, f"where to hang: {steps['where']}")
    cands = where(obj, sup, config.seed)
    timings["where"] = time.perf_counter() - t

    # ---- check in MuJoCo
    t = time.perf_counter()
    status = settled = penetration = None
    chosen = 0
    verdict = "unverified"
    if scene is not None and config.verify:
        from omnihang_jax.evaluate import protocol_stability
        from sim import kernels

        _say(log, f"checking {len(cands.poses)} candidates in MuJoCo (1 s each, from rest)")
        res = kernels.stability(scene, cands.poses, protocol_stability())
        status, settled, penetration = res.status, res.settled_pose, res.initial_penetration
        stable = np.flatnonzero(res.stable)
        chosen = int(stable[0]) if len(stable) else 0
        verdict = kernels.STATUS_NAMES[int(status[chosen])]
        steps["check"] = (
            f"MuJoCo, evaluation protocol (omnihang_jax.evaluate.protocol_stability): "
            f"{len(stable)} of {len(cands.poses)} candidates stay hanging"
        )
    elif scene is None:
        only = " and ".join(
            k for k, a in (("the object", obj_asset), ("the support", sup_asset)) if a is None
        )
        if config.verify and wc.check > 0 and len(cands.poses):
            chosen, text, steps["observed_check"] = observed_check(
                obj, sup, sup_asset, cands.poses, wc.check, log
            )
            steps["check"] = (
                f"not possible in MuJoCo on meshes: only clouds were given for {only}; {text}"
            )
        else:
            steps["check"] = (
                f"not possible: only clouds were given for {only}; the answer is the "
                "best-ranked candidate, unverified"
            )
    else:
        steps["check"] = "skipped (verify=False)"
    timings["check"] = time.perf_counter() - t
    pose = cands.poses[chosen]

    # ---- how
    t = time.perf_counter()
    path = None
    if config.plan:
        if how is None:
            how, reason = _planner(config)
        else:
            reason = f"user function {getattr(how, '__name__', repr(how))}"
        if how is None:
            steps["how"] = f"not available yet: {reason}"
        elif verdict not in ("stable", "unverified"):
            steps["how"] = "not run: no candidate hangs"
        else:
            _say(log, f"how to hang: {reason}")
            try:
                path = how(scene, obj, sup, pose)
            except Exception as exc:  # a planner failure must not lose the where answer
                path = PathPlan(
                    np.zeros((0, 7)), reason, {"status": f"{type(exc).__name__}: {exc}"}
                )
                warnings.append(f"how to hang failed: {type(exc).__name__}: {exc}")
            if path is None:
                steps["how"] = f"not possible: {reason} needs the meshes of both bodies"
            elif len(path.poses) == 0:
                steps["how"] = f"{reason}: no path found ({path.info.get('status')})"
                path = None
            else:
                steps["how"] = f"{path.planner}: {len(path.poses)} poses"
    else:
        steps["how"] = "skipped (plan=False)"
    timings["how"] = time.perf_counter() - t

    # ---- search
    search = None
    t = time.perf_counter()
    if config.search:
        if scene is None:
            steps["search"] = "not possible: needs the meshes of both object and support"
        else:
            from tqdm.auto import tqdm

            bar = tqdm(
                total=config.search_candidates, desc="search", unit="pose", disable=log is None
            )
            search = search_stable_poses(
                obj_asset, sup_asset, config.search_candidates,
                np.random.default_rng([config.seed, 13]), scene, bar.update,
            )  # fmt: skip
            bar.close()
            if len(search["poses"]):
                # nearest in the planner's metric: translation + half-extent x angle, roughly
                # the largest displacement of an object point (omnihang_jax.planner)
                dt, dr = pose_distance(pose, search["poses"])
                half = 0.5 * float(np.max(obj_asset.extents))
                j = int(np.argmin(dt + half * np.radians(dr)))
                search["nearest_to_answer"] = dict(
                    index=j, translation_m=float(dt[j]), rotation_deg=float(dr[j]),
                    metric="translation + half-extent x angle", pose_xyz_wxyz=[
                        float(x) for x in search["poses"][j]
                    ], answer_xyz_wxyz=[float(x) for x in pose],
                )  # fmt: skip
            steps["search"] = f"{search['sampler']}: {search['stable']} of {search['candidates']}"
    else:
        steps["search"] = "not requested (--search)"
    timings["search"] = time.perf_counter() - t

    result = HangResult(
        obj,
        sup,
        cands,
        chosen,
        pose,
        pose_matrix(pose),
        verdict,
        None if settled is None else settled[chosen],
        status,
        penetration,
        path,
        search,
        steps,
        timings,
        warnings,
    )
    if out is not None:
        t = time.perf_counter()
        write_outputs(result, out, config, scene, log=log)
        timings["write"] = time.perf_counter() - t
    return result


def network_sizes(model: str | os.PathLike) -> tuple[int, int]:
    """(points per cloud, fewest points allowed) of a trained model folder, read from its
    Stage-1 config.json without loading the networks: the encoder's ``num_points`` and its
    first set-abstraction level's ``npoint`` (the centres it samples)."""
    path = Path(model) / "stage1" / "config.json"
    if not path.exists() or not (Path(model) / "stage2b" / "config.json").exists():
        raise HangInputError(
            f"{model}: no trained model there (expected stage1/ and stage2b/ with config.json, "
            f"e.g. {DEFAULT_MODEL})"
        )
    return _stage1_sizes(path)


def _stage1_sizes(path: Path) -> tuple[int, int]:
    try:
        encoder = json.loads(path.read_text())["config"]["stage1"]["encoder"]
        first = int(encoder["sa_levels"][0]["npoint"])
        return int(max(encoder["num_points"], first)), first
    except (ValueError, KeyError, IndexError, TypeError) as exc:
        raise HangInputError(f"{path}: not a Stage-1 config ({type(exc).__name__}: {exc})") from exc


def _predictor_sizes(predictor) -> tuple[int, int]:
    first = int(predictor.stage1_config.encoder.sa_levels[0].npoint)
    return predictor.num_points, first


def _partner(kind: str, obj_asset, sup_asset):
    """The other body of a render scene when only one mesh is known: a library stand-in that
    is never drawn in the cloud (clouds are cast per body)."""
    if kind == "object":
        return sup_asset if sup_asset is not None else _library_asset(DEFAULT_SUPPORT, "support")
    return obj_asset if obj_asset is not None else _library_asset(DEFAULT_OBJECT, "object")
