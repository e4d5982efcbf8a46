"""The asset library: every object and supporting item of the dataset, seeded and split.

The paper's dataset has 340 objects over 11 categories and 72 supporting items; we generate
the same numbers procedurally from the registries in :mod:`sim.assets.base`, so the library
is a pure function of a :class:`LibraryConfig` (plus the generator code). Whole assets are
held out for testing (about 15 % per category and per family), so test pairs always show a
shape the networks never saw.

Seeds and names
---------------
Asset ``i`` of category ``c`` is named ``f"{c}_{i:04d}"`` and generated from the seed
``SeedSequence(base_seed, spawn_key=(sha(kind), sha(c), i))``, where ``sha`` is the first 8
bytes of a SHA-256. The seed of an asset therefore never depends on Python's ``hash()``, on
the process, on the registration order, or on how many other categories exist.

Split
-----
Within each category (family), the assets are ranked by ``sha256(base_seed, kind, c, i)`` and
the first ``n_test = min(n - 1, max(1, round(fraction * n)))`` go to test (none for
``fraction = 0``, and none when the category has a single asset).

Meshes are lazy: building a library only builds the convex parts (milliseconds each); the
union meshes (``Asset.mesh``) are built on first use, or all at once by
:meth:`Library.build_meshes`, which also keeps them in ``cache_dir/meshes`` when given.
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import json
import logging
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import trimesh
from tqdm.auto import tqdm

import sim.assets.objects  # noqa: F401  (registers the object categories)
import sim.assets.supports  # noqa: F401  (registers the support families)
from sim import atomic, decompose
from sim.assets.base import (
    OBJECT_CATEGORIES,
    SUPPORT_FAMILIES,
    Asset,
    HangLoop,
    Peg,
    build_object,
    build_support,
)
from sim.geometry import Box, Capsule, ConvexMesh

log = logging.getLogger(__name__)

MANIFEST_FORMAT = 1
SPLITS = ("train", "test")


@dataclasses.dataclass(frozen=True)
class LibraryConfig:
    """What to generate. ``None`` category/family lists mean every registered one."""

    n_objects: int = 340  # the paper's dataset size
    n_supports: int = 72  # the paper's number of supporting items
    seed: int = 0  # base seed of every asset and of the split
    object_test_fraction: float = 0.15  # whole objects held out per category
    support_test_fraction: float = 0.15  # whole supports held out per family
    object_categories: tuple[str, ...] | None = None
    support_families: tuple[str, ...] | None = None

    def categories(self) -> tuple[str, ...]:
        """The object categories used, sorted (the registry's order is an import accident)."""
        return _resolve(self.object_categories, OBJECT_CATEGORIES, "object category")

    def families(self) -> tuple[str, ...]:
        return _resolve(self.support_families, SUPPORT_FAMILIES, "support family")

    def objects_per_category(self) -> dict[str, int]:
        """Planned counts: n_objects spread as evenly as possible, extras to the first names."""
        return _spread(self.n_objects, self.categories())

    def supports_per_family(self) -> dict[str, int]:
        return _spread(self.n_supports, self.families())


TINY = LibraryConfig(n_objects=22, n_supports=10)  # tests: two objects per category


@dataclasses.dataclass
class Library:
    """Assets by name and the train/test split of their names."""

    config: LibraryConfig
    objects: dict[str, Asset]
    supports: dict[str, Asset]
    split: dict[str, dict[str, list[str]]]  # split -> {"objects": names, "supports": names}
    cache_dir: Path | None = None

    def split_of(self, name: str) -> str:
        for split, groups in self.split.items():
            if any(name in names for names in groups.values()):
                return split
        raise KeyError(f"{name} is in no split")

    def assets(self, split: str | None = None, kind: str | None = None) -> list[Asset]:
        """Assets of one split ("train" / "test", None: both) and kind (None: both)."""
        out = []
        for s in SPLITS if split is None else (split,):
            if kind in (None, "object"):
                out += [self.objects[n] for n in self.split[s]["objects"]]
            if kind in (None, "support"):
                out += [self.supports[n] for n in self.split[s]["supports"]]
        return out

    def objects_per_category(self) -> dict[str, int]:
        return dict(collections.Counter(a.category for a in self.objects.values()))

    def supports_per_family(self) -> dict[str, int]:
        return dict(collections.Counter(a.category for a in self.supports.values()))

    # ------------------------------------------------------------------------- user assets

    def add_user_object(
        self,
        path: str | os.PathLike,
        category: str = "others",
        scale: float | None = None,
        name: str | None = None,
        *,
        target_size: float | None = None,
        hang_loops: Sequence[HangLoop] = (),
        split: str = "test",
        up: str = "z",
        settings: decompose.CoacdSettings = decompose.CoacdSettings(),
    ) -> Asset:
        """Load, check, decompose and add a user mesh as an object (default: to the test split).

        ``scale`` multiplies the file's coordinates (0.001 for millimetres); ``target_size``
        rescales the largest extent to that many metres. ``hang_loops`` are in the asset
        frame (metres about the mesh's bounding-box centre).
        """
        asset = decompose.asset_from_user_mesh(
            path,
            category,
            "object",
            name,
            features=hang_loops,
            scale=scale,
            target_size=target_size,
            up=up,
            settings=settings,
            cache_dir=self._coacd_dir(),
        )
        self._add(asset, self.objects, "objects", split)
        return asset

    def add_user_support(
        self,
        path: str | os.PathLike,
        family: str = "user",
        scale: float | None = None,
        name: str | None = None,
        *,
        wall: bool = True,
        pegs: Sequence[Peg] = (),
        target_size: float | None = None,
        split: str = "test",
        up: str = "z",
        settings: decompose.CoacdSettings = decompose.CoacdSettings(),
    ) -> Asset:
        """As :meth:`add_user_object` for a supporting item, in the support frame (z up;
        ``wall=True``: the wall is at the mesh's lowest y and the item reaches towards +y)."""
        asset = decompose.asset_from_user_mesh(
            path,
            family,
            "support",
            name,
            wall=wall,
            features=pegs,
            scale=scale,
            target_size=target_size,
            up=up,
            settings=settings,
            cache_dir=self._coacd_dir(),
        )
        self._add(asset, self.supports, "supports", split)
        return asset

    def _coacd_dir(self) -> Path | None:
        return None if self.cache_dir is None else self.cache_dir / "coacd"

    def _add(self, asset: Asset, table: dict[str, Asset], group: str, split: str) -> None:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        if asset.name in self.objects or asset.name in self.supports:
            raise ValueError(f"an asset named {asset.name!r} is already in the library")
        table[asset.name] = asset
        self.split[split][group].append(asset.name)

    # ------------------------------------------------------------------------- meshes

    def build_meshes(self, progress: bool = True) -> None:
        """Build (or load from ``cache_dir/meshes``) every asset's union mesh."""
        assets = [*self.objects.values(), *self.supports.values()]
        for asset in tqdm(assets, desc="union meshes", disable=not progress):
            if asset._mesh is not None:
                continue
            if self.cache_dir is None:
                asset.mesh  # noqa: B018  (builds and caches on the asset)
            else:
                asset._mesh = _cached_union_mesh(asset, self.cache_dir / "meshes")

    # ------------------------------------------------------------------------- records

    def manifest(self) -> dict:
        """JSON-able description of the library: config, counts, split, one record per asset."""
        config = dataclasses.asdict(self.config)
        config["object_categories"] = list(self.config.categories())
        config["support_families"] = list(self.config.families())
        split_of = {n: s for s, groups in self.split.items() for g in groups.values() for n in g}
        return dict(
            format=MANIFEST_FORMAT,
            config=config,
            objects_per_category=self.objects_per_category(),
            supports_per_family=self.supports_per_family(),
            split={s: {k: list(v) for k, v in g.items()} for s, g in self.split.items()},
            objects=[_record(a, split_of[a.name]) for a in self.objects.values()],
            supports=[_record(a, split_of[a.name]) for a in self.supports.values()],
        )

    def save_manifest(self, path: str | os.PathLike) -> None:
        atomic.write_text(Path(path), json.dumps(self.manifest(), indent=1))


def build_library(
    config: LibraryConfig = LibraryConfig(),
    cache_dir: str | os.PathLike | None = None,
    progress: bool = True,
) -> Library:
    """Generate every asset of ``config`` (convex parts only; meshes stay lazy) and split them.

    ``cache_dir`` keeps this library's union meshes (``meshes/``) and user-mesh
    decompositions (``coacd/``); None uses no mesh cache and the default CoACD cache.
    """
    objects, supports = {}, {}
    split = {s: {"objects": [], "supports": []} for s in SPLITS}
    plan = [
        ("object", config.objects_per_category(), config.object_test_fraction, objects),
        ("support", config.supports_per_family(), config.support_test_fraction, supports),
    ]
    for kind, counts, fraction, table in plan:
        jobs = [(c, i) for c, n in counts.items() for i in range(n)]
        build = build_object if kind == "object" else build_support
        for category, index in tqdm(jobs, desc=f"{kind}s", disable=not progress):
            asset = build(category, asset_seed(config.seed, kind, category, index), index)
            table[asset.name] = asset
        for category, n in counts.items():
            test = set(held_out_indices(config.seed, kind, category, n, fraction))
            for index in range(n):
                name = f"{category}_{index:04d}"
                split["test" if index in test else "train"][kind + "s"].append(name)
    library = Library(config, objects, supports, split, Path(cache_dir) if cache_dir else None)
    check_split(library)
    return library


def check_split(library: Library) -> None:
    """Raise ValueError if the split leaks: an asset in both splits, a test asset generated
    from the same (category, seed) or the same file as a train asset, or an asset in no split
    (or a split name that is no asset)."""
    problems = []
    for group, table in (("objects", library.objects), ("supports", library.supports)):
        train, test = (library.split[s][group] for s in SPLITS)
        both = sorted(set(train) & set(test))
        if both:
            problems.append(f"{group} in both train and test: {both}")
        for s in SPLITS:
            dups = [n for n, c in collections.Counter(library.split[s][group]).items() if c > 1]
            if dups:
                problems.append(f"{group} listed twice in {s}: {sorted(dups)}")
        listed = set(train) | set(test)
        if listed - set(table):
            problems.append(
                f"{group} in the split but not in the library: {sorted(listed - set(table))}"
            )
        if set(table) - listed:
            problems.append(f"{group} in no split: {sorted(set(table) - listed)}")
        train_origins = {_origin(table[n]): n for n in train if n in table}
        for n in test:
            if n in table and _origin(table[n]) in train_origins:
                twin = train_origins[_origin(table[n])]
                problems.append(f"test {n} is the same shape as train {twin} ({_origin(table[n])})")
    if problems:
        raise ValueError("train/test split leaks: " + "; ".join(problems))


# ----------------------------------------------------------------------------- seeds, split


def stable_id(text: str) -> int:
    """A 64-bit integer from the SHA-256 of ``text`` (same in every process, unlike hash())."""
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little")


def asset_seed(base_seed: int, kind: str, category: str, index: int) -> int:
    """The uint32 seed of asset ``index`` of ``category`` ("object" or "support" ``kind``)."""
    seq = np.random.SeedSequence(base_seed, spawn_key=(stable_id(kind), stable_id(category), index))
    return int(seq.generate_state(1, np.uint32)[0])


def held_out_indices(
    base_seed: int, kind: str, category: str, n: int, fraction: float
) -> list[int]:
    """Indices in range(n) held out for test, sorted; see the module docstring."""
    if n < 2 or fraction <= 0:
        return []
    n_test = min(n - 1, max(1, int(np.floor(fraction * n + 0.5))))
    rank = sorted(
        range(n),
        key=lambda i: hashlib.sha256(f"split/{base_seed}/{kind}/{category}/{i}".encode()).digest(),
    )
    return sorted(rank[:n_test])


def _spread(total: int, names: Sequence[str]) -> dict[str, int]:
    if not names:
        raise ValueError("no categories/families registered or selected")
    base, extra = divmod(total, len(names))
    return {name: base + (i < extra) for i, name in enumerate(names)}


def _resolve(chosen: Iterable[str] | None, registry: dict, what: str) -> tuple[str, ...]:
    if chosen is None:
        return tuple(sorted(registry))
    unknown = [c for c in chosen if c not in registry]
    if unknown:
        raise ValueError(f"unknown {what} {unknown}; registered: {sorted(registry)}")
    return tuple(sorted(set(chosen)))


def _origin(asset: Asset) -> tuple:
    if asset.seed >= 0 and asset.source == "procedural":
        return (asset.kind, asset.category, asset.seed)
    return (asset.kind, "file", os.path.abspath(asset.source))


# ----------------------------------------------------------------------------- records


def _record(asset: Asset, split: str) -> dict:
    kinds = collections.Counter(p.kind for p in asset.parts)
    hull_sizes = [len(p.vertices) for p in asset.parts if isinstance(p, ConvexMesh)]
    record = dict(
        name=asset.name,
        kind=asset.kind,
        category=asset.category,
        seed=int(asset.seed),
        split=split,
        n_parts=len(asset.parts),
        part_kinds={k: kinds.get(k, 0) for k in (Capsule.kind, Box.kind, ConvexMesh.kind)},
        max_hull_vertices=max(hull_sizes, default=0),
        extents=[round(float(e), 6) for e in asset.extents],
        n_features=len(asset.features),
        source=asset.source,
    )
    if asset.kind == "support":
        record.update(
            wall=asset.wall_y is not None,
            wall_y=None if asset.wall_y is None else round(float(asset.wall_y), 6),
            floor_z=round(float(asset.floor_z), 6),
        )
    return record


def _parts_digest(asset: Asset) -> str:
    """SHA-256 of the exact part geometry: the key of the asset's union mesh."""
    h = hashlib.sha256(b"omnihang-union-1")
    for p in asset.parts:
        h.update(p.kind.encode())
        for field in dataclasses.fields(p):
            h.update(np.ascontiguousarray(getattr(p, field.name), np.float64).tobytes())
    return h.hexdigest()


def _cached_union_mesh(asset: Asset, directory: Path) -> trimesh.Trimesh:
    path = directory / f"{_parts_digest(asset)}.npz"
    if path.exists():
        try:
            with np.load(path, allow_pickle=False) as data:
                return trimesh.Trimesh(data["vertices"], data["faces"], process=False)
        except Exception as exc:  # corrupt: rebuild below
            log.warning("corrupt union-mesh cache file %s (%s); rebuilding", path, exc)
    mesh = asset.mesh
    directory.mkdir(parents=True, exist_ok=True)
    atomic.savez(
        path, compressed=False, vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.faces)
    )
    return mesh
