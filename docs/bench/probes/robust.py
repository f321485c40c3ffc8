"""Robustness sweep of cases not in `warp-cloth bench meshes`, checked per written frame in
float64 with the bench's checkers: ``python docs/bench/probes/robust.py CASE SOLVER [FRAMES]``
(CASE: fine highdrop rotbox sweep meshmove corner bigstep heavy pinch headon tube throw
spinwrap fasttwist graded massratio squeeze stiff lowpoly spinbox tiltbox ribbon elevator disk blob bowl terrain paddle drag;
env TH (thickness, m), FPS, FRIC (friction, default 0.4), SELF (0: self-collision off), OPTS (the
solver's options as a Python dict literal, e.g. OPTS='{"contact_iterations": 60}')) prints one
JSON row. Measured 2026-12-07: docs/bench/selfcollision.md."""
import sys, os, math, time, json, tempfile, numpy as np
from warp_cloth.util import quiet_warp
quiet_warp()
from warp_cloth import TriMesh, ClothModel, Scene, SimulationDiverged, make_solver
from warp_cloth.collision import CollisionStage, Box, Plane, Sphere, MeshObstacle, Motion, KeyframePath
from warp_cloth.contact_scenes import thin_parts_mesh
from warp_cloth.bench.meshes import edges_of, segment_triangle_hits, jittered_grid, _fold
from warp_cloth.usd import read_points


def _icosphere(sub, r):
    """An icosahedron subdivided ``sub`` times, on a sphere of radius ``r``: (V, F)."""
    m = TriMesh.icosphere(sub, r)
    return np.asarray(m.vertices), np.asarray(m.triangles)


case, solver = sys.argv[1], sys.argv[2]
frames = int(sys.argv[3]) if len(sys.argv) > 3 else 90
th = float(os.environ.get("TH", "0.005")); fps = float(os.environ.get("FPS", "60"))
x0 = pins = None; masses_arg = None; pin_path = None; substeps = None; density = 0.15; k = 1000.0
if case == "fine":  # edges (4 mm) shorter than the thickness
    mesh = TriMesh.grid(40, 40, size=0.16, plane="xz", origin=(-0.08, th, -0.08), name="cloth")
    x0 = _fold(mesh.vertices, 0.0, 120.0, th); obs = [Plane()]
elif case == "highdrop":  # falls 4 m: ~9 m/s onto the floor, folded in the air
    mesh = jittered_grid(20, 0.8, 11, 4.0)
    x0 = _fold(mesh.vertices, 0.1, 60.0, 4.0); obs = [Plane()]
elif case == "rotbox":  # onto a rotated box's edge and corner
    mesh = jittered_grid(22, 1.0, 5, 0.8)
    s = math.sin(0.4); c = math.cos(0.4)
    q = np.array([0.3, 0.2, 0.1]); q = q / np.linalg.norm(q) * math.sin(0.5); q = (*q, math.cos(0.5))
    obs = [Box((0.2, 0.15, 0.25), (0.05, 0.25, 0.0), rotation=q), Plane()]
elif case == "sweep":  # a sphere at 4 m/s along the floor through a lying sheet
    mesh = TriMesh.grid(24, 24, size=1.0, plane="xz", origin=(-0.5, th + 0.001, -0.5), name="cloth")
    obs = [Sphere(0.1, (-0.8, 0.1 + th, 0.0), motion=Motion(linear_velocity=(4.0, 0, 0), start=0.2)), Plane()]
elif case == "meshmove":  # the thin-parts mesh driven up through a hanging sheet at 2 m/s
    mesh = TriMesh.grid(24, 24, size=1.2, plane="xy", origin=(-0.6, 0.5, 0.6), name="cloth")
    top = np.flatnonzero(np.isclose(mesh.vertices[:, 1], mesh.vertices[:, 1].max()))
    pins = top
    path = KeyframePath([0.0, 0.2, 1.0, 2.0], [[0, 0, 0], [0, 0, 0], [0, 0, 1.5], [0, 0, 1.5]])
    obs = [MeshObstacle(thin_parts_mesh(), name="thin_parts", position=(0, 0.3, 0), motion=Motion(path=path)), Plane()]
