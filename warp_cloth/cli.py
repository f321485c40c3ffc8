"""The ``warp-cloth`` command line: ``run``, ``bench``, ``check`` and ``info``.

    warp-cloth run hanging --out hanging.usd [--frames N --fps F --substeps S --res N
                           --solver {explicit,implicit,pbd,pd} --stiffness K --density RHO ...]
    warp-cloth bench NAME [options of that benchmark]
    warp-cloth sweep SPEC.toml|SPEC.json [--workers N --address RAY --executor auto|ray|pool]
    warp-cloth check FILE.usd [--prim PATH --json]
    warp-cloth view FILE.usd [--out PAGE.html --open]
    warp-cloth render FILE.usd --out X.png|X.gif [--frames A:B:STEP --size WxH --camera AZ,EL[,D]]
    warp-cloth info

Bad options and values give a usage error (exit status 2), never a traceback. Exit statuses of
``run``: 0 done, 2 usage error, 3 diverged, 4 the output cannot be written (one-line message),
5 the cloth passed through itself or into an obstacle (``--check-intersections``), 130 interrupted (SIGINT, Ctrl-C), 143 terminated (SIGTERM); the file then holds the frames done.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import signal
import sys
import threading
import warnings


def init_warp(*args, **kwargs):
    """`warp_cloth.util.init_warp`, imported on first use (Warp loads only for commands that
    need it: ``sweep``'s driver and ``--help`` never do)."""
    from .util import init_warp as _init

    return _init(*args, **kwargs)


SCENE_NAMES = ["hanging", "flag", "drape", "table", "spin", "mesh", "thin", "fold", "twist",
               "stack"]
SOLVER_NAMES = ["explicit", "implicit", "pbd", "pd"]
CONTACT_SCENES = ["drape", "table", "spin", "mesh", "thin", "fold", "stack"]
#: scenes whose default solver is not explicit Euler (self-collision at its many substeps is slow)
# projective dynamics with the self-contacts in its solve: on the default fold 0.9 % strain and
# 159 ms/frame against implicit's 3.8 % and 209 (stack: 3.0 %, 150 against 5.4 %, 207)
SCENE_SOLVERS = {"fold": "pd", "twist": "pd", "stack": "pd"}
CONTACT_OPTIONS = ["friction", "restitution", "thickness"]
BENCH_NAMES = ["explicit", "implicit", "pbd", "pd", "contact", "tradeoff", "stability", "ccd", "limits",
               "scale", "selfcollision", "render", "usd", "scenes", "meshes"]

# option -> (solver option name, solvers that accept it)
SOLVER_OPTIONS = {
    "linear": ("linear", ("implicit", "pd")),
    "linear_iterations": ("linear_iterations", ("implicit", "pd")),
    "newton_iterations": ("newton_iterations", ("implicit",)),
    "initial_guess": ("initial_guess", ("implicit",)),
    "smoothing_sweeps": ("smoothing_sweeps", ("implicit", "pd")),
    "iterations": ("iterations", ("pbd", "pd")),
    "gauss_seidel": ("gauss_seidel", ("pbd",)),
    "compliance": ("compliance", ("pbd",)),
    "no_tethers": ("tethers", ("pbd",)),
    "over_relaxation": ("over_relaxation", ("pbd",)),
    "blend": ("blend", ("pbd",)),
}


#: exit statuses of ``run`` (besides 0 and argparse's 2)
EXIT_DIVERGED, EXIT_OUTPUT, EXIT_CROSSINGS, EXIT_SIGINT, EXIT_SIGTERM = 3, 4, 5, 130, 143


class _Terminated(BaseException):
    """Raised in the main thread by the SIGTERM handler, so the run finishes like on Ctrl-C.
    A `BaseException`, like `KeyboardInterrupt`: no ``except Exception`` on the way (the
    runner's fall-back when a frame graph cannot be recorded) may swallow it."""


def _on_sigterm(signum, frame):
    raise _Terminated()


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings during a run as one line, without Python's source location."""
    print(f"warp-cloth: warning: {message}", file=sys.stderr)


def _int_at_least(lowest: int, what: str):
    """An argparse type: an integer >= ``lowest`` (``what`` names it in the error)."""
    def parse(s):
        try:
            v = int(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {s!r}") from None
        if v < lowest:
            raise argparse.ArgumentTypeError(f"expected {what}, got {s!r}")
        return v
    return parse


_positive_int = _int_at_least(1, "a positive integer")
_nonneg_int = _int_at_least(0, "an integer >= 0")


def _positive_float(s):
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {s!r}") from None
    if not (v > 0 and v != float("inf")):
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {s!r}")
    return v


def _nonneg_float(s):
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {s!r}") from None
    if not (v >= 0 and v != float("inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {s!r}")
    return v


def _compliance(s):
    """``--compliance``: a number >= 0 (m/N), ``springs`` (each spring's ``1/k``) or ``none``
    (plain PBD, also where a scene would give PBD a compliance: the twist's moving pins)."""
    if s in ("springs", "none"):
        return s
    try:
        return _nonneg_float(s)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0 (m/N), 'springs' or 'none', "
                                         f"got {s!r}") from None


def _unit_float(s):
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {s!r}") from None
    if not (0.0 <= v <= 1.0):
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {s!r}")
    return v


def _range_pair(s):
    parts = s.split(",")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"expected MIN,MAX, got {s!r}")
    try:
        lo, hi = float(parts[0]), float(parts[1])
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two numbers MIN,MAX, got {s!r}") from None
    if not (0 <= lo <= hi):
        raise argparse.ArgumentTypeError(f"expected 0 <= MIN <= MAX, got {s!r}")
    return lo, hi


def _frame_span(s):
    """``A:B`` (frames A to B, inclusive) or ``A`` (one frame), 1 <= A <= B."""
    parts = s.split(":")
    try:
        lo, hi = (int(parts[0]), int(parts[-1])) if len(parts) in (1, 2) else (0, -1)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected FIRST:LAST frames, got {s!r}") from None
    if not 1 <= lo <= hi:
        raise argparse.ArgumentTypeError(f"expected FIRST:LAST with 1 <= FIRST <= LAST, got {s!r}")
    return lo, hi


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="warp-cloth", description="Cloth simulation on NVIDIA Warp.")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run a scene and write a USD file")
    r.add_argument("scene", choices=SCENE_NAMES)
    r.add_argument("--out", default=None, help="output .usd (default: SCENE.usd)")
    r.add_argument("--frames", type=_positive_int, default=None, help="frames written, incl. frame 0")
    r.add_argument("--fps", type=_positive_float, default=60.0)
    r.add_argument("--substeps", type=_positive_int, default=None,
                   help="solver steps per frame (default: the solver's choice; explicit derives "
                        "it from its stability bound)")
    r.add_argument("--res", type=_positive_int, default=None, help="cells along each side")
    r.add_argument("--solver", choices=SOLVER_NAMES, default=None,
                   help="default: the scene's own (pd for fold, twist and stack, explicit "
                        "otherwise)")
    r.add_argument("--stiffness", type=_nonneg_float, default=None, help="stretch springs, N/m")
    r.add_argument("--density", type=_positive_float, default=None, help="kg/m^2")
    r.add_argument("--bending", choices=["none", "springs", "dihedral", "quadratic"], default=None)
    r.add_argument("--bend-stiffness", type=_nonneg_float, default=None,
                   help="N/m (springs) or N m (dihedral, quadratic)")
    r.add_argument("--damping", type=_nonneg_float, default=None, help="velocity damping, 1/s")
    r.add_argument("--linear", choices=["jacobi", "chebyshev", "cg", "cholesky"], default=None,
                   help="inner linear solver (implicit, pd; cholesky: CG with a banded Cholesky factor "
                        "of the matrix, pd's default on the CPU without contact)")
    r.add_argument("--linear-iterations", type=_positive_int, default=None,
                   help="inner iterations per Newton or global step (implicit, pd; default: "
                        "the inner solver's: pd's cholesky 1 without contact, CG 20)")
    r.add_argument("--newton-iterations", type=_positive_int, default=None, help="implicit")
    r.add_argument("--initial-guess", choices=["inertial", "start", "velocity", "auto"],
                   default=None,
                   help="implicit: where Newton starts (default auto: x0 + dt v0 in steps "
                        "with contact, the inertial guess in the others; inertial: the guess "
                        "of the figures measured before 2026-12-06)")
    r.add_argument("--smoothing-sweeps", type=_nonneg_int, default=None, metavar="N",
                   help="implicit, pd: Gauss-Seidel sweeps on the step's potential after its "
                        "solve (implicit: one that stopped short; default 4; pd: default 0)")
    r.add_argument("--iterations", type=_positive_int, default=None, help="pbd, pd")
    r.add_argument("--gauss-seidel", action="store_true", default=None, help="pbd: coloured GS")
    r.add_argument("--compliance", type=_compliance, default=None,
                   help="pbd: XPBD compliance, m/N, or 'springs' (each spring's 1/k; the twist's "
                        "default) or 'none' (plain PBD)")
    r.add_argument("--no-tethers", action="store_const", const=False, default=None,
                   help="pbd: no long-range attachments to the pins (on by default with pins)")
    r.add_argument("--over-relaxation", type=_positive_float, default=None, metavar="OMEGA",
                   help="pbd: Jacobi blend over-relaxation in (0, 2) (default 1.7; 1: no "
                        "over-relaxation)")
    r.add_argument("--blend", choices=["constraint", "vertex"], default=None,
                   help="pbd: Jacobi corrections shared per constraint (default: keeps the "
                        "momentum) or averaged per vertex (the notes' blend, gains energy)")
    r.add_argument("--strain-limit", type=_range_pair, default=None, metavar="SMIN,SMAX")
    r.add_argument("--area-limit", type=_range_pair, default=None, metavar="AMIN,AMAX")
    r.add_argument("--friction", type=_nonneg_float, default=None,
                   help="contact scenes: Coulomb friction coefficient mu_T")
    r.add_argument("--restitution", type=_unit_float, default=None,
                   help="contact scenes: normal restitution mu_N in [0, 1]")
    r.add_argument("--thickness", type=_positive_float, default=None,
                   help="contact scenes: contact thickness in m")
    r.add_argument("--obstacle", default=None, metavar="FILE",
                   help="mesh scene: drop the sheet on this mesh (.obj, .usd, .usda, .usdc) "
                        "instead of the moving torus; it stands still on the floor, centred, "
                        "the sheet 0.1 m above its top")
    r.add_argument("--obstacle-scale", type=_positive_float, default=None, metavar="S",
                   help="with --obstacle: metres per file unit for an OBJ (default 1), a "
                        "further factor for a USD mesh (already in metres)")
    r.add_argument("--save-interval", type=_nonneg_float, default=2.0, metavar="SECONDS",
                   help="wall time between saves of the output (default 2; 0: every frame); a "
                        "crash loses at most the frames since the last save")
    r.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument("--verbose", action="store_true",
                   help="Warp's own messages: start-up, module loads, a missing CUDA driver")
    r.add_argument("--json", action="store_true", help="print the run statistics as JSON")
    r.add_argument("--self-collision", choices=["on", "off"], default=None,
                   help="keep the cloth from passing through itself (default: on in every "
                        "scene)")
    r.add_argument("--check-intersections", action="store_true",
                   help="count the cloth's crossing edge-triangle pairs in every frame, and its "
                        "edges inside the obstacles (warning per frame with any; exit status 5 "
                        "if any)")
    r.add_argument("--retries", type=_int_at_least(0, "an integer in [0, 8]"), default=None,
                   metavar="N",
                   help="a frame in which a self-collision step failed (the whole cloth returned "
                        "to its start or frozen into impact zones, contacts dropped for want "
                        "of room, or an edge over-stretched by the collision response) runs again from its start with 2, 4, ... times the steps, up to "
                        "N times (default 2; 0: off)")
    r.add_argument("--ledger", type=_frame_span, default=None, metavar="FIRST:LAST",
                   help="print where the energy of frames FIRST to LAST went, per stage of each "
                        "step (solve, limits, obstacle contact, features, self-collision; "
                        "`warp_cloth.ledger`); the run is eager and slower")
    r.add_argument("--preview", action="store_true",
                   help="also write a PNG of the last frame beside the USD (OUT with .png)")

    b = sub.add_parser("bench", help="benchmarks: warp-cloth bench NAME --help",
                       add_help=False)
    b.add_argument("name", choices=BENCH_NAMES)
    b.add_argument("args", nargs=argparse.REMAINDER)

    w = sub.add_parser("sweep", help="many runs from a spec file, on Ray or a process pool "
                       "(resumable; results CSV)")
    from .sweep import add_arguments as _sweep_arguments

    _sweep_arguments(w)

    c = sub.add_parser("check", help="intersections per frame of a USD file's meshes (each "
                       "mesh through itself and through the others) and animated mesh edges "
                       "inside its spheres and cubes")
    c.add_argument("file", help="a .usd/.usda/.usdc/.usdz with one or more meshes (animated "
                   "or not)")
    c.add_argument("--prim", action="append", default=None, metavar="PATH",
                   help="check only this mesh prim (repeat for several; default: every mesh)")
    c.add_argument("--no-solids", action="store_true",
                   help="do not test the animated meshes against the stage's spheres and cubes "
                        "(for a stage whose spheres and cubes are not solid obstacles)")
    c.add_argument("--json", action="store_true", help="print the counts as JSON")

    _add_view_parsers(sub)
    sub.add_parser("info", help="versions and devices")
    return p


