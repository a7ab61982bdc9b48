"""The two defects of SMARTS 2.0.1 the backend runs into, each repaired only while it is still there.

- ``ViaSensor.__call__`` sorts the via points near the vehicle with ``key=lambda dist, _: dist``: a key takes
  one argument, so the sort raises ``TypeError`` as soon as a mission has a via point in range. The fix
  swaps that lambda's code for ``lambda point: point[0]`` in the method's constants; nothing else changes.
- ``smarts.env.utils.record`` (the GIF recorder) calls ``np.product``, gone in numpy 2. The fix gives that
  module (only it) a numpy whose ``product`` is ``prod``; numpy itself is left alone. The module imports
  OpenCV, which the extras do not install: without it the module cannot load and needs no fix.

SMARTS also calls TraCI's ``moveToXY`` with ``lane=``, which SUMO 1.28 has renamed: a ``UserWarning`` per
call (every step of every SUMO vehicle it places). It does what SMARTS means, so that one warning is
silenced (``MOVE_TO_XY_WARNING``); every other warning is left as it is.
"""

from __future__ import annotations

import types
import warnings
from typing import Any

import numpy as np

MOVE_TO_XY_WARNING = "Use of deprecated parameter lane in function moveToXY"
"""Start of the warning TraCI gives for SMARTS's ``moveToXY(..., lane=...)``."""


def _sort_key_by_distance(point: Any) -> Any:
    return point[0]


def via_sort_needs_fix(method: Any) -> bool:
    """Whether ``method`` (``ViaSensor.__call__``) makes a lambda of two arguments, the broken sort key."""
    return any(_two_argument_lambdas(method.__code__))


def _two_argument_lambdas(code: types.CodeType) -> list[types.CodeType]:
    return [
        c
        for c in code.co_consts
        if isinstance(c, types.CodeType) and c.co_name == "<lambda>" and c.co_argcount == 2
    ]


def fix_via_sort(sensor_class: type) -> bool:
    """Give ``sensor_class.__call__`` a one-argument sort key if it has the two-argument one.

    :return: whether the fix was applied
    """
    method = sensor_class.__call__
    if not via_sort_needs_fix(method):
        return False
    code = method.__code__
    key = _sort_key_by_distance.__code__
    constants = tuple(key if c in _two_argument_lambdas(code) else c for c in code.co_consts)
    method.__code__ = code.replace(co_consts=constants)
    return True


class _NumpyWithProduct(types.ModuleType):
    """numpy as seen by one module, with ``product`` (removed in numpy 2) back as ``prod``."""

    product = staticmethod(np.prod)

    def __getattr__(self, name: str) -> Any:
        return getattr(np, name)


def product_needs_fix(module: types.ModuleType) -> bool:
    """Whether ``module`` calls ``np.product`` on a numpy that no longer has it."""
    numpy = getattr(module, "np", None)
    return numpy is not None and not hasattr(numpy, "product") and "product" in _names_used(module)


def _names_used(module: types.ModuleType) -> set[str]:
    """Global and attribute names the functions and methods of ``module`` use."""
    values = list(vars(module).values())
    values += [member for value in values if isinstance(value, type) for member in vars(value).values()]
    stack = [code for value in values if isinstance(code := getattr(value, "__code__", None), types.CodeType)]
    names: set[str] = set()
    while stack:
        current = stack.pop()
        names.update(current.co_names)
        stack.extend(c for c in current.co_consts if isinstance(c, types.CodeType))
    return names


def fix_numpy_product(module: types.ModuleType) -> bool:
    """Give ``module`` a numpy with ``product`` if it calls it and numpy has none.

    :return: whether the fix was applied
    """
    if not product_needs_fix(module):
        return False
    module.np = _NumpyWithProduct("numpy")  # type: ignore[attr-defined]
    return True


def apply_fixes() -> dict[str, bool]:
    """Apply each fix still needed by the installed SMARTS; return which were applied (by name). Also
    silence the ``moveToXY`` warning (``MOVE_TO_XY_WARNING``)."""
    from smarts.core.sensor import ViaSensor

    warnings.filterwarnings("ignore", message=MOVE_TO_XY_WARNING, category=UserWarning)
    try:
        from smarts.env.utils import record
    except ImportError:  # it needs OpenCV, which no extra of SMARTS installs: then nothing can call it
        return {"via_sort": fix_via_sort(ViaSensor), "numpy_product": False}
    return {"via_sort": fix_via_sort(ViaSensor), "numpy_product": fix_numpy_product(record)}
