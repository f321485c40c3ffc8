"""Obstacles and contact: rigid plane, sphere, box and triangle-mesh obstacles with scripted motion,
and the `ObstacleContact` correction (projection, continuous path test, impulse with restitution
and Coulomb friction) that every solver runs.

    from warp_cloth.collision import ObstacleContact, Sphere, Plane, Motion

    ball = Sphere(0.3, center=(0, 0.5, 0), motion=Motion(angular_velocity=(0, 2, 0), start=1.0))
    solver.add_correction(ObstacleContact(model, [ball, Plane()], friction=0.5))
    Scene(model, solver, obstacles=[ball, Plane()]).run("out.usd")

Modules: `motion` (scripted rigid motion), `obstacles` (shapes, USD), `contact` (the correction),
`analytic` and `mesh_contact` (the kernels, compiled only when used), `response` (the impulse),
`scenes` (``drape``, ``table``, ``spin``, ``mesh``). Self-collision is not part of this package.
"""

from .contact import (
    DEFAULT_FRICTION, DEFAULT_RESTITUTION, DEFAULT_THICKNESS, PENETRATION_TOLERANCE,
    ObstacleContact,
)
from .motion import KeyframePath, Motion, quat_from_axis_angle
from .obstacles import Box, MeshObstacle, Obstacle, Plane, Sphere

__all__ = [
    "ObstacleContact", "Obstacle", "Plane", "Sphere", "Box", "MeshObstacle", "Motion",
    "KeyframePath", "quat_from_axis_angle", "PENETRATION_TOLERANCE", "DEFAULT_THICKNESS",
    "DEFAULT_FRICTION", "DEFAULT_RESTITUTION",
]