elif case == "corner":  # pinned at one corner, released sideways: flaps onto itself
    mesh = TriMesh.grid(20, 20, size=0.8, plane="xy", origin=(-0.4, 0.4, 0.0), name="cloth")
    v = mesh.vertices; pins = [int(np.argmax(v[:, 1] - v[:, 0]))]
    obs = [Plane()]
elif case == "bigstep":  # a fold at 24 fps, one solver step a frame
    mesh = jittered_grid(16, 1.0, 2, th, keep_column=0.0)
    x0 = _fold(mesh.vertices, 0.0, 120.0, th); obs = [Plane()]; fps = 24.0; substeps = 1
elif case == "heavy":  # light stiff cloth (0.1 kg/m^2, 1e4 N/m) crumpled onto a sphere
    mesh = jittered_grid(26, 1.0, 9, 0.7); density = 0.1; k = 1.0e4
    obs = [Sphere(0.15, (0.0, 0.15, 0.0)), Plane()]
elif case == "pinch":  # a sheet dropped into a narrow gap between two boxes (8 cm apart)
    mesh = jittered_grid(20, 0.8, 4, 0.6)
    obs = [Box((0.2, 0.2, 0.5), (-0.24, 0.2, 0.0)), Box((0.2, 0.2, 0.5), (0.24, 0.2, 0.0)), Plane()]
elif case == "headon":  # two sheets meeting in the air at 12 m/s, then on the floor
    a = TriMesh.grid(16, 16, size=0.6, plane="xz", origin=(-0.3, 0.9, -0.3))
    b = TriMesh.grid(16, 16, size=0.6, plane="xz", origin=(-0.2, 1.2, -0.35))
    n = len(a.vertices)
    mesh = TriMesh(np.vstack([a.vertices, b.vertices]),
                   np.vstack([a.triangles, np.asarray(b.triangles) + n]), name="cloth")
    vel = np.zeros((2 * n, 3)); vel[:n, 1] = 6.0; vel[n:, 1] = -6.0
    obs = [Plane()]
elif case == "tube":  # a closed tube lying across the floor, collapsing flat onto itself
    nu, nv, r, L = 24, 12, 0.12, 0.8
    u = np.arange(nu) * 2 * math.pi / nu; s = np.linspace(-L / 2, L / 2, nv + 1)
    V = np.array([[x, 0.3 + r * math.cos(t), r * math.sin(t)] for x in s for t in u])
    T = []
    for j in range(nv):
        for i in range(nu):
            a0 = j * nu + i; a1 = j * nu + (i + 1) % nu; b0 = a0 + nu; b1 = a1 + nu
            T += [[a0, a1, b1], [a0, b1, b0]]
    mesh = TriMesh(V, np.array(T), name="cloth"); obs = [Plane()]
elif case == "throw":  # a ball thrown at 8 m/s into a sheet hanging from its top row
    mesh = TriMesh.grid(24, 24, size=1.0, plane="xy", origin=(-0.5, 0.3, 0.0), name="cloth")
    pins = np.flatnonzero(np.isclose(mesh.vertices[:, 1], mesh.vertices[:, 1].max()))
    obs = [Sphere(0.12, (0.0, 0.8, -0.5), motion=Motion(linear_velocity=(0, 0, 8.0), start=0.1))]
elif case == "spinwrap":  # dropped on a sphere turning at 12 rad/s about the vertical
    mesh = TriMesh.grid(24, 24, size=1.0, plane="xz", origin=(-0.5, 0.5, -0.5), name="cloth")
    obs = [Sphere(0.2, (0.0, 0.2, 0.0), motion=Motion(angular_velocity=(0, 12.0, 0))), Plane()]
