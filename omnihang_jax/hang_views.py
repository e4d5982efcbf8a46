"""Pictures, pages and scenes of a :class:`omnihang_jax.hang.HangResult`.

- :func:`write_scene_xml`: the pair's MJCF (``sim.scene.write_scene``: convex parts as STL,
  visual meshes as OBJ) with the object at the answer and keyframes ``answer``, ``settled``
  and ``path_000``... (MuJoCo's viewer: the Simulation panel's Key slider, then "Load key").
- :func:`draw_png`: the clouds, the candidates (coloured by their simulated status), the
  answer before and after the simulated second (ray-cast renders, ``sim.render``), the path.
- :func:`write_viewer`: one self-contained interactive 3-D page (plotly's offline HTML with
  plotly.js inlined: no server, no network), the clouds, meshes, candidates with their
  scores and the path.
"""

from __future__ import annotations

import os
import re
import textwrap
from pathlib import Path

import numpy as np

STATUS_RGB = {  # candidate markers: the simulated status (unverified: grey)
    "stable": (0.10, 0.62, 0.25),
    "fallen": (0.95, 0.55, 0.10),
    "penetrating": (0.85, 0.15, 0.15),
    "diverged": (0.55, 0.20, 0.60),
    "unverified": (0.45, 0.45, 0.45),
}
OBJECT_RGB = (0.86, 0.42, 0.12)  # as sim.render
SUPPORT_RGB = (0.22, 0.42, 0.78)


def _rot(pose: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.roll(np.asarray(pose[3:7], float), -1)).as_matrix()


