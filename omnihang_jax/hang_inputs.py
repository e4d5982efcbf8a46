"""The ``hang`` command's inputs: its settings, its types and how a user's object and support
are read and checked (meshes, clouds, library names; units, frames and a swapped pair caught with
a one-line error naming the file). :mod:`omnihang_jax.hang` re-exports every name here."""

from __future__ import annotations

import dataclasses
import os
import re
import zipfile
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

DEFAULT_OBJECT = "mug_0016"  # held-out mug (15 % of objects are never trained on)
DEFAULT_SUPPORT = "single_rod_hook_0001"  # held-out wall hook
DEFAULT_MODEL = "weights/stage12"
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


@dataclasses.dataclass(frozen=True)
class HangConfig:
    """Settings of :func:`hang`; every field has a CLI flag of the same name."""

    where: str = "default"  # the where-to-hang answer: omnihang_jax.where.CONFIGS
    model: str | None = None  # Stage 1 + 2 folder instead of the answer's (load_predictor)
    num_proposals: int | None = None  # K Stage-1 draws instead of the answer's
    seed: int = 0  # camera views, depth noise, Stage-1 noise and the search's sampler
    depth_noise: float = 0.0  # m, std along each ray of the rendered depth (dataset: 0)
    image_width: int = 640  # rendered depth view (the dataset's camera)
    image_height: int = 480
    verify: bool = True  # simulate the candidates when meshes are known
    search: bool = False  # also find stable poses with the data engine's sampler
    search_candidates: int = 4096  # uniform yield is ~0.8 % (results/proposal_yield.json)
    plan: bool = True  # run the how-to-hang planner when it exists
    plan_time: float = 20.0  # s, OMPL's time limit (omnihang_jax.planner.PlannerConfig)
    # s: a second plan after a time-out (None: plan_time where the config replans; 0: none)
    replan_time: float | None = None
    # the planner (omnihang_jax.paths.for_hang): "auto" (paths.DEFAULT, then the full meshes
    # when it finds no path), "nce" (paths.PAPER_NCE), "hce" (paths.PAPER_HCE) or "mesh"
    checker: str = "auto"
    scale: float | None = None  # multiply both inputs' coordinates (0.001 for millimetres)
    object_scale: float | None = None  # overrides ``scale`` for the object
    support_scale: float | None = None  # overrides ``scale`` for the support
    up: str = "z"  # meshes: "y" rotates a y-up file (glTF, Blender exports) to z-up
    free_standing: bool = False  # a user support stands on the floor instead of a wall
    recenter: bool = False  # clouds: move each cloud's bounding-box centre to the origin
    # CoACD settings of user meshes (sim.decompose.PRESETS): "user" (no manifold remeshing,
    # seconds), "library" (the asset library's, remeshing non-manifold files: minutes), "fast"
    coacd: str = "user"
    value: str | None = None  # "off": Stages 1-2 only, ranked by the observed-cloud clearance
    cache_dir: str | None = None  # CoACD cache; None: out/cache/coacd in the working directory
    # clouds only: the answer is the first of the best N candidates that stays when dropped on
    # the observed clouds (sim.observed); None: the answer's reach (WhereConfig.check); 0: off
    observed_check: int | None = None

    def scale_of(self, kind: str) -> float | None:
        own = self.object_scale if kind == "object" else self.support_scale
        return own if own is not None else self.scale

    def stage12_folder(self) -> str:
        """The Stage 1 + 2 networks' folder: ``model``, else the answer's."""
        if self.model is not None:
            return self.model
        from omnihang_jax import where

        return where.CONFIGS.get(self.where, where.DEFAULT).stage12


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


def _estimate_normals(points: np.ndarray, eye: np.ndarray | None = None) -> np.ndarray:
    """[N, 3] unit normals by PCA over each point's nearest neighbours, turned towards the
    camera at ``eye`` when it is known (a depth camera's normals face it), else away from the
    cloud's centroid (a one-view cloud's visible side mostly faces outwards)."""
    from scipy.spatial import cKDTree

    k = min(NORMAL_NEIGHBOURS, len(points))
    _, idx = cKDTree(points).query(points, k=k)
    nb = points[idx] - points[idx].mean(1, keepdims=True)
    _, _, vt = np.linalg.svd(nb, full_matrices=False)
    normals = vt[:, -1, :]
    out = points - points.mean(0) if eye is None else np.asarray(eye) - points
    normals[np.einsum("ij,ij->i", normals, out) < 0] *= -1
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

    settings = decompose.PRESETS[config.coacd]
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


def _say(log, msg: str) -> None:
    if log is not None:
        log(msg)
