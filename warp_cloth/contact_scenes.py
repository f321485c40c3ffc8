"""Contact scenes: ``drape``, ``table``, ``spin`` and ``mesh`` (``warp-cloth run NAME``).

Same keyword style as `warp_cloth.scenes.hanging`: SI units, real-cloth defaults (a free 1 m sheet
of 0.15 kg/m^2 with 1000 N/m springs and quadratic bending of 1e-4 N m: `SCENE_BENDING`),
``solver=`` any of `warp_cloth.solvers.available()`, and the contact options ``thickness`` (m),
``friction`` (mu_T) and ``restitution`` (mu_N). Each returns a `Scene` whose solver carries a
`CollisionStage` with the obstacles (simulated, and written to the USD stage by the runner);
``scene.collision`` is that stage.

- ``drape``: a sheet falls onto a sphere (r = 0.3 m) and drapes over it.
- ``table``: a sheet falls on a table (a box, top at 0.75 m) with most of it over the edge, and
  slides off onto the floor (low friction).
- ``spin``: a sheet drapes over a sphere that starts spinning about the vertical at ``start`` s;
  friction carries the cloth round.
- ``mesh``: a sheet falls onto a torus (``warp_cloth/assets/torus.obj``, 960 triangles) that then slides and
  tilts along a keyframed path.
"""

from __future__ import annotations

import math
import os

import numpy as np

from .collision import CollisionStage
from .collision.contact import DEFAULT_THICKNESS
from .collision.motion import KeyframePath, Motion, quat_from_axis_angle
from .collision.obstacles import Box, MeshObstacle, Plane, Sphere
from .mesh import TriMesh
from .model import DEFAULT_DENSITY, DEFAULT_STRETCH_STIFFNESS, ClothModel
from .scenes import _finish, _grid_shape

__all__ = ["drape", "table", "spin", "mesh", "thin", "fold", "twist", "stack", "thin_parts_mesh",
           "load_obstacle_mesh",
           "sheet_model", "SCENE_BENDING", "SCENE_NEWTON_ITERATIONS",
           "asset_path"]

#: the bending of every scene here (``bending``, ``bend_stiffness`` in N m), unless given: real
#: cloth resists bending a little, and a sheet without any folds to creases of zero radius, where
#: the layers cannot be the self-collision thickness apart (on 3 cm cells a crease through a vertex
#: must stay open about 26 degrees to keep its 2-ring 5 mm apart): self-collision then props each
#: crease open against the springs, stretching the edges around it and churning energy through
#: them. Measured at defaults (2026-11-25, 180 / 120 frames, max strain and largest one-frame
#: energy rise, without -> with): table implicit 7.74 % / 1.4e-3 J -> 3.62 % / 4.8e-7 J,
#: explicit 4.85 % / 8.1e-4 J -> 3.44 % / none, PBD 3.64 % / 1.2e-4 J -> 2.55 % / 1.7e-5 J, PD
#: 5.12 % / none -> 4.86 % / 4.7e-5 J; drape implicit 4.17 % -> 3.06 %, explicit 3.07 % -> 4.17
#: %, no rise above 3.1e-5 J either way (``python`` runs of `build_scene` with `Meter`)
SCENE_BENDING = ("quadratic", 1e-4)

#: implicit Euler's Newton iterations in every scene here, unless ``solver_options`` give them
#: (the solver's own default is 8). In contact Newton rarely reaches its tolerance (the penalty
#: dominates the residual: most steps of these scenes stop at the cap), so the cap decides how
#: far the springs are from balance. Measured at defaults (2026-11-25, `build_scene` runs with
#: `Meter`, max strain and ms/frame at 8 -> 10): table 5.20 % -> 3.73 % (12: 2.95 %), drape 2.48
#: -> 2.81 %, spin 2.84 -> 2.39 %, mesh 2.00 -> 1.69 %, fold 3.22 -> 0.75 %, stack 4.81 -> 4.00 %;
#: about 20 % more time (drape 64 -> 80, spin 66 -> 89, fold 113 -> 144, stack 89 -> 77 ms a
#: frame). At 8 the table's implicit run had passed 5 % (1.56 times explicit Euler's) on a
#: trajectory moved by a change elsewhere (4.65 % before): a margin, not luck, is wanted there
SCENE_NEWTON_ITERATIONS = 10


