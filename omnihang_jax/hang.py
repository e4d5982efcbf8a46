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

1. *where to hang*: :func:`stages_where` runs the committed Stage 1 + 2 networks
   (``weights/where_small_paper``), K proposals refined by Stage 2 = 2K candidates, ranked by
   the Stage-3 value function when ``omnihang_jax.stage3`` provides one, else by the
   observed-cloud clearance (:mod:`omnihang_jax.heuristics`: the share of the object cloud that
   does not sink into the observed support cloud).
2. *check* (meshes only): every candidate is simulated with the evaluation protocol
   (``omnihang_jax.evaluate.protocol_stability``: 1 s from rest, > 3 mm initial penetration
   fails); the answer is the best-ranked candidate that stays hanging. From clouds alone the
   true shapes cannot be simulated: the candidates are dropped on the observed clouds instead
   (:func:`observed_check`, ``sim.observed``) and the answer is the first that stays there,
   marked "unverified".
3. *how to hang* (a collision-free path from a start pose above and in front of the support
   to the answer): the OMPL planner of ``omnihang_jax.planner`` when it is there.
4. *search* (``HangConfig.search``, meshes only): the data engine's sampler finds
   simulated stable poses directly (hang-feature threading when both assets know their hang
   features, else uniform poses around the support), the reference the learned answer is
   compared with.

:func:`write_outputs` writes ``result.json``, ``scene.xml`` (+ meshes), ``hang.png`` and
``viewer.html`` into a temporary folder beside ``out`` and renames it: the output folder is
complete or absent.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import os
import re
import shutil
import tempfile
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

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

DEFAULT_OBJECT = "mug_0016"  # held-out mug (15 % of objects are never trained on)
DEFAULT_SUPPORT = "single_rod_hook_0001"  # held-out wall hook
DEFAULT_MODEL = "weights/where_small_paper"
MESH_FORMATS = (".obj", ".stl", ".glb", ".gltf")  # .ply is a mesh when it has faces
CLOUD_FORMATS = (".npy", ".npz")
MIN_EXTENT = 0.005  # m; as sim.meshio: smaller is surely in the wrong units
MAX_EXTENT = 5.0  # m; as sim.meshio: larger is millimetres or centimetres
# Library sizes (largest extent) the networks were trained on: objects 0.08-0.73 m,
# supports 0.07-0.58 m. Outside these (with a margin) the answer is a guess: warned.
TRAINED_EXTENT = {"object": (0.04, 1.1), "support": (0.035, 0.9)}
FAR_FROM_ORIGIN = 0.05  # m beyond the cloud's own extent: the cloud is not in its frame
WALL_CONTACT_AREA = 5e-4  # m^2 (5 cm^2); library wall supports have >= 15 cm^2 on the wall
WALL_TOLERANCE = 1e-3  # m; faces within this of the wall plane lie on it
# Share of the bounding box's back (x-z) face that lies flat on the wall: library wall
# supports 0.13-1.0 (towel bars lowest), objects 0-0.39 but for a few plate-like "others"
# (up to 0.89). An object that is mounted like a hook (>= 0.6) given with a support that is
# mounted less than any library support (< 0.12) is taken as a swap.
MOUNTED, UNMOUNTED = 0.6, 0.12
MIN_PROTRUSION = 0.01  # m; a support reaching less than 1 cm off its wall/floor holds nothing
SEARCH_ENOUGH = 100  # stable poses after which the search stops (dataset: 2 x max_stable)
SEARCH_KEEP = 50  # stable poses written to result.json (dataset: max_stable)
NORMAL_NEIGHBOURS = 16  # points per PCA normal estimate for clouds given without normals


class HangInputError(ValueError):
    """Bad user input; the message names the file (or argument) and the problem."""


# the subsamples (j, T) of the clouds CEM and the ranking run on, as stage3.ANSWER_PIPELINE.views
# (stage3.subset_clouds): every view refines the same starts with the same seed, each view's
# candidates ranked on its own subsample, the answer the best of all of them (HangConfig.views,
# --views). Three views since the thirty-third session: held-out 82.90 % against 81.88 for the
# two views 0/1,1/2 over three CEM keys, ~1.3x the CEM work (docs/stage3.md "Thirty-second
# session")
VIEWS = ((0, 1), (1, 2), (3, 4))


# The clouds-only answer check's reach (sim.observed.ANSWER_TOP; HangConfig.observed_check).
OBSERVED_CHECK = 60


@dataclasses.dataclass(frozen=True)
class HangConfig:
    """Settings of :func:`hang`; every field has a CLI flag of the same name."""

    model: str = DEFAULT_MODEL  # trained Stage 1 + 2 folder (load_predictor)
    num_proposals: int = 32  # K Stage-1 draws (the paper evaluates 5; 32 cost ~5 s on a CPU)
    seed: int = 0  # camera views, depth noise, Stage-1 noise and the search's sampler
    depth_noise: float = 0.0  # m, std along each ray of the rendered depth (dataset: 0)
    image_width: int = 640  # rendered depth view (the dataset's camera)
    image_height: int = 480
    verify: bool = True  # simulate the candidates when meshes are known
    search: bool = False  # also find stable poses with the data engine's sampler
    search_candidates: int = 4096  # uniform yield is ~0.8 % (results/proposal_yield.json)
    plan: bool = True  # run the how-to-hang planner when it exists
    plan_time: float = 20.0  # s, OMPL's time limit (omnihang_jax.planner.PlannerConfig)
    # s: a second plan after the hybrid's time-out (None: plan_time if HYBRID["replan"]; 0: none)
    replan_time: float | None = None
    # the planner's checker (planner_how): "auto" (the hybrid of HYBRID, else the NCE, then the
    # full meshes when it finds no path), "nce" (the estimator alone) or "mesh"
    checker: str = "auto"
    scale: float | None = None  # multiply both inputs' coordinates (0.001 for millimetres)
    object_scale: float | None = None  # overrides ``scale`` for the object
    support_scale: float | None = None  # overrides ``scale`` for the support
    up: str = "z"  # meshes: "y" rotates a y-up file (glTF, Blender exports) to z-up
    free_standing: bool = False  # a user support stands on the floor instead of a wall
    recenter: bool = False  # clouds: move each cloud's bounding-box centre to the origin
    coacd: str = "default"  # "default" or "fast" (sim.decompose.FAST: previews, tests)
    value: str | None = None  # Stage-3 value weights; None: find_value_weights(model); "off"
    cache_dir: str | None = None  # CoACD cache; None: out/cache/coacd in the working directory
    # m: Stage 2 moves its pose this far along the observed support normal at its chosen
    # contacts (Stage2Config.clearance); None: the model's own
    stage2_clearance: float | None = None
    # the subsamples (j, T) of the clouds Stage 3 runs on (VIEWS)
    views: tuple[tuple[int, int], ...] = VIEWS
    # clouds only: the answer is the first of the best N candidates that stays when dropped on
    # the observed clouds (sim.observed, the fifty-first session's check); 0: the best-ranked
    observed_check: int = OBSERVED_CHECK

    def scale_of(self, kind: str) -> float | None:
        own = self.object_scale if kind == "object" else self.support_scale
        return own if own is not None else self.scale

    def stage2_overrides(self) -> dict | None:
        """``load_predictor``'s ``stage2_overrides`` (None: the model's Stage 2 as trained)."""
        if self.stage2_clearance is None:
            return None
        return {"clearance": float(self.stage2_clearance)}


class Body(NamedTuple):
    """One input, object or support, as the pipeline sees it.

    points, normals: [N, 3] float32 partial cloud (object frame / support frame), N = the
    networks' input size; asset: the ``sim`` Asset when a mesh is known (None for clouds);
    eye: [3] camera position of the rendered view (None for given clouds); source: "builtin",
    "library", "mesh" or "cloud"; report: JSON-able record of what was read and checked.
    """

    kind: str
    name: str
    source: str
    path: str | None
    points: np.ndarray
    normals: np.ndarray
    asset: Any
    eye: np.ndarray | None
    report: dict


class Candidates(NamedTuple):
    """C candidate poses of the where-to-hang step, in ranking order (best first).

    poses: [C, 7] object frame in support frame (xyz m + quaternion wxyz); stage: [C] str
    ("stage1", "stage1_2", "stage1_3", "stage3"); proposal: [C] int, the Stage-1 draw each comes from;
    score: [C] float, higher is better, of kind ``score_name``.
    """

    poses: np.ndarray
    stage: np.ndarray
    proposal: np.ndarray
    score: np.ndarray
    score_name: str


class PathPlan(NamedTuple):
    """A how-to-hang path: poses [T, 7] from the start pose to the hanging pose."""

    poses: np.ndarray
    planner: str
    info: dict