def _add_view_parsers(sub):
    v = sub.add_parser("view", help="write a self-contained HTML page that plays a USD file")
    v.add_argument("file", help="a .usd/.usda/.usdc with meshes (time-sampled or not)")
    v.add_argument("--out", default=None, help="the page to write (default: FILE with .html)")
    v.add_argument("--open", action="store_true", help="open the page in the default browser")
    g = sub.add_parser("render", help="ray-cast PNG or GIF previews of a USD file (Warp kernels)")
    g.add_argument("file", help="a .usd/.usda/.usdc with meshes (time-sampled or not)")
    g.add_argument("--out", required=True, help="X.png (one frame) or X.gif (an animation)")
    g.add_argument("--frames", default=None, metavar="A:B:STEP",
                   help="frame indices, Python slice syntax (default: the last frame for a PNG, "
                        "every frame for a GIF); a PNG takes the last frame selected")
    g.add_argument("--size", default="640x480", metavar="WxH", help="pixels (default 640x480)")
    g.add_argument("--camera", default=None, metavar="AZ,EL[,DIST]",
                   help="degrees around the up axis (0: from the front), degrees above the "
                        "horizon, metres from the centre (default 30,25 and a distance that "
                        "frames the bounds of the frames drawn, floors left out)")
    g.add_argument("--fov", type=_positive_float, default=40.0, help="vertical field of view, "
                   "degrees (default 40)")
    g.add_argument("--supersample", type=_positive_int, default=1,
                   help="rays per pixel along each axis (anti-aliasing)")
    g.add_argument("--no-shadows", action="store_true", help="skip the shadow rays")
    g.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0")


