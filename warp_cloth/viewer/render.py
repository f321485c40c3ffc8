"""Preview images without a GPU or a display: ray casting with Warp kernels.

`Renderer` takes a `Playback` (see `playback.py`) and draws any frame into an RGB image. Each part
(the cloth, each obstacle) is a `wp.Mesh` (a BVH) in its own local frame; a rigid part's BVH is
built once and its per-frame pose moves the rays into its frame, a deforming part's points are
updated and the BVH refitted each frame. One thread per pixel casts ``supersample**2`` primary
rays, keeps the nearest hit over all parts, and shades it:

- smooth normals (per-vertex area-weighted normals, gathered per vertex over its triangles in a
  fixed order, so a render is the same bytes on every device), turned to face the camera: both
  sides of the cloth are lit, the back side a little lighter in tone so folds read;
- Lambert from one directional light (above and behind the camera) plus a sky/ground ambient term,
  a soft headlight fill, and an optional shadow ray toward the light (``shadows=True``);
- a vertical background gradient; sRGB-like gamma.

All arrays live on the renderer's device; nothing assumes ``"cpu"``. Writes PNG and GIF with
Pillow (`save_png`, `save_gif`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from .playback import Playback

__all__ = ["Camera", "Renderer", "save_png", "save_gif", "parse_frames", "parse_size",
           "parse_camera"]


@dataclass
class Camera:
    """A pinhole camera: ``eye`` looking at ``target``, ``up`` roughly up, vertical field of view
    ``fov`` in degrees."""

    eye: tuple
    target: tuple
    up: tuple = (0.0, 1.0, 0.0)
    fov: float = 40.0

    def basis(self):
        """(forward, right, up) unit vectors; a view straight along ``up`` picks another up."""
        eye, target = np.asarray(self.eye, float), np.asarray(self.target, float)
        f = target - eye
        n = np.linalg.norm(f)
        if not n > 0:
            raise ValueError("camera eye and target coincide")
        f /= n
        up = np.asarray(self.up, float)
        r = np.cross(f, up)
        if np.linalg.norm(r) < 1e-6 * max(np.linalg.norm(up), 1e-30):
            alt = np.array([0.0, 0.0, -1.0]) if abs(f[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
            r = np.cross(f, alt)
        r /= np.linalg.norm(r)
        u = np.cross(r, f)
        return f, r, u

    @staticmethod
    def framing(bounds, up_axis: str = "Y", azimuth: float = 30.0, elevation: float = 25.0,
                distance: float | None = None, fov: float = 40.0, aspect: float = 4 / 3,
                margin: float = 0.92) -> "Camera":
        """A camera at ``azimuth``/``elevation`` (degrees; azimuth 0 looks from the front, +Z for
        Y-up stages and -Y for Z-up ones) around the centre of ``bounds`` (2, 3), at ``distance``
        m from it, or by default just far enough for every corner of the bounds to fit in
        ``margin`` of the image."""
        b = np.asarray(bounds, float)
        c = 0.5 * (b[0] + b[1])
        az, el = math.radians(azimuth), math.radians(elevation)
        if up_axis == "Z":
            d = np.array([math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el), math.sin(el)])
            up = (0.0, 0.0, 1.0)
        else:
            d = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
            up = (0.0, 1.0, 0.0)
        cam = Camera(tuple(c + d), tuple(c), up, fov)
        if distance is None:
            f, r, u = cam.basis()
            tv = math.tan(math.radians(fov) / 2) * margin
            th = tv * aspect
            corners = np.array([[x, y, z] for x in b[:, 0] for y in b[:, 1] for z in b[:, 2]]) - c
            need = np.maximum(np.abs(corners @ r) / th, np.abs(corners @ u) / tv) - corners @ f
            extent = float(np.linalg.norm(b[1] - b[0]))
            distance = max(float(need.max()), 1e-3 * max(extent, 1e-3), 1e-6)
            # keep the near corners in front of the camera
            distance = max(distance, float((corners @ -f).max()) + 1e-3 * max(extent, 1e-3))
        elif not (distance > 0 and math.isfinite(distance)):
            raise ValueError(f"camera distance must be positive, got {distance}")
        return Camera(tuple(c + distance * d), tuple(c), up, fov)


@wp.kernel
def _vertex_normals(points: wp.array(dtype=wp.vec3), tris: wp.array(dtype=wp.int32),
                    adj_start: wp.array(dtype=wp.int32), adj_tri: wp.array(dtype=wp.int32),
                    normals: wp.array(dtype=wp.vec3)):
    """Per vertex, the sum of its triangles' area-weighted normals (gathered in a fixed order)."""
    v = wp.tid()
    n = wp.vec3(0.0)
    for k in range(adj_start[v], adj_start[v + 1]):
        t = adj_tri[k]
        a = points[tris[3 * t]]
        b = points[tris[3 * t + 1]]
        c = points[tris[3 * t + 2]]
        n = n + wp.cross(b - a, c - a)
    ln = wp.length(n)
    if ln > 0.0:
        n = n / ln
    normals[v] = n