#: PBD's compliance in a scene whose pins follow a path (`twist`), unless ``solver_options``
#: give one: XPBD with each spring's own ``1/k`` (`PositionBased` ``compliance="springs"``).
#: Pins that move apart or wind the cloth up impose stretch, and plain PBD's constraints (with
#: their tethers) are inextensible: on the twist, once the rope's layers (kept a thickness
#: apart) needed more length than the edges had, each substep's projection pulled vertices up
#: to 20 mm into the layers around them (76 m/s) and the self-collision response pushed them
#: back, until its impact zones failed and returned the whole cloth to its start in every step
#: (frozen from frame ~111 of 600, then stopped as diverged). The material's own compliance
#: lets the cloth stretch as the springs say, as implicit Euler and projective dynamics do
#: there: the default twist then winds on to frame 257 (frozen there; 111 before), no crossing.
#: Measured: docs/bench/selfcollision.md (*PBD on the twist*)
SCENE_PBD_MOVING_PINS_COMPLIANCE = "springs"
#: the twist's projective dynamics runs no contact iterations (`ProjectiveDynamics`'s
#: ``contact_iterations``) unless asked for: its scripted pins do work, so the energy criterion
#: is off and only the penalty residual ran them, 7-9 more iterations a step once the rope
#: forms. Measured (361 frames, two runs side by side): 317 -> 244 ms a frame, no crossing
#: either way, no impact zones either way, 136.4 -> 134.6 % max strain (the twist's own)
SCENE_TWIST_PD_CONTACT_ITERATIONS = 0


def _solver_defaults(solver: str, solver_options: dict | None, model) -> dict:
    """``solver_options`` with the scenes' implicit Newton cap (`SCENE_NEWTON_ITERATIONS`)
    and, where ``model``'s pins follow a path, PBD's compliance
    (`SCENE_PBD_MOVING_PINS_COMPLIANCE`), where not given."""
    options = dict(solver_options or {})
    if solver == "implicit":
        options.setdefault("newton_iterations", SCENE_NEWTON_ITERATIONS)
    if solver == "pbd" and model.pin_path is not None and len(model.pins):
        options.setdefault("compliance", SCENE_PBD_MOVING_PINS_COMPLIANCE)
    return options


def _cloth_defaults(model_args: dict) -> dict:
    """``model_args`` with the scenes' bending (`SCENE_BENDING`) where not given."""
    model_args.setdefault("bending", SCENE_BENDING[0])
    model_args.setdefault("bend_stiffness", SCENE_BENDING[1])
    return model_args


#: the meshes shipped with the package (``warp_cloth/assets``; ``assets/make_assets.py`` makes them)
ASSETS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "assets")


def asset_path(name: str) -> str:
    """Path of a mesh shipped in the package's ``assets/`` folder (installed with it)."""
    p = os.path.join(ASSETS, name)
    if not os.path.isfile(p):
        raise ValueError(f"asset {name!r} not found in {ASSETS}; run python assets/make_assets.py")
    return p


def sheet_model(*, res: int = 32, shape=None, size: float = 1.0, height: float = 1.0,
                center=(0.0, 0.0), stiffness: float = DEFAULT_STRETCH_STIFFNESS,
                density: float = DEFAULT_DENSITY, bending: str = "none",
                bend_stiffness: float = 0.0, shear_stiffness: float = 0.0, damping: float = 0.1,
                spring_damping: float = 0.0, device=None, **model_options) -> ClothModel:
    """A free (unpinned) horizontal ``size`` m sheet at ``height`` m centred at (x, z) = ``center``."""
    nx, ny = _grid_shape(res, shape)
    w, d = size, size * ny / nx
    mesh = TriMesh.grid(nx, ny, size=(w, d), plane="xz",
                        origin=(center[0] - 0.5 * w, height, center[1] - 0.5 * d), name="cloth")
    return ClothModel(mesh, density=density, stretch_stiffness=stiffness,
                      shear_stiffness=shear_stiffness, bending=bending,
                      bend_stiffness=bend_stiffness, spring_damping=spring_damping,
                      damping=damping, device=device, **model_options)


