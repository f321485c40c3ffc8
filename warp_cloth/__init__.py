"""warp_cloth: cloth and mass-spring simulation on NVIDIA Warp, with USD output.

Quick start::

    import warp_cloth as wc

    mesh = wc.TriMesh.grid(32, 32, size=1.0, plane="xz", origin=(-0.5, 1.0, -0.5))
    model = wc.ClothModel(mesh, density=0.15, stretch_stiffness=1000.0, pins=[0, 32])
    solver = wc.make_solver("explicit", model)
    scene = wc.Scene(model, solver, fps=60, frames=120)
    print(scene.run("hanging.usd").summary())
"""

from .errors import SimulationDiverged
from .mesh import TriMesh
from .model import ClothModel, PinPath, State
from .scene import RunStats, Scene
from .solvers import make_solver

__version__ = "0.1.0"

__all__ = [
    "TriMesh", "ClothModel", "State", "PinPath", "Scene", "RunStats", "SimulationDiverged",
    "make_solver", "__version__",
]
