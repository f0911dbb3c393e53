"""The `cosim` command: run | validate | gradcheck | optimize | sweep | bench | render.

Every user error (a wrong scene key, a missing file, an unstable step) ends as
one message on stderr and a non-zero exit code (2: bad scene, 3: simulation
became invalid, 4: gradient check failed), never a traceback.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cosim.bench import BENCHMARKS
from cosim.cli_args import add_ray_options, positive_float, positive_int, positive_ints, words
from cosim.errors import CosimError

DEFAULT_SCENE = "cloth_catch.yaml"


def resolve_scene(arg: str | None) -> Path:
    """A scene path: as given, else a shipped scene by name (with or without .yaml)."""
    from cosim.scene.shipped import scenes_dir

    if arg is None:
        return scenes_dir() / DEFAULT_SCENE
    path = Path(arg)
    if path.is_file():
        return path
    for candidate in (scenes_dir() / arg, scenes_dir() / f"{arg}.yaml"):
        if candidate.is_file():
            return candidate
    return path  # load_scene reports it missing


def _load(args, **defaults):
    """The scene ``args.scene`` with the command's ``defaults`` for top-level keys (gradcheck's float64),
    then ``--precision`` / ``--arch`` and the ``--set`` assignments, which win over both."""
    from cosim.scene import load_scene

    scene = load_scene(resolve_scene(args.scene), defaults or None, _assignments(args))
    if "precision" in defaults:
        _say_precision(args, scene.precision)
    return scene


def _say_precision(args, used: str) -> None:
    """Tell when a command runs in another precision than the scene file's (gradcheck and optimize
    default to float64: central differences and long adjoints need its round-off)."""
    import yaml

    data = yaml.safe_load(resolve_scene(args.scene).read_text()) or {}
    written = data.get("precision", "float32") if isinstance(data, dict) else "float32"
    chosen = getattr(args, "precision", None) or any(
        a.startswith("precision=") for a in getattr(args, "set", None) or []
    )
    if written != used:
        why = "as asked" if chosen else f"{args.command}'s default; --precision {written} keeps the scene's"
        print(f"precision: {used}, not the scene's {written} ({why})")


def add_scene_options(parser: argparse.ArgumentParser) -> None:
    """``--set``, ``--precision`` and ``--arch``: change a scene without editing its file."""
    parser.add_argument(
        "--set",
        action="append",
        metavar="KEY.PATH=VALUE",
        help="set one scene value (repeatable), e.g. --set mpm.bodies[0].material.E=4e4 --set contact.friction=0.3",
    )
    parser.add_argument("--precision", choices=["float32", "float64"], help="override the scene's precision")
    parser.add_argument("--arch", choices=["cpu", "cuda"], help="override the scene's Taichi arch")


def cmd_run(args) -> int:
    import numpy as np

    from cosim.run import run_scene

    scene = _load(args)
    if args.contact:
        if scene.rigid is None and scene.articulated is None and not scene.cloth:
            from cosim.errors import InputError

            raise InputError(
                f"--contact {args.contact}: nothing meets the MPM through a contact model in this scene "
                "(no 'rigid:', 'articulated:' or 'cloth:' section)"
            )
        scene.contact.model = args.contact
    out = Path(args.out or f"out/{scene.name}")
    m = run_scene(
        scene, out, steps=args.steps, progress=not args.quiet, preview=not args.no_preview, save_target=args.save_target
    )
    print(
        f"{scene.name}: {m['steps']} steps, {m['substeps_total']} substeps"
        + (f" in {m['exchanges_per_step']} exchanges per step" if m["exchanges_per_step"] > 1 else "")
        + f", {m['particles']} particles, "
        f"{m['wall_time_s']:.2f} s, the first step {m['first_step_s']:.2f} s of it "
        f"({m['particle_substeps_per_s'] / 1e6:.2f} M particle-substeps/s), "
        f"max CFL {m['max_cfl']:.3f}"
    )
    if "particles_inside_rigid" in m:
        inside = ", ".join(f"{k}: {v}" for k, v in m["particles_inside_rigid"].items())
        print(f"contact model {m['contact_model']}: particles inside rigid bodies at the end: {inside}")
    if m.get("particles_passed_through"):
        through = ", ".join(f"{k}: {v}" for k, v in m["particles_passed_through"].items())
        print(f"particles that went through rigid bodies (body/rigid body): {through}")
    for skeleton, q in m.get("joint_positions", {}).items():
        print(f"skeleton {skeleton}: joint positions {np.round(q, 4).tolist()}")
    if "particles_held" in m:
        held = ", ".join(f"{k}: {v}" for k, v in m["particles_held"].items())
        print(f"particles held by containers: {held}; elsewhere (spilled): {m['particles_elsewhere']}")
    extra = (f", {out}/{m['preview']}" if "preview" in m else "") + (f", {out}/target.npz" if args.save_target else "")
    print(f"wrote {out}/trajectory.npz, {out}/metrics.json{extra}")
    return 0


def cmd_validate(args) -> int:
    """Every check `run` makes before its first step (``cosim.scene.start``): no Taichi unless the
    arch is a GPU's or a mesh SDF is not cached yet, DART only for ``articulated:`` sections."""
    from cosim.scene.start import check_machine, check_start

    scene = _load(args)
    check_machine(scene)  # run's order: the machine (Taichi's start-up), then the scene
    start = check_start(scene)
    print(
        f"{args.scene}: valid ({scene.dim}D, {len(start.bodies)} bodies, {start.particles} particles, "
        f"grid {scene.cells}, dx {scene.dx:g} m)"
    )
    return 0


