"""Rigid obstacles: infinite plane, sphere, box and triangle mesh, each with a scripted motion.

Every obstacle is a shape in its own local frame plus a pose: a rest centre ``position`` and
``rotation`` (unit quaternion ``(x, y, z, w)``) moved by an optional `Motion` (linear and angular
velocity with a start time and ramp, and/or a `KeyframePath`); see `warp_cloth.collision.motion`.
Local shapes and their signed distance ``phi`` (negative inside, metres):

- `Plane`: the half-space below ``y = 0`` in the local frame (built from a world ``normal`` and a
  ``point``): ``phi = y``. Infinite; a vertex anywhere below it is inside, so it cannot tunnel.
- `Sphere`: ``phi = |p| - radius``.
- `Box`: ``half_extents``; the exact box distance (outside: distance to the box; inside: minus the
  distance to the nearest face).
- `MeshObstacle`: a closed (watertight, outward-oriented: inside/outside known) or open
  (two-sided: a vertex is kept on the side it came from) triangle mesh, queried with Warp's
  `wp.Mesh` BVH. Closedness is detected from the mesh's boundary edges; a closed mesh with
  inward-facing triangles is flipped.

Each obstacle writes itself to the USD stage (`usd_define` once, `usd_write` every frame): an
``Xform`` under ``/World`` whose ``translate`` and ``orient`` are time-sampled when it moves, with
the geometry (``Sphere``, ``Cube`` scaled to the box, a ``Mesh``; a plane is a finite square
``display_size`` m wide) as its child.

Per-obstacle ``friction`` (mu_T) and ``restitution`` (mu_N) override the contact's defaults.
"""

from __future__ import annotations

import copy
import math
import os

import numpy as np

from ..util import not_text_or_bool
from .motion import FLOAT32_MAX
from .motion import (
    KIND_BOX, KIND_MESH, KIND_PLANE, KIND_SPHERE, Motion, check_quat, check_vec3, quat_between,
    quat_rotate,
)

__all__ = ["Obstacle", "Plane", "Sphere", "Box", "MeshObstacle"]


def _check_coefficient(name, value, upper=None):
    if value is None:
        return None
    not_text_or_bool(value, name)
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value) or value < 0 or (upper is not None and value > upper):
        rng = f"in [0, {upper:g}]" if upper is not None else ">= 0"
        raise ValueError(f"{name} must be finite and {rng}, got {value}")
    return value


def _box_corners(lo, hi) -> np.ndarray:
    """The 8 corners (8, 3) of the axis-aligned box ``[lo, hi]``."""
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                     for z in (lo[2], hi[2])], dtype=np.float64)


