"""Data contract between the dataset engine and the goal-pose networks.

One record per (object, supporting item) pair: ``HangSample``. The same NamedTuple holds a batch
(every field gains a leading B axis). Frames: object points live in the OBJECT frame (origin at
the mesh's bounding-box centre), support points in the SUPPORT frame; a stable pose maps the
first into the second (``omnihang_jax.poses``).

On disk (``load_hang_dataset``): one ``.npz`` per pair whose keys are the ``HangSample`` field
names (unbatched, unpadded D and C allowed; ``pose_mask`` / ``contact_mask`` may be omitted when
every row is valid).

Also here: ``synthetic_batch`` (ring-on-peg scenes for tests and dry runs), ``stack_samples``
(padding), ``validate_sample`` / ``check_point_clouds`` (clear errors at the Python boundary) and
the host-side datasets used by the training loop.
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple, Protocol

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from omnihang_jax.poses import pose6_to_pose7, pose7_to_pose6

__all__ = [
    "HangSample",
    "MAX_STABLE_POSES",
    "synthetic_sample",
    "synthetic_batch",
    "stack_samples",
    "make_hang_sample",
    "validate_sample",
    "check_point_clouds",
    "HangDataset",
    "ArrayDataset",
    "NpzDirectoryDataset",
    "load_hang_dataset",
    "validation_objects",
    "object_name_of",
    "split_by_object",
    "pack_dataset",
    "PackedDataset",
    "pose7_to_pose6",
    "pose6_to_pose7",
]

MAX_STABLE_POSES = 50  # at most 50 stable poses are kept per pair (facts)


class HangSample(NamedTuple):
    """One (object, support) pair, or a batch of them (leading B axis on every field).

    object_points: [N, 3] float32, metres, object frame (N = 4096 in the original).
    object_normals: [N, 3] float32 unit outward normals.
    support_points: [M, 3] float32, metres, support frame.
    support_normals: [M, 3] float32.
    stable_poses: [D, 7] float32 -- object frame in support frame: xyz (metres) + quaternion wxyz.
    pose_mask: [D] bool, True for real poses (padding rows False); D <= 50.
    object_contact_maps: [D, N] float32 in [0, 1], soft contact map of each stable pose.
    support_contact_maps: [D, M] float32 in [0, 1].
    contact_pairs: [D, C, 2] int32 (object point index, support point index) of the contacts
      at each stable pose.
    contact_mask: [D, C] bool, True for real contact pairs.
    """

    object_points: np.ndarray | jax.Array
    object_normals: np.ndarray | jax.Array
    support_points: np.ndarray | jax.Array
    support_normals: np.ndarray | jax.Array
    stable_poses: np.ndarray | jax.Array
    pose_mask: np.ndarray | jax.Array
    object_contact_maps: np.ndarray | jax.Array
    support_contact_maps: np.ndarray | jax.Array
    contact_pairs: np.ndarray | jax.Array
    contact_mask: np.ndarray | jax.Array


_DTYPES = {
    "object_points": np.float32,
    "object_normals": np.float32,
    "support_points": np.float32,
    "support_normals": np.float32,
    "stable_poses": np.float32,
    "pose_mask": np.bool_,
    "object_contact_maps": np.float32,
    "support_contact_maps": np.float32,
    "contact_pairs": np.int32,
    "contact_mask": np.bool_,
}


# ----------------------------------------------------------------------------------------------
# Validation at the Python boundary (never inside jit).


def check_point_clouds(
    object_points, support_points, batched: bool = True, context: str = ""
) -> None:
    """Raise ValueError unless both clouds are finite arrays of shape [B, *, 3] ([*, 3] when
    not ``batched``). ``context`` (e.g. a file name) prefixes the message."""
    prefix = f"{context}: " if context else ""
    for name, pts in (("object_points", object_points), ("support_points", support_points)):
        pts = np.asarray(pts)
        want = 3 if batched else 2
        if pts.ndim != want or pts.shape[-1] != 3:
            raise ValueError(
                f"{prefix}{name} must have shape {'[B, N, 3]' if batched else '[N, 3]'}, "
                f"got {pts.shape}"
            )
        if not np.all(np.isfinite(pts)):
            bad = int(np.sum(~np.isfinite(pts).all(-1)))
            raise ValueError(f"{prefix}{name} contains {bad} non-finite (NaN/inf) points")


def validate_sample(sample: HangSample, name: str = "sample") -> None:
    """Check shapes and finiteness of one unbatched HangSample; raise ValueError if wrong."""
    s = HangSample(*(np.asarray(x) for x in sample))
    check_point_clouds(s.object_points, s.support_points, batched=False, context=name)
    n, m = s.object_points.shape[0], s.support_points.shape[0]
    d = s.stable_poses.shape[0]
    expect = {
        "object_normals": (n, 3),
        "support_normals": (m, 3),
        "stable_poses": (d, 7),
        "pose_mask": (d,),
        "object_contact_maps": (d, n),
        "support_contact_maps": (d, m),
    }
    for field, shape in expect.items():
        if getattr(s, field).shape != shape:
            raise ValueError(f"{name}: {field} has shape {getattr(s, field).shape}, want {shape}")
    if s.contact_pairs.ndim != 3 or s.contact_pairs.shape[::2] != (d, 2):
        raise ValueError(f"{name}: contact_pairs has shape {s.contact_pairs.shape}, want [D, C, 2]")
    if s.contact_mask.shape != s.contact_pairs.shape[:2]:
        raise ValueError(f"{name}: contact_mask shape {s.contact_mask.shape} != [D, C]")
    for field in ("object_normals", "support_normals", "stable_poses"):
        if not np.all(np.isfinite(getattr(s, field))):
            raise ValueError(f"{name}: {field} contains NaN/inf")
    if not np.any(s.pose_mask):
        raise ValueError(f"{name}: no valid stable pose (pose_mask all False)")
    if np.any(s.contact_pairs[..., 0] >= n) or np.any(s.contact_pairs[..., 1] >= m):
        raise ValueError(f"{name}: contact_pairs index out of range")


# ----------------------------------------------------------------------------------------------
# Padding / batching (host side, numpy).


def _pad_axis(x: np.ndarray, axis: int, size: int) -> np.ndarray:
    if x.shape[axis] > size:
        raise ValueError(f"cannot pad axis {axis} of size {x.shape[axis]} down to {size}")
    pad = [(0, 0)] * x.ndim
    pad[axis] = (0, size - x.shape[axis])
    return np.pad(x, pad)


def stack_samples(
    samples: Sequence[HangSample], max_poses: int | None = None, max_contacts: int | None = None
) -> HangSample:
    """Stack unbatched samples into a batch, padding D (poses) and C (contacts) with masked rows.

    All samples must share N and M (the dataset engine resamples clouds to a fixed count).
    max_poses / max_contacts default to the largest D / C in ``samples``. Padded poses are the
    identity (never used: masked). Returns a HangSample of numpy arrays with leading B axis.
    """
    samples = [HangSample(*(np.asarray(x) for x in s)) for s in samples]
    d = max_poses or max(s.stable_poses.shape[0] for s in samples)
    c = max_contacts or max(s.contact_pairs.shape[1] for s in samples)
    shapes = {(s.object_points.shape[0], s.support_points.shape[0]) for s in samples}
    if len(shapes) != 1:
        raise ValueError(f"all samples must share (N, M) point counts, got {sorted(shapes)}")
    out = []
    for s in samples:
        poses = _pad_axis(s.stable_poses, 0, d)
        poses[s.stable_poses.shape[0] :, 3] = 1.0  # identity quaternion in padding rows
        out.append(
            HangSample(
                object_points=s.object_points,
                object_normals=s.object_normals,
                support_points=s.support_points,
                support_normals=s.support_normals,
                stable_poses=poses,
                pose_mask=_pad_axis(s.pose_mask, 0, d),
                object_contact_maps=_pad_axis(s.object_contact_maps, 0, d),
                support_contact_maps=_pad_axis(s.support_contact_maps, 0, d),
                contact_pairs=_pad_axis(_pad_axis(s.contact_pairs, 0, d), 1, c),
                contact_mask=_pad_axis(_pad_axis(s.contact_mask, 0, d), 1, c),
            )
        )
    return HangSample(
        *(np.stack(xs).astype(_DTYPES[f]) for f, xs in zip(HangSample._fields, zip(*out)))
    )


def make_hang_sample(
    object_points,
    object_normals,
    support_points,
    support_normals,
    stable_poses,
    object_contact_maps,
    support_contact_maps,
    contact_pairs: Sequence[np.ndarray] | np.ndarray,
    **_ignored,
) -> HangSample:
    """One unbatched HangSample from per-pair arrays, with masks filled in.

    contact_pairs: either [D, C, 2] (all valid) or a list of D arrays [C_d, 2] (ragged, as
    ``sim.dataset.derive_pair`` returns them), padded here to max C_d with masked rows.
    Extra keyword arguments are ignored so a ``derive_pair`` dict can be splatted in.
    """
    poses = np.asarray(stable_poses, np.float32).reshape(-1, 7)
    d = poses.shape[0]
    if isinstance(contact_pairs, np.ndarray) and contact_pairs.ndim == 3:
        ragged = list(contact_pairs)
    else:
        ragged = [np.asarray(p, np.int32).reshape(-1, 2) for p in contact_pairs]
    if len(ragged) != d:
        raise ValueError(f"{len(ragged)} contact-pair sets for {d} stable poses")
    c = max([1] + [len(p) for p in ragged])
    pairs = np.zeros((d, c, 2), np.int32)
    mask = np.zeros((d, c), bool)
    for i, p in enumerate(ragged):
        pairs[i, : len(p)] = p
        mask[i, : len(p)] = True
    sample = HangSample(
        object_points=np.asarray(object_points, np.float32),
        object_normals=np.asarray(object_normals, np.float32),
        support_points=np.asarray(support_points, np.float32),
        support_normals=np.asarray(support_normals, np.float32),
        stable_poses=poses,
        pose_mask=np.ones(d, bool),
        object_contact_maps=np.asarray(object_contact_maps, np.float32),
        support_contact_maps=np.asarray(support_contact_maps, np.float32),
        contact_pairs=pairs,
        contact_mask=mask,
    )
    validate_sample(sample)
    return sample


def unstack(batch: HangSample) -> list[HangSample]:
    """Inverse of ``stack_samples`` (padding kept)."""
    b = np.asarray(batch.object_points).shape[0]
    return [HangSample(*(np.asarray(x)[i] for x in batch)) for i in range(b)]


# ----------------------------------------------------------------------------------------------
# Synthetic ring-on-peg scenes (JAX, jittable, vmapped over the batch).


def _ring_cloud(key, n, major, minor):
    """Torus around the object z axis (angles uniform; not exactly area-uniform)."""
    ku, kv = jax.random.split(key)
    u = jax.random.uniform(ku, (n,), maxval=2 * jnp.pi)
    v = jax.random.uniform(kv, (n,), maxval=2 * jnp.pi)
    normals = jnp.stack([jnp.cos(v) * jnp.cos(u), jnp.cos(v) * jnp.sin(u), jnp.sin(v)], -1)
    centre_line = jnp.stack([major * jnp.cos(u), major * jnp.sin(u), jnp.zeros_like(u)], -1)
    return centre_line + minor * normals, normals


def _peg_cloud(key, m, radius, length, plate_half):
    """Horizontal peg along +x from a square wall plate at x = 0 (support frame)."""
    m_peg = (m * 4) // 5
    kx, kt, kp = jax.random.split(key, 3)
    x = jax.random.uniform(kx, (m_peg,), maxval=length)
    theta = jax.random.uniform(kt, (m_peg,), maxval=2 * jnp.pi)
    peg_normals = jnp.stack([jnp.zeros_like(x), jnp.cos(theta), jnp.sin(theta)], -1)
    peg = jnp.stack([x, radius * jnp.cos(theta), radius * jnp.sin(theta)], -1)
    yz = jax.random.uniform(kp, (m - m_peg, 2), minval=-plate_half, maxval=plate_half)
    plate = jnp.concatenate([jnp.zeros((m - m_peg, 1)), yz], -1)
    plate_normals = jnp.tile(jnp.array([[1.0, 0.0, 0.0]]), (m - m_peg, 1))
    return jnp.concatenate([peg, plate]), jnp.concatenate([peg_normals, plate_normals])


def _soft_map(points, contact, sigma):
    d2 = jnp.sum(jnp.square(points - contact), -1)
    w = jnp.exp(-0.5 * d2 / sigma**2)
    return w / jnp.max(w)


def synthetic_sample(
    key: jax.Array,
    n_object: int = 128,
    n_support: int = 128,
    max_poses: int = 4,
    max_contacts: int = 2,
    contact_sigma: float = 0.01,
) -> HangSample:
    """One synthetic ring-on-peg pair (unbatched HangSample of jax arrays).

    Object: a torus (major radius 3-5 cm, tube 4-7 mm) centred at its bounding-box centre.
    Support: a horizontal peg (radius 3-6 mm, length 12 cm) along +x from a wall plate.
    Stable poses (1..max_poses valid): the ring's axis along the peg, spun by a random angle
    about it (|spin| <= 90 deg), centred at x in [3, 9] cm with its inner top edge resting on the peg's top.
    One contact pair per pose (the nearest cloud points to the contact), padded to max_contacts.
    Contact maps: Gaussian of the distance to the contact point (sigma 1 cm), max-normalised
    (the real engine uses geodesic/normal weights; the shape of the signal is the same).
    """
    keys = jax.random.split(key, 8)
    major = jax.random.uniform(keys[0], minval=0.03, maxval=0.05)
    minor = jax.random.uniform(keys[1], minval=0.004, maxval=0.007)
    peg_radius = jax.random.uniform(keys[2], minval=0.003, maxval=0.006)
    object_points, object_normals = _ring_cloud(keys[3], n_object, major, minor)
    support_points, support_normals = _peg_cloud(keys[4], n_support, peg_radius, 0.12, 0.03)

    num_valid = jax.random.randint(keys[5], (), 1, max_poses + 1)
    pose_mask = jnp.arange(max_poses) < num_valid
    # The torus is symmetric about its axis; spins within +-90 deg keep the axis-angle away from
    # the pi wrap-around (the angle of Ry(90) Rz(spin) is arccos((cos(spin) - 1) / 2) <= 2.1).
    spin = jax.random.uniform(keys[6], (max_poses,), minval=-jnp.pi / 2, maxval=jnp.pi / 2)
    x_centre = jax.random.uniform(keys[7], (max_poses,), minval=0.03, maxval=0.09)
    z_centre = peg_radius - (major - minor)  # inner top of the tube touches the top of the peg
    # R = Ry(+90 deg) @ Rz(spin): object z (ring axis) -> support x (peg axis).
    ry = jnp.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    c, s = jnp.cos(spin), jnp.sin(spin)
    zeros, ones = jnp.zeros_like(c), jnp.ones_like(c)
    rz = jnp.stack(
        [
            jnp.stack([c, -s, zeros], -1),
            jnp.stack([s, c, zeros], -1),
            jnp.stack([zeros, zeros, ones], -1),
        ],
        axis=-2,
    )
    rotation = jnp.einsum("ij,djk->dik", ry, rz)  # [D, 3, 3]
    translation = jnp.stack(
        [x_centre, jnp.zeros_like(x_centre), jnp.full_like(x_centre, z_centre)], -1
    )
    wxyz = jaxlie.SO3.from_matrix(rotation).wxyz
    stable_poses = pose6_to_pose7(pose7_to_pose6(jnp.concatenate([translation, wxyz], -1)))

    contact_support = jnp.stack(
        [x_centre, jnp.zeros_like(x_centre), jnp.full_like(x_centre, peg_radius)], -1
    )
    contact_object = jnp.einsum("dji,dj->di", rotation, contact_support - translation)  # R^T(.)
    object_maps = jax.vmap(_soft_map, (None, 0, None))(object_points, contact_object, contact_sigma)
    support_maps = jax.vmap(_soft_map, (None, 0, None))(
        support_points, contact_support, contact_sigma
    )

    def nearest(pts, q):
        return jnp.argmin(jnp.sum(jnp.square(pts[None] - q[:, None]), -1), -1)

    pair = jnp.stack(
        [nearest(object_points, contact_object), nearest(support_points, contact_support)], -1
    )
    contact_pairs = jnp.zeros((max_poses, max_contacts, 2), jnp.int32).at[:, 0].set(pair)
    contact_mask = jnp.zeros((max_poses, max_contacts), bool).at[:, 0].set(True)
    contact_mask = contact_mask & pose_mask[:, None]

    return HangSample(
        object_points=object_points.astype(jnp.float32),
        object_normals=object_normals.astype(jnp.float32),
        support_points=support_points.astype(jnp.float32),
        support_normals=support_normals.astype(jnp.float32),
        stable_poses=stable_poses,
        pose_mask=pose_mask,
        object_contact_maps=object_maps.astype(jnp.float32),
        support_contact_maps=support_maps.astype(jnp.float32),
        contact_pairs=contact_pairs,
        contact_mask=contact_mask,
    )


def synthetic_batch(
    key: jax.Array,
    batch: int,
    n_points: int = 128,
    n_support: int | None = None,
    max_poses: int = 4,
    max_contacts: int = 2,
) -> HangSample:
    """A batch of ``synthetic_sample`` pairs as numpy arrays (host side, like a real loader).

    n_points: object cloud size N; n_support: support cloud size M (default N).
    """
    fn = jax.jit(
        jax.vmap(
            lambda k: synthetic_sample(k, n_points, n_support or n_points, max_poses, max_contacts)
        )
    )
    return HangSample(*(np.asarray(x) for x in fn(jax.random.split(key, batch))))


# ----------------------------------------------------------------------------------------------
# Host-side datasets for the training loop.


class HangDataset(Protocol):
    """What the training loop needs from a dataset."""

    def __len__(self) -> int: ...

    def sample_batch(self, rng: np.random.Generator, batch_size: int) -> HangSample:
        """A batch (numpy, leading B axis) drawn uniformly with replacement."""
        ...


class ArrayDataset:
    """All pairs in memory as one padded batched HangSample (synthetic pools, small sets)."""

    def __init__(self, samples: HangSample):
        self.samples = HangSample(*(np.asarray(x) for x in samples))

    def __len__(self) -> int:
        return self.samples.object_points.shape[0]

    def sample_batch(self, rng: np.random.Generator, batch_size: int) -> HangSample:
        idx = rng.integers(0, len(self), batch_size)
        return HangSample(*(x[idx] for x in self.samples))


def _load_npz_sample(path: str) -> HangSample:
    with np.load(path) as f:
        missing = [k for k in HangSample._fields if k not in f and not k.endswith("_mask")]
        if missing:
            raise ValueError(f"{path}: missing keys {missing}; expected HangSample fields")
        data = {k: f[k] for k in f.files}
    d = data["stable_poses"].shape[0]
    data.setdefault("pose_mask", np.ones(d, bool))
    data.setdefault("contact_mask", np.ones(data["contact_pairs"].shape[:2], bool))
    sample = HangSample(**{k: np.asarray(data[k], _DTYPES[k]) for k in HangSample._fields})
    validate_sample(sample, name=path)
    return sample


class NpzDirectoryDataset:
    """Pairs stored one per ``.npz`` file, read lazily per batch and padded to ``max_poses``."""

    def __init__(
        self,
        files: Sequence[str],
        max_poses: int = MAX_STABLE_POSES,
        max_contacts=None,
        cache: bool = False,
    ):
        self.files = list(files)
        self.max_poses = max_poses
        # cache=True keeps every pair read so far in memory (decompressing .npz files was
        # the GPU's bottleneck: ~2 MB per paper-scale pair, 32 per step)
        self._cache: dict[int, HangSample] | None = {} if cache else None
        # C over ALL files: a batch with more contacts than this changes the padded shape and
        # recompiles the jitted step (seconds each; it made the demo's Stage-2 runs crawl).
        self.max_contacts = max_contacts or _max_contacts(self.files)

    def __len__(self) -> int:
        return len(self.files)

    def sample_batch(self, rng: np.random.Generator, batch_size: int) -> HangSample:
        idx = rng.integers(0, len(self), batch_size)
        samples = [self._sample(int(i)) for i in idx]
        c = max(self.max_contacts, *(s.contact_pairs.shape[1] for s in samples))
        return stack_samples(samples, self.max_poses, c)

    def _sample(self, i: int) -> HangSample:
        if self._cache is None:
            return _load_npz_sample(self.files[i])
        if i not in self._cache:
            self._cache[i] = _load_npz_sample(self.files[i])
        return self._cache[i]


class DeviceDataset:
    """All pairs padded once into device-resident arrays; batches are gathered on the device.

    Same batches as :class:`NpzDirectoryDataset` for the same ``rng`` (same indices, same
    padding), without re-stacking ~50 MB of clouds and contact maps on the host every step,
    which bound GPU training at ~75 ms per step (docs/benchmarks.md). Memory: ~1.8 MB per
    paper-scale pair (4096-point clouds, 50 maps), e.g. ~29 GB for 16k pairs on an 80 GB GPU.
    ``sample_batch`` returns a HangSample of jax arrays.
    """

    def __init__(self, files: Sequence[str], max_poses: int = MAX_STABLE_POSES, max_contacts=None):
        import jax

        self.files = list(files)
        c = max_contacts or _max_contacts(self.files)
        first = stack_samples([_load_npz_sample(self.files[0])], max_poses, c)
        host = {
            f: np.empty((len(self.files), *x.shape[1:]), x.dtype)
            for f, x in first._asdict().items()
        }
        for i, path in enumerate(self.files):
            one = stack_samples([_load_npz_sample(path)], max_poses, c)
            for f, x in one._asdict().items():
                if x.shape[1:] != host[f].shape[1:]:
                    raise ValueError(
                        f"{path}: {f} has shape {x.shape[1:]}, expected {host[f].shape[1:]}"
                    )
                host[f][i] = x[0]
        self.samples = HangSample(**{f: jax.device_put(x) for f, x in host.items()})

    def __len__(self) -> int:
        return len(self.files)

    def sample_batch(self, rng: np.random.Generator, batch_size: int) -> HangSample:
        import jax.numpy as jnp

        idx = jnp.asarray(rng.integers(0, len(self), batch_size))
        return HangSample(*(x[idx] for x in self.samples))


def _max_contacts(files: Sequence[str]) -> int:
    c = 1
    for path in files:
        with np.load(path) as f:
            c = max(c, f["contact_pairs"].shape[1])
    return c


def load_hang_dataset(
    directory: str | os.PathLike,
    split: str = "train",
    max_poses: int = MAX_STABLE_POSES,
    cache: bool = False,
    on_device: bool = False,
) -> NpzDirectoryDataset | DeviceDataset:
    """Loader hook for the dataset engine's output.

    Expected layout: ``<directory>/<split>/*.npz`` (or ``<directory>/*.npz``, or
    ``<directory>/derived/<split>/*.npz`` for a generated dataset derived by
    ``experiments.derive_dataset``), one file per
    (object, support) pair, keys = ``HangSample`` field names, unbatched (see module docstring).
    Raises FileNotFoundError with the expected layout when no such file exists, ValueError
    when a file breaks the contract (checked per file when it is read).
    """
    directory = os.fspath(directory)
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"dataset directory {directory!r} does not exist")
    files = sorted(glob.glob(os.path.join(directory, split, "*.npz")))
    files = files or sorted(glob.glob(os.path.join(directory, "*.npz")))
    # A generated dataset whose pairs were derived (experiments.derive_dataset) into DIR/derived.
    files = files or sorted(glob.glob(os.path.join(directory, "derived", split, "*.npz")))
    if not files and os.path.exists(os.path.join(directory, "recipe.json")):
        raise FileNotFoundError(
            f"{directory!r} holds dataset-engine labels (recipe.json + shards/) but no per-pair "
            f"{split!r} files yet: run `python -m experiments.derive_dataset --data {directory}` "
            f"(writes {directory}/derived/{split}/*.npz), or derive each pair's clouds/maps/contacts "
            f"(sim.dataset.derive_pair), build a HangSample with "
            f"omnihang_jax.data.make_hang_sample(**derived, stable_poses=...), and save it "
            f"with np.savez(<dir>/{split}/<pair>.npz, **sample._asdict())."
        )
    if not files:
        raise FileNotFoundError(
            f"no pair files in {directory!r}: expected {directory}/{split}/*.npz (or "
            f"{directory}/*.npz), one .npz per (object, support) pair with keys "
            f"{', '.join(HangSample._fields)} (see omnihang_jax.data.HangSample). "
            "Use --data synthetic for a dry run."
        )
    if on_device:
        return DeviceDataset(files, max_poses=max_poses)
    return NpzDirectoryDataset(files, max_poses=max_poses, cache=cache)


# ----------------------------------------------------------------------------------------------
# Validation split by OBJECT, and a compact packed copy of a derived split for the GPU.


def validation_objects(names, fraction: float) -> set[str]:
    """A fixed subset of object names (by a hash of the name, independent of order): the
    validation objects of every trainer (Stages 1-3 share it)."""

    def h(n):
        return int(hashlib.sha1(n.encode()).hexdigest()[:8], 16) / 0xFFFFFFFF

    return {n for n in names if h(n) < fraction}


def object_name_of(path: str) -> str:
    """Object name of a derived pair file ``<index>_<object>__<support>.npz``; for other
    names the file's stem (each such file then counts as its own object)."""
    stem = os.path.basename(path).split("__")[0]
    index, sep, name = stem.partition("_")
    if "__" not in os.path.basename(path) or not index.isdigit() or not name:
        return os.path.splitext(os.path.basename(path))[0]
    return name


def split_by_object(names: Sequence[str], fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """(fit indices, validation indices) of a list of per-pair object names."""
    val = validation_objects(sorted(set(names)), fraction)
    is_val = np.array([n in val for n in names], bool)
    return np.flatnonzero(~is_val), np.flatnonzero(is_val)


# Packed dtypes: contact maps in [0, 1] as uint8 (1/255 steps), normals float16, contact
# indices int16 (clouds have < 32768 points); points and poses stay float32 (metres).
_PACKED = {
    "object_points": np.float32,
    "object_normals": np.float16,
    "support_points": np.float32,
    "support_normals": np.float16,
    "stable_poses": np.float32,
    "pose_mask": np.bool_,
    "object_contact_maps": np.uint8,
    "support_contact_maps": np.uint8,
    "contact_pairs": np.int16,
    "contact_mask": np.bool_,
}
PACK_FILE = "pack.json"


def pack_dataset(
    files: Sequence[str],
    out: str | os.PathLike,
    max_poses: int = MAX_STABLE_POSES,
    threads: int = 8,
    progress: bool = True,
) -> dict:
    """Write the pairs of ``files`` into one padded array per field under ``out`` (``.npy``,
    memory-mappable) + ``pack.json`` (files, object names, shapes): ~0.55 MB per
    paper-scale pair instead of ~1.8 MB, loaded in seconds by :class:`PackedDataset`.

    Files that break the contract are skipped and listed in ``pack.json["skipped"]``
    (with the reason), so one bad pair does not lose the pack. Returns the pack.json dict.
    """
    from tqdm.auto import tqdm

    out = os.fspath(out)
    os.makedirs(out, exist_ok=True)
    files = list(files)
    if not files:
        raise ValueError("pack_dataset: no files given")
    c, first_ok, has_maps = 1, None, True
    for path in files:  # largest C over the readable files; a broken file is skipped later
        try:
            with np.load(path) as f:
                c = max(c, f["contact_pairs"].shape[1])
                has_maps = has_maps and bool(f["contact_maps"]) if "contact_maps" in f else has_maps
            first_ok = first_ok or path
        except (ValueError, OSError, KeyError, EOFError):
            continue
    if first_ok is None:
        raise ValueError(f"pack_dataset: none of the {len(files)} files is a readable pair file")
    first = stack_samples([_load_npz_sample(first_ok)], max_poses, c)
    arrays = {
        f: np.lib.format.open_memmap(
            os.path.join(out, f"{f}.npy"), "w+", _PACKED[f], (len(files), *x.shape[1:])
        )
        for f, x in first._asdict().items()
    }
    ok = np.zeros(len(files), bool)
    skipped = {}

    def load(i):
        try:
            return i, stack_samples([_load_npz_sample(files[i])], max_poses, c), None
        except (ValueError, OSError, KeyError, EOFError) as e:
            return i, None, f"{type(e).__name__}: {e}"

    with ThreadPoolExecutor(threads) as pool:
        for i, one, err in tqdm(
            pool.map(load, range(len(files))), total=len(files), desc="pack", disable=not progress
        ):
            if one is None:
                skipped[os.path.basename(files[i])] = err
                continue
            for f, x in one._asdict().items():
                if x.shape[1:] != arrays[f].shape[1:]:
                    skipped[os.path.basename(files[i])] = f"{f} shape {x.shape[1:]}"
                    break
            else:
                for f, x in one._asdict().items():
                    if _PACKED[f] is np.uint8:
                        x = np.round(np.clip(x, 0.0, 1.0) * 255.0)
                    arrays[f][i] = x[0]
                ok[i] = True
    for a in arrays.values():
        a.flush()
    meta = {
        "files": [os.path.basename(f) for f in files],
        "object_names": [object_name_of(f) for f in files],
        "valid": ok.tolist(),
        "skipped": skipped,
        "max_poses": max_poses,
        "max_contacts": c,
        # False when any pair was derived with --clouds-only (zero maps: not for Stage 2)
        "has_contact_maps": has_maps,
        "dtypes": {f: np.dtype(t).name for f, t in _PACKED.items()},
    }
    with open(os.path.join(out, PACK_FILE), "w") as f:
        json.dump(meta, f)
    return meta


class PackedDataset:
    """A :func:`pack_dataset` folder (or a subset of its pairs) in device memory.

    indices: pairs to use (default all valid ones). fields: the HangSample fields to put on
    the device (default all); the others come back as zeros of shape [B, 1] (e.g. Stage 1
    needs only clouds and stable poses: ~0.1 MB per pair instead of ~0.55 MB).
    ``sample_batch`` gathers on the device and restores float32 / int32.
    """

    def __init__(self, pack_dir: str | os.PathLike, indices=None, fields=None):
        pack_dir = os.fspath(pack_dir)
        with open(os.path.join(pack_dir, PACK_FILE)) as f:
            self.meta = json.load(f)
        valid = np.asarray(self.meta["valid"], bool)
        idx = np.flatnonzero(valid) if indices is None else np.asarray(indices, np.int64)
        self.indices = idx[valid[idx]]
        self.object_names = [self.meta["object_names"][i] for i in self.indices]
        self.fields = tuple(HangSample._fields if fields is None else fields)
        self.arrays = {
            f: jax.device_put(np.load(os.path.join(pack_dir, f"{f}.npy"), mmap_mode="r")[self.indices])
            for f in self.fields
        }  # fmt: skip

    def __len__(self) -> int:
        return len(self.indices)

    def sample_batch(self, rng: np.random.Generator, batch_size: int) -> HangSample:
        idx = jnp.asarray(rng.integers(0, len(self), batch_size))
        out = {}
        for f in HangSample._fields:
            if f not in self.arrays:
                out[f] = jnp.zeros((batch_size, 1), _DTYPES[f])
                continue
            x = self.arrays[f][idx]
            if x.dtype == jnp.uint8:
                x = x.astype(jnp.float32) / 255.0
            out[f] = x.astype(_DTYPES[f])
        return HangSample(**out)