elif case == "graded":  # cells from ~2 mm to ~6 cm (geometric), slivers, folded on the floor
    g = np.cumsum(np.concatenate([[0.0], 0.002 * 1.25 ** np.arange(16)])); g = g / g[-1] * 0.8 - 0.4
    h = np.linspace(-0.4, 0.4, 9)
    V = np.array([[x, th, z] for z in h for x in g]); nx = len(g)
    T = []
    for j in range(len(h) - 1):
        for i in range(nx - 1):
            a0 = j * nx + i; T += [[a0, a0 + nx, a0 + 1], [a0 + 1, a0 + nx, a0 + nx + 1]]
    mesh = TriMesh(V, np.array(T), name="cloth")
    x0 = _fold(mesh.vertices, float(g[9]), 150.0, th); obs = [Plane()]
elif case == "massratio":  # checkerboard masses 1:1000 (0.15 kg/m^2 in all) dropped onto a sphere
    mesh = jittered_grid(20, 0.8, 13, 0.6)
    nv = len(mesh.vertices); masses_arg = np.where(np.arange(nv) % 2 == 0, 1e-3, 1.0); masses_arg *= 0.15 * 0.64 / masses_arg.sum()
    obs = [Sphere(0.15, (0.0, 0.15, 0.0)), Plane()]
elif case == "squeeze":  # a fold on the floor pressed by a box whose bottom comes down to 3 cm
    mesh = jittered_grid(16, 0.6, 3, th, keep_column=0.0)
    x0 = _fold(mesh.vertices, 0.0, 175.0, th)
    path = KeyframePath([0.0, 0.3, 1.0, 2.0], [[0, 0.3, 0], [0, 0.3, 0], [0, 0.03 + 0.1, 0], [0, 0.13, 0]])
    obs = [Box((0.5, 0.1, 0.5), (0.0, 0.0, 0.0), motion=Motion(path=path)), Plane()]
elif case == "stiff":  # light, very stiff cloth (0.1 kg/m^2, 1e5 N/m) dropped onto a sphere
    mesh = jittered_grid(24, 1.0, 21, 0.8); density = 0.1; k = 1.0e5
    obs = [Sphere(0.2, (0.0, 0.2, 0.0)), Plane()]
elif case == "lowpoly":  # a sheet draped over a coarse icosphere mesh (env SUB subdivisions,
    # default 1: 21 degree creases, which the sheet's 59 mm diagonals could dip 0.35 mm past)
    V, F = _icosphere(int(os.environ.get("SUB", "1")), 0.25)
    mesh = TriMesh.grid(24, 24, size=1.0, plane="xz", origin=(-0.5, 0.6, -0.5), name="cloth")
    obs = [MeshObstacle(TriMesh(V, F, name="ico"), name="ico", position=(0, 0.3, 0)), Plane()]
elif case == "spinbox":  # dropped on a box turning at 6 rad/s about the vertical
    mesh = jittered_grid(20, 0.8, 17, 0.45)
    obs = [Box((0.25, 0.1, 0.15), (0.0, 0.2, 0.0), motion=Motion(angular_velocity=(0, 6.0, 0))), Plane()]
elif case == "tiltbox":  # dropped on a box rocking about x (keyframed, +-0.5 rad at 1 Hz)
    mesh = jittered_grid(20, 0.8, 19, 0.5)
    tt = np.linspace(0, 3, 61); qs = [[math.sin(0.25 * math.sin(2 * math.pi * u)), 0, 0, math.cos(0.25 * math.sin(2 * math.pi * u))] for u in tt]
    obs = [Box((0.3, 0.05, 0.3), (0.0, 0.2, 0.0), motion=Motion(path=KeyframePath(tt, np.zeros((len(tt), 3)), qs))), Plane()]
