"""``warp-cloth view``: one self-contained HTML page that plays a USD stage's animation.

The page inlines the vendored three.js (``vendor/``, pinned, MIT) and the animation, so it works
offline from a ``file://`` URL. The animation is packed per part (see `playback.py` for parts):

- triangles: uint32, zlib-compressed;
- a deforming part's points: quantised to integers in steps of ``resolution`` (default 1e-4)
  times the largest extent of the part over all frames (the error is at most half a step: 0.05 mm
  on a 1 m cloth, a twentieth of a pixel on a 1,000-pixel view of it), then each frame is
  replaced by its residual from a linear prediction of the two frames before it
  (``q[f] - 2 q[f-1] + q[f-2]``, exact to invert), zigzag-coded to 16 bits, laid out x, y, z of
  all vertices per frame with the low and high bytes as separate planes, and the whole
  zlib-compressed. Smooth motion leaves small residuals, which compress well: measured by
  ``warp-cloth bench render`` on a 2,500-vertex cloth, about 6.4 kB of page per frame (raw
  float32 would be 30 kB, 40 kB in base64);
- a rigid part's local points (float32) and, when it moves, its 4x4 matrix per frame (float32).

Binary blobs are base64 in a JSON block; the browser inflates them with its built-in
``DecompressionStream("deflate")``. The page's URL hash ``#frame=N`` opens it paused at frame
index N (used by the headless-browser test; handy to share a moment).
"""

from __future__ import annotations

import base64
import json
import os
import zlib
from importlib import resources

import numpy as np

from .playback import Playback

__all__ = ["write_page", "page_html", "pack_playback", "THREE_VERSION"]

THREE_VERSION = "0.170.0"

#: quantisation step of a deforming part's points, as a fraction of their largest extent
DEFAULT_RESOLUTION = 1e-4


def _blob(arr: np.ndarray) -> str:
    return base64.b64encode(zlib.compress(np.ascontiguousarray(arr).tobytes(), 9)).decode("ascii")


def quantise_frames(points: np.ndarray, resolution: float = DEFAULT_RESOLUTION):
    """(F, N, 3) float -> (lo, step, packed bytes) as described in the module docstring:
    ``step = resolution`` times the largest extent of the points over all frames (one step on
    every axis), zigzag-coded residuals of the second-order prediction, x then y then z of all
    vertices per frame, low bytes then high bytes."""
    if not (1.0 / 16383.0 <= resolution <= 0.1):
        raise ValueError(f"resolution must be in [1/16383, 0.1] of the extent, got {resolution}")
    pts = np.asarray(points, np.float64)
    lo, hi = pts.reshape(-1, 3).min(axis=0), pts.reshape(-1, 3).max(axis=0)
    ext = float((hi - lo).max())
    step = ext * resolution if ext > 0 else 1.0
    q = np.rint((pts - lo) / step).astype(np.int64).transpose(0, 2, 1).reshape(len(pts), -1)
    pred = np.zeros_like(q)
    if len(q) > 1:
        pred[1] = q[0]
    if len(q) > 2:
        pred[2:] = 2 * q[1:-1] - q[:-2]
    r = q - pred                                  # |r| <= 2 * 16383: zigzag fits 16 bits
    z = np.where(r >= 0, 2 * r, -2 * r - 1).astype("<u2")
    planes = np.concatenate([(z & 0xFF).astype(np.uint8).ravel(),
                             (z >> 8).astype(np.uint8).ravel()])
    return lo, step, planes


def dequantise_frames(lo, step, planes: np.ndarray, frames: int, count: int) -> np.ndarray:
    """Inverse of `quantise_frames` (what the page does in JavaScript): (F, count, 3) float32."""
    n = frames * count * 3
    z = planes[:n].astype(np.int64) | (planes[n:2 * n].astype(np.int64) << 8)
    r = np.where(z & 1, -((z + 1) >> 1), z >> 1).reshape(frames, 3 * count)
    q = np.zeros_like(r)
    for f in range(frames):
        pred = 0 if f == 0 else (q[0] if f == 1 else 2 * q[f - 1] - q[f - 2])
        q[f] = r[f] + pred
    q = q.reshape(frames, 3, count).transpose(0, 2, 1)
    return (q * step + np.asarray(lo)).astype(np.float32)


def pack_playback(pb: Playback, resolution: float = DEFAULT_RESOLUTION) -> dict:
    """The page's data block: JSON-ready dict with base64 blobs (``resolution``: see
    `quantise_frames`)."""
    parts = []
    for p in pb.parts:
        d = {"path": p.path, "kind": p.kind, "color": [round(c, 4) for c in p.color],
             "vertices": int(p.num_vertices), "triangles": _blob(p.triangles.astype("<u4")),
             "triangle_count": int(len(p.triangles))}
        if p.deforming:
            lo, step, planes = quantise_frames(p.points, resolution)
            d.update(deforming=True, lo=lo.tolist(), step=step,
                     points=base64.b64encode(zlib.compress(planes.tobytes(), 9)).decode("ascii"))
        else:
            d.update(deforming=False, points=_blob(p.points.astype("<f4")))
            # column-major 4x4 (three.js Matrix4.fromArray): the transpose, flattened row-major
            mats = np.transpose(p.matrices, (0, 2, 1)).reshape(len(p.matrices), 16)
            d["matrices"] = _blob((mats if p.moving else mats[:1]).astype("<f4"))
            d["moving"] = bool(p.moving)
        parts.append(d)
    b = pb.bounds()
    return {"source": os.path.basename(pb.source), "times": [float(t) for t in pb.times],
            "tcps": pb.time_codes_per_second, "up": pb.up_axis, "bounds": b.tolist(),
            "parts": parts, "skipped": [f"{p} ({t})" for p, t in pb.skipped]}


def _vendor(name: str) -> str:
    return resources.files("warp_cloth.viewer").joinpath("vendor", name).read_text("utf-8")


def page_html(pb: Playback, title: str | None = None,
              resolution: float = DEFAULT_RESOLUTION) -> str:
    """The whole page as a string."""
    data = json.dumps(pack_playback(pb, resolution), separators=(",", ":")).replace("<", "\\u003c")
    template = resources.files("warp_cloth.viewer").joinpath("player.html").read_text("utf-8")
    title = title or os.path.basename(pb.source)
    esc = title.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    three, orbit = _vendor("three.module.min.js"), _vendor("OrbitControls.js")
    for src in (three, orbit):
        if "</script" in src.lower():  # would end the inline block early
            raise RuntimeError("vendored three.js contains '</script': cannot inline it")
    out = template.replace("%%TITLE%%", esc).replace("%%THREE_VERSION%%", THREE_VERSION)
    # data and sources last: nothing inside them is substituted again
    out = out.replace("%%DATA%%", data, 1)
    out = out.replace("%%THREE%%", three, 1).replace("%%ORBIT%%", orbit, 1)
    return out


def write_page(pb: Playback, out, title: str | None = None,
               resolution: float = DEFAULT_RESOLUTION) -> int:
    """Write the page to ``out``; returns its size in bytes."""
    html = page_html(pb, title, resolution)
    with open(out, "w", encoding="utf-8") as fh:
        fh.write(html)
    return len(html.encode("utf-8"))
