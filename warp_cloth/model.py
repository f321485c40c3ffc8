"""`ClothModel` (constant device data for a run) and `State` (positions, velocities, time).

The model is built once from a `TriMesh` and material parameters, in SI units:

- lumped vertex masses from triangle area x areal density (kg/m^2), or given per vertex (kg);
- springs (index pairs, rest lengths in m, stiffness in N/m): one on every mesh edge (stretch),
  optionally shear springs (the missing diagonal of every grid cell) and bending springs (skip-one
  springs along grid rows/columns; across every interior edge for unstructured meshes);
- pinned vertices (inverse mass 0), optionally following a scripted `PinPath`;
- gravity (m/s^2) and a velocity damping rate (1/s): ``v <- v * exp(-damping * dt)`` each step;
- optional force terms that the solvers evaluate: wind (`warp_cloth.forces.wind.Wind`) and
  dihedral or quadratic bending (`warp_cloth.forces.bending`).

Only the force terms a model names are ever launched, so a cloth without wind or bending never
compiles their kernels.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from .mesh import FLOAT32_MAX, TriMesh, _number_array, index_array

__all__ = ["ClothModel", "State", "PinPath", "DEFAULT_DENSITY", "DEFAULT_STRETCH_STIFFNESS",
           "ORIGIN_THRESHOLD"]

#: kg/m^2, a light cotton or polyester (real cloth: about 0.1-0.3 kg/m^2)
DEFAULT_DENSITY = 0.15
#: N/m per spring; for a spring grid this is close to the sheet's membrane stiffness, independent
#: of resolution. Keeps the hanging 1 m sheet's stretch at a few tenths of a percent.
DEFAULT_STRETCH_STIFFNESS = 1000.0

#: m/s^2, down the mesh's up axis unless ``gravity`` is given
STANDARD_GRAVITY = 9.81

#: m: a cloth whose bounding box's centre is farther than this from the world origin along
#: some axis is simulated in a frame centred on it (`ClothModel`'s ``origin``): float32
#: positions 1,000 m out are resolved to 6e-5 m, and a step's small moves rounded away
#: (a 16 x 16 fold there froze under projective dynamics, gained 94 % of its energy under
#: PBD and did not fold under explicit Euler; at the origin all three folded alike).
#: Within it positions resolve to 5e-7 m or better
ORIGIN_THRESHOLD = 4.0

BENDING_MODELS = ("none", "springs", "dihedral", "quadratic")


@dataclass
class PinPath:
    """A scripted motion for the pinned vertices: keyframes interpolated linearly in time.

    Args:
        times: (K,) strictly increasing keyframe times in seconds. Before the first key the pins
            sit at the first key; after the last they stay at the last.
        positions: (K, P, 3) positions of the P pinned vertices (in the order of ``pins``) at each
            key, in metres.

    Use `PinPath.from_function` to sample any ``f(t) -> (P, 3)`` at chosen times.
    """

    times: np.ndarray
    positions: np.ndarray

    def __post_init__(self):
        self.times = np.asarray(self.times, dtype=np.float64).reshape(-1)
        self.positions = np.asarray(self.positions, dtype=np.float64)
        k = len(self.times)
        if k < 1:
            raise ValueError("PinPath: needs at least one keyframe")
        if self.positions.ndim != 3 or self.positions.shape[0] != k or self.positions.shape[2] != 3:
            raise ValueError(
                f"PinPath: positions must have shape (K={k}, P, 3), got {self.positions.shape}"
            )
        if not np.all(np.isfinite(self.times)) or not np.all(np.isfinite(self.positions)):
            raise ValueError("PinPath: times and positions must be finite")
        if self.positions.size and np.abs(self.positions).max() > FLOAT32_MAX:
            raise ValueError("PinPath: positions beyond the float32 range the simulation "
                             "computes in")
        if k > 1 and np.any(np.diff(self.times) <= 0):
            i = int(np.argmax(np.diff(self.times) <= 0))
            raise ValueError(f"PinPath: times must increase strictly (key {i + 1})")

    @classmethod
    def from_function(cls, fn, times) -> "PinPath":
        times = np.asarray(times, dtype=np.float64)
        return cls(times, np.stack([np.asarray(fn(t), dtype=np.float64) for t in times]))


class State:
    """Positions ``x`` (m), velocities ``v`` (m/s) and the simulated time (s) on the device.

    The time lives in a one-element device array so that a whole step, scripted pins and moving
    obstacles included, can be recorded once as a Warp graph and replayed.
    """

    def __init__(self, x: wp.array, v: wp.array, time: wp.array, origin=None):
        self.x, self.v, self.time = x, v, time
        #: the world point of the simulation frame (`ClothModel.origin`): ``x`` is relative to it
        self.origin = (np.zeros(3) if origin is None
                       else np.asarray(origin, dtype=np.float64).reshape(3))

    @property
    def t(self) -> float:
        """The simulated time in seconds (a host read; not for use inside a step)."""
        return float(self.time.numpy()[0])

    def positions(self) -> np.ndarray:
        """``x`` (N, 3) in float64: the simulation frame (`ClothModel.origin`)."""
        return self.x.numpy().astype(np.float64)

    def world_positions(self) -> np.ndarray:
        """World positions (N, 3) in float64: ``x`` plus the simulation frame's origin."""
        return self.x.numpy().astype(np.float64) + self.origin

    def velocities(self) -> np.ndarray:
        return self.v.numpy().astype(np.float64)

    def clone(self) -> "State":
        return State(wp.clone(self.x), wp.clone(self.v), wp.clone(self.time), self.origin)

    def assign(self, other: "State") -> None:
        """Copy another state's arrays into this one (no allocation)."""
        wp.copy(self.x, other.x)
        wp.copy(self.v, other.v)
        wp.copy(self.time, other.time)