elif case == "ribbon":  # a 2 x 60 cm ribbon (2 x 60 cells) hung by one end that whips about
    from warp_cloth.model import PinPath
    w, L, nw, nl = 0.02, 0.6, 2, 60
    V = np.array([[i * w / nw, 0.75 - j * L / nl, 0.0] for j in range(nl + 1) for i in range(nw + 1)])
    T = []
    for j in range(nl):
        for i in range(nw):
            a0 = j * (nw + 1) + i
            T += [[a0, a0 + nw + 1, a0 + 1], [a0 + 1, a0 + nw + 1, a0 + nw + 2]]
    mesh = TriMesh(V, np.array(T), name="cloth"); obs = [Plane()]
    pins = np.arange(nw + 1); p0 = V[pins]
    pin_path = PinPath.from_function(
        lambda t, p0=p0: p0 + np.array([0.3 * math.sin(6.0 * t), -0.3 * min(t, 1.0), 0.2 * math.sin(4.0 * t)]),
        np.linspace(0, frames / fps + 0.1, 400))
elif case == "elevator":  # a fold on a tilted floor that rises at 2 m/s from 0.3 s, then stops
    mesh = jittered_grid(16, 0.6, 5, th, keep_column=0.0)
    x0 = _fold(mesh.vertices, 0.0, 150.0, th)
    path = KeyframePath([0.0, 0.3, 0.8, 3.0], [[0, 0, 0], [0, 0, 0], [0, 1.0, 0], [0, 1.0, 0]])
    obs = [Plane((0.1, 1.0, 0.0), (0.0, -0.05, 0.0), motion=Motion(path=path))]
elif case == "disk":  # a round tablecloth (rings of 6 i vertices: valences 4-8) onto a square table
    nr, R = 12, 0.45
    V = [[0.0, 0.7, 0.0]]; rings = [[0]]
    for i in range(1, nr + 1):
        rings.append(list(range(len(V), len(V) + 6 * i)))
        V += [[R * i / nr * math.cos(2 * math.pi * (j + 0.3 * (i % 2)) / (6 * i)), 0.7,
               R * i / nr * math.sin(2 * math.pi * (j + 0.3 * (i % 2)) / (6 * i))] for j in range(6 * i)]
    V = np.array(V); T = []
    for i in range(1, nr + 1):  # triangulate ring i-1 to ring i by angle order
        a, b = rings[i - 1], rings[i]; ia = ib = 0
        ang = lambda k: math.atan2(V[k, 2], V[k, 0]) % (2 * math.pi)
        if len(a) == 1:
            T += [[0, b[(j + 1) % len(b)], b[j]] for j in range(len(b))]; continue
        while ia < len(a) or ib < len(b):
            a0, a1 = a[ia % len(a)], a[(ia + 1) % len(a)]; b0, b1 = b[ib % len(b)], b[(ib + 1) % len(b)]
            ta = ang(a1) + (2 * math.pi if ia + 1 >= len(a) else 0); tb = ang(b1) + (2 * math.pi if ib + 1 >= len(b) else 0)
            if ib >= len(b) or (ia < len(a) and ta < tb):
                T.append([a0, a1, b0]); ia += 1
            else:
                T.append([a0, b1, b0]); ib += 1
    mesh = TriMesh(V, np.array(T), name="cloth")
    obs = [Box((0.2, 0.25, 0.2), (0.05, 0.25, 0.03), rotation=(0.0, math.sin(0.2), 0.0, math.cos(0.2))), Plane()]
elif case == "blob":  # onto a lumpy, concave closed mesh (an icosphere, radii 0.13-0.27 m)
    V, F = _icosphere(3, 1.0)
    rng = np.random.default_rng(7); c = rng.normal(size=(6, 3))
    r = 0.2 * (1 + 0.35 * np.tanh(sum(np.sin(3 * V @ ci + k) for k, ci in enumerate(c)) / 2))
    mesh = jittered_grid(24, 1.0, 23, 0.75)
    obs = [MeshObstacle(TriMesh(V * r[:, None], F, name="blob"), name="blob", position=(0, 0.3, 0)), Plane()]
