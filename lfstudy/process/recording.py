"""Recorded plenoptic frames: find them, check them, read them (dark-corrected).

A recording is a calibration image (pinhole or white, sec. 5.1), optional dark
frames and the particle frames: independent pairs, or a time series processed
as the pairs 1–2, 2–3, … Frames are TIFF files (8-, 12-, 16-bit integers, or
float), one per file or several pages of one file.

:func:`open_recording` reads only the TIFF headers and refuses, before any pixel
is processed, frames of different size or bit depth and frames whose size is
not the camera's sensor; :func:`read_frame` reads one frame, subtracts the mean
dark frame (clipped at 0) and reports the fraction of saturated pixels (at full
scale, ``2**bit_depth - 1``). Every error is one :class:`RecordingError` line
naming the config key and the file.
"""

from __future__ import annotations

import glob
import math
import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

__all__ = [
    "RecordingError",
    "SaturationWarning",
    "Frame",
    "TiffInfo",
    "Recording",
    "tiff_info",
    "expand_frames",
    "recording_files",
    "open_recording",
    "mean_dark",
    "read_frame",
    "warn_saturated",
    "frame_dir",
]

_TAG_MAX_SAMPLE_VALUE = 281  # TIFF baseline MaxSampleValue


class RecordingError(ValueError):
    """A recording that cannot be processed (the message names the config key and the file)."""


class SaturationWarning(UserWarning):
    """Frames with pixels at full scale: intensities there are clipped, particle centres biased."""


def frame_dir(k: int) -> str:
    """Directory (relative to the output) of frame ``k``'s light field, stack and volume."""
    return f"frames/{k:03d}"


@dataclass(frozen=True)
class Frame:
    """One image: a page of a TIFF file."""

    path: Path
    page: int = 0
    n_pages: int = 1

    @property
    def label(self) -> str:
        """The file name, with the page when the file holds several."""
        return self.path.name if self.n_pages == 1 else f"{self.path.name} (page {self.page + 1} of {self.n_pages})"


@dataclass(frozen=True)
class TiffInfo:
    """What a TIFF's header says: pages, page size, sample type and significant bits."""

    path: Path
    n_pages: int
    rows: int
    cols: int
    dtype: np.dtype
    bits: int

    @property
    def depth(self) -> str:
        """``"12-bit (uint16)"``, ``"32-bit float"``."""
        if self.dtype.kind == "f":
            return f"{self.bits}-bit float"
        return f"{self.bits}-bit ({self.dtype.name})"

    @property
    def size(self) -> str:
        """``"384 x 384 px (cols x rows)"``."""
        return f"{self.cols} x {self.rows} px (cols x rows)"


def _unreadable(path: Path, exc: Exception) -> RecordingError:
    return RecordingError(f"image file {str(path)!r} cannot be read as a TIFF image ({exc}): truncated or not a TIFF")


def tiff_info(path: str | Path, *, key: str = "recording", bit_depth: int | None = None) -> TiffInfo:
    """Read a TIFF's header (no pixel data).

    Parameters
    ----------
    path : path
        The file.
    key : str
        The config key it comes from, for the messages.
    bit_depth : int, optional
        Significant bits (``recording.bit_depth``); default the MaxSampleValue
        tag if present, else BitsPerSample.

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    RecordingError
        Unreadable, not grayscale, or ``bit_depth`` beyond the sample type.
    """
    import tifffile

    path = Path(path)
    if path.is_dir():
        raise RecordingError(f"{key}: {str(path)!r} is a folder, not an image file; name the TIFF files in it")
    if not path.is_file():
        raise FileNotFoundError(f"{key}: image file {str(path)!r} does not exist")
    try:
        with tifffile.TiffFile(path) as tf:
            pages = tf.pages
            n = len(pages)
            if n == 0:
                raise RecordingError(f"{key}: image file {str(path)!r} holds no image")
            p = pages.first
            shape, dtype = tuple(p.shape), np.dtype(p.dtype)
            bps = int(p.bitspersample)
            tag = p.tags.get(_TAG_MAX_SAMPLE_VALUE)
            max_value = int(tag.value) if tag is not None and np.ndim(tag.value) == 0 else None
    except RecordingError:
        raise
    except Exception as exc:  # tifffile's errors for truncated or foreign files
        raise _unreadable(path, exc) from None
    if len(shape) != 2:
        raise RecordingError(
            f"{key}: image file {str(path)!r} has pages of shape {shape}; a plenoptic frame is one grayscale "
            "image (rows, cols)"
        )
    if dtype.kind not in "uif":
        raise RecordingError(f"{key}: image file {str(path)!r} holds {dtype} pixels; expected integers or floats")
    container = 8 * dtype.itemsize
    if bit_depth is not None:
        if dtype.kind == "f" or bit_depth > container:
            raise RecordingError(
                f"config key 'recording.bit_depth' = {bit_depth}: {str(path)!r} holds {dtype} pixels; allowed "
                f"range is [1, {container}]"
                if dtype.kind != "f"
                else f"config key 'recording.bit_depth' = {bit_depth}: {str(path)!r} holds float pixels "
                "(no bit depth); drop the key"
            )
        bits = int(bit_depth)
    elif dtype.kind != "f" and max_value is not None and 0 < max_value < 2**container - 1:
        bits = max(1, math.ceil(math.log2(max_value + 1)))
    else:
        bits = bps if dtype.kind != "f" else container
    return TiffInfo(path, n, int(shape[0]), int(shape[1]), dtype, bits)