@wp.func
def _nearest(meshes: wp.array(dtype=wp.uint64), to_local: wp.array(dtype=wp.mat44), o: wp.vec3,
             d: wp.vec3, max_t: float):
    """Nearest hit over the parts: (part or -1, t, face, u, v)."""
    best = int(-1)
    best_t = max_t
    face = int(0)
    bu = float(0.0)
    bv = float(0.0)
    for k in range(meshes.shape[0]):
        m = to_local[k]
        ol = wp.transform_point(m, o)
        dl = wp.transform_vector(m, d)
        q = wp.mesh_query_ray(meshes[k], ol, dl, best_t)
        if q.result:
            if q.t < best_t:
                best = k
                best_t = q.t
                face = q.face
                bu = q.u
                bv = q.v
    return best, best_t, face, bu, bv


@wp.func
def _occluded(meshes: wp.array(dtype=wp.uint64), to_local: wp.array(dtype=wp.mat44), o: wp.vec3,
              d: wp.vec3):
    for k in range(meshes.shape[0]):
        m = to_local[k]
        q = wp.mesh_query_ray(meshes[k], wp.transform_point(m, o), wp.transform_vector(m, d), 1.0e6)
        if q.result:
            return True
    return False


@wp.kernel
def _render(meshes: wp.array(dtype=wp.uint64), to_local: wp.array(dtype=wp.mat44),
            tri_start: wp.array(dtype=wp.int32), vert_start: wp.array(dtype=wp.int32),
            tris: wp.array(dtype=wp.int32), normals: wp.array(dtype=wp.vec3),
            colors: wp.array(dtype=wp.vec3), eye: wp.vec3, fwd: wp.vec3, right: wp.vec3,
            up: wp.vec3, tan_half: float, width: int, height: int, ss: int, light: wp.vec3,
            sky: wp.vec3, shadows: int, eps: float, image: wp.array(dtype=wp.vec3)):
    tid = wp.tid()
    px = tid % width
    py = tid / width
    aspect = float(width) / float(height)
    acc = wp.vec3(0.0)
    for sy in range(ss):
        for sx in range(ss):
            fx = (float(px) + (float(sx) + 0.5) / float(ss)) / float(width)
            fy = (float(py) + (float(sy) + 0.5) / float(ss)) / float(height)
            x = (2.0 * fx - 1.0) * tan_half * aspect
            y = (1.0 - 2.0 * fy) * tan_half
            d = wp.normalize(fwd + x * right + y * up)
            k, t, face, u, v = _nearest(meshes, to_local, eye, d, 1.0e8)
            col = wp.vec3(0.0)
            if k < 0:
                g = 0.5 * (1.0 - fy) + 0.25
                col = wp.vec3(0.93, 0.95, 0.97) * g + wp.vec3(0.80, 0.83, 0.87) * (1.0 - g)
            else:
                t0 = tri_start[k] + face
                vs = vert_start[k]
                i0 = vs + tris[3 * t0]
                i1 = vs + tris[3 * t0 + 1]
                i2 = vs + tris[3 * t0 + 2]
                nl = normals[i0] * u + normals[i1] * v + normals[i2] * (1.0 - u - v)
                m = to_local[k]
                # normals go to the world by the inverse transpose of local-to-world
                n = wp.transform_vector(wp.transpose(m), nl)
                ln = wp.length(n)
                if ln > 0.0:
                    n = n / ln
                else:
                    n = -d
                back = float(0.0)
                if wp.dot(n, d) > 0.0:
                    n = -n
                    back = 1.0
                base = colors[k]
                base = base * (1.0 - 0.25 * back) + wp.vec3(1.0) * (0.25 * back)
                hemi = 0.5 + 0.5 * wp.dot(n, sky)
                amb = 0.22 + 0.18 * hemi
                diff = wp.max(wp.dot(n, light), 0.0)
                if shadows != 0 and diff > 0.0:
                    p = eye + d * t + n * eps
                    if _occluded(meshes, to_local, p, light):
                        diff = diff * 0.35
                head = 0.15 * wp.abs(wp.dot(n, d))
                col = wp.cw_mul(base, wp.vec3(amb + 0.65 * diff + head))
            acc = acc + col
    image[tid] = acc / float(ss * ss)