elif case == "bowl":  # into an open hemispherical bowl (two-sided, a thin rim), over its rim
    nu, nv, r = 48, 12, 0.3
    V = [[0.0, 0.05, 0.0]] + [[r * math.sin(b) * math.cos(a), 0.05 + r - r * math.cos(b), r * math.sin(b) * math.sin(a)]
                             for b in np.linspace(math.pi / 2 / nv, math.pi / 2, nv) for a in np.arange(nu) * 2 * math.pi / nu]
    T = [[0, 1 + (i + 1) % nu, 1 + i] for i in range(nu)]
    for j in range(nv - 1):
        for i in range(nu):
            a0 = 1 + j * nu + i; a1 = 1 + j * nu + (i + 1) % nu
            T += [[a0, a1, a1 + nu], [a0, a1 + nu, a0 + nu]]
    mesh = jittered_grid(24, 0.9, 29, 0.6)
    obs = [MeshObstacle(TriMesh(np.array(V), np.array(T), name="bowl"), name="bowl", position=(0.12, 0.0, 0.0)), Plane()]
elif case == "terrain":  # onto an open bumpy heightfield (no floor), hanging over its border
    g = np.linspace(-0.4, 0.4, 25)
    V = np.array([[x, 0.05 * math.sin(9 * x) * math.cos(7 * z) + 0.04 * math.exp(-40 * (x * x + z * z)), z] for z in g for x in g])
    T = []
    for j in range(24):
        for i in range(24):
            a0 = j * 25 + i; T += [[a0, a0 + 25, a0 + 1], [a0 + 1, a0 + 25, a0 + 26]]
    mesh = jittered_grid(24, 0.9, 31, 0.4)
    obs = [MeshObstacle(TriMesh(V, np.array(T), name="terrain"), name="terrain", position=(0.25, 0.0, 0.1))]
elif case == "paddle":  # an open 8 x 8 cell paddle (two-sided, no thickness) swung at ~4 m/s through a hanging sheet
    g = np.linspace(-0.15, 0.15, 9)
    V = np.array([[0.0, y, z] for z in g for y in g]); T = []
    for j in range(8):
        for i in range(8):
            a0 = j * 9 + i; T += [[a0, a0 + 9, a0 + 1], [a0 + 1, a0 + 9, a0 + 10]]
    mesh = TriMesh.grid(24, 24, size=1.0, plane="xy", origin=(-0.5, 0.2, 0.0), name="cloth")
    pins = np.flatnonzero(np.isclose(mesh.vertices[:, 1], mesh.vertices[:, 1].max()))
    tt = np.linspace(0, 2.0, 81)  # swings about the vertical axis through (0, 0.7, 0.25), a 0.35 m arm
    qs = [[0, math.sin(0.5 * a), 0, math.cos(0.5 * a)] for a in 1.2 * np.sin(2.0 * np.pi * 0.5 * tt)]
    offs = [[0.35 * math.sin(a), 0.0, -0.35 * (1 - math.cos(a))] for a in 1.2 * np.sin(2.0 * np.pi * 0.5 * tt)]
    obs = [MeshObstacle(TriMesh(V, np.array(T), name="paddle"), name="paddle", position=(0.0, 0.7, 0.25),
                        motion=Motion(path=KeyframePath(tt, np.array(offs), np.array(qs))))]
