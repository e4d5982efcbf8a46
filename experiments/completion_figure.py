"""A picture of shape completion on held-out pairs: each body's observed cloud and the points the
completion networks add (experiments.train_completion), object and support side by side.

    python -m experiments.completion_figure --completion weights/completion_s25 \\
        --out docs/img/completion.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from omnihang_jax import completion


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--completion", default="weights/completion_s25", help="networks' folder")
    ap.add_argument("--data", default="datasets/paper", help="dataset (its derived held-out pairs)")
    ap.add_argument("--pairs", type=int, default=3, help="pairs shown (rows)")
    ap.add_argument("--out", default="docs/img/completion.png")
    args = ap.parse_args(argv)
    files = sorted(Path(args.data, "derived", "collision", "test").glob("*.npz"))
    if not files:
        raise FileNotFoundError(
            f"no held-out pairs in {args.data}/derived/collision/test: run experiments.eval_paths "
            "(or experiments.train_collision) once to derive them"
        )
    # spread over categories: every k-th file
    picks = files[:: max(1, len(files) // args.pairs)][: args.pairs]
    nets = completion.load_nets(args.completion)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(9, 4.2 * len(picks)))
    for row, path in enumerate(picks):
        with np.load(path) as f:
            obs = {"object": f["object_points"], "support": f["support_points"]}
            name = path.stem
        pred = dict(
            zip(completion.KINDS, completion.predict_points(nets, obs["object"], obs["support"]))
        )
        for col, kind in enumerate(completion.KINDS):
            ax = fig.add_subplot(len(picks), 2, 2 * row + col + 1, projection="3d")
            o = obs[kind][:: max(1, len(obs[kind]) // 1500)]
            ax.scatter(*o.T, s=1, c="0.45", label="observed")
            ax.scatter(*pred[kind].T, s=1, c="tab:orange", alpha=0.6, label="added by completion")
            allp = np.concatenate([obs[kind], pred[kind]])
            c, r = allp.mean(0), np.abs(allp - allp.mean(0)).max()
            ax.set(xlim=(c[0] - r, c[0] + r), ylim=(c[1] - r, c[1] + r), zlim=(c[2] - r, c[2] + r))
            ax.set_title(f"{name.split('_', 1)[1]}\n{kind}", fontsize=8)
            ax.tick_params(labelsize=5)
            if row == 0 and col == 0:
                ax.legend(fontsize=7, markerscale=6, loc="upper left")
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    plt.close(fig)
    print(f"wrote {args.out}")
    return args.out


if __name__ == "__main__":
    from experiments import _cli

    _cli.run(main)
