"""Classes other packages register under an entry-point group: flow kinds, reconstruction methods.

One loader and one rule for both registries (:mod:`lfstudy.simulate.flows`, group
``lfstudy.flows``; :mod:`lfstudy.reconstruct`, group ``lfstudy.reconstruct``):

* an entry point that fails to import, or that its registry's ``check`` refuses, is skipped
  with a warning naming it (as xarray's backend loader does), so one broken package does not
  stop every config from loading;
* an entry point whose name is a built-in's is skipped with a warning too, without importing
  it: a config that names a built-in gets the built-in, whatever is installed. (At run time
  :func:`lfstudy.reconstruct.register_method` replaces a built-in only when asked to,
  ``replace=True``.)
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Collection
from importlib.metadata import entry_points
from typing import Any

__all__ = ["load_plugins"]


def load_plugins(
    group: str, what: str, check: Callable[[str, Any], None], builtin: Collection[str] = ()
) -> tuple[dict[str, Any], dict[str, str]]:
    """Load every entry point of ``group``.

    Parameters
    ----------
    group : str
        The entry-point group (``lfstudy.flows``, ``lfstudy.reconstruct``).
    what : str
        What one plugin is, for the warning (``flow kind``, ``reconstruction method``).
    check : callable
        ``check(name, obj)`` raises for a loaded object its registry refuses.
    builtin : collection of str
        The registry's built-in names: an entry point of one of them is skipped (not loaded).

    Returns
    -------
    found : dict
        ``{name: loaded object}``.
    skipped : dict
        ``{name: why it was skipped}`` (a built-in's name stays the built-in's: it is not listed).

    Warns
    -----
    RuntimeWarning
        For each entry point skipped, naming it, its target and why.
    """
    found: dict[str, Any] = {}
    skipped: dict[str, str] = {}
    for ep in entry_points(group=group):
        where = f"{what} {ep.name!r} (entry point {ep.value!r} of group {group!r})"
        if ep.name in builtin:
            warnings.warn(
                f"{where} is skipped: {ep.name!r} is a built-in {what}, which a plugin cannot replace; "
                "give the entry point another name",
                RuntimeWarning,
                stacklevel=3,
            )
            continue
        try:
            obj = ep.load()
            check(ep.name, obj)
        except Exception as exc:  # a third-party import may raise anything
            why = f"{type(exc).__name__}: {exc}"
            skipped[ep.name] = why
            warnings.warn(f"{where} is skipped, it failed to load: {why}", RuntimeWarning, stacklevel=3)
            continue
        found[ep.name] = obj
    return found, skipped
