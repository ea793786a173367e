"""What a training loop's ``info`` must carry for a strategy, checked at the first steps.

Each base strategy declares the keys its step methods read: vadgs's strategies by a method
``info_keys(packed)`` (:meth:`~vadgs.train.strategy.DefaultStrategy.info_keys`), gsplat's (which
vadgs cannot edit) in the table :data:`FOREIGN_INFO_KEYS`. :func:`info_requirements` reads the
declaration; :func:`check_info` names a missing key in one line (instead of a ``KeyError`` deep in
the base); :func:`check_info_values` checks the values
:class:`~vadgs.train.vad.VisibilityAwareDensification` itself reads (``view``, the image size, a
render's ``depth`` / ``alpha``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch

from vadgs.checks import check_size, int_field
from vadgs.train.strategy.default import GSPLAT_META

__all__ = ["FOREIGN_INFO_KEYS", "check_info", "check_info_values", "info_requirements"]


def _gsplat_default(base: Any, packed: bool) -> list[dict[str, str]]:
    """Gsplat's ``DefaultStrategy``: its ``key_for_gradient``, the image size, ``radii``, ``gaussian_ids``."""
    keys = (base.key_for_gradient, "width", "height", "n_cameras", "radii")
    req = dict.fromkeys(keys, GSPLAT_META)
    req["gaussian_ids"] = GSPLAT_META + (" with packed=True" if packed else " (None when packed=False)")
    return [req]


def _reads_nothing(base: Any, packed: bool) -> list[dict[str, str]]:
    return []


FOREIGN_INFO_KEYS: dict[str, Callable[[Any, bool], list[dict[str, str]]]] = {
    "gsplat.strategy.default.DefaultStrategy": _gsplat_default,
    "gsplat.strategy.mcmc.MCMCStrategy": _reads_nothing,  # it takes lr=, reads no info
}
"""What the strategies of other libraries read from ``info``: the class's ``module.qualname`` (gsplat
need not be imported to look it up; a subclass finds its base's entry) → ``(strategy, packed) ->``
alternatives of ``{key: where it comes from}``, as a vadgs strategy's ``info_keys`` returns."""


def info_requirements(base: Any, packed: bool = False) -> list[dict[str, str]]:
    """What a base strategy reads from the loop's ``info``: alternatives of ``{key: where it comes from}``.

    The strategy's own declaration (``info_keys(packed)``, vadgs's strategies), else the entry of
    :data:`FOREIGN_INFO_KEYS` of its class or the nearest base class that has one (gsplat's
    ``DefaultStrategy``: its ``key_for_gradient`` (``means2d``), ``width``, ``height``,
    ``n_cameras``, ``radii`` and ``gaussian_ids`` (None unless ``packed``); gsplat's
    ``MCMCStrategy``: nothing, it takes ``lr=``). A strategy that declares nothing: nothing is
    known (an empty list), nothing is checked.

    Example:
        >>> from vadgs.train.strategy import DefaultStrategy
        >>> [sorted(a) for a in info_requirements(DefaultStrategy())]
        [['image_size', 'raster'], ['height', 'means2d', 'radii', 'width']]
        >>> info_requirements(object())
        []
    """
    declared = getattr(base, "info_keys", None)
    if callable(declared):
        return declared(packed)
    for cls in type(base).__mro__:
        read = FOREIGN_INFO_KEYS.get(f"{cls.__module__}.{cls.__qualname__}")
        if read is not None:
            return read(base, packed)
    return []


def check_info(base: Any, info: Mapping[str, Any], packed: bool = False) -> None:
    """Check the loop's ``info`` against what ``base`` reads (:func:`info_requirements`).

    Raises:
        ValueError: naming the missing key, the base that reads it and where it comes from.
    """
    alternatives = info_requirements(base, packed)
    if not alternatives:
        return
    if not isinstance(info, Mapping):
        raise ValueError(f"info: expected a dict (the renderer's meta), got {type(info).__name__}")
    missing = [[k for k in alt if k not in info] for alt in alternatives]
    if any(not m for m in missing):
        if packed and info.get("gaussian_ids", 0) is None and "gaussian_ids" in alternatives[-1]:
            raise ValueError(
                "info['gaussian_ids']: expected the ids of gsplat's rasterization(packed=True) with "
                "packed=True, got None"
            )
        return
    best = min(range(len(missing)), key=lambda i: (len(missing[i]) - len(alternatives[i]), len(missing[i])))
    key = missing[best][0]
    name = f"{type(base).__module__.split('.')[0]}'s {type(base).__name__}"
    raise ValueError(
        f"info: expected key {key!r} (read by {name}; from {alternatives[best][key]}), "
        f"got keys {sorted(info)}"
    )


def check_info_values(info: Mapping[str, Any], num_views: int | None) -> None:
    """Check the values ``info`` carries for the strategy: metadata only (no tensor value is read).

    ``view`` an integer in ``[0, num_views)`` (when known), ``image_size`` a positive ``(H, W)``,
    ``width`` / ``height`` positive integers, and the render's ``depth`` / ``alpha`` (of
    ``info["raster"]`` or ``info``) tensors of shape ``(1, H, W)``, ``(H, W)`` or ``(1, 1, H, W)``
    of one ``(H, W)``, that of ``image_size`` or ``height``, ``width`` when given.

    Raises:
        ValueError: naming the key, the expected and the actual value or shape.
    """
    if not isinstance(info, Mapping):
        return  # check_info names it when the base reads info; otherwise nothing is read
    view = info.get("view")
    if view is not None:
        hi = None if num_views is None else num_views - 1
        note = "" if num_views is None else f" (a view of the inputs' {num_views})"
        int_field(0, hi, note=note)("info['view']", view)
    size = None
    if info.get("image_size") is not None:
        size = check_size(info["image_size"], "info['image_size']")
    for key in ("height", "width"):
        if info.get(key) is not None:
            int_field(1)(f"info[{key!r}]", info[key])
    if size is None and info.get("height") is not None and info.get("width") is not None:
        size = (int(info["height"]), int(info["width"]))
    raster = info.get("raster")
    maps = {}
    for key in ("depth", "alpha"):
        name, value = f"info[{key!r}]", info.get(key)
        if raster is not None:
            name, value = f"info['raster'].{key}", getattr(raster, key, None)
        if value is None:
            continue
        if not isinstance(value, torch.Tensor):
            raise ValueError(
                f"{name}: expected a torch.Tensor (the view's rendered {key}), got {type(value).__name__}"
            )
        shape = tuple(value.shape)
        ok = (
            (len(shape) == 2)
            or (len(shape) == 3 and shape[0] == 1)
            or (len(shape) == 4 and shape[:2] == (1, 1))
        )
        hw = shape[-2:]
        want = (
            "(1, H, W), (H, W) or (1, 1, H, W)"
            if size is None
            else f"(1, {size[0]}, {size[1]}) or (H, W) = {size}"
        )
        if not ok or (size is not None and hw != size):
            raise ValueError(f"{name}: expected the view's {key} of shape {want}, got {shape}")
        maps[name] = hw
    if len(set(maps.values())) > 1:
        (a, ha), (b, hb) = maps.items()
        raise ValueError(f"{a}, {b}: expected maps of one size (H, W), got {ha} and {hb}")