class HangResult(NamedTuple):
    """What :func:`hang` found. ``pose``: [7] the answer (object frame in support frame);
    ``matrix``: [4, 4] the same; ``verdict``: "stable", a failure status of
    ``sim.kernels.STATUS_NAMES`` (no candidate hung), or "unverified" (clouds only; checked on
    the observed clouds, ``steps["observed_check"]``);
    ``settled_pose``: [7] where the object rests after the simulated second (None unverified);
    ``chosen``: index into ``candidates``; ``status``: [C] simulated status per candidate
    (None unverified); ``path``: PathPlan or None; ``search``: dict or None; ``steps``: which
    step ran with what, or why not; ``timings``: seconds per step."""

    object: Body
    support: Body
    candidates: Candidates
    chosen: int
    pose: np.ndarray
    matrix: np.ndarray
    verdict: str
    settled_pose: np.ndarray | None
    status: np.ndarray | None
    penetration: np.ndarray | None
    path: PathPlan | None
    search: dict | None
    steps: dict
    timings: dict
    warnings: list

    @property
    def verified(self) -> bool:
        return self.status is not None

    @property
    def hung(self) -> bool:
        return self.verdict == "stable"


# ----------------------------------------------------------------------------- inputs


def _library_asset(name: str, kind: str):
    """The library asset called ``name`` (``<category>_<index:04d>`` of the default library),
    or None when ``name`` does not look like one."""
    from sim.assets.base import OBJECT_CATEGORIES, SUPPORT_FAMILIES, build_object, build_support
    from sim.library import LibraryConfig, asset_seed

    m = re.fullmatch(r"([a-z_]+)_(\d{4})", name)
    if not m:
        return None
    group, index = m.group(1), int(m.group(2))
    config = LibraryConfig()
    registry = OBJECT_CATEGORIES if kind == "object" else SUPPORT_FAMILIES
    if group not in registry:
        other = SUPPORT_FAMILIES if kind == "object" else OBJECT_CATEGORIES
        if group in other:
            raise HangInputError(
                f"{name}: is a library {'support' if kind == 'object' else 'object'}, given as "
                f"the {kind}: object and support given in the wrong order? (--object is what "
                f"hangs, --support what it hangs on)"
            )
        return None
    counts = config.objects_per_category() if kind == "object" else config.supports_per_family()
    if index >= counts[group]:
        raise HangInputError(
            f"{name}: the library has {counts[group]} {group} assets (indices 0000-"
            f"{counts[group] - 1:04d})"
        )
    build = build_object if kind == "object" else build_support
    return build(group, asset_seed(config.seed, kind, group, index), index)


def _read_cloud(path: Path) -> np.ndarray:
    """[N, 3 or 6] float64 array of a cloud file (points, optionally normals)."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                keys = list(data.files)
                if not keys:
                    raise HangInputError(f"{path}: the .npz holds no arrays")
                key = next((k for k in ("points", "xyz", "cloud") if k in keys), keys[0])
                arr = data[key]
                if arr.ndim == 2 and arr.shape[-1] == 3 and "normals" in keys:
                    arr = np.concatenate([arr, data["normals"]], axis=-1)
        else:  # .ply without faces
            import trimesh

            cloud = trimesh.load(str(path), process=False)
            arr = np.asarray(cloud.vertices, np.float64)
            data = getattr(cloud, "metadata", {}).get("_ply_raw", {}).get("vertex", {}).get("data")
            if isinstance(data, dict):  # trimesh's ASCII reader: one array per property
                columns = data
            elif data is not None and getattr(data, "dtype", None) is not None:  # binary
                columns = {k: data[k] for k in (data.dtype.names or ())}
            else:
                columns = {}
            if all(k in columns for k in ("nx", "ny", "nz")):
                normals = np.stack(
                    [np.asarray(columns[k], float).ravel() for k in ("nx", "ny", "nz")], 1
                )
                arr = np.concatenate([arr, normals], 1)
    except HangInputError:
        raise
    except zipfile.BadZipFile as exc:
        raise HangInputError(
            f"{path}: unreadable .npz (truncated or not a zip file: {exc})"
        ) from exc
    except (ValueError, OSError, EOFError, KeyError) as exc:
        raise HangInputError(
            f"{path}: unreadable as a {suffix[1:]} point cloud ({type(exc).__name__}: {exc})"
        ) from exc
    arr = np.asarray(arr)
    if arr.dtype.kind not in "fiu":
        raise HangInputError(f"{path}: the cloud array has dtype {arr.dtype}, not numbers")
    if arr.ndim != 2 or arr.shape[1] not in (3, 6):
        raise HangInputError(
            f"{path}: a cloud must be [N, 3] points or [N, 6] points + normals, got shape "
            f"{list(arr.shape)}"
        )
    return arr.astype(np.float64)


def _estimate_normals(points: np.ndarray) -> np.ndarray:
    """[N, 3] unit normals by PCA over each point's nearest neighbours, turned away from
    the cloud's centroid (a one-view cloud's visible side mostly faces outwards)."""
    from scipy.spatial import cKDTree

    k = min(NORMAL_NEIGHBOURS, len(points))
    _, idx = cKDTree(points).query(points, k=k)
    nb = points[idx] - points[idx].mean(1, keepdims=True)
    _, _, vt = np.linalg.svd(nb, full_matrices=False)
    normals = vt[:, -1, :]
    flip = np.einsum("ij,ij->i", normals, points - points.mean(0)) < 0
    normals[flip] *= -1
    return normals


def _check_extent(label: str, largest: float, scale: float | None) -> None:
    if largest > MAX_EXTENT:
        if MIN_EXTENT <= largest * 1e-3 <= MAX_EXTENT:
            raise HangInputError(
                f"{label}: absurd size, largest extent {largest:.4g} m (> {MAX_EXTENT} m) looks "
                f"like millimetres; inputs are in metres: pass --scale 0.001 (or for one input "
                f"--object-scale / --support-scale)"
            )
        raise HangInputError(
            f"{label}: absurd size, largest extent {largest:.4g} m (> {MAX_EXTENT} m); "
            f"inputs are in metres, pass --scale <factor>"
        )
    if largest < MIN_EXTENT:
        raise HangInputError(
            f"{label}: absurd size, largest extent {largest:.4g} m (< {MIN_EXTENT * 1000:g} mm); "
            f"inputs are in metres, pass --scale <factor>"
        )


def cloud_body(
    points: np.ndarray,
    kind: str,
    n_points: int,
    min_points: int,
    rng: np.random.Generator,
    *,
    label: str,
    scale: float | None = None,
    recenter: bool = False,
    path: str | None = None,
) -> Body:
    """A :class:`Body` from a cloud array [N, 3] or [N, 6] (checks, units, frame, resampling)."""
    arr = np.asarray(points, np.float64)
    if arr.ndim != 2 or arr.shape[1] not in (3, 6):
        raise HangInputError(
            f"{label}: a cloud must be [N, 3] points or [N, 6] points + normals, got shape "
            f"{list(arr.shape)}"
        )
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        raise HangInputError(
            f"{label}: {int(bad.sum())} of {len(arr)} points are NaN or infinite "
            f"(first at row {int(np.flatnonzero(bad)[0])})"
        )
    if len(arr) < min_points:
        raise HangInputError(
            f"{label}: {len(arr)} points, the networks need at least {min_points} "
            f"(their first layer samples {min_points} centres; clouds are resampled to "
            f"{n_points})"
        )
    if scale is not None:
        if not np.isfinite(scale) or scale <= 0:
            raise HangInputError(f"{label}: scale must be a positive number, got {scale!r}")
        arr = arr.copy()
        arr[:, :3] *= scale
    pts = arr[:, :3]
    lo, hi = pts.min(0), pts.max(0)
    largest = float((hi - lo).max())
    _check_extent(label, largest, scale)
    centre = 0.5 * (lo + hi)
    offset = np.zeros(3)
    if recenter:
        offset = centre
        pts = pts - centre
    elif float(np.linalg.norm(centre)) > largest + FAR_FROM_ORIGIN:
        frame = (
            "the object frame (origin at the object's bounding-box centre)"
            if kind == "object"
            else "the support frame (origin at the support's bounding-box centre, z up, wall at "
            "its lowest y)"
        )
        raise HangInputError(
            f"{label}: the cloud's centre is {np.linalg.norm(centre):.3g} m from the origin "
            f"(its extent is {largest:.3g} m): clouds are expected in {frame}; pass --recenter "
            f"to move it there"
        )
    if arr.shape[1] == 6:
        normals = arr[:, 3:]
        norm = np.linalg.norm(normals, axis=1, keepdims=True)
        if (norm < 1e-9).any():
            raise HangInputError(f"{label}: {int((norm < 1e-9).sum())} normals are zero")
        normals = normals / norm
        normals_from = "file"
    else:
        normals = _estimate_normals(pts)
        normals_from = f"estimated (PCA over {NORMAL_NEIGHBOURS} neighbours)"
    idx = rng.choice(len(pts), n_points, replace=len(pts) < n_points)
    report = dict(
        points_read=len(arr),
        points_used=n_points,
        resampled_with_replacement=bool(len(pts) < n_points),
        normals=normals_from,
        extents=[float(e) for e in hi - lo],
        scale=1.0 if scale is None else float(scale),
        recentered_by=[float(c) for c in offset],
    )
    name = Path(path).stem if path else f"{kind}_cloud"
    return Body(
        kind,
        name,
        "cloud",
        path,
        pts[idx].astype(np.float32),
        normals[idx].astype(np.float32),
        None,
        None,
        report,
    )


def _face_area_on_plane(mesh, axis: int, tol: float = WALL_TOLERANCE) -> float:
    """Area (m^2) of the faces lying on the mesh's lowest plane along ``axis``, facing down
    that axis: what rests on a wall (axis 1) or on the floor (axis 2)."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    lowest = v[:, axis].min()
    on = (v[f][:, :, axis] < lowest + tol).all(1) & (np.asarray(mesh.face_normals)[:, axis] < -0.9)
    return float(np.asarray(mesh.area_faces)[on].sum())