def cmd_gradcheck(args) -> int:
    from cosim.adjoint.gradcheck import check_gradients, report_gradcheck
    from cosim.adjoint.objective import Objective
    from cosim.scene.build import build_system
    from cosim.scene.params import select_params

    scene = _load(args, precision="float64")
    steps = args.steps or scene.gradient.steps or min(scene.steps, 5)
    sim = build_system(scene, requires_grad=True, steps=steps)
    obj = Objective(sim)
    params = obj.initial_params()
    names = select_params(obj, scene, "gradient")
    print(
        f"gradcheck {scene.name}: {steps} steps x {_exchanges(sim)}{sim.grad_substeps} substeps, {scene.precision}, "
        f"loss {scene.loss.type}"
    )
    print(obj.memory_estimate().describe(), flush=True)
    tolerance = args.tolerance or scene.gradient.tolerance
    directions = args.directions or scene.gradient.directions
    results = check_gradients(obj.evaluate, params, names, obj.natural_scales(), directions, tolerance=tolerance)
    return report_gradcheck(results, tolerance, steps)


def _exchanges(sim) -> str:
    """ "M exchanges x " where a light body's coupling makes several per macro step, else nothing."""
    return f"{sim.exchanges} exchanges x " if sim.exchanges > 1 else ""


def cmd_optimize(args) -> int:
    from cosim.adjoint.optimize_scene import optimize_scene
    from cosim.errors import InputError

    if args.starts > 1:
        from cosim.scale.commands import optimize_starts

        if args.resume:
            raise InputError("--resume continues one optimisation; resume each start with its own folder OUT/start_K")
        scene = _load(args, precision="float64")  # validates, and says so when not the scene's precision
        return optimize_starts(
            scene.name, resolve_scene(args.scene), _assignments(args), args.starts, args.perturb, args.iters, args.lr,
            args.method, args.steps, args.out, not args.no_preview, args.workers, args.address, args.quiet,
        )  # fmt: skip
    scene = _load(args, precision="float64")
    out = Path(args.out or f"out/{scene.name}_optimize")
    summary = optimize_scene(
        scene,
        out,
        args.iters,
        args.lr,
        args.method,
        args.steps,
        resume=args.resume,
        progress=not args.quiet,
        preview=not args.no_preview,
    )
    _report_optimisation(summary)
    print("wrote " + ", ".join(summary["written"]))
    return 1 if summary.get("stopped") else 0


def _report_optimisation(summary: dict) -> None:
    """The loss's first and best values; a run that stopped early (a step no halving could save) says why."""
    first, best = summary["losses"][0], summary["best_loss"]
    change = f" ({100 * (best - first) / abs(first):+.1f}%)" if first else ""
    stopped = summary.get("stopped")
    iterations = len(summary["losses"]) - (0 if stopped else 1)  # a finished run evaluates its final step too
    print(f"loss {first:.6e} -> {best:.6e}{change} in {iterations} iterations ({summary['wall_time_s']:.1f} s)")
    if stopped:
        print(f"stopped early, the best parameters so far kept: {stopped}", file=sys.stderr)


def _assignments(args) -> list[str]:
    """The command line's scene changes as assignments: --precision, --arch, then every --set."""
    out = [f"{key}={getattr(args, key)}" for key in ("precision", "arch") if getattr(args, key, None)]
    return out + (getattr(args, "set", None) or [])


def cmd_sweep(args) -> int:
    from cosim.scale.commands import sweep

    if not args.grid:
        from cosim.errors import InputError

        raise InputError(
            "cosim sweep needs at least one --grid KEY.PATH=v1,v2,... (e.g. --grid contact.friction=0,0.3)"
        )
    return sweep(
        resolve_scene(args.scene), _assignments(args), args.grid, args.samples, args.seed, args.loss, args.steps,
        args.out, args.workers, args.address, args.quiet,
    )  # fmt: skip