def _corrections(args):
    out = []
    if args.strain_limit is not None or args.area_limit is not None:
        from . import limits

        if args.strain_limit is not None:
            lo, hi = args.strain_limit
            out.append(lambda model, lo=lo, hi=hi: limits.StrainLimit(model, lo, hi))
        if args.area_limit is not None:
            lo, hi = args.area_limit
            out.append(lambda model, lo=lo, hi=hi: limits.AreaLimit(model, lo, hi))
    return out


def cmd_run(args, parser) -> int:
    init_warp(verbose=args.verbose, device=args.device)
    from .errors import SimulationDiverged
    from .scenes import build_scene

    if args.solver is None:
        args.solver = SCENE_SOLVERS.get(args.scene, "explicit")
    solver_options = {}
    for opt, (name, solvers) in SOLVER_OPTIONS.items():
        val = getattr(args, opt)
        if val is None:
            continue
        if args.solver not in solvers:
            parser.error(f"--{opt.replace('_', '-')} applies to --solver {'/'.join(solvers)}, "
                         f"not {args.solver}")
        solver_options[name] = None if (opt == "compliance" and val == "none") else val
    kw = dict(solver=args.solver, solver_options=solver_options, fps=args.fps,
              substeps=args.substeps, corrections=_corrections(args))
    for opt, name in (("frames", "frames"), ("res", "res"), ("stiffness", "stiffness"),
                      ("density", "density"), ("bending", "bending"),
                      ("bend_stiffness", "bend_stiffness"), ("damping", "damping"),
                      ("device", "device")):
        val = getattr(args, opt)
        if val is not None:
            kw[name] = val
    if args.self_collision is not None:
        kw["self_collision"] = args.self_collision == "on"
    for opt in CONTACT_OPTIONS:
        val = getattr(args, opt)
        if val is None:
            continue
        if args.scene not in CONTACT_SCENES:
            parser.error(f"--{opt} applies to the contact scenes {'/'.join(CONTACT_SCENES)}, "
                         f"not {args.scene}")
        kw[opt] = val
    if args.obstacle_scale is not None and args.obstacle is None:
        parser.error("--obstacle-scale applies with --obstacle")
    if args.obstacle is not None:
        if args.scene != "mesh":
            parser.error(f"--obstacle applies to the mesh scene, not {args.scene}")
        from .collision.motion import KeyframePath
        from .contact_scenes import load_obstacle_mesh

        try:
            tm, position, height = load_obstacle_mesh(args.obstacle, args.obstacle_scale or 1.0)
        except ValueError as e:
            parser.error(f"--obstacle: {e}")
        kw.update(mesh_file=tm, scale=args.obstacle_scale or 1.0, position=position,
                  height=height, path=KeyframePath([0.0], [[0.0, 0.0, 0.0]]))
    out = args.out or f"{args.scene}.usd"
    ext = os.path.splitext(out)[1].lower()
    if ext not in (".usd", ".usda", ".usdc"):
        parser.error(f"--out must name a .usd, .usda or .usdc file, got {out!r}")
    if not os.path.isdir(os.path.dirname(os.path.abspath(out))):
        parser.error(f"--out: directory {os.path.dirname(os.path.abspath(out))!r} does not exist")
    if args.retries is not None and args.retries > 8:
        parser.error(f"--retries: expected an integer in [0, 8], got {args.retries}")
    try:
        scene = build_scene(args.scene, **kw)
    except (ValueError, TypeError, RuntimeError) as e:
        parser.error(str(e))
    except MemoryError as e:  # (--res 1000000: 7 TiB of vertices)
        from .usd import _one_line

        parser.error(f"the scene does not fit in this machine's memory ({_one_line(e)}): "
                     "lower --res")
    if args.retries is not None:
        scene.retries = args.retries
    ledger = None
    if args.ledger is not None:
        if args.ledger[1] >= scene.frames:
            parser.error(f"--ledger: frame {args.ledger[1]} is past the run's last frame "
                         f"({scene.frames - 1})")
        from .ledger import EnergyLedger

        ledger = EnergyLedger(scene, frames=args.ledger)
    from .errors import OutputError

    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if main_thread else None
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            stats = scene.run(out, quiet=args.quiet, save_interval=args.save_interval,
                              check_intersections=args.check_intersections)
    except ValueError as e:  # a start the run refuses (before anything is written)
        print(f"warp-cloth: {e}", file=sys.stderr)
        return 2
    except SimulationDiverged as e:
        print(f"warp-cloth: {e}; {out} holds the frames before it", file=sys.stderr)
        if args.preview and os.path.isfile(out):
            _write_preview(out, args.device)
        return EXIT_DIVERGED
    except KeyboardInterrupt:
        print(f"\nwarp-cloth: interrupted; {out} holds the frames done so far", file=sys.stderr)
        return EXIT_SIGINT
    except _Terminated:
        print(f"\nwarp-cloth: terminated (SIGTERM); {out} holds the frames done so far",
              file=sys.stderr)
        return EXIT_SIGTERM
    except OutputError as e:
        print(f"warp-cloth: {e}", file=sys.stderr)
        return EXIT_OUTPUT
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    if args.json:
        d = stats.as_dict()
        if ledger is not None:  # one JSON document: the ledger's steps under "ledger"
            d["ledger"] = ledger.as_list()
        print(json.dumps(d, indent=2, default=str))
    else:
        print(stats.summary())
        if ledger is not None:
            print(ledger.report())
    if args.preview:
        _write_preview(out, args.device)
    if stats.crossing_frames or stats.obstacle_frames:
        if stats.crossing_frames:
            print(f"warp-cloth: the cloth passes through itself in {stats.crossing_frames} frames",
                  file=sys.stderr)
        if stats.obstacle_frames:
            print(f"warp-cloth: the cloth is inside an obstacle in {stats.obstacle_frames} frames "
                  f"(deepest {1e3 * stats.obstacle_depth:.3f} mm)", file=sys.stderr)
        return EXIT_CROSSINGS
    return 0


