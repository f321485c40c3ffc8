"""The solvers by name: ``name -> (module, class)``. A module of its own that imports nothing,
so that a sweep's driver can check solver names without loading Warp
(`warp_cloth.solvers.available` imports each module to say which exist)."""

SOLVERS = {
    "explicit": ("warp_cloth.solvers.explicit", "SymplecticEuler"),
    "implicit": ("warp_cloth.solvers.implicit", "ImplicitEuler"),
    "pbd": ("warp_cloth.solvers.pbd", "PositionBased"),
    "pd": ("warp_cloth.solvers.projective", "ProjectiveDynamics"),
}
