"""Loading user meshes (OBJ, STL, PLY, GLB/GLTF) into the library's conventions, with checks.

A user mesh passes through four steps before it becomes an :class:`~sim.assets.base.Asset`
(see :func:`sim.decompose.asset_from_user_mesh`):

1. *read*: trimesh reads the file; a scene (GLB/GLTF, multi-object OBJ) is flattened into one
   mesh with its node transforms applied.
2. *validate*: every problem that would make the mesh useless raises :class:`MeshError`
   naming the file and the problem: missing or unreadable file, no triangles, NaN/inf
   vertices, zero area, zero thickness, absurd size (with a hint about millimetres).
3. *repair*: merge duplicate vertices, drop degenerate and duplicate faces, make the winding
   consistent and outward, close small holes. A mesh that is still open afterwards is kept
   (CoACD decomposes open meshes too) and a warning is logged.
4. *centre*: translate so that the bounding-box centre is the origin, as the original code
   did with its meshes.

Lengths are metres after ``scale`` / ``target_size`` are applied.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components

log = logging.getLogger(__name__)

SUPPORTED_FORMATS = (".obj", ".stl", ".ply", ".glb", ".gltf")
MIN_EXTENT = 0.005  # m; smaller than any hangable object (5 mm): the units are surely wrong.
MAX_EXTENT = 5.0  # m; larger than any household object or hook: probably mm or cm units.
MIN_THICKNESS = 2e-4  # m; thinner than a 0.2 mm blade is a flat sheet, not a solid.
MIN_AREA = 1e-8  # m^2; (0.1 mm)^2: below this the surface is degenerate.
MAX_HOLE_EDGES = 8  # boundary loops up to this many edges are missing faces and get filled;
# longer ones are real openings (a cup modelled as a surface) and are left to CoACD.
MERGE_DIGITS = 8  # vertices equal to 1e-8 m are merged (trimesh merge_vertices precision)


class MeshError(ValueError):
    """A user mesh cannot be used; the message names the file and the problem."""


def load_user_mesh(
    path: str | os.PathLike,
    *,
    target_size: float | None = None,
    scale: float | None = None,
    up: str = "z",
) -> tuple[trimesh.Trimesh, dict]:
    """Read, validate, repair and centre a user mesh.

    Args:
      path: an OBJ, STL, PLY, GLB or GLTF file.
      target_size: if given, rescale so that the largest bounding-box extent is this many
        metres (applied after ``scale``).
      scale: a factor applied to the file's coordinates first, e.g. 0.001 for a file in
        millimetres.
      up: ``"z"`` (our convention, default) or ``"y"`` to rotate a y-up file (glTF's own
        convention, most Blender exports) so that its +y becomes +z.

    Returns:
      ``(mesh, report)``: the repaired, centred mesh (metres), and a JSON-able dict of what was
      read and repaired: ``path, format, n_vertices_read, n_faces_read, scale, merged_vertices,
      degenerate_faces_removed, duplicate_faces_removed, winding_flipped, inverted, holes_filled,
      watertight, centre`` (the offset subtracted, metres), ``extents``, ``n_vertices, n_faces``.

    Raises:
      MeshError: when the file cannot be used; the message says which file and why.
    """
    path = Path(path)
    fmt = path.suffix.lower()
    if not path.exists():
        raise MeshError(f"{path}: file not found")
    if not path.is_file():
        raise MeshError(f"{path}: not a file")
    if fmt not in SUPPORTED_FORMATS:
        raise MeshError(
            f"{path}: unsupported format {fmt!r}; use one of {', '.join(SUPPORTED_FORMATS)}"
        )
    if path.stat().st_size == 0:
        raise MeshError(f"{path}: file is empty (0 bytes)")
    if up not in ("z", "y"):
        raise MeshError(f"{path}: up must be 'z' or 'y', got {up!r}")

    vertices, faces = _read(path, fmt)
    report: dict = dict(
        path=str(path), format=fmt[1:], n_vertices_read=len(vertices), n_faces_read=len(faces)
    )
    if len(faces) == 0 or len(vertices) == 0:
        raise MeshError(f"{path}: mesh is empty (no triangles; a point cloud or empty scene?)")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"{path}: faces index vertices that do not exist")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise MeshError(
            f"{path}: {int(bad.sum())} of {len(vertices)} vertices are NaN or infinite "
            f"(first at index {int(np.flatnonzero(bad)[0])})"
        )

    if up == "y":  # +y -> +z, +z -> -y (a right-handed rotation of +90 degrees about x)
        vertices = vertices @ np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]).T
    factor = 1.0 if scale is None else float(scale)
    if not np.isfinite(factor) or factor <= 0:
        raise MeshError(f"{path}: scale must be a positive number, got {scale!r}")
    vertices = vertices * factor
    # Only referenced vertices count for the size (files may carry stray points).
    used = vertices[np.unique(faces)]
    largest = float((used.max(0) - used.min(0)).max())
    if largest <= 0:
        raise MeshError(f"{path}: degenerate mesh, all vertices coincide (zero extent)")
    if target_size is not None:
        if not MIN_EXTENT <= target_size <= MAX_EXTENT:
            raise MeshError(
                f"{path}: target_size {target_size} m is outside [{MIN_EXTENT}, {MAX_EXTENT}] m"
            )
        factor *= target_size / largest
        vertices = vertices * (target_size / largest)
        largest = float(target_size)
    report["scale"] = factor
    if largest > MAX_EXTENT:
        raise MeshError(
            f"{path}: absurd size, largest extent is {largest:.4g} m (> {MAX_EXTENT} m); "
            f"is the file in millimetres? pass scale=0.001 or target_size=<metres>"
        )
    if largest < MIN_EXTENT:
        raise MeshError(
            f"{path}: absurd size, largest extent is {largest:.4g} m (< {MIN_EXTENT * 1000:g} mm); "
            f"pass scale=<factor> or target_size=<metres> to give it its real size"
        )

    thickness = _thickness(vertices[np.unique(faces)])
    if thickness < MIN_THICKNESS:
        raise MeshError(
            f"{path}: degenerate mesh, flat (thickness {thickness * 1000:.3g} mm along its "
            f"thinnest axis, < {MIN_THICKNESS * 1000:g} mm): zero volume"
        )

    mesh = trimesh.Trimesh(vertices, faces, process=False, validate=False)
    _repair(mesh, path, report)

    volume = _signed_volume(mesh)
    if report["watertight"] and abs(volume) < MIN_THICKNESS * MIN_AREA:
        raise MeshError(f"{path}: degenerate mesh, zero volume ({volume:.3g} m^3)")

    lo, hi = mesh.bounds
    centre = 0.5 * (lo + hi)
    mesh.apply_translation(-centre)
    report.update(
        centre=[float(c) for c in centre],
        extents=[float(e) for e in hi - lo],
        n_vertices=len(mesh.vertices),
        n_faces=len(mesh.faces),
    )
    return mesh, report


# ----------------------------------------------------------------------------- reading


def _read(path: Path, fmt: str) -> tuple[np.ndarray, np.ndarray]:
    """Raw ``vertices`` [V, 3] float64 and ``faces`` [F, 3] int64 of the file, unprocessed."""
    try:
        loaded = trimesh.load(str(path), force=None, process=False)
    except Exception as exc:  # trimesh raises many kinds on bad files
        raise MeshError(
            f"{path}: unreadable as {fmt[1:].upper()} ({type(exc).__name__}: {exc})"
        ) from exc
    if isinstance(loaded, trimesh.Scene):
        meshes = _scene_meshes(loaded)
    elif isinstance(loaded, trimesh.Trimesh):
        meshes = [loaded]
    else:  # PointCloud, Path3D, ...
        meshes = []
    meshes = [m for m in meshes if len(m.faces)]
    if not meshes:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    vertices, faces, offset = [], [], 0
    for m in meshes:
        vertices.append(np.asarray(m.vertices, np.float64))
        faces.append(np.asarray(m.faces, np.int64) + offset)
        offset += len(m.vertices)
    return np.concatenate(vertices), np.concatenate(faces)


def _scene_meshes(scene: trimesh.Scene) -> list[trimesh.Trimesh]:
    """Every mesh instance of a scene, with its node transform applied."""
    meshes = []
    for node in scene.graph.nodes_geometry:
        transform, geom_name = scene.graph[node]
        geom = scene.geometry.get(geom_name)
        if isinstance(geom, trimesh.Trimesh):
            m = trimesh.Trimesh(geom.vertices.copy(), geom.faces.copy(), process=False)
            m.apply_transform(transform)
            meshes.append(m)
    return meshes


# ----------------------------------------------------------------------------- repairs


def _repair(mesh: trimesh.Trimesh, path: Path, report: dict) -> None:
    """Repairs ``mesh`` in place and records each one in ``report``."""
    n_v = len(mesh.vertices)
    mesh.merge_vertices(digits_vertex=MERGE_DIGITS)
    report["merged_vertices"] = n_v - len(mesh.vertices)

    if float(mesh.area_faces.sum()) < MIN_AREA:
        raise MeshError(
            f"{path}: degenerate mesh, total surface area {mesh.area_faces.sum():.3g} m^2 "
            f"(all faces degenerate)"
        )
    keep = mesh.nondegenerate_faces()
    report["degenerate_faces_removed"] = int((~keep).sum())
    if not keep.any():
        raise MeshError(f"{path}: degenerate mesh, all {len(keep)} faces have zero area")
    mesh.update_faces(keep)
    n_f = len(mesh.faces)
    mesh.update_faces(mesh.unique_faces())
    report["duplicate_faces_removed"] = n_f - len(mesh.faces)
    mesh.remove_unreferenced_vertices()

    report["winding_flipped"] = _fix_winding(mesh)
    report["holes_filled"] = _fill_small_holes(mesh)
    watertight = bool(mesh.is_watertight)
    report["inverted"] = False
    if watertight and _signed_volume(mesh) < 0:  # consistent but inward: turn it outside out
        mesh.invert()
        report["inverted"] = True
    report["watertight"] = watertight
    if not watertight:
        log.warning(
            "%s: mesh is not watertight after repair (%d open boundary edges); "
            "using it anyway, CoACD decomposes open meshes",
            path,
            _n_boundary_edges(mesh),
        )


def _fix_winding(mesh: trimesh.Trimesh) -> int:
    """Make neighbouring faces agree on orientation; returns the number of faces flipped.

    Breadth-first over the face adjacency graph: two faces sharing edge (a, b) agree when
    exactly one of them runs a -> b. (trimesh's own fix_winding needs networkx.)
    """
    faces = np.asarray(mesh.faces)
    pairs = np.asarray(mesh.face_adjacency)
    if len(pairs) == 0:
        return 0
    edges = np.asarray(mesh.face_adjacency_edges)

    def runs_forward(face_ids):
        f = faces[face_ids]
        a, b = edges[:, :1], edges[:, 1:]
        return ((f == a) & (np.roll(f, -1, axis=1) == b)).any(axis=1)

    disagree = runs_forward(pairs[:, 0]) == runs_forward(pairs[:, 1])
    if not disagree.any():
        return 0
    n = len(faces)
    rows = np.concatenate([pairs[:, 0], pairs[:, 1]])
    cols = np.concatenate([pairs[:, 1], pairs[:, 0]])
    parity = np.concatenate([disagree, disagree]).astype(np.int8) + 1  # 1 agree, 2 disagree
    graph = coo_matrix((parity, (rows, cols)), shape=(n, n)).tocsr()
    graph.data = np.minimum(graph.data, 2)  # duplicate pairs (non-manifold edges) summed
    flip = np.zeros(n, bool)
    _, labels = connected_components(graph, directed=False)
    for root in np.unique(labels, return_index=True)[1]:
        order, pred = breadth_first_order(graph, root, directed=False, return_predecessors=True)
        children = order[1:]
        if len(children) == 0:  # a face with no neighbour: nothing to agree with
            continue
        flips_edge = (np.asarray(graph[pred[children], children]).ravel() == 2).tolist()
        parents = pred[children].tolist()
        state = {int(root): False}
        for node, parent, f in zip(children.tolist(), parents, flips_edge):
            state[node] = state[parent] ^ f
        flip[list(state)] = list(state.values())
    if flip.any():
        new_faces = faces.copy()
        new_faces[flip] = new_faces[flip][:, ::-1]
        mesh.faces = new_faces
    return int(flip.sum())


def _boundary_edges(mesh: trimesh.Trimesh) -> np.ndarray:
    """[B, 2] directed edges (as the faces run them) that belong to exactly one face."""
    directed = np.asarray(mesh.edges)
    undirected = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    return directed[counts[inverse.reshape(-1)] == 1]


def _n_boundary_edges(mesh: trimesh.Trimesh) -> int:
    return len(_boundary_edges(mesh))


def _fill_small_holes(mesh: trimesh.Trimesh) -> int:
    """Close boundary loops of at most MAX_HOLE_EDGES edges; returns how many were filled.

    Each loop gets a new vertex at its centroid and a fan of triangles run against the loop's
    direction, so the patch agrees with the surrounding winding.
    """
    boundary = _boundary_edges(mesh)
    if len(boundary) == 0:
        return 0
    nxt: dict[int, int] = {}
    for a, b in boundary:
        if a in nxt:  # a vertex on two boundary loops (non-manifold): leave this mesh alone
            return 0
        nxt[int(a)] = int(b)
    vertices = [np.asarray(mesh.vertices)]
    faces = [np.asarray(mesh.faces)]
    n_vertices = len(mesh.vertices)
    seen: set[int] = set()
    filled = 0
    for start in list(nxt):
        if start in seen:
            continue
        loop = [start]
        seen.add(start)
        while nxt.get(loop[-1]) is not None and nxt[loop[-1]] != start:
            v = nxt[loop[-1]]
            if v in seen:
                break
            loop.append(v)
            seen.add(v)
        if nxt.get(loop[-1]) != start or len(loop) > MAX_HOLE_EDGES:
            continue
        if len(loop) == 3:
            faces.append(np.array([[loop[2], loop[1], loop[0]]]))
        else:
            centroid = np.asarray(mesh.vertices)[loop].mean(0)
            vertices.append(centroid[None])
            c = n_vertices
            n_vertices += 1
            faces.append(
                np.array([[loop[(i + 1) % len(loop)], loop[i], c] for i in range(len(loop))])
            )
        filled += 1
    if filled:
        mesh.vertices = np.concatenate(vertices)
        mesh.faces = np.concatenate(faces)
    return filled


def _thickness(vertices: np.ndarray) -> float:
    """Extent of the points along their thinnest principal axis, metres."""
    centred = vertices - vertices.mean(0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    projected = centred @ axes[-1]
    return float(projected.max() - projected.min())


def _signed_volume(mesh: trimesh.Trimesh) -> float:
    """Enclosed volume, m^3, positive for outward winding (divergence theorem)."""
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)