class Obstacle:
    """Base class: pose, motion, material overrides, USD output. Use a subclass."""

    kind = -1
    default_name = "obstacle"
    color = (0.55, 0.6, 0.7)

    def __init__(self, position=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0, 1.0), motion=None,
                 friction=None, restitution=None, name=None):
        self.position = check_vec3("position", position)
        self.rotation = check_quat("rotation", rotation)
        if motion is None:
            motion = Motion()
        if not isinstance(motion, Motion):
            raise TypeError(f"motion must be a warp_cloth.collision.Motion, got {type(motion).__name__}")
        self.motion = motion
        self.friction = _check_coefficient("friction", friction)
        self.restitution = _check_coefficient("restitution", restitution, upper=1.0)
        if name is not None and not isinstance(name, str):
            # (an int name passed every check and broke the run's USD output after it opened)
            raise ValueError(f"{type(self).__name__}: name must be a string or None, got "
                            f"{type(name).__name__}")
        self.name = name or self.default_name
        self._usd = None

    # ------------------------------------------------------------ pose
    @property
    def moving(self) -> bool:
        return not self.motion.is_static

    def pose(self, t: float = 0.0):
        """World centre (3,) and rotation quaternion ``(x, y, z, w)`` at time ``t`` (s)."""
        return self.motion.pose(float(t), self.position, self.rotation)

    def shifted(self, offset) -> "Obstacle":
        """A copy of this obstacle moved by ``offset`` (m; the same shape, motion and material):
        the obstacle in a simulation frame whose origin is ``-offset`` (`in_frame`). Shares the
        shape's data (a mesh's BVH is in its own local frame)."""
        ob = copy.copy(self)
        ob.position = np.asarray(self.position, dtype=np.float64) + np.asarray(offset, np.float64)
        ob._usd = None
        return ob

    def to_local(self, points, t: float = 0.0) -> np.ndarray:
        c, q = self.pose(t)
        qi = np.array([-q[0], -q[1], -q[2], q[3]])
        return quat_rotate(qi, np.asarray(points, dtype=np.float64) - c)

    def to_world(self, points, t: float = 0.0) -> np.ndarray:
        c, q = self.pose(t)
        return quat_rotate(q, np.asarray(points, dtype=np.float64)) + c

    def _travel_points(self) -> np.ndarray:
        """Local points whose rigid motion bounds that of every surface point (the corners of a
        box holding the shape: a point's displacement is affine in it, so its norm is largest
        at a corner). Overridden where part of the motion is invisible to contact."""
        h = np.asarray(self._size(), dtype=np.float64)
        return _box_corners(-h, h)

    def travel(self, t0: float, t1: float) -> float:
        """How far (m) a point of the obstacle's surface moves from time ``t0`` to ``t1`` at most
        (straight-line displacement; 0 for a static obstacle)."""
        if not self.moving:
            return 0.0
        p = self._travel_points()
        return float(np.linalg.norm(self.to_world(p, t1) - self.to_world(p, t0), axis=1).max())

    def signed_distance(self, points, t: float = 0.0) -> np.ndarray:
        """Signed distance (m, negative inside) of world points (N, 3) at time ``t``."""
        return self._local_sdf(self.to_local(np.atleast_2d(points), t))

    def _local_sdf(self, p):  # pragma: no cover - abstract
        raise NotImplementedError

    def surface_velocity(self, points, t: float = 0.0, h: float = 1e-4) -> np.ndarray:
        """Velocity (m/s) of the obstacle's material points now at ``points`` (central difference)."""
        p = np.atleast_2d(np.asarray(points, dtype=np.float64))
        local = self.to_local(p, t)
        return (self.to_world(local, t + h) - self.to_world(local, t - h)) / (2 * h)

    # ------------------------------------------------------------ device data
    def _size(self):
        return (0.0, 0.0, 0.0)

    def device_data(self, key_start: int, friction: float, restitution: float,
                    pad: float = 0.0):
        """The `ObstacleData` struct for the contact kernels; ``pad`` (m, spheres only: see
        `sphere_contact_pad`) is added to the radius the kernels see."""
        import warp as wp

        from .motion import ObstacleData

        if pad and self.kind != KIND_SPHERE:
            raise ValueError(f"{self.name}: only a sphere's contact can be padded")
        d = ObstacleData()
        d.kind = self.kind
        size = self._size()
        d.size = wp.vec3(size[0] + pad, size[1], size[2])
        d.center = wp.vec3(*self._center())
        d.closed = int(getattr(self, "closed", False))
        d.moving = int(self.moving)
        d.bound = float(self._bound()) + pad
        d.position = wp.vec3(*self.position)
        d.rotation = wp.quat(*self.rotation)
        m = self.motion
        d.velocity = wp.vec3(*m.linear_velocity)
        rate = float(np.linalg.norm(m.angular_velocity))
        d.spin_axis = wp.vec3(*(m.angular_velocity / rate if rate > 0 else (0.0, 1.0, 0.0)))
        d.spin_rate = wp.float64(rate)
        d.start = wp.float64(m.start)
        d.ramp = wp.float64(m.ramp)
        d.key_start = int(key_start)
        d.key_count = 0 if m.path is None else len(m.path.times)
        d.friction = float(friction if self.friction is None else self.friction)
        d.restitution = float(restitution if self.restitution is None else self.restitution)
        return d

    def _center(self):
        return (0.0, 0.0, 0.0)

    def _bound(self) -> float:
        """Radius of a ball about the local origin that holds the shape (0: unbounded)."""
        return 0.0

    # ------------------------------------------------------------ USD
    def usd_define(self, stage, parent: str = "/World"):
        """Define this obstacle's prims under ``parent`` (an Xform with the geometry inside)."""
        from pxr import Gf, UsdGeom

        base = f"{parent}/{''.join(c if c.isalnum() or c == '_' else '_' for c in self.name)}"
        path, k = base, 1
        while stage.GetPrimAtPath(path).IsValid():
            path, k = f"{base}_{k}", k + 1
        xf = UsdGeom.Xform.Define(stage, path)
        t_op = xf.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
        o_op = xf.AddOrientOp(UsdGeom.XformOp.PrecisionFloat)
        geom = self._usd_geometry(stage, path)
        UsdGeom.Gprim(geom.GetPrim()).CreateDisplayColorAttr([Gf.Vec3f(*self.color)])
        self._usd = (t_op, o_op)
        c, q = self.pose(0.0)
        t_op.Set(Gf.Vec3d(*c))
        o_op.Set(Gf.Quatf(float(q[3]), float(q[0]), float(q[1]), float(q[2])))
        return path

    def usd_write(self, stage, frame: int, t: float):
        """Record the pose at simulated time ``t`` at time code ``frame`` (moving obstacles only)."""
        if self._usd is None or not self.moving:
            return
        from pxr import Gf, Usd

        t_op, o_op = self._usd
        c, q = self.pose(t)
        tc = Usd.TimeCode(frame)
        t_op.Set(Gf.Vec3d(*c), tc)
        o_op.Set(Gf.Quatf(float(q[3]), float(q[0]), float(q[1]), float(q[2])), tc)

    def _usd_geometry(self, stage, path):  # pragma: no cover - abstract
        raise NotImplementedError

    def __repr__(self):
        mv = " moving" if self.moving else ""
        return f"{type(self).__name__}({self.name!r}{mv}, position={self.position.tolist()})"