def _contact_scene(model, obstacles, *, solver, solver_options, fps, frames, substeps,
                   corrections, extra_obstacles, strain_bound, name, thickness, friction,
                   restitution, ccd=True, self_collision=True):
    stage = CollisionStage(model, [*obstacles, *extra_obstacles], thickness=thickness,
                           friction=friction, restitution=restitution, ccd=ccd,
                           self_collision=self_collision)
    scene = _finish(model, solver, _solver_defaults(solver, solver_options, model),
                    corrections, fps, frames, substeps, (),
                    strain_bound, name, collision=stage)
    scene.contact = stage.contact
    scene.collision = stage
    return scene


def drape(*, solver: str = "explicit", solver_options: dict | None = None, fps: float = 60.0,
          frames: int = 120, substeps=None, corrections=(), obstacles=(),
          strain_bound: float = 10.0, radius: float = 0.3, sphere_center=(0.0, 0.5, 0.0),
          ground: bool = False, thickness: float = DEFAULT_THICKNESS, friction: float = 0.4,
          restitution: float = 0.0, height: float = 0.9, self_collision: bool = True,
          **model_args):
    """A sheet dropped from ``height`` m onto a sphere of ``radius`` m (and a floor if
    ``ground``). ``obstacles``: more obstacles, simulated and drawn like the others."""
    model = sheet_model(height=height, **_cloth_defaults(model_args))
    obs = [Sphere(radius, sphere_center)]
    if ground:
        obs.append(Plane())
    return _contact_scene(model, obs, solver=solver, solver_options=solver_options, fps=fps,
                          frames=frames, substeps=substeps, corrections=corrections,
                          extra_obstacles=obstacles, strain_bound=strain_bound, name="drape",
                          thickness=thickness, friction=friction, restitution=restitution,
                          self_collision=self_collision)


def table(*, solver: str = "explicit", solver_options: dict | None = None, fps: float = 60.0,
          frames: int = 180, substeps=None, corrections=(), obstacles=(),
          strain_bound: float = 10.0, table_size=(0.8, 0.75, 0.6), overhang: float = 0.45,
          thickness: float = DEFAULT_THICKNESS, friction: float = 0.15,
          restitution: float = 0.0, height: float = 0.85, self_collision: bool = True,
          **model_args):
    """A sheet dropped on a table (box ``table_size`` = width x height x depth, m) with its centre
    ``overhang`` m past the table's centre along +x, so that it slides off onto the floor."""
    w, h, d = (float(c) for c in table_size)
    if min(w, h, d) <= 0:
        raise ValueError(f"table_size must be positive, got {table_size}")
    model = sheet_model(height=height, center=(overhang, 0.0), **_cloth_defaults(model_args))
    obs = [Box((0.5 * w, 0.5 * h, 0.5 * d), (0.0, 0.5 * h, 0.0), name="table"), Plane()]
    return _contact_scene(model, obs, solver=solver, solver_options=solver_options, fps=fps,
                          frames=frames, substeps=substeps, corrections=corrections,
                          extra_obstacles=obstacles, strain_bound=strain_bound, name="table",
                          thickness=thickness, friction=friction, restitution=restitution,
                          self_collision=self_collision)


def spin(*, solver: str = "explicit", solver_options: dict | None = None, fps: float = 60.0,
         frames: int = 180, substeps=None, corrections=(), obstacles=(),
         strain_bound: float = 10.0, radius: float = 0.3, sphere_center=(0.0, 0.5, 0.0),
         spin_rate: float = 3.0, start: float = 1.0, ramp: float = 0.5,
         thickness: float = DEFAULT_THICKNESS, friction: float = 0.6,
         restitution: float = 0.0, height: float = 0.85, self_collision: bool = True,
         **model_args):
    """A sheet drapes over a sphere that starts spinning about +y at ``start`` s, reaching
    ``spin_rate`` rad/s after ``ramp`` s; friction carries the cloth round."""
    model = sheet_model(height=height, **_cloth_defaults(model_args))
    ball = Sphere(radius, sphere_center, name="ball",
                  motion=Motion(angular_velocity=(0.0, spin_rate, 0.0), start=start, ramp=ramp))
    return _contact_scene(model, [ball], solver=solver, solver_options=solver_options, fps=fps,
                          frames=frames, substeps=substeps, corrections=corrections,
                          extra_obstacles=obstacles, strain_bound=strain_bound, name="spin",
                          thickness=thickness, friction=friction, restitution=restitution,
                          self_collision=self_collision)