def cmd_bench(args) -> int:
    from cosim.bench import run_bench

    return run_bench(
        args.what,
        Path(args.out),
        quick=args.quick,
        repeat=args.repeat,
        workers=args.workers,
        address=args.address,
        count=args.count,
        seed=args.seed,
        steps=args.steps,
        scenes=args.scene,
        sizes=args.sizes,
        baseline=args.baseline,
        profile=args.profile,
        arch=args.arch,
        threads=args.threads,
        scatters=args.scatter,
        particles=args.particles,
        peer=args.peer,
    )


def cmd_render(args) -> int:
    """Redraw a saved trajectory as ``cosim run``'s preview draws it (``cosim.trajectory.write_trajectory_preview``:
    particles, rigid bodies at their saved poses, cloth)."""
    import numpy as np

    from cosim.errors import InputError
    from cosim.trajectory import write_trajectory_preview

    scene = _load(args)
    path = Path(args.trajectory)
    if not path.is_file():
        raise InputError(f"trajectory file not found: {path}; `cosim run` writes one as OUT/trajectory.npz")
    traj = np.load(path, allow_pickle=False)
    bodies = traj.get("body_names", [])
    cloths = traj.get("cloth_names", [])
    required = ["body_names", "time", *(f"x_{n}" for n in bodies)]
    required += [f"cloth_{k}_{n}" for n in cloths for k in ("x", "faces")]
    missing = [key for key in required if key not in traj]
    if missing:
        raise InputError(f"{path}: not a cosim trajectory (missing {', '.join(missing)})")
    out = write_trajectory_preview(Path(args.output), traj, scene, _rigid_of(scene, traj, path))
    print(f"wrote {out}")
    return 0


def _rigid_of(scene, traj, path: Path):
    """The scene's ``RigidBodies`` (for their SDF surfaces), checked against the trajectory's rigid
    bodies, or None for a trajectory without rigid bodies."""
    from cosim.errors import InputError

    if "rigid_names" not in traj:
        return None
    if "rigid_pos" not in traj:
        raise InputError(
            f"{path}: written by an older cosim (per-body rigid_pos_<body> keys, not rigid_pos); "
            "run the scene again to render it"
        )
    from cosim.scene.build import build_system

    rigid = build_system(scene).rigid
    names = [str(n) for n in traj["rigid_names"]]
    if rigid is None or list(rigid.names) != names:
        raise InputError(
            f"{path}: its rigid bodies {names} are not the scene's {list(rigid.names) if rigid else []}; "
            "render it with the scene that wrote it"
        )
    return rigid


