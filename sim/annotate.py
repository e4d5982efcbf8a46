"""Contact annotations on partial clouds: contact point pairs and soft contact maps.

Original recipe (facts file): contacts at the stable pose, de-duplicated within 1 mm on both
bodies; each contact maps to its nearest cloud point; a soft map spreads from it with weight
``exp(-3 * angle / max_angle) * exp(-5 * geodesic / max_geodesic)``, where ``angle`` is the
angle between a point's normal and the seed point's normal and the geodesic distance comes
from Dijkstra on a k = 10 nearest-neighbour graph of the cloud; maps are summed over
contacts and max-normalised.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation


@dataclasses.dataclass(frozen=True)
class AnnotationConfig:
    dedupe_radius: float = 0.001  # m; contacts closer than this on both bodies are one
    knn: int = 10  # neighbours in the geodesic graph (original)
    angle_weight: float = 3.0  # original exp(-3 * angle / max)
    geodesic_weight: float = 5.0  # original exp(-5 * geodesic / max)


class ContactAnnotation(NamedTuple):
    object_map: np.ndarray  # [N] float32 in [0, 1], soft contact map on the object cloud
    support_map: np.ndarray  # [M] float32 in [0, 1]
    pairs: np.ndarray  # [K, 2] int32 (object cloud index, support cloud index) per contact
    object_points: np.ndarray  # [K, 3] contact points on the object, object frame
    support_points: np.ndarray  # [K, 3] contact points on the support, world frame


def dedupe_contacts(
    object_points: np.ndarray, support_points: np.ndarray, radius: float
) -> np.ndarray:
    """Indices of contacts kept: a contact is dropped if an earlier kept one lies within
    ``radius`` of it on both bodies."""
    kept: list[int] = []
    for i in range(len(object_points)):
        close = [
            np.linalg.norm(object_points[i] - object_points[j]) < radius
            and np.linalg.norm(support_points[i] - support_points[j]) < radius
            for j in kept
        ]
        if not any(close):
            kept.append(i)
    return np.asarray(kept, dtype=int)


class CloudGraph:
    """The k-nearest-neighbour graph of one cloud and a cache of each seed's spread weights.

    A pair's clouds are the same for all of its stable poses, and nearby poses share
    contact seeds, so :func:`derive_pair <sim.dataset.derive_pair>` builds one per cloud and
    passes it to every :func:`annotate` call (the maps are identical to building it afresh).
    """

    def __init__(self, points: np.ndarray, normals: np.ndarray, config: AnnotationConfig):
        self.n = n = len(points)
        self.config = config
        k = min(config.knn + 1, n)
        dist, nbr = cKDTree(points).query(points, k=k)
        rows = np.repeat(np.arange(n), k - 1)
        self.graph = csr_matrix(
            (np.maximum(dist[:, 1:].ravel(), 1e-9), (rows, nbr[:, 1:].ravel())), shape=(n, n)
        )
        self.unit = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        self._weights: dict[int, np.ndarray] = {}

    def weights(self, seeds: np.ndarray) -> list[np.ndarray]:
        """[N] spread weight of each seed (sorted unique indices), computed once per seed."""
        new = [int(s) for s in seeds if int(s) not in self._weights]
        if new:
            cfg = self.config
            geo = dijkstra(self.graph, directed=False, indices=new)  # [S, N]
            for s, g in zip(new, geo, strict=True):
                angle = np.arccos(np.clip(self.unit @ self.unit[s], -1.0, 1.0))
                finite = np.isfinite(g)
                gmax = g[finite].max() if finite.any() and g[finite].max() > 0 else 1.0
                amax = angle.max() if angle.max() > 0 else 1.0
                self._weights[s] = np.exp(-cfg.angle_weight * angle / amax) * np.exp(
                    -cfg.geodesic_weight * np.where(finite, g, np.inf) / gmax
                )
        return [self._weights[int(s)] for s in seeds]


def soft_contact_map(
    points: np.ndarray,
    normals: np.ndarray,
    seeds: np.ndarray,
    config: AnnotationConfig = AnnotationConfig(),
    graph: CloudGraph | None = None,
) -> np.ndarray:
    """[N] soft contact map spread from the ``seeds`` (cloud indices), max-normalised.
    ``graph``: a :class:`CloudGraph` of this cloud to reuse (built here if None)."""
    n = len(points)
    out = np.zeros(n)
    if len(seeds) == 0:
        return out.astype(np.float32)
    graph = graph if graph is not None else CloudGraph(points, normals, config)
    for w in graph.weights(np.unique(seeds)):
        out += w
    return (out / out.max()).astype(np.float32)


def contact_points(
    contacts_object: np.ndarray,
    contacts_support: np.ndarray,
    pose: np.ndarray,
    config: AnnotationConfig = AnnotationConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """The deduplicated contact points of :func:`annotate` without the soft maps: (object
    points [K, 3] in the object frame, support points [K, 3] in the world frame)."""
    keep = dedupe_contacts(contacts_object, contacts_support, config.dedupe_radius)
    co, cs = contacts_object[keep], contacts_support[keep]
    rot = Rotation.from_quat(np.roll(np.asarray(pose[3:7], float), -1)).as_matrix()
    return (co - pose[:3]) @ rot, cs  # object points: world -> object frame


def annotate(
    contacts_object: np.ndarray,
    contacts_support: np.ndarray,
    pose: np.ndarray,
    object_cloud,
    support_cloud,
    config: AnnotationConfig = AnnotationConfig(),
    graphs: tuple[CloudGraph, CloudGraph] | None = None,
) -> ContactAnnotation:
    """Annotate one stable pose.

    ``contacts_object`` / ``contacts_support``: [K, 3] world-frame contact points on each body
    (from :func:`sim.kernels.contact_query`, masked); ``pose`` [7] the object's pose;
    ``object_cloud`` (object frame) and ``support_cloud`` (world frame) are
    :class:`sim.camera.PointCloud`. ``graphs``: (object, support) :class:`CloudGraph` of
    these clouds, shared by all poses of a pair (built per call if None).
    """
    co_local, cs = contact_points(contacts_object, contacts_support, pose, config)
    if len(cs):
        oi = cKDTree(object_cloud.points).query(co_local)[1]
        si = cKDTree(support_cloud.points).query(cs)[1]
    else:
        oi = si = np.zeros(0, dtype=int)
    return ContactAnnotation(
        soft_contact_map(
            object_cloud.points, object_cloud.normals, oi, config, graphs and graphs[0]
        ),
        soft_contact_map(
            support_cloud.points, support_cloud.normals, si, config, graphs and graphs[1]
        ),
        np.stack([oi, si], axis=1).astype(np.int32) if len(cs) else np.zeros((0, 2), np.int32),
        co_local.astype(np.float32),
        cs.astype(np.float32),
    )
