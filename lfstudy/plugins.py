"""Classes other packages register under an entry-point group: flow kinds, reconstruction methods.

A plugin that fails to import, or that its registry's ``check`` refuses, is skipped with a
warning (as xarray's backend loader does), so one broken package does not stop every config
from loading.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from importlib.metadata import entry_points
from typing import Any

__all__ = ["load_plugins"]


def load_plugins(group: str, what: str, check: Callable[[str, Any], None]) -> tuple[dict[str, Any], dict[str, str]]:
    """Load every entry point of ``group``.

    Parameters
    ----------
    group : str
        The entry-point group (``lfstudy.flows``, ``lfstudy.reconstruction``).
    what : str
        What one plugin is, for the warning (``flow kind``, ``reconstruction method``).
    check : callable
        ``check(name, obj)`` raises for a loaded object its registry refuses.

    Returns
    -------
    found : dict
        ``{name: loaded object}``.
    skipped : dict
        ``{name: why it was skipped}``.
    """
    found: dict[str, Any] = {}
    skipped: dict[str, str] = {}
    for ep in entry_points(group=group):
        try:
            obj = ep.load()
            check(ep.name, obj)
        except Exception as exc:  # a third-party import may raise anything
            why = f"{type(exc).__name__}: {exc}"
            skipped[ep.name] = why
            warnings.warn(
                f"{what} {ep.name!r} (entry point {ep.value!r} of group {group!r}) is skipped, "
                f"it failed to load: {why}",
                RuntimeWarning,
                stacklevel=3,
            )
            continue
        found[ep.name] = obj
    return found, skipped