def cmd_bench(args, parser) -> int:
    dev = args.args[args.args.index("--device") + 1] if "--device" in args.args[:-1] else None
    init_warp(device=dev)  # quiet; a CUDA --device still shows why CUDA is missing
    try:
        mod = importlib.import_module(f"warp_cloth.bench.{args.name}")
    except ImportError:
        parser.error(f"benchmark {args.name!r} is not available in this installation")
    return int(mod.main(args.args) or 0)


def cmd_info() -> int:
    import warp as wp

    from . import __version__
    from .solvers import available

    init_warp()
    print(f"warp_cloth {__version__}")
    print(f"warp {wp.__version__}")
    try:
        from pxr import Usd

        print(f"usd {'.'.join(str(v) for v in Usd.GetVersion())}")
    except ImportError:
        print("usd: not installed")
    print(f"python {sys.version.split()[0]}")
    print("devices: " + ", ".join(f"{d.alias} ({d.name})" for d in wp.get_devices()))
    if not wp.is_cuda_available():
        print("cuda: not available (no NVIDIA CUDA driver found)")
    print("solvers: " + ", ".join(available()))
    print(f"kernel cache: {wp.config.kernel_cache_dir}")
    return 0


def cmd_check(args, parser) -> int:
    """Per frame, the (edge, triangle) pairs of the stage's meshes that pass through each other
    (sharing no vertex), within each mesh and between meshes, in world space, and the points
    along the animated meshes' edges inside the stage's spheres and cubes (`solid_depths`).
    Exit status 1 when any frame has one or a non-finite point, 2 on an unreadable file."""
    import json

    init_warp()
    path = args.file
    if not os.path.isfile(path):
        parser.error(f"check: no such file: {path}")
    try:
        from .usd import read_meshes

        times, tracks = read_meshes(path, args.prim)
        from .usd import read_solids

        solids = [] if args.no_solids else read_solids(path, times)
    except Exception as e:  # noqa: BLE001 - any unreadable stage is a usage error here
        print(f"warp-cloth check: cannot read meshes from {path}: {e}", file=sys.stderr)
        return 2
    from .collision.check import check_meshes, solid_depths

    rep = check_meshes(tracks)
    dep = solid_depths(tracks, solids)
    per_frame, nonfinite = rep["crossings"], rep["nonfinite"]
    bad = [i for i, c in enumerate(per_frame) if c]
    broken = [i for i, c in enumerate(nonfinite) if c]
    inside = [i for i, c in enumerate(dep["inside"]) if c]
    if args.json:
        print(json.dumps({"file": path, "frames": len(per_frame),
                          "times": [None if t != t else float(t) for t in times],
                          "crossings": per_frame, "frames_with_crossings": len(bad),
                          "meshes": [t.path for t in tracks], "per_mesh": rep["per_mesh"],
                          "between": rep["between"], "between_rigid": rep["between_rigid"],
                          "nonfinite": nonfinite,
                          "frames_with_nonfinite": len(broken),
                          "solids": [f"{x.path} ({x.kind})" for x in solids],
                          "inside_solids": dep["inside"], "inside_depth": dep["depth"],
                          "frames_inside_solids": len(inside)}))
    else:
        names = [t.path for t in tracks]
        print(f"{path}: {len(names)} mesh{'es' if len(names) != 1 else ''} "
              f"({', '.join(names)}), {len(per_frame)} frame{'s' if len(per_frame) != 1 else ''}")
        for f, t in enumerate(times):
            label = "default time" if t != t else f"time {t:g}"
            if nonfinite[f]:
                print(f"{label}: {nonfinite[f]} non-finite point(s), not checked")
                continue
            parts = [f"{n} {rep['per_mesh'][n][f]}" for n in names if rep["per_mesh"][n][f]]
            if rep["between"][f]:
                parts.append(f"between meshes {rep['between'][f]}")
            detail = f" ({'; '.join(parts)})" if parts and len(names) > 1 else ""
            rigid = rep["between_rigid"][f]
            note = (f"; {rigid} between rigid meshes (layout, not counted)" if rigid else "")
            if dep["inside"][f]:
                note += (f"; {dep['inside'][f]} edge point(s) inside the solids, deepest "
                         f"{1e3 * dep['depth'][f]:.3f} mm")
            print(f"{label}: {per_frame[f]} crossing (edge, triangle) pairs{detail}{note}")
        print(f"{len(bad)} of {len(per_frame)} frames with crossings; most in a frame: "
              f"{max(per_frame) if per_frame else 0}"
              + (f"; {len(broken)} with non-finite points" if broken else ""))
        if solids:
            print(f"{len(inside)} of {len(per_frame)} frames with animated mesh edges inside "
                  f"the {len(solids)} sphere/cube solid(s)"
                  + (f"; deepest {1e3 * max(dep['depth']):.3f} mm" if inside else ""))
    return 1 if bad or broken or inside else 0


