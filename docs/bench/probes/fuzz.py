"""Randomized robustness sweep: one random scene per seed, every written frame checked in float64
by an independent checker (`fuzz_check.py`, numpy only: no simulator code).

    python docs/bench/probes/fuzz.py SEED [--frames N] [--n CELLS] [--only-obs K] [--solver NAME]
        [--no-offset] [--no-limit] [--no-pins] [--no-pinpath] [--log FILE] [--keep] [--describe]

A scene draws: the solver (explicit, implicit, pbd, pd), fps, frames, thickness, friction; a grid,
jittered or irregular sheet (holes; an OBJ with a seam written twice and welded, unreferenced
vertices or a sliver triangle; a fold, waves, a tilt, offsets up to 2 km); 0-3 obstacles (planes,
spheres, rotated boxes, meshes: icospheres, lumpy, blades, tori) still or moving (velocities,
spins, keyframe paths); pins (a corner or an edge, still or on a path); a throw; density,
stiffness, bending; a StrainLimit. Seeds >= 1000 are harder (closer drops, faster obstacles),
>= 2000 keep one obstacle moving. Self-collision is on. Prints one JSON row: ``status`` pass,
refusal (a clear error: bad input or a stop of the divergence guard) or FAILURE (a crash, NaN in
the file, the cloth through itself, a free vertex nearer an obstacle than the thickness less
0.1 mm, a cloth edge inside an obstacle or an obstacle edge through the cloth), with ``notes``:
FORCED:pin-in-obstacle (a pin driven into an obstacle: the cloth beside it cannot stay out),
FORCED:obstacles-pinch (two obstacles within two thicknesses of each other in a failing frame),
strain>15% (unpinned), slow (> 3 s a frame). ``--log FILE`` appends the row. A loop over seeds:
``for s in $(seq 3000 3299); do python docs/bench/probes/fuzz.py $s --log fz.jsonl; done``.
Results: docs/bench/robustness.md.
"""
import sys, os, math, time, json, tempfile, traceback
import numpy as np
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from fuzz_check import check_frame, edges_from, qmat

args = sys.argv[1:]
seed = int(args[0])
def opt(name, default=None, cast=str):
    if name in args:
        return cast(args[args.index(name) + 1])
    return default
FR_OVERRIDE = opt("--frames", None, int)
ONLY_OBS = opt("--only-obs", None, int)
N_OVERRIDE = opt("--n", None, int)
LOG = opt("--log", None)
KEEP = "--keep" in args
SOLVER_OVERRIDE = opt("--solver", None)

from warp_cloth.util import quiet_warp
quiet_warp()
import warp_cloth as wc
from warp_cloth import TriMesh, ClothModel, Scene, SimulationDiverged, make_solver
from warp_cloth.collision import CollisionStage, Box, Plane, Sphere, MeshObstacle, Motion, KeyframePath
from warp_cloth.model import PinPath
from warp_cloth.limits import StrainLimit
from warp_cloth.usd import read_points

rng = np.random.default_rng(seed)
HARD = seed >= 1000
D = {}  # description
WORK = tempfile.mkdtemp(prefix=f"fz{seed}-")


def rand_quat():
    q = rng.normal(size=4); return q / np.linalg.norm(q)


def quat_axis(axis, ang):
    a = np.asarray(axis, float); a = a / np.linalg.norm(a)
    return np.array([*(a * math.sin(ang / 2)), math.cos(ang / 2)])


def write_obj(path, V, T, extra_v=()):
    with open(path, "w") as f:
        for v in V: f.write(f"v {v[0]:.9g} {v[1]:.9g} {v[2]:.9g}\n")
        for v in extra_v: f.write(f"v {v[0]:.9g} {v[1]:.9g} {v[2]:.9g}\n")
        for t in T: f.write(f"f {t[0]+1} {t[1]+1} {t[2]+1}\n")


