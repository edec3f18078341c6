"""The registry of volume reconstruction methods (thesis sec. 5.5–5.6).

Reconstructions (MART, 3-D deconvolution, sec. 5.6) plug in by name::

    @register_method("mart")
    def mart(stack, **kw) -> xr.DataArray: ...

    reconstruct(stack, method="mart", iterations=5)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import xarray as xr

__all__ = ["reconstruct", "register_method", "available_methods"]

_METHODS: dict[str, Callable[..., xr.DataArray]] = {}


def register_method(name: str) -> Callable[[Callable[..., xr.DataArray]], Callable[..., xr.DataArray]]:
    """Decorator registering ``func(stack, **kw) -> DataArray`` as reconstruction ``name``."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"reconstruction method name must be a non-empty string, got {name!r}")

    def deco(func: Callable[..., xr.DataArray]) -> Callable[..., xr.DataArray]:
        _METHODS[name] = func
        return func

    return deco


def available_methods() -> list[str]:
    """Names accepted by :func:`reconstruct`, sorted."""
    return sorted(_METHODS)


def reconstruct(stack: xr.DataArray, method: str = "threshold", **kwargs: Any) -> xr.DataArray:
    """Reconstruct a particle volume from a focal stack with a registered method.

    Parameters
    ----------
    stack : xarray.DataArray
        Focal stack, dims ``("z", "y", "x")`` (see :func:`lfstudy.lightfield.refocus.focal_stack`).
    method : str
        A name from :func:`available_methods` (default ``"threshold"``).
    **kwargs
        Passed to the method.

    Returns
    -------
    xarray.DataArray
        The volume with the stack's dims and coords, one dask chunk per plane.

    Raises
    ------
    ValueError
        Unknown method (the message lists the available ones).
    """
    try:
        func = _METHODS[method]
    except KeyError:
        raise ValueError(
            f"unknown reconstruction method {method!r}; available: {', '.join(available_methods())}"
        ) from None
    if not isinstance(stack, xr.DataArray) or stack.ndim != 3:
        raise ValueError("stack must be a 3-D DataArray with dims ('z', 'y', 'x')")
    return func(stack, **kwargs)