def _read_playback(path, parser, command):
    """The stage's animation, or a one-line usage error naming the file."""
    from .viewer.playback import read_playback

    if not os.path.isfile(path):
        parser.error(f"{command}: no such file: {path}")
    if os.path.splitext(path)[1].lower() not in (".usd", ".usda", ".usdc", ".usdz"):
        parser.error(f"{command}: expected a .usd, .usda, .usdc or .usdz file, got {path!r}")
    try:
        return read_playback(path)
    except ValueError as e:
        parser.error(f"{command}: {e}")


def cmd_view(args, parser) -> int:
    """Write the player page (and open it with --open)."""
    from .viewer.page import write_page

    out = args.out or os.path.splitext(args.file)[0] + ".html"
    if not out.lower().endswith((".html", ".htm")):
        parser.error(f"view: --out must name an .html file, got {out!r}")
    if not os.path.isdir(os.path.dirname(os.path.abspath(out))):
        parser.error(f"view: --out: directory {os.path.dirname(os.path.abspath(out))!r} "
                     "does not exist")
    pb = _read_playback(args.file, parser, "view")
    size = write_page(pb, out)
    verts = sum(p.num_vertices for p in pb.parts)
    print(f"wrote {out}: {pb.num_frames} frames, {len(pb.parts)} prims, {verts} vertices, "
          f"{size / 1e6:.2f} MB")
    if args.open:
        import pathlib
        import webbrowser

        if not webbrowser.open(pathlib.Path(os.path.abspath(out)).as_uri()):
            print(f"view: no browser could be started here; open {out} in one", file=sys.stderr)
    return 0


