"""Built-in scenes used by the CLI, the examples and the benchmarks.

Every builder takes keyword arguments in SI units and returns a `Scene`. Defaults are real cloth:
a 1 m sheet of 0.15 kg/m^2 with 1000 N/m stretch springs.

- ``hanging``: a horizontal sheet pinned at two corners of one side, falling and swinging.
- ``flag``: a vertical sheet pinned along one side, in gusty wind.

`SCENES` maps names to builders; later features register theirs (contact scenes) here.
"""

from __future__ import annotations

from .mesh import TriMesh
from .model import DEFAULT_DENSITY, DEFAULT_STRETCH_STIFFNESS, ClothModel
from .scene import Scene
from .solvers import make_solver

__all__ = ["SCENES", "build_scene", "hanging", "flag", "hanging_model"]


def _grid_shape(res, shape):
    if shape is not None:
        nx, ny = shape
    else:
        nx = ny = res
    if int(nx) != nx or int(ny) != ny or nx < 1 or ny < 1:
        raise ValueError(f"resolution must be positive integers, got {(nx, ny)}")
    return int(nx), int(ny)


def _finish(model, solver, solver_options, corrections, fps, frames, substeps, obstacles,
            strain_bound, name, collision=None, self_collision: bool = False):
    solver_obj = make_solver(solver, model, **(solver_options or {}))
    if collision is None and self_collision:
        from .collision import CollisionStage

        collision = CollisionStage(model, list(obstacles or ()), self_collision=True)
    if collision is not None:
        solver_obj.set_collision(collision)
    for c in corrections or ():
        # a correction object, or a factory ``model -> correction`` (the CLI passes factories)
        solver_obj.add_correction(c if hasattr(c, "apply") else c(model))
    return Scene(model, solver_obj, fps=fps, frames=frames, substeps=substeps,
                 obstacles=obstacles, strain_bound=strain_bound, name=name)


def hanging_model(*, res: int = 32, shape=None, size: float = 1.0, height: float = 1.0,
                  stiffness: float = DEFAULT_STRETCH_STIFFNESS, density: float = DEFAULT_DENSITY,
                  bending: str = "none", bend_stiffness: float = 0.0, shear_stiffness: float = 0.0,
                  damping: float = 0.1, spring_damping: float = 0.0, masses=None, device=None,
                  **model_options) -> ClothModel:
    """The hanging-cloth model: an ``nx`` x ``ny`` grid, ``size`` m wide (square cells),
    horizontal at ``height`` m, pinned at the two corners of its ``j = 0`` side."""
    nx, ny = _grid_shape(res, shape)
    mesh = TriMesh.grid(nx, ny, size=(size, size * ny / nx), plane="xz",
                        origin=(-0.5 * size, height, -0.5 * size * ny / nx))
    return ClothModel(mesh, density=density, masses=masses, stretch_stiffness=stiffness,
                      shear_stiffness=shear_stiffness, bending=bending,
                      bend_stiffness=bend_stiffness, spring_damping=spring_damping,
                      pins=[0, nx], damping=damping, device=device, **model_options)


def hanging(*, solver: str = "explicit", solver_options: dict | None = None, fps: float = 60.0,
            frames: int = 120, substeps=None, corrections=(), obstacles=(),
            strain_bound: float = 10.0, self_collision: bool = True, **model_args) -> Scene:
    """A sheet hanging from two corners (the GAMES103 lab scene in real-cloth units).
    ``self_collision``: keep it from passing through itself (a `CollisionStage`)."""
    model = hanging_model(**model_args)
    return _finish(model, solver, solver_options, corrections, fps, frames, substeps, obstacles,
                   strain_bound, "hanging", self_collision=self_collision)


def flag(*, solver: str = "explicit", solver_options: dict | None = None, fps: float = 60.0,
         frames: int = 180, substeps=None, corrections=(), obstacles=(), res: int = 24, shape=None,
         size: float = 1.5, stiffness: float = DEFAULT_STRETCH_STIFFNESS,
         density: float = DEFAULT_DENSITY, wind_speed: float = 6.0, bending: str = "none",
         bend_stiffness: float = 0.0, damping: float = 0.1, strain_bound: float = 10.0,
         device=None, self_collision: bool = True, **model_options) -> Scene:
    """A flag ``size`` x ``2/3 size`` m pinned along its left edge (x = 0) in gusty wind along +x;
    ``self_collision`` as `hanging`."""
    from .forces.wind import Wind

    nx, ny = _grid_shape(res, shape) if shape is not None else (res, max(1, round(res * 2 / 3)))
    mesh = TriMesh.grid(nx, ny, size=(size, size * ny / nx), plane="xy", origin=(0.0, 1.0, 0.0),
                        name="flag")
    pins = [j * (nx + 1) for j in range(ny + 1)]
    wind = Wind(velocity=(wind_speed, 0.0, 0.15 * wind_speed))
    model = ClothModel(mesh, density=density, stretch_stiffness=stiffness, bending=bending,
                       bend_stiffness=bend_stiffness, pins=pins, damping=damping, wind=wind,
                       device=device, **model_options)
    return _finish(model, solver, solver_options, corrections, fps, frames, substeps, obstacles,
                   strain_bound, "flag", self_collision=self_collision)


SCENES = {"hanging": hanging, "flag": flag}


#: scenes whose builders live with the feature they need (imported on demand)
LAZY_SCENES = {
    "drape": "warp_cloth.contact_scenes",
    "table": "warp_cloth.contact_scenes",
    "spin": "warp_cloth.contact_scenes",
    "mesh": "warp_cloth.contact_scenes",
    "thin": "warp_cloth.contact_scenes",
    "fold": "warp_cloth.contact_scenes",
    "twist": "warp_cloth.contact_scenes",
    "stack": "warp_cloth.contact_scenes",
}


def build_scene(name: str, **kwargs) -> Scene:
    """Build a scene by name (``hanging``, ``flag``, and the contact scenes when available)."""
    if name not in SCENES and name in LAZY_SCENES:
        import importlib

        try:
            builder = getattr(importlib.import_module(LAZY_SCENES[name]), name)
        except (ImportError, AttributeError):
            raise ValueError(f"scene {name!r} is not available in this installation") from None
        return builder(**kwargs)
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; choose one of {sorted(SCENES)}")
    return SCENES[name](**kwargs)