# ------------------------------------------------------------------ solver, timing
solver_name = str(rng.choice(["explicit", "implicit", "pbd", "pd"])); solver_name = SOLVER_OVERRIDE or solver_name
fps = float(rng.choice([30, 40, 50, 60]))
frames = int(rng.integers(30, 91)) if not HARD else int(rng.integers(30, 61)); frames = frames if FR_OVERRIDE is None else FR_OVERRIDE
th = float(rng.uniform(0.002, 0.010))
fric = float(rng.uniform(0, 1))
D.update(solver=solver_name, fps=fps, frames=frames, th=round(th, 5), fric=round(fric, 3))

# ------------------------------------------------------------------ cloth (local, xz plane, centred)
n = int(rng.integers(8, 25)); n = n if N_OVERRIDE is None else N_OVERRIDE
fold = rng.random() < 0.3
if fold and n % 2: n += 1
size = float(rng.uniform(0.3, 1.5))
kind = str(rng.choice(["grid", "jitter", "irregular"]))
g = np.linspace(-size / 2, size / 2, n + 1)
V = np.array([[x, 0.0, z] for z in g for x in g])
h = size / n
inner = (np.abs(V[:, 0]) < size / 2 - 1e-9) & (np.abs(V[:, 2]) < size / 2 - 1e-9)
if kind != "grid":
    amp = 0.25 if kind == "jitter" else 0.33
    mx = inner & ~(fold & (np.abs(V[:, 0]) < 1e-9))
    V[mx, 0] += rng.uniform(-amp, amp, mx.sum()) * h
    V[inner, 2] += rng.uniform(-amp, amp, inner.sum()) * h
T = []
for i in range(n):
    for j in range(n):
        a = i * (n + 1) + j; b = a + 1; c = b + n + 1; d = a + n + 1
        if kind == "grid" or rng.random() < 0.5:
            T += [(a, b, c), (a, c, d)]
        else:
            T += [(a, b, d), (b, c, d)]
T = np.array(T)
hole = rng.random() < 0.25 and n >= 10
if hole:
    cc = rng.uniform(-0.2, 0.2, 2) * size; rad = rng.uniform(0.1, 0.25) * size
    cen = V[T].mean(1)
    keep = np.hypot(cen[:, 0] - cc[0], cen[:, 2] - cc[1]) > rad
    T = T[keep]
D.update(n=n, size=round(size, 3), mesh=kind, hole=hole, fold=fold)
# remove unreferenced vertices (hole)
used = np.unique(T); remap = -np.ones(len(V), int); remap[used] = np.arange(len(used))
V = V[used]; T = remap[T]

