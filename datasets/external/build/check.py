"""Load every mesh of the manifest with the project's loader and record what it reports.

    cd <repo> && .venv/bin/python datasets/external/build/check.py

Writes each object's "loader" field: the repairs sim.meshio.load_user_mesh made (only those
it made), whether the mesh is watertight after them, and any warning it logged.
"""

import json
import logging
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(HERE.parents[1]))  # the repository root
from sim.meshio import load_user_mesh  # noqa: E402

REPAIRS = (
    "merged_vertices",
    "degenerate_faces_removed",
    "duplicate_faces_removed",
    "winding_flipped",
    "inverted",
    "holes_filled",
)


class Collect(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def main():
    path = HERE / "manifest.json"
    manifest = json.loads(path.read_text())
    log = logging.getLogger("sim.meshio")
    for obj in manifest["objects"]:
        collect = Collect()
        log.addHandler(collect)
        try:
            _, report = load_user_mesh(HERE / obj["file"])
            found = {k: report[k] for k in REPAIRS if report[k]}
            found["watertight"] = report["watertight"]
            if collect.messages:
                found["warnings"] = [m.split(": ", 1)[1].split(";")[0] for m in collect.messages]
        except Exception as exc:  # a MeshError says which file and why
            found = dict(error=str(exc))
        finally:
            log.removeHandler(collect)
        obj["loader"] = found
        print(obj["name"], found)
    path.write_text(json.dumps(manifest, indent=1) + "\n")


if __name__ == "__main__":
    main()
