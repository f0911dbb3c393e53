"""The `cosim` command: run | validate | gradcheck | optimize | bench | render.

Every user error (a wrong scene key, a missing file, an unstable step) ends as
one message on stderr and a non-zero exit code (2: bad scene, 3: simulation
became invalid, 4: gradient check failed), never a traceback.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cosim.bench import BENCHMARKS
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

    assignments = [f"{key}={getattr(args, key)}" for key in ("precision", "arch") if getattr(args, key, None)]
    assignments += getattr(args, "set", None) or []
    return load_scene(resolve_scene(args.scene), defaults or None, assignments)


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
        if scene.rigid is None:
            from cosim.errors import InputError

            raise InputError(f"--contact {args.contact}: the scene has no rigid bodies (no 'rigid:' section)")
        scene.contact.model = args.contact
    out = Path(args.out or f"out/{scene.name}")
    m = run_scene(
        scene, out, steps=args.steps, progress=not args.quiet, preview=not args.no_preview, save_target=args.save_target
    )
    print(
        f"{scene.name}: {m['steps']} steps, {m['substeps_total']} substeps, {m['particles']} particles, "
        f"{m['wall_time_s']:.2f} s ({m['particle_substeps_per_s'] / 1e6:.2f} M particle-substeps/s), "
        f"max CFL {m['max_cfl']:.3f}"
    )
    if "particles_inside_rigid" in m:
        inside = ", ".join(f"{k}: {v}" for k, v in m["particles_inside_rigid"].items())
        print(f"contact model {m['contact_model']}: particles inside rigid bodies at the end: {inside}")
    for skeleton, q in m.get("joint_positions", {}).items():
        print(f"skeleton {skeleton}: joint positions {np.round(q, 4).tolist()}")
    if "particles_held" in m:
        held = ", ".join(f"{k}: {v}" for k, v in m["particles_held"].items())
        print(f"particles held by containers: {held}; elsewhere (spilled): {m['particles_elsewhere']}")
    extra = (f", {out}/{m['preview']}" if "preview" in m else "") + (f", {out}/target.npz" if args.save_target else "")
    print(f"wrote {out}/trajectory.npz, {out}/metrics.json{extra}")
    return 0


def cmd_validate(args) -> int:
    from cosim.scene.particles import body_positions  # NumPy only: validating imports neither Taichi nor DART

    scene = _load(args)
    bodies = body_positions(scene)  # also checks meshes and that bodies fit the grid
    n = sum(len(b) for b in bodies)
    print(
        f"{args.scene}: valid ({scene.dim}D, {len(bodies)} bodies, {n} particles, "
        f"grid {scene.cells}, dx {scene.dx:g} m)"
    )
    return 0


def cmd_gradcheck(args) -> int:
    from cosim.adjoint.gradcheck import check_gradients
    from cosim.adjoint.objective import Objective
    from cosim.errors import GradientCheckError
    from cosim.scene.build import build_system

    scene = _load(args, precision="float64")
    steps = args.steps or scene.gradient.steps or min(scene.steps, 5)
    sim = build_system(scene, requires_grad=True, steps=steps)
    obj = Objective(sim)
    params = obj.initial_params()
    names = obj.select(scene.gradient.params)
    print(
        f"gradcheck {scene.name}: {steps} steps x {sim.grad_substeps} substeps, {scene.precision}, loss {scene.loss.type}"
    )
    results = check_gradients(
        obj.evaluate, params, names, obj.natural_scales(), args.directions or scene.gradient.directions
    )
    print(f"{'param':>8} {'dir':>4} {'adjoint':>16} {'finite diff':>16} {'rel error':>10}")
    for r in results:
        print(
            f"{r.param:>8} {r.direction:>4} {r.adjoint:>16.9e} {r.finite_difference:>16.9e} {r.relative_error:>10.2e}"
        )
    if all(r.adjoint == 0 and r.finite_difference == 0 for r in results):
        print(
            f"warning: every gradient is zero over {steps} steps: the parameters do not reach the loss yet; use --steps"
        )
    worst = max(r.relative_error for r in results)
    tol = args.tolerance or scene.gradient.tolerance
    print(f"max relative error: {worst:.3e} (tolerance {tol:g})")
    if worst > tol:
        raise GradientCheckError(f"adjoint and finite differences disagree: {worst:.3e} > {tol:g}")
    return 0


def cmd_optimize(args) -> int:
    import json

    import numpy as np
    from tqdm import tqdm

    from cosim.adjoint.objective import Objective
    from cosim.adjoint.optimize import PARAM_BOUNDS, minimise
    from cosim.adjoint.report import plot_losses, write_history
    from cosim.errors import SceneError
    from cosim.run import Recorder
    from cosim.scene.build import build_system

    scene = _load(args, precision="float64")
    spec = scene.optimize
    sim = build_system(scene, requires_grad=True, steps=args.steps)
    obj = Objective(sim)
    names = obj.select(spec.params)
    if not names:
        raise SceneError(f"optimize.params: none of {spec.params} exists in this scene (impulse needs controls)")
    iterations = args.iters or spec.iterations
    lr = args.lr or spec.learning_rate
    method = args.method or spec.method
    out = Path(args.out or f"out/{scene.name}_optimize")
    out.mkdir(parents=True, exist_ok=True)
    print(
        f"optimize {scene.name}: {', '.join(names)}; loss {' + '.join(obj.loss.values)}; {sim.steps} steps; "
        f"{method} lr {lr:g} x scale" + ("; resuming" if args.resume else "")
    )
    bar = tqdm(total=iterations, desc="optimize", unit="it", disable=args.quiet)

    def on_iteration(row: dict, history: list[dict]) -> None:
        write_history(out, history)  # every iteration: an interrupted run keeps its log
        bar.update(row["iteration"] + 1 - bar.n)
        bar.set_postfix(loss=f"{row['loss']:.4e}")

    result = minimise(
        obj.evaluate,
        obj.initial_params(),
        names,
        obj.natural_scales(),
        iterations,
        lr,
        method,
        {**PARAM_BOUNDS, **obj.bounds()},
        obj.projections(),
        terms=lambda: dict(obj.loss.values),
        on_iteration=on_iteration,
        checkpoint=out / "checkpoint.npz",
        resume=args.resume,
    )
    bar.close()
    wall = sum(r["seconds"] for r in result.history)
    first, best = result.losses[0], result.best_loss
    change = f" ({100 * (best - first) / abs(first):+.1f}%)" if first else ""
    print(f"loss {first:.6e} -> {best:.6e}{change} in {iterations} iterations ({wall:.1f} s)")
    np.savez(out / "params.npz", **{k: result.params[k] for k in names})  # the optimised ones, not x0 etc.
    write_history(out, result.history)
    plot_losses(out, result.losses, f"{scene.name}: {method}, {', '.join(names)}")
    summary = {"params": names, "method": method, "losses": result.losses, "best_loss": best, "wall_time_s": wall}
    (out / "optimization.json").write_text(json.dumps(summary, indent=2))
    recorder = Recorder(sim)
    obj.rollout(result.params, on_step=lambda n: recorder(n) if n == 0 or recorder.wants(n) else None)
    preview = recorder.write(out, preview=not args.no_preview)
    written = ["params.npz", "optimization.json", "optimization.csv", "loss.png", "trajectory.npz"]
    written += ["checkpoint.npz"] if method != "lbfgs" else []  # scipy's L-BFGS-B is not checkpointed
    print("wrote " + ", ".join(f"{out}/{name}" for name in written + ([preview] if preview else [])))
    return 0


def cmd_bench(args) -> int:
    from cosim.bench import run_bench

    return run_bench(args.what, Path(args.out), quick=args.quick, repeat=args.repeat)


def cmd_render(args) -> int:
    import numpy as np

    from cosim.errors import InputError
    from cosim.render import write_preview
    from cosim.run import preview_frames, up_axis

    scene = _load(args)
    path = Path(args.trajectory)
    if not path.is_file():
        raise InputError(f"trajectory file not found: {path}; `cosim run` writes one as OUT/trajectory.npz")
    traj = np.load(path, allow_pickle=False)
    names = [str(n) for n in traj["body_names"]] if "body_names" in traj else []
    missing = [f"x_{n}" for n in names if f"x_{n}" not in traj] if names else ["body_names"]
    if missing:
        raise InputError(f"{path}: not a cosim trajectory (missing {', '.join(missing)})")
    frames = [[traj[f"x_{n}"][i] for n in names] for i in range(len(traj["time"]))]
    rigid, poses = _rigid_of(scene, traj, path)
    spacing = min(b.spacing or 0.5 * scene.dx for b in scene.mpm.bodies)
    path = write_preview(
        Path(args.output),
        preview_frames(frames, traj["time"], rigid, poses),
        np.asarray(scene.cells) * scene.dx,
        spacing,
        scene.output.resolution,
        scene.output.fps,
        up_axis(scene.gravity),
    )
    print(f"wrote {path}")
    return 0


def _rigid_of(scene, traj, path: Path):
    """The scene's ``RigidBodies`` (for their SDF surfaces) and the trajectory's poses per frame,
    or (None, None) for a trajectory without rigid bodies."""
    from cosim.errors import InputError

    if "rigid_names" not in traj:
        return None, None
    from cosim.scene.build import build_system

    rigid = build_system(scene).rigid
    names = [str(n) for n in traj["rigid_names"]]
    if rigid is None or list(rigid.names) != names:
        raise InputError(
            f"{path}: its rigid bodies {names} are not the scene's {list(rigid.names) if rigid else []}; "
            "render it with the scene that wrote it"
        )
    count = len(traj["time"])
    return rigid, [[(traj[f"rigid_pos_{n}"][i], traj[f"rigid_rot_{n}"][i]) for n in names] for i in range(count)]


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {value}")
    return value


def make_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="cosim", description="Differentiable MPM co-simulation for soft-body manipulation."
    )
    p.add_argument(
        "--optimize-kernels",
        action="store_true",
        help="compile Taichi kernels with advanced optimisation: ~1.3x faster kernels for a 1.5-3.6x longer "
        "compile; pays off on long runs (always on for `bench`)",
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
    o.set_defaults(func=cmd_optimize)

    b = sub.add_parser("bench", help="benchmarks: throughput, backward/forward ratio, memory")
    b.add_argument("what", choices=BENCHMARKS)
    b.add_argument("--out", default="out/bench", help="folder for the results (CSV; cloth: JSON)")
    b.add_argument("--quick", action="store_true", help="fewer substeps (a smoke run)")
    b.add_argument(
        "--repeat", type=positive_int, default=3, help="contact, coupling, cloth: repetitions; times are medians"
    )
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