class Plane(Obstacle):
    """An infinite plane through ``point`` with outward unit ``normal`` (the side the cloth is on).

    Args:
        normal: outward normal (normalised here).
        point: a point on the plane, m.
        motion, friction, restitution, name: see `Obstacle`.
        display_size: side of the square drawn in USD, m (the plane itself is infinite).
    """

    kind = KIND_PLANE
    default_name = "ground"
    color = (0.45, 0.47, 0.5)

    def __init__(self, normal=(0.0, 1.0, 0.0), point=(0.0, 0.0, 0.0), *, motion=None,
                 friction=None, restitution=None, name=None, display_size: float = 4.0):
        n = check_vec3("normal", normal)
        ln = float(np.linalg.norm(n))
        if ln < 1e-9:
            raise ValueError(f"normal must be a non-zero vector, got {normal!r}")
        self.normal = n / ln
        self.display_size = float(display_size)
        if not (math.isfinite(self.display_size) and self.display_size > 0):
            raise ValueError(f"display_size must be > 0, got {display_size}")
        super().__init__(point, quat_between((0.0, 1.0, 0.0), self.normal), motion, friction,
                         restitution, name)

    def shifted(self, offset) -> "Plane":
        """`Obstacle.shifted`; a plane that does not turn is anchored at its point nearest the
        new frame's origin (float32 keeps the point near the cloth: ``(x - p) . n`` with ``p``
        a thousand metres away rounds to 1e-4 m)."""
        ob = super().shifted(offset)
        if not np.any(self.motion.angular_velocity) and self.motion.path is None:
            n = self.normal
            ob.position = n * float(np.dot(ob.position, n))
        return ob

    def travel(self, t0: float, t1: float) -> float:
        """How far the plane moves along its normal from ``t0`` to ``t1`` (sliding in itself
        does not show; a turn is not counted)."""
        if not self.moving:
            return 0.0
        c0, _ = self.pose(t0)
        c1, _ = self.pose(t1)
        n = self.to_world(np.array([[0.0, 1.0, 0.0]]), t1)[0] - c1
        return float(abs(np.dot(c1 - c0, n)))

    def _local_sdf(self, p):
        return p[:, 1].copy()

    def _usd_geometry(self, stage, path):
        from pxr import UsdGeom

        h = 0.5 * self.display_size
        m = UsdGeom.Mesh.Define(stage, f"{path}/geom")
        m.CreatePointsAttr([(-h, 0, -h), (-h, 0, h), (h, 0, h), (h, 0, -h)])
        m.CreateFaceVertexCountsAttr([4])
        m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
        m.CreateExtentAttr([(-h, 0, -h), (h, 0, h)])
        m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        return m