def _natural(path: str) -> list[Any]:
    """Sort key: frame_2 before frame_10."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path)]


def expand_frames(spec: str | Sequence[str], *, key: str, bit_depth: int | None = None) -> list[Frame]:
    """The frames of a path, a glob, a multi-page file or a list of them, in order.

    A glob matches in natural order (``frame_2`` before ``frame_10``); every page of
    a multi-page file is a frame.

    Raises
    ------
    RecordingError
        A glob that matches nothing.
    FileNotFoundError
        A file that does not exist.
    """
    paths: list[str] = []
    for item in [spec] if isinstance(spec, str) else list(spec):
        if glob.has_magic(item):
            hits = sorted(glob.glob(item), key=_natural)
            if not hits:
                raise RecordingError(f"{key}: no file matches {item!r}")
            paths += hits
        else:
            paths.append(item)
    frames = []
    for p in paths:
        info = tiff_info(p, key=key, bit_depth=bit_depth)
        frames += [Frame(Path(p), k, info.n_pages) for k in range(info.n_pages)]
    return frames


def recording_files(rec: Mapping[str, Any]) -> list[str]:
    """Every file a ``recording`` section names (globs expanded, no header read), in order.

    For a workflow's input list; a glob that matches nothing contributes nothing (the
    processing then says so).
    """
    fr = rec["frames"]
    items: list[str] = [rec["calibration"]["image"], *([rec["dark"]] if isinstance(rec["dark"], str) else rec["dark"])]
    for spec in fr.get("pairs", []) + ([fr["series"]] if "series" in fr else []):
        items += [spec] if isinstance(spec, str) else list(spec)
    for section in ("depth_calibration", "volumetric_calibration"):
        if section in rec:
            imgs = rec[section]["images"]
            items += [imgs] if isinstance(imgs, str) else list(imgs)
    out: list[str] = []
    for item in items:
        for p in sorted(glob.glob(item), key=_natural) if glob.has_magic(item) else [item]:
            if p not in out:
                out.append(p)
    return out


@dataclass(frozen=True)
class Recording:
    """A checked recording: where its images are and what they hold.

    Attributes
    ----------
    calibration : Frame
        The calibration image; ``calibration_kind`` is ``"pinhole"`` or ``"white"``.
    dark : list of Frame
        Dark frames (may be empty).
    frames : list of Frame
        The particle frames, in order.
    pairs : list of (int, int)
        Indices into ``frames`` of each pair, in order.
    series : bool
        True for a time series (pairs 1–2, 2–3, …), False for independent pairs.
    rows, cols : int
        Frame size [px].
    dtype : numpy.dtype
        Sample type of the frames.
    bit_depth : int
        Significant bits of the frames (for integers: full scale is ``2**bit_depth - 1``).
    dt : float or None
        Time between the frames of a pair [s].
    max_saturated : float
        Saturated fraction of a frame above which :func:`warn_saturated` warns.
    depth_frames : list of Frame
        The recorded traverse of the depth calibration: start image, then one
        per traverse (empty: none given).
    depth_shifts : list of float
        Traverse of each later depth-calibration image from the start [mm].
    volcal_frames : list of Frame
        The dot-target images of the volumetric calibration, one per depth (empty: none given).
    volcal_depths : list of float
        The card's depth in each dot-target image [mm].
    """

    calibration: Frame
    calibration_kind: str
    dark: list[Frame]
    frames: list[Frame]
    pairs: list[tuple[int, int]]
    series: bool
    rows: int
    cols: int
    dtype: np.dtype
    bit_depth: int
    dt: float | None
    max_saturated: float
    depth_frames: list[Frame] = field(default_factory=list)
    depth_shifts: list[float] = field(default_factory=list)
    volcal_frames: list[Frame] = field(default_factory=list)
    volcal_depths: list[float] = field(default_factory=list)

    @property
    def full_scale(self) -> float | None:
        """The saturation level of integer frames, ``2**bit_depth - 1``; None for float frames."""
        return None if self.dtype.kind == "f" else float(2**self.bit_depth - 1)

    @property
    def pair_dim(self) -> str:
        """Dimension along which the pairs' results are combined: ``time`` (series) or ``pair``."""
        return "time" if self.series else "pair"

    def summary(self) -> dict[str, Any]:
        """Plain facts for the report and the stores' attrs."""
        return {
            "calibration": str(self.calibration.path),
            "calibration_kind": self.calibration_kind,
            "dark_frames": len(self.dark),
            "frames": len(self.frames),
            "pairs": len(self.pairs),
            "kind": "series" if self.series else "pairs",
            "sensor_px": f"{self.cols} x {self.rows}",
            "bit_depth": self.bit_depth,
            "dtype": self.dtype.name,
            "dt_s": self.dt,
            "depth_calibration_images": len(self.depth_frames),
            "volumetric_calibration_images": len(self.volcal_frames),
        }


