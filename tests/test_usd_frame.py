"""Input in its own frame: a Z-up USD file falls down its z axis at its real size; units and up
axes of USD and OBJ input; the output stage records the frame it was written in."""

import os

import numpy as np
import pytest
import warp as wp
from pxr import Usd, UsdGeom

import warp_cloth as wc
from warp_cloth.usd import read_points


def square_cloth_path():
    """warp-lang's own example asset (Z-up, metersPerUnit 1, a 150 x 100 unit sheet)."""
    return os.path.join(os.path.dirname(wp.__file__), "examples", "assets", "square_cloth.usd")


@pytest.fixture(scope="module")
def square_cloth():
    path = square_cloth_path()
    if not os.path.isfile(path):
        pytest.skip("this warp-lang has no examples/assets/square_cloth.usd")
    return wc.TriMesh.from_usd(path)


def test_square_cloth_keeps_its_frame_and_size(square_cloth):
    m = square_cloth
    assert m.up_axis == "Z"
    lo, hi = m.vertices.min(0), m.vertices.max(0)
    # horizontal in a Z-up world (the prim's transform turns its local xz sheet into world xy),
    # 150 m x 100 m at metersPerUnit 1
    assert np.allclose(hi - lo, [150.0, 100.0, 0.0], atol=1e-3)
    model = wc.ClothModel(m, device="cpu")
    assert model.gravity == (0.0, 0.0, -9.81)


@pytest.mark.parametrize("method", ["explicit", "implicit", "pbd", "pd"])
def test_square_cloth_falls_down_its_up_axis(square_cloth, method, tmp_path):
    m = square_cloth
    x = m.vertices
    # the two corners of the +y side
    top = x[:, 1] > x[:, 1].max() - 1e-6
    pins = [int(np.flatnonzero(top)[np.argmin(x[top, 0])]), int(np.flatnonzero(top)[np.argmax(x[top, 0])])]
    model = wc.ClothModel(m, pins=pins, damping=0.1, device="cpu")
    opts = {"iterations": 4} if method in ("pbd", "pd") else {}
    solver = wc.make_solver(method, model, **opts)
    substeps = {"explicit": None, "implicit": 1, "pbd": 4, "pd": 1}[method]
    fps, frames = 10.0, 4
    out = os.fspath(tmp_path / "sq.usd")
    stats = wc.Scene(model, solver, fps=fps, frames=frames, substeps=substeps).run(out)
    t = (frames - 1) / fps
    times, pts, stage = read_points(out)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    d = pts[-1] - pts[0]
    free = np.ones(len(x), bool)
    free[pins] = False
    fall = 0.5 * 9.81 * t * t
    # falls down z near free fall (implicit Euler at one step per frame over-shoots 0.5 g t^2
    # by a third: 6 g h^2 after 3 steps of h), nothing sideways
    assert -1.4 * fall < d[free, 2].mean() < -0.7 * fall, d[free].mean(0)
    assert np.abs(d[free, :2].mean(0)).max() < 0.05 * fall
    assert np.allclose(d[pins], 0.0, atol=1e-4)
    # RunStats heights are along the model's up axis (z here)
    assert stats.max_height == pytest.approx(0.0, abs=1e-3)
    assert stats.min_height == pytest.approx(pts[:, :, 2].min(), abs=1e-5)


def _quad_stage(path, up, mpu):
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, up)
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    q = UsdGeom.Mesh.Define(stage, "/Q")
    q.CreatePointsAttr([(0, 0, 0), (100, 0, 0), (100, 100, 0), (0, 100, 0)])
    q.CreateFaceVertexCountsAttr([4])
    q.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    stage.Save()


def test_usd_units_and_up_axis(tmp_path):
    _quad_stage(tmp_path / "cm.usda", UsdGeom.Tokens.z, 0.01)  # centimetres, Z up
    m = wc.TriMesh.from_usd(tmp_path / "cm.usda")
    assert m.up_axis == "Z" and m.extent() == pytest.approx(1.0)
    _quad_stage(tmp_path / "mm.usda", UsdGeom.Tokens.y, 0.001)
    m = wc.TriMesh.from_usd(tmp_path / "mm.usda")
    assert m.up_axis == "Y" and m.extent() == pytest.approx(0.1)
    assert wc.ClothModel(m, device="cpu").gravity == (0.0, -9.81, 0.0)


def test_usd_unauthored_units_are_centimetres(tmp_path):
    stage = Usd.Stage.CreateNew(str(tmp_path / "plain.usda"))  # no upAxis, no metersPerUnit
    q = UsdGeom.Mesh.Define(stage, "/Q")
    q.CreatePointsAttr([(0, 0, 0), (100, 0, 0), (100, 0, 100), (0, 0, 100)])
    q.CreateFaceVertexCountsAttr([4])
    q.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    stage.Save()
    m = wc.TriMesh.from_usd(tmp_path / "plain.usda")
    assert m.up_axis == "Y" and m.extent() == pytest.approx(1.0)  # USD's fallbacks: Y, 0.01


def test_obj_scale_and_up_axis(tmp_path):
    p = tmp_path / "q.obj"
    p.write_text("v 0 0 0\nv 100 0 0\nv 100 100 0\nv 0 100 0\nf 1 2 3 4\n")
    m = wc.TriMesh.from_obj(p, scale=0.01, up_axis="z")
    assert m.up_axis == "Z" and m.extent() == pytest.approx(1.0)
    assert wc.TriMesh.from_obj(p).up_axis == "Y"
    with pytest.raises(ValueError, match="up_axis must be 'Y' or 'Z'"):
        wc.TriMesh.from_obj(p, up_axis="x")
    with pytest.raises(ValueError, match="scale must be positive"):
        wc.TriMesh.from_obj(p, scale=-1)
    with pytest.raises(ValueError, match="scale must be a positive number"):
        wc.TriMesh.from_obj(p, scale="big")


def test_z_up_grid_written_z_up(tmp_path):
    mesh = wc.TriMesh.grid(3, 3, plane="xy", origin=(0, 0, 1.0), up_axis="Z")
    model = wc.ClothModel(mesh, pins=[0, 3], device="cpu")
    out = tmp_path / "z.usda"
    stats = wc.Scene(model, wc.make_solver("implicit", model), fps=30, frames=3).run(out)
    stage = Usd.Stage.Open(str(out))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert stats.max_height == pytest.approx(1.0) and stats.min_height < 1.0 - 1e-3


def test_from_usd_on_a_file_that_is_not_usd(tmp_path):
    p = tmp_path / "junk.usda"
    p.write_text("#usda 1.0\n(((( not usd")
    with pytest.raises(ValueError, match=r"junk.usda: cannot open USD stage"):
        wc.TriMesh.from_usd(p)