def torus_path(rest: float = 0.8, move: float = 1.2, back: float = 1.0) -> KeyframePath:
    """The mesh scene's path: rest, then slide 0.3 m along +x while tilting 25 degrees about z,
    then come back level and rise 0.1 m."""
    t0, t1, t2 = rest, rest + move, rest + move + back
    tilt = quat_from_axis_angle((0, 0, 1), math.radians(25.0))
    level = np.array([0.0, 0.0, 0.0, 1.0])
    return KeyframePath(times=[0.0, t0, t1, t2],
                        offsets=[[0, 0, 0], [0, 0, 0], [0.3, 0, 0], [0.0, 0.1, 0.0]],
                        rotations=[level, level, tilt, level])


def mesh(*, solver: str = "explicit", solver_options: dict | None = None, fps: float = 60.0,
         frames: int = 180, substeps=None, corrections=(), obstacles=(),
         strain_bound: float = 10.0, mesh_file: str | None = None, scale: float = 1.0,
         position=(0.0, 0.45, 0.0), path: KeyframePath | None = None, ground: bool = True,
         thickness: float = DEFAULT_THICKNESS, friction: float = 0.4,
         restitution: float = 0.0, height: float = 0.65, self_collision: bool = True,
         **model_args):
    """A sheet dropped on a triangle-mesh obstacle (default ``warp_cloth/assets/torus.obj``) that moves along
    a keyframed ``path`` (default `torus_path`), over a floor if ``ground``. ``mesh_file``: an
    ``.obj`` path or a `TriMesh` (`load_obstacle_mesh` reads any mesh file and places it on
    the floor)."""
    model = sheet_model(height=height, **_cloth_defaults(model_args))
    ob = MeshObstacle(mesh_file or asset_path("torus.obj"), position=position, scale=scale,
                      motion=Motion(path=path if path is not None else torus_path()),
                      name="torus" if mesh_file is None else None)
    obs = [ob] + ([Plane()] if ground else [])
    return _contact_scene(model, obs, solver=solver, solver_options=solver_options, fps=fps,
                          frames=frames, substeps=substeps, corrections=corrections,
                          extra_obstacles=obstacles, strain_bound=strain_bound, name="mesh",
                          thickness=thickness, friction=friction, restitution=restitution,
                          self_collision=self_collision)


def load_obstacle_mesh(path, scale: float = 1.0, gap: float = 0.1):
    """A mesh file as the `mesh` scene's obstacle, standing still on the floor: ``(mesh,
    position, height)`` for `mesh`'s ``mesh_file``, ``position`` and ``height`` (``warp-cloth
    run mesh --obstacle FILE``). ``path``: an ``.obj`` (``scale``: metres per file unit) or a
    ``.usd``/``.usda``/``.usdc`` (all its `UsdGeom.Mesh` prims as one, in metres by the stage's
    ``metersPerUnit``, times ``scale``); a Z-up stage's mesh is turned Y-up, the scenes' up.
    The mesh is centred over the origin with its lowest point on the floor (y = 0), and the
    sheet starts ``gap`` m above its highest point. Raises ValueError naming the file when it
    cannot be read or holds no usable mesh."""
    from .mesh import USD_EXTENSIONS
    from .util import positive_finite

    path = os.fspath(path)
    scale = positive_finite(scale, "obstacle scale")
    if not os.path.isfile(path):
        raise ValueError(f"obstacle mesh file {path!r} does not exist")
    if os.path.splitext(path)[1].lower() not in (".obj",) + USD_EXTENSIONS:
        raise ValueError(f"obstacle mesh file {path!r}: expected an .obj, .usd, .usda or .usdc "
                         f"file")
    tm = TriMesh.from_file(path, all_meshes=True)
    v = np.asarray(tm.vertices, dtype=np.float64)
    if getattr(tm, "up_axis", "Y") == "Z":  # (x, y, z) Z-up -> (x, z, -y) Y-up
        v = np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)
        tm = TriMesh(v, np.asarray(tm.triangles), name=tm.name)
    v = v * scale
    lo, hi = v.min(axis=0), v.max(axis=0)
    position = (-0.5 * (lo[0] + hi[0]), -lo[1], -0.5 * (lo[2] + hi[2]))
    return tm, position, float(hi[1] - lo[1]) + float(gap)


