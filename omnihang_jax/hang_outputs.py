"""What ``hang`` writes: ``result.json`` and the output folder, whole or absent (the pictures
and the page are :mod:`omnihang_jax.hang_views`)."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from omnihang_jax.hang_inputs import (
    SEARCH_KEEP,
    Body,
    HangConfig,
    HangInputError,
    HangResult,
    _say,
)

# ----------------------------------------------------------------------------- outputs


def _check_out(out: Path) -> None:
    """The output folder may be new, empty, or a previous hang output (replaced whole)."""
    if out.exists() and not out.is_dir():
        raise HangInputError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / "result.json").exists():
        raise HangInputError(
            f"{out}: folder exists and is not a previous hang output (no result.json); "
            f"choose a new --out"
        )
    parent = out.resolve().parent
    if parent.exists() and not os.access(parent, os.W_OK):
        raise HangInputError(f"{out}: cannot write into {parent} (permission denied)")


def _input_frame_pose(result: HangResult) -> dict | None:
    """With --recenter: the answer between the clouds as given (before recentring):
    ``T_input = Trans(c_support) T Trans(-c_object)``; None when nothing was recentred."""
    c_obj = np.asarray(result.object.report.get("recentered_by", np.zeros(3)), float)
    c_sup = np.asarray(result.support.report.get("recentered_by", np.zeros(3)), float)
    if not (c_obj.any() or c_sup.any()):
        return None
    m = result.matrix.copy()
    m[:3, 3] = m[:3, 3] - m[:3, :3] @ c_obj + c_sup
    return dict(
        xyz=[float(x) for x in m[:3, 3]],
        quat_wxyz=[float(x) for x in result.pose[3:]],
        matrix=[[float(x) for x in row] for row in m],
        note="the answer between the input clouds before --recenter moved them",
    )


def result_json(result: HangResult, config: HangConfig) -> dict:
    """The JSON record of a result (the layout of result.json; docs/hang.md)."""
    from sim import kernels

    c = result.candidates

    def body(b: Body) -> dict:
        return dict(kind=b.kind, name=b.name, source=b.source, path=b.path, report=b.report)

    candidates = []
    for i in range(len(c.poses)):
        row = dict(
            rank=i,
            stage=str(c.stage[i]),
            proposal=int(c.proposal[i]),
            score=float(c.score[i]),
            pose_xyz_wxyz=[float(x) for x in c.poses[i]],
        )
        if result.status is not None:
            row["status"] = kernels.STATUS_NAMES[int(result.status[i])]
            row["initial_penetration_m"] = float(result.penetration[i])
        candidates.append(row)
    search = None
    if result.search is not None:
        search = {k: v for k, v in result.search.items() if k != "poses"}
        search["poses_xyz_wxyz"] = [
            [float(x) for x in p] for p in result.search["poses"][:SEARCH_KEEP]
        ]
    return dict(
        convention=(
            "pose of the object frame (origin at the object's bounding-box centre) in the "
            "support frame (z up; wall-mounted supports: wall at the lowest y, reaching "
            "towards +y): p_support = R p_object + t; metres; quaternion w, x, y, z"
        ),
        object=body(result.object),
        support=body(result.support),
        verdict=result.verdict,
        verified=result.verified,
        hung=result.hung,
        pose=dict(
            xyz=[float(x) for x in result.pose[:3]],
            quat_wxyz=[float(x) for x in result.pose[3:]],
            matrix=[[float(x) for x in row] for row in result.matrix],
            stage=str(c.stage[result.chosen]),
            proposal=int(c.proposal[result.chosen]),
            rank=int(result.chosen),
            score=float(c.score[result.chosen]),
        ),
        pose_in_input_frames=_input_frame_pose(result),
        settled_pose_xyz_wxyz=(
            None if result.settled_pose is None else [float(x) for x in result.settled_pose]
        ),
        score_name=c.score_name,
        candidates=candidates,
        path=(
            None
            if result.path is None
            else dict(
                planner=result.path.planner,
                info=result.path.info,
                poses_xyz_wxyz=[[float(x) for x in p] for p in result.path.poses],
            )
        ),
        search=search,
        steps=result.steps,
        timings_s={k: round(v, 3) for k, v in result.timings.items()},
        warnings=result.warnings,
        config=dataclasses.asdict(config),
    )


def write_outputs(
    result: HangResult, out, config: HangConfig = HangConfig(), scene=None, log=print
) -> Path:
    """Write result.json, scene.xml (+ meshes; meshes known only), hang.png and viewer.html
    into a temporary folder beside ``out``, then rename it to ``out`` (replacing a previous
    hang output): the folder is complete or absent."""
    from omnihang_jax import hang_views

    out = Path(out)
    _check_out(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp-"))
    tmp.chmod(0o755)  # mkdtemp makes it private; the result is an ordinary folder
    try:
        record = result_json(result, config)
        files = ["result.json", "hang.png", "viewer.html"]
        if scene is not None:
            _say(log, "writing scene.xml")
            hang_views.write_scene_xml(result, scene, tmp)
            files.append("scene.xml")
        else:
            record["scene"] = "not written: MuJoCo needs the meshes of both bodies"
        _say(log, "drawing hang.png")
        hang_views.draw_png(result, scene, tmp / "hang.png")
        _say(log, "writing viewer.html")
        hang_views.write_viewer(result, tmp / "viewer.html")
        record["files"] = files
        (tmp / "result.json").write_text(json.dumps(record, indent=1))
        _replace_folder(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def _replace_folder(tmp: Path, out: Path) -> None:
    """Move the finished folder ``tmp`` to ``out``; an existing ``out`` is replaced whole (a
    reader sees the old folder or the new one, never a mix)."""
    if out.exists():
        old = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.old-"))
        os.replace(out, old / "previous")
        os.replace(tmp, out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, out)
