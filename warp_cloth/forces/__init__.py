"""Force terms: springs (always), wind, dihedral and quadratic bending (each its own Warp module).

A force term is bound to a `ClothModel` and offers:

- ``eval(x, v, f, time)``: scatter its forces (N) into ``f`` with atomics;
- ``energy(x, out)``: add its potential energy (J) to ``out[0]`` (0 for non-conservative terms).

Terms used by the implicit solvers also offer ``add_hessian_diag`` / ``hessian_product`` (see each
module).
"""
