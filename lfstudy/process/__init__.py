"""Recorded plenoptic images → 3-D PIV (``lfstudy process``): no simulation, no known flow.

Modules: :mod:`~lfstudy.process.config` (the recording config, its schema
``process_schema.yaml`` built on the study schema's sections),
:mod:`~lfstudy.process.recording` (finding, checking and reading the frames),
:mod:`~lfstudy.process.pipeline` (calibration → registration → refocus →
reconstruction → PIV, through the case layer of a simulated study),
:mod:`~lfstudy.process.metrics` (what a measurement says about itself),
:mod:`~lfstudy.process.uncertainty_calibration` (σ scaled by what a simulated study measured) and
:mod:`~lfstudy.process.report` (the HTML report). Import from this package:
the modules behind it may move.
"""

from __future__ import annotations

from lfstudy.process.config import load_process_config, load_process_schema, validate_process_config
from lfstudy.process.metrics import divergence, pair_metrics, peak_ratio
from lfstudy.process.pipeline import calibrate_recording, open_result, process_recording
from lfstudy.process.recording import (
    Frame,
    Recording,
    RecordingError,
    SaturationWarning,
    open_recording,
    read_frame,
)
from lfstudy.process.uncertainty_calibration import (
    CalibrationError,
    UncertaintyCalibration,
    apply_calibration,
    fit_calibration,
    read_study,
)

__all__ = [
    "load_process_config",
    "validate_process_config",
    "load_process_schema",
    "RecordingError",
    "SaturationWarning",
    "Frame",
    "Recording",
    "open_recording",
    "read_frame",
    "calibrate_recording",
    "process_recording",
    "open_result",
    "peak_ratio",
    "divergence",
    "pair_metrics",
    "CalibrationError",
    "UncertaintyCalibration",
    "read_study",
    "fit_calibration",
    "apply_calibration",
]