def _same(infos: list[tuple[str, TiffInfo]], key: str, *, depth: bool = True) -> None:
    first_label, first = infos[0]
    for label, info in infos[1:]:
        if (info.rows, info.cols) != (first.rows, first.cols):
            raise RecordingError(
                f"{key}: frames differ in size: {first_label!r} is {first.size}, {label!r} is {info.size}"
            )
        if depth and (info.dtype != first.dtype or info.bits != first.bits):
            raise RecordingError(
                f"{key}: frames differ in bit depth: {first_label!r} is {first.depth}, {label!r} is {info.depth}"
            )


def open_recording(rec: Mapping[str, Any], camera: Any) -> Recording:
    """Find and check every image of a recording config (headers only; no pixel is read).

    Parameters
    ----------
    rec : mapping
        The validated ``recording`` section, paths absolute
        (:func:`lfstudy.process.config.validate_process_config`).
    camera : PlenopticCamera
        The camera description: the frames must have its sensor's size.

    Raises
    ------
    RecordingError
        Frames (or dark frames) of different size or bit depth, a calibration
        image or frames whose size is not the sensor's, a series of fewer than
        two frames, a pair that is not two frames, an unreadable file.
    FileNotFoundError
        A file that does not exist.
    """
    bd = rec.get("bit_depth")
    fr = rec["frames"]
    if "series" in fr:
        frames = expand_frames(fr["series"], key="recording.frames.series", bit_depth=bd)
        if len(frames) < 2:
            raise RecordingError(
                f"recording.frames.series: {len(frames)} frame found ({frames[0].label!r}); a series needs at least 2"
            )
        pairs = [(i, i + 1) for i in range(len(frames) - 1)]
        series = True
    else:
        frames, pairs = [], []
        for k, item in enumerate(fr["pairs"]):
            got = expand_frames(item, key=f"recording.frames.pairs[{k}]", bit_depth=bd)
            if len(got) != 2:
                raise RecordingError(
                    f"recording.frames.pairs[{k}]: {len(got)} frames ({', '.join(f.label for f in got)}); a pair is "
                    "two frames (two files, or one two-page TIFF)"
                )
            pairs.append((len(frames), len(frames) + 1))
            frames += got
        series = False
    key = "recording.frames"
    infos = {f.path: tiff_info(f.path, key=key, bit_depth=bd) for f in frames}
    _same([(f.label, infos[f.path]) for f in frames], key)
    first = infos[frames[0].path]
    n_x, n_y = camera.n_pixels_x, camera.n_pixels_y
    if (first.cols, first.rows) != (n_x, n_y):
        raise RecordingError(
            f"{key}: the frames are {first.size} but camera.sensor is {n_x} x {n_y} px (n_pixels_x x n_pixels_y): "
            "wrong camera description, or a cropped or binned recording"
        )
    dark = expand_frames(rec.get("dark") or [], key="recording.dark", bit_depth=bd)
    if dark:
        dinfo = [(d.label, tiff_info(d.path, key="recording.dark", bit_depth=bd)) for d in dark]
        _same([(frames[0].label, first), *dinfo], "recording.dark")
    calib = Frame(Path(rec["calibration"]["image"]))
    cinfo = tiff_info(calib.path, key="recording.calibration.image", bit_depth=bd if dark else None)
    if (cinfo.rows, cinfo.cols) != (first.rows, first.cols):
        raise RecordingError(
            f"recording.calibration.image: {calib.path.name!r} is {cinfo.size} but the frames and "
            f"camera.sensor are {n_x} x {n_y} px"
        )
    if dark and (cinfo.dtype != first.dtype or cinfo.bits != first.bits):
        # the mean dark frame is subtracted from the calibration image too: same camera, same scale
        raise RecordingError(
            f"recording.calibration.image: {calib.path.name!r} is {cinfo.depth} but the frames and dark frames "
            f"are {first.depth}; the dark frames are subtracted from it"
        )
    calib = Frame(calib.path, 0, cinfo.n_pages)
    depth_frames, depth_shifts = [], []
    if rec.get("depth_calibration"):
        dc = rec["depth_calibration"]
        key = "recording.depth_calibration.images"
        depth_frames = expand_frames(dc["images"], key=key, bit_depth=bd)
        depth_shifts = [float(s) for s in dc["shifts"]]
        if len(depth_frames) != len(depth_shifts) + 1:
            raise RecordingError(
                f"{key}: {len(depth_frames)} images for {len(depth_shifts)} traverses in "
                "recording.depth_calibration.shifts; give the start image and one image per traverse"
            )
        _same(
            [(frames[0].label, first), *((f.label, tiff_info(f.path, key=key, bit_depth=bd)) for f in depth_frames)],
            key,
        )
    volcal_frames, volcal_depths = [], []
    if rec.get("volumetric_calibration"):
        vc = rec["volumetric_calibration"]
        key = "recording.volumetric_calibration.images"
        volcal_frames = expand_frames(vc["images"], key=key, bit_depth=bd)
        volcal_depths = [float(z) for z in vc["depths"]]
        if len(volcal_frames) != len(volcal_depths):
            raise RecordingError(
                f"{key}: {len(volcal_frames)} images for {len(volcal_depths)} depths in "
                "recording.volumetric_calibration.depths; give one image per depth, in the same order"
            )
        # dark frames are subtracted from these too: same size and scale as the frames
        _same(
            [(frames[0].label, first), *((f.label, tiff_info(f.path, key=key, bit_depth=bd)) for f in volcal_frames)],
            key,
            depth=bool(dark),
        )
    return Recording(
        calibration=calib,
        calibration_kind=rec["calibration"].get("kind", "pinhole"),
        dark=dark,
        frames=frames,
        pairs=pairs,
        series=series,
        rows=first.rows,
        cols=first.cols,
        dtype=first.dtype,
        bit_depth=first.bits,
        dt=rec.get("dt"),
        max_saturated=float(rec.get("max_saturated", 1e-4)),
        depth_frames=depth_frames,
        depth_shifts=depth_shifts,
        volcal_frames=volcal_frames,
        volcal_depths=volcal_depths,
    )