class Renderer:
    """Ray-cast renders of a `Playback`.

    Args:
        playback: the animation (`read_playback`).
        width, height: image size in pixels.
        camera: a `Camera`; default: `Camera.framing` of the playback's bounds (floors left out).
        supersample: rays per pixel along each axis (anti-aliasing; 2 = 4 rays a pixel).
        shadows: cast a shadow ray from every lit hit toward the light.
        device: Warp device (default: Warp's default device).
    """

    def __init__(self, playback: Playback, width: int = 640, height: int = 480,
                 camera: Camera | None = None, supersample: int = 1, shadows: bool = True,
                 device=None):
        if int(width) < 1 or int(height) < 1:
            raise ValueError(f"image size must be at least 1x1, got {width}x{height}")
        if int(supersample) < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        self.playback = playback
        self.width, self.height = int(width), int(height)
        self.supersample = int(supersample)
        self.shadows = bool(shadows)
        self.device = wp.get_device(device)
        self.camera = camera or Camera.framing(playback.bounds(), playback.up_axis,
                                               aspect=self.width / self.height)
        dev = self.device
        parts = playback.parts
        self._points, self._meshes, self._normals_kernel_args = [], [], []
        tri_start, vert_start, tri_all, t0, v0 = [], [], [], 0, 0
        for p in parts:
            local = p.points[0] if p.deforming else p.points
            pts = wp.array(local, dtype=wp.vec3, device=dev)
            idx = wp.array(p.triangles.reshape(-1), dtype=wp.int32, device=dev)
            mesh = wp.Mesh(points=pts, indices=idx)
            # vertex -> triangles adjacency (CSR), for the normals gather
            nv = p.num_vertices
            owner = p.triangles.reshape(-1).astype(np.int64)
            order = np.argsort(owner, kind="stable")
            adj_tri = (order // 3).astype(np.int32)
            starts = np.zeros(nv + 1, np.int32)
            np.add.at(starts, owner + 1, 1)
            starts = np.cumsum(starts).astype(np.int32)
            self._points.append(pts)
            self._meshes.append(mesh)
            self._normals_kernel_args.append((idx, wp.array(starts, dtype=wp.int32, device=dev),
                                              wp.array(adj_tri, dtype=wp.int32, device=dev)))
            tri_start.append(t0)
            vert_start.append(v0)
            tri_all.append(p.triangles.reshape(-1))
            t0 += len(p.triangles)
            v0 += nv
        self._normals = wp.zeros(v0, dtype=wp.vec3, device=dev)
        self._normal_views = []
        for k, p in enumerate(parts):
            self._normal_views.append(self._normals[vert_start[k]:vert_start[k] + p.num_vertices])
        self._tri_start = wp.array(tri_start, dtype=wp.int32, device=dev)
        self._vert_start = wp.array(vert_start, dtype=wp.int32, device=dev)
        self._tris = wp.array(np.concatenate(tri_all), dtype=wp.int32, device=dev)
        self._ids = wp.array([m.id for m in self._meshes], dtype=wp.uint64, device=dev)
        self._colors = wp.array(np.array([p.color for p in parts], np.float32), dtype=wp.vec3,
                                device=dev)
        self._to_local = wp.zeros(len(parts), dtype=wp.mat44, device=dev)
        self._image = wp.zeros(self.width * self.height, dtype=wp.vec3, device=dev)
        for k in range(len(parts)):
            self._update_normals(k)
        b = playback.bounds(include_backdrop=True)
        self._eps = 1e-4 * max(float(np.linalg.norm(b[1] - b[0])), 1e-6)

    def _update_normals(self, k):
        idx, starts, adj = self._normals_kernel_args[k]
        wp.launch(_vertex_normals, dim=self.playback.parts[k].num_vertices,
                  inputs=[self._points[k], idx, starts, adj], outputs=[self._normal_views[k]],
                  device=self.device)

    def _set_frame(self, frame: int):
        mats = np.empty((len(self.playback.parts), 4, 4), np.float32)
        for k, p in enumerate(self.playback.parts):
            if p.deforming:
                self._points[k].assign(wp.array(p.points[frame], dtype=wp.vec3, device=self.device))
                self._meshes[k].refit()
                self._update_normals(k)
                mats[k] = np.eye(4)
            else:
                try:
                    mats[k] = np.linalg.inv(p.matrices[frame])
                except np.linalg.LinAlgError:  # (a traceback before)
                    raise ValueError(f"{p.path}: its transform at frame index {frame} is "
                                     "singular (a zero scale): no shape to draw") from None
        self._to_local.assign(wp.array(mats, dtype=wp.mat44, device=self.device))

    def render(self, frame: int = -1) -> np.ndarray:
        """The image of frame index ``frame`` (negative counts from the end) as (H, W, 3) uint8."""
        (frame,) = self.playback.frame_index([frame])
        self._set_frame(frame)
        cam = self.camera
        f, r, u = cam.basis()
        up_vec = np.array([0.0, 0.0, 1.0]) if self.playback.up_axis == "Z" else np.array([0.0, 1.0, 0.0])
        light = up_vec * 1.0 - f * 0.45 - r * 0.35
        light /= np.linalg.norm(light)
        wp.launch(_render, dim=self.width * self.height,
                  inputs=[self._ids, self._to_local, self._tri_start, self._vert_start, self._tris,
                          self._normals, self._colors, wp.vec3(*cam.eye), wp.vec3(*f),
                          wp.vec3(*r), wp.vec3(*u), math.tan(math.radians(cam.fov) / 2),
                          self.width, self.height, self.supersample, wp.vec3(*light),
                          wp.vec3(*up_vec), int(self.shadows), self._eps],
                  outputs=[self._image], device=self.device)
        img = self._image.numpy().reshape(self.height, self.width, 3)
        img = np.clip(img, 0.0, 1.0) ** (1.0 / 1.6)
        return (img * 255.0 + 0.5).astype(np.uint8)


def save_png(image: np.ndarray, path) -> None:
    """Write an (H, W, 3) uint8 image as PNG (Pillow)."""
    from PIL import Image

    Image.fromarray(image, "RGB").save(path, format="PNG")


def save_gif(images, path, fps: float) -> None:
    """Write (H, W, 3) uint8 frames as a looping GIF shown at ``fps`` frames per second, with one
    256-colour palette for all frames (taken from the first, middle and last) and no dithering:
    small files, no palette flicker."""
    from PIL import Image

    images = list(images)
    if not images:
        raise ValueError("no frames to write")
    picks = [images[0], images[len(images) // 2], images[-1]]
    ref = Image.fromarray(np.concatenate(picks, axis=0), "RGB").quantize(
        256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    frames = [Image.fromarray(im, "RGB").quantize(palette=ref, dither=Image.Dither.NONE)
              for im in images]
    duration = max(20, int(round(1000.0 / fps / 10.0)) * 10)
    frames[0].save(path, format="GIF", save_all=True, append_images=frames[1:], loop=0,
                   duration=duration, optimize=False, disposal=1)


def parse_frames(spec: str, num_frames: int) -> list:
    """Frame indices from ``"a:b:step"`` (Python slice syntax, any part optional; ``"-1"`` or
    ``"5"`` is one frame). Raises ValueError naming the problem."""
    s = spec.strip()
    usage = f"--frames expects A:B:STEP (integers, each optional) or a frame index, got {spec!r}"

    def num(v):
        try:
            return int(v) if v.strip() else None
        except ValueError:
            raise ValueError(usage) from None

    if ":" in s:
        bits = s.split(":")
        if len(bits) > 3:
            raise ValueError(usage)
        a, b, c = (num(v) for v in (bits + [""] * 3)[:3])
        if c is not None and c <= 0:
            raise ValueError(f"--frames {spec!r}: step must be positive")
        out = list(range(num_frames))[slice(a, b, c)]
    else:
        f = num(s)
        if f is None:
            raise ValueError(usage)
        if not -num_frames <= f < num_frames:
            raise ValueError(f"--frames {spec!r}: the stage has {num_frames} frames "
                             f"(0..{num_frames - 1})")
        out = [f % num_frames]
    if not out:
        raise ValueError(f"--frames {spec!r} selects no frame of the {num_frames} in the stage")
    return out


def parse_size(spec: str):
    """``"WxH"`` -> (W, H), both 1..8192."""
    try:
        w, h = (int(v) for v in spec.lower().split("x"))
    except ValueError:
        raise ValueError(f"--size expects WIDTHxHEIGHT such as 640x480, got {spec!r}") from None
    if not (1 <= w <= 8192 and 1 <= h <= 8192):
        raise ValueError(f"--size: width and height must be 1..8192 pixels, got {spec!r}")
    return w, h


def parse_camera(spec: str):
    """``"AZ,EL"`` or ``"AZ,EL,DIST"`` (degrees, degrees, metres from the scene's centre)."""
    try:
        vals = [float(v) for v in spec.split(",")]
    except ValueError:
        vals = []
    if len(vals) not in (2, 3) or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"--camera expects AZIMUTH,ELEVATION[,DISTANCE] (degrees, degrees, m), "
                         f"got {spec!r}")
    if not -90.0 <= vals[1] <= 90.0:
        raise ValueError(f"--camera: elevation must be in [-90, 90] degrees, got {vals[1]:g}")
    if len(vals) == 3 and not vals[2] > 0:
        raise ValueError(f"--camera: distance must be positive, got {vals[2]:g}")
    return vals[0], vals[1], (vals[2] if len(vals) == 3 else None)
