"""warp_cloth: cloth and mass-spring simulation on NVIDIA Warp, with USD output.

Quick start::

    import warp_cloth as wc

    mesh = wc.TriMesh.grid(32, 32, size=1.0, plane="xz", origin=(-0.5, 1.0, -0.5))
    model = wc.ClothModel(mesh, density=0.15, stretch_stiffness=1000.0, pins=[0, 32])
    solver = wc.make_solver("explicit", model)
    scene = wc.Scene(model, solver, fps=60, frames=120)
    print(scene.run("hanging.usd").summary())
"""

from .errors import OutputError, SimulationDiverged

__version__ = "0.1.0"

#: names importable from ``warp_cloth`` whose modules load on first use (PEP 562), so that
#: ``import warp_cloth`` stays light: it does not even import Warp (0.5 s) until a name that
#: needs it is used, so the CLI starts fast and a sweep's driver never loads it
_LAZY = {
    "TriMesh": "mesh", "ClothModel": "model", "PinPath": "model", "State": "model",
    "RunStats": "scene", "Scene": "scene", "make_solver": "solvers",
    "StrainLimit": "limits", "AreaLimit": "limits",
    "Wind": "forces.wind",
    "CollisionStage": "collision", "ObstacleContact": "collision", "Plane": "collision",
    "Sphere": "collision", "Box": "collision", "MeshObstacle": "collision",
    "Motion": "collision", "KeyframePath": "collision",
    "UsdWriter": "usd", "read_points": "usd",
}

__all__ = [
    "TriMesh", "ClothModel", "State", "PinPath", "Scene", "RunStats", "SimulationDiverged",
    "OutputError", "make_solver", "__version__", *_LAZY,
]


def __getattr__(name):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'warp_cloth' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