def _mount_ratio(mesh) -> float:
    """Area flat on the wall plane / area of the bounding box's back face (x-z)."""
    e = np.ptp(np.asarray(mesh.vertices), axis=0)
    return _face_area_on_plane(mesh, 1) / max(float(e[0] * e[2]), 1e-12)


def check_support_mesh(mesh, wall: bool, object_mesh=None, path: str = "support") -> dict:
    """Geometric sanity of a user support mesh (centred, metres; frames in the module
    docstring): something of it lies on its wall plane (or floor), and it reaches at least
    MIN_PROTRUSION off it. Returns the measured figures; raises HangInputError naming the
    problem (and a likely swap of object and support)."""
    axis = 1 if wall else 2
    area = _face_area_on_plane(mesh, axis)
    depth = float(np.ptp(np.asarray(mesh.vertices)[:, axis]))
    where = "wall plane (its lowest y)" if wall else "floor (its lowest z)"
    if area < WALL_CONTACT_AREA:
        swap = ""
        if object_mesh is not None and _face_area_on_plane(object_mesh, axis) >= WALL_CONTACT_AREA:
            swap = (
                "; the object has a flat back that would: object and support given in the "
                "wrong order? (--object is what hangs, --support what it hangs on)"
            )
        hint = " or pass --free-standing" if wall else ""
        raise HangInputError(
            f"{path}: nothing of this support rests on the {where}: "
            f"{area * 1e4:.2f} cm^2 < {WALL_CONTACT_AREA * 1e4:g} cm^2{swap}; supports are z up"
            f"{', mounted on a wall at their lowest y and reaching towards +y' if wall else ''}"
            f"{hint}"
        )
    if wall and object_mesh is not None:
        mount = _mount_ratio(mesh)
        if mount < UNMOUNTED and _mount_ratio(object_mesh) >= MOUNTED:
            raise HangInputError(
                f"{path}: object and support given in the wrong order? this support barely sits "
                f"on the wall ({100 * mount:.0f} % of its back is flat, library supports "
                f">= 13 %) while the object has a flat back like a hook's (--object is what "
                f"hangs, --support what it hangs on)"
            )
    if depth < MIN_PROTRUSION:
        raise HangInputError(
            f"{path}: support has no hangable feature: it reaches only {depth * 1000:.1f} mm off "
            f"the {'wall' if wall else 'floor'} (< {MIN_PROTRUSION * 1000:g} mm), nothing can "
            f"hang on it"
        )
    return dict(rest_area_m2=area, protrusion_m=depth)


def _mesh_kind(spec) -> bool:
    """Whether an input spec names a mesh file (as opposed to a cloud, a name or None)."""
    if not isinstance(spec, str | os.PathLike):
        return False
    path = Path(spec)
    suffix = path.suffix.lower()
    if suffix in MESH_FORMATS:
        return path.is_file()
    return suffix == ".ply" and path.is_file() and path.stat().st_size > 0 and _ply_has_faces(path)


def _check_stl(path: Path) -> None:
    """An STL is ASCII ("solid ...") or binary (80-byte header, uint32 N, 50 bytes per
    triangle); anything else is refused before trimesh guesses at it."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(84)
    if head.lstrip().lower().startswith(b"solid"):
        return
    n = int(np.frombuffer(head[80:84], "<u4")[0]) if len(head) == 84 else -1
    if size != 84 + 50 * n:
        raise HangInputError(
            f"{path}: not an STL file (not ASCII 'solid ...', and {size} bytes is not a binary "
            f"STL's 84 + 50 x {n} triangles)"
        )


def read_mesh(spec, kind: str, config: HangConfig):
    """(mesh, report) of a mesh file: read, checked, repaired, centred (sim.meshio)."""
    from sim.meshio import MeshError, load_user_mesh

    if Path(spec).suffix.lower() == ".stl":
        _check_stl(Path(spec))
    try:
        return load_user_mesh(spec, scale=config.scale_of(kind), up=config.up)
    except MeshError as exc:
        raise HangInputError(_cli_hint(str(exc))) from exc


def _cli_hint(message: str) -> str:
    """sim.meshio's hints in the words of this command's flags."""
    for python, flag in (
        ("pass scale=0.001", "pass --scale 0.001"),
        ("scale=<factor>", "--scale <factor>"),
        (" or target_size=<metres>", ""),
    ):
        message = message.replace(python, flag)
    return message


def load_body(
    spec,
    kind: str,
    config: HangConfig,
    n_points: int,
    min_points: int,
    rng: np.random.Generator,
) -> Body | tuple:
    """Resolve one input: None (built-in default), a library name, a mesh or cloud path, or a
    cloud array. Returns a Body for clouds, or ``("asset", asset, report)`` for meshes whose
    clouds are rendered later in the pair's scene."""
    if spec is None:
        name = DEFAULT_OBJECT if kind == "object" else DEFAULT_SUPPORT
        return ("asset", _library_asset(name, kind), dict(source="builtin", name=name))
    if isinstance(spec, np.ndarray):
        return cloud_body(
            spec, kind, n_points, min_points, rng, label=f"{kind} array",
            scale=config.scale_of(kind), recenter=config.recenter,
        )  # fmt: skip
    spec = os.fspath(spec)
    path = Path(spec)
    suffix = path.suffix.lower()
    if not path.exists():
        asset = _library_asset(spec, kind) if not suffix else None
        if asset is not None:
            return ("asset", asset, dict(source="library", name=spec))
        raise HangInputError(
            f"{spec}: file not found"
            + ("" if suffix else " (and not a library asset name such as mug_0016)")
        )
    if path.is_dir():
        raise HangInputError(f"{spec}: is a folder, not a mesh or cloud file")
    if not os.access(path, os.R_OK):
        raise HangInputError(f"{spec}: unreadable (permission denied)")
    if suffix not in MESH_FORMATS + CLOUD_FORMATS + (".ply",):
        raise HangInputError(
            f"{spec}: unsupported format {suffix or '(none)'!r}; meshes: "
            f"{', '.join(MESH_FORMATS + ('.ply',))}; clouds: {', '.join(CLOUD_FORMATS + ('.ply',))}"
        )
    if path.stat().st_size == 0:
        raise HangInputError(f"{spec}: file is empty (0 bytes)")
    if not _mesh_kind(spec):
        return cloud_body(
            _read_cloud(path), kind, n_points, min_points, rng, label=spec,
            scale=config.scale_of(kind), recenter=config.recenter, path=spec,
        )  # fmt: skip
    return ("mesh", spec, read_mesh(spec, kind, config))


def decompose_mesh(spec: str, kind: str, config: HangConfig, report: dict):
    """The Asset of a checked mesh file: CoACD hulls (cached in :func:`cache_dir`)."""
    from sim import decompose
    from sim.meshio import MeshError

    settings = decompose.FAST if config.coacd == "fast" else decompose.CoacdSettings()
    try:
        asset = decompose.asset_from_user_mesh(
            spec,
            "user",
            kind,
            name=f"{kind}_{Path(spec).stem}",
            wall=not config.free_standing,
            scale=config.scale_of(kind),
            up=config.up,
            settings=settings,
            cache_dir=cache_dir(config),
        )
    except MeshError as exc:
        raise HangInputError(_cli_hint(str(exc))) from exc
    report = dict(source="mesh", name=asset.name, **report)
    report["decomposition"] = {
        k: asset.params["decomposition"][k]
        for k in ("n_hulls", "cache_hit", "cache_file", "seconds", "volume_kept")
    }
    return asset, report


def _ply_has_faces(path: Path) -> bool:
    """Whether a PLY header declares faces (a mesh) or only vertices (a cloud)."""
    with open(path, "rb") as f:
        head = f.read(4096)
    if not head.startswith(b"ply"):
        raise HangInputError(f"{path}: not a PLY file (no 'ply' header)")
    m = re.search(rb"element face (\d+)", head)
    return bool(m and int(m.group(1)) > 0)


