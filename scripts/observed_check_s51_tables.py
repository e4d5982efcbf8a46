"""The fifty-first session's tables: results/observed_check_s51/{validation_sweep,summary}.json
from the ``experiments.observed_check --out`` files of the sweep (out/s51/, see docs/stage3.md,
"Fifty-first session", for the commands), and the per-key files copied beside them.

    python scripts/observed_check_s51_tables.py
"""

import json
import os
import shutil

import numpy as np

R = "results/observed_check_s51"
os.makedirs(R, exist_ok=True)
held = [json.load(open(f"out/s51/held_k{k}_r0.004_ext60.json")) for k in range(3)]
val = [json.load(open(f"out/s51/val_k{k}_r0.004_ext60.json")) for k in range(3)]
for k in range(3):
    shutil.copy(f"out/s51/held_k{k}_r0.004_ext60.json", f"{R}/heldout_k{k}.json")
    shutil.copy(f"out/s51/val_k{k}_r0.004_ext60.json", f"{R}/validation_k{k}.json")


def agg(runs, rule):
    per_key = [r["rules"][rule]["mean"] for r in runs]
    cats = runs[0]["rules"][rule]["per_category"]
    per_cat = {c: float(np.mean([r["rules"][rule]["per_category"][c] for r in runs])) for c in cats}
    return dict(
        mean=float(np.mean(per_key)),
        std_over_keys=float(np.std(per_key)),
        per_key=per_key,
        per_category=per_cat,
        pair_mean=float(np.mean([r["rules"][rule]["pair_mean"] for r in runs])),
    )


summary = {}
for rule in held[0]["rules"]:
    summary[rule] = dict(heldout=agg(held, rule), validation=agg(val, rule))
json.dump(summary, open(f"{R}/summary.json", "w"), indent=1)
for rule, s in summary.items():
    h, v = s["heldout"], s["validation"]
    print(
        f"{rule:>15}: validation {v['mean']:.2f} ({' / '.join(f'{x:.2f}' for x in v['per_key'])}), held out {h['mean']:.2f} +- {h['std_over_keys']:.2f} ({' / '.join(f'{x:.2f}' for x in h['per_key'])})"
    )
print(json.dumps(summary["first_of_60"]["heldout"]["per_category"], indent=0))
print(json.dumps(summary["default"]["heldout"]["per_category"], indent=0))

V = {
    "r 2 mm": ["out/s51/val_r2.json", "out/s51/val_k1_r0.002.json", "out/s51/val_k2_r0.002.json"],
    "r 3 mm": [
        "out/s51/val_radius0.003.json",
        "out/s51/val_k1_r0.003.json",
        "out/s51/val_k2_r0.003.json",
    ],
    "r 3 mm, evaluation protocol (1 s, 3 mm)": [
        f"out/s51/val_k{k}_r0.003_eval.json" for k in range(3)
    ],
    "r 4 mm (chosen)": [f"out/s51/val_k{k}_r0.004.json" for k in range(3)],
    "r 5 mm": [f"out/s51/val_k{k}_r0.005.json" for k in range(3)],
    "r 1.5 mm (key 0 only)": ["out/s51/val_radius0.0015.json"],
    "r 2 mm, voxel 3 mm (key 0 only)": ["out/s51/val_voxel0.003.json"],
    "r 2 mm, voxel 1.5 mm (key 0 only)": ["out/s51/val_voxel0.0015.json"],
    "r 4 mm, > 3 mm initial penetration fails (2 s)": [
        f"out/s51/val_k{k}_r0.004_p3.json" for k in range(3)
    ],
    "r 4 mm, no wall, no floor (clouds only)": [
        f"out/s51/val_k{k}_r0.004_clouds.json" for k in range(3)
    ],
}
out = {}
for name, files in V.items():
    files = [f for f in files if os.path.exists(f)]
    if not files:
        continue
    rs = [json.load(open(f)) for f in files]
    row = {}
    for rule in rs[0]["rules"]:
        vals = [r["rules"][rule]["mean"] for r in rs]
        row[rule] = dict(per_key=[round(v, 2) for v in vals], mean=round(sum(vals) / len(vals), 2))
    out[name] = dict(
        files=files,
        keys=[r["key"] for r in rs],
        config=rs[0]["config"],
        rules=row,
        confusion_key0=rs[0]["confusion"],
    )
json.dump(out, open("results/observed_check_s51/validation_sweep.json", "w"), indent=1)


def cell(r: dict, k: str) -> str:
    v = r[k]
    if len(v["per_key"]) > 1:
        return " / ".join(f"{x:.2f}" for x in v["per_key"]) + f" (**{v['mean']:.2f}**)"
    return f"{v['mean']:.2f}"


print("| variant | default | first of 2 | 3 | 5 | **8** | 10 |")
print("| --- | --- | --- | --- | --- | --- | --- |")
for name, o in out.items():
    r = o["rules"]
    cols = [f"{r[k]['mean']:.2f}" for k in ("default", "first_of_2", "first_of_3", "first_of_5")]
    print(
        f"| {name} | {' | '.join(cols)} | {cell(r, 'first_of_8')} | {r['first_of_10']['mean']:.2f} |"
    )