def _read(frame: Frame, key: str) -> np.ndarray:
    import tifffile

    try:
        data = tifffile.imread(frame.path, key=frame.page)
    except Exception as exc:
        raise RecordingError(f"{key}: {_unreadable(frame.path, exc)}") from None
    if data.dtype.kind in "fc":
        bad = int(np.count_nonzero(~np.isfinite(data)))
        if bad:  # a NaN would spread through refocusing and PIV into silent NaN vectors
            raise RecordingError(
                f"{key}: {frame.label!r} ({str(frame.path)!r}) has {bad} non-finite (NaN/inf) pixels; "
                "replace them (dead or masked pixels) with finite values"
            )
    return data


def mean_dark(recording: Recording) -> np.ndarray | None:
    """The mean of the dark frames (float64), or None without any."""
    if not recording.dark:
        return None
    acc = np.zeros((recording.rows, recording.cols))
    for d in recording.dark:
        acc += _read(d, "recording.dark")
    return acc / len(recording.dark)


def _check_counts(img: np.ndarray, dtype: np.dtype, frame: Frame, key: str, *, dark: bool) -> None:
    """A frame to register holds counts >= 0, not all zero (registration's checks, naming the file)."""
    where = f"{key}: {frame.label!r} ({str(frame.path)!r})"
    low = float(img.min())
    if low < 0:
        raise RecordingError(
            f"{where} has {int(np.count_nonzero(img < 0))} negative pixels (min {low:.4g}, {dtype}): a recorded "
            "image holds counts >= 0; a signed (int16) file of an unsigned camera, or a wrongly converted one? "
            "(dark frames, recording.dark, are subtracted with clipping at 0)"
        )
    if not np.any(img > 0):
        what = "nowhere above the mean dark frame" if dark else "all zero"
        raise RecordingError(f"{where} is {what}: nothing was recorded (exposure, or the wrong file?)")