def cache_dir(config: HangConfig) -> Path:
    """The CoACD cache used for user meshes: ``config.cache_dir`` or ``out/cache/coacd``
    under the working directory (never the home folder unannounced)."""
    return Path(config.cache_dir) if config.cache_dir else Path("out") / "cache" / "coacd"


def _check_training_domain(body_or_asset, kind: str, label: str) -> list[str]:
    extents = (
        np.asarray(body_or_asset.extents)
        if hasattr(body_or_asset, "extents")
        else np.ptp(body_or_asset.points, axis=0)
    )
    lo, hi = TRAINED_EXTENT[kind]
    largest = float(np.max(extents))
    if not lo <= largest <= hi:
        return [
            f"{label}: largest extent {largest:.3g} m is outside the {kind} sizes the networks "
            f"were trained on ({lo}-{hi} m): expect a poor answer (is the scale right?)"
        ]
    return []


def render_body(scene, kind: str, eye, rng, config: HangConfig, n_points: int):
    """The partial cloud of one body of ``scene`` seen from ``eye`` (sim.camera)."""
    from sim import camera

    cam = camera.CameraConfig(
        width=config.image_width,
        height=config.image_height,
        n_points=n_points,
        depth_noise=config.depth_noise,
    )
    return camera.partial_cloud(scene, kind, eye, rng, cam)


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


# where Stage-3 value weights are looked for: the first is the pipeline's CEM V
# (stage3.CEM_VALUE, chosen on validation objects), then the paper-recipe V and the folders
# scripts/device_stage3.sh writes; then any weights/value_* folder
VALUE_WEIGHTS = (
    "weights/value_s16_hardneg",
    "weights/value_small_paper",
    "weights/value_paper",
    "weights/stage3_paper",
)
# CEM refines the CEM_STARTS best-V Stage-1 proposals and as many Stage-2 proposals (as many
# as stage3.ANSWER_PIPELINE refines of each: K = 16 since the fifteenth session; population x
# iterations = 320 value-network states each), and the refined candidates are ranked by the
# answer rule chosen on validation objects (omnihang_jax.selection.CHOSEN); K = 10 since the
# twenty-seventh session, on each of VIEWS
CEM_STARTS = 10


def find_value_weights(model: str | os.PathLike = DEFAULT_MODEL) -> Path | None:
    """The trained Stage-3 value network (``config.json`` + ``params.msgpack``, as
    ``omnihang_jax.refine.save_value`` writes): ``MODEL/stage3``, ``MODEL/value``, then
    VALUE_WEIGHTS (each folder or its ``value/``); None when there is none yet."""
    places = [Path(model) / "stage3", Path(model) / "value"]
    for folder in [*VALUE_WEIGHTS, *map(str, sorted(Path("weights").glob("value_*")))]:
        places += [Path(folder), Path(folder) / "value"]
    for place in places:
        if (place / "params.msgpack").exists() and (place / "config.json").exists():
            return place
    return None


class Stage3(NamedTuple):
    """A loaded value network: ``score(clouds, poses [P, 7]) -> [P]`` log P(hang),
    ``refine(clouds, starts [K, 7], seed) -> (poses [K, 7], scores [K])`` (CEM on V) and
    ``rank(clouds, poses [P, 7]) -> [P]``: the mean log V over V and the ranking networks
    (``stage3.RANK_VALUES``, as the pipeline's ``PipelineConfig.rank_values``; V alone when
    there are none). Each takes ``view=(j, T)``: the networks see that subsample of the clouds
    (``stage3.subset_clouds``; default (0, 1), the pipeline's first view)."""

    folder: str
    score: Callable
    refine: Callable
    rank: Callable = None
    rank_folders: tuple = ()


def load_stage3(folder: str | os.PathLike, rank_folders=None) -> Stage3:
    """Stage 3 from a value-weights folder (``omnihang_jax.refine.load_value``), jitted;
    one per folder and process (so many pairs compile the networks once). ``rank_folders``:
    the value folders that rank beside it (None: those of ``stage3.RANK_VALUES`` that exist,
    when ``folder`` is the committed V they were chosen with)."""
    from omnihang_jax import stage3

    if rank_folders is None:
        committed = os.path.abspath(folder) == os.path.abspath(VALUE_WEIGHTS[0])
        rank_folders = [f for f in stage3.RANK_VALUES if committed and Path(f).exists()]
    return _load_stage3(os.path.abspath(folder), tuple(os.path.abspath(f) for f in rank_folders))


@functools.lru_cache(maxsize=4)
def _load_stage3(folder: str, rank_folders: tuple = ()) -> Stage3:
    import jax

    from omnihang_jax import predict, refine, stage3

    config, params = refine.load_value(folder)
    rank_configs, extra = predict.load_rank_values(rank_folders)
    value = stage3.make_value(config)
    score_jit = jax.jit(value.score)
    jits = {c: jax.jit(stage3.make_value(c).score) for c in set(rank_configs)}  # one per config
    rank_jits = [jits[c] for c in rank_configs]
    refine_jit = jax.jit(stage3.make_refiner(config, stage3.CEMConfig()))

    def clouds_of(obj: Body, sup: Body, of=config, view=(0, 1)):
        full = stage3.PairClouds(obj.points, obj.normals, sup.points, sup.normals)
        return stage3.subset_clouds(full, of, *view)

    def score(obj: Body, sup: Body, poses, view=(0, 1)):
        poses = np.asarray(poses, np.float32)
        return np.asarray(score_jit(params, clouds_of(obj, sup, view=view), poses))

    def rank(obj: Body, sup: Body, poses, view=(0, 1)):
        poses = np.asarray(poses, np.float32)
        logs = [np.asarray(fn(p, clouds_of(obj, sup, c, view), poses))
                for fn, c, p in zip(rank_jits, rank_configs, extra, strict=True)]  # fmt: skip
        if stage3.RANK_WITH_CEM_VALUE or not extra:
            logs.insert(0, score(obj, sup, poses, view))
        return np.mean(logs, axis=0)

    def refine_fn(obj: Body, sup: Body, starts, seed: int, view=(0, 1)):
        small = jax.tree.map(lambda x: x[None], clouds_of(obj, sup, view=view))
        out = refine_jit(params, jax.random.key(seed), small, np.asarray(starts, np.float32)[None])
        return np.asarray(out.poses[0], np.float64), np.asarray(out.scores[0], np.float64)

    return Stage3(os.fspath(folder), score, refine_fn, rank, rank_folders)


def stage3_scorer(config: HangConfig | None = None):
    """(Stage3 or None, description): the value network when trained weights exist
    (``config.value`` or :func:`find_value_weights`), else None and the reason."""
    config = config or HangConfig()
    if config.value == "off":
        return None, "switched off (--value off)"
    folder = Path(config.value) if config.value else find_value_weights(config.model)
    if folder is None:
        return None, (
            "no trained Stage-3 value weights yet (looked in MODEL/stage3, MODEL/value, "
            + ", ".join(VALUE_WEIGHTS)
            + ")"
        )
    try:
        s3 = load_stage3(folder)
        return s3, (
            f"Stage-3 value network {folder} (CEM from the best {CEM_STARTS} Stage-1 and "
            f"{CEM_STARTS} Stage-2 proposals on each of {len(config.views)} views of the clouds "
            f"{', '.join(f'{j}/{t}' for j, t in config.views)}, "
            "the answer by the observed-cloud rule "
            "selection.CHOSEN"
            + (
                f", ranked by the mean log V with {', '.join(map(os.path.relpath, s3.rank_folders))}"
                if s3.rank_folders
                else ""
            )
            + ")"
        )
    except Exception as exc:  # present but unusable weights: say so, rank without them
        return None, f"Stage-3 weights {folder} not loadable ({type(exc).__name__}: {exc})"


