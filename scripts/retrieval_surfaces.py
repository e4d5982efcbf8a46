"""The retrieval base of `scripts/probe_retrieval.py` (forty-sixth session): the whole outer
surface (``sim.camera.surface_cloud``, the completion networks' target) of every training object
that is not a validation object (`omnihang_jax.data.validation_objects`, 10 % by name), in its
own object frame, as one ``.npz`` (names, surfaces [M, 2048, 3]). CPU, ~5 min on 2 cores.

    python scripts/retrieval_surfaces.py --out out/s46/surfaces.npz
"""

from __future__ import annotations

import argparse
import dataclasses
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

_W: dict = {}


def _init(data: str, n_dirs: int) -> None:
    from omnihang_jax import dataset_bridge
    from sim.library import build_library

    cfg = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(data))
    _W.update(library=build_library(cfg.library, progress=False), camera=cfg.camera, n_dirs=n_dirs)


def surface(name: str) -> np.ndarray:
    from sim import camera
    from sim.scene import build_scene

    lib, cam = _W["library"], _W["camera"]
    scene = build_scene(lib.objects[name], next(iter(lib.supports.values())))
    coarse = dataclasses.replace(cam, width=cam.width // 2, height=cam.height // 2)
    rng = np.random.default_rng([0, *name.encode()])
    return camera.surface_cloud(scene, "object", rng, coarse, n_dirs=_W["n_dirs"]).astype(
        np.float32
    )


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--n-dirs", type=int, default=20, help="cameras over the sphere")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    from omnihang_jax.data import validation_objects

    _init(args.data, args.n_dirs)
    train = sorted(_W["library"].split["train"]["objects"])
    val = validation_objects(train, 0.1)
    names = [n for n in train if n not in val]
    print(f"{len(names)} training objects ({len(val)} validation objects left out)", flush=True)
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(args.workers, ctx, initializer=_init,
                             initargs=(args.data, args.n_dirs)) as ex:  # fmt: skip
        surfaces = list(tqdm(ex.map(surface, names), total=len(names), desc="surfaces"))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, names=np.asarray(names), surfaces=np.stack(surfaces))


if __name__ == "__main__":
    main()