def _number(name: str, x) -> float:
    """``x`` as a float, or `ValueError` naming the parameter."""
    if isinstance(x, (str, bytes)) or x is None:
        raise ValueError(f"{name} must be a number, got {x!r}")
    try:
        return float(x)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{name} must be a number, got {x!r}") from None


def _check_float32(name: str, values, unit: str = "") -> None:
    """Reject values the device's float32 arrays cannot hold (they would become inf)."""
    a = np.abs(np.asarray(values, dtype=np.float64))
    if a.size and a.max() > FLOAT32_MAX:
        k = int(np.argmax(a.reshape(-1)))
        where = f" (entry {k})" if a.size > 1 else ""
        raise ValueError(f"{name}{where} is {np.asarray(values).reshape(-1)[k]:.4g}{unit}, beyond "
                         f"the float32 range (+-{FLOAT32_MAX:.3g}) the simulation computes in")


def _check_stiffness(name: str, k) -> float:
    k = _number(name, k)
    if not (math.isfinite(k) and k >= 0.0):
        raise ValueError(f"{name} must be finite and >= 0, got {k}")
    _check_float32(name, k)
    return k


def _choose_origin(points, origin) -> np.ndarray:
    """`ClothModel`'s ``origin``: given (a finite 3-vector), or the bounding box's centre of
    ``points`` rounded to whole metres when farther than `ORIGIN_THRESHOLD` along some axis."""
    if origin is not None:
        o = _number_array(origin, "origin", "3 numbers (m)").reshape(-1)
        if o.shape != (3,) or not np.all(np.isfinite(o)):
            raise ValueError(f"origin must be 3 finite numbers (m), got {origin!r}")
        _check_float32("origin", o, " m")
        return o.astype(np.float64)
    return frame_origin(points)


def frame_origin(points) -> np.ndarray:
    """The origin of a simulation frame for ``points`` (N, 3): their bounding box's centre
    rounded to whole metres when it is farther than `ORIGIN_THRESHOLD` from the origin along
    some axis, else zeros (`ClothModel`'s default ``origin``; a mesh obstacle's re-centring,
    `MeshObstacle.shifted`)."""
    p = np.asarray(points, dtype=np.float64)
    c = 0.5 * (p.min(axis=0) + p.max(axis=0)) if len(p) else np.zeros(3)
    if np.abs(c).max() <= ORIGIN_THRESHOLD:
        return np.zeros(3)
    return np.round(c)


