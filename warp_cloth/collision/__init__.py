"""The collision layer (below the solvers: nothing here imports `warp_cloth.solvers`): rigid
plane, sphere, box and triangle-mesh obstacles with scripted motion, the `CollisionStage` that
owns every contact source of a scene and its `ContactRecord`, and the geometry they share.

    from warp_cloth.collision import CollisionStage, Sphere, Plane, Motion

    ball = Sphere(0.3, center=(0, 0.5, 0), motion=Motion(angular_velocity=(0, 2, 0), start=1.0))
    stage = CollisionStage(model, [ball, Plane()], friction=0.5)
    solver = make_solver("implicit", model, collision=stage)
    Scene(model, solver).run("out.usd")      # obstacles given once: simulated and drawn

Modules: `stage` (`CollisionStage`), `record` (the contact record), `contact`
(`ObstacleContact`: detection and response against obstacles), `geometry` (closest points,
distances and continuous tests shared by every contact source), `motion` (scripted rigid
motion), `obstacles` (shapes, USD), `analytic` and `mesh_contact` (the kernels, compiled only
when used), `planes` (contact planes), `response` (the impulse).
"""

from .contact import (
    DEFAULT_FRICTION, DEFAULT_RESTITUTION, DEFAULT_THICKNESS, PENETRATION_TOLERANCE,
    ObstacleContact,
)
from .motion import KeyframePath, Motion, quat_from_axis_angle
from .obstacles import Box, MeshObstacle, Obstacle, Plane, Sphere
from .record import ContactRecord
from .stage import CollisionStage

__all__ = [
    "CollisionStage", "ContactRecord", "ObstacleContact", "Obstacle", "Plane", "Sphere", "Box", "MeshObstacle", "Motion",
    "KeyframePath", "quat_from_axis_angle", "PENETRATION_TOLERANCE", "DEFAULT_THICKNESS",
    "DEFAULT_FRICTION", "DEFAULT_RESTITUTION",
]