class Sphere(Obstacle):
    """A solid sphere of ``radius`` m centred at ``center``."""

    kind = KIND_SPHERE
    default_name = "sphere"

    def __init__(self, radius: float, center=(0.0, 0.0, 0.0), *, rotation=(0.0, 0.0, 0.0, 1.0),
                 motion=None, friction=None, restitution=None, name=None):
        not_text_or_bool(radius, "radius", "a positive finite number of metres")
        try:
            r = float(radius)
        except (TypeError, ValueError):
            raise ValueError(f"radius must be a positive finite number of metres, got "
                             f"{radius!r}") from None
        if not (math.isfinite(r) and 0 < r <= FLOAT32_MAX):
            raise ValueError(f"radius must be a positive finite number of metres (within "
                             f"float32), got {radius}")
        self.radius = r
        super().__init__(center, rotation, motion, friction, restitution, name)

    def _size(self):
        return (self.radius, 0.0, 0.0)

    def _bound(self):
        return self.radius

    def edge_dip(self, length: float, thickness: float) -> float:
        """How deep (m) the middle of a straight cloth edge of ``length`` whose ends are held
        ``thickness`` outside dips into the sphere: the sagitta ``L^2 / (8 R)`` less the
        thickness (negative: it stays outside). Wherever the edge lies on the sphere."""
        return float(length) ** 2 / (8.0 * self.radius) - float(thickness)

    def _local_sdf(self, p):
        return np.linalg.norm(p, axis=1) - self.radius

    def _travel_points(self):  # a sphere's spin does not move its surface
        return np.zeros((1, 3))

    def _usd_geometry(self, stage, path):
        from pxr import UsdGeom

        s = UsdGeom.Sphere.Define(stage, f"{path}/geom")
        s.CreateRadiusAttr(self.radius)
        r = self.radius
        s.CreateExtentAttr([(-r, -r, -r), (r, r, r)])
        return s


class Box(Obstacle):
    """A solid box with ``half_extents`` (m) centred at ``center``, oriented by ``rotation``."""

    kind = KIND_BOX
    default_name = "box"

    def __init__(self, half_extents, center=(0.0, 0.0, 0.0), *, rotation=(0.0, 0.0, 0.0, 1.0),
                 motion=None, friction=None, restitution=None, name=None):
        h = check_vec3("half_extents", half_extents)
        if np.any(h <= 0):
            raise ValueError(f"half_extents must all be > 0 m, got {tuple(h)}")
        self.half_extents = h
        super().__init__(center, rotation, motion, friction, restitution, name)

    def _size(self):
        return tuple(self.half_extents)

    def _bound(self):
        return float(np.linalg.norm(self.half_extents))

    def _local_sdf(self, p):
        q = np.abs(p) - self.half_extents
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        return outside + inside

    def _usd_geometry(self, stage, path):
        from pxr import Gf, UsdGeom

        c = UsdGeom.Cube.Define(stage, f"{path}/geom")
        c.CreateSizeAttr(2.0)
        c.AddScaleOp().Set(Gf.Vec3f(*[float(v) for v in self.half_extents]))
        c.CreateExtentAttr([(-1, -1, -1), (1, 1, 1)])
        return c


def weld_seams(mesh):
    """``mesh`` with the vertices that share their exact coordinates merged, when that leaves
    fewer boundary edges and a valid manifold mesh; else ``mesh`` as given. Exporters split a
    closed surface's vertices along its texture seams (an OBJ of one vertex per face corner): as
    given, such a mesh is open, two-sided, with every seam edge a rim kept as a sharp feature
    (a lumpy 1,280-triangle mesh split so: 899 against 270 ms a frame, and no inside)."""
    from ..mesh import TriMesh

    v = np.asarray(mesh.vertices, dtype=np.float64)
    uniq, inv = np.unique(v, axis=0, return_inverse=True)
    if len(uniq) == len(v):
        return mesh
    tris = inv.ravel()[np.asarray(mesh.triangles, dtype=np.int64)]
    try:
        welded = TriMesh(uniq, tris, name=mesh.name)
    except ValueError:  # a triangle collapsed, or an edge shared by more than two: keep it
        return mesh
    return welded if len(welded.boundary_edges) < len(mesh.boundary_edges) else mesh


