"""Read the animation of a USD stage into triangle soups, one per drawable prim, for the viewer
page and the renderer.

Everything is read through USD composition (`pxr.Usd.Stage.Open`, ``attribute.Get(time)``,
`UsdGeom.XformCache`), never by parsing a layer's layout, so stages made of several layers (sublayers,
references, value clips) read the same as one file.

Drawn prims: `UsdGeom.Mesh` (polygons fan-triangulated; time-sampled ``points`` make it a
*deforming* part), `UsdGeom.Sphere`, `UsdGeom.Cube` (tessellated in their local frame) and
`UsdGeom.Plane` where the USD version has it. Other gprims (cylinders, cones, capsules, curves,
points) are listed in `Playback.skipped`, never dropped silently; invisible prims and prims
whose purpose is ``guide`` or ``proxy`` are not drawn.

Frames are the union of the time samples of every drawn prim's ``points`` and of the transforms
above it (a stage with none has one frame, at the default time). A part is either

- deforming: world-space points per frame, ``points[F, N, 3]``; or
- rigid: fixed local points ``points[N, 3]`` and a local-to-world matrix per frame
  ``matrices[F, 4, 4]`` (column-vector convention: ``world = M @ [p, 1]``).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Part", "Playback", "read_playback", "NoMeshError"]


class NoMeshError(ValueError):
    """The stage has nothing the viewer or renderer can draw."""


@dataclass
class Part:
    """One drawable prim as triangles."""

    path: str
    color: tuple
    triangles: np.ndarray            # (T, 3) int32
    points: np.ndarray               # (F, N, 3) world (deforming) or (N, 3) local (rigid)
    matrices: np.ndarray | None = None   # (F, 4, 4) float64 local-to-world, rigid parts only
    kind: str = "Mesh"               # the USD type name

    @property
    def deforming(self) -> bool:
        return self.points.ndim == 3

    @property
    def num_vertices(self) -> int:
        return self.points.shape[-2]

    @property
    def moving(self) -> bool:
        """A rigid part whose matrix changes over the frames (or a deforming part)."""
        if self.deforming:
            return True
        return bool(np.any(np.abs(self.matrices - self.matrices[:1]) > 0))

    def world_points(self, frame: int) -> np.ndarray:
        """(N, 3) float32 world-space points at frame index ``frame``."""
        if self.deforming:
            return self.points[frame]
        m = self.matrices[frame]
        return (self.points.astype(np.float64) @ m[:3, :3].T + m[:3, 3]).astype(np.float32)

    def bounds(self, frames=None) -> np.ndarray:
        """(2, 3) world bounds over every frame, or over the frame indices ``frames``."""
        sel = slice(None) if frames is None else list(frames)
        if self.deforming:
            flat = self.points[sel].reshape(-1, 3)
            return np.stack([flat.min(axis=0), flat.max(axis=0)]).astype(np.float64)
        lo, hi = self.points.min(axis=0), self.points.max(axis=0)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])], dtype=np.float64)
        m = self.matrices[sel]
        w = np.einsum("fij,cj->fci", m[:, :3, :3], corners) + m[:, None, :3, 3]
        w = w.reshape(-1, 3)
        return np.stack([w.min(axis=0), w.max(axis=0)])

    def is_backdrop(self) -> bool:
        """A static flat part (a ground plane): left out of automatic camera framing."""
        if self.moving:
            return False
        b = self.bounds()
        ext = b[1] - b[0]
        return bool(ext.min() <= 1e-6 * max(ext.max(), 1e-12))


@dataclass
class Playback:
    """The drawable animation of a stage."""

    source: str
    times: np.ndarray                 # (F,) time codes
    time_codes_per_second: float
    up_axis: str                      # "Y" or "Z"
    parts: list = field(default_factory=list)
    skipped: list = field(default_factory=list)   # (path, type name) not drawn

    @property
    def num_frames(self) -> int:
        return len(self.times)

    @property
    def fps(self) -> float:
        return self.time_codes_per_second

    def bounds(self, include_backdrop: bool = False, frames=None) -> np.ndarray:
        """(2, 3) world bounds over all frames (or the frame indices ``frames``): of every part,
        or (default) every part but the static flat ones (floors), unless those are all there
        is."""
        parts = [p for p in self.parts if include_backdrop or not p.is_backdrop()] or self.parts
        b = np.stack([p.bounds(frames) for p in parts])
        return np.stack([b[:, 0].min(axis=0), b[:, 1].max(axis=0)])

    def frame_index(self, frames) -> list:
        """Indices for a Python slice or a list of indices into `times`, checked."""
        if isinstance(frames, slice):
            return list(range(self.num_frames))[frames]
        out = []
        for f in frames:
            f = int(f)
            if not -self.num_frames <= f < self.num_frames:
                raise ValueError(f"frame {f} out of range: the stage has {self.num_frames} frames")
            out.append(f % self.num_frames)
        return out


def _triangulate(counts, indices, path, left_handed=False):
    from ..usd import fan_triangulate

    tris = fan_triangulate(counts, indices, path)
    if left_handed:
        tris = tris[:, ::-1]
    return np.ascontiguousarray(tris, dtype=np.int32)


def uv_sphere(radius: float, segments: int = 32, rings: int = 16):
    """Points and triangles of a UV sphere about the origin (poles on the local y axis)."""
    pts = [(0.0, radius, 0.0)]
    for i in range(1, rings):
        th = math.pi * i / rings
        for j in range(segments):
            ph = 2 * math.pi * j / segments
            pts.append((radius * math.sin(th) * math.cos(ph), radius * math.cos(th),
                        radius * math.sin(th) * math.sin(ph)))
    pts.append((0.0, -radius, 0.0))
    tris = []
    for j in range(segments):
        tris.append((0, 1 + (j + 1) % segments, 1 + j))
    for i in range(rings - 2):
        a, b = 1 + i * segments, 1 + (i + 1) * segments
        for j in range(segments):
            j1 = (j + 1) % segments
            tris += [(a + j, a + j1, b + j), (a + j1, b + j1, b + j)]
    last, base = len(pts) - 1, 1 + (rings - 2) * segments
    for j in range(segments):
        tris.append((last, base + j, base + (j + 1) % segments))
    return np.asarray(pts, np.float32), np.asarray(tris, np.int32)


def box(half):
    """Points and triangles of an axis-aligned box of half extents ``half`` (outward faces; four
    vertices per face, so smooth vertex normals stay flat on each face)."""
    h = np.asarray(half, np.float32)
    pts, tris = [], []
    for axis in range(3):
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        for sign in (-1.0, 1.0):
            base = len(pts)
            for s1, s2 in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = [0.0, 0.0, 0.0]
                p[axis], p[a1], p[a2] = sign, s1, s2
                pts.append(p)
            # (a1, a2, axis) is right-handed: counter-clockwise seen from +axis
            q = [(0, 1, 2), (0, 2, 3)] if sign > 0 else [(0, 2, 1), (0, 3, 2)]
            tris += [(base + i, base + j, base + k) for i, j, k in q]
    return np.asarray(pts, np.float32) * h, np.asarray(tris, np.int32)


def _color(gprim, default=(0.7, 0.7, 0.7)):
    try:
        c = gprim.GetDisplayColorAttr().Get()
    except Exception:  # noqa: BLE001 - any unreadable colour falls back to the default
        c = None
    if c is not None and len(c) > 0:
        return tuple(float(v) for v in c[0])
    return default


def read_playback(path, prim_paths=None) -> Playback:
    """Read every drawable prim of the USD stage at ``path`` over all its time samples.

    Args:
        path: a ``.usd``, ``.usda`` or ``.usdc`` file.
        prim_paths: draw only these prims (and what is under them); default: the whole stage.

    Raises:
        FileNotFoundError: no such file.
        ValueError: USD cannot open it; `NoMeshError` when it has nothing drawable.
    """
    from pxr import Usd, UsdGeom

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no such file: {path}")
    try:
        stage = Usd.Stage.Open(path)
    except Exception as e:  # noqa: BLE001 - pxr raises Tf errors of its own types
        quoted = re.findall(r"'([^']+)'", str(e))
        detail = quoted[-1] if quoted else str(e).strip().splitlines()[-1]
        raise ValueError(f"USD cannot open {path}: {detail}") from None
    if stage is None:
        raise ValueError(f"USD cannot open {path}")
    tcps = float(stage.GetTimeCodesPerSecond() or 24.0)
    up = "Z" if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z else "Y"
    roots = [stage.GetPseudoRoot()] if not prim_paths else []
    for pp in prim_paths or []:
        prim = stage.GetPrimAtPath(pp)
        if not prim.IsValid():
            raise ValueError(f"{path}: no prim at {pp}")
        roots.append(prim)

    plane_type = getattr(UsdGeom, "Plane", None)
    found, skipped = [], []
    for root in roots:
        for prim in Usd.PrimRange(root):
            if not prim.IsA(UsdGeom.Gprim):
                continue
            img = UsdGeom.Imageable(prim)
            if img.ComputeVisibility() == UsdGeom.Tokens.invisible or \
                    img.ComputePurpose() in (UsdGeom.Tokens.guide, UsdGeom.Tokens.proxy):
                continue
            if prim.IsA(UsdGeom.Mesh) or prim.IsA(UsdGeom.Sphere) or prim.IsA(UsdGeom.Cube) or \
                    (plane_type is not None and prim.IsA(plane_type)):
                found.append(prim)
            else:
                skipped.append((str(prim.GetPath()), str(prim.GetTypeName())))

    # frames: union of the time samples of the drawn prims' points and of the transforms above
    samples = set()
    for prim in found:
        if prim.IsA(UsdGeom.Mesh):
            samples.update(UsdGeom.Mesh(prim).GetPointsAttr().GetTimeSamples())
        p = prim
        while p and p.IsValid() and not p.IsPseudoRoot():
            if p.IsA(UsdGeom.Xformable):
                samples.update(UsdGeom.Xformable(p).GetTimeSamples())
            p = p.GetParent()
    times = np.array(sorted(samples), dtype=np.float64)
    tcs = [Usd.TimeCode(t) for t in times] if len(times) else [Usd.TimeCode.Default()]
    nf = len(tcs)

    parts = []
    for prim in found:
        ppath = str(prim.GetPath())
        gprim = UsdGeom.Gprim(prim)
        if prim.IsA(UsdGeom.Mesh):
            mesh = UsdGeom.Mesh(prim)
            counts = mesh.GetFaceVertexCountsAttr().Get()
            idx = mesh.GetFaceVertexIndicesAttr().Get()
            if counts is None or idx is None or len(counts) == 0:
                skipped.append((ppath, "Mesh without faces"))
                continue
            left = mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded
            tris = _triangulate(counts, idx, ppath, left)
            attr = mesh.GetPointsAttr()
            deforming = attr.GetNumTimeSamples() > 1
            if deforming:
                pts = [np.asarray(attr.Get(tc), dtype=np.float32) for tc in tcs]
                n = {len(p) for p in pts}
                if len(n) != 1:
                    raise ValueError(f"{ppath}: the number of points changes over time "
                                     f"({sorted(n)}); the viewer needs fixed topology")
                pts = np.stack(pts)
            else:
                pts = np.asarray(attr.Get(tcs[0]) if attr.GetNumTimeSamples() else attr.Get(),
                                 dtype=np.float32)
                if pts.ndim != 2 or len(pts) == 0:
                    skipped.append((ppath, "Mesh without points"))
                    continue
            nv = pts.shape[-2]
            if tris.size and (tris.min() < 0 or tris.max() >= nv):
                raise ValueError(f"{ppath}: face vertex index {int(tris.max())} out of range for "
                                 f"{nv} points")
            local, kind = pts, "Mesh"
        elif prim.IsA(UsdGeom.Sphere):
            local, tris = uv_sphere(float(UsdGeom.Sphere(prim).GetRadiusAttr().Get()))
            deforming, kind = False, "Sphere"
        elif prim.IsA(UsdGeom.Cube):
            s = 0.5 * float(UsdGeom.Cube(prim).GetSizeAttr().Get())
            local, tris = box((s, s, s))
            deforming, kind = False, "Cube"
        else:  # UsdGeom.Plane
            pl = plane_type(prim)
            w, ln = 0.5 * pl.GetWidthAttr().Get(), 0.5 * pl.GetLengthAttr().Get()
            axis = pl.GetAxisAttr().Get()
            q = {"X": [(0, -w, -ln), (0, w, -ln), (0, w, ln), (0, -w, ln)],
                 "Y": [(-w, 0, -ln), (w, 0, -ln), (w, 0, ln), (-w, 0, ln)],
                 "Z": [(-w, -ln, 0), (w, -ln, 0), (w, ln, 0), (-w, ln, 0)]}[axis]
            local, tris = np.asarray(q, np.float32), np.array([[0, 1, 2], [0, 2, 3]], np.int32)
            deforming, kind = False, "Plane"
        if len(tris) == 0:
            skipped.append((ppath, f"{kind} without triangles"))
            continue
        # world transforms per frame (USD matrices are row-vector: transpose to column-vector)
        mats = np.empty((nf, 4, 4), dtype=np.float64)
        cache = UsdGeom.XformCache()
        for f, tc in enumerate(tcs):
            cache.SetTime(tc)
            mats[f] = np.asarray(cache.GetLocalToWorldTransform(prim), dtype=np.float64).T
        color = _color(gprim, (0.8, 0.35, 0.3) if deforming else (0.7, 0.7, 0.7))
        if deforming:
            w = np.einsum("fij,fnj->fni", mats[:, :3, :3], local.astype(np.float64)) \
                + mats[:, None, :3, 3]
            parts.append(Part(ppath, color, tris, w.astype(np.float32), None, kind))
        else:
            parts.append(Part(ppath, color, tris, np.ascontiguousarray(local, np.float32), mats,
                              kind))
        p = parts[-1]
        if not np.all(np.isfinite(p.points)) or not np.all(np.isfinite(mats)):
            raise ValueError(f"{ppath}: non-finite points or transform")
    if not parts:
        extra = f" (not drawn: {', '.join(f'{p} ({t})' for p, t in skipped)})" if skipped else ""
        raise NoMeshError(f"{path}: no mesh, sphere, cube or plane to draw{extra}")
    return Playback(path, times if len(times) else np.zeros(1), tcps, up, parts, skipped)