def _pin_indices(pins, n: int) -> np.ndarray:
    """Pins as vertex indices: a list of integers, or a boolean mask with one entry per vertex."""
    if pins is None:
        return np.zeros(0, dtype=np.int64)
    if not isinstance(pins, (str, bytes)):
        try:
            arr = np.asarray(pins)
        except (TypeError, ValueError):
            arr = None
        if arr is not None and arr.dtype.kind == "b":
            if arr.shape != (n,):
                raise ValueError(f"pins: a boolean mask needs one entry per vertex ({n}), got "
                                 f"shape {arr.shape}")
            return np.flatnonzero(arr).astype(np.int64)
    return index_array(pins, "pins", "vertex").reshape(-1)


class ClothModel:
    """Constant device data of a cloth: masses, springs, pins, gravity, damping, force terms.

    Args:
        mesh: the cloth's `TriMesh` (rest shape = its vertices).
        density: areal density in kg/m^2 for lumped masses (ignored if ``masses`` is given).
        masses: optional (N,) vertex masses in kg (all > 0).
        stretch_stiffness: N/m of the spring on every mesh edge: one number, or one per edge in
            the order of ``mesh.edges`` (anisotropic or graded materials).
        shear_stiffness: N/m of the extra cell diagonal springs (grid meshes only); 0 = none.
        bending: ``"none"``, ``"springs"`` (skip-one springs on a grid, across-edge springs on an
            unstructured mesh), ``"dihedral"`` (Bridson et al. 2003) or ``"quadratic"`` (Bergou et
            al. 2006).
        bend_stiffness: N/m for bending springs; N*m for the dihedral and quadratic models.
        spring_damping: N*s/m dashpot along every spring (explicit solver only; the implicit
            methods damp numerically).
        pins: vertex indices held fixed (inverse mass 0).
        pin_path: optional `PinPath` the pins follow; without it they stay at their rest positions.
        gravity: m/s^2, a 3-vector; default ``None``: 9.81 m/s^2 down the mesh's up axis
            (``mesh.up_axis``: -y for a Y-up mesh, -z for a Z-up one such as a Z-up USD file).
        damping: velocity damping rate in 1/s, ``v <- v exp(-damping dt)`` every step. The
            library default is 0 (undamped: exact energy tests); the built-in scenes and the CLI
            use 0.1 1/s.
        wind: optional `warp_cloth.forces.wind.Wind`.
        velocity: optional initial velocity, (3,) or (N, 3), m/s.
        positions: optional initial positions (N, 3), m (default: the mesh's vertices, which
            stay the rest shape either way).
        device: Warp device (default: Warp's default device).
        origin: the world point (m) that the simulation frame is centred on. ``None`` (the
            default): the centre of the initial positions' bounding box rounded to whole
            metres when it is farther than `ORIGIN_THRESHOLD` (4 m) from the world origin
            along some axis, else ``(0, 0, 0)``; ``(0, 0, 0)`` keeps the world frame.

    The solvers compute in float32 in the simulation frame, ``world = simulation + origin``:
    ``model.mesh``, ``initial_positions``, ``x_rest``, the pins' path and ``state.x`` are in
    it; `State.world_positions` and the USD output, the run's heights and energies, the obstacles
    (given in the world frame, moved into this one by the collision stage) are in the
    world frame. Near the world origin the two are the same (``origin`` zero).
    """

    def __init__(
        self,
        mesh: TriMesh,
        *,
        density: float = DEFAULT_DENSITY,
        masses=None,
        stretch_stiffness: float = DEFAULT_STRETCH_STIFFNESS,
        shear_stiffness: float = 0.0,
        bending: str = "none",
        bend_stiffness: float = 0.0,
        spring_damping: float = 0.0,
        pins=(),
        pin_path: PinPath | None = None,
        gravity=None,
        damping: float = 0.0,
        wind=None,
        velocity=None,
        positions=None,
        device=None,
        origin=None,
    ):
        if not isinstance(mesh, TriMesh):
            raise TypeError(f"mesh must be a TriMesh, got {type(mesh).__name__}")
        self.device = wp.get_device(device)
        n = mesh.num_vertices
        if positions is not None:
            positions = _number_array(positions, "positions", f"an ({n}, 3) array (m)")
            if positions.shape != (n, 3):
                raise ValueError(f"positions must have shape ({n}, 3), got {positions.shape}")
            bad = np.flatnonzero(~np.isfinite(positions).all(axis=1))
            if len(bad):
                raise ValueError(f"positions of vertex {int(bad[0])} are not finite")
            _check_float32("positions", positions, " m")
        #: the world point the simulation frame is centred on (float64, m; see the class doc)
        self.origin = _choose_origin(positions if positions is not None else mesh.vertices,
                                     origin)
        #: the mesh as given, in the world frame (``mesh``: in the simulation frame)
        self.world_mesh = mesh
        if np.any(self.origin):
            mesh = copy.copy(mesh)
            mesh.vertices = np.asarray(self.world_mesh.vertices, dtype=np.float64) - self.origin
            if positions is not None:
                positions = positions - self.origin
            if pin_path is not None and isinstance(pin_path, PinPath):
                pin_path = PinPath(pin_path.times, pin_path.positions - self.origin)
        self.mesh = mesh

        # ---- masses
        if masses is None:
            density = _number("density", density)
            if not (math.isfinite(density) and density > 0):
                raise ValueError(f"density must be a positive finite number (kg/m^2), got {density}")
            used = np.zeros(n, dtype=bool)
            used[mesh.triangles.reshape(-1)] = True
            if not used.all():
                i = int(np.argmin(used))
                raise ValueError(f"vertex {i} is isolated (in no triangle): it gets no mass from "
                                 f"the density; remove it from the mesh or give masses")
            m = mesh.vertex_areas() * density
            self.density = density
        else:
            m = _number_array(masses, "masses", "one mass per vertex in kg").reshape(-1)
            if len(m) != n:
                raise ValueError(f"masses has {len(m)} entries, the mesh has {n} vertices")
            self.density = None
        bad = np.flatnonzero(~(np.isfinite(m) & (m > 0)))
        if len(bad):
            raise ValueError(f"vertex {int(bad[0])} has non-positive or non-finite mass {m[bad[0]]}")
        _check_float32("mass of a vertex", m, " kg")
        if (1.0 / m).max() > FLOAT32_MAX:
            i = int(np.argmin(m))
            raise ValueError(f"vertex {i} has mass {m[i]:.3g} kg: its inverse is beyond float32")

        # ---- pins
        pins = _pin_indices(pins, n)
        bad = np.flatnonzero((pins < 0) | (pins >= n))
        if len(bad):
            raise ValueError(f"pin {int(pins[bad[0]])} is not a vertex index in [0, {n - 1}]")
        uniq, cnt = np.unique(pins, return_counts=True)
        if (cnt > 1).any():
            raise ValueError(f"vertex {int(uniq[np.argmax(cnt > 1)])} is pinned twice")
        self.pins = pins
        inv_m = 1.0 / m
        inv_m[pins] = 0.0
        self.masses = m
        self.inverse_masses = inv_m

        if pin_path is not None:
            if not isinstance(pin_path, PinPath):
                raise TypeError("pin_path must be a PinPath")
            if pin_path.positions.shape[1] != len(pins):
                raise ValueError(
                    f"pin_path moves {pin_path.positions.shape[1]} vertices, pins has {len(pins)}"
                )
        self.pin_path = pin_path

        # ---- springs
        ks_edges = _number_array(stretch_stiffness, "stretch_stiffness",
                                 "a number or one per edge (N/m)")
        if ks_edges.ndim == 0:
            ks_edges = np.full(len(mesh.edges), _check_stiffness("stretch_stiffness", ks_edges))
        elif ks_edges.shape != (len(mesh.edges),):
            raise ValueError(f"stretch_stiffness must be a number or one per edge, shape "
                             f"({len(mesh.edges)},): got shape {ks_edges.shape}")
        bad = np.flatnonzero(~(np.isfinite(ks_edges) & (ks_edges >= 0)))
        if len(bad):
            raise ValueError(f"stretch_stiffness of edge {int(bad[0])} {tuple(mesh.edges[bad[0]])} "
                             f"must be finite and >= 0, got {ks_edges[bad[0]]}")
        _check_float32("stretch_stiffness", ks_edges, " N/m")
        self.stretch_stiffness = float(ks_edges.max()) if len(ks_edges) else 0.0
        self.shear_stiffness = _check_stiffness("shear_stiffness", shear_stiffness)
        self.bend_stiffness = _check_stiffness("bend_stiffness", bend_stiffness)
        self.spring_damping = _check_stiffness("spring_damping", spring_damping)
        if not isinstance(bending, str) or bending not in BENDING_MODELS:
            raise ValueError(f"bending must be one of {BENDING_MODELS}, got {bending!r}")
        self.bending = bending
        pairs, ks, kinds = [mesh.edges], [ks_edges], ["stretch"]
        if self.shear_stiffness > 0:
            sh = self._shear_pairs()
            pairs.append(sh), ks.append(np.full(len(sh), self.shear_stiffness)), kinds.append("shear")
        if bending == "springs" and self.bend_stiffness > 0:
            bp = self._bend_spring_pairs()
            pairs.append(bp), ks.append(np.full(len(bp), self.bend_stiffness)), kinds.append("bend")
        pairs = np.concatenate(pairs).astype(np.int64)
        self.spring_pairs = pairs
        self.spring_stiffness = np.concatenate(ks)
        x0 = mesh.vertices
        self.spring_rest = np.linalg.norm(x0[pairs[:, 0]] - x0[pairs[:, 1]], axis=1)
        _check_float32("a spring's rest length", self.spring_rest, " m")
        self.num_stretch_springs = len(mesh.edges)  # the first springs are the mesh edges

        # ---- global parameters
        #: the mesh's up axis ("Y" or "Z") and its index: heights in RunStats, the output frame
        self.up_axis = mesh.up_axis
        self.up_index = 1 if mesh.up_axis == "Y" else 2
        if gravity is None:
            g = np.zeros(3)
            g[self.up_index] = -STANDARD_GRAVITY
        else:
            g = _number_array(gravity, "gravity", "3 numbers (m/s^2)").reshape(-1)
        if g.shape != (3,) or not np.all(np.isfinite(g)):
            raise ValueError(f"gravity must be 3 finite numbers, got {gravity}")
        _check_float32("gravity", g, " m/s^2")
        self.gravity = tuple(float(c) for c in g)
        self.damping = _check_stiffness("damping", damping)

        v0 = np.zeros((n, 3))
        if velocity is not None:
            va = _number_array(velocity, "velocity", "a 3-vector or (N, 3) array (m/s)")
            try:
                v0 = np.broadcast_to(va, (n, 3)).copy()
            except ValueError:
                raise ValueError(f"velocity must have shape (3,) or ({n}, 3), got {va.shape}") from None
            if not np.all(np.isfinite(v0)):
                raise ValueError("initial velocity must be finite")
            _check_float32("velocity", v0, " m/s")
            v0[pins] = 0.0
        self.initial_velocity = v0
        x0 = mesh.vertices if positions is None else positions
        #: the initial positions in the simulation frame (world minus ``origin``)
        self.initial_positions = x0

        # ---- device arrays (built once)
        d = self.device
        self.num_vertices = n
        self.num_triangles = mesh.num_triangles
        self.num_springs = len(pairs)
        self.x_rest = wp.array(x0, dtype=wp.vec3, device=d)
        self.mass = wp.array(m, dtype=wp.float32, device=d)
        self.inv_mass = wp.array(inv_m, dtype=wp.float32, device=d)
        self.tri_indices = wp.array(mesh.triangles.astype(np.int32), dtype=wp.int32, ndim=2, device=d)
        self.spring_indices = wp.array(pairs.astype(np.int32), dtype=wp.int32, ndim=2, device=d)
        self.spring_rest_length = wp.array(self.spring_rest, dtype=wp.float32, device=d)
        self.spring_k = wp.array(self.spring_stiffness, dtype=wp.float32, device=d)
        self.pin_indices = wp.array(pins.astype(np.int32), dtype=wp.int32, device=d)
        if pin_path is not None:
            self.pin_times = wp.array(pin_path.times, dtype=wp.float64, device=d)
            self.pin_keys = wp.array(
                pin_path.positions.reshape(-1, 3), dtype=wp.vec3, device=d
            )  # key k, pin p at k * P + p
        else:
            self.pin_times = None
            self.pin_keys = None

        # ---- optional force terms (each in its own Warp module)
        self.force_terms = []
        from .forces.springs import SpringForce

        if self.num_springs:
            self.force_terms.append(SpringForce(self))
        if bending in ("dihedral", "quadratic") and self.bend_stiffness > 0:
            from .forces import bending as _bending

            cls = _bending.DihedralBending if bending == "dihedral" else _bending.QuadraticBending
            self.force_terms.append(cls(self, self.bend_stiffness))
        if wind is not None and not hasattr(wind, "bind"):
            raise ValueError(f"wind must be a warp_cloth.Wind or None, got {type(wind).__name__}")
        self.wind = wind
        if wind is not None:
            self.force_terms.append(wind.bind(self))

    # ------------------------------------------------------------------ helpers
    def _shear_pairs(self) -> np.ndarray:
        """The diagonal of every grid cell that is not a mesh edge, ``(min, max)``, in cell order
        (row-major), the ``v00-v11`` diagonal before the ``v10-v01`` one. Vectorised."""
        if self.mesh.grid_shape is None:
            raise ValueError("shear_stiffness > 0 needs a structured grid mesh (TriMesh.grid)")
        nx, ny = self.mesh.grid_shape
        n = self.mesh.num_vertices
        j, i = np.meshgrid(np.arange(ny, dtype=np.int64), np.arange(nx, dtype=np.int64),
                           indexing="ij")
        v00 = (j * (nx + 1) + i).reshape(-1)
        cand = np.stack([np.stack([v00, v00 + nx + 2], 1),
                         np.stack([v00 + 1, v00 + nx + 1], 1)], axis=1).reshape(-1, 2)
        cand = np.sort(cand, axis=1)
        # the edges are sorted lexicographically, so their keys a * n + b are sorted
        ekey = self.mesh.edges[:, 0] * n + self.mesh.edges[:, 1]
        key = cand[:, 0] * n + cand[:, 1]
        at = np.minimum(np.searchsorted(ekey, key), len(ekey) - 1)
        have = ekey[at] == key
        return cand[~have].reshape(-1, 2)

    def _bend_spring_pairs(self) -> np.ndarray:
        """Skip-one springs along grid rows and columns, vertex by vertex (row-major), the row
        spring ``(v, v + 2)`` before the column spring ``(v, v + 2 (nx + 1))``; across every
        interior edge for an unstructured mesh. Vectorised."""
        if self.mesh.grid_shape is None:
            return self.mesh.bending_pairs
        nx, ny = self.mesh.grid_shape
        j, i = np.meshgrid(np.arange(ny + 1, dtype=np.int64), np.arange(nx + 1, dtype=np.int64),
                           indexing="ij")
        j, i = j.reshape(-1), i.reshape(-1)
        v = j * (nx + 1) + i
        cand = np.stack([np.stack([v, v + 2], 1), np.stack([v, v + 2 * (nx + 1)], 1)], axis=1)
        keep = np.stack([i + 2 <= nx, j + 2 <= ny], axis=1)
        return cand[keep].reshape(-1, 2)

    def state(self) -> State:
        """A new state at the initial positions (default: the rest shape) with the initial
        velocity, at time 0."""
        d = self.device
        return State(
            wp.array(self.initial_positions, dtype=wp.vec3, device=d),
            wp.array(self.initial_velocity, dtype=wp.vec3, device=d),
            wp.zeros(1, dtype=wp.float64, device=d),
            origin=self.origin,
        )

    def to_world(self, x) -> np.ndarray:
        """Simulation-frame positions (N, 3) as world positions (float64, m)."""
        return np.asarray(x, dtype=np.float64) + self.origin

    @property
    def total_mass(self) -> float:
        return float(self.masses.sum())

    def has_term(self, cls) -> bool:
        return any(isinstance(t, cls) for t in self.force_terms)

    def __repr__(self) -> str:
        return (
            f"ClothModel({self.num_vertices} vertices, {self.num_triangles} triangles, "
            f"{self.num_springs} springs, {len(self.pins)} pins, bending={self.bending!r}, "
            f"device={self.device})"
        )
