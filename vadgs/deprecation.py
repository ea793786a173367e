"""Names that moved to another module: the old import keeps working, with a ``DeprecationWarning``.

A module that used to re-export names defined elsewhere (issue 41: re-exports only in a package's
``__init__``) no longer binds them; :func:`moved_names` makes its module-level ``__getattr__``
(PEP 562), which returns such a name from its new place and says where that is::

    if not TYPE_CHECKING:  # mypy: the old names are gone (vadgs's own code imports the new places)
        __getattr__ = moved_names(__name__, {"ViewCache": "vadgs.train.vad.visibility"})
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["moved_names"]


def moved_names(module: str, moved: Mapping[str, str]) -> Callable[[str], Any]:
    """A module-level ``__getattr__`` for ``module`` whose names ``moved`` (name → the new module).

    The returned function gives a moved name from its new module with a ``DeprecationWarning``
    naming that module (the warning points at the importing line); any other name raises
    ``AttributeError`` as a module does.

    Example:
        >>> import warnings
        >>> getattr_ = moved_names("old.place", {"sqrt": "math"})
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     sqrt = getattr_("sqrt")
        >>> sqrt(4.0), str(caught[0].message)
        (2.0, 'old.place.sqrt moved: import it from math')
        >>> getattr_("cbrt")
        Traceback (most recent call last):
        ...
        AttributeError: module 'old.place' has no attribute 'cbrt'
    """
    table = dict(moved)

    def __getattr__(name: str) -> Any:
        if name in table:
            new = table[name]
            warnings.warn(f"{module}.{name} moved: import it from {new}", DeprecationWarning, stacklevel=2)
            return getattr(importlib.import_module(new), name)
        raise AttributeError(f"module {module!r} has no attribute {name!r}")

    return __getattr__
