"""``warp-cloth bench selfcollision``: what self-collision costs per step, on fold and twist.

For each scene (``--scenes``: ``fold``, the default, and ``twist``) and solver (``--solver``,
default all), the scene (``--res`` cells a side, default 16 for fold and 49 for twist, i.e. its
50x50 vertices; 60 fps, each solver's default substeps) runs ``--warmup`` frames with
self-collision: the fold until the lifted half lies on the other (the expensive case: every
vertex near another layer), the twist until its middle has wound up. From that state each
variant runs `SETTLE_FRAMES` frames and then ``--rounds`` timed frames (the median is
reported): with the self-collision pass taken out (``stage.self_collision = None``), and with
it, once with each broad phase (``--broadphase``: the hash grid and the swept-box BVH of
`warp_cloth.collision.broadphase`) and each ``--self-motion`` (0: the response after every
step; 0.25, the default: once a span of steps has moved a vertex a quarter of the thickness,
and at the frame's end, `CollisionStage.plan`). Overhead = with / without - 1, beside the
absolute times, the responses run and the contacts found per timed frame.

A solver whose frame a scene run records as Warp graphs (``solver.capturable``: explicit Euler,
PBD and projective dynamics at their defaults) is timed the same way here, each variant's frame recorded once
(`scene._record_frame`) and replayed; ``--no-capture`` times the launches one by one instead.
Measured (fold 16 x 16, explicit Euler, 93 steps a frame): 0.05 / 0.17 ms a step without /
with self-collision launched one by one (+247 %), but a scene run (`warp-cloth run fold`)
replays the frame without self-collision at 1.6 ms (0.017 ms a step) and with it at 13 ms
(+700 %): the launches' own cost had hidden most of the overhead.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
import warp as wp

from ..util import quiet_warp


#: frames each variant runs from the warm state before its timed frames
SETTLE_FRAMES = 3


def _frame(solver, state, substeps, dt):
    for _ in range(substeps):
        solver.step(state, dt)
    wp.synchronize_device(state.x.device)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench selfcollision", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--solver", nargs="+", default=["implicit", "pd", "explicit", "pbd"])
    p.add_argument("--scenes", nargs="+", default=["fold"], choices=["fold", "twist"])
    p.add_argument("--res", type=int, default=None,
                   help="cells a side (default: 16 for fold, 49 for twist)")
    p.add_argument("--warmup", type=int, default=60, help="frames before timing")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--device", default=None)
    p.add_argument("--broadphase", nargs="+", default=["grid", "bvh"], choices=["grid", "bvh"])
    p.add_argument("--self-motion", default="0,0.25",
                   help="comma-separated CollisionStage self_motion values (default 0,0.25)")
    p.add_argument("--no-capture", action="store_true",
                   help="launch every step's kernels one by one, even where a scene run would "
                        "replay the frame as recorded Warp graphs")
    p.add_argument("--initial-guess", nargs="+", default=["auto"],
                   choices=["inertial", "start", "velocity", "auto"],
                   help="implicit Euler's initial guesses to time (default: auto, its default)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    if (args.res is not None and args.res < 2) or args.warmup < 0 or args.rounds < 1:
        p.error("--res >= 2, --warmup >= 0 and --rounds >= 1")
    try:
        motions = [float(v) for v in args.self_motion.split(",")]
    except ValueError:
        p.error(f"--self-motion: comma-separated numbers, got {args.self_motion!r}")
    if not motions or any(not (v >= 0) for v in motions):
        p.error("--self-motion values must be >= 0")
    quiet_warp()
    from .. import contact_scenes
    from ..scene import _record_frame, _replay, suggest_substeps

    rows = []
    t_all = time.perf_counter()
    cases = [(sn, name, g) for sn in args.scenes for name in args.solver
             for g in (args.initial_guess if name == "implicit" else [None])]
    for scene_name, name, guess in cases:
        res = args.res if args.res is not None else {"fold": 16, "twist": 49}[scene_name]
        options = {"initial_guess": guess} if guess is not None else None
        scene = getattr(contact_scenes, scene_name)(solver=name, res=res, frames=600,
                                                    device=args.device,
                                                    solver_options=options)
        solver, stage = scene.solver, scene.collision
        substeps = suggest_substeps(solver, 1.0 / 60.0)
        dt = 1.0 / (60.0 * substeps)
        state = scene.model.state()
        for _ in range(args.warmup):
            _frame(solver, state, substeps, dt)
        snap = (wp.clone(state.x), wp.clone(state.v), wp.clone(state.time))
        from ..collision.self_collision import SelfCollision

        sc = stage.self_collision
        motion0 = stage.self_motion
        variants = {"without": (None, 0.0)}
        for bp in args.broadphase:
            obj = sc if sc.broad.method == bp else SelfCollision(
                scene.model, sc.thickness, sc.rounds, sc.iterations, broadphase=bp)
            for mo in motions:
                variants[(bp, mo)] = (obj, mo)
        times = {k: [] for k in variants}
        contacts, responses = {}, {}
        captured = bool(solver.capturable and not args.no_capture)
        for variant, (obj, mo) in variants.items():
            stage.self_collision = obj
            stage.self_motion = mo
            stage.plan(substeps)
            graph = (_record_frame(solver, state, dt, substeps, state.x.device)
                     if captured else None)  # records; runs nothing
            wp.copy(state.x, snap[0])
            wp.copy(state.v, snap[1])
            wp.copy(state.time, snap[2])

            def frame():
                if graph is not None:
                    _replay(graph)
                    wp.synchronize_device(state.x.device)
                else:
                    _frame(solver, state, substeps, dt)

            # from the warm state, a few frames with this variant before the timed ones, and
            # the timed frames one after another, as in a run: what the stage and the solver
            # keep between frames (the last response's contacts, held through the next span;
            # contact forces and sags) is then this variant's and belongs to the positions.
            # Before, the positions were restored before each timed frame and the stage's
            # state was the end of the frame timed before (another variant's, for the first):
            # explicit Euler's spans found 20,156 contacts in a frame (+760 %) timed after the
            # every-step variant, 5,039 (+510 %) after none. A frame's responses and contacts
            # still vary with the state (a vertex passing its allowance or not): compare runs
            # over several frames (``--rounds``)
            for _ in range(SETTLE_FRAMES):
                frame()
            before = obj.stats["self_contacts_total"] if obj is not None else 0
            runs = obj.stats["self_responses_total"] if obj is not None else 0
            for _ in range(args.rounds):
                wp.synchronize_device(state.x.device)
                t0 = time.perf_counter()
                frame()
                times[variant].append(time.perf_counter() - t0)
            if obj is not None:  # per frame, over the timed frames
                contacts[variant] = round((obj.stats["self_contacts_total"] - before)
                                          / args.rounds)
                responses[variant] = round((obj.stats["self_responses_total"] - runs)
                                           / args.rounds)
        stage.self_collision = sc
        stage.self_motion = motion0
        stage.plan(substeps)
        wo = 1e3 * statistics.median(times["without"]) / substeps
        for variant in variants:
            if variant == "without":
                continue
            bp, mo = variant
            w = 1e3 * statistics.median(times[variant]) / substeps
            used = getattr(solver, "initial_guess", None)  # the solver's own, not the option
            label = name if used in (None, "auto") else f"{name} ({used})"
            rows.append(dict(scene=scene_name, res=res, solver=label, broadphase=bp, self_motion=mo, substeps=substeps,
                             ms_step_with=w, ms_step_without=wo, overhead=w / wo - 1.0,
                             responses=responses[variant], contacts=contacts[variant],
                             vertices=scene.model.num_vertices, captured=captured))
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"# self-collision cost: {', '.join(args.scenes)}, after {args.warmup} frames, median "
          f"of {args.rounds} rounds; frames replayed as recorded graphs where the solver "
          f"allows it (as a scene run does), else launched one by one\n")
    print("| scene | solver | broad phase | self_motion | substeps/frame | graphs | "
          "ms/step without | ms/step with | overhead | responses in the frame | "
          "contacts in the frame |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} {r['res']}x{r['res']} | {r['solver']} | {r['broadphase']} | "
              f"{r['self_motion']:g} | {r['substeps']} | {'yes' if r['captured'] else 'no'} | "
              f"{r['ms_step_without']:.3f} | {r['ms_step_with']:.3f} | "
              f"{100 * r['overhead']:+.0f} % | {r['responses']} | {r['contacts']} |")
    print(f"\n({time.perf_counter() - t_all:.0f} s)")
    return 0