use_obj = rng.random() < 0.35
obj_mode = None
extra_v = []
if use_obj:
    obj_mode = str(rng.choice(["dup", "unref", "sliver", "plain"]))
    if obj_mode == "sliver":  # add a sliver triangle on a boundary edge
        E = np.sort(np.vstack([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]]), axis=1)
        u, cnt = np.unique(E, axis=0, return_counts=True)
        be = u[cnt == 1]; e = be[rng.integers(len(be))]
        a, b = V[e[0]], V[e[1]]; m = (a + b) / 2
        # outward: away from the centroid of the triangle owning the edge
        owner = T[np.flatnonzero(((T == e[0]).any(1)) & ((T == e[1]).any(1)))[0]]
        oc = V[owner].mean(0); out = m - oc; out -= out @ (b - a) / ((b - a) @ (b - a)) * (b - a)
        out /= np.linalg.norm(out)
        m = m + out * np.linalg.norm(b - a) * float(rng.choice([1e-2, 3e-3, 1e-3]))
        V = np.vstack([V, m]); T = np.vstack([T, [e[1], e[0], len(V) - 1]])
    if obj_mode == "dup":  # split along a row: duplicate vertices on seam, weld on load
        zs = np.unique(np.round(V[:, 2], 9)); zsplit = g[n // 2]
        row = np.flatnonzero(np.abs(V[:, 2] - zsplit) < 1e-9)
        if len(row):
            newidx = {int(r): len(V) + k for k, r in enumerate(row)}
            V = np.vstack([V, V[row]])
            cen = V[T].mean(1)
            for ti in np.flatnonzero(cen[:, 2] > zsplit):
                T[ti] = [newidx.get(int(x), int(x)) for x in T[ti]]
    if obj_mode == "unref":
        extra_v = [V.mean(0) + [0, 5.0, 0], V.mean(0) + [0.1, 7.0, 0.3]]
    D["obj"] = obj_mode

# initial shape (local): fold or waves
X = V.copy()
if fold:
    ang = float(rng.uniform(90, 175)); D["fold_deg"] = round(ang, 1)
    up = X[:, 0] > 1e-9; r = X[up, 0]; a = math.radians(ang)
    X[up, 0] = r * math.cos(a); X[up, 1] = r * math.sin(a)
    if use_obj and obj_mode != "plain":
        pass
elif rng.random() < 0.3:
    X[:, 1] += 0.03 * size * np.sin(2 * math.pi * X[:, 0] / size * rng.uniform(0.5, 2)) * np.cos(2 * math.pi * X[:, 2] / size)
    D["wavy"] = True

# orientation and placement
tilt = rng.random() < 0.5
Rc = qmat(rand_quat()) if (tilt and rng.random() < 0.3) else (qmat(quat_axis([1, 0, 0], rng.uniform(-0.5, 0.5))) @ qmat(quat_axis([0, 1, 0], rng.uniform(0, 6.28))) if tilt else np.eye(3))
far = rng.random() < 0.25
O = np.zeros(3)
if far:
    O = rng.choice([-1, 1], 3) * rng.uniform(50, 2000, 3) * (rng.random(3) < 0.7)
    D["offset"] = [round(float(o), 1) for o in O]
if "--no-offset" in args: O = np.zeros(3)

# ------------------------------------------------------------------ obstacles (local world, offset later)
any_moving = False
nobs = int(rng.integers(0, 4)) if not HARD else int(rng.integers(1, 4))
obs_specs = []
top = 0.0
has_floor = False
for k in range(nobs):
    kind_o = str(rng.choice(["plane", "sphere", "box", "mesh"], p=[0.25, 0.25, 0.25, 0.25]))
    if kind_o == "plane" and has_floor: kind_o = "sphere"
    sp = dict(kind=kind_o, lin=(0, 0, 0), ang=(0, 0, 0), start=0.0, ramp=0.0, path=None, rot=(0, 0, 0, 1))
    moving = rng.random() < (0.4 if not HARD else 0.7)
    if seed >= 2000 and (kind_o == "plane" or any_moving): moving = False
    any_moving = any_moving or moving
    xz = rng.uniform(-0.2, 0.2, 2) * size * (0.5 if HARD else 1.0)
    if kind_o == "plane":
        has_floor = True
        nrm = np.array([rng.uniform(-0.2, 0.2), 1.0, rng.uniform(-0.2, 0.2)]) if rng.random() < 0.4 else np.array([0, 1.0, 0])
        nrm /= np.linalg.norm(nrm)
        sp.update(normal=nrm, point=np.array([0.0, 0.0, 0.0]))
        y = np.array([0, 1.0, 0]); c = float(y @ nrm); ax = np.cross(y, nrm)
        sp["rot"] = np.array([*ax, 1 + c]) / np.linalg.norm([*ax, 1 + c])
        sp["pos"] = sp["point"]
        if moving:
            tt = [0.0, rng.uniform(0.1, 0.5), rng.uniform(0.6, 1.2)]; hgt = rng.uniform(0.05, 0.4)
            sp["path"] = (np.array(tt), np.array([[0, 0, 0], [0, 0, 0], [0, hgt, 0]]), np.tile([0, 0, 0, 1.0], (3, 1)))
        t_top = 0.0
    elif kind_o == "sphere":
        r = float(rng.uniform(0.05, 0.35) * max(size, 0.5))
        sp.update(r=r, pos=np.array([xz[0], r, xz[1]]))
        t_top = 2 * r
    elif kind_o == "box":
        hh = rng.uniform(0.03, 0.3, 3) * max(size, 0.5)
        if rng.random() < 0.3: hh[rng.integers(3)] = rng.uniform(0.003, 0.01)  # thin
        sp.update(h=hh, rot=rand_quat() if rng.random() < 0.7 else np.array([0, 0, 0, 1.0]))
        R = qmat(sp["rot"]); ext = np.abs(R) @ hh
        sp["pos"] = np.array([xz[0], ext[1], xz[1]])
        t_top = 2 * ext[1]
    else:
        shape = str(rng.choice(["ico", "blade", "torus", "lumpy"]))
        scale = float(rng.choice([1.0, rng.uniform(0.3, 3.0)]))
        if shape in ("ico", "lumpy"):
            m = TriMesh.icosphere(int(rng.integers(1, 4)), 1.0)
            MV, MT = np.asarray(m.vertices, float), np.asarray(m.triangles)
            rr = rng.uniform(0.08, 0.3) * max(size, 0.5)
            if shape == "lumpy":
                cdir = rng.normal(size=(4, 3))
                MV = MV * (1 + 0.3 * np.tanh(sum(np.sin(3 * MV @ ci + j) for j, ci in enumerate(cdir)) / 2))[:, None]
            MV = MV * rr
        elif shape == "blade":
            L, W, Hh = rng.uniform(0.2, 0.6) * max(size, 0.5), rng.uniform(0.002, 0.01), rng.uniform(0.05, 0.2)
            MV = np.array([[x, y, z] for x in (-L, L) for y in (-Hh, Hh) for z in (-W, W)])
            MT = []
            for q in [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]:
                MT += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
            MT = np.array(MT)
        else:  # torus
            R0, r0 = rng.uniform(0.1, 0.3) * max(size, 0.5), 0
            r0 = R0 * rng.uniform(0.15, 0.45); nu, nv = 24, 12
            MV = np.array([[(R0 + r0 * math.cos(b)) * math.cos(a), r0 * math.sin(b), (R0 + r0 * math.cos(b)) * math.sin(a)]
                           for a in np.arange(nu) * 2 * math.pi / nu for b in np.arange(nv) * 2 * math.pi / nv])
            MT = []
            for i in range(nu):
                for j in range(nv):
                    a0 = i * nv + j; a1 = i * nv + (j + 1) % nv; b0 = ((i + 1) % nu) * nv + j; b1 = ((i + 1) % nu) * nv + (j + 1) % nv
                    MT += [[a0, b0, b1], [a0, b1, a1]]
            MT = np.array(MT)
        MV = MV / scale  # file units; scaled back by MeshObstacle(scale=)
        path = os.path.join(WORK, f"obs{k}.obj"); write_obj(path, MV, MT)
        rot = rand_quat() if rng.random() < 0.6 else np.array([0, 0, 0, 1.0])
        R = qmat(rot); Wv = (MV * scale) @ R.T
        sp.update(V=MV, T=MT, scale=scale, rot=rot, obj=path, shape=shape, closed=True)
        sp["pos"] = np.array([xz[0], -Wv[:, 1].min() + 0.001, xz[1]])
        t_top = Wv[:, 1].max() - Wv[:, 1].min()
    if kind_o != "plane" and moving:
        mk = str(rng.choice(["lin", "spin", "path"]))
        if mk == "lin":
            sp["lin"] = rng.uniform(-1.5, 1.5, 3) * np.array([1, 0.5, 1]) * (2.0 if HARD else 1.0); sp["start"] = float(rng.uniform(0, 0.5)); sp["ramp"] = float(rng.choice([0, 0.2]))
        elif mk == "spin":
            sp["ang"] = rng.uniform(-6, 6, 3) * (rng.random(3) < 0.6) * (2.0 if HARD else 1.0)
            if not np.any(sp["ang"]): sp["ang"] = np.array([0, 4.0, 0])
        else:
            tt = np.sort(rng.uniform(0, 2.0, 3)); tt = np.concatenate([[0.0], tt])
            if np.any(np.diff(tt) <= 1e-3): tt = np.array([0, 0.4, 0.9, 1.5])
            offs = np.vstack([[0, 0, 0], rng.uniform(-0.3, 0.3, (3, 3))]) * max(size, 0.5)
            offs[:, 1] = np.abs(offs[:, 1])
            qs = [np.array([0, 0, 0, 1.0])]
            for _ in range(3):
                qs.append(np.array([*(rng.normal(size=3) * 0.3), 1.0]))
            qs = np.array([q / np.linalg.norm(q) for q in qs])
            sp["path"] = (tt, offs, qs)
    sp["t_top"] = t_top
    obs_specs.append(sp)
if HARD and not has_floor and rng.random() < 0.5:
    obs_specs.append(dict(kind="plane", lin=(0, 0, 0), ang=(0, 0, 0), start=0.0, ramp=0.0, path=None, rot=np.array([0, 0, 0, 1.0]),
                          normal=np.array([0, 1.0, 0]), point=np.zeros(3), pos=np.zeros(3), t_top=0.0))
if ONLY_OBS is not None:
    obs_specs = [obs_specs[ONLY_OBS]]
top = max([s["t_top"] for s in obs_specs], default=0.0)
D["obs"] = [dict(kind=s["kind"], shape=s.get("shape"), moving=bool(s["path"] is not None or np.any(s["lin"]) or np.any(s["ang"]))) for s in obs_specs]

# cloth world placement
drop = rng.choice([0.02, 0.1, 0.3, 1.0, 2.5]) if not HARD else rng.choice([0.005, 0.02, 0.05, 0.15, 0.5])
Xw = X @ Rc.T
Xw += np.array([0, top + th + 0.005 - Xw[:, 1].min() + drop, 0]) if obs_specs else np.array([0, 1.0, 0])
Vw_rest = V @ Rc.T + (Xw.mean(0) - (X @ Rc.T).mean(0))  # mesh (rest) placed similarly
D["drop"] = float(drop)
vel = None
if rng.random() < 0.25:
    tgt = np.array([0, top / 2, 0]) - Xw.mean(0); tgt /= np.linalg.norm(tgt) + 1e-12
    sp_ = float(rng.uniform(2, 8)); vel = np.tile(tgt * sp_, (len(X), 1)); D["throw"] = round(sp_, 2)

# pins
pins = None; pin_path = None
pr = rng.random()
bnd = np.flatnonzero(~inner[:0]) if False else None
if pr < 0.35:
    # local corner / edge of the original rectangle
    xmax = V[:, 0].max(); zmax = V[:, 2].max()
    if rng.random() < 0.5:
        cand = np.flatnonzero(np.isclose(V[:, 0], V[:, 0].min()) & np.isclose(V[:, 2], V[:, 2].min()))
        D["pins"] = "corner"
    else:
        cand = np.flatnonzero(np.isclose(V[:, 2], V[:, 2].min()))
        D["pins"] = "edge"
    pins = cand
    if len(pins) and rng.random() < 0.5:
        p0 = Xw[pins] + O
        vv = rng.uniform(-1, 1, 3); dur = 3.2
        circ = rng.random() < 0.5
        fn = (lambda t, p0=p0, vv=vv: p0 + vv * min(t, 1.0)) if not circ else \
             (lambda t, p0=p0: p0 + 0.15 * np.array([math.sin(4 * t), 0.0, 1 - math.cos(4 * t)]))
        pin_path = PinPath.from_function(fn, np.linspace(0, dur, 100)); D["pin_path"] = "circle" if circ else "line"

dens = float(rng.uniform(0.1, 0.3)); k = float(10 ** rng.uniform(2, 5))
bend = str(rng.choice(["none", "springs", "dihedral", "quadratic"]))
bk = float(10 ** rng.uniform(-5, -3)) if bend != "none" else 0.0
slimit = float(rng.uniform(1.01, 1.1)) if rng.random() < 0.3 else None
if "--no-limit" in args: slimit = None
if "--no-pins" in args: pins = None; pin_path = None
if "--no-pinpath" in args: pin_path = None
D.update(density=round(dens, 3), k=round(k, 1), bending=bend, bend_k=bk, strain_limit=slimit)

# ------------------------------------------------------------------ build
def to_world_spec(sp):
    s = dict(sp); s["pos"] = np.asarray(sp["pos"], float) + O; return s

world_specs = [to_world_spec(s) for s in obs_specs]


def build():
    if use_obj:
        path = os.path.join(WORK, "cloth.obj")
        write_obj(path, Vw_rest + O, T, extra_v=[e + O for e in extra_v])
        mesh = TriMesh.from_obj(path, weld=(obj_mode == "dup"))
    else:
        mesh = TriMesh(Vw_rest + O, T, name="cloth")
    nv = mesh.num_vertices
    posw = None
    # initial positions in world
    if use_obj and obj_mode == "dup":
        # after welding the vertex count changes: map positions via nearest rest vertex
        MVr = np.asarray(mesh.vertices, float)
        idx = np.array([int(np.argmin(np.linalg.norm(Vw_rest + O - p, axis=1))) for p in MVr])
        posw = Xw[idx] + O
        pm = None
        if pins is not None:
            pm = np.unique([int(np.argmin(np.linalg.norm(MVr - (Vw_rest[p] + O), axis=1))) for p in pins])
        vv = vel[idx] if vel is not None else None
    else:
        posw = np.vstack([Xw + O, np.asarray(extra_v).reshape(-1, 3) + O]) if len(extra_v) else Xw + O
        pm = pins
        vv = None if vel is None else np.vstack([vel, np.zeros((len(extra_v), 3))])
    masses = None
    if len(extra_v):
        masses = np.full(nv, dens * size * size / max(nv - len(extra_v), 1))
    pp = pin_path
    if pp is not None and use_obj and obj_mode == "dup":
        pp = None  # pin order changed by weld; keep static
    model = ClothModel(mesh, density=dens, masses=masses, stretch_stiffness=k, bending=bend, bend_stiffness=bk,
                       pins=() if pm is None else pm, pin_path=pp, damping=0.1, velocity=vv, positions=posw)
    obstacles = []
    for s in world_specs:
        mo = Motion(linear_velocity=tuple(s["lin"]), angular_velocity=tuple(s["ang"]), start=s["start"], ramp=s["ramp"],
                    path=None if s["path"] is None else KeyframePath(*s["path"]))
        if s["kind"] == "plane":
            obstacles.append(Plane(tuple(s["normal"]), tuple(s["pos"]), motion=mo))
        elif s["kind"] == "sphere":
            obstacles.append(Sphere(s["r"], tuple(s["pos"]), motion=mo))
        elif s["kind"] == "box":
            obstacles.append(Box(tuple(s["h"]), tuple(s["pos"]), rotation=tuple(s["rot"]), motion=mo))
        else:
            obstacles.append(MeshObstacle(s["obj"], position=tuple(s["pos"]), rotation=tuple(s["rot"]), scale=s["scale"], motion=mo))
    stage = CollisionStage(model, obstacles, thickness=th, self_collision=True, **(dict(friction=fric) if obstacles else {}))
    solver = make_solver(solver_name, model, collision=stage)
    if slimit:
        solver.add_correction(StrainLimit(model, 0, slimit))
    scene = Scene(model, solver, fps=fps, frames=frames, name=f"fz{seed}")
    return scene, model, mesh, posw, pm


row = dict(seed=seed, **D)
if "--geom" in args:
    from fuzz_check import pose, sdf_analytic
    F = int(opt("--geom")); t = F / fps
    for k_, s_ in enumerate(world_specs):
        c_, R_ = pose(s_, t)
        if s_["kind"] == "mesh":
            W_ = (s_["V"] * s_["scale"]) @ R_.T + c_
            print(k_, "mesh", s_["shape"], "bbox", W_.min(0).round(4), W_.max(0).round(4))
            for j_, o_ in enumerate(world_specs):
                if o_["kind"] != "mesh":
                    c2, R2 = pose(o_, t); print("   verts sdf vs", j_, o_["kind"], sdf_analytic(o_, c2, R2, W_).min().round(4))
        else:
            print(k_, s_["kind"], "c", c_.round(4), "n/h", (R_ @ [0, 1, 0]).round(3), s_.get("h"), s_.get("r"))
    sys.exit()
if "--describe" in args:
    print(json.dumps(row, default=str)); sys.exit()
out = os.path.join(WORK, "out.usd")
t0 = time.perf_counter()
status = "pass"; err = None; model = None
try:
    scene, model, mesh, posw, pm = build()
    scene.run(out, quiet=("--verbose" not in args), progress=("--verbose" in args))
except SimulationDiverged as e:
    status = "refusal"; err = "SimulationDiverged: " + str(e)[:300]
except ValueError as e:
    status = "refusal"; err = "ValueError: " + str(e)[:300]
except Exception as e:
    status = "FAILURE"; err = f"{type(e).__name__}: {str(e)[:300]}"; row["tb"] = traceback.format_exc()[-1500:]
wall = time.perf_counter() - t0
row["wall_s"] = round(wall, 1)
print(f"run done {wall:.1f}s status={status} err={err}", file=sys.stderr, flush=True)
# ------------------------------------------------------------------ check frames
viol = {}
if model is not None and os.path.exists(out):
    try:
        times, pts, _ = read_points(out)
    except Exception as e:
        times, pts = [], []
        if status == "pass":
            status = "FAILURE"; err = f"read back: {type(e).__name__}: {e}"
    row["frames_written"] = len(pts)
    if len(pts):
        row["s_per_frame"] = round(wall / max(len(pts), 1), 3)
    tris = np.asarray(mesh.triangles, np.int64); edges = edges_from(tris)
    Vr = np.asarray(mesh.vertices, float)
    rest = np.linalg.norm(Vr[edges[:, 0]] - Vr[edges[:, 1]], axis=1)
    nvv = len(Vr)
    free = np.ones(nvv, bool)
    if pm is not None and len(pm): free[np.asarray(pm)] = False
    if len(extra_v) and not (use_obj and obj_mode == "dup"):
        used_ = np.zeros(nvv, bool); used_[tris.reshape(-1)] = True; free &= used_
    maxstrain = -1; worst = {}
    first = {}
    for f, P in enumerate(pts):
        P = np.asarray(P, float)
        if f % 10 == 0: print(f"check frame {f} {time.perf_counter()-t0:.1f}s", file=sys.stderr, flush=True)
        r = check_frame(P, tris, edges, free, world_specs, f / fps, th, rest)
        if "strain" in r and r["strain"] > maxstrain: maxstrain = r["strain"]; row["max_strain_frame"] = f
        for key in ("nan", "self_cross", "obs_viol", "obs_cross", "edge_inside"):
            if key in r:
                viol.setdefault(key, []).append(f)
                if key not in first: first[key] = dict(frame=f, detail=r[key], ex=r.get("self_cross_ex"))
        if "pin_clear" in r:
            row["pin_clear_mm"] = round(min(row.get("pin_clear_mm", 1e9), r["pin_clear"] * 1e3), 3)
        if "clear" in r:
            for kk, v in r["clear"].items():
                worst[kk] = min(worst.get(kk, np.inf), v)
    row["max_strain"] = round(maxstrain, 4)
    row["min_clear_mm"] = {int(k): round(v * 1e3, 3) for k, v in worst.items()}
    if viol:
        row["viol"] = {k: dict(nframes=len(v), frames=v[:8]) for k, v in viol.items()}
        row["first"] = json.loads(json.dumps(first, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
        status = "FAILURE"
    notes = []
    if row.get("pin_clear_mm", 1e9) < th * 1e3: notes.append("FORCED:pin-in-obstacle")
    from fuzz_check import obstacles_pinch
    bad = sorted({f for k, v in viol.items() if k != "nan" for f in v})
    if len(world_specs) > 1 and any(obstacles_pinch(world_specs, f / fps, 2 * th) for f in bad[:8]):
        notes.append("FORCED:obstacles-pinch")  # two obstacles within two thicknesses
    if maxstrain > 0.15 and pin_path is None: notes.append("strain>15%")
    if len(pts) and wall / len(pts) > 3: notes.append("slow")
    if notes: row["notes"] = notes
row.update(status=status, err=err)
line = json.dumps(row, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
print(line, flush=True)
if LOG:
    with open(LOG, "a") as f: f.write(line + "\n")
if not KEEP:
    import shutil
    shutil.rmtree(WORK, ignore_errors=True)