def stages_where(
    predictor, num_proposals: int, stage3: Stage3 | None = None, views=VIEWS
) -> WhereFn:
    """The where-to-hang step on the committed networks: K Stage-1 proposals and their
    Stage-2 refinements (2K candidates). With ``stage3``: the CEM_STARTS best-V candidates of
    each stage refined by CEM on the value network (stage "stage1_3" from Stage 1, "stage3"
    from Stage 2; with K = 16 every one, as ``stage3.ANSWER_PIPELINE``) and ranked as that
    pipeline picks its answer: the refined candidates first, by
    ``selection.select_key`` of ``selection.CHOSEN`` (log V, minus 1e4 per object point more
    than 0.5 mm inside the observed support), then the unrefined ones by the same key; without:
    ranked by the observed-cloud clearance. ``views``: the subsamples of the clouds CEM and
    the ranking run on (``HangConfig.views``)."""
    import jax

    views = tuple(tuple(v) for v in views)
    if not views:
        raise ValueError("stages_where: no views")

    def where(obj: Body, sup: Body, seed: int) -> Candidates:
        out = predictor(
            obj.points[None], sup.points[None], key=jax.random.key(seed),
            num_proposals=num_proposals, support_normals=sup.normals[None],
        )  # fmt: skip
        poses = np.concatenate([out.stage1_poses[0], out.stage2_poses[0]]).astype(np.float64)
        poses[:, 3:] /= np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
        k = num_proposals
        stage = np.array(["stage1"] * k + ["stage1_2"] * k)
        proposal = np.concatenate([np.arange(k), np.arange(k)])
        if stage3 is not None:
            from omnihang_jax import selection

            rule = selection.CHOSEN
            log_v = stage3.score(obj, sup, poses).astype(np.float64)
            n = min(CEM_STARTS, k)
            starts = np.concatenate([np.argsort(-log_v[:k], kind="stable")[:n],
                                     k + np.argsort(-log_v[k:], kind="stable")[:n]])  # fmt: skip
            # every view refines the same starts (same seed) on its own subsample of the clouds
            unrefined = poses
            refined, refined_v = zip(*(stage3.refine(obj, sup, poses[starts], seed, view)
                                       for view in views))  # fmt: skip
            refined = np.concatenate(refined)
            refined[:, 3:] /= np.linalg.norm(refined[:, 3:], axis=1, keepdims=True)
            poses = np.concatenate([poses, refined])
            stage = np.concatenate([stage, (["stage1_3"] * n + ["stage3"] * n) * len(views)])
            proposal = np.concatenate([proposal, np.tile(proposal[starts], len(views))])
            inside = selection.inside_counts(
                obj.points, sup.points, sup.normals, poses, rule.depth, rule.radius
            )
            # the final ranking: V's mean log with the ranking networks (V alone without), each
            # view's candidates on its own subsample, the unrefined ones on the first view's
            if stage3.rank_folders:
                log_v = np.concatenate(
                    [stage3.rank(obj, sup, unrefined, views[0])]
                    + [stage3.rank(obj, sup, refined[i * 2 * n:(i + 1) * 2 * n], view)
                       for i, view in enumerate(views)]
                )  # fmt: skip
            else:
                log_v = np.concatenate([log_v, *refined_v])
            key = selection.select_key(log_v.astype(np.float32), inside, rule)
            score = np.asarray(key, np.float64)
            name = "stage3_value_clear"
            order = np.lexsort((-score, np.arange(len(score)) < 2 * k))  # refined first (>= 2K)
            return Candidates(poses[order], stage[order], proposal[order], score[order], name)
        score, name = _clearance_scores(obj, sup, poses), "observed_clearance"
        order = np.argsort(-score, kind="stable")
        return Candidates(poses[order], stage[order], proposal[order], score[order], name)

    return where


# The best NCE first (docs/paths.md: the eighteenth session's contact NCE plans 46.2 / 30.0 /
# 36.4 alone on the 40 held-out pairs, the sixteenth session's 26.5 / 22.5 / 24.3), then the
# folders scripts/device_collision.sh writes (weights/collision_<preset>/).
COLLISION_WEIGHTS = (
    "weights/collision_s18_contact",
    "weights/collision_s16_planner",
    "weights/collision_paper",
    "weights/collision_small",
    "weights/collision_fast",
)


# The planner's best checker on the 80 held-out pairs (docs/paths.md, twenty-second session:
# 71.7 / 53.8 / 61.4 against 36.4 F1 for the contact NCE alone): the observed-cloud test first,
# then the NCE, strict (the selection's threshold) beyond 2 cm of the goal and lenient (0.99)
# within it. Used for the NCE folder it names when its selection file is there.
HYBRID = dict(
    weights="weights/collision_s18_contact",
    selection="results/paths_hybrid_s18_joint95_selection.json",
    near_threshold=0.99,
    goal_ball=0.02,
    # twenty-fourth session: the returned path moved away from the observed support where the
    # hybrid allows (planner.clear_path), the goal's last 4.5 cm kept: over three paired runs
    # 11 colliding paths became free and 4 free ones colliding (docs/paths.md)
    clear_target=0.03,
    clear_keep_ball=0.045,
    # twenty-fifth session: shape completion (omnihang_jax.completion) of both bodies, carved
    # with their cameras; beyond far_ball of the goal a state collides when the completed
    # clouds come within far_clearance (planner.ClearanceFarFromGoal, first in the cascade).
    # None: off (docs/paths.md "Shape completion")
    completion=None,
    far_clearance=0.0015,
    far_ball=0.045,
    # thirty-fourth session: when the hybrid's plan times out, plan once more, as long, with
    # the same checker (a fresh RRT-Connect search). Paired over five runs of the 80 held-out
    # pairs: +2.0 to +4.4 F1, precision level (docs/paths.md "A replan after a time-out")
    replan=True,
    # thirty-sixth session: the path ends with a straight 4.5-cm approach into the hang when the
    # approach network (omnihang_jax.approach, on the observed clouds) is sure enough of one
    # (probability >= threshold, chosen on the validation objects' labels), never towards the
    # wall of a wall-mounted support; a replan after a time-out plans plainly to the goal.
    # None: off (docs/paths.md "The approach rule chosen on validation"). Thirty-seventh
    # session: the network trained on 8,000 pairs, its threshold chosen by the same rule
    # (docs/paths.md "More approach data")
    approach=dict(
        weights="weights/approach_s37_8k",
        threshold=0.8,
        length=0.045,
        open_side=True,
        replan="plain",
    ),
    # forty-first session: before the straight approach, the route network (one or two
    # straight moves from the hang ending >= 1 cm off the support, fortieth session) is asked
    # first: its first route at p >= threshold, best first (at most ``tries``), that the hybrid
    # checker calls free at every state and whose end the observed clouds show >= ``end_gap``
    # clear (approach.checked_route; the rule chosen on the validation objects' goals). The
    # plan goes to the route's end and ends along the route. None: off (docs/paths.md "The
    # route asked of the planner's checker")
    routes=dict(
        weights="weights/approach_routes_s40_8k",
        threshold=0.3,
        end_gap=0.01,
        tries=10,
    ),
)

FAR_TEST_POINTS = 1024  # observed object points (and as many predicted) in the far test


def completed_far_test(obj: Body, sup: Body, pose: np.ndarray, radius: float, folder=None):
    """(checker or None, info) of :data:`HYBRID`'s far clearance on the completed clouds: the
    observed clouds plus the completion networks' points, less what each body's camera would
    have seen (``completion.carve``). None (with the reason in info) without networks or
    without a camera position for a body (given clouds): carving needs the camera."""
    from omnihang_jax import completion, planner

    folder = folder or HYBRID.get("completion")
    if not folder:
        return None, dict(used=False, why="off")
    if not all((Path(folder) / k / "config.json").exists() for k in completion.KINDS):
        return None, dict(used=False, why=f"no completion networks in {folder}")
    if obj.eye is None or sup.eye is None:
        return None, dict(used=False, why="a body came as a cloud: no camera to carve with")
    po, ps = completion.predict_points(folder, obj.points, sup.points, eyes=(obj.eye, sup.eye))
    clouds = completion.clearance_clouds(obj.points, sup.points, po, ps, FAR_TEST_POINTS)
    test = planner.ClearanceFarFromGoal(
        *clouds, pose, HYBRID["far_ball"], HYBRID["far_clearance"], radius
    )
    info = dict(used=True, networks=str(folder), object_points_added=int(len(po)),
                support_points_added=int(len(ps)), far_clearance_m=HYBRID["far_clearance"],
                far_ball_m=HYBRID["far_ball"])  # fmt: skip
    return test, info


def hybrid_settings(nce_folder) -> tuple[Any, str]:
    """(planner.HybridSettings or None, why) for the NCE folder ``<weights>/nce``."""
    from omnihang_jax import planner

    if nce_folder is None or Path(nce_folder).parent.resolve() != Path(HYBRID["weights"]).resolve():
        return None, f"no hybrid settings for {nce_folder} (they are for {HYBRID['weights']})"
    if not Path(HYBRID["selection"]).exists():
        return None, f"{HYBRID['selection']} missing: the NCE alone"
    settings = planner.HybridSettings.from_selection(
        HYBRID["selection"], HYBRID["near_threshold"], HYBRID["goal_ball"]
    )
    return settings, (
        f"the observed-cloud test (depth {settings.geometric.depth * 1e3:g} mm, radius "
        f"{settings.geometric.radius * 1e3:g} mm) OR the NCE at {settings.far_threshold:g} "
        f"({settings.near_threshold:g} within {settings.goal_ball * 100:g} cm of the goal)"
    )


def hybrid_approach() -> tuple[Any, str]:
    """(approach.ApproachPredictor or None, why) of :data:`HYBRID`'s approach network."""
    settings = HYBRID.get("approach")
    if not settings:
        return None, "no approach network (HYBRID['approach'] is off)"
    folder = Path(settings["weights"])
    if not (folder / "config.json").exists():
        return None, f"{folder} missing: no learned approach"
    return _approach(str(folder.resolve()), float(settings["threshold"])), (
        f"a straight {settings['length'] * 100:g}-cm approach into the hang when the approach "
        f"network {settings['weights']} gives it p >= {settings['threshold']:g}"
    )


