"""`warp_cloth.util.launch`: a replayed launch computes exactly what `wp.launch` computes."""

import numpy as np
import warp as wp

from warp_cloth import util
from warp_cloth.util import launch


@wp.struct
class Pair:
    a: wp.array(dtype=float)
    scale: float


@wp.kernel
def _axpy_kernel(x: wp.array(dtype=wp.vec3), y: wp.array(dtype=wp.vec3), s: float,
                 shift: wp.vec3, k: int):
    i = wp.tid()
    y[i] = y[i] + s * x[i] + shift * float(k)


@wp.kernel
def _struct_kernel(p: Pair, out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = p.scale * p.a[i]


def test_replay_follows_changed_numbers_vectors_and_arrays(device):
    """Each call changes a number, a vector or an array: the replay must use the new value
    (a cache that skipped re-packing would repeat the first call's arguments)."""
    rng = np.random.default_rng(3)
    xs = [wp.array(rng.normal(size=(5, 3)), dtype=wp.vec3, device=device) for _ in range(2)]
    y = wp.zeros(5, dtype=wp.vec3, device=device)
    expect = np.zeros((5, 3))
    calls = [(0, 1.0, (0.0, 0.0, 0.0), 1), (0, 2.0, (0.0, 0.0, 0.0), 1),
             (0, 2.0, (1.0, -2.0, 0.5), 1), (0, 2.0, (1.0, -2.0, 0.5), 3),
             (1, 2.0, (1.0, -2.0, 0.5), 3), (0, -0.5, (0.0, 1.0, 0.0), 2)]
    for which, s, shift, k in calls:
        launch(_axpy_kernel, 5, [xs[which], y, s, wp.vec3(*shift), k], device=device)
        expect += s * xs[which].numpy() + np.array(shift) * k
        np.testing.assert_allclose(y.numpy(), expect, rtol=1e-6, atol=1e-6)


def test_replay_sees_a_struct_field_assigned_after_recording(device):
    """A struct's fields are read at each launch: assigning a new array or scale to the same
    struct between launches changes the result."""
    p = Pair()
    p.a = wp.array([1.0, 2.0, 3.0], dtype=float, device=device)
    p.scale = 2.0
    out = wp.zeros(3, dtype=float, device=device)
    launch(_struct_kernel, 3, [p, out], device=device)
    np.testing.assert_allclose(out.numpy(), [2.0, 4.0, 6.0])
    p.a = wp.array([10.0, 20.0, 30.0], dtype=float, device=device)
    p.scale = -1.0
    launch(_struct_kernel, 3, [p, out], device=device)
    np.testing.assert_allclose(out.numpy(), [-10.0, -20.0, -30.0])


def test_zero_dimension_and_graph_capture(device):
    """A zero launch dimension does nothing; inside a graph capture the launch is recorded into
    the graph (plain `wp.launch`), and the graph replays it."""
    y = wp.zeros(4, dtype=wp.vec3, device=device)
    x = wp.array(np.ones((4, 3)), dtype=wp.vec3, device=device)
    launch(_axpy_kernel, 0, [x, y, 1.0, wp.vec3(0.0), 0], device=device)
    assert np.all(y.numpy() == 0.0)
    launch(_axpy_kernel, 4, [x, y, 1.0, wp.vec3(0.0), 0], device=device)  # recorded here
    with wp.ScopedCapture(device=device, force_module_load=False) as cap:
        launch(_axpy_kernel, 4, [x, y, 1.0, wp.vec3(0.0), 0], device=device)
    assert np.allclose(y.numpy(), 1.0)  # recorded into the graph, not run
    wp.capture_launch(cap.graph)
    wp.capture_launch(cap.graph)
    assert np.allclose(y.numpy(), 3.0)


def test_cache_is_bounded(device, monkeypatch):
    """Launches over many distinct arrays never hold more than the cap of recorded commands."""
    monkeypatch.setattr(util, "_LAUNCHES", {})
    monkeypatch.setattr(util, "_LAUNCHES_CAP", 8)
    y = wp.zeros(2, dtype=wp.vec3, device=device)
    keep = []
    for n in range(20):
        x = wp.array(np.full((2, 3), float(n)), dtype=wp.vec3, device=device)
        keep.append(x)  # distinct live arrays: distinct keys
        launch(_axpy_kernel, 2, [x, y, 1.0, wp.vec3(0.0), 0], device=device)
        assert len(util._LAUNCHES) <= 8
    assert np.allclose(y.numpy(), sum(range(20)))


def test_cache_keeps_no_struct_alive(device):
    """A recorded launch holds no reference to its struct (nor to the arrays the struct
    holds): a solver's contact record is freed with the solver, and a new struct is never
    replayed from a dead one's command."""
    import gc
    import weakref

    out = wp.zeros(3, dtype=float, device=device)
    p = Pair()
    p.a = wp.array([1.0, 2.0, 3.0], dtype=float, device=device)
    p.scale = 1.0
    launch(_struct_kernel, 3, [p, out], device=device)
    gone = weakref.ref(p)
    del p
    gc.collect()
    assert gone() is None
    for k in range(5):  # new structs (some may reuse the dead one's id): their own values
        q = Pair()
        q.a = wp.array([float(k), 0.0, 1.0], dtype=float, device=device)
        q.scale = 2.0
        launch(_struct_kernel, 3, [q, out], device=device)
        np.testing.assert_allclose(out.numpy(), [2.0 * k, 0.0, 2.0])
        del q
        gc.collect()
