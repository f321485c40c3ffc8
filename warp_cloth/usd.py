"""USD output: one stage with the animated cloth and its obstacles, readable at every moment.

The stage has ``upAxis`` (the model's), ``metersPerUnit = 1``, ``timeCodesPerSecond =
framesPerSecond = fps`` and start/end time codes. Each cloth is a `UsdGeom.Mesh` whose face counts
and indices are written once and whose ``points`` and ``extent`` are time-sampled, one sample per
frame (time code = frame index). Obstacles write their own prims (see `warp_cloth.collision`).

Layout on disk (``OUT`` is the path given, e.g. ``hanging.usd``)::

    OUT                      the root layer: stage metadata, a sublayer and the clip list (small)
    OUT.frames/static.usdc   everything that does not move: prims, topology, obstacle shapes
    OUT.frames/NNNNNN.usdc   the time samples of frames NNNNNN ... (one file per save)

The frame files are USD *value clips* of ``/World`` (``clips`` metadata in the root layer), so
``Usd.Stage.Open(OUT)`` composes every frame and any USD reader sees one animated stage; copy or
move ``OUT`` together with ``OUT.frames/``.

Crash safety at a flat cost: every file is written to a temporary name beside it and moved into
place with ``os.replace`` (atomic), frame files first, the root last. Each save writes only the
frames since the previous save plus the root (a few hundred bytes per frame file), so its cost
does not grow with the run, and a process killed at any moment (even by SIGKILL) leaves the
previous root or the new one, each naming only complete files: a readable stage whose end time
code is its last frame. SIGINT and SIGTERM are held back while a save runs. The writer saves
every ``save_interval`` seconds of wall time and on `close` (the scene runner calls it from a
``finally`` block). An existing ``OUT`` is replaced, with a warning if it was not a readable USD
layer; a path that cannot be written raises `OutputError` (an ``OSError``) with a one-line
message. A frame with a non-finite coordinate is refused with `ValueError`: no NaN is written.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import re
import signal
import threading
import time as _time
import warnings

import numpy as np

from .errors import OutputError

__all__ = ["UsdWriter", "read_points", "read_meshes", "MeshTrack", "read_solids", "SolidTrack",
           "fan_triangulate", "OutputError", "frames_dir"]

_FRAME_FILE = re.compile(r"^(\d{6,})\.usdc$")


_ROOT_COMMENT = ("warp_cloth output: static prims in the sublayer, frames as value clips of "
                 "/World in the .frames folder")


def frames_dir(path) -> str:
    """The folder that holds a root layer's static layer and frame files."""
    return os.fspath(path) + ".frames"


@contextlib.contextmanager
def _signals_held():
    """Hold SIGINT/SIGTERM back while a save moves its files: their Python handlers are
    swapped for a recorder and the signals raised again, to the previous handlers, afterwards.

    (Blocking them with ``pthread_sigmask`` is not enough: USD's worker threads would take a
    process-directed signal and Python would run the handler in the middle of the save.)"""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending = []
    old = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            old[sig] = signal.signal(sig, lambda signum, frame: pending.append(signum))
        except (ValueError, OSError):  # not settable here
            pass
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        for sig in dict.fromkeys(pending):
            signal.raise_signal(sig)


def _one_line(e: BaseException) -> str:
    lines = [ln.strip() for ln in str(e).strip().splitlines() if ln.strip()]
    return lines[-1] if lines else type(e).__name__


def _output_error(path: str, e: BaseException | None = None) -> OutputError:
    err = getattr(e, "errno", None)
    try:
        # (a pseudo file system such as /proc reports no blocks at all: not a full disk)
        st = os.statvfs(os.path.dirname(os.path.abspath(path)) or ".")
        full = st.f_blocks > 0 and st.f_bavail == 0
    except OSError:
        full = False
    if err == errno.ENOSPC or (full and err in (None, errno.EIO, errno.EDQUOT)):
        why = "the disk is full"
    elif isinstance(e, OSError) and e.strerror:
        why = e.strerror
    else:
        why = _one_line(e) if e is not None else "write failed"
    return OutputError(f"cannot write {path}: {why}")