def make_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="cosim", description="Differentiable MPM co-simulation for soft-body manipulation."
    )
    p.add_argument(
        "--optimize-kernels",
        action="store_true",
        help="compile Taichi kernels with advanced optimisation: faster kernels for a longer compile; pays off "
        "on long runs (always on for `bench`)",
    )
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run a scene and write trajectory, metrics and a preview")
    r.add_argument("scene", nargs="?", help=f"scene file or shipped scene name (default: {DEFAULT_SCENE})")
    r.add_argument("--out", help="output folder (default: out/SCENE_NAME)")
    r.add_argument("--steps", type=positive_int, help="macro steps (default: the scene's)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument("--no-preview", action="store_true", help="skip the preview (trajectory and metrics only)")
    add_scene_options(r)
    r.add_argument("--contact", choices=["grid", "particle", "forecast"], help="override the scene's contact model")
    r.add_argument(
        "--save-target", action="store_true", help="also write OUT/target.npz: final positions, a chamfer target"
    )
    r.set_defaults(func=cmd_run)

    v = sub.add_parser("validate", help="check a scene file and report its size")
    v.add_argument("scene")
    add_scene_options(v)
    v.set_defaults(func=cmd_validate)

    g = sub.add_parser("gradcheck", help="adjoint vs central finite differences (float64)")
    g.add_argument("scene")
    add_scene_options(g)
    g.add_argument(
        "--steps", type=positive_int, help="macro steps (default: the scene's gradient.steps, else min(steps, 5))"
    )
    g.add_argument("--directions", type=positive_int, help="random directions per parameter")
    g.add_argument("--tolerance", type=positive_float, help="largest relative error accepted")
    g.set_defaults(func=cmd_gradcheck)

    o = sub.add_parser("optimize", help="minimise the scene's loss over its inputs with the adjoint gradient")
    o.add_argument("scene")
    add_scene_options(o)
    o.add_argument("--iters", type=positive_int, help="iterations (default: optimize.iterations)")
    o.add_argument("--lr", type=positive_float, help="learning rate, a fraction of each parameter's scale")
    o.add_argument("--steps", type=positive_int, help="macro steps of the rollout (default: the scene's)")
    o.add_argument("--out", help="output folder (default: out/SCENE_optimize)")
    o.add_argument("--method", choices=["adam", "sgd", "lbfgs"], help="optimiser (default: optimize.method, adam)")
    o.add_argument(
        "--resume", action="store_true", help="continue from OUT/checkpoint.npz (saved after every iteration)"
    )
    o.add_argument("--quiet", action="store_true", help="no progress bar")
    o.add_argument("--no-preview", action="store_true", help="skip the final rollout's preview")
    o.add_argument(
        "--starts", type=positive_int, default=1, help="K optimisations in parallel on Ray from perturbed guesses"
    )
    o.add_argument(
        "--perturb",
        type=positive_float,
        default=0.1,
        help="--starts: initial-guess noise, a fraction of each parameter's scale (default 0.1)",
    )
    add_ray_options(o)
    o.set_defaults(func=cmd_optimize)

    sw = sub.add_parser("sweep", help="run a scene over a grid of settings on Ray, into one CSV")
    sw.add_argument("scene")
    sw.add_argument(
        "--grid",
        action="append",
        metavar="KEY.PATH=v1,v2,...",
        help="values of one scene key (repeatable: every combination runs), e.g. --grid contact.friction=0,0.3",
    )
    sw.add_argument("--samples", type=positive_int, help="run N combinations drawn at random instead of all")
    sw.add_argument("--seed", type=int, default=0, help="--samples: the draw's seed (default 0)")
    sw.add_argument(
        "--loss", action="store_true", help="record the loss and gradient norms (float64) instead of run metrics"
    )
    sw.add_argument("--steps", type=positive_int, help="macro steps (default: the scene's)")
    sw.add_argument("--out", help="output folder (default: out/SCENE_sweep)")
    sw.add_argument("--quiet", action="store_true", help="no progress bar")
    add_scene_options(sw)
    add_ray_options(sw)
    sw.set_defaults(func=cmd_sweep)

    b = sub.add_parser("bench", help="benchmarks: throughput, backward/forward ratio, memory")
    b.add_argument("what", choices=BENCHMARKS)
    b.add_argument("--out", default="out/bench", help="folder for the results (CSV; cloth: JSON)")
    b.add_argument("--quick", action="store_true", help="fewer substeps (a smoke run)")
    b.add_argument(
        "--repeat",
        type=positive_int,
        default=3,
        help="contact, coupling, cloth, mpm --baseline / --peer: repetitions; times are medians",
    )
    b.add_argument("--sizes", action="store_true", help="mpm: 3D float32 from 10k to 1M particles, 8 per cell")
    b.add_argument(
        "--baseline",
        type=Path,
        metavar="DIR",
        help="mpm: also run each configuration with the cosim in DIR (made by scripts/baseline_env.sh, "
        "a virtualenv or a checkout), interleaved; prints current/baseline ratios",
    )
    b.add_argument(
        "--peer",
        metavar="softmac=DIR",
        help="mpm: also run SoftMAC's MPM from its checkout DIR on 3D float64 blocks, interleaved; "
        "prints current/peer ratios",
    )
    b.add_argument("--profile", action="store_true", help="mpm: kernel profile of 3D 64³ float32; contact: of a frame")
    b.add_argument("--arch", choices=["cpu", "cuda"], default="cpu", help="mpm, contact: where Taichi runs")
    b.add_argument("--threads", type=positive_ints, metavar="N,N", help="mpm: each config on these CPU thread counts")
    b.add_argument("--scatter", type=words, metavar="S,S", help="mpm: each config with these scatters (serial, ...)")
    b.add_argument("--particles", type=positive_int, metavar="N", help="mpm: one 3D float32 block of about N particles")
    b.add_argument("--count", type=positive_int, default=200, help="fuzz: how many random scenes (default 200)")
    b.add_argument("--seed", type=int, default=0, help="fuzz: the first scene's seed; the others follow (default 0)")
    b.add_argument("--steps", type=positive_int, default=10_000, help="long: macro steps per scene (default 10000)")
    b.add_argument(
        "--scene",
        action="append",
        metavar="NAME",
        help="long: a shipped scene to run (repeatable; default one per type)",
    )
    add_ray_options(b)
    b.set_defaults(func=cmd_bench)

    rd = sub.add_parser("render", help="render a saved trajectory.npz to a GIF/MP4")
    rd.add_argument("scene")
    add_scene_options(rd)
    rd.add_argument("trajectory")
    rd.add_argument("output")
    rd.set_defaults(func=cmd_render)
    return p


def main(argv: list[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    if args.optimize_kernels or args.command == "bench":
        from cosim.runtime import optimize_kernels

        optimize_kernels(True)
    try:
        return args.func(args)
    except CosimError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