def orient_closed(mesh, vertices) -> np.ndarray:
    """The triangles of the closed manifold `TriMesh` ``mesh`` (its ``vertices`` as the obstacle
    scales them) with consistent windings: every edge is run one way by one of its two
    triangles (`TriMesh.edge_tris`) and the other way by the other. A part (connected
    component) that was inconsistent is wound so that its signed volume is positive (outward);
    a part that was consistent keeps its windings (a cavity's inward shell stays so); the
    caller then turns the whole mesh outward by its total volume. An exported mesh with some
    faces flipped otherwise had its sign of distance wrong near them (10 % of a lumpy mesh's
    faces flipped: cloth vertices 42 mm inside it, 24 % strain). Raises ValueError naming the
    mesh for a non-orientable one (a Moebius-like part)."""
    name = mesh.name
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(mesh.triangles, dtype=np.int64).copy()
    nf = len(t)
    if nf == 0:
        return t
    inner = mesh.edge_tris[:, 1] >= 0
    a, b = mesh.edges[inner, 0], mesh.edges[inner, 1]
    f1, f2 = mesh.edge_tris[inner, 0], mesh.edge_tris[inner, 1]

    def forward(f):  # does triangle f run its edge a -> b?
        k = np.argmax(t[f] == a[:, None], axis=1)
        return t[f, (k + 1) % 3] == b

    same = forward(f1) == forward(f2)  # both run the edge the same way
    if not same.any():
        return t
    nbr = [[] for _ in range(nf)]
    for g1, g2, s in zip(f1.tolist(), f2.tolist(), same.tolist()):
        nbr[g1].append((g2, s))
        nbr[g2].append((g1, s))
    flip = np.full(nf, -1, dtype=np.int64)
    for root in range(nf):
        if flip[root] >= 0:
            continue
        flip[root] = 0
        part, stack, changed = [root], [root], False
        while stack:
            f = stack.pop()
            for g, s in nbr[f]:
                want = flip[f] ^ int(s)
                if flip[g] < 0:
                    flip[g] = want
                    changed |= bool(want)
                    part.append(g)
                    stack.append(g)
                elif flip[g] != want:
                    raise ValueError(f"mesh {name!r} is not orientable (its triangles cannot "
                                     f"all be wound consistently; e.g. around triangle {g}); a "
                                     "closed obstacle needs an inside and an outside")
        if changed:
            part = np.asarray(part)
            sel = part[flip[part] == 1]
            t[sel] = t[sel][:, [0, 2, 1]]
            a, b, c = v[t[part, 0]], v[t[part, 1]], v[t[part, 2]]
            if np.einsum("ij,ij->i", a, np.cross(b, c)).sum() < 0:
                t[part] = t[part][:, [0, 2, 1]]
    return t