def render_file(path, out, *, frames=None, size=(640, 480), camera=None, fov=40.0,
                supersample=1, shadows=True, device=None, parser=None, playback=None):
    """Render ``path`` (a USD file) to ``out`` (.png: one frame; .gif: the frames selected).
    ``frames`` is an A:B:STEP string, ``camera`` an AZ,EL[,DIST] string. Returns the number of
    frames written. Raises ValueError on bad input (or ``parser.error`` when given one)."""
    from .viewer.playback import read_playback
    from .viewer.render import Camera, Renderer, parse_camera, parse_frames, save_gif, save_png

    def bad(msg):
        if parser is not None:
            parser.error(f"render: {msg}")
        raise ValueError(msg)

    ext = os.path.splitext(out)[1].lower()
    if ext not in (".png", ".gif"):
        bad(f"--out must name a .png or .gif file, got {out!r}")
    if not os.path.isdir(os.path.dirname(os.path.abspath(out))):
        bad(f"--out: directory {os.path.dirname(os.path.abspath(out))!r} does not exist")
    try:
        cam_spec = parse_camera(camera) if camera is not None else (30.0, 25.0, None)
    except ValueError as e:
        bad(str(e))
    if playback is None:
        playback = _read_playback(path, parser, "render") if parser else read_playback(path)
    try:
        if frames is None:
            idx = [playback.num_frames - 1] if ext == ".png" else list(range(playback.num_frames))
        else:
            idx = parse_frames(frames, playback.num_frames)
    except ValueError as e:
        bad(str(e))
    w, h = size
    az, el, dist = cam_spec
    # frame what is drawn: the one frame of a PNG, the frames of a GIF
    shown = idx[-1:] if ext == ".png" else idx
    cam = Camera.framing(playback.bounds(frames=shown), playback.up_axis, az, el, dist, fov, w / h)
    r = Renderer(playback, w, h, cam, supersample=supersample, shadows=shadows, device=device)
    try:
        images = [r.render(i) for i in (idx[-1:] if ext == ".png" else idx)]
    except ValueError as e:  # a part that cannot be drawn (nothing is written)
        bad(str(e))
    if ext == ".png":
        save_png(images[-1], out)
        return 1
    step = idx[1] - idx[0] if len(idx) > 1 else 1
    times = playback.times
    dt = (times[idx[1]] - times[idx[0]]) / playback.time_codes_per_second if len(idx) > 1 else 0
    fps = 1.0 / dt if dt > 0 else playback.fps / step
    save_gif(images, out, fps)
    return len(idx)


