"""``warp-cloth bench contact``: what obstacle contact adds to a step, at equal solver work.

The drape scene (a free 1 m sheet, ``--res`` cells a side, 0.15 kg/m^2, 1000 N/m, dropped from
0.9 m; 60 fps, each solver's default substeps) with one `ObstacleContact` per configuration:

- ``sphere``: the analytic `Sphere` (r = 0.3 m, centre (0, 0.5, 0));
- ``sphere+plane``: the sphere and a ground plane (two analytic obstacles, one launch);
- ``mesh sphere``: `MeshObstacle` of ``warp_cloth/assets/sphere.obj`` (960 triangles) scaled to the
  same sphere, through Warp's BVH queries;
- ``spinning sphere``: the analytic sphere spinning (adds the per-step pose launch).

**Method.** For every solver (``--solver``, default all) and configuration, the cloth first runs
``--warmup`` frames with contact so that it lies draped on the obstacle (the expensive case: many
vertices within the contact thickness). Then every device array of the state, the solver, its
linear solver and the contact (its caches included) is snapshotted, and one frame of substeps is
recorded twice as a Warp graph on the *same* solver and state objects: with the collision stage,
and with it taken out (``solver.collision = None``, and the solver's ``x_start`` copy switched
off, as in a solver built without obstacles; both are put back after recording).
Before every timed frame the snapshot is restored (outside the timed region), so both variants
start each frame from the same draped state with the same warm starts: the baseline does the
solver's own work on the draped state, not the (cheaper, for iterative solvers) work of a free
fall. Overhead = t_with / t_without - 1. Timed frames alternate between the variants and
configurations of all solvers (the order rotates each round) so that load from other processes
spreads over all of them; the median of the ``--rounds`` round means counts.

Equal work needs a solver whose work per step does not depend on the state: explicit Euler,
position-based and projective dynamics run fixed iteration counts; the implicit solver's default
Newton and CG tolerances do not (contact changes the state after the first substep, and with it
the CG count), so it runs here with fixed counts close to those the tolerances give on the draped
cloth (`EQUAL_WORK_OPTIONS`), which also makes its step capturable. ``--adaptive`` keeps its
defaults instead: its step is then timed as a Python loop and its Newton / CG iteration counts per
frame, with and without contact, are reported.

What the overhead contains: the ``x_start`` copy and the contact launches (for position-based
dynamics the contact projection runs inside every constraint iteration, and the velocity update
that the last iteration would otherwise fuse runs as its own launch; for implicit Euler and
projective dynamics the detection of the step's contacts into the record, the contact term in
every Newton assembly or local step, the per-vertex contact blocks in every matrix product, and
the final ``resolve``).

**Floor row** (explicit solver, static sphere): a hand-written kernel here that does the complete
contact for exactly that sphere (far test by squared lengths, the sphere's continuous test for
paths longer than the slack, projection to the thickness, impulse with restitution 0 and Coulomb
friction) and nothing else, run as a separate correction pass on the same solver and snapshot:
what a per-vertex contact pass written for this one case costs on this machine (no target). Its
positions after one frame are compared with those of `ObstacleContact` (``floor_max_deviation``
in ``--json``: 0 when both compute the same thing). `ObstacleContact` runs static spheres and
planes inside explicit Euler's own vertex update, so it can come out at or below the floor.

Targets (issue 5): analytic < 20 %, mesh (~1,000 triangles) < 50 %.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
import warp as wp

from ..collision.response import impulse
from ..util import quiet_warp
from .common import capture, markdown_table

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

TARGETS = {"sphere": 0.20, "sphere+plane": 0.20, "spinning sphere": 0.20, "mesh sphere": 0.50}
FLOOR = "sphere (floor: hand-specialised kernel)"
CENTER = (0.0, 0.5, 0.0)
RADIUS = 0.3
#: default frames per solver (warm-up, timed per variant and round): a frame of the iterative
#: solvers costs several times one of the explicit solver, and they drape in fewer frames
DEFAULTS = {"explicit": (45, 10), "implicit": (30, 4), "pbd": (30, 3), "pd": (30, 6)}
#: solver options for equal work: the implicit solver's default tolerances make its Newton and CG
#: iteration counts depend on the state (and its step uncapturable); fixed counts close to what
#: the tolerances give on the draped cloth (8 Newton x 22-26 CG per step) keep both variants equal.
#: No smoothing sweeps: they run only in steps without contact entries, so the frame without
#: obstacles paid 4 Gauss-Seidel sweeps a step that the frame with them skips (3.4 of its 15.6 ms
#: of kernels), and contact measured -10 to -15 % ("cheaper than none").
#: ``--adaptive`` uses the defaults instead.
EQUAL_WORK_OPTIONS = {"implicit": dict(tolerance=None, newton_iterations=8, linear_iterations=25,
                                       linear_tolerance=None, smoothing_sweeps=0)}


def _configs():
    from ..collision import MeshObstacle, Motion, Plane, Sphere
    from ..contact_scenes import asset_path

    c = CENTER
    return {
        "sphere": lambda: [Sphere(RADIUS, c)],
        "sphere+plane": lambda: [Sphere(RADIUS, c), Plane()],
        "mesh sphere": lambda: [MeshObstacle(asset_path("sphere.obj"), scale=RADIUS, position=c)],
        "spinning sphere": lambda: [Sphere(RADIUS, c, motion=Motion(angular_velocity=(0, 1.0, 0)))],
    }


# ---------------------------------------------------------------------- the floor
@wp.kernel
def floor_sphere_kernel(x: wp.array(dtype=wp.vec3), x_start: wp.array(dtype=wp.vec3),
                        v: wp.array(dtype=wp.vec3), center: wp.vec3, radius: float,
                        thickness: float, slack: float, mu: float):
    """Complete contact with one static sphere, nothing else (no pins: the sheet has none)."""
    i = wp.tid()
    x1 = x[i]
    x0 = x_start[i]
    p1 = x1 - center
    reach = thickness + slack
    d = x1 - x0
    s2 = wp.dot(d, d)
    short = s2 <= slack * slack
    if short:  # far exactly when the end is (squared lengths)
        rr = radius + reach
        if wp.dot(p1, p1) >= rr * rr:
            return
    l1 = wp.length(p1)
    phi = l1 - radius
    if not short and phi >= reach:
        g = phi - thickness
        if g * g >= s2:
            return
    p0 = x0 - center
    n = wp.vec3(0.0, 1.0, 0.0)
    if l1 > 1.0e-9:
        n = p1 / l1
    moved = False
    # continuous test (paths longer than the slack): first entry of p0 -> p1 into the sphere
    # inflated by the thickness
    r = radius + thickness
    dl = p1 - p0
    qa = wp.dot(dl, dl)
    qb = wp.dot(p0, dl)
    qc = wp.dot(p0, p0) - r * r
    if qc > 0.0 and qa > slack * slack:
        disc = qb * qb - qa * qc
        if disc >= 0.0:
            t = (-qb - wp.sqrt(disc)) / qa
            if t >= 0.0 and t <= 1.0:
                nh = wp.normalize(p0 + t * dl)
                p1 = p1 + wp.max(-wp.dot(p1 - (p0 + t * dl), nh), 0.0) * nh
                l1 = wp.length(p1)
                phi = l1 - radius
                n = p1 / l1
                moved = True
    if phi < thickness:
        p1 = p1 + (thickness - phi) * n
        moved = True
    if moved or phi < reach:
        vnew, a = impulse(v[i], wp.vec3(0.0), n, 0.0, mu)
        dd = p1 - p0
        d_t = dd - wp.dot(dd, n) * n
        x[i] = p1 - (1.0 - a) * d_t + center
        v[i] = vnew


class FloorSphereContact:
    """The floor correction: `floor_sphere_kernel` for the static sphere of ``contact``."""

    capturable = True

    def __init__(self, model, contact):
        self.model = model
        self.thickness, self.slack = contact.thickness, contact.slack
        self.friction = contact.friction
        # the radius the contact's kernels see (its pad: `obstacles.sphere_contact_pad`)
        self.radius = RADIUS + max(contact.pads)
        if np.any(model.inverse_masses == 0):
            raise ValueError("the floor kernel skips the pinned-vertex test: the sheet has no pins")

    def apply(self, state, x_start, dt):
        wp.launch(floor_sphere_kernel, self.model.num_vertices,
                  [state.x, x_start, state.v, wp.vec3(*CENTER), self.radius, self.thickness,
                   self.slack, self.friction], device=self.model.device)


# ---------------------------------------------------------------------- set-up
def _device_arrays(*objs):
    """The contiguous device arrays held by ``objs`` (state, solver, contact...): their
    attributes, and the fields of the Warp struct instances among them (a contact's caches)."""
    out, seen = [], set()

    def add(values):
        for a in values:
            if isinstance(a, wp.array):
                if a.is_contiguous and a.size and id(a) not in seen:
                    seen.add(id(a))
                    out.append(a)
            elif hasattr(getattr(a, "_cls", None), "vars"):  # a wp.struct instance
                add(getattr(a, name) for name in a._cls.vars)

    for o in objs:
        if o is not None:
            add(vars(o).values())
    return out


class Setup:
    """One solver on one configuration: the draped snapshot and one variant per correction list
    (``without``: none; ``with``: the ObstacleContact; ``floor``: the floor kernel)."""

    def __init__(self, solver_name, config, make, args, warmup, floor=False, options=None):
        from ..collision import ObstacleContact
        from ..contact_scenes import sheet_model
        from ..scene import suggest_substeps
        from ..solvers import make_solver

        self.solver_name, self.config = solver_name, config
        self.model = model = sheet_model(res=args.res, height=0.9, device=args.device)
        self.device = model.device
        self.options = dict(options or {})
        self.solver = solver = make_solver(solver_name, model, **self.options)
        self.contact = contact = ObstacleContact(model, make())
        solver.set_collision(contact)
        stage = solver.collision
        self.substeps = args.substeps or suggest_substeps(solver, 1.0 / 60.0)
        self.dt = 1.0 / (60.0 * self.substeps)
        self.state = model.state()
        self.captured = bool(solver.capturable)
        self.work = {}  # variant -> [newton, inner] iterations of the last uncaptured frame

        x_start = solver._x_start
        # variant -> (corrections, collision stage, x_start)
        self.variants = {"without": ([], None, None), "with": ([], stage, x_start)}
        if floor:
            self.variants["floor"] = ([FloorSphereContact(model, contact)], None, x_start)
        self.graphs = {}

        self._use("with")
        self.frame("with")  # compile
        wp.synchronize_device(self.device)
        if self.captured:
            self.graphs["with"] = capture(lambda: self.frame("with"), self.device)
        for _ in range(warmup):
            self.run("with")
        wp.synchronize_device(self.device)

        linear = getattr(solver, "linear", None)
        coupling = getattr(solver, "_coupling", None)
        self._arrays = _device_arrays(self.state, solver, linear, getattr(solver, "A", None),
                                      getattr(solver, "operator", None), contact, stage,
                                      coupling)
        self._snap = [wp.clone(a) for a in self._arrays]
        for name in self.variants:
            if name == "with":
                continue
            self._use(name)
            self.frame(name)  # load any module the variant needs (none expected)
            wp.synchronize_device(self.device)
            if self.captured:
                self.graphs[name] = capture(lambda n=name: self.frame(n), self.device)
        self._use("with")
        self.restore()
        self.in_contact = self._count_contacts()
        self.times = {name: [] for name in self.variants}

    def _count_contacts(self) -> int:
        """Vertices within ``thickness + slack`` of an obstacle (beyond its pad,
        `ObstacleContact.contact_distances`) at the snapshot or at the end of some substep of
        one frame from it (with contact); host reads, not timed."""
        c = self.contact
        reach = c.thickness + c.slack + 1e-4
        touched = np.zeros(self.model.num_vertices, dtype=bool)
        for k in range(self.substeps + 1):
            if k:
                self.solver.step(self.state, self.dt)
            touched |= c.contact_distances(self.state.positions(), self.state.t).min(axis=0) < reach
        self.restore()
        return int(touched.sum())

    def _use(self, name):
        corrections, stage, x_start = self.variants[name]
        self.solver.corrections = list(corrections)
        self.solver.collision = stage
        self.solver._x_start = x_start

    def frame(self, name):
        """One frame of substeps, as the solver is configured now (``_use``)."""
        count = not self.captured
        newton = inner = 0
        for _ in range(self.substeps):
            self.solver.step(self.state, self.dt)
            if count:
                st = self.solver.stats
                newton += int(st.get("newton_iterations", 0))
                inner += int(st.get("inner_iterations", 0))
        if count:
            self.work[name] = [newton, inner]

    def run(self, name):
        if self.captured:
            wp.capture_launch(self.graphs[name])
        else:
            self.frame(name)

    def restore(self):
        for a, s in zip(self._arrays, self._snap):
            wp.copy(a, s)
        wp.synchronize_device(self.device)

    def timed(self, name) -> float:
        """Seconds of one frame of variant ``name`` from the snapshot (restore not timed)."""
        self._use(name)
        self.restore()
        t0 = time.perf_counter()
        self.run(name)
        wp.synchronize_device(self.device)
        dt = time.perf_counter() - t0
        self._use("with")
        return dt

    def deviation(self, a, b) -> float:
        """Largest distance between the positions after one frame of variants ``a`` and ``b``."""
        out = []
        for name in (a, b):
            self._use(name)
            self.restore()
            self.run(name)
            wp.synchronize_device(self.device)
            out.append(self.state.x.numpy().copy())  # on the CPU numpy() is a view
        self._use("with")
        return float(np.linalg.norm(out[0] - out[1], axis=1).max())


# ---------------------------------------------------------------------- main
def _pick(value, solver, k):
    return DEFAULTS.get(solver, DEFAULTS["explicit"])[k] if value is None else value


def main(argv=None) -> int:
    from ..solvers import available

    p = argparse.ArgumentParser(prog="warp-cloth bench contact", description=__doc__.split("\n")[0])
    p.add_argument("--res", type=int, default=32, help="cells along each side (default 32)")
    p.add_argument("--solver", nargs="+", default=None,
                   help="solvers to run (default: all available)")
    p.add_argument("--substeps", type=int, default=None, help="default: each solver's choice")
    p.add_argument("--warmup", type=int, default=None,
                   help="frames simulated before timing (default per solver: "
                        + ", ".join(f"{k} {v[0]}" for k, v in DEFAULTS.items()) + ")")
    p.add_argument("--frames", type=int, default=None,
                   help="timed frames per variant and round (default per solver: "
                        + ", ".join(f"{k} {v[1]}" for k, v in DEFAULTS.items()) + ")")
    p.add_argument("--rounds", type=int, default=11, help="timing rounds (default 11)")
    p.add_argument("--only", nargs="*", default=None, help="configurations to run")
    p.add_argument("--adaptive", action="store_true",
                   help="the implicit solver with its default tolerances (work then depends on "
                        "the state; its iteration counts are reported) instead of fixed counts")
    p.add_argument("--device", default=None)
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    quiet_warp()
    wp.init()

    solvers = args.solver or available()
    unknown = [s for s in solvers if s not in available()]
    if unknown:
        p.error(f"unknown solver(s) {unknown}; choose from {available()}")
    cfgs = _configs()
    names = [n for n in cfgs if args.only is None or n in args.only]
    if args.only is not None and (bad := sorted(set(args.only) - set(cfgs))):
        p.error(f"unknown configuration(s) {bad}; choose from {list(cfgs)}")
    if not names:
        p.error(f"no configuration chosen; choose from {list(cfgs)}")
    for k in ("res", "substeps", "warmup", "frames", "rounds"):
        v = getattr(args, k)
        if v is not None and v < (0 if k == "warmup" else 1):
            p.error(f"--{k} must be {'>= 0' if k == 'warmup' else 'positive'}")

    t_start = time.perf_counter()
    setups = []
    for s in solvers:
        for n in names:
            setups.append(Setup(s, n, cfgs[n], args, _pick(args.warmup, s, 0),
                                floor=(s == "explicit" and n == "sphere"),
                                options=None if args.adaptive else EQUAL_WORK_OPTIONS.get(s)))
    rounds = args.rounds
    # rounds alternate variants and configurations frame by frame, in an order that rotates
    slots = [(st, name) for st in setups for name in st.variants]
    per = {id(st): _pick(args.frames, st.solver_name, 1) for st in setups}
    for r in range(rounds):
        order = slots[r % len(slots):] + slots[: r % len(slots)]
        acc = {(id(st), name): [] for st, name in slots}
        for f in range(max(per.values())):
            for st, name in order:
                if f < per[id(st)]:
                    acc[(id(st), name)].append(st.timed(name))
        for st, name in slots:
            st.times[name].append(statistics.fmean(acc[(id(st), name)]))

    rows, out = [], []
    for st in setups:
        base = statistics.median(st.times["without"])
        for name in [v for v in st.variants if v != "without"]:
            t = statistics.median(st.times[name])
            over = t / base - 1.0
            label = FLOOR if name == "floor" else st.config
            target = None if name == "floor" else TARGETS.get(st.config)
            verdict = "" if target is None else ("ok" if over < target else "MISSED")
            rows.append([st.solver_name, label, 1e3 * base, 1e3 * t, f"{100 * over:+.1f} %",
                         "" if target is None else f"< {100 * target:.0f} % {verdict}",
                         st.in_contact, st.substeps])
            row = dict(solver=st.solver_name, config=label, ms_per_frame_without=1e3 * base,
                       ms_per_frame_with=1e3 * t, overhead=over, target=target,
                       verdict=verdict or None, vertices_in_contact=st.in_contact,
                       vertices=st.model.num_vertices, substeps=st.substeps,
                       captured=st.captured, solver_options=st.options, rounds=rounds,
                       frames=per[id(st)])
            if not st.captured:
                row["iterations_without"] = st.work.get("without")
                row["iterations_with"] = st.work.get(name)
            if name == "floor":
                row["floor_max_deviation"] = st.deviation("with", "floor")
            out.append(row)
    wall = time.perf_counter() - t_start
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    what = ("adaptive implicit solver: its work differs with and without contact" if args.adaptive
            else "at equal solver work")
    print(f"# contact cost ({what}): drape scene, {args.res}x{args.res} cells "
          f"({setups[0].model.num_vertices} vertices), 60 fps, median of {rounds} rounds\n")
    print(markdown_table(["solver", "config", "ms/frame without contact", "ms/frame with",
                          "overhead", "target", "vertices in contact", "substeps"], rows))
    notes = ["Overhead = with / without - 1: same solver, same draped snapshot (restored before "
             "every timed frame), same substeps; only the contact correction differs. In contact: "
             "vertices within thickness + slack of an obstacle at some substep of that frame."]
    if any("floor" in st.variants for st in setups):
        notes.append("Floor: a hand-written pass for that one static sphere and nothing else, "
                     "with the same result (no target).")
    opts = {st.solver_name: st.options for st in setups if st.options}
    for s, o in opts.items():
        notes.append(f"{s}: " + ", ".join(f"{k}={v}" for k, v in o.items())
                     + " (fixed work per step; --adaptive for the default tolerances).")
    for st in setups:
        if not st.captured:
            w0, w1 = st.work.get("without"), st.work.get("with")
            notes.append(f"{st.solver_name} / {st.config}: not capturable (Python loop); "
                         f"Newton / inner iterations per frame without {w0}, with {w1}.")
    print("\n" + "\n".join(notes))
    print(f"\n({wall:.0f} s including compile, warm-up and timing)")
    return 0


if __name__ == "__main__":  # pragma: no cover
    import sys

    sys.exit(main(sys.argv[1:]))
