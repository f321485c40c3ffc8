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
import numbers

import numpy as np

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


def _check_option_types(name: str, params, options) -> None:
    """Each option of the type its default says (a bool where the default is a bool, an integer
    where it is an int, a real number where it is a float; None passes where the solver may
    take it): the solvers' own checks then compare numbers. Before, ``tolerance="1e-4"`` raised
    "must be real number, not str", ``iterations=float("nan")`` "cannot convert float NaN to
    integer", ``line_search="no"`` turned into True and ``newton_iterations=True`` into 1, none
    naming the option."""
    from ..util import check_number

    for key, value in options.items():
        p = params.get(key)
        if p is None or p.default is inspect.Parameter.empty or value is None:
            continue
        d = p.default
        where = f"{name}: option {key!r}"
        if isinstance(d, (bool, np.bool_)):
            if not isinstance(value, (bool, np.bool_)):
                raise ValueError(f"{where} must be True or False, got {value!r}")
        elif isinstance(d, numbers.Real):
            check_number(value, where, integer=isinstance(d, numbers.Integral))


def make_solver(name: str, model, **options) -> Solver:
    """Build the solver ``name`` on ``model``; unknown options raise `ValueError`, options of
    the wrong type (by their defaults') `ValueError` too, each naming the option."""
    cls = solver_class(name)
    params = inspect.signature(cls.__init__).parameters
    if not any(p.kind == p.VAR_KEYWORD for p in params.values()):
        unknown = sorted(set(options) - set(params))
        if unknown:
            valid = sorted(k for k in params if k not in ("self", "model"))
            raise ValueError(f"solver {name!r} has no option(s) {unknown}; valid: {valid}")
    from ..util import check_model

    check_model(model, f"make_solver({name!r}, model)")
    _check_option_types(name, params, options)
    return cls(model, **options)


__all__ = ["Solver", "check_dt", "make_solver", "solver_class", "available"]
