"""Wind: per-triangle aerodynamic drag and lift against the relative air velocity.

For a triangle of area A, unit normal n and centroid velocity v_t, with relative air velocity
``u = u_air(x, t) - v_t`` (so ``|u . n| = |u| |cos(theta)|``):

    drag  F_D = 1/2 rho A C_D |u . n| u                        (along the flow, scaled by the
                                                                projected area)
    lift  F_L = 1/2 rho A C_L |u| (u . n) (n - (n . u_hat) u_hat)  (across the flow, in the plane
                                                                of u and n)

each shared equally by the three vertices. Both vanish for a triangle edge-on to the flow. The
air velocity has travelling gusts, ``u_air = U (1 + a sin(2 pi (f t - (x . U_hat)/lambda)))``, so a
flag does not settle into a static pose. This is a thin-plate model in the spirit of
Keckeisen et al. 2004; the course notes only name wind as an external force (note 001).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..util import launch

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile


@wp.kernel
def wind_forces_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    tris: wp.array2d(dtype=wp.int32),
    time: wp.array(dtype=wp.float64),
    air_velocity: wp.vec3,
    half_rho: float,
    cd: float,
    cl: float,
    gust_amplitude: float,
    gust_frequency: float,
    gust_wavelength: float,
    f: wp.array(dtype=wp.vec3),
):
    t = wp.tid()
    i = tris[t, 0]
    j = tris[t, 1]
    k = tris[t, 2]
    xi = x[i]
    nvec = wp.cross(x[j] - xi, x[k] - xi)
    nl = wp.length(nvec)
    if nl < 1.0e-12:
        return
    n = nvec / nl
    area = 0.5 * nl
    c = (xi + x[j] + x[k]) / 3.0
    speed = wp.length(air_velocity)
    uair = air_velocity
    if speed > 0.0:
        phase = 2.0 * wp.pi * (gust_frequency * float(time[0]) - wp.dot(c, air_velocity / speed) / gust_wavelength)
        uair = air_velocity * (1.0 + gust_amplitude * wp.sin(phase))
    u = uair - (v[i] + v[j] + v[k]) / 3.0
    ul = wp.length(u)
    if ul < 1.0e-9:
        return
    un = wp.dot(u, n)
    uhat = u / ul
    drag = half_rho * area * cd * wp.abs(un) * u
    lift = half_rho * area * cl * ul * un * (n - wp.dot(n, uhat) * uhat)
    fv = (drag + lift) / 3.0
    wp.atomic_add(f, i, fv)
    wp.atomic_add(f, j, fv)
    wp.atomic_add(f, k, fv)


@dataclass
class Wind:
    """Wind parameters (SI units).

    Args:
        velocity: mean air velocity U in m/s.
        air_density: kg/m^3 (air at 20 C: 1.2).
        drag_coefficient: C_D of the thin-plate model.
        lift_coefficient: C_L.
        gust_amplitude: relative gust strength a (0 = steady wind).
        gust_frequency: Hz.
        gust_wavelength: m, the distance between gust fronts along the wind.
    """

    velocity: tuple = (5.0, 0.0, 0.0)
    air_density: float = 1.2
    drag_coefficient: float = 1.0
    lift_coefficient: float = 0.5
    gust_amplitude: float = 0.3
    gust_frequency: float = 1.5
    gust_wavelength: float = 1.5

    def __post_init__(self):
        u = np.asarray(self.velocity, dtype=np.float64).reshape(-1)
        if u.shape != (3,) or not np.all(np.isfinite(u)):
            raise ValueError(f"Wind.velocity must be 3 finite numbers, got {self.velocity}")
        if np.abs(u).max() > 1.0e6:  # (1e39 m/s passed and became inf on the device)
            raise ValueError(f"Wind.velocity must be within 1e6 m/s, got {self.velocity}")
        self.velocity = tuple(float(c) for c in u)
        for name in ("air_density", "drag_coefficient", "lift_coefficient", "gust_amplitude",
                     "gust_frequency"):
            val = float(getattr(self, name))
            if not (math.isfinite(val) and 0 <= val <= 1.0e12):
                raise ValueError(f"Wind.{name} must be finite, >= 0 and within 1e12, got {val}")
        if not (self.gust_wavelength > 0 and math.isfinite(self.gust_wavelength)):
            raise ValueError(f"Wind.gust_wavelength must be > 0, got {self.gust_wavelength}")

    def bind(self, model) -> "WindForce":
        return WindForce(self, model)


class WindForce:
    name = "wind"

    def __init__(self, wind: Wind, model):
        self.wind, self.model = wind, model

    def eval(self, x, v, f, time, **_):
        w, m = self.wind, self.model
        launch(
            wind_forces_kernel,
            m.num_triangles,
            [x, v, m.tri_indices, time, wp.vec3(*w.velocity), 0.5 * w.air_density,
             w.drag_coefficient, w.lift_coefficient, w.gust_amplitude, w.gust_frequency,
             w.gust_wavelength, f],
            device=m.device,
        )

    def energy(self, x, out):
        """Wind is not conservative: it contributes no potential energy."""
