"""Solvers: one module per method, all ``solver = Method(model, **options)``,
``solver.step(state, dt)``.

=============  ==================================  ==========================================
name           class                               module
=============  ==================================  ==========================================
``explicit``   `SymplecticEuler`                   `warp_cloth.solvers.explicit`
``implicit``   `ImplicitEuler` (Newton)            `warp_cloth.solvers.implicit`
``pbd``        `PositionBased`                     `warp_cloth.solvers.pbd`
``pd``         `ProjectiveDynamics`                `warp_cloth.solvers.projective`
=============  ==================================  ==========================================

`make_solver` builds one by name; modules are imported only when asked for.
"""

from __future__ import annotations

import importlib
import inspect

from .base import Solver, check_dt

from ..registry import SOLVERS as _REGISTRY


def available() -> list[str]:
    """Names of the solvers that exist in this installation."""
    out = []
    for name, (mod, cls) in _REGISTRY.items():
        try:
            getattr(importlib.import_module(mod), cls)
            out.append(name)
        except (ImportError, AttributeError):
            pass
    return out


def solver_class(name: str):
    if name not in _REGISTRY:
        raise ValueError(f"unknown solver {name!r}; choose one of {available()}")
    mod, cls = _REGISTRY[name]
    try:
        return getattr(importlib.import_module(mod), cls)
    except (ImportError, AttributeError):
        raise ValueError(f"solver {name!r} is not available; choose one of {available()}") from None


def make_solver(name: str, model, **options) -> Solver:
    """Build the solver ``name`` on ``model``; unknown options raise `ValueError`."""
    cls = solver_class(name)
    params = inspect.signature(cls.__init__).parameters
    if not any(p.kind == p.VAR_KEYWORD for p in params.values()):
        unknown = sorted(set(options) - set(params))
        if unknown:
            valid = sorted(k for k in params if k not in ("self", "model"))
            raise ValueError(f"solver {name!r} has no option(s) {unknown}; valid: {valid}")
    return cls(model, **options)


__all__ = ["Solver", "check_dt", "make_solver", "solver_class", "available"]