class MeshObstacle(Obstacle):
    """A rigid triangle mesh obstacle.

    Args:
        mesh: a `warp_cloth.TriMesh`, a path to an ``.obj`` file or a USD stage (every mesh
            of the stage as one, in metres: `TriMesh.from_usd` with ``all_meshes``), or
            ``(vertices, triangles)``.
            Its vertices are the local frame (times ``scale``); spin is about the local origin.
        position, rotation: rest pose of the local origin.
        scale: uniform scale (> 0) applied to the vertices.
        closed: ``None`` (default) detects it: closed when no edge has a single triangle. A closed
            mesh must be watertight; inside points are pushed out. An open mesh is two-sided.
        motion, friction, restitution, name: see `Obstacle`.

    The `wp.Mesh` (BVH) is built on first use on the contact's device (`wp_mesh`).
    """

    kind = KIND_MESH
    default_name = "mesh_obstacle"

    def __init__(self, mesh, *, position=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0, 1.0),
                 scale: float = 1.0, closed=None, motion=None, friction=None, restitution=None,
                 name=None):
        from ..mesh import TriMesh

        if isinstance(mesh, (str, os.PathLike)):
            # a USD stage's first mesh (in metres, in the stage's frame), else an OBJ (a stage
            # was read as an OBJ: "no vertices found")
            mesh = TriMesh.from_file(mesh, all_meshes=True)
        elif isinstance(mesh, tuple) and len(mesh) == 2:
            mesh = TriMesh(np.asarray(mesh[0], dtype=np.float64), np.asarray(mesh[1]),
                           name=name or self.default_name)
        if not isinstance(mesh, TriMesh):
            raise TypeError("mesh must be a TriMesh, an .obj path or (vertices, triangles)")
        not_text_or_bool(scale, "scale", "a positive finite number")
        try:
            scale = float(scale)
        except (TypeError, ValueError):
            raise ValueError(f"scale must be a positive finite number, got {scale!r}") from None
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"scale must be a positive finite number, got {scale}")
        if scale * float(np.abs(np.asarray(mesh.vertices, dtype=np.float64)).max(initial=0.0)) \
                > FLOAT32_MAX:
            raise ValueError(f"scale {scale:g} puts the mesh's vertices beyond the float32 range "
                             "the simulation computes in")
        given = mesh
        if len(mesh.boundary_edges):
            mesh = weld_seams(mesh)
        auto_closed = len(mesh.boundary_edges) == 0
        if closed is None:
            closed = auto_closed
        elif closed and not auto_closed:
            raise ValueError(f"mesh {mesh.name!r} has {len(mesh.boundary_edges)} boundary edges; "
                             "it cannot be used as a closed obstacle")
        self.closed = bool(closed)
        verts = np.asarray(mesh.vertices, dtype=np.float64) * scale
        tris = np.asarray(mesh.triangles, dtype=np.int64).copy()
        if self.closed:
            tris = orient_closed(mesh, verts)
            a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
            vol = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
            if vol < 0:  # inward-facing: flip so that normals point out
                tris = tris[:, [0, 2, 1]]
        self.vertices = verts
        self.triangles = tris
        self.source = given  # as given (before welding and winding)
        self._wp_mesh = {}
        super().__init__(position, rotation, motion, friction, restitution, name or mesh.name)

    @property
    def num_triangles(self) -> int:
        return len(self.triangles)

    def shifted(self, offset) -> "MeshObstacle":
        """`Obstacle.shifted`; a mesh whose vertices lie far from its own origin (an OBJ
        exported in world coordinates: its vertices 1,000 m out, ``position`` zero) and that
        does not turn is also re-centred on its vertices' bounding box (the same surface, its
        vertices near its origin, its origin moved there): its BVH queries run in float32 in
        that frame (a sheet draped on such a sphere kept 4.93 mm of a 5 mm clearance against
        5.00 mm with the same sphere given by ``position``)."""
        ob = super().shifted(offset)
        from ..model import frame_origin

        path = self.motion.path
        turns = bool(np.any(self.motion.angular_velocity)) or (
            path is not None and not np.allclose(np.abs(path.rotations[:, 3]), 1.0))
        c = frame_origin(self.vertices)
        if turns or not np.any(c):
            return ob
        ob.vertices = self.vertices - c
        ob.position = ob.position + quat_rotate(np.asarray(self.rotation, np.float64), c)
        ob._wp_mesh = {}
        return ob

    def wp_mesh(self, device):
        """The `wp.Mesh` of the local-frame vertices on ``device`` (built once per device)."""
        import warp as wp

        key = str(wp.get_device(device))
        if key not in self._wp_mesh:
            pts = wp.array(self.vertices, dtype=wp.vec3, device=device)
            idx = wp.array(self.triangles.astype(np.int32).reshape(-1), dtype=wp.int32, device=device)
            self._wp_mesh[key] = wp.Mesh(points=pts, indices=idx)
        return self._wp_mesh[key]

    def _size(self):
        return tuple(0.5 * (self.vertices.max(axis=0) - self.vertices.min(axis=0)))

    def _center(self):
        return tuple(0.5 * (self.vertices.max(axis=0) + self.vertices.min(axis=0)))

    def _travel_points(self):  # the corners of the vertices' bounding box
        return _box_corners(self.vertices.min(axis=0), self.vertices.max(axis=0))

    def _bound(self):
        return float(np.linalg.norm(self.vertices, axis=1).max())

    def _local_sdf(self, p):
        from .mesh_contact import mesh_signed_distance

        return mesh_signed_distance(self, p)

    def _usd_geometry(self, stage, path):
        from pxr import UsdGeom, Vt

        m = UsdGeom.Mesh.Define(stage, f"{path}/geom")
        m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(self.vertices.astype(np.float32)))
        m.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(self.triangles), 3, np.int32)))
        m.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(self.triangles.astype(np.int32).reshape(-1)))
        m.CreateExtentAttr([tuple(self.vertices.min(axis=0)), tuple(self.vertices.max(axis=0))])
        m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        m.CreateDoubleSidedAttr(not self.closed)
        return m


