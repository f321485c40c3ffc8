"""Validation that names the problem: every bad input is a ValueError saying what and where,
attacked case by case and by a property-based fuzz (hypothesis) over TriMesh, from_obj,
ClothModel and the CLI's argument handling."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import warp_cloth as wc
from warp_cloth import cli
from warp_cloth.mesh import TriMesh

QUAD_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
QUAD_T = np.array([[0, 1, 2], [0, 2, 3]])


def quad():
    return TriMesh(QUAD_V, QUAD_T)


@pytest.mark.parametrize("verts,tris,match", [
    ("abc", QUAD_T, r"vertices must be an \(N, 3\) array of numbers, got str"),
    (None, QUAD_T, r"vertices must be an \(N, 3\) array of numbers, got NoneType"),
    ([["a", "b", "c"]] * 4, QUAD_T, r"vertices must be an \(N, 3\) array of numbers"),
    (QUAD_V, "abc", r"triangles must be vertex indices \(integers\), got str"),
    (QUAD_V, None, r"triangles must be vertex indices \(integers\), got NoneType"),
    (QUAD_V, [["a", "b", "c"]], r"triangles must be vertex indices .* got an array of <U1"),
    (QUAD_V, [[True, False, True]], r"triangles must be vertex indices .* booleans"),
    (QUAD_V, [[0, 1, 2.5]], r"triangles: entry \[0, 2\] is 2.5, not an integer vertex index"),
    (QUAD_V, [[0, 1, 10**30]], r"vertex index 1e\+30 at \[0, 2\] is out of range"),
    (QUAD_V, np.array([[0, 1, 2**63 + 5]], dtype=np.uint64), r"out of range"),
    (QUAD_V * 1e39, QUAD_T, r"vertex 1 has a coordinate beyond the float32 range"),
])
def test_mesh_input_errors_name_the_problem(verts, tris, match):
    with pytest.raises(ValueError, match=match):
        TriMesh(verts, tris)


def test_relative_zero_area():
    # a 1e30 m triangle is not "zero area", nor a 1 mm one in a 1 km mesh
    TriMesh(QUAD_V * 1e30, QUAD_T)
    v = np.vstack([QUAD_V * 1e-3, QUAD_V[:3] * 1e3 + 5e3])
    TriMesh(v, np.vstack([QUAD_T, [[4, 5, 6]]]))
    with pytest.raises(ValueError, match=r"triangle 0 \[0, 1, 2\] has zero area .*collinear"):
        TriMesh([[0, 0, 0], [1e30, 0, 0], [2e30, 1e14, 0]], [[0, 1, 2]])
    # but its mass in float32 is named
    with pytest.raises(ValueError, match=r"mass of a vertex .* beyond the float32 range"):
        wc.ClothModel(TriMesh(QUAD_V * 1e30, QUAD_T), device="cpu")


def test_obj_bytes_and_huge_indices(tmp_path):
    p = tmp_path / "latin.obj"
    p.write_bytes(b"# caf\xe9 made in Latin-1\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3 # r\xe9sum\xe9\n")
    assert TriMesh.from_obj(p).num_triangles == 1  # comments may be in any encoding
    p.write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 \xe93\n")
    with pytest.raises(ValueError, match=r"latin.obj:4: bytes that are not UTF-8"):
        TriMesh.from_obj(p)
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999999\n")
    with pytest.raises(ValueError, match=r"latin.obj:4: face index 99999999999999999999999 is out of range"):
        TriMesh.from_obj(p)


@pytest.mark.parametrize("kwargs,match", [
    (dict(pins=[0.5]), r"pins: entry \[0\] is 0.5, not an integer vertex index"),
    (dict(pins=[True, False]), r"pins: a boolean mask needs one entry per vertex \(4\)"),
    (dict(pins="0"), r"pins must be vertex indices"),
    (dict(stretch_stiffness=1e40), r"stretch_stiffness is 1e\+40.*beyond the float32 range"),
    (dict(stretch_stiffness="stiff"), r"stretch_stiffness must be a number or one per edge"),
    (dict(stretch_stiffness=None), r"stretch_stiffness must be"),
    (dict(bend_stiffness=None), r"bend_stiffness must be a number, got None"),
    (dict(damping="x"), r"damping must be a number"),
    (dict(density=None), r"density must be a number"),
    (dict(gravity=(0, 0, 1e39)), r"gravity .* beyond the float32 range"),
    (dict(gravity="down"), r"gravity must be 3 numbers"),
    (dict(masses=[1e-50] * 4), r"vertex 0 has mass 1e-50 kg: its inverse is beyond float32"),
    (dict(velocity=[1, 2]), r"velocity must have shape \(3,\) or \(4, 3\)"),
    (dict(bending=["springs"]), r"bending must be one of"),
])
def test_model_input_errors_name_the_problem(kwargs, match):
    with pytest.raises(ValueError, match=match):
        wc.ClothModel(quad(), device="cpu", **kwargs)


def test_boolean_pin_mask_is_a_mask_and_integral_floats_are_indices():
    m = wc.ClothModel(quad(), pins=np.array([True, False, False, True]), device="cpu")
    assert m.pins.tolist() == [0, 3]
    assert wc.ClothModel(quad(), pins=[1.0, 2.0], device="cpu").pins.tolist() == [1, 2]


def test_isolated_vertex_is_called_isolated():
    v = np.vstack([QUAD_V, [[5, 5, 5]]])
    mesh = TriMesh(v, QUAD_T)
    with pytest.raises(ValueError, match="vertex 4 is isolated"):
        wc.ClothModel(mesh, device="cpu")
    wc.ClothModel(mesh, masses=[1.0] * 5, device="cpu")  # a free particle with a given mass


def test_cli_rejects_float32_overflow(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "hanging", "--res", "2", "--frames", "2", "--stiffness", "1e40", "--quiet"])
    assert e.value.code == 2
    assert "beyond the float32 range" in capsys.readouterr().err


# ------------------------------------------------------------------ property-based fuzz

FUZZ = settings(max_examples=60, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

junk = st.one_of(
    st.none(), st.booleans(), st.text(max_size=5), st.binary(max_size=5),
    st.integers(min_value=-2**70, max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.lists(st.one_of(st.integers(-5, 10), st.floats(allow_nan=True), st.text(max_size=2),
                       st.none(), st.booleans()), max_size=7),
    st.lists(st.lists(st.one_of(st.integers(-2, 5), st.sampled_from([2**64, 2**63, -2**70]),
                                st.floats(-1e40, 1e40), st.booleans()),
                      min_size=3, max_size=3), min_size=1, max_size=4),
)


@FUZZ
@given(verts=junk, tris=junk)
def test_fuzz_trimesh_raises_only_value_error(verts, tris):
    try:
        TriMesh(verts, tris)
    except ValueError as e:
        assert str(e)


index = st.one_of(st.integers(-4, 5), st.sampled_from([2**63, -2**63 - 1, 10**30]),
                  st.integers(-2**70, 2**70))


@FUZZ
@given(lines=st.lists(st.one_of(
    st.sampled_from(["v 0 0 0", "v 1 0 0", "v 0 1 0", "v 1 1 0", "f 1 2 3", "f 1 2 3 4",
                     "f -1 -2 -3", "f 1/1/1 2//2 3/3", "vn 0 0 1", "# c", "o x", ""]),
    st.builds(lambda a, b, c: f"f {a} {b} {c}", index, index, index),
    st.builds(lambda x: f"v {x} {x} {x}", st.floats(allow_nan=True)),
    st.text(max_size=12)), max_size=10), raw=st.binary(max_size=16), prefix=st.booleans(),
    scale=st.one_of(st.floats(allow_nan=True), st.just("2"), st.none()),
    up=st.sampled_from(["Y", "Z", "z", "x", "", None]))
def test_fuzz_from_obj_raises_only_value_error(tmp_path_factory, lines, raw, prefix, scale, up):
    p = tmp_path_factory.mktemp("obj") / "f.obj"
    head = b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" if prefix else b""
    p.write_bytes(head + "\n".join(lines).encode("utf-8", "surrogatepass") + b"\n" + raw)
    try:
        TriMesh.from_obj(p, scale=1.0 if scale is None else scale, up_axis=up)
    except ValueError as e:
        assert str(e)


@FUZZ
@given(kw=st.fixed_dictionaries({}, optional={
    "density": junk, "masses": junk, "stretch_stiffness": junk, "shear_stiffness": junk,
    "bending": st.one_of(junk, st.sampled_from(["none", "springs", "dihedral", "quadratic"])),
    "bend_stiffness": junk, "spring_damping": junk, "pins": junk, "gravity": junk,
    "damping": junk, "velocity": junk, "positions": junk}))
def test_fuzz_cloth_model_raises_only_value_error(kw):
    try:
        wc.ClothModel(TriMesh.grid(2, 1), device="cpu", **kw)
    except ValueError as e:
        assert str(e)


OPTIONS = ["--frames", "--fps", "--substeps", "--res", "--solver", "--stiffness", "--density",
           "--bending", "--bend-stiffness", "--damping", "--linear", "--linear-iterations",
           "--newton-iterations",
           "--iterations", "--compliance", "--strain-limit", "--area-limit", "--friction",
           "--restitution", "--thickness", "--save-interval", "--out", "--bogus"]
values = st.one_of(st.sampled_from(["1", "2", "0.5", "1e40", "1e-300", "1e-30", "0", "-1", "nan",
                                    "inf", "abc", "0,1", "1,0", "0,1e40", "cg", "pbd", "x.usd",
                                    ""]),
                   st.text(max_size=4))


NUMERIC = ["--stiffness", "--density", "--bend-stiffness", "--damping", "--fps", "--thickness",
           "--friction", "--compliance", "--frames", "--substeps"]
extreme = st.sampled_from(["1e40", "4e38", "1e300", "1e-300", "1e-45", "0", "1", "0.5", "3"])


@settings(FUZZ, max_examples=120)
@given(scene=st.sampled_from(["hanging", "flag", "drape", "nowhere", ""]),
       opts=st.one_of(
           st.lists(st.tuples(st.sampled_from(OPTIONS), values), max_size=3),
           # numbers the parser accepts, at the extremes the model must reject by name
           st.lists(st.tuples(st.sampled_from(NUMERIC), extreme), min_size=1, max_size=2)),
       flags=st.lists(st.sampled_from(["--gauss-seidel", "--quiet", "--json"]), max_size=2))
def test_fuzz_cli_run_arguments(monkeypatch, tmp_path_factory, scene, opts, flags):
    """Parse and build (not run) a scene from random arguments: a usage error (exit 2 with a
    message) or a built scene, never another exception."""
    import contextlib
    import io

    import warp_cloth.scene as scene_mod

    class Built(Exception):
        pass

    def fake_run(self, *a, **k):
        raise Built()

    monkeypatch.setattr(scene_mod.Scene, "run", fake_run)
    argv = ["run", scene, *flags]
    for o, v in opts:
        argv += [o, v]
    if "--res" not in argv:
        argv += ["--res", "2"]  # keep the models tiny
    if "--out" not in argv:
        argv += ["--out", str(tmp_path_factory.mktemp("cli") / "o.usd")]
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            cli.main(argv)
    except SystemExit as e:
        assert e.code == 2 and "error:" in err.getvalue(), (argv, err.getvalue())
    except Built:
        pass


def _small():
    return wc.ClothModel(TriMesh.grid(4, 4, plane="xz", origin=(-0.5, 1.0, -0.5)), pins=[0, 4])


def _api_cases():
    from warp_cloth.collision import Box, CollisionStage, MeshObstacle, ObstacleContact, Sphere
    from warp_cloth.model import PinPath

    m = _small()
    other = wc.ClothModel(TriMesh.grid(8, 8, plane="xz", origin=(-0.5, 1.0, -0.5)), pins=[0, 8])
    return [
        # a limit built for another model: its arrays are another mesh's (the process ended in
        # a heap corruption)
        (lambda: wc.make_solver("explicit", m, corrections=[wc.StrainLimit(other, 0, 1.01)]),
         ValueError, "StrainLimit was built for another model"),
        (lambda: wc.make_solver("pd", m, delay=-1), ValueError, "pd: delay must be"),
        (lambda: wc.make_solver("implicit", m, tolerance="1e-4"), ValueError,
         "implicit: option 'tolerance' must be a number, got '1e-4'"),
        (lambda: wc.make_solver("pbd", m, iterations=float("nan")), ValueError,
         "pbd: option 'iterations' must be an integer"),
        (lambda: wc.make_solver("implicit", m, line_search="no"), ValueError,
         "option 'line_search' must be True or False"),
        (lambda: wc.make_solver("implicit", m, newton_iterations=True), ValueError,
         "option 'newton_iterations' must be an integer, got True"),
        (lambda: wc.make_solver("pd", m, delay=2.5), ValueError, "option 'delay' must be an integer"),
        (lambda: wc.make_solver("explicit", None), ValueError, "model must be a warp_cloth.ClothModel"),
        (lambda: wc.Scene(m, wc.make_solver("implicit", m), fps=1e200), ValueError,
         "gives a step of"),
        (lambda: wc.Scene(m, wc.make_solver("implicit", m), fps=1e-40, substeps=1), ValueError,
         "gives a step of 1e\\+40 s"),
        (lambda: wc.Scene(m, wc.make_solver("explicit", m), substeps=10**9), ValueError,
         "substeps must be at most"),
        (lambda: wc.Scene(m, wc.make_solver("explicit", m), frames=True), ValueError,
         "frames must be an integer"),
        (lambda: wc.Scene(m, None), ValueError, "solver must be a warp_cloth solver"),
        (lambda: wc.Scene(m, wc.make_solver("explicit", m), obstacles=5), ValueError,
         "Scene: obstacles must be an obstacle or a list of them, got int"),
        (lambda: Sphere(0.1, name=5), ValueError, "Sphere: name must be a string"),
        (lambda: CollisionStage(None, [Sphere(0.1)]), ValueError,
         "CollisionStage: model must be a warp_cloth.ClothModel, got NoneType"),
        (lambda: CollisionStage(m, [Sphere(0.1), "floor"]), ValueError,
         r"CollisionStage: obstacles\[1\] is a str, not an obstacle"),
        (lambda: ObstacleContact(m, 5), ValueError, "ObstacleContact: obstacles must be"),
        (lambda: wc.StrainLimit(None, 0, 1.01), ValueError, "StrainLimit: model must be"),
        (lambda: wc.ClothModel(m.mesh, wind="strong"), ValueError, "wind must be a warp_cloth.Wind"),
        # values beyond what the device's float32 holds (they became inf at frame 1)
        (lambda: wc.Wind(velocity=(1e39, 0, 0)), ValueError, "Wind.velocity must be within"),
        (lambda: wc.Wind(drag_coefficient=1e39), ValueError, "Wind.drag_coefficient must be"),
        (lambda: PinPath([0, 1], np.full((2, 2, 3), 1e39)), ValueError,
         "PinPath: positions beyond the float32 range"),
        (lambda: Box((1e39, 0.1, 0.1), (0, -0.5, 0)), ValueError,
         r"half_extents \(1e\+39, 0.1, 0.1\) is beyond the float32 range"),
        (lambda: CollisionStage(m, [Sphere(0.1)], thickness=1e39), ValueError,
         r"thickness must be in \(0, 1e\+06\]"),
        (lambda: MeshObstacle(m.mesh, scale=1e39), ValueError, "beyond the float32 range"),
        (lambda: wc.ClothModel(m.mesh, stretch_stiffness=np.ones((len(m.mesh.edges), 1))),
         ValueError, r"one per edge, shape \(56,\): got shape \(56, 1\)"),
    ]


@pytest.mark.parametrize("k", range(27))
def test_api_input_errors_name_the_problem(k):
    """Found by an audit of the public API with bad input (2026-12-07): each raised deep inside
    numpy or Warp, crashed the process, was accepted silently, or failed only once the run had
    opened its output."""
    cases = _api_cases()
    assert len(cases) == 27
    make, exc, match = cases[k]
    with pytest.raises(exc, match=match):
        make()


def test_obj_face_errors_name_file_and_line_and_a_path_must_be_a_path(tmp_path):
    p = tmp_path / "oor.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    with pytest.raises(ValueError, match=r"oor.obj:4: face index 9 is out of range \(the file "
                                         r"has 3 vertices\)"):
        TriMesh.from_obj(p)
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -7\n")
    with pytest.raises(ValueError, match=r"oor.obj:4: face index -7 is out of range"):
        TriMesh.from_obj(p)
    p.write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\n\x85\nf 1 2 3\n")  # a line of one NEL byte
    assert len(TriMesh.from_obj(p).triangles) == 1
    with pytest.raises(ValueError, match="path must be a str or os.PathLike, got int"):
        TriMesh.from_obj(0)  # (a file descriptor: 0 read standard input)


def test_cli_res_beyond_memory_is_a_usage_error(tmp_path, capsys):
    out = tmp_path / "big.usd"
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "hanging", "--res", "1000000", "--frames", "2", "--out", str(out)])
    assert e.value.code == 2 and "does not fit in this machine's memory" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("kwargs,match", [
    (dict(origin=(0, 0)), r"grid: origin must be 3 finite numbers, got \(0, 0\)"),
    (dict(origin=None), "grid: origin must be 3 finite numbers, got None"),
    (dict(plane=["xz"]), r"grid: plane must be one of"),
    (dict(size=(1.0, 2.0, 3.0)), "grid: size must be a positive number or two"),
    (dict(size="big"), "grid: size must be a positive number or two"),
    (dict(nx=True), "grid: nx and ny must be positive integers"),
    (dict(nx="4"), "grid: nx and ny must be positive integers"),
])
def test_grid_arguments_are_checked(kwargs, match):
    """(Before: numpy's broadcast error for a 2-number origin, 'vertex 0 has a non-finite
    coordinate' for None, 'unhashable type' for a list plane, True taken as 1.)"""
    args = dict(nx=4, ny=4)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        TriMesh.grid(**args)


def _text_and_bool_cases():
    from warp_cloth.collision import Box, CollisionStage, MeshObstacle, Plane, Sphere
    from warp_cloth.contact_scenes import asset_path
    from warp_cloth.limits import AreaLimit, StrainLimit

    m = wc.contact_scenes.sheet_model(res=4)
    return [
        (lambda: Sphere("0.3"), "radius"), (lambda: Sphere(True), "radius"),
        (lambda: Sphere(0.3, friction=True), "friction"),
        (lambda: Sphere(0.3, restitution="1"), "restitution"),
        (lambda: Box("abc"), "half_extents"), (lambda: Box((0.1, "0.2", 0.3)), "half_extents"),
        (lambda: Box((0.1, 0.2, 0.3), center=(True, 0, 0)), "position"),  # its centre
        (lambda: MeshObstacle(asset_path("sphere.obj"), scale="2"), "scale"),
        (lambda: MeshObstacle(asset_path("sphere.obj"), scale=True), "scale"),
        (lambda: StrainLimit(m, "0", 1.01), "sigma_min"), (lambda: StrainLimit(m, 0, True), "sigma_max"),
        (lambda: AreaLimit(m, "0.9", 1.1), "a_min"),
        (lambda: CollisionStage(m, [Plane()], thickness="0.005"), "thickness"),
        (lambda: CollisionStage(m, [Plane()], friction=True), "friction"),
        (lambda: CollisionStage(m, [Plane()], restitution="0"), "restitution"),
    ]


@pytest.mark.parametrize("k", range(15))
def test_numbers_given_as_text_or_bools_are_refused_by_name(k):
    """A radius of ``"0.3"`` or ``True``, a friction of ``"0.4"``, limit bounds as strings: the
    constructors converted them with ``float()`` and went on (a sphere of 1 m for ``True``)."""
    make, name = _text_and_bool_cases()[k]
    with pytest.raises(ValueError, match=name):
        make()
