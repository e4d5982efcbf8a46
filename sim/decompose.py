"""Convex decomposition of user meshes with CoACD, cached on disk, and user-mesh assets.

Procedural assets are built from convex parts and never need this module. A user mesh is an
arbitrary (often concave, sometimes open) surface; MuJoCo collides every mesh geom as its
convex hull, so the mesh is split into approximately convex pieces first (the original code
used V-HACD; we use CoACD, which keeps thin hang loops open more reliably).

Each CoACD hull is thinned to at most :data:`sim.geometry.MAX_HULL_VERTICES` vertices, because
MJX's convex collision cost grows with the vertex count of every hull.

The cache
---------
CoACD takes seconds to minutes per mesh, so results are kept in
``$OMNIHANG_CACHE/coacd`` (default ``~/.cache/omnihang_jax/coacd``), one ``<key>.npz`` per
mesh, where ``key`` is the SHA-256 of the vertices rounded to 1e-6 m, the faces, the CoACD
settings and the CoACD version. The raw CoACD hulls are stored (thinning happens on load),
files are written atomically (temporary file + ``os.replace``), and a file that fails to
load or to match its key is reported and recomputed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.metadata
import json
import logging
import os
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import trimesh

from sim import geometry
from sim.assets.base import FLOOR_GAP, Asset, HangLoop, Peg
from sim.geometry import MAX_HULL_VERTICES, ConvexMesh
from sim.meshio import load_user_mesh

log = logging.getLogger(__name__)

CACHE_FORMAT = 1  # bump when the .npz layout changes: old files then miss the cache
KEY_PRECISION = 1e-6  # m; vertices are rounded to this before hashing (float noise ignored)
MIN_HULL_VOLUME = 1e-10  # m^3 (a 0.5 mm cube): slivers CoACD sometimes emits are dropped
GROUND_TOLERANCE = 1e-3  # m; hulls of a free-standing support within this of its bottom = base


@dataclasses.dataclass(frozen=True)
class CoacdSettings:
    """The CoACD parameters we use (names as in ``coacd.run_coacd``)."""

    threshold: float = 0.05  # concavity bound; CoACD's default, keeps handles and rings open
    max_convex_hull: int = 16  # each hull is one MJX geom; 16 bounds the per-pair collision cost
    preprocess_mode: str = "auto"  # manifold remeshing only when the input is not manifold
    preprocess_resolution: int = 50
    resolution: int = 2000  # surface samples for the concavity metric
    mcts_nodes: int = 20
    mcts_iterations: int = 150
    mcts_max_depth: int = 3
    seed: int = 0  # CoACD's tree search is random; fixed for reproducible hulls


# User meshes in the hang command: CoACD's search as above without the manifold remeshing, which
# is most of the time on a non-manifold file (pybullet_data's open mug, handle along +y, on 2
# cores: 8.9 s instead of 73-118 s; 16 hulls either way, no hull inside the handle's opening).
USER = dataclasses.replace(CoacdSettings(), preprocess_mode="off")

# Cheap settings for tests and previews: ~0.3 s on a 256-face torus instead of ~0.8 s.
FAST = CoacdSettings(
    preprocess_mode="off", resolution=500, mcts_nodes=10, mcts_iterations=60, mcts_max_depth=2
)

# The settings by name (the hang command's --coacd): "library" is the asset library's.
PRESETS = {"user": USER, "library": CoacdSettings(), "fast": FAST}


class Decomposition(NamedTuple):
    """The convex parts of one mesh and a JSON-able record of how they were made."""

    hulls: list[ConvexMesh]
    stats: dict


def default_cache_dir() -> Path:
    """``$OMNIHANG_CACHE/coacd`` if that variable is set, else ``~/.cache/omnihang_jax/coacd``."""
    root = os.environ.get("OMNIHANG_CACHE")
    base = Path(root) if root else Path.home() / ".cache" / "omnihang_jax"
    return base / "coacd"


def coacd_version() -> str:
    try:
        return importlib.metadata.version("coacd")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def cache_key(vertices: np.ndarray, faces: np.ndarray, settings: CoacdSettings) -> str:
    """SHA-256 hex of the rounded vertices, faces, settings and CoACD version."""
    quantised = np.rint(np.asarray(vertices, np.float64) / KEY_PRECISION).astype("<i8")
    h = hashlib.sha256()
    h.update(f"omnihang-coacd-{CACHE_FORMAT}".encode())
    h.update(np.asarray(quantised.shape, "<i8").tobytes())
    h.update(quantised.tobytes())
    f = np.asarray(faces, "<i8")
    h.update(np.asarray(f.shape, "<i8").tobytes())
    h.update(f.tobytes())
    h.update(json.dumps(dataclasses.asdict(settings), sort_keys=True).encode())
    h.update(coacd_version().encode())
    return h.hexdigest()


def decompose(
    mesh: trimesh.Trimesh,
    settings: CoacdSettings = CoacdSettings(),
    cache_dir: str | os.PathLike | None = None,
) -> Decomposition:
    """Convex decomposition of ``mesh`` (metres), from the cache when possible.

    Returns the hulls, each with at most MAX_HULL_VERTICES vertices, and ``stats``:
    ``key, cache_hit, cache_file, seconds`` (CoACD wall time, 0 on a hit), ``n_hulls``,
    ``raw_hull_vertices`` (per hull, before thinning), ``hull_vertices`` (after),
    ``n_thinned``, ``n_dropped`` (sliver hulls), ``volume_kept`` (summed hull volume after
    thinning / before; farthest-point thinning typically keeps > 99.5 %), ``coacd_version``.
    """
    vertices = np.asarray(mesh.vertices, np.float64)
    faces = np.asarray(mesh.faces, np.int64)
    key = cache_key(vertices, faces, settings)
    directory = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    cache_file = directory / f"{key}.npz"

    raw = _read_cache(cache_file, key)
    hit = raw is not None
    seconds = 0.0
    if not hit:
        start = time.perf_counter()
        raw = _run_coacd(vertices, faces, settings)
        seconds = time.perf_counter() - start
        _write_cache(cache_file, key, raw)

    hulls, dropped = [], 0
    for points in raw:
        part = _thin_hull(points)
        if part is None:
            dropped += 1
        else:
            hulls.append(part)
    if not hulls:
        raise ValueError(f"CoACD produced no usable convex hull (key {key[:12]})")
    stats = dict(
        key=key,
        cache_hit=hit,
        cache_file=str(cache_file),
        seconds=seconds,
        n_hulls=len(hulls),
        raw_hull_vertices=[len(p) for p in raw],
        hull_vertices=[len(h.vertices) for h in hulls],
        n_thinned=sum(len(p) > MAX_HULL_VERTICES for p in raw),
        n_dropped=dropped,
        volume_kept=_volume_kept(raw, hulls),
        coacd_version=coacd_version(),
    )
    log.info(
        "CoACD %s: %d hulls (%d thinned to %d vertices, %.1f %% volume kept, %d dropped) in %.2f s",
        "cache hit" if hit else "ran",
        len(hulls),
        stats["n_thinned"],
        MAX_HULL_VERTICES,
        100 * stats["volume_kept"],
        dropped,
        seconds,
    )
    return Decomposition(hulls, stats)


def convex_decompose(
    mesh: trimesh.Trimesh,
    *,
    threshold: float = CoacdSettings.threshold,
    max_convex_hull: int = CoacdSettings.max_convex_hull,
    settings: CoacdSettings | None = None,
    cache_dir: str | os.PathLike | None = None,
) -> list[ConvexMesh]:
    """The convex hulls of ``mesh``; ``threshold`` / ``max_convex_hull`` override ``settings``.

    See :func:`decompose` for the statistics (time, hull sizes, cache hit).
    """
    base = settings if settings is not None else CoacdSettings()
    base = dataclasses.replace(base, threshold=threshold, max_convex_hull=max_convex_hull)
    return decompose(mesh, base, cache_dir).hulls


# ----------------------------------------------------------------------------- CoACD + cache


def _run_coacd(vertices: np.ndarray, faces: np.ndarray, s: CoacdSettings) -> list[np.ndarray]:
    import coacd  # here, not at the top: procedural assets (and machines without coacd) never need it

    coacd.set_log_level("error")
    parts = coacd.run_coacd(
        coacd.Mesh(vertices, faces.astype(np.int32)),
        threshold=s.threshold,
        max_convex_hull=s.max_convex_hull,
        preprocess_mode=s.preprocess_mode,
        preprocess_resolution=s.preprocess_resolution,
        resolution=s.resolution,
        mcts_nodes=s.mcts_nodes,
        mcts_iterations=s.mcts_iterations,
        mcts_max_depth=s.mcts_max_depth,
        seed=s.seed,
    )
    return [np.asarray(v, np.float64) for v, _ in parts]


def _read_cache(path: Path, key: str) -> list[np.ndarray] | None:
    """The raw hulls stored at ``path``, or None when absent or corrupt (reported)."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            stored_key = str(data["key"])
            fmt = int(data["format"])
            points = np.asarray(data["vertices"], np.float64)
            sizes = np.asarray(data["sizes"], np.int64)
        if stored_key != key or fmt != CACHE_FORMAT:
            raise ValueError("key or format does not match the file name")
        if points.ndim != 2 or points.shape[1] != 3 or sizes.sum() != len(points):
            raise ValueError("hull arrays have inconsistent shapes")
        if len(sizes) == 0 or (sizes < 1).any() or not np.isfinite(points).all():
            raise ValueError("hull arrays are empty or not finite")
    except Exception as exc:  # truncated zip, missing array, bad values: all mean recompute
        log.warning("corrupt CoACD cache file %s (%s); recomputing", path, exc)
        return None
    return np.split(points, np.cumsum(sizes)[:-1])