def thin_parts_mesh(*, blade=(0.5, 0.25, 0.003), blade_cells=(50, 24), ring_radius=0.3,
                    tube_radius=0.006, ring_segments=(192, 12), ring_height=0.2) -> TriMesh:
    """A closed mesh with thin parts, for testing that cloth edges do not cut through obstacles:
    a vertical blade (a box ``blade`` = width x height x thickness, m, standing on y = 0, its
    large faces split into ``blade_cells``) and a thin horizontal ring around it (a torus of
    ``ring_radius`` with a tube of ``tube_radius``, ``ring_segments`` = around x across) at
    ``ring_height``. Defaults: 9,704 triangles (4,608 in the ring)."""
    w, h, t = (float(c) for c in blade)
    nx, ny = (int(c) for c in blade_cells)
    if min(w, h, t, ring_radius, tube_radius) <= 0 or min(nx, ny) < 1:
        raise ValueError("thin_parts_mesh: sizes must be positive")
    verts, tris = [], []

    def grid(origin, du, dv, nu, nv):
        base = sum(len(v) for v in verts)
        u = np.linspace(0.0, 1.0, nu + 1)
        vv = np.linspace(0.0, 1.0, nv + 1)
        pts = (np.asarray(origin)[None, None] + u[:, None, None] * np.asarray(du)[None, None]
               + vv[None, :, None] * np.asarray(dv)[None, None]).reshape(-1, 3)
        idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1) + base
        a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
        verts.append(pts)
        tris.append(np.stack([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], 2).reshape(-1, 3))

    # the blade: six faces of the box [-w/2, w/2] x [0, h] x [-t/2, t/2], outward (u x v)
    x0, x1, z0, z1 = -0.5 * w, 0.5 * w, -0.5 * t, 0.5 * t
    grid((x0, 0, z1), (w, 0, 0), (0, h, 0), nx, ny)  # +z
    grid((x1, 0, z0), (-w, 0, 0), (0, h, 0), nx, ny)  # -z
    grid((x0, h, z1), (w, 0, 0), (0, 0, -t), nx, 1)  # +y (the rim)
    grid((x0, 0, z0), (w, 0, 0), (0, 0, t), nx, 1)  # -y
    grid((x1, 0, z1), (0, 0, -t), (0, h, 0), 1, ny)  # +x
    grid((x0, 0, z0), (0, 0, t), (0, h, 0), 1, ny)  # -x
    # weld the box's duplicate corner vertices
    v = np.concatenate(verts)
    f = np.concatenate(tris)
    key = np.round(v / (1e-6 * max(w, h, t)), 0).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    v, f = v[first], inv.reshape(-1)[f]
    # the ring
    nu, nv = (int(c) for c in ring_segments)
    a = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    b = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    A, B = np.meshgrid(a, b, indexing="ij")
    r = ring_radius + tube_radius * np.cos(B)
    ring = np.stack([r * np.cos(A), ring_height + tube_radius * np.sin(B), r * np.sin(A)], -1)
    idx = np.arange(nu * nv).reshape(nu, nv) + len(v)
    i0, i1 = idx, np.roll(idx, -1, axis=0)
    j0, j1 = i0, np.roll(i0, -1, axis=1)
    k1 = np.roll(i1, -1, axis=1)
    rt = np.stack([np.stack([i0, j1, k1], -1), np.stack([i0, k1, i1], -1)], 2).reshape(-1, 3)
    v = np.concatenate([v, ring.reshape(-1, 3)])
    f = np.concatenate([f, rt])
    return TriMesh(v, f, name="thin_parts")


