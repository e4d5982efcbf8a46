"""Per-category hanging success against the paper's table, one panel per stage.

    python -m experiments.success_figure                      # results/hanging_success.json
    python -m experiments.success_figure --results R.json --out out/R_categories.png   # + out/R_categories.json

Reads the four rows of a held-out evaluation (``stage1``, ``stage1_2``, ``stage1_3``,
``all_stages``: each with ``mean`` and ``per_category``, as ``eval_stage3`` and
``results/hanging_success.json`` write them) and draws, per stage, our success per object
category and the mean over categories beside the paper's (its hanging-success table). The
table also goes to JSON: ``results/success_categories.json`` for the default figure, else
beside ``--out`` (``--json`` to choose). Nothing is computed here but the plot.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from experiments import _cli

STAGES = ("stage1", "stage1_2", "stage1_3", "all_stages")
DEFAULT_OUT = "docs/img/success_categories.png"
TITLES = {"stage1": "Stage 1", "stage1_2": "Stages 1+2", "stage1_3": "Stages 1+3",
          "all_stages": "All stages"}  # fmt: skip
CATEGORIES = ("bag", "cap", "clothes_hanger", "cooking_utensil", "headphone", "knife", "mug",
              "others", "racquet", "scissors", "wrench")  # fmt: skip
# The paper's hanging-success table ("Hanging pose prediction accuracy"), per stage: mean and
# per category (its Hanger = clothes_hanger, Utensil = cooking_utensil)
PAPER = {
    "stage1": (36.0, dict(bag=50.0, cap=58.5, clothes_hanger=44.0, cooking_utensil=17.7,
                          headphone=41.2, knife=26.0, mug=30.3, racquet=28.7, scissors=22.5,
                          wrench=21.5, others=30.7)),
    "stage1_2": (34.2, dict(bag=47.4, cap=55.7, clothes_hanger=56.0, cooking_utensil=20.1,
                            headphone=30.2, knife=30.8, mug=20.7, racquet=27.6, scissors=22.1,
                            wrench=27.9, others=30.0)),
    "stage1_3": (56.2, dict(bag=63.6, cap=60.8, clothes_hanger=69.1, cooking_utensil=37.8,
                            headphone=60.9, knife=46.2, mug=44.4, racquet=44.8, scissors=55.4,
                            wrench=41.9, others=58.1)),
    "all_stages": (68.3, dict(bag=78.3, cap=60.2, clothes_hanger=72.2, cooking_utensil=45.1,
                              headphone=80.5, knife=49.0, mug=61.9, racquet=49.4, scissors=66.2,
                              wrench=55.2, others=71.5)),
}  # fmt: skip


def table(results: dict) -> dict:
    """{stage: {"ours": {"mean", "per_category"}, "paper": {...}}} for the stages present."""
    out = {}
    for stage in STAGES:
        row = results.get(stage)
        if not isinstance(row, dict) or "per_category" not in row or "mean" not in row:
            continue
        missing = [c for c in CATEGORIES if c not in row["per_category"]]
        if missing:
            raise ValueError(f"{stage}: no per-category success for {missing}")
        mean, cats = PAPER[stage]
        out[stage] = {
            "ours": {"mean": float(row["mean"]),
                     "per_category": {c: float(row["per_category"][c]) for c in CATEGORIES}},
            "paper": {"mean": mean, "per_category": dict(cats)},
        }  # fmt: skip
        if row.get("answer"):  # the results' own words for how the stage's answer is chosen
            out[stage]["answer"] = str(row["answer"])
    if not out:
        raise ValueError(f"none of {STAGES} with 'mean' and 'per_category' in the results")
    return out


def draw(rows: dict, out: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [*CATEGORIES, "MEAN"]
    x = np.arange(len(labels))
    fig, axes = plt.subplots(len(rows), 1, figsize=(11, 2.4 * len(rows)), sharex=True,
                             squeeze=False)  # fmt: skip
    for ax, (stage, row) in zip(axes[:, 0], rows.items(), strict=True):
        ours = [row["ours"]["per_category"][c] for c in CATEGORIES] + [row["ours"]["mean"]]
        paper = [row["paper"]["per_category"][c] for c in CATEGORIES] + [row["paper"]["mean"]]
        ax.bar(x - 0.2, ours, 0.4, label="ours", color="tab:blue")
        ax.bar(x + 0.2, paper, 0.4, label="paper", color="tab:gray")
        for xi, v in zip(x, ours, strict=True):
            ax.text(xi - 0.2, v + 1, f"{v:.0f}", ha="center", fontsize=7)
        ax.set_ylim(0, 105)
        ax.set_ylabel("success %")
        name = TITLES[stage] + (f" (answer: {row['answer']})" if "answer" in row else "")
        ax.set_title(f"{name}: ours {row['ours']['mean']:.1f} vs paper "
                     f"{row['paper']['mean']:.1f}", fontsize=10)  # fmt: skip
        ax.axvline(len(CATEGORIES) - 0.5, color="k", lw=0.5)
        ax.grid(axis="y", alpha=0.3)
    axes[0, 0].legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xticks(x, [c.replace("_", "\n") for c in labels], fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--results", default="results/hanging_success.json")
    parser.add_argument("--out", default=DEFAULT_OUT, help="PNG")
    parser.add_argument(
        "--json",
        default=None,
        help="the table as JSON (default: results/success_categories.json for the default "
        "--out, else OUT with .json)",
    )
    args = parser.parse_args(argv)
    path = Path(args.results)
    if not path.exists():
        parser.error(f"{path}: no such results file (python -m experiments.eval_stage3 writes one)")
    results = json.loads(path.read_text())
    rows = table(results)
    n = results.get("pairs") or (results.get("all_stages") or {}).get("pairs")
    draw(rows, Path(args.out), f"held-out hanging success per category ({path.name}"
         + (f", {n} pairs)" if n else ")"))  # fmt: skip
    record = {"results": str(path), "figure": args.out, "stages": rows}
    if args.json:
        jpath = Path(args.json)
    elif args.out == DEFAULT_OUT:
        jpath = Path("results/success_categories.json")
    else:
        jpath = Path(args.out).with_suffix(".json")
    jpath.parent.mkdir(parents=True, exist_ok=True)
    jpath.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {args.out} and {jpath}: "
          + ", ".join(f"{TITLES[s]} {r['ours']['mean']:.1f} (paper {r['paper']['mean']:.1f})"
                      for s, r in rows.items()))  # fmt: skip
    return record


if __name__ == "__main__":
    _cli.run(main)