def hybrid_routes() -> tuple[Any, str]:
    """(approach.ApproachPredictor or None, why) of :data:`HYBRID`'s route network."""
    settings = HYBRID.get("routes")
    if not settings or not HYBRID.get("approach"):
        return None, "no route network (HYBRID['routes'] or ['approach'] is off)"
    folder = Path(settings["weights"])
    if not (folder / "config.json").exists():
        return None, f"{folder} missing: no learned route"
    return _approach(str(folder.resolve()), float(settings["threshold"])), (
        f"a route of one or two straight moves off the support ({folder}, p >= "
        f"{settings['threshold']:g}, checked by the planner's checker, its end "
        f"{settings['end_gap'] * 100:g} cm clear in the observed clouds)"
    )


@functools.lru_cache(maxsize=4)  # the straight approach network and the route network
def _approach(folder: str, threshold: float):
    """The approach network of ``folder`` at ``threshold``, compiled, once per process."""
    from omnihang_jax import approach

    cfg, params, _ = approach.load(folder)
    predictor = approach.ApproachPredictor(dataclasses.replace(cfg, threshold=threshold), params)
    predictor.warm_up()
    return predictor


def find_collision_weights() -> Path | None:
    """The first trained neural collision estimator (``<folder>/nce/config.json``) among
    COLLISION_WEIGHTS, then any ``weights/collision_*``; None when there is none yet.
    (Before the eighteenth session the list held only folders nobody had written, so the
    alphabetical fallback picked the sixth session's CPU NCE, ``collision_fast_cpu``.)"""
    for folder in [*COLLISION_WEIGHTS, *map(str, sorted(Path("weights").glob("collision_*")))]:
        if (Path(folder) / "nce" / "config.json").exists():
            return Path(folder) / "nce"
    return None


class _CloudGeometry(NamedTuple):
    """What ``omnihang_jax.planner``'s start, bounds and metric read from a scene, taken from
    the clouds when there is no scene: the object's extents and the support's box."""

    obj: Any
    support_bounds: np.ndarray


def planner_how(
    time_limit: float = 20.0, path_step: float = 0.01, checker: str = "auto",
    replan_s: float | None = None, free_standing: bool = False,
):  # fmt: skip
    """(how, description) of the OMPL RRT-Connect planner (``omnihang_jax.planner``), or
    (None, reason). The checker is the neural collision estimator on the observed clouds when
    trained weights exist (the paper's "how"), else the full meshes in MuJoCo
    (``planner.MeshChecker``, needs both meshes). With meshes, every returned path is checked
    densely against the meshes (``planner.dense_check``). The path is resampled every
    ``path_step`` (m, in the planner's metric) for drawing and keyframes. ``checker``:
    "auto" (as described, the estimator as the hybrid of :data:`HYBRID` where its settings
    are there: the observed-cloud test OR the NCE, lenient near the goal), "mesh" (the full
    meshes only) or "nce" (the estimator alone, no fallback). When the hybrid's plan times
    out, it plans once more for ``replan_s`` seconds (None: ``time_limit`` when
    ``HYBRID["replan"]``, else no; 0: no). With the hybrid and ``HYBRID["approach"]``, the
    plan goes to a pre-goal 4.5 cm back along the approach network's direction and ends
    straight in (``free_standing``: the support stands on the floor, so no wall side to avoid
    when there is no scene to say so)."""
    if replan_s is None:
        replan_s = time_limit if HYBRID["replan"] else 0.0
    replan = float(replan_s)
    if checker not in ("auto", "mesh", "nce"):
        raise ValueError(f"checker must be 'auto', 'mesh' or 'nce', got {checker!r}")
    try:
        from omnihang_jax import approach, planner
    except Exception as exc:  # ompl missing or the module broken: say so, do not fail
        return None, f"omnihang_jax.planner not importable ({type(exc).__name__}: {exc})"
    weights = None if checker == "mesh" else find_collision_weights()
    if checker == "nce" and weights is None:
        return None, "no trained neural collision estimator (weights/collision_*/nce)"
    hybrid, hybrid_why = (None, "") if checker != "auto" else hybrid_settings(weights)
    approach_net, approach_why = (None, "") if hybrid is None else hybrid_approach()
    routes_net, routes_why = (None, "") if approach_net is None else hybrid_routes()

    def how(scene, obj: Body, sup: Body, pose: np.ndarray) -> PathPlan | None:

        if scene is not None:
            geometry = scene
        else:
            extents = type("Extents", (), {"extents": np.ptp(obj.points, axis=0)})()
            geometry = _CloudGeometry(extents, np.stack([sup.points.min(0), sup.points.max(0)]))
        start = planner.start_pose(geometry, pose)
        bounds = planner.default_bounds(geometry)
        radius = planner.object_radius(geometry)
        config = planner.PlannerConfig(time_limit=time_limit)

        def attempt(checker, name, seconds=None, approach_to=None, route=None):
            limits = config if seconds is None else dataclasses.replace(config, time_limit=seconds)
            with _captured_stderr() as log:  # OMPL's C++ warnings: kept in info, not shown
                if approach_to is None and route is None:
                    res, retreat = planner.plan(checker, start, pose, bounds, radius, limits), None
                else:  # to the pre-goal, then straight in (the network's choice taken as free)
                    res, retreat = planner.plan_with_retreat(
                        checker, start, pose, bounds, radius,
                        dataclasses.replace(limits, retreat_lengths=(HYBRID["approach"]["length"],)),
                        retreat_checker=approach.never_colliding,
                        retreat_directions=approach.DIRECTIONS if approach_to is None else approach_to,
                        retreat=route,
                    )  # fmt: skip
            info = dict(
                checker=name,
                status=res.status,
                planning_s=res.planning_s,
                states_checked=res.states_checked,
                start_xyz_wxyz=[float(x) for x in start],
            )
            if retreat is not None:
                info["approach_direction"] = [float(x) for x in retreat.direction]
            if log.text.strip():
                info["ompl_log"] = log.text.strip().splitlines()[:20]
            return res.path, info

        path, info, tried = None, None, []
        if weights is not None:
            cfg, params, collides = _nce(os.path.abspath(weights))
            # one plan, not hundreds: powers of two (8 sizes to compile up to 128, not the
            # evaluation's 21 multiples of 8), an edge's coarse states still first
            if hybrid is not None:
                nce_checker = planner.hybrid_checker(
                    cfg, params, obj.points, sup.points, sup.normals, hybrid, pose, radius,
                    pow2=True,
                )  # fmt: skip
                name = f"the hybrid checker ({hybrid_why}; NCE {weights})"
                far, far_info = completed_far_test(obj, sup, pose, radius)
                if far is not None:
                    nce_checker = planner.CascadeChecker(far, nce_checker)
                    name += (f"; the completed clouds {HYBRID['far_clearance'] * 1e3:g} mm apart "
                             f"beyond {HYBRID['far_ball'] * 100:g} cm of the goal")  # fmt: skip
            else:
                nce_checker = planner.EstimatorChecker(
                    collides, params, *nce_clouds(cfg, obj.points, sup.points), pow2=True
                )
                name = f"the neural collision estimator {weights}"
            nce_checker.warm_up(128)
            approach_to, approach_info, route = None, None, None
            if routes_net is not None:  # the checked route first (forty-first session)
                t0 = time.perf_counter()
                rs = HYBRID["routes"]
                choice = approach.checked_route(
                    routes_net, obj.points, sup.points, pose, nce_checker, rs["end_gap"],
                    rs["tries"], config.resolution,
                )  # fmt: skip
                checked = dict(
                    network=routes_why, used=choice.route is not None, p=choice.probability,
                    rank=choice.rank, tried=choice.tried, seconds=round(time.perf_counter() - t0, 4),
                )  # fmt: skip
                if choice.route is not None:
                    route = planner.route_retreat(pose, choice.route, routes_net.config.length)
                    checked |= dict(
                        waypoints=len(route.via) + 1, last=[float(x) for x in route.direction],
                        corner=[float(x) for x in route.via[-1][:3] - pose[:3]]
                        if len(route.via) else None,
                    )  # fmt: skip
                approach_info = dict(route=checked, used=choice.route is not None)
            if approach_net is not None and route is None:
                t0 = time.perf_counter()
                directions, probs = approach_net.order(obj.points, sup.points, pose)
                wall = (
                    (scene.support.wall_y is not None) if scene is not None else not free_standing
                )
                keep = approach.usable(directions, probs, approach_net.config.threshold, wall,
                                       HYBRID["approach"]["open_side"])  # fmt: skip
                approach_info = dict(
                    (approach_info or {}), network=approach_why,
                    best=[float(x) for x in directions[0]], best_p=float(probs[0]),
                    used=bool(keep.any()), seconds=round(time.perf_counter() - t0, 4),
                )  # fmt: skip
                if keep.any():
                    approach_to = directions[keep][:1]
                    approach_info["p"] = float(probs[keep][0])
            path, info = attempt(nce_checker, name, approach_to=approach_to, route=route)
            if (
                path is None
                and hybrid is not None
                and replan > 0
                and planner.timed_out(info["status"])
            ):
                first = info  # a time-out (not an invalid start or goal): one fresh search
                plain = HYBRID["approach"] and HYBRID["approach"]["replan"] == "plain"
                again, again_route = (None, None) if plain else (approach_to, route)
                path, info = attempt(nce_checker, name, replan, approach_to=again,
                                     route=again_route)  # fmt: skip
                info = dict(info, replanned_after=first)
            if approach_info is not None:
                info["approach"] = approach_info
            if hybrid is not None:
                info["completion"] = far_info
            if path is not None and hybrid is not None:
                cleared = planner.clear_path(
                    path, nce_checker, obj.points, sup.points, pose, radius, bounds,
                    config.resolution,
                    planner.ClearanceConfig(target=HYBRID["clear_target"],
                                            keep_ball=HYBRID["clear_keep_ball"]),
                    config.goal_radius,
                )  # fmt: skip
                path = cleared.path
                info.update(
                    cleared=dict(
                        gap_before_m=cleared.gap_before, gap_after_m=cleared.gap_after,
                        moves=cleared.moves, waypoints_removed=cleared.removed,
                        seconds=round(cleared.seconds, 2),
                    )
                )  # fmt: skip
            tried.append(info)
        if path is None and scene is not None and checker != "nce":
            # no NCE, or it found no path (an estimator can call the start colliding): the
            # full meshes in MuJoCo, the planner's ground truth
            path, info = attempt(planner.MeshChecker(scene), "the full meshes in MuJoCo")
            tried.append(info)
        if info is None:
            return None
        info = dict(info, attempts=tried) if len(tried) > 1 else info
        name = f"RRT-Connect (OMPL) with {info['checker']}"
        if path is None:
            return PathPlan(np.zeros((0, 7)), name, info)
        info["waypoints"] = len(path)
        if scene is not None:
            free, deepest, n = planner.dense_check(
                planner.MeshChecker(scene, config.penetration_tolerance), path,
                config.dense_resolution, radius,
            )  # fmt: skip
            info.update(
                dense_check_collision_free=free, deepest_penetration_m=deepest, dense_states=n
            )
        return PathPlan(planner.interpolate_path(path, path_step, radius), name, info)

    if weights is None:
        return how, "OMPL RRT-Connect, full-mesh checker (no trained collision estimator yet)"
    if hybrid is not None:
        return how, (
            f"OMPL RRT-Connect, hybrid checker: {hybrid_why}, NCE {weights}"
            + (f"; {approach_why}" if approach_net is not None else "")
            + " (the full meshes when it finds no path and meshes are known)"
        )
    return how, (
        f"OMPL RRT-Connect, neural collision estimator {weights} (the full meshes when it "
        f"finds no path and meshes are known)"
    )