def cmd_render(args, parser) -> int:
    from .viewer.render import parse_size

    init_warp(device=args.device)
    try:
        size = parse_size(args.size)
    except ValueError as e:
        parser.error(f"render: {e}")
    if args.device is not None:
        import warp as wp

        try:
            wp.get_device(args.device)
        except Exception as e:  # noqa: BLE001 - Warp raises RuntimeError/ValueError here
            parser.error(f"render: --device {args.device!r}: {e}")
    n = render_file(args.file, args.out, frames=args.frames, size=size, camera=args.camera,
                    fov=args.fov, supersample=args.supersample, shadows=not args.no_shadows,
                    device=args.device, parser=parser)
    print(f"wrote {args.out}: {n} frame{'s' if n != 1 else ''}, {size[0]}x{size[1]}")
    return 0


def _write_preview(usd_path, device=None) -> None:
    """``run --preview``: a PNG of the last frame beside the USD."""
    png = os.path.splitext(usd_path)[0] + ".png"
    render_file(usd_path, png, device=device)
    print(f"preview: {png}", file=sys.stderr)  # stderr: keeps --json output parseable


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "run":
        return cmd_run(args, parser)
    if args.command == "bench":
        return cmd_bench(args, parser)
    if args.command == "check":
        return cmd_check(args, parser)
    if args.command == "sweep":  # the driver never loads Warp: its workers do (`sweep.warm`)
        from .sweep import cmd_sweep

        return cmd_sweep(args)
    if args.command == "view":
        return cmd_view(args, parser)
    if args.command == "render":
        return cmd_render(args, parser)
    return cmd_info()


if __name__ == "__main__":
    sys.exit(main())
