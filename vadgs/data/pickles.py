"""Reading gzip'd pickled pandas DataFrames (PandaSet's ``.pkl.gz``) without running their code.

A pickle may name any importable callable and call it while it loads (``os.system`` through
``__reduce__``), so :func:`read_pickled_dataframe` unpickles with :class:`RestrictedUnpickler`:
only the pandas and numpy classes that a DataFrame of numbers and strings needs
(:data:`PICKLE_ALLOWED`) are looked up; any other global is refused before it is imported, with
an error naming it. pandas is needed (``pip install 'vadgs[pandaset]'``).

Example:
    >>> import io, os, pickle  # doctest: +ELLIPSIS
    >>> class Evil:
    ...     def __reduce__(self):
    ...         return (os.getcwd, ())
    >>> RestrictedUnpickler(io.BytesIO(pickle.dumps(Evil()))).load()
    Traceback (most recent call last):
        ...
    _pickle.UnpicklingError: refused to load ...getcwd: not one of the pandas/numpy classes ...
"""

from __future__ import annotations

import gzip
import importlib
import pickle
import zlib
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["PICKLE_ALLOWED", "RestrictedUnpickler", "read_pickled_dataframe", "require_pandas"]

#: numpy 2 moved ``numpy.core`` to ``numpy._core`` (pickles of either name load on either).
_MULTIARRAY = "numpy._core.multiarray" if int(np.__version__.split(".")[0]) >= 2 else "numpy.core.multiarray"

#: The globals a pickled DataFrame of numbers, booleans and strings names (pandas 0.25 to 3, numpy
#: 1 and 2), as ``(module, name)``; the right-hand side is where the class lives today when
#: pandas moved it (as ``pandas.compat.pickle_compat`` maps it).
PICKLE_ALLOWED: dict[tuple[str, str], tuple[str, str]] = {
    ("builtins", "slice"): ("builtins", "slice"),
    ("numpy", "dtype"): ("numpy", "dtype"),
    ("numpy", "ndarray"): ("numpy", "ndarray"),
    ("numpy.core.multiarray", "_reconstruct"): (_MULTIARRAY, "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"): (_MULTIARRAY, "_reconstruct"),
    ("numpy.core.multiarray", "scalar"): (_MULTIARRAY, "scalar"),
    ("numpy._core.multiarray", "scalar"): (_MULTIARRAY, "scalar"),
    ("pandas.core.frame", "DataFrame"): ("pandas", "DataFrame"),
    ("pandas", "DataFrame"): ("pandas", "DataFrame"),
    ("pandas.core.indexes.base", "Index"): ("pandas", "Index"),
    ("pandas", "Index"): ("pandas", "Index"),
    ("pandas.core.indexes.base", "_new_Index"): ("pandas.core.indexes.base", "_new_Index"),
    ("pandas.core.indexes.range", "RangeIndex"): ("pandas", "RangeIndex"),
    ("pandas", "RangeIndex"): ("pandas", "RangeIndex"),
    ("pandas.core.indexes.numeric", "Int64Index"): ("pandas", "Index"),
    ("pandas.core.indexes.numeric", "UInt64Index"): ("pandas", "Index"),
    ("pandas.core.indexes.numeric", "Float64Index"): ("pandas", "Index"),
    ("pandas.core.internals.managers", "BlockManager"): ("pandas.core.internals.managers", "BlockManager"),
    ("pandas._libs.internals", "_unpickle_block"): ("pandas._libs.internals", "_unpickle_block"),
    ("pandas.core.internals.blocks", "new_block"): ("pandas._libs.internals", "_unpickle_block"),
}


def require_pandas(what: str) -> Any:
    """The ``pandas`` module, or an :class:`ImportError` of one line naming the extra to install."""
    try:
        import pandas
    except ImportError:
        raise ImportError(f"{what} needs pandas: pip install 'vadgs[pandaset]'") from None
    return pandas


class RestrictedUnpickler(pickle.Unpickler):
    """A :class:`pickle.Unpickler` that looks up only the globals of :data:`PICKLE_ALLOWED`.

    Anything else (``os.system``, ``builtins.eval``, ``subprocess.Popen``, another class) raises
    :class:`pickle.UnpicklingError` naming it, before its module is imported.
    """

    def find_class(self, module: str, name: str) -> Any:
        """The allowed global ``module.name``; any other is refused (see the class)."""
        target = PICKLE_ALLOWED.get((module, name))
        if target is None:
            raise pickle.UnpicklingError(
                f"refused to load {module}.{name}: not one of the pandas/numpy classes a DataFrame needs"
            )
        mod, attr = target
        return getattr(importlib.import_module(mod), attr)


def read_pickled_dataframe(path: Path, what: str, columns: tuple[str, ...] = ()) -> Any:
    """A gzip'd pickled pandas DataFrame, unpickled by :class:`RestrictedUnpickler`.

    Args:
        path: the ``.pkl.gz`` file.
        what: the file as the messages name it, e.g. ``"PandaSet LiDAR sweep"``.
        columns: the columns it must have.

    Returns:
        The :class:`pandas.DataFrame`.

    Raises:
        ImportError: without pandas (one line naming the ``pandaset`` extra).
        FileNotFoundError: ``"<what>: missing file <path>"``.
        ValueError: ``"<what> <path>: ..."`` when the file is not gzip, is cut short, names a
            global that is not allowed, is not a DataFrame or lacks a column.
    """
    pd = require_pandas(what)
    if not path.is_file():
        raise FileNotFoundError(f"{what}: missing file {path}")
    try:
        with gzip.open(path, "rb") as f:
            df = RestrictedUnpickler(f).load()
    except pickle.UnpicklingError as e:
        raise ValueError(f"{what} {path}: {e}") from None
    except (OSError, EOFError, zlib.error) as e:  # gzip.BadGzipFile is an OSError
        raise ValueError(f"{what} {path}: not a complete gzip'd pickle ({type(e).__name__}: {e})") from None
    except Exception as e:  # a malformed pickle fails inside pandas or numpy with anything
        raise ValueError(f"{what} {path}: not a pickled DataFrame ({type(e).__name__}: {e})") from None
    if not isinstance(df, pd.DataFrame):
        raise ValueError(f"{what} {path}: expected a pickled pandas DataFrame, got {type(df).__name__}")
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"{what} {path}: missing column(s) {missing}, have {[str(c) for c in df.columns]}")
    return df
