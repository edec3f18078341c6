"""Raw image → light field → focal stack (thesis ch. 5.1–5.4, 6.2).

Modules: :mod:`~lfstudy.lightfield.calibrate` (lenslet grid, sec. 5.1),
:mod:`~lfstudy.lightfield.registration` (4-D light field, eqs 5.2–5.9) and
:mod:`~lfstudy.lightfield.refocus` (focal stack, eqs 5.10–5.20, sec. 6.2).
Import from this package: the modules behind it may move.
"""

from __future__ import annotations

from lfstudy.lightfield.calibrate import (
    CalibrationError,
    expected_centers,
    find_lenslet_centers,
    lenslet_positions,
    pixel_to_sensor,
    synthetic_pinhole,
)
from lfstudy.lightfield.refocus import focal_stack
from lfstudy.lightfield.registration import RegistrationError, pixels_per_lenslet, register

__all__ = [
    "CalibrationError",
    "find_lenslet_centers",
    "expected_centers",
    "lenslet_positions",
    "synthetic_pinhole",
    "pixel_to_sensor",
    "RegistrationError",
    "register",
    "pixels_per_lenslet",
    "focal_stack",
]
