"""USD output: one stage with the animated cloth and its obstacles, readable at any moment.

The stage has ``upAxis``, ``metersPerUnit``, ``timeCodesPerSecond = framesPerSecond = fps`` and
start/end time codes. Each cloth is a `UsdGeom.Mesh` whose face counts and indices are written
once and whose ``points`` and ``extent`` are time-sampled, one sample per frame (time code =
frame index). Obstacles write their own prims (see `warp_cloth.collision`).

Saving: the writer saves the layer every ``save_interval`` seconds of wall time and on `close`
(which the scene runner calls from a ``finally`` block), so a run interrupted by Ctrl-C or an
exception leaves a readable file holding exactly the frames done so far, with the end time code
set to the last of them. A frame with a non-finite coordinate is refused with `ValueError`: no NaN
is ever written.
"""

from __future__ import annotations

import os
import time as _time

import numpy as np

__all__ = ["UsdWriter", "read_points"]


class UsdWriter:
    """Writes time-sampled meshes to a USD stage.

    Args:
        path: output file (``.usd``, ``.usda`` or ``.usdc``).
        fps: frames per second (= time codes per second).
        up_axis: ``"Y"`` or ``"Z"``.
        meters_per_unit: stage unit (1.0: the simulator works in metres).
        save_interval: seconds of wall time between saves while writing frames.
    """

    def __init__(self, path, fps: float = 60.0, up_axis: str = "Y", meters_per_unit: float = 1.0,
                 save_interval: float = 2.0):
        from pxr import Sdf, Usd, UsdGeom

        if not (fps > 0 and np.isfinite(fps)):
            raise ValueError(f"fps must be positive, got {fps}")
        if up_axis not in ("Y", "Z"):
            raise ValueError(f"up_axis must be 'Y' or 'Z', got {up_axis!r}")
        path = os.fspath(path)
        if os.path.splitext(path)[1].lower() not in (".usd", ".usda", ".usdc"):
            raise ValueError(f"output file must end in .usd, .usda or .usdc: {path}")
        parent = os.path.dirname(os.path.abspath(path))
        if not os.path.isdir(parent):
            raise ValueError(f"output directory does not exist: {parent}")
        self.path = path
        self.fps = float(fps)
        self.save_interval = float(save_interval)
        layer = Sdf.Layer.FindOrOpen(path)
        if layer is not None:
            layer.Clear()
            self.stage = Usd.Stage.Open(layer)
        else:
            self.stage = Usd.Stage.CreateNew(path)
        st = self.stage
        UsdGeom.SetStageUpAxis(st, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(st, meters_per_unit)
        st.SetTimeCodesPerSecond(self.fps)
        st.SetFramesPerSecond(self.fps)
        st.SetStartTimeCode(0)
        st.SetEndTimeCode(0)
        root = UsdGeom.Xform.Define(st, "/World")
        st.SetDefaultPrim(root.GetPrim())
        self._meshes = {}
        self._obstacles = []
        self.frames_written = 0
        self._last_save = _time.perf_counter()
        self._closed = False

    @staticmethod
    def _prim_name(name: str) -> str:
        out = "".join(c if (c.isalnum() or c == "_") else "_" for c in name) or "mesh"
        return out if not out[0].isdigit() else "_" + out

    def add_mesh(self, name: str, triangles, points=None, color=(0.8, 0.35, 0.3)):
        """Add a `UsdGeom.Mesh` under ``/World`` with fixed topology; returns its prim path."""
        from pxr import UsdGeom, Vt, Gf

        path = f"/World/{self._prim_name(name)}"
        if path in self._meshes:
            raise ValueError(f"a mesh named {name!r} is already in the stage")
        mesh = UsdGeom.Mesh.Define(self.stage, path)
        tris = np.asarray(triangles, dtype=np.int32)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(tris), 3, dtype=np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(tris.reshape(-1)))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateDoubleSidedAttr(True)
        mesh.CreateDisplayColorAttr([Gf.Vec3f(*color)])
        mesh.CreatePointsAttr()
        mesh.CreateExtentAttr()
        self._meshes[path] = mesh
        if points is not None:
            self._set_points(mesh, points, None)
        return path

    def add_obstacle(self, obstacle):
        """Let an obstacle define its prims (``obstacle.usd_define(stage, parent_path)``)."""
        obstacle.usd_define(self.stage, "/World")
        self._obstacles.append(obstacle)

    def _set_points(self, mesh, points, time):
        from pxr import Vt, Usd

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

        Obstacles record their pose at ``sim_time`` (default ``frame / fps``).
        """
        if self._closed:
            raise RuntimeError("UsdWriter is closed")
        for path, p in points.items():
            if path not in self._meshes:
                raise KeyError(f"unknown mesh {path}; add it with add_mesh first")
            self._set_points(self._meshes[path], p, frame)
        t = frame / self.fps if sim_time is None else sim_time
        for ob in self._obstacles:
            ob.usd_write(self.stage, frame, t)
        self.frames_written = max(self.frames_written, frame + 1)
        self.stage.SetEndTimeCode(frame)
        if _time.perf_counter() - self._last_save > self.save_interval:
            self.save()

    def save(self):
        self.stage.GetRootLayer().Save()
        self._last_save = _time.perf_counter()

    def close(self):
        if not self._closed:
            self.save()
            self._closed = True

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