def transform(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """[N, 3] object-frame points -> support frame at ``pose`` [7]."""
    return np.asarray(points, float) @ _rot(pose).T + np.asarray(pose[:3], float)


def statuses(result) -> list[str]:
    from sim.kernels import STATUS_NAMES

    if result.status is None:
        return ["unverified"] * len(result.candidates.poses)
    return [STATUS_NAMES[int(s)] for s in result.status]


# ----------------------------------------------------------------------------- scene.xml


def write_scene_xml(result, scene, folder: str | os.PathLike) -> Path:
    """``folder/scene.xml`` (+ meshes/, the two OBJ meshes, scene.json) with keyframes."""
    import mujoco

    from sim.scene import write_scene

    folder = Path(folder)
    path = write_scene(scene.obj, scene.support, folder, pose=result.pose)
    keys = [("answer", result.pose)]
    if result.settled_pose is not None:
        keys.append(("settled", result.settled_pose))
    if result.path is not None:
        keys += [(f"path_{i:03d}", p) for i, p in enumerate(result.path.poses)]
    lines = "\n".join(
        f'    <key name="{name}" qpos="{" ".join(f"{float(x):.7g}" for x in pose)}"/>'
        for name, pose in keys
    )
    xml = path.read_text()
    xml = re.sub(r"</mujoco>\s*$", f"  <keyframe>\n{lines}\n  </keyframe>\n</mujoco>\n", xml)
    path.write_text(xml)
    mujoco.MjModel.from_xml_path(str(path))  # fail here, not in the viewer
    return path


# ----------------------------------------------------------------------------- hang.png


def _scatter(ax, pts, rgb, size=0.6, alpha=0.5, stride=4):
    p = np.asarray(pts)[::stride]
    ax.scatter(p[:, 0], p[:, 1], p[:, 2], s=size, color=rgb, alpha=alpha, depthshade=False)


def _equal(ax, pts):
    lo, hi = pts.min(0), pts.max(0)
    c, r = 0.5 * (lo + hi), 0.5 * float((hi - lo).max()) + 1e-3
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_xlabel("x (m)", fontsize=7)
    ax.set_ylabel("y (m)", fontsize=7)
    ax.set_zlabel("z (m)", fontsize=7)
    ax.tick_params(labelsize=6)


def draw_png(result, scene, path: str | os.PathLike) -> Path:
    """Four panels: object cloud; support cloud + candidates + answer (+ path); the answer
    before and after the simulated second (renders with meshes, clouds otherwise)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim import render

    obj, sup, c = result.object, result.support, result.candidates
    st = statuses(result)
    fig = plt.figure(figsize=(16, 4.4), dpi=110)
    ax = fig.add_subplot(1, 4, 1, projection="3d")
    _scatter(ax, obj.points, OBJECT_RGB, stride=2)
    _equal(ax, obj.points)
    ax.set_title(f"object cloud ({obj.source}: {obj.name})\nobject frame", fontsize=9)

    ax = fig.add_subplot(1, 4, 2, projection="3d")
    _scatter(ax, sup.points, SUPPORT_RGB, stride=2)
    placed = transform(obj.points, result.pose)
    _scatter(ax, placed, OBJECT_RGB, stride=4, alpha=0.35)
    pos = c.poses[:, :3]
    for name in STATUS_RGB:
        k = [i for i, s in enumerate(st) if s == name]
        if k:
            ax.scatter(*pos[k].T, s=14, color=STATUS_RGB[name], label=f"{name} ({len(k)})",
                       depthshade=False)  # fmt: skip
    ax.scatter(*result.pose[:3], s=120, marker="*", color="black", label="answer")
    pts = [sup.points, placed, pos]
    if result.path is not None:
        p = np.asarray(result.path.poses)[:, :3]
        ax.plot(p[:, 0], p[:, 1], p[:, 2], color="black", lw=1.2, label="path")
        pts.append(p)
    _equal(ax, np.concatenate(pts))
    ax.legend(fontsize=6, loc="upper left")
    ax.set_title(
        f"support cloud ({sup.source}: {sup.name}), {len(pos)} candidates\n"
        f"(object centres, by {'simulated status' if result.verified else 'rank'})",
        fontsize=9,
    )
    before = f"answer: {c.stage[result.chosen]} proposal {c.proposal[result.chosen]}, rank {result.chosen}"
    if scene is not None:
        for j, (pose, title) in enumerate(
            [
                (result.pose, f"{before}\nbefore simulation"),
                (
                    result.settled_pose if result.settled_pose is not None else result.pose,
                    f"after 1 s simulated: {result.verdict}"
                    if result.settled_pose is not None
                    else "not simulated (verify=False)",
                ),
            ]
        ):
            ax = fig.add_subplot(1, 4, 3 + j)
            ax.imshow(render.render_scene(scene, pose, width=360, height=300))
            ax.set_axis_off()
            ax.set_title(title, fontsize=9)
    else:
        ax = fig.add_subplot(1, 4, 3, projection="3d")
        _scatter(ax, sup.points, SUPPORT_RGB, stride=2)
        _scatter(ax, placed, OBJECT_RGB, stride=2)
        _equal(ax, np.concatenate([sup.points, placed]))
        ax.set_title(f"{before}\n(clouds only: unverified)", fontsize=9)
        ax = fig.add_subplot(1, 4, 4)
        ax.set_axis_off()
        reason = result.steps.get("check", "no meshes to simulate").split(";")[0]
        ax.text(0.0, 0.5, "no simulation:\n" + textwrap.fill(reason, 34), fontsize=10,
                va="center")  # fmt: skip
    fig.suptitle(
        f"hang {obj.name} on {sup.name}: {result.verdict}"
        + ("" if result.path is None else f", path of {len(result.path.poses)} poses"),
        fontsize=11,
    )
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------- viewer.html


def _mesh3d(mesh, pose, rgb, name, opacity=1.0, max_faces=20000):
    import plotly.graph_objects as go

    v = np.asarray(mesh.vertices, float)
    f = np.asarray(mesh.faces)
    if len(f) > max_faces:  # keep the page small: every k-th face of huge meshes
        f = f[:: int(np.ceil(len(f) / max_faces))]
    if pose is not None:
        v = transform(v, pose)
    colour = "rgb({},{},{})".format(*(int(255 * x) for x in rgb))
    return go.Mesh3d(
        x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2],
        color=colour, opacity=opacity, name=name, showlegend=True, flatshading=True,
        hoverinfo="name",
    )  # fmt: skip


def viewer_figure(result):
    """The plotly Figure of :func:`write_viewer`."""
    import plotly.graph_objects as go

    obj, sup, c = result.object, result.support, result.candidates
    st = statuses(result)
    traces = []

    def cloud(pts, rgb, name, visible=True):
        colour = "rgb({},{},{})".format(*(int(255 * x) for x in rgb))
        return go.Scatter3d(
            x=pts[:, 0], y=pts[:, 1], z=pts[:, 2], mode="markers", name=name,
            marker=dict(size=1.6, color=colour), visible=True if visible else "legendonly",
            hoverinfo="name",
        )  # fmt: skip

    traces.append(cloud(sup.points, SUPPORT_RGB, "support cloud"))
    traces.append(cloud(transform(obj.points, result.pose), OBJECT_RGB, "object cloud at answer"))
    if sup.asset is not None:
        traces.append(_mesh3d(sup.asset.mesh, None, SUPPORT_RGB, "support mesh", 0.6))
    if obj.asset is not None:
        traces.append(
            _mesh3d(obj.asset.mesh, result.pose, OBJECT_RGB, "object mesh at answer", 0.8)
        )
        if result.settled_pose is not None:
            traces.append(
                _mesh3d(
                    obj.asset.mesh, result.settled_pose, (0.6, 0.6, 0.6), "object after 1 s", 0.5
                )
            )
            traces[-1].visible = "legendonly"
    text = [
        f"rank {i}: {c.stage[i]} proposal {c.proposal[i]}<br>{c.score_name} {c.score[i]:.3f}"
        f"<br>{st[i]}" for i in range(len(c.poses))
    ]  # fmt: skip
    for name, rgb in STATUS_RGB.items():
        k = [i for i, s in enumerate(st) if s == name]
        if not k:
            continue
        p = c.poses[k, :3]
        traces.append(
            go.Scatter3d(
                x=p[:, 0], y=p[:, 1], z=p[:, 2], mode="markers", name=f"candidates: {name}",
                text=[text[i] for i in k], hoverinfo="text",
                marker=dict(size=5, color=[float(c.score[i]) for i in k], colorscale="Viridis",
                            cmin=float(c.score.min()), cmax=float(c.score.max()),
                            line=dict(color="rgb({},{},{})".format(*(int(255 * x) for x in rgb)),
                                      width=3)),
            )
        )  # fmt: skip
    traces.append(
        go.Scatter3d(
            x=[result.pose[0]], y=[result.pose[1]], z=[result.pose[2]], mode="markers",
            name="answer", marker=dict(size=9, symbol="diamond", color="black"),
            text=[text[result.chosen]], hoverinfo="text",
        )
    )  # fmt: skip
    if result.path is not None:
        p = np.asarray(result.path.poses)[:, :3]
        traces.append(
            go.Scatter3d(x=p[:, 0], y=p[:, 1], z=p[:, 2], mode="lines+markers", name="path",
                         line=dict(color="black", width=4), marker=dict(size=2))
        )  # fmt: skip
    fig = go.Figure(traces)
    fig.update_layout(
        title=(
            f"hang {obj.name} on {sup.name}: {result.verdict} "
            f"({len(c.poses)} candidates, ranked by {c.score_name})"
        ),
        scene=dict(
            aspectmode="data", xaxis_title="x (m)", yaxis_title="y (m)", zaxis_title="z (m)"
        ),
        legend=dict(itemsizing="constant"),
        margin=dict(l=0, r=0, t=40, b=0),
    )
    return fig


def write_viewer(result, path: str | os.PathLike) -> Path:
    """One self-contained HTML page (plotly.js inlined; opens from disk, offline)."""
    path = Path(path)
    viewer_figure(result).write_html(
        path, include_plotlyjs=True, full_html=True, config={"displaylogo": False}
    )
    return path