def thin(*, solver: str = "explicit", solver_options: dict | None = None, fps: float = 60.0,
         frames: int = 120, substeps=None, corrections=(), obstacles=(),
         strain_bound: float = 10.0, thickness: float = DEFAULT_THICKNESS, friction: float = 0.4,
         restitution: float = 0.0, height: float = 0.45, size: float = 0.9, mesh_options=None,
         self_collision: bool = True,
         **model_args):
    """A sheet dropped onto an obstacle with thin parts (`thin_parts_mesh`: a 3 mm blade and a
    12 mm ring, 9,704 triangles) over a floor: the cloth drapes over the blade's rim and the
    ring, where its edges would cut through them without edge contact."""
    model = sheet_model(height=height, size=size, **_cloth_defaults(model_args))
    ob = MeshObstacle(thin_parts_mesh(**(mesh_options or {})), name="thin_parts")
    return _contact_scene(model, [ob, Plane()], solver=solver, solver_options=solver_options,
                          fps=fps, frames=frames, substeps=substeps, corrections=corrections,
                          extra_obstacles=obstacles, strain_bound=strain_bound, name="thin",
                          thickness=thickness, friction=friction, restitution=restitution,
                          self_collision=self_collision)


def fold(*, solver: str = "pd", solver_options: dict | None = None, fps: float = 60.0,
         frames: int = 120, substeps=None, corrections=(), obstacles=(),
         strain_bound: float = 10.0, thickness: float = DEFAULT_THICKNESS, friction: float = 0.4,
         restitution: float = 0.0, angle: float = 100.0, self_collision: bool = True,
         **model_args):
    """A sheet lying on the floor with one half lifted ``angle`` degrees about its middle line
    (past the vertical, so that it falls over): the lifted half folds down onto the other.
    Self-collision keeps the two layers apart (``self_collision=False`` lets them pass).
    Quadratic bending of 1e-4 N m by default: without bending the sheet folds to a crease of
    zero radius, where the layers cannot be the thickness apart, and the self-collision
    fail-safe holds the vertices there still (counted in its stats)."""
    _cloth_defaults(model_args)
    model = sheet_model(height=thickness, **model_args)
    x = model.mesh.vertices.copy()
    c = float(np.mean(x[:, 0]))
    a = math.radians(float(angle))
    up = x[:, 0] > c
    r = x[up, 0] - c
    x[up, 0] = c + r * math.cos(a)
    x[up, 1] = thickness + r * math.sin(a)
    model.initial_positions = x
    stage = CollisionStage(model, [Plane(), *obstacles], thickness=thickness, friction=friction,
                           restitution=restitution, self_collision=self_collision)
    scene = _finish(model, solver, _solver_defaults(solver, solver_options, model),
                    corrections, fps, frames, substeps, (),
                    strain_bound, "fold", collision=stage)
    scene.contact, scene.collision = stage.contact, stage
    return scene