def _atomic_export(layer, path: str, args: dict | None = None) -> None:
    """Write ``layer`` to ``path`` through a temporary file in the same folder and a rename
    (``args``: Sdf file format arguments, e.g. ``{"format": "usda"}``)."""
    from pxr import Tf

    folder, base = os.path.split(os.path.abspath(path))
    stem, ext = os.path.splitext(base)
    tmp = os.path.join(folder, f".{stem}.{os.getpid()}.tmp{ext}")
    try:
        # probe with plain I/O first: OSError carries errno (permission, read-only, full disk)
        with open(tmp, "wb"):
            pass
        ok = layer.Export(tmp, args=args or {})
        if not ok:
            err = _output_error(path)
            _remove_quietly(tmp)
            raise err
        os.replace(tmp, path)
    except OutputError:
        _remove_quietly(tmp)
        raise
    except (OSError, Tf.ErrorException) as e:
        err = _output_error(path, e)  # before the partial file goes: a full disk is seen full
        _remove_quietly(tmp)
        raise err from None


def _atomic_write_bytes(data: bytes, path: str) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename."""
    folder, base = os.path.split(os.path.abspath(path))
    stem, ext = os.path.splitext(base)
    tmp = os.path.join(folder, f".{stem}.{os.getpid()}.tmp{ext}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except OSError as e:
        err = _output_error(path, e)
        _remove_quietly(tmp)
        raise err from None


def _remove_quietly(path: str) -> None:
    with contextlib.suppress(OSError):
        os.remove(path)


class UsdWriter:
    """Writes time-sampled meshes to a USD stage, crash-safe (see the module docstring).

    Args:
        path: output root layer (``.usd``, ``.usda`` or ``.usdc``); its frames go to
            ``path + ".frames/"``.
        fps: frames per second (= time codes per second).
        up_axis: ``"Y"`` or ``"Z"``: the frame the points are given in (the model's up axis).
        meters_per_unit: stage unit (1.0: the simulator works in metres).
        save_interval: seconds of wall time between saves while writing frames (0: every frame).

    Raises:
        ValueError: bad fps, up axis, extension, or a missing parent folder.
        OutputError: the path is a directory or cannot be written (permissions, read-only or
            full file system, ``/proc``).
    """

    def __init__(self, path, fps: float = 60.0, up_axis: str = "Y", meters_per_unit: float = 1.0,
                 save_interval: float = 2.0):
        from pxr import Sdf, Tf, Usd, UsdGeom

        if not (fps > 0 and np.isfinite(fps)):
            raise ValueError(f"fps must be positive, got {fps}")
        if up_axis not in ("Y", "Z"):
            raise ValueError(f"up_axis must be 'Y' or 'Z', got {up_axis!r}")
        if not (meters_per_unit > 0 and np.isfinite(meters_per_unit)):
            raise ValueError(f"meters_per_unit must be positive, got {meters_per_unit}")
        if not (save_interval >= 0):
            raise ValueError(f"save_interval must be >= 0 s, got {save_interval}")
        path = os.fspath(path)
        self.ext = os.path.splitext(path)[1].lower()
        if self.ext not in (".usd", ".usda", ".usdc"):
            raise ValueError(f"output file must end in .usd, .usda or .usdc: {path}")
        parent = os.path.dirname(os.path.abspath(path))
        if not os.path.isdir(parent):
            raise ValueError(f"output directory does not exist: {parent}")
        if os.path.isdir(path):
            raise OutputError(f"cannot write {path}: it is a directory")
        self.path = path
        self.frames_dir = frames_dir(path)
        self.fps = float(fps)
        self.up_axis = up_axis
        self.meters_per_unit = float(meters_per_unit)
        self.save_interval = float(save_interval)
        self.replaced_unreadable = False
        if os.path.lexists(path):
            try:
                readable = Sdf.Layer.OpenAsAnonymous(path, metadataOnly=True) is not None
            except Tf.ErrorException:
                readable = False
            if not readable:
                self.replaced_unreadable = True
                warnings.warn(f"{path} exists but is not a readable USD file; replacing it",
                              stacklevel=2)

        # the static layer (in memory until saved) and, as the stage's session layer, the
        # frames since the last save; frames are authored into the session layer
        self._static = Sdf.Layer.CreateAnonymous("static.usdc")
        self.stage = Usd.Stage.Open(self._static)
        self._session = self.stage.GetSessionLayer()
        st = self.stage
        UsdGeom.SetStageUpAxis(st, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(st, meters_per_unit)
        root = UsdGeom.Xform.Define(st, "/World")
        st.SetDefaultPrim(root.GetPrim())
        st.SetEditTarget(Usd.EditTarget(self._session))
        self._meshes = {}
        self._obstacles = []
        self._clips: list[tuple[int, str]] = []  # (first frame, file name) of saved frame files
        self._clip_fmt: list[tuple[str, str]] = []  # their text in the root, formatted once
        self._pending_first: int | None = None
        self._last_frame = -1
        self._saved_last = 0
        self._static_dirty = True
        self.frames_written = 0
        self.saves = 0
        self._closed = False
        with _signals_held():
            try:
                os.makedirs(self.frames_dir, exist_ok=True)
            except OSError as e:
                raise _output_error(self.frames_dir, e) from None
            if not os.path.isdir(self.frames_dir):
                raise OutputError(f"cannot write {self.frames_dir}: not a directory")
            # a readable empty stage replaces whatever was there, then old frame files go
            self._write_root(self._clips, 0, with_static=False)
            self._clean_frames_dir()
        self._last_save = _time.perf_counter()

    def _clean_frames_dir(self):
        """Remove the frame files and temporaries of earlier runs (the new root names none)."""
        folder, base = os.path.split(os.path.abspath(self.path))
        stem = os.path.splitext(base)[0]
        for name in os.listdir(self.frames_dir):
            if _FRAME_FILE.match(name) or name == "static.usdc" or name.startswith("."):
                _remove_quietly(os.path.join(self.frames_dir, name))
        for name in os.listdir(folder):
            if name.startswith(f".{stem}.") and ".tmp" in name:
                _remove_quietly(os.path.join(folder, name))

    def _rel(self, name: str) -> str:
        return f"./{os.path.basename(self.frames_dir)}/{name}"

    def _write_root(self, clips, end: int, with_static: bool = True):
        """Replace the root layer: stage metadata, the static sublayer and the clip list."""
        rel_dir = os.path.basename(self.frames_dir)
        if self.ext != ".usdc" and all(c not in rel_dir for c in '@"\\\n'):
            # a .usd/.usda root is text written here: its cost per clip is a few hundred
            # nanoseconds (through Sdf it is about 7 us a clip: 15 ms at 2,000 saves)
            text = self._root_text(clips, end, with_static)
            _atomic_write_bytes(text.encode("utf-8"), self.path)
            return
        from pxr import Sdf, Vt

        r = Sdf.Layer.CreateAnonymous("root" + self.ext)
        r.pseudoRoot.SetInfo("upAxis", self.up_axis)
        r.pseudoRoot.SetInfo("metersPerUnit", self.meters_per_unit)
        r.timeCodesPerSecond = self.fps
        r.framesPerSecond = self.fps
        r.startTimeCode = 0
        r.endTimeCode = end
        r.defaultPrim = "World"
        r.comment = _ROOT_COMMENT
        if with_static:
            r.subLayerPaths.append(self._rel("static.usdc"))
        world = Sdf.CreatePrimInLayer(r, "/World")
        world.specifier = Sdf.SpecifierOver if with_static else Sdf.SpecifierDef
        if clips:
            world.SetInfo("clips", {"default": {
                "assetPaths": Sdf.AssetPathArray([Sdf.AssetPath(self._rel(n)) for _, n in clips]),
                "primPath": "/World",
                "active": Vt.Vec2dArray([(float(f), float(i)) for i, (f, _) in enumerate(clips)]),
            }})
        _atomic_export(r, self.path)

    def _root_text(self, clips, end: int, with_static: bool) -> str:
        head = [
            "#usda 1.0", "(", f'    "{_ROOT_COMMENT}"', '    defaultPrim = "World"',
            f"    endTimeCode = {int(end)}", f"    framesPerSecond = {self.fps!r}",
            f"    metersPerUnit = {self.meters_per_unit!r}", "    startTimeCode = 0",
        ]
        if with_static:
            head += ["    subLayers = [", f"        @{self._rel('static.usdc')}@", "    ]"]
        head += [f"    timeCodesPerSecond = {self.fps!r}", f'    upAxis = "{self.up_axis}"', ")", ""]
        if not clips:
            return "\n".join(head + [f'{"over" if with_static else "def"} "World"', "{", "}", ""])
        # clips only grow (or a failed save retries the same last one): format each once
        fmt = self._clip_fmt
        del fmt[len(clips) - 1:]
        rel = self._rel("")
        fmt += [(f"({f}, {i})", f"@{rel}{n}@") for i, (f, n) in enumerate(clips[len(fmt):], len(fmt))]
        active = ", ".join(a for a, _ in fmt)
        assets = ", ".join(b for _, b in fmt)
        return "\n".join(head + [
            'over "World" (', "    clips = {", "        dictionary default = {",
            f"            double2[] active = [{active}]",
            f"            asset[] assetPaths = [{assets}]",
            '            string primPath = "/World"', "        }", "    }", ")", "{", "}", ""])

    @staticmethod
    def _prim_name(name: str) -> str:
        out = "".join(c if (c.isalnum() or c == "_") else "_" for c in name) or "mesh"
        return out if not out[0].isdigit() else "_" + out

    def add_mesh(self, name: str, triangles, points=None, color=(0.8, 0.35, 0.3)):
        """Add a `UsdGeom.Mesh` under ``/World`` with fixed topology; returns its prim path.

        ``points`` (optional) become the mesh's default (unanimated) points."""
        from pxr import Gf, Usd, UsdGeom, Vt

        path = f"/World/{self._prim_name(name)}"
        if path in self._meshes:
            raise ValueError(f"a mesh named {name!r} is already in the stage")
        with Usd.EditContext(self.stage, self._static):
            mesh = UsdGeom.Mesh.Define(self.stage, path)
            tris = np.asarray(triangles, dtype=np.int32)
            mesh.CreateFaceVertexCountsAttr(
                Vt.IntArray.FromNumpy(np.full(len(tris), 3, dtype=np.int32)))
            mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(tris.reshape(-1)))
            mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            mesh.CreateDoubleSidedAttr(True)
            mesh.CreateDisplayColorAttr([Gf.Vec3f(*color)])
            mesh.CreatePointsAttr()
            mesh.CreateExtentAttr()
            if points is not None:
                self._set_points(mesh, points, None)
        self._meshes[path] = mesh
        self._static_dirty = True
        return path

    def add_obstacle(self, obstacle):
        """Let an obstacle define its prims (``obstacle.usd_define(stage, parent_path)``)."""
        from pxr import Usd

        with Usd.EditContext(self.stage, self._static):
            obstacle.usd_define(self.stage, "/World")
        self._obstacles.append(obstacle)
        self._static_dirty = True

    def _set_points(self, mesh, points, time):
        from pxr import Usd, Vt

        p = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        if not np.all(np.isfinite(p)):
            bad = int(np.argwhere(~np.isfinite(p))[0, 0])
            raise ValueError(f"refusing to write non-finite point {bad} of {mesh.GetPath()}")
        tc = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(p), tc)
        ext = np.stack([p.min(axis=0), p.max(axis=0)])
        mesh.GetExtentAttr().Set(Vt.Vec3fArray.FromNumpy(ext), tc)

    def write_frame(self, frame: int, points: dict, sim_time: float | None = None):
        """Write one frame: ``points`` maps mesh prim paths (from `add_mesh`) to (N, 3) arrays.

        Frames must come in increasing order. Obstacles record their pose at ``sim_time``
        (default ``frame / fps``).
        """
        if self._closed:
            raise RuntimeError("UsdWriter is closed")
        frame = int(frame)
        if frame <= self._last_frame:
            raise ValueError(f"frame {frame} written after frame {self._last_frame}: frames must "
                             "increase")
        for path, p in points.items():
            if path not in self._meshes:
                raise KeyError(f"unknown mesh {path}; add it with add_mesh first")
            self._set_points(self._meshes[path], p, frame)
        t = frame / self.fps if sim_time is None else sim_time
        for ob in self._obstacles:
            ob.usd_write(self.stage, frame, t)
        if self._pending_first is None:
            self._pending_first = frame
        self._last_frame = frame
        self.frames_written = max(self.frames_written, frame + 1)
        if _time.perf_counter() - self._last_save >= self.save_interval:
            self.save()

    def save(self):
        """Write the static layer (when changed), the frames since the last save, and the root.

        Each file is replaced atomically, the root last; SIGINT/SIGTERM wait until it is done.
        Raises `OutputError` when a file cannot be written (the previous root stays valid).
        """
        with _signals_held():
            if self._static_dirty:
                _atomic_export(self._static, os.path.join(self.frames_dir, "static.usdc"))
                self._static_dirty = False
            clips = self._clips
            if self._pending_first is not None:
                name = f"{self._pending_first:06d}.usdc"
                _atomic_export(self._session, os.path.join(self.frames_dir, name))
                clips = clips + [(self._pending_first, name)]
            end = max(self._last_frame, 0)
            self._write_root(clips, end)
            # committed: the root on disk names these files
            self._clips = clips
            if self._pending_first is not None:
                self._session.Clear()
                self._pending_first = None
            self._saved_last = end
            self.saves += 1
        self._last_save = _time.perf_counter()

    def close(self):
        """Save what is left; the writer takes no more frames."""
        if not self._closed:
            self._closed = True
            self.save()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def read_points(path, prim_path: str | None = None):
    """Read back a stage: returns ``(times, points[F, N, 3], stage)`` of a mesh (the first
    time-sampled `UsdGeom.Mesh`, or the one at ``prim_path``)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(os.fspath(path))
    if prim_path is None:
        prim = next(
            p for p in stage.Traverse()
            if p.IsA(UsdGeom.Mesh) and UsdGeom.Mesh(p).GetPointsAttr().GetNumTimeSamples() > 0
        )
    else:
        prim = stage.GetPrimAtPath(prim_path)
    attr = UsdGeom.Mesh(prim).GetPointsAttr()
    times = attr.GetTimeSamples()
    pts = np.stack([np.asarray(attr.Get(t)) for t in times]) if times else np.zeros((0, 0, 3))
    return np.asarray(times), pts, stage


class MeshTrack:
    """One `UsdGeom.Mesh` of a stage as `read_meshes` returns it: ``path`` (the prim path),
    ``triangles`` (T, 3: its faces fan-triangulated, faces of fewer than 3 corners and
    triangles that repeat a corner left out), ``points`` (F, N, 3 float64: world positions
    at each of the stage's times, the prim's and its ancestors' transforms applied) and
    ``deforming`` (its points are time-sampled: a cloth; else a rigid shape, moved by
    transforms at most)."""

    def __init__(self, path: str, triangles: np.ndarray, points: np.ndarray,
                 deforming: bool = True):
        self.path = path
        self.triangles = triangles
        self.points = points
        self.deforming = bool(deforming)

    def __repr__(self):
        return (f"MeshTrack({self.path!r}, {len(self.triangles)} triangles, "
                f"{self.points.shape[1]} points, {self.points.shape[0]} times)")


class SolidTrack:
    """One `UsdGeom.Sphere` or `UsdGeom.Cube` of a stage as `read_solids` returns it: ``path``,
    ``kind`` (``"sphere"`` or ``"cube"``), ``size`` (F: the radius, or half the cube's edge, in
    its own frame) and ``matrices`` (F, 4, 4: local to world, USD's row-vector convention) at
    each of the times asked."""

    def __init__(self, path: str, kind: str, size: np.ndarray, matrices: np.ndarray):
        self.path, self.kind, self.size, self.matrices = path, kind, size, matrices

    def __repr__(self):
        return f"SolidTrack({self.path!r}, {self.kind}, {len(self.size)} times)"


def read_solids(path, times) -> list:
    """Every `UsdGeom.Sphere` and `UsdGeom.Cube` of the stage at ``path`` (the implicit solids our
    writer gives spheres and boxes; instance proxies included), sampled at ``times`` (those of
    `read_meshes`; a NaN: the default time). Returns a list of `SolidTrack` (empty when there are
    none). Raises `ValueError` naming the prim for a radius or size that is not a positive
    finite number."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(os.fspath(path))
    if stage is None:
        raise ValueError(f"{path}: not a USD stage")
    codes = [Usd.TimeCode.Default() if t != t else Usd.TimeCode(float(t)) for t in times]
    out = []
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        if prim.IsA(UsdGeom.Sphere):
            kind, attr, half = "sphere", UsdGeom.Sphere(prim).GetRadiusAttr(), 1.0
        elif prim.IsA(UsdGeom.Cube):
            kind, attr, half = "cube", UsdGeom.Cube(prim).GetSizeAttr(), 0.5
        else:
            continue
        xf = UsdGeom.Xformable(prim)
        size, mats = [], []
        for tc in codes:
            v = attr.Get(tc)
            v = float(v) * half if v is not None else float("nan")
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{path}: {prim.GetPath()} has a {kind} size of {v / half!r} at "
                                 f"time {tc.GetValue():g}: not a positive number")
            size.append(v)
            mats.append(np.asarray(xf.ComputeLocalToWorldTransform(tc), dtype=np.float64))
        out.append(SolidTrack(str(prim.GetPath()), kind, np.asarray(size), np.stack(mats)))
    return out


def fan_triangulate(counts, indices, where: str) -> np.ndarray:
    """A USD mesh's faces (``faceVertexCounts``, ``faceVertexIndices``) as triangles (T, 3
    int64): polygons fanned from their first corner ``(v0, vk, vk+1)``, faces of fewer than 3
    corners dropped. Raises `ValueError` naming ``where`` when the counts do not add up to the
    indices. Shared by `read_meshes` and the viewer (`viewer.playback`)."""
    counts = np.asarray(counts, dtype=np.int64).reshape(-1)
    indices = np.asarray(indices, dtype=np.int64).reshape(-1)
    if np.any(counts < 0) or counts.sum() != len(indices):
        raise ValueError(f"{where}: faceVertexCounts sum to {int(counts.sum())} but there are "
                         f"{len(indices)} faceVertexIndices")
    if len(counts) and np.all(counts == 3):
        return indices.reshape(-1, 3)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    parts = []
    for k in range(1, int(counts.max(initial=0)) - 1):
        sel = counts >= k + 2
        s0 = starts[sel]
        parts.append(np.stack([indices[s0], indices[s0 + k], indices[s0 + k + 1]], axis=1))
    return np.concatenate(parts) if parts else np.zeros((0, 3), np.int64)


def read_meshes(path, prim_paths=None):
    """Every `UsdGeom.Mesh` of the stage at ``path`` (or those at ``prim_paths``) in world
    space, sampled at the stage's times: returns ``(times, [MeshTrack, ...])``.

    The times are the union of the time samples of the meshes' ``points`` and of their and
    their ancestors' transforms (value clips included); a stage with none is read once, at its
    default time (``times`` is then ``[nan]``). Instanced meshes are read through their
    instance proxies. Raises `ValueError` naming the prim for a stage without meshes, a path
    that is not a mesh, a topology that changes over time, a point count that does, or face
    indices outside the points."""
    from pxr import Usd, UsdGeom

    path = os.fspath(path)
    stage = Usd.Stage.Open(path)
    if stage is None:
        raise ValueError(f"{path}: not a USD stage")
    if prim_paths:
        prims = []
        for pp in prim_paths:
            prim = stage.GetPrimAtPath(pp)
            if not prim.IsValid():
                raise ValueError(f"{path}: no prim at {pp}")
            if not prim.IsA(UsdGeom.Mesh):
                raise ValueError(f"{path}: {pp} is a {prim.GetTypeName() or 'typeless prim'}, "
                                 "not a Mesh")
            prims.append(prim)
    else:
        prims = [p for p in stage.Traverse(Usd.TraverseInstanceProxies())
                 if p.IsA(UsdGeom.Mesh)]
    if not prims:
        raise ValueError(f"{path}: the stage has no Mesh prim")
    samples = set()
    for prim in prims:
        samples.update(UsdGeom.Mesh(prim).GetPointsAttr().GetTimeSamples())
        p = prim
        while p.IsValid() and not p.IsPseudoRoot():
            if p.IsA(UsdGeom.Xformable):
                samples.update(UsdGeom.Xformable(p).GetTimeSamples())
            p = p.GetParent()
    times = sorted(samples)
    codes = [Usd.TimeCode(t) for t in times] or [Usd.TimeCode.Default()]
    tracks = []
    for prim in prims:
        mesh = UsdGeom.Mesh(prim)
        where = f"{path}: {prim.GetPath()}"
        cattr, iattr = mesh.GetFaceVertexCountsAttr(), mesh.GetFaceVertexIndicesAttr()
        topo_times = sorted(set(cattr.GetTimeSamples()) | set(iattr.GetTimeSamples()))
        first = Usd.TimeCode(topo_times[0]) if topo_times else Usd.TimeCode.Default()
        counts, indices = cattr.Get(first), iattr.Get(first)
        for t in topo_times[1:]:
            if (list(cattr.Get(t) or []) != list(counts or [])
                    or list(iattr.Get(t) or []) != list(indices or [])):
                raise ValueError(f"{where}: its faces change at time {t:g} (a fixed topology "
                                 "is checked)")
        pts = []
        n = None
        for tc in codes:
            x = mesh.GetPointsAttr().Get(tc)
            x = np.zeros((0, 3)) if x is None else np.asarray(x, dtype=np.float64).reshape(-1, 3)
            if n is None:
                n = len(x)
            elif len(x) != n:
                raise ValueError(f"{where}: {len(x)} points at time {tc.GetValue():g}, {n} at "
                                 "the first (a fixed topology is checked)")
            m = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(tc),
                           dtype=np.float64)
            pts.append(x @ m[:3, :3] + m[3, :3])  # USD's row vectors: p' = p M
        idx = np.asarray(indices if indices is not None else [], dtype=np.int64).reshape(-1)
        bad = np.flatnonzero((idx < 0) | (idx >= n))
        if len(bad):
            raise ValueError(f"{where}: faceVertexIndices[{int(bad[0])}] = {int(idx[bad[0]])} "
                             f"is outside its {n} points")
        tri = fan_triangulate(counts if counts is not None else [], idx, where)
        # a triangle that repeats a corner (a degenerate polygon's fan) is crossed by nothing
        tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])]
        tracks.append(MeshTrack(str(prim.GetPath()), tri, np.stack(pts),
                                mesh.GetPointsAttr().GetNumTimeSamples() > 0))
    return np.asarray(times if times else [float("nan")], dtype=np.float64), tracks
