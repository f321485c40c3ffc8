"""Small helpers shared across the package."""

from __future__ import annotations

import logging
import math
import numbers
import weakref

import numpy as np
import warp as wp


def quiet_warp() -> None:
    """Silence Warp's start-up banner and per-module compile messages (warnings still show).

    Warp >= 1.13 uses ``wp.config.log_level``; older releases ``wp.config.quiet``.
    """
    if hasattr(wp.config, "log_level"):
        wp.config.log_level = logging.WARNING
    else:
        wp.config.quiet = True


#: Warp's native start-up warning on a machine without a CUDA driver
_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"


def init_warp(*, verbose: bool = False, device=None) -> None:
    """Initialise Warp, quietly unless asked.

    Without ``verbose``: Warp's info messages (start-up banner, a line per module load, which
    would land inside a progress bar) are off (`quiet_warp`), and Warp's native "could not find
    the NVIDIA CUDA driver" warning, printed by its C library on a CPU-only machine, is held back
    unless ``device`` names a CUDA device. Anything else Warp prints while starting still shows.
    Calling it again is harmless (Warp initialises once).
    """
    import os
    import sys
    import tempfile

    if not verbose:
        quiet_warp()
    wants_cuda = device is not None and str(device).startswith("cuda")
    if verbose or wants_cuda:
        wp.init()
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        wp.init()
        return
    with tempfile.TemporaryFile() as tmp:
        try:
            os.dup2(tmp.fileno(), 2)
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        text = tmp.read().decode("utf-8", "replace")
    kept = [ln for ln in text.splitlines() if _NO_DRIVER not in ln]
    if kept:
        sys.stderr.write("\n".join(kept) + "\n")
        sys.stderr.flush()


def not_text_or_bool(value, what: str, kind: str = "a number"):
    """``value``, unless it is a string, bytes or a bool: a `ValueError` naming ``what``. The
    numeric checks convert with ``float()``, which took ``"0.3"`` and ``True`` for numbers
    without a word (a sphere of radius ``True`` m, a friction of ``"0.4"``)."""
    if isinstance(value, (str, bytes, bool, np.bool_)):
        raise ValueError(f"{what} must be {kind}, got {value!r}")
    return value


def positive_finite(value, what: str, unit: str = "") -> float:
    """``float(value)`` if it is a positive finite number, else a `ValueError` naming ``what``
    (and its ``unit``, e.g. ``"metres"``)."""
    of = f" of {unit}" if unit else ""
    not_text_or_bool(value, what, f"a positive number{of}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a positive number{of}, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{what} must be positive and finite{f' ({unit})' if unit else ''}, "
                         f"got {value!r}")
    return v


def check_number(value, what: str, integer: bool = False):
    """``value`` if it is a real number (``integer``: a whole one, an integral float allowed),
    not a bool, else a `ValueError` naming ``what`` (`make_solver`'s options, `Scene`'s counts):
    no ``int()`` or ``float()`` of a string, NaN or None that fails without the name."""
    kind = "an integer" if integer else "a number"
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ValueError(f"{what} must be {kind}, got {value!r}")
    if integer and not isinstance(value, numbers.Integral) and not (
            math.isfinite(float(value)) and float(value).is_integer()):
        raise ValueError(f"{what} must be {kind}, got {value!r}")
    return value


def nonnegative_finite(value, what: str, unit: str = "") -> float:
    """``float(value)`` if it is a finite number >= 0, else a `ValueError` naming ``what`` (and
    its ``unit``): `positive_finite`'s twin for quantities that may be zero."""
    of = f" of {unit}" if unit else ""
    not_text_or_bool(value, what, f"a number{of} >= 0")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a number{of} >= 0, got {value!r}") from None
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{what} must be finite and >= 0{f' ({unit})' if unit else ''}, "
                         f"got {value!r}")
    return v


# ---------------------------------------------------------------------------- recorded launches
#: recorded launches by (kernel, dim, device, array layout); cleared when it reaches the cap
_LAUNCHES: dict = {}
_LAUNCHES_CAP = 4096
_NUMBERS = (int, float, bool)