elif case == "drag":  # a sheet pulled by two pinned corners across the thin-parts mesh at 1 m/s
    from warp_cloth.model import PinPath
    mesh = jittered_grid(20, 0.6, 37, 0.45)
    v = mesh.vertices; pins = [int(np.argmin(v[:, 0] + v[:, 2])), int(np.argmin(v[:, 0] - v[:, 2]))]
    mesh = TriMesh(v + np.array([-0.8, 0.0, 0.0]), np.asarray(mesh.triangles), name="cloth")
    p0 = mesh.vertices[pins]
    pin_path = PinPath.from_function(lambda t, p0=p0: p0 + np.array([min(t, 1.6), 0.0, 0.0]), np.linspace(0, frames / fps + 0.1, 200))
    obs = [MeshObstacle(thin_parts_mesh(), name="thin_parts", position=(0, 0.0, 0)), Plane()]
elif case == "fasttwist":  # the twist at 2 pi rad/s, 25 x 25 vertices
    from warp_cloth.contact_scenes import twist
    tw = twist(solver=solver, res=24, rate=2 * math.pi, frames=frames)
    mesh = tw.model.mesh; obs = []; pins = tw.model.pins
    scene = tw
else:
    raise SystemExit("case?")
if case != "fasttwist":
    model = ClothModel(mesh, density=density, masses=masses_arg, pin_path=pin_path, stretch_stiffness=k, damping=0.1, pins=pins,
                       velocity=vel if case == "headon" else None)
if case != "fasttwist":
    if x0 is not None: model.initial_positions = x0
    stage = CollisionStage(model, obs, thickness=th, friction=float(os.environ.get("FRIC", "0.4")), self_collision=os.environ.get("SELF", "1") == "1")
    scene = Scene(model, make_solver(solver, model, collision=stage, **eval(os.environ.get("OPTS", "{}"))), fps=fps, frames=frames,
                  substeps=substeps, name=case)
out = os.path.join(tempfile.mkdtemp(prefix="rb-"), f"{case}-{solver}.usd")
t0 = time.perf_counter(); err = None; stats = None
try:
    stats = scene.run(out, quiet=True, check_intersections=True)
except SimulationDiverged as e:
    err = str(e)[:200]
wall = time.perf_counter() - t0
_, pts, _ = read_points(out)
tris = np.asarray(mesh.triangles, np.int64); edges = edges_of(tris)
cross = nan = through = 0; clear = math.inf; inside = 0.0; worst_f = None
ts = np.linspace(0, 1, 9)[:, None, None]
for f, P in enumerate(pts):
    t = f / fps
    if not np.all(np.isfinite(P)): nan += 1; continue
    P = P.astype(np.float64)
    c = segment_triangle_hits(P, edges, P, tris, True)
    if c: cross += 1; worst_f = f
    free = np.ones(len(P), bool)
    if pins is not None: free[np.asarray(pins)] = False
    S = (P[edges[:, 0]][None] * (1 - ts) + P[edges[:, 1]][None] * ts).reshape(-1, 3)
    for ob in obs:
        if isinstance(ob, MeshObstacle):
            OV = ob.to_world(np.asarray(ob.vertices, np.float64), t); OT = np.asarray(ob.triangles, np.int64)
            h = segment_triangle_hits(P, edges, OV, OT, False) + segment_triangle_hits(OV, edges_of(OT), P, tris, False)
            through += h > 0
        else:
            d = ob.signed_distance(P[free], t); clear = min(clear, float(d.min()))
            inside = max(inside, float(-ob.signed_distance(S, t).min()))
row = dict(case=case, solver=solver, err=err, frames=len(pts), cross=cross, run_cross=None if stats is None else stats.crossing_frames,
           nan=nan, clear_mm=round(clear * 1e3, 3), run_clear_mm=None if stats is None else round(stats.min_clearance * 1e3, 3),
           run_inside=None if stats is None else stats.obstacle_frames, inside_mm=round(inside * 1e3, 3), through=through,
           strain=None if stats is None else round(100 * stats.max_strain, 2), ms=None if stats is None else round(stats.ms_per_frame, 1),
           short=None if stats is None else stats.short_frames, retried=None if stats is None else stats.retried_frames)
print(json.dumps(row), flush=True)