def read_frame(
    recording: Recording,
    frame: Frame,
    dark: np.ndarray | None = None,
    *,
    key: str = "recording.frames",
    counts: bool = True,
) -> tuple[xr.DataArray, float]:
    """Read one image, subtract the mean dark frame (clipped at 0) and measure its saturation.

    Parameters
    ----------
    recording : Recording
    frame : Frame
        A frame of the recording (or its calibration image).
    dark : ndarray, optional
        :func:`mean_dark`.
    key : str
        Config key of the frame, for the messages.
    counts : bool
        Refuse an image registration cannot take: negative pixels (after the dark
        frame), or nothing recorded. Off for the calibration image, whose own checks
        (:func:`~lfstudy.process.pipeline.calibrate_recording`) apply.

    Returns
    -------
    image : xarray.DataArray
        ``intensity`` over (``row``, ``col``), float64 counts, row 0 at the top.
    saturated : float
        Fraction of the raw pixels at or above full scale (0 for float frames).

    Raises
    ------
    RecordingError
        Pixels above the full scale of ``recording.bit_depth``, negative pixels or an image
        with nothing recorded (all zero, or nowhere above the mean dark frame) where
        ``counts``, or an unreadable page; the message names the file.
    """
    raw = _read(frame, key)
    saturated = 0.0
    fs = recording.full_scale
    if fs is not None and raw.dtype.kind in "ui":
        top = float(raw.max())
        if top > fs:
            raise RecordingError(
                f"config key 'recording.bit_depth' = {recording.bit_depth}: {frame.label!r} holds values up to "
                f"{top:.0f}, above full scale {fs:.0f}; give the camera's bit depth"
            )
        saturated = float(np.count_nonzero(raw >= fs)) / raw.size
    img = raw.astype(np.float64)
    if dark is not None:
        img -= dark
        np.maximum(img, 0.0, out=img)  # a pixel darker than the mean dark: noise, not negative light
    if counts:  # what registration refuses, said here with the file's name
        _check_counts(img, raw.dtype, frame, key, dark=dark is not None)
    da = xr.DataArray(
        img,
        dims=("row", "col"),
        name="intensity",
        attrs={
            "units": "counts",
            "long_name": "recorded intensity" + (" minus the mean dark frame" if dark is not None else ""),
            "source": str(frame.path),
            "page": frame.page,
            "y_direction": "row 0 at the top",
        },
    )
    return da, saturated


def warn_saturated(recording: Recording, fractions: Mapping[str, float]) -> None:
    """One :class:`SaturationWarning` for the frames whose saturated fraction exceeds ``max_saturated``.

    Parameters
    ----------
    fractions : mapping
        Frame label → saturated fraction (:func:`read_frame`).
    """
    bad = {k: v for k, v in fractions.items() if v > recording.max_saturated}
    if not bad:
        return
    worst = max(bad, key=bad.__getitem__)
    warnings.warn(
        f"{len(bad)} of {len(fractions)} frames saturated (more than {100 * recording.max_saturated:.3g} % of "
        f"pixels at full scale {recording.full_scale:.0f}, {recording.bit_depth}-bit): up to "
        f"{100 * bad[worst]:.3g} % in {worst!r}; particle intensities are clipped there",
        SaturationWarning,
        stacklevel=2,
    )