def launch(kernel, dim, inputs, device=None) -> None:
    """``wp.launch(kernel, dim, inputs, device=device)``, replayed from a recorded command.

    On the CPU a plain `wp.launch` spends most of its time packing its arguments in Python
    (about 20 us for five arguments, 40-60 us for the solvers' dozen: measured with Warp 1.19 on
    this project's CPU, where a small kernel itself runs in a few microseconds). Here the packed
    command (``wp.launch(..., record_cmd=True)``) is kept, keyed by the kernel, the launch
    dimension, the device and the layout of every array argument (data pointer, shape,
    strides, dtype) and the identity of every struct argument, and replayed; only number, vector
    and matrix arguments whose value changed since the last replay are packed again
    (`wp.Launch.set_param_at_index`). A command holds no reference to its arrays: a later array
    with the same pointer, shape, strides and dtype packs to the same bytes, so replaying for it
    is exact, and arrays are freed as usual. A struct argument is packed as its live C value
    (Warp's ``StructInstance._ctype``, updated in place when a field is assigned), so a replay
    sees its current fields; the command is replayed only for that same struct object (a weak
    reference: the cache keeps no struct, and the arrays it holds, alive).

    Falls back to a plain `wp.launch` (same result) while the device records a graph (the
    capture needs the launch's own arguments), and for ``None``, differentiable-array or other
    arguments.
    """
    dev = wp.get_device(device)
    key = [kernel, dim, dev.ordinal]
    values = []
    structs = []
    for i, a in enumerate(inputs):
        if isinstance(a, wp.array):
            if a.requires_grad:
                return wp.launch(kernel, dim, inputs, device=device)
            key.append((a.ptr, a.shape, a.strides, a.dtype))
        elif isinstance(a, _NUMBERS):
            key.append(type(a))
            values.append((i, a))
        elif wp.types.type_is_vector(type(a)) or wp.types.type_is_matrix(type(a)):
            key.append(type(a))
            values.append((i, tuple(a) if wp.types.type_is_vector(type(a)) else
                           tuple(tuple(r) for r in a)))
        elif wp.types.is_struct(a):
            key.append(id(a))
            structs.append(a)
        else:
            return wp.launch(kernel, dim, inputs, device=device)
    if dev.is_capturing:
        return wp.launch(kernel, dim, inputs, device=device)
    key = tuple(key)
    entry = _LAUNCHES.get(key)
    if entry is not None and any(r() is not a for r, a in zip(entry[2], structs)):
        entry = None  # a new struct where a dead one was (the same id): record again
    if entry is None:
        if len(_LAUNCHES) >= _LAUNCHES_CAP:
            _LAUNCHES.clear()
        cmd = wp.launch(kernel, dim, inputs, device=device, record_cmd=True)
        if cmd is None:  # nothing to launch (a zero dimension)
            return None
        cmd.fwd_args = None  # no references to the arrays (see above)
        _LAUNCHES[key] = entry = [cmd, dict(values), [weakref.ref(a) for a in structs]]
        cmd.launch()
        return None
    cmd, seen, _ = entry
    for i, v in values:
        if seen[i] != v:
            cmd.set_param_at_index(i, inputs[i])
            seen[i] = v
    cmd.launch()
    return None


def count_since(counter, seen: int, slot: int = 0) -> tuple[int, int]:
    """A device counter's growth since the last report (one host read, for a frame's messages):
    ``(new, total)`` with ``new = counter[slot] - seen``; keep ``total`` as the next ``seen``."""
    total = int(counter.numpy()[slot])
    return total - int(seen), total


def stride_threads(n: int, device, batch: int = 1) -> int:
    """Threads for a kernel that strides over ``n`` elements (``for i in range(tid, n,
    threads)``): one on the CPU, whose backend runs a launch's threads one after another on
    one core (a thread that finds nothing to do still costs its call, and a thread's loop sums
    in registers and adds each total once); one per ``batch`` elements elsewhere. The inner
    solvers' per-vertex sums take ``batch=1`` (on a GPU one element a thread, as a plain
    launch): summing every vertex into one float64 address with ``wp.atomic_add`` cost CG's
    update about twice its arithmetic on the CPU, each add waiting for the last (2,500
    vertices: 38-48 us against 19-24 us a launch). Contact records take 16 (`record_threads`)."""
    if wp.get_device(device).is_cpu:
        return 1
    return max(1, -(-int(n) // int(batch)))


def check_model(model, who: str):
    """``model`` if it is a `warp_cloth.ClothModel`, else a ValueError naming ``who`` (before:
    None or a TriMesh failed later on a missing attribute, ``'NoneType' object has no
    attribute 'device'``)."""
    from .model import ClothModel

    if not isinstance(model, ClothModel):
        raise ValueError(f"{who}: model must be a warp_cloth.ClothModel, got "
                         f"{type(model).__name__}")
    return model


def obstacle_list(obstacles, who: str) -> list:
    """``obstacles`` (one obstacle or an iterable of them) as a list, each checked to be an
    obstacle (`warp_cloth.collision.Obstacle`), else a ValueError naming ``who`` and the entry."""
    from .collision.obstacles import Obstacle

    if isinstance(obstacles, Obstacle):
        return [obstacles]
    try:
        out = list(obstacles)
    except TypeError:
        raise ValueError(f"{who}: obstacles must be an obstacle or a list of them, got "
                         f"{type(obstacles).__name__}") from None
    for k, ob in enumerate(out):
        if not isinstance(ob, Obstacle):
            raise ValueError(f"{who}: obstacles[{k}] is a {type(ob).__name__}, not an obstacle "
                             "(Plane, Sphere, Box, MeshObstacle)")
    return out
