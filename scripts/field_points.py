"""The distance field's object points for the forty-eighth session's probe pairs (issue 12, s49).

``scripts/probe_true_surface.py --points`` reads, per pair, the object points a model put on the
object's hidden side. The field's extraction (``omnihang_jax.distance_field.extract``) is a few
hundred thousand network queries per pair: seconds on these CPUs, milliseconds on the GPU. So:

    python scripts/field_points.py pack --out out/s49/probe_inputs.npz          # here (seconds)
    python scripts/field_points.py extract --field weights/field_s49 \\
        --inputs out/s49/probe_inputs.npz --out $OUT/field_points               # the device
    python scripts/probe_true_surface.py --points field=out/s49/field_points --out ...

``pack``: every probe pair's network input, the SAME subset of its observed object points the
probe gives the completion networks (``n_input`` points, ``np.random.default_rng(0).choice``),
as float16 (13 MB for the 2,139 pairs). ``extract``: the field's points per pair, those within
``--new`` of the input points dropped (the probe drops those within ``--new`` of every observed
point again), at most ``--max-points``, written in parts of at most ``--part-mb`` (the device
returns files of at most 16 MiB): ``OUT.partNN.npz`` with ``pair`` [P], ``offsets`` [P + 1],
``points`` [M, 3] float16 (and ``upper`` [M]: each point's upper quantile, for a field of two;
``--points NAME=PREFIX:MM`` keeps those below MM millimetres).
"""

from __future__ import annotations

import argparse
import glob
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def probe_rows(keys: int = 3, heldout_keys: int = 3) -> list[dict]:
    """One row per distinct pair of the probe's validation and held-out records."""
    from probe_symmetry import HELDOUT, VALIDATION

    from experiments.rerank_stage3 import read_records

    rows: dict[int, dict] = {}
    for runs in (VALIDATION[:keys], HELDOUT[:heldout_keys]):
        for r in read_records(runs[0][0]):
            rows.setdefault(int(r["pair_index"]), r)
    return [rows[i] for i in sorted(rows)]


def network_input(obs: np.ndarray, n_input: int) -> np.ndarray:
    """The probe's input subset of one pair's observed object points (as for the completions)."""
    pick = np.random.default_rng(0).choice(len(obs), n_input, replace=len(obs) < n_input)
    return np.asarray(obs, np.float32)[pick]


def pack(args) -> None:
    from tqdm.auto import tqdm

    from experiments.rerank_completed import load_clouds

    rows = probe_rows()
    clouds = [network_input(load_clouds(Path(args.data), r)["object_points"], args.n_input)
              for r in tqdm(rows, desc="pack")]  # fmt: skip
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, pair=np.asarray([int(r["pair_index"]) for r in rows]),
                        clouds=np.stack(clouds).astype(np.float16))  # fmt: skip
    print(f"{args.out}: {len(rows)} pairs", flush=True)


def load_points(prefix: str, upper_max: float | None = None) -> dict[int, np.ndarray]:
    """pair index -> [M, 3] float32 points of ``PREFIX.partNN.npz`` (as ``extract`` writes);
    with ``upper_max`` (m) only those whose upper quantile lies below it (the field is sure)."""
    files = sorted(glob.glob(f"{prefix}.part*.npz"))
    if not files:
        raise FileNotFoundError(f"no {prefix}.partNN.npz: run `field_points.py extract` first")
    out = {}
    for f in files:
        with np.load(f) as z:
            o, p = z["offsets"], z["points"].astype(np.float32)
            if upper_max is None:
                keep = np.ones(len(p), bool)
            elif "upper" in z:
                keep = z["upper"].astype(np.float32) < upper_max
            else:
                raise ValueError(f"{f}: no upper quantile stored (a field of one quantile)")
            out.update({int(i): p[o[j] : o[j + 1]][keep[o[j] : o[j + 1]]]
                        for j, i in enumerate(z["pair"])})  # fmt: skip
    return out