class _Captured:
    text = ""


@contextlib.contextmanager
def _captured_stderr():
    """Capture what C/C++ code writes to file descriptor 2 (OMPL's console log) while the
    block runs; ``.text`` holds it afterwards."""
    import sys

    captured = _Captured()
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield captured
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            captured.text = sink.read().decode(errors="replace")


def nce_clouds(cfg, object_points: np.ndarray, support_points: np.ndarray):
    """The NCE's fixed cloud subsets, as ``train_collision`` trains and ``eval_paths`` plans
    with them (``train_collision.planner_clouds``, seeds 0 / 1): ``cfg.object_input`` object
    points and ``cfg.support_input`` support points: a support-crop NCE
    (``support_crop_from``) is given that many and keeps the nearest ``support_points``
    itself; given only ``support_points`` it would see a sparse uniform subset, not the
    dense crop it was trained on."""
    from omnihang_jax import collision

    return (
        collision.subsample_cloud(object_points, cfg.object_input, 0),
        collision.subsample_cloud(support_points, cfg.support_input, 1),
    )


@functools.lru_cache(maxsize=2)
def _nce(folder: str):
    """(config, params, jitted collides) of an NCE folder, once per process."""
    import jax

    from omnihang_jax import collision

    cfg, params, _ = collision.load_estimator(folder)
    if cfg.input_clouds != "observed":  # the hang command gives the observed clouds
        raise ValueError(
            f"{folder}: an NCE trained on {cfg.input_clouds} clouds; the hang command plans "
            "with one trained on observed clouds (experiments.eval_paths --completion takes it)"
        )
    return cfg, params, jax.jit(collision.nce_collides(cfg))


def default_how():
    """The how-to-hang step: :func:`planner_how` (or None, the reason)."""
    return planner_how()


def available_steps() -> dict:
    """Which steps exist in this checkout: {"stage3": reason, "planner": reason}."""
    _, s3 = stage3_scorer()
    _, how = default_how()
    return {"stage3": s3, "planner": how}


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


