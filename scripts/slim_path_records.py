"""An eval_stage3 run's per-pair records cut to what experiments.eval_paths reads (pair index,
names, the all-stages answer and its status), for a device call whose tree must stay small:

    python scripts/slim_path_records.py results/hanging_success_stage3_s14_cemv.pairs.jsonl.gz \\
        out/paths_records.jsonl.gz      # 7.9 MB -> ~0.3 MB; same pairs, same answers
"""

import gzip
import json
import sys

src, dst = sys.argv[1:3]
opener = gzip.open if src.endswith(".gz") else open
with opener(src, "rt") as f, gzip.open(dst, "wt") as out:
    for line in f:
        if not line.strip():
            continue
        r = json.loads(line)
        out.write(json.dumps({
            "pair_index": r["pair_index"], "object": r.get("object"), "support": r.get("support"),
            "poses_all": [r["poses_all"][r["answer_index"]]], "answer_index": 0,
            "all_stages": {"status": r["all_stages"]["status"]},
        }) + "\n")  # fmt: skip