def extract(args) -> None:
    from scipy.spatial import cKDTree
    from tqdm.auto import tqdm

    from omnihang_jax import distance_field

    cfg, params, _ = distance_field.load_field(args.field)
    with np.load(args.inputs) as z:
        pairs, clouds = z["pair"], z["clouds"].astype(np.float32)
    stop = len(pairs) if args.stop is None else args.stop
    pairs, clouds = pairs[args.start : stop], clouds[args.start : stop]
    if clouds.shape[1] != cfg.n_input:
        raise ValueError(
            f"{args.inputs}: {clouds.shape[1]} points per cloud, the field takes {cfg.n_input}"
        )
    t0, part, buf, size = time.time(), args.first_part, [], 0
    upper = len(cfg.quantiles) > 1  # store each point's upper quantile too
    kw = dict(step=args.step, levels=args.levels, per_cell=args.per_cell, final=args.final,
              max_points=1 << 30, chunk=args.chunk, with_upper=upper)  # fmt: skip

    def flush():
        nonlocal part, buf, size
        if not buf:
            return
        pts = [b[1] for b in buf]
        offsets = np.concatenate([[0], np.cumsum([len(p) for p in pts])])
        extra = {"upper": np.concatenate([b[2] for b in buf]).astype(np.float16)} if upper else {}
        np.savez(f"{args.out}.part{part:02d}.npz", pair=np.asarray([b[0] for b in buf]),
                 offsets=offsets, points=np.concatenate(pts).astype(np.float16), **extra)  # fmt: skip
        part, buf, size = part + 1, [], 0

    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    kept = []
    for i, cloud in zip(
        tqdm(pairs, desc="field points", disable=args.no_progress), clouds, strict=True
    ):
        got = distance_field.extract(params, cfg, cloud, seed=int(i), **kw)
        p, u = got if upper else (got, np.zeros(len(got), np.float32))
        if len(p):
            far = cKDTree(cloud).query(p, k=1)[0] > args.new
            p, u = p[far], u[far]
        if len(p) > args.max_points:
            pick = np.sort(
                np.random.default_rng(int(i)).choice(len(p), args.max_points, replace=False)
            )
            p, u = p[pick], u[pick]
        kept.append(len(p))
        nbytes = p.nbytes // 2 + (u.nbytes // 2 if upper else 0)
        if size + nbytes > args.part_mb * 2**20:
            flush()
        buf.append((int(i), p, u))
        size += nbytes
    flush()
    print(f"{len(pairs)} pairs, parts up to {part - 1}, points per pair: median {np.median(kept):.0f}, "
          f"min {min(kept)}, {time.time() - t0:.0f} s", flush=True)  # fmt: skip


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])  # fmt: skip
    sub = ap.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("pack", help="the probe pairs' network inputs")
    a.add_argument("--data", default="datasets/paper")
    a.add_argument("--n-input", type=int, default=1024)
    a.add_argument("--out", required=True)
    b = sub.add_parser("extract", help="the field's points of every packed pair")
    b.add_argument("--field", required=True, help="a folder of distance_field.save_field")
    b.add_argument("--inputs", required=True)
    b.add_argument("--out", required=True, help="prefix of the parts")
    b.add_argument("--new", type=float, default=0.003, help="m: points nearer the input dropped")
    b.add_argument("--max-points", type=int, default=4096)
    b.add_argument("--step", type=float, default=0.008, help="m: the coarse grid")
    b.add_argument("--levels", type=int, default=2)
    b.add_argument("--per-cell", type=int, default=2)
    b.add_argument("--final", type=float, default=0.0015, help="m: points kept below this")
    b.add_argument("--chunk", type=int, default=32768, help="queries per network call")
    b.add_argument("--part-mb", type=float, default=14.0)
    b.add_argument("--start", type=int, default=0, help="the packed pairs from this index ...")
    b.add_argument("--stop", type=int, default=None, help="... to this one (a killed run's rest)")
    b.add_argument("--first-part", type=int, default=0, help="the first part's number")
    b.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    pack(args) if args.cmd == "pack" else extract(args)


if __name__ == "__main__":
    main()