def _say(log, msg: str) -> None:
    if log is not None:
        log(msg)


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
    if config.num_proposals < 1:
        raise HangInputError(f"--num-proposals must be >= 1, got {config.num_proposals}")
    if not config.plan_time > 0:
        raise HangInputError(f"--plan-time must be > 0 s, got {config.plan_time}")
    if config.replan_time is not None and not config.replan_time >= 0:
        raise HangInputError(f"--replan-time must be >= 0 s, got {config.replan_time}")
    if config.checker not in ("auto", "nce", "mesh"):
        raise HangInputError(f"--checker must be 'auto', 'nce' or 'mesh', got {config.checker!r}")
    if config.coacd not in ("default", "fast"):
        raise HangInputError(f"--coacd must be 'default' or 'fast', got {config.coacd!r}")
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
        n_points, min_points = network_sizes(config.model)
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
    if predictor is None and where is None:
        from omnihang_jax.predict import load_predictor

        _say(log, f"loading the where-to-hang networks from {config.model}")
        predictor = load_predictor(
            config.model, seed=config.seed, stage2_overrides=config.stage2_overrides()
        )
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
    if where is None:
        scorer, steps["stage3"] = stage3_scorer(config)
        where = stages_where(predictor, config.num_proposals, scorer, config.views)
        steps["where"] = (
            f"Stages 1-2 ({config.model}), {config.num_proposals} proposals + their Stage-2 "
            f"refinements"
            + (
                f", the best {CEM_STARTS} of each refined by CEM on the Stage-3 value on each "
                f"of {len(config.views)} views of the clouds, the refined ones ranked by the "
                "observed-cloud rule selection.CHOSEN"
                if scorer
                else ", ranked by observed-cloud clearance"
            )
        )
        if scorer is None and not steps["stage3"].startswith("switched off"):
            steps["stage3"] = f"not available yet: {steps['stage3']}"
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
        if config.verify and config.observed_check > 0 and len(cands.poses):
            chosen, text, steps["observed_check"] = observed_check(
                obj, sup, sup_asset, cands.poses, config.observed_check, log
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
            how, reason = planner_how(
                config.plan_time,
                checker=config.checker,
                replan_s=config.replan_time,
                free_standing=config.free_standing,
            )
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
    first set-abstraction level's ``npoint`` (the centres it samples). ``"A+B"`` (a Stage-1
    mix, ``predict.load_predictor``): the most over the networks."""
    if "+" in os.fspath(model):
        first, *more = os.fspath(model).split("+")
        sizes = [network_sizes(first)]
        for other in more:
            path = Path(other) / "stage1" / "config.json"
            if not path.exists():
                raise HangInputError(f"{other}: no Stage-1 network there (the mix {model})")
            sizes.append(_stage1_sizes(path))
        return max(n for n, _ in sizes), max(f for _, f in sizes)
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
    first = max(int(c.encoder.sa_levels[0].npoint) for c in predictor.stage1_configs)
    return predictor.num_points, first


def _partner(kind: str, obj_asset, sup_asset):
    """The other body of a render scene when only one mesh is known: a library stand-in that
    is never drawn in the cloud (clouds are cast per body)."""
    if kind == "object":
        return sup_asset if sup_asset is not None else _library_asset(DEFAULT_SUPPORT, "support")
    return obj_asset if obj_asset is not None else _library_asset(DEFAULT_OBJECT, "object")


# ----------------------------------------------------------------------------- outputs


def _check_out(out: Path) -> None:
    """The output folder may be new, empty, or a previous hang output (replaced whole)."""
    if out.exists() and not out.is_dir():
        raise HangInputError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / "result.json").exists():
        raise HangInputError(
            f"{out}: folder exists and is not a previous hang output (no result.json); "
            f"choose a new --out"
        )
    parent = out.resolve().parent
    if parent.exists() and not os.access(parent, os.W_OK):
        raise HangInputError(f"{out}: cannot write into {parent} (permission denied)")


def _input_frame_pose(result: HangResult) -> dict | None:
    """With --recenter: the answer between the clouds as given (before recentring):
    ``T_input = Trans(c_support) T Trans(-c_object)``; None when nothing was recentred."""
    c_obj = np.asarray(result.object.report.get("recentered_by", np.zeros(3)), float)
    c_sup = np.asarray(result.support.report.get("recentered_by", np.zeros(3)), float)
    if not (c_obj.any() or c_sup.any()):
        return None
    m = result.matrix.copy()
    m[:3, 3] = m[:3, 3] - m[:3, :3] @ c_obj + c_sup
    return dict(
        xyz=[float(x) for x in m[:3, 3]],
        quat_wxyz=[float(x) for x in result.pose[3:]],
        matrix=[[float(x) for x in row] for row in m],
        note="the answer between the input clouds before --recenter moved them",
    )


def result_json(result: HangResult, config: HangConfig) -> dict:
    """The JSON record of a result (the layout of result.json; docs/hang.md)."""
    from sim import kernels

    c = result.candidates

    def body(b: Body) -> dict:
        return dict(kind=b.kind, name=b.name, source=b.source, path=b.path, report=b.report)

    candidates = []
    for i in range(len(c.poses)):
        row = dict(
            rank=i,
            stage=str(c.stage[i]),
            proposal=int(c.proposal[i]),
            score=float(c.score[i]),
            pose_xyz_wxyz=[float(x) for x in c.poses[i]],
        )
        if result.status is not None:
            row["status"] = kernels.STATUS_NAMES[int(result.status[i])]
            row["initial_penetration_m"] = float(result.penetration[i])
        candidates.append(row)
    search = None
    if result.search is not None:
        search = {k: v for k, v in result.search.items() if k != "poses"}
        search["poses_xyz_wxyz"] = [
            [float(x) for x in p] for p in result.search["poses"][:SEARCH_KEEP]
        ]
    return dict(
        convention=(
            "pose of the object frame (origin at the object's bounding-box centre) in the "
            "support frame (z up; wall-mounted supports: wall at the lowest y, reaching "
            "towards +y): p_support = R p_object + t; metres; quaternion w, x, y, z"
        ),
        object=body(result.object),
        support=body(result.support),
        verdict=result.verdict,
        verified=result.verified,
        hung=result.hung,
        pose=dict(
            xyz=[float(x) for x in result.pose[:3]],
            quat_wxyz=[float(x) for x in result.pose[3:]],
            matrix=[[float(x) for x in row] for row in result.matrix],
            stage=str(c.stage[result.chosen]),
            proposal=int(c.proposal[result.chosen]),
            rank=int(result.chosen),
            score=float(c.score[result.chosen]),
        ),
        pose_in_input_frames=_input_frame_pose(result),
        settled_pose_xyz_wxyz=(
            None if result.settled_pose is None else [float(x) for x in result.settled_pose]
        ),
        score_name=c.score_name,
        candidates=candidates,
        path=(
            None
            if result.path is None
            else dict(
                planner=result.path.planner,
                info=result.path.info,
                poses_xyz_wxyz=[[float(x) for x in p] for p in result.path.poses],
            )
        ),
        search=search,
        steps=result.steps,
        timings_s={k: round(v, 3) for k, v in result.timings.items()},
        warnings=result.warnings,
        config=dataclasses.asdict(config),
    )


def write_outputs(
    result: HangResult, out, config: HangConfig = HangConfig(), scene=None, log=print
) -> Path:
    """Write result.json, scene.xml (+ meshes; meshes known only), hang.png and viewer.html
    into a temporary folder beside ``out``, then rename it to ``out`` (replacing a previous
    hang output): the folder is complete or absent."""
    from omnihang_jax import hang_views

    out = Path(out)
    _check_out(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp-"))
    tmp.chmod(0o755)  # mkdtemp makes it private; the result is an ordinary folder
    try:
        record = result_json(result, config)
        files = ["result.json", "hang.png", "viewer.html"]
        if scene is not None:
            _say(log, "writing scene.xml")
            hang_views.write_scene_xml(result, scene, tmp)
            files.append("scene.xml")
        else:
            record["scene"] = "not written: MuJoCo needs the meshes of both bodies"
        _say(log, "drawing hang.png")
        hang_views.draw_png(result, scene, tmp / "hang.png")
        _say(log, "writing viewer.html")
        hang_views.write_viewer(result, tmp / "viewer.html")
        record["files"] = files
        (tmp / "result.json").write_text(json.dumps(record, indent=1))
        _replace_folder(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def _replace_folder(tmp: Path, out: Path) -> None:
    """Move the finished folder ``tmp`` to ``out``; an existing ``out`` is replaced whole (a
    reader sees the old folder or the new one, never a mix)."""
    if out.exists():
        old = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.old-"))
        os.replace(out, old / "previous")
        os.replace(tmp, out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, out)


# ----------------------------------------------------------------------------- held-out pairs

HELDOUT_RESULTS = "results/hang_heldout.json"  # the measured rates quoted beside a demo run


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
    """Per support family and per object category: [pairs, hung, top-ranked stable]."""
    import collections

    out: dict[str, dict] = {"per_support_family": {}, "per_object_category": {}}
    for key, field in (("per_support_family", "support"), ("per_object_category", "object")):
        table: dict = collections.defaultdict(lambda: [0, 0, 0])
        for r in rows:
            entry = table[r[field].rsplit("_", 1)[0]]
            entry[0] += 1
            entry[1] += int(r["hung"])
            entry[2] += int(r["top_ranked"] == "stable")
        out[key] = {
            k: dict(pairs=v[0], hung=v[1], top_ranked_stable=v[2]) for k, v in sorted(table.items())
        }
    return out


def expected_heldout(path: str | os.PathLike = HELDOUT_RESULTS) -> dict | None:
    """The measured held-out rates (``results/hang_heldout.json``), or None if absent."""
    try:
        return json.loads(Path(path).read_text())["summary"]
    except (OSError, ValueError, KeyError):
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
    and ``OUT/heldout.json``: per pair the verdict, how many candidates stay hanging and the
    status of the top-ranked one (what a clouds-only run would answer), and the rates.
    The folder is written whole or not at all; ``outputs=False`` writes only heldout.json
    (measurements over many pairs: each pair's page is 5 MB)."""
    from tqdm.auto import tqdm

    from omnihang_jax.predict import load_predictor

    out = Path(out)
    if out.exists() and not (out / "heldout.json").exists() and any(out.iterdir()):
        raise HangInputError(f"{out}: folder exists and is not a previous held-out run")
    network_sizes(config.model)
    pairs = heldout_pairs(n, dataset_dir, config.seed)
    _say(log, f"{len(pairs)} held-out pairs over {len({s.rsplit('_', 1)[0] for _, s in pairs})} "
              f"support families and {len({o.rsplit('_', 1)[0] for o, _ in pairs})} object categories")  # fmt: skip
    predictor = load_predictor(
        config.model, seed=config.seed, stage2_overrides=config.stage2_overrides()
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp-"))
    tmp.chmod(0o755)
    rows = []
    t0 = time.perf_counter()
    try:
        for i, (o, s) in enumerate(tqdm(pairs, desc="held-out pairs", disable=log is None)):
            folder = tmp / f"{i:02d}_{o}__{s}" if outputs else None
            r = hang(o, s, folder, config, predictor=predictor, log=None)
            from sim.kernels import STATUS_NAMES

            rows.append(
                dict(
                    object=o,
                    support=s,
                    verdict=r.verdict,
                    hung=r.hung,
                    stable_candidates=int((r.status == 0).sum()),
                    candidates=len(r.status),
                    top_ranked=STATUS_NAMES[int(r.status[0])],
                    seconds=round(sum(r.timings.values()), 2),
                )
            )
        hung = sum(r["hung"] for r in rows)
        top = sum(r["top_ranked"] == "stable" for r in rows)
        summary = dict(
            pairs=len(rows),
            hung=hung,
            hung_rate=hung / max(1, len(rows)),
            top_ranked_stable=top,
            top_ranked_rate=top / max(1, len(rows)),
            num_proposals=config.num_proposals,
            candidates_per_pair=2 * config.num_proposals,
            seconds=round(time.perf_counter() - t0, 1),
            support_families=sorted({s.rsplit("_", 1)[0] for _, s in pairs}),
            object_categories=sorted({o.rsplit("_", 1)[0] for o, _ in pairs}),
            **heldout_rates(rows),
        )
        record = dict(
            summary=summary,
            expected=expected_heldout(),
            definition=(
                "hung: some simulated candidate of the pair stays hanging (the answer hang "
                "gives with meshes); top_ranked: the best-ranked candidate (observed-cloud "
                "clearance, no simulation: the answer from clouds alone) stays hanging. One "
                "rendered view per body (sim.camera.default_eyes), the evaluation protocol "
                "(omnihang_jax.evaluate.protocol_stability)."
            ),
            dataset=os.fspath(dataset_dir),
            model=config.model,
            pairs=rows,
        )
        (tmp / "heldout.json").write_text(json.dumps(record, indent=1))
        _replace_folder(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return record