def twist(*, solver: str = "pd", solver_options: dict | None = None, fps: float = 60.0,
          frames: int = 600, substeps=None, corrections=(), obstacles=(),
          strain_bound: float = 10.0, thickness: float = DEFAULT_THICKNESS, res: int = 49,
          size: float = 1.0, rate: float = math.pi / 3.0, height: float = 1.0,
          self_collision: bool = True, **model_args):
    """A square sheet (``res`` x ``res`` cells: 50 x 50 vertices by default) held by two opposite
    edges, which turn about the axis between them in opposite directions at ``rate`` rad/s (as
    Newton's cloth_twist: pi/3 rad/s for 10 s): the middle winds up into a rope that must not
    pass through itself."""
    from .model import PinPath

    n = int(res)
    mesh = TriMesh.grid(n, n, size=size, plane="xz", origin=(-0.5 * size, height, -0.5 * size),
                        name="cloth")
    x = mesh.vertices
    left = np.flatnonzero(np.isclose(x[:, 0], x[:, 0].min()))
    right = np.flatnonzero(np.isclose(x[:, 0], x[:, 0].max()))
    pins = np.concatenate([left, right])
    p0 = x[pins]
    sign = np.concatenate([np.ones(len(left)), -np.ones(len(right))])
    duration = frames / float(fps)
    times = np.linspace(0.0, duration, max(2, int(math.ceil(duration * 60.0)) + 1))

    def at(t):  # rotate each edge about the x axis through the sheet's centre line
        a = sign * rate * t
        y, z = p0[:, 1] - height, p0[:, 2]
        return np.stack([p0[:, 0], height + y * np.cos(a) - z * np.sin(a),
                         y * np.sin(a) + z * np.cos(a)], axis=1)

    _cloth_defaults(model_args)
    if solver == "pd":
        solver_options = dict(solver_options or {})
        solver_options.setdefault("contact_iterations", SCENE_TWIST_PD_CONTACT_ITERATIONS)
    model = ClothModel(mesh, density=model_args.pop("density", DEFAULT_DENSITY),
                       stretch_stiffness=model_args.pop("stiffness", DEFAULT_STRETCH_STIFFNESS),
                       pins=pins, pin_path=PinPath.from_function(at, times),
                       damping=model_args.pop("damping", 0.1), **model_args)
    # the solve's self margin at the thickness: with the obstacles' 1 cm, a vertex and the
    # triangle across its 2 cm cell's diagonal (1.4 cm) were entries of every step
    # (`CollisionStage`'s ``self_solve_margin``: 932 -> 809 ms a frame, the same motion)
    stage = CollisionStage(model, list(obstacles), thickness=thickness,
                           self_collision=self_collision, self_solve_margin=thickness) \
        if (obstacles or self_collision) else None
    scene = _finish(model, solver, _solver_defaults(solver, solver_options, model),
                    corrections, fps, frames, substeps, (),
                    strain_bound, "twist", collision=stage)
    scene.collision = stage
    scene.contact = stage.contact if stage is not None else None
    return scene


def stack(*, solver: str = "pd", solver_options: dict | None = None, fps: float = 60.0,
          frames: int = 150, substeps=None, corrections=(), obstacles=(),
          strain_bound: float = 10.0, thickness: float = DEFAULT_THICKNESS, sheets: int = 3,
          res: int = 16, size: float = 0.8, radius: float = 0.2, gap: float = 0.08,
          friction: float = 0.4, self_collision: bool = True, **model_args):
    """``sheets`` sheets (``res`` x ``res`` cells, ``size`` m) one above the other, each turned
    a little, dropped onto a sphere of ``radius`` m on the ground: they drape over it and over
    each other. Self-collision keeps them apart (one model: the sheets are one mesh)."""
    if int(sheets) < 1:
        raise ValueError(f"stack: sheets must be >= 1, got {sheets}")
    verts, tris = [], []
    base = 0
    for k in range(int(sheets)):
        g = TriMesh.grid(res, res, size=size, plane="xz",
                         origin=(-0.5 * size, 0.0, -0.5 * size))
        a = 0.35 * k
        c, s_ = math.cos(a), math.sin(a)
        v = g.vertices.copy()
        v[:, 0], v[:, 2] = c * g.vertices[:, 0] - s_ * g.vertices[:, 2], \
            s_ * g.vertices[:, 0] + c * g.vertices[:, 2]
        v[:, 1] = 2.0 * radius + 0.05 + gap * (k + 1)
        verts.append(v)
        tris.append(g.triangles + base)
        base += len(v)
    mesh = TriMesh(np.concatenate(verts), np.concatenate(tris), name="cloth")
    _cloth_defaults(model_args)
    model = ClothModel(mesh, density=model_args.pop("density", DEFAULT_DENSITY),
                       stretch_stiffness=model_args.pop("stiffness", DEFAULT_STRETCH_STIFFNESS),
                       damping=model_args.pop("damping", 0.1), **model_args)
    obs = [Sphere(radius, (0.0, radius, 0.0)), Plane(), *obstacles]
    stage = CollisionStage(model, obs, thickness=thickness, friction=friction,
                           self_collision=self_collision)
    scene = _finish(model, solver, _solver_defaults(solver, solver_options, model),
                    corrections, fps, frames, substeps, (),
                    strain_bound, "stack", collision=stage)
    scene.contact, scene.collision = stage.contact, stage
    return scene
