"""Export one stable pose of a generated dataset as OBJ meshes + a JSON pose, so other engines
and tools can check it.

    python -m experiments.export_sample --data datasets/paper --pair 231 --pose 0 --out /tmp/s
    python -m experiments.export_sample --data datasets/paper --list 5     # pairs with poses

Writes ``OUT/object.obj`` (object frame), ``OUT/support.obj`` (support frame = world) and
``OUT/pose.json``: the 4x4 matrix, position and quaternion in both orders, with the
convention ``p_support = T @ p_object`` (metres), the wall plane and the floor height
(``sim.dataset_io.export_sample``). The library is rebuilt from the dataset's recipe.
"""

from __future__ import annotations

import argparse
import json

from experiments import _cli
from omnihang_jax import dataset_bridge
from sim import dataset, dataset_io


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", required=True, help="generated dataset (recipe.json + shards/)")
    parser.add_argument("--pair", type=int, default=None, help="pair index (recipe pair list)")
    parser.add_argument("--pose", type=int, default=0, help="which stable pose of the pair")
    parser.add_argument("--out", default=None, help="output folder")
    parser.add_argument(
        "--list", type=int, default=None, metavar="N", help="print the first N pairs with poses"
    )
    args = parser.parse_args(argv)
    recipe = dataset_bridge.read_recipe(args.data)
    records = {int(r["pair_index"]): r for r in dataset.load_records(args.data)}
    with_poses = sorted(i for i, r in records.items() if len(r["stable_poses"]))
    if args.list is not None:
        rows = [
            {"pair": i, "pair_names": recipe["pairs"][i], "poses": len(records[i]["stable_poses"])}
            for i in with_poses[: args.list]
        ]
        for row in rows:
            print(json.dumps(row))
        return {"pairs": rows}
    if args.pair is None or args.out is None:
        parser.error("--pair and --out are required (or --list N)")
    if args.pair not in records:
        parser.error(
            f"pair {args.pair} is not in the shards present ({len(records)} pairs generated; "
            f"first with poses: {with_poses[:5]})"
        )
    record = records[args.pair]
    n = len(record["stable_poses"])
    if not 0 <= args.pose < n:
        parser.error(f"pair {args.pair} has {n} stable poses; --pose must be in [0, {n})")
    from sim.library import build_library

    config = dataset_bridge.dataset_config_from_recipe(recipe)
    library = build_library(config.library, progress=False)
    out = dataset_io.export_sample(library, record, recipe["pairs"], args.out, args.pose)
    meta = json.loads((out / "pose.json").read_text())
    print(f"wrote {out}/object.obj, support.obj, pose.json ({meta['object']} on {meta['support']})")
    return meta


if __name__ == "__main__":
    _cli.run(main)