def _write_cache(path: Path, key: str, hulls: Sequence[np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem[:16], suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(
                f,
                key=np.array(key),
                format=np.array(CACHE_FORMAT),
                coacd_version=np.array(coacd_version()),
                vertices=np.concatenate(hulls) if hulls else np.zeros((0, 3)),
                sizes=np.array([len(h) for h in hulls], np.int64),
            )
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _thin_hull(points: np.ndarray) -> ConvexMesh | None:
    """A hull part of <= MAX_HULL_VERTICES vertices, or None for a flat or tiny sliver."""
    if len(points) < 4:
        return None
    try:
        part = geometry.hull(points)
    except Exception:  # qhull refuses flat point sets
        return None
    if len(part.vertices) < 4 or part.volume < MIN_HULL_VOLUME:
        return None
    return part


def _volume_kept(raw: Sequence[np.ndarray], hulls: Sequence[ConvexMesh]) -> float:
    before = 0.0
    for points in raw:
        try:
            before += float(trimesh.convex.convex_hull(points).volume)
        except Exception:  # flat slivers have no volume to lose
            pass
    after = sum(h.volume for h in hulls)
    return float(after / before) if before > 0 else 1.0


def clear_cache(cache_dir: str | os.PathLike | None = None) -> int:
    """Delete every cached decomposition; returns how many files were removed."""
    directory = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    removed = 0
    for f in [*directory.glob("*.npz"), *directory.glob("*.tmp")]:
        f.unlink(missing_ok=True)
        removed += 1
    return removed


# ----------------------------------------------------------------------------- user assets


def asset_from_user_mesh(
    path: str | os.PathLike,
    category: str,
    kind: str = "object",
    name: str | None = None,
    *,
    wall: bool = True,
    features: Sequence[HangLoop | Peg] = (),
    scale: float | None = None,
    target_size: float | None = None,
    up: str = "z",
    settings: CoacdSettings = CoacdSettings(),
    cache_dir: str | os.PathLike | None = None,
) -> Asset:
    """An :class:`Asset` whose parts are the CoACD hulls of the mesh file at ``path``.

    Args:
      path: mesh file, read by :func:`sim.meshio.load_user_mesh` (checks and repairs).
      category: object category or support family recorded on the asset (need not be a
        registered procedural one).
      kind: ``"object"`` or ``"support"``.
      name: unique asset name; default ``"<category>_<file stem>"``.
      wall: supports only: mounted on a wall (the wall is the plane of the lowest y, the item
        reaches towards +y as in :mod:`sim.assets.base`) or free-standing on its lowest z.
      features: :class:`HangLoop` (objects) or :class:`Peg` (supports) in the asset frame,
        i.e. metres about the mesh's bounding-box centre; empty unless the user knows them.
      scale, target_size, up: passed to :func:`load_user_mesh`.
      settings, cache_dir: passed to :func:`decompose`.

    The asset's ``mesh`` is the repaired user mesh itself (for point clouds), its ``parts``
    the hulls (for physics); ``seed`` is -1 (not generated); ``params`` holds the load report
    and the decomposition statistics.
    """
    if kind not in ("object", "support"):
        raise ValueError(f"kind must be 'object' or 'support', got {kind!r}")
    for f in features:
        expected = HangLoop if kind == "object" else Peg
        if not isinstance(f, expected):
            raise TypeError(f"{kind} features must be {expected.__name__}, got {type(f).__name__}")
    mesh, report = load_user_mesh(path, target_size=target_size, scale=scale, up=up)
    result = decompose(mesh, settings, cache_dir)
    parts = list(result.hulls)
    name = name or f"{category}_{Path(path).stem}"
    params = dict(load_report=report, decomposition=result.stats)
    if kind == "object":
        return Asset(
            name,
            "object",
            category,
            -1,
            parts,
            list(features),
            params,
            source=str(path),
            _mesh=mesh,
        )
    pts = geometry.support_points(parts)
    lowest = float(pts[:, 2].min())
    if wall:
        wall_y = float(pts[:, 1].min())
        floor_z = lowest - FLOOR_GAP
        ground: tuple[int, ...] = ()
    else:
        wall_y, floor_z = None, lowest
        ground = tuple(
            i
            for i, p in enumerate(parts)
            if p.support_points()[:, 2].min() < lowest + GROUND_TOLERANCE
        )
    params["wall"] = wall
    return Asset(
        name,
        "support",
        category,
        -1,
        parts,
        list(features),
        params,
        ground,
        wall_y,
        floor_z,
        source=str(path),
        _mesh=mesh,
    )
