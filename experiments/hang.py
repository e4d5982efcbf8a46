"""Where (and how) to hang an object on a supporting item: meshes or clouds in, a hanging
pose checked in MuJoCo out.

    python -m experiments.hang --out out/hang                         # built-in mug on hook
    python -m experiments.hang --object tests/fixtures/hang_pair/mug.obj \
        --support tests/fixtures/hang_pair/l_hook.stl --out out/my_hang --search
    python -m experiments.hang --object tests/fixtures/hang_pair/mug_cloud.ply --out out/clouds
    python -m experiments.hang --object towel_bar_0001 --support mug_0016 --out out/x  # error: swapped
    python -m experiments.hang --object my_mug_in_mm.stl --scale 0.001 --out out/mm
    python -m experiments.hang --heldout 6 --out out/hang_heldout    # held-out library pairs

Inputs: a mesh (OBJ, STL, PLY, GLB/GLTF), a point cloud (.npy / .npz / .ply of [N, 3] points
or [N, 6] points + normals), a library asset name (mug_0016, single_rod_hook_0001) or
nothing (the built-in default: held-out mug_0016 on held-out single_rod_hook_0001). Metres:
--scale 0.001 for millimetre files. The object is in its own frame (origin at its bounding-
box centre; meshes are centred for you); the support is z up, wall-mounted with its back on
the wall at its lowest y and reaching towards +y (--free-standing: standing on its lowest z).

Writes OUT/result.json (the pose as a 4x4 matrix and xyz + quaternion wxyz, every
candidate's score and simulated status, the path, timings), OUT/scene.xml (meshes only; open
with `python -m mujoco.viewer --mjcf=OUT/scene.xml`, keyframes "answer", "settled",
"path_*"), OUT/hang.png and OUT/viewer.html (interactive 3-D, works offline from disk).
The folder is written whole or not at all.

Exit codes: 0 a hanging pose was found (checked in MuJoCo when meshes were given); 3 no
candidate stays hanging (outputs still written); 2 bad input (one line on stderr); 1 an
internal error (traceback). docs/hang.md has the details.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from experiments import _cli

# XLA prints multi-line "constant folding is slow" alarms while compiling the networks
# (harmless, ~1 s each); keep the terminal to our progress lines unless asked.
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")


def build_parser() -> argparse.ArgumentParser:
    from omnihang_jax.hang import HangConfig
    from omnihang_jax.where import CONFIGS as WHERE_CONFIGS
    from sim.decompose import PRESETS

    d = HangConfig()
    p = argparse.ArgumentParser(
        prog="python -m experiments.hang",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--object", default=None, help="mesh, cloud or library name (default mug_0016)")
    p.add_argument(
        "--support", default=None, help="mesh, cloud or library name (default single_rod_hook_0001)"
    )
    p.add_argument("--out", default="out/hang", help="output folder (default out/hang)")
    p.add_argument("--scale", type=float, default=None, help="factor for both inputs (mm: 0.001)")
    p.add_argument("--object-scale", type=float, default=None, help="factor for the object only")
    p.add_argument("--support-scale", type=float, default=None, help="factor for the support only")
    p.add_argument(
        "--up", choices=["z", "y"], default="z", help="up axis of mesh files (default z)"
    )
    p.add_argument(
        "--free-standing", action="store_true", help="a mesh support stands on the floor, no wall"
    )
    p.add_argument(
        "--recenter",
        action="store_true",
        help="move each cloud's bounding-box centre to the origin",
    )
    p.add_argument(
        "--where", choices=list(WHERE_CONFIGS), default=d.where,
        help="the where-to-hang answer (omnihang_jax.where): default (Stages 1-3, three views, "
        "the rankers, the observed-cloud check), paper (the paper's pipeline), frames (default "
        "with a Stage 1 trained for it reading the object in 32 frames, V picking CEM's starts), "
        "canon (default with Stages 1-2 reading the object in the object-frame network's "
        "hypotheses of the library's frame, V picking CEM's starts)",
    )  # fmt: skip
    p.add_argument("--model", default=None, help="Stage 1 + 2 networks instead of the answer's")
    p.add_argument(
        "--value", choices=["on", "off"], default=None,
        help="off: Stages 1-2 only, ranked by observed-cloud clearance (no CEM)",
    )  # fmt: skip
    p.add_argument(
        "--num-proposals", type=int, default=None,
        help="Stage-1 proposals instead of the answer's (default: 10; the paper's: 5)",
    )  # fmt: skip
    p.add_argument("--noise", type=float, default=0.0, help="depth noise std of rendered views, m")
    p.add_argument(
        "--seed", type=int, default=0, help="views, noise, proposals, search (default 0)"
    )
    p.add_argument(
        "--search", action="store_true",
        help="also find simulated stable poses with the data engine's sampler (meshes only)",
    )  # fmt: skip
    p.add_argument(
        "--search-candidates", type=int, default=d.search_candidates,
        help=f"poses the search simulates (default {d.search_candidates})",
    )  # fmt: skip
    p.add_argument("--no-verify", action="store_true", help="do not simulate the candidates")
    p.add_argument(
        "--observed-check", type=int, default=None, metavar="N",
        help="clouds only: answer the first of the best N candidates that stays when dropped "
        "on the observed clouds (sim.observed; default: the answer's, 60; 0: the best-ranked)",
    )  # fmt: skip
    p.add_argument("--no-plan", action="store_true", help="do not run the how-to-hang planner")
    p.add_argument(
        "--plan-time",
        type=float,
        default=d.plan_time,
        help=f"planner time limit, s (default {d.plan_time:g})",
    )
    p.add_argument(
        "--replan-time", type=float, default=None, metavar="S",
        help="after the planner's plan times out, plan once more for S s with a fresh search "
        "(default: as long as --plan-time where the planner replans; 0: never)",
    )  # fmt: skip
    p.add_argument(
        "--checker", choices=["auto", "nce", "hce", "mesh"], default=d.checker,
        help="the planner (omnihang_jax.paths): auto (the default planner; the full meshes when "
        "it finds no path), nce / hce (the paper's estimators alone) or mesh (the full meshes)",
    )  # fmt: skip
    p.add_argument(
        "--coacd", choices=sorted(PRESETS), default=d.coacd,
        help="convex decomposition settings for user meshes: user (seconds; no manifold "
        "remeshing), library (the asset library's: remeshes non-manifold files, minutes), "
        "fast (previews)",
    )  # fmt: skip
    p.add_argument(
        "--cache", default=None,
        help="CoACD cache folder for user meshes (default out/cache/coacd)",
    )  # fmt: skip
    p.add_argument(
        "--heldout", type=int, default=None, metavar="N",
        help="instead: hang N held-out library pairs of --dataset, spread over support families "
        "and object categories, one folder each + OUT/heldout.json with the measured rates",
    )  # fmt: skip
    p.add_argument(
        "--summary-only", action="store_true",
        help="--heldout: write only OUT/heldout.json (no per-pair folders; for many pairs)",
    )  # fmt: skip
    p.add_argument(
        "--dataset", default="datasets/paper",
        help="labelled dataset whose test split --heldout draws from (default datasets/paper)",
    )  # fmt: skip
    p.add_argument(
        "--compile-cache", default=None, metavar="DIR",
        help="where compiled networks are kept between runs (default ~/.cache/omnihang/jax, "
        "or $OMNIHANG_CACHE/jax; 'off': compile every run)",
    )  # fmt: skip
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    return p


def heldout_main(args, config, log) -> int:
    from omnihang_jax.hang_heldout import HELDOUT_RESULTS, run_heldout

    if args.heldout < 1:
        raise ValueError(f"--heldout must be >= 1, got {args.heldout}")
    if args.object or args.support:
        raise ValueError("--heldout picks its own pairs: leave out --object and --support")
    record = run_heldout(
        args.heldout, args.out, config, args.dataset, log=log, outputs=not args.summary_only
    )
    s, e = record["summary"], record["expected"]
    print(
        f"held-out pairs: the answer from the clouds hangs on {s['answer_hangs']} of "
        f"{s['pairs']} ({100 * s['answer_rate']:.0f} %); some candidate hangs on "
        f"{s['some_candidate_hangs']} of {s['pairs']}"
    )
    if e:
        print(
            f"expected: {e['all_stages']:.1f} % (all stages, mean over categories, "
            f"{e['pairs']} held-out pairs x seeds {e['seeds']}, {HELDOUT_RESULTS}: "
            f"{e['source']}); a handful of pairs varies a lot around it"
        )
    print(
        f"wrote {args.out}/heldout.json"
        + ("" if args.summary_only else " and one hang folder per pair")
    )
    return _cli.EXIT_OK


def main(argv=None) -> int:
    from omnihang_jax.hang import HangConfig, hang

    parser = build_parser()
    args = parser.parse_args(argv)
    config = HangConfig(
        where=args.where,
        model=args.model,
        num_proposals=args.num_proposals,
        seed=args.seed,
        depth_noise=args.noise,
        verify=not args.no_verify,
        observed_check=args.observed_check,
        search=args.search,
        search_candidates=args.search_candidates,
        plan=not args.no_plan,
        plan_time=args.plan_time,
        replan_time=args.replan_time,
        checker=args.checker,
        scale=args.scale,
        object_scale=args.object_scale,
        support_scale=args.support_scale,
        up=args.up,
        free_standing=args.free_standing,
        recenter=args.recenter,
        coacd=args.coacd,
        cache_dir=args.cache,
        value=args.value,
    )
    if args.noise < 0:
        raise ValueError(f"--noise must be >= 0, got {args.noise}")
    if args.search_candidates < 1:
        raise ValueError(f"--search-candidates must be >= 1, got {args.search_candidates}")
    t0 = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:6.1f} s] {msg}", flush=True)

    from omnihang_jax.hang import compile_cache

    cached = compile_cache(args.compile_cache)
    if cached is not None and not args.quiet:
        log(f"compiled networks are kept in {cached} (--compile-cache DIR to move, off to disable)")

    if args.heldout is not None:
        return heldout_main(args, config, None if args.quiet else log)
    result = hang(args.object, args.support, args.out, config, log=None if args.quiet else log)
    c = result.candidates
    pose = " ".join(f"{x:.4f}" for x in result.pose)
    lines = [
        f"{result.object.name} on {result.support.name}: {result.verdict}"
        + ("" if result.verified else " (clouds only: not simulated)"),
        f"pose (xyz m, quat wxyz): {pose}  [{c.stage[result.chosen]} proposal "
        f"{c.proposal[result.chosen]}, rank {result.chosen} of {len(c.poses)}]",
    ]
    if result.status is not None:
        lines.append(
            f"candidates that stay hanging: {int((result.status == 0).sum())} of {len(c.poses)}"
        )
    if result.search is not None:
        s = result.search
        near = s.get("nearest_to_answer")
        lines.append(
            f"search: {s['stable']} stable of {s['candidates']} sampled ({s['sampler']})"
            + (
                f"; the nearest to the answer is {100 * near['translation_m']:.1f} cm, "
                f"{near['rotation_deg']:.0f} deg away"
                if near
                else ""
            )
        )
    for step in ("stage3", "how"):
        if step in result.steps:
            lines.append(f"{step}: {result.steps[step]}")
    lines.append(f"wrote {args.out}/: result.json, hang.png, viewer.html"
                 + (", scene.xml" if result.verified or result.object.asset is not None
                    and result.support.asset is not None else ""))  # fmt: skip
    lines.append(f"total {time.perf_counter() - t0:.1f} s")
    print("\n".join(lines))
    if result.verified and not result.hung:
        return _cli.EXIT_NEGATIVE
    return _cli.EXIT_OK


if __name__ == "__main__":
    try:
        _cli.run(main, sys.argv[1:])
    except SystemExit as done:
        # OMPL's nanobind bindings print a page of "leaked instance" warnings at interpreter
        # shutdown; every output is written and closed by now, so leave without the teardown.
        sys.stdout.flush()
        sys.stderr.flush()
        if "ompl" in sys.modules:
            os._exit(done.code if isinstance(done.code, int) else 1)
        raise