#: cloth lying on a sphere is taken this much longer than at rest (its `cloth_chord`) when its
#: vertex contact is padded (`sphere_contact_pad`): cloth stretches a few percent
SPHERE_EDGE_STRETCH = 1.05


def sphere_needs_features(sphere: "Sphere", chord: float, thickness: float) -> bool:
    """Whether a cloth whose rest `cloth_chord` is ``chord`` m would cut more than half the
    thickness into ``sphere`` between vertices held the thickness out: its triangles are then
    kept out too (`features.FeatureContact`, the sphere's centre as a sharp vertex)."""
    return sphere.edge_dip(chord, thickness) > 0.5 * float(thickness)


def cloth_chord(vertices, triangles) -> float:
    """The largest diameter over a mesh's triangles of the smallest circle holding the triangle
    (its circumcircle when acute, its longest edge as diameter otherwise): a flat triangle
    whose corners lie on a sphere dips deepest below it by the sagitta of that chord. For a
    grid's right triangles it is the diagonal; for equilateral ones 2/sqrt(3) of the edge."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if not len(t):
        return 0.0
    p = v[t]
    l2 = np.stack([((p[:, 1] - p[:, 2]) ** 2).sum(1), ((p[:, 2] - p[:, 0]) ** 2).sum(1),
                   ((p[:, 0] - p[:, 1]) ** 2).sum(1)], axis=1)
    big = l2.max(axis=1)
    obtuse = 2.0 * big >= l2.sum(axis=1)  # the largest angle is 90 degrees or more
    area2 = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)  # 2 A
    with np.errstate(divide="ignore", invalid="ignore"):
        circum = np.sqrt(l2.prod(axis=1)) / np.maximum(area2, 1e-300)  # 2 R = abc / (2 A)
    d = np.where(obtuse | (area2 <= 0.0), np.sqrt(big), circum)
    return float(d.max())


def sphere_contact_pad(sphere: "Sphere", chord: float, thickness: float) -> float:
    """Metres added to the radius the vertex contact sees, so that a cloth triangle (its
    `cloth_chord` stretched by `SPHERE_EDGE_STRETCH`) between vertices held the thickness from
    that larger sphere stays outside this one: the chord's dip (`Sphere.edge_dip`) when
    positive, 0 when the sphere is flat enough for the cloth's cells or curved enough for the
    triangle entries (`sphere_needs_features`, asked with the chord). The cloth then rests up to
    about half the thickness farther out than the thickness. Measured: a jittered 20 x 20 sheet
    (79 mm rest diagonals) on a 0.15 m sphere, vertices held 5 mm out: an edge 0.17 mm inside it
    (implicit Euler, `docs/bench/probes/robust.py massratio`), none with the pad (0.83 mm); a
    sheet of equilateral triangles (9 cm edges) on a 0.25 m sphere: every edge outside, the
    triangles' middles 0.44 mm inside (PD) before the chord replaced the longest edge."""
    if sphere_needs_features(sphere, chord, thickness):
        return 0.0
    return max(0.0, sphere.edge_dip(SPHERE_EDGE_STRETCH * float(chord), thickness))


def in_frame(obstacles, origin) -> list:
    """``obstacles`` in a simulation frame centred on the world point ``origin``
    (`warp_cloth.model.ClothModel.origin`): `Obstacle.shifted` copies, or the same list when
    ``origin`` is None or zero."""
    obstacles = list(obstacles)
    if origin is None or not np.any(origin):
        return obstacles
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    return [ob.shifted(-o) for ob in obstacles]
