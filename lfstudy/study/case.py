"""The case layer: one case's config → the science of that case.

Every function here takes a case config (:func:`lfstudy.study.config.case_config`,
or the part of it a stage reads) and calls the pure science functions of the
stage packages. The Snakemake rules (:mod:`lfstudy.workflow`), the CLI and a
notebook all go through this module, so they produce the same bytes; the
science packages know nothing of configs or cases.

Seeds are derived, never drawn from the clock: the particle field depends on
(study seed, magnification, ppp) only, so every f-number and lenslet pitch of
a sweep images the *same* particles (sec. 4.3.2 keeps the particle field
apart from the optics for exactly this reason); ray-tracing streams depend on
the images' own location (the settings the simulation reads) and the frame,
so cases that differ only in processing share their images.
"""

from __future__ import annotations

import functools
import zlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import xarray as xr

from lfstudy import io
from lfstudy.optics import PlenopticCamera

__all__ = [
    "derive_seed",
    "case_camera",
    "case_planes",
    "truth_sigma",
    "PARTICLE_SIGMA",
    "particle_sigma",
    "case_particles",
    "case_displaced",
    "case_illuminated",
    "case_sensor",
    "case_image",
    "case_pinhole",
    "simulate_case",
    "case_grid",
    "case_stack",
    "case_volume",
    "case_reconstruction",
    "case_piv",
    "case_paired_piv",
    "case_tracked_piv",
    "volume_voxel",
    "oracle_volumes",
    "oracle_piv",
    "case_depth_calibration",
    "render_volume",
    "render_frame",
]


def _noise_stream(stage_id: str) -> str:
    """A simulate stage id without its imperfection segments (:data:`lfstudy.study.sweep.TOLERANCES`):
    the random stream of the images, shared by the levels of a tolerance sweep."""
    from lfstudy.study.sweep import is_tolerance

    return "/".join(seg for seg in stage_id.split("/") if not is_tolerance(seg.partition("~")[0]))


def derive_seed(base: int, *parts: Any) -> int:
    """A stable 32-bit seed from the study seed and labels (crc32, not ``hash``)."""
    text = "/".join(str(p) for p in (base, *parts))
    return zlib.crc32(text.encode()) & 0x7FFFFFFF


def _stage_id(ccfg: Mapping[str, Any], stage: str) -> str:
    """Where ``stage``'s outputs live, from a case config or a stage config."""
    ids = ccfg.get("stage_ids")
    return ids[stage] if ids else ccfg["stage_id"]


def case_camera(ccfg: Mapping[str, Any]) -> PlenopticCamera:
    """The camera of a case config (the nominal one: what the processing knows)."""
    return PlenopticCamera.from_config(ccfg)


def case_imperfections(ccfg: Mapping[str, Any]) -> Any:
    """The imaging imperfections of a case (``camera.imperfections``; ideal when absent).

    The lenslet scatter is drawn from a seed derived from the study seed alone, so every image
    and the pinhole image of a study see one physical lenslet array.
    """
    from lfstudy.simulate.imperfections import CameraImperfections

    return CameraImperfections.from_config(ccfg, scatter_seed=derive_seed(ccfg["seed"], "lenslet_scatter"))


def case_planes(ccfg: Mapping[str, Any], camera: PlenopticCamera | None = None) -> xr.Dataset:
    """The refocus planes of a case (``refocus``: n_planes, depth_scale, cubic; eqs 5.16–5.20)."""
    cam = camera if camera is not None else case_camera(ccfg)
    r = ccfg["refocus"]  # a stage given no refocus section must fail loudly, not use defaults
    return cam.focal_planes(r["n_planes"], depth_scale=r["depth_scale"], cubic=bool(r["cubic"]))


def truth_sigma(camera: PlenopticCamera) -> tuple[float, float, float]:
    """σ (z, y, x) [mm] of the true particles for Q: half the camera's resolution cell.

    In x, y the cell is one lenslet at the focal-plane magnification, pl/|M|; in z
    the depth of focus of one refocus plane (the Table 5.1 plane spacing at the
    focal plane). Fixed by the camera, the same for every method and grid.
    """
    from lfstudy.reconstruct.grid import default_voxel_z

    dxy = camera.lenslet_pitch / abs(camera.magnification)
    return (default_voxel_z(camera), dxy / 2.0, dxy / 2.0)


#: ``piv.particle_sigma`` where unset [voxels per axis]: σ of each particle in the volumes the PIV correlates where
#: they are rendered from particle lists (the oracle's true volumes, :func:`oracle_volumes`; the paired particles',
#: :func:`case_paired_piv`). Half a voxel makes a particle image about two voxels across (4σ), as the lateral truth
#: σ is on a grid of one voxel per lenslet. Q's truth σ (:func:`truth_sigma`) is the camera's depth of focus
#: instead: 1.4-3.7 z voxels on the demo's 0.25 mm z voxels, against its 4-voxel-deep final window, and the
#: correlation of such images reads w at 0.30-0.74 of its size (the oracle on the demo's Hill vortex, seeds 7 and
#: 8; at half a voxel 0.97-1.00, w RMS 0.027-0.068 -> 0.008-0.011 mm; benchmarks/bench_particle_sigma.py).
PARTICLE_SIGMA = 0.5


def particle_sigma(ccfg: Mapping[str, Any], voxel: Sequence[float]) -> tuple[float, float, float]:
    """σ (z, y, x) [mm] of a particle in the PIV's particle volumes: ``piv.particle_sigma`` voxels per axis
    (:data:`PARTICLE_SIGMA` where unset) of ``voxel`` (dx, dy, dz) [mm]."""
    k = float((ccfg.get("piv") or {}).get("particle_sigma", PARTICLE_SIGMA))
    dx, dy, dz = (float(v) for v in voxel)
    return (k * dz, k * dy, k * dx)


def case_particles(ccfg: Mapping[str, Any], *, seed: int | None = None) -> xr.Dataset:
    """The first-exposure particle field of a case config (``seed``: another field of the
    same seeding, e.g. the depth calibration's)."""
    from lfstudy.simulate.particles import seed_particles

    cam = case_camera(ccfg)
    p = ccfg["particles"]
    # the field depends on the seed, magnification and ppp only: every f-number and pitch
    # of a sweep images the same particles
    if seed is None:
        seed = derive_seed(ccfg["seed"], "particles", float(ccfg["camera"]["magnification"]), float(p["ppp"]))
    kw: dict[str, Any] = {"count": p["count"]} if p.get("count") else {"ppp": p["ppp"]}
    d = p.get("diameter", {})
    field = seed_particles(
        cam,
        **kw,
        x_span=p["x_span"],
        y_span=p["y_span"],
        z_span=p["z_span"],
        intensity=tuple(p["intensity"]),
        seed=seed,
        depth_margin=p.get("depth_margin", 0.0),
        diameter=d.get("distribution", "fixed"),
        diameter_mean_um=d.get("mean_um"),
        diameter_sd_um=d.get("sd_um", 0.0),
        z_center=p.get("z_center", 0.0),
    )
    field.attrs.update(io.provenance(ccfg, seed))
    return field


def case_displaced(ccfg: Mapping[str, Any], field: xr.Dataset) -> xr.Dataset:
    """The second-exposure field: ``field`` advected by the case's flow."""
    from lfstudy.simulate.flows import displace, flow_from_config

    spec = ccfg["flow"]
    moved = displace(field, flow_from_config(spec), dt=spec.get("dt", 1.0), n_steps=spec.get("n_steps", 100))
    moved.attrs.update(io.provenance(ccfg, field.attrs.get("seed")), flow=spec["name"])
    return moved


def case_illuminated(ccfg: Mapping[str, Any], field: xr.Dataset) -> xr.Dataset:
    """``field`` as the case's light volume lights it (``illumination`` section;
    :func:`lfstudy.simulate.particles.illuminate`): each intensity times the profile at the
    particle's own depth. With ``profile: none`` (the default) ``field`` itself."""
    from lfstudy.simulate.particles import illuminate

    il = ccfg["illumination"]  # a stage given no illumination section must fail loudly
    if il["profile"] == "none":
        return field
    return illuminate(
        field, profile=il["profile"], center=il["center"], thickness=il["thickness"], edge_width=il["edge_width"]
    )


@functools.lru_cache(maxsize=2)
def _white(camera: PlenopticCamera, fnumber: float, diffraction: bool, max_image_bytes: float) -> np.ndarray:
    """The exact white image of a uniform field at ``fnumber``, mean 1 (read-only; cached for the
    depth calibration's many images of one camera). One Gauss–Legendre node per lenslet: the
    lenslet's disc moves by a few hundredths of a pixel across its square, and 3 x 3 nodes (the
    pinhole image's) change the normalised image by < 5e-4 (demo and tiny designs) at 9x the cost."""
    from lfstudy.simulate.raytrace import render_pinhole
    from lfstudy.simulate.sensor import lenslet_background

    img = render_pinhole(
        camera,
        fnumber=fnumber,
        count=1,
        rays_per_point=1,
        method="exact",
        nodes=1,
        diffraction=diffraction,
        max_image_bytes=max_image_bytes,
    )
    out = lenslet_background(img)
    out.flags.writeable = False
    return out


def _background(ccfg: Mapping[str, Any], image: xr.DataArray, fnumber: float | None) -> float | np.ndarray:
    """The case's background light [photons/pixel] for ``image`` (``sensor.background``): the uniform
    level plus the lenslet-structured one, the exact white image at ``fnumber`` (the working
    f-number when None) scaled to its mean (:func:`lfstudy.simulate.sensor.lenslet_background`)."""
    bg = ccfg["sensor"].get("background", {})
    level: float | np.ndarray = float(bg.get("uniform", 0.0))
    if bg.get("lenslet", 0.0) > 0:
        cam = case_camera(ccfg)
        rt = ccfg["raytrace"]
        args = (cam, float(cam.main_fnumber if fnumber is None else fnumber), bool(rt["diffraction"]))
        try:
            white = _white(*args, float(rt["max_image_bytes"]))
        except TypeError:  # a camera that cannot be hashed (e.g. array-valued fields): no cache
            white = _white.__wrapped__(*args, float(rt["max_image_bytes"]))
        if white.shape != image.shape:
            raise ValueError(f"lenslet background: white image {white.shape} differs from the image {image.shape}")
        level = level + float(bg["lenslet"]) * white
    return level


def case_sensor(
    ccfg: Mapping[str, Any], image: xr.DataArray, seed: int, photons_default: int, *, fnumber: float | None = None
) -> xr.DataArray:
    """Record a rendered image with the case's sensor (``sensor`` section; :mod:`lfstudy.simulate.sensor`).

    ``photons_default`` stands in for a null ``sensor.photons_per_particle`` (one
    photon per ray: the image's ray count). The background light (``sensor.background``;
    its lenslet structure at ``fnumber``, the image's f-number, default the working one)
    and the hot pixels (``sensor.hot_pixels``; positions from their seed, or the study seed:
    the same in every image) are the same for every renderer: they act here.
    """
    from lfstudy.simulate.sensor import apply_sensor

    s = ccfg["sensor"]  # a stage given no sensor section must fail loudly, not use defaults
    photons = s["photons_per_particle"]
    hot = s.get("hot_pixels", {})
    hot_seed = hot.get("seed")
    return apply_sensor(
        image,
        photons_per_particle=photons_default if photons is None else photons,
        quantum_efficiency=s["quantum_efficiency"],
        shot_noise=s["shot_noise"],
        read_noise=s["read_noise"],
        dark_level=s["dark_level"],
        full_well=s["full_well"],
        bit_depth=s["bit_depth"],
        gain=s["gain"],
        seed=seed,
        background=_background(ccfg, image, fnumber),
        hot_pixel_fraction=hot.get("fraction", 0.0),
        hot_pixel_level=hot.get("level", 0.0),
        hot_pixel_seed=derive_seed(ccfg["seed"], "hot-pixels") if hot_seed is None else hot_seed,
    )


def case_image(
    ccfg: Mapping[str, Any], field: xr.Dataset, frame: str, *, progress: bool = False, illuminate: bool = True
) -> xr.DataArray:
    """The recorded raw image of exposure ``frame`` ("a" or "b") of a case.

    The field is lit by the case's light volume (:func:`case_illuminated`; ``illuminate=False``:
    it already is), rendered with ``raytrace.method`` (exact: the expected image; montecarlo: ray
    traced), then recorded by the case's sensor; both seeds derive from the
    study seed, the simulate stage's location (frame a's: shared by the flows) and the frame, so one config gives
    one image, byte for byte. The location's imperfection settings (``TOLERANCES``) are left out
    of the seeds: the levels of a tolerance sweep see the same rays and noise (common random
    numbers), so what differs between them is the imperfection. Every particle setting acts on
    the particle list (intensities, positions) and every sensor setting in :func:`case_sensor`:
    both renderers honour all.
    """
    from lfstudy.simulate.raytrace import render
    from lfstudy.study.sweep import frame_stage

    rt = ccfg["raytrace"]
    sid = _noise_stream(_stage_id(ccfg, frame_stage("simulate", frame)))
    seed = derive_seed(ccfg["seed"], "raytrace", sid, frame)
    img = render(
        case_camera(ccfg),
        case_illuminated(ccfg, field) if illuminate else field,
        rt["rays_per_particle"],
        seed,
        diffraction=rt["diffraction"],
        max_image_bytes=rt["max_image_bytes"],
        progress=progress,
        method=rt["method"],
        imperfections=case_imperfections(ccfg),
    )
    img = case_sensor(ccfg, img, derive_seed(ccfg["seed"], "sensor", sid, frame), rt["rays_per_particle"])
    img.attrs.update(io.provenance(ccfg, seed), frame=frame)
    return img


def case_pinhole(ccfg: Mapping[str, Any], *, progress: bool = False) -> xr.DataArray:
    """The calibration pinhole image (sec. 5.1), shared by the case's calibration group.

    Rendered with ``raytrace.method`` and recorded by the case's sensor (a null
    ``sensor.photons_per_particle`` is ``pinhole.rays_per_point`` here; its background light and
    hot pixels too, the lenslet background at the pinhole's f-number). The particle settings
    (light volume, diameters, depth margin) are the flow's seeding's, not the calibration field's.
    """
    from lfstudy.simulate.raytrace import render_pinhole

    ph = ccfg["pinhole"]
    seed = derive_seed(ccfg["seed"], "pinhole", ccfg["calib_id"])
    img = render_pinhole(
        case_camera(ccfg),
        fnumber=ph["fnumber"],
        count=ph["count"],
        rays_per_point=ph["rays_per_point"],
        seed=seed,
        max_image_bytes=ccfg["raytrace"]["max_image_bytes"],
        progress=progress,
        method=ccfg["raytrace"]["method"],
        imperfections=case_imperfections(ccfg),
    )
    img = case_sensor(
        ccfg,
        img,
        derive_seed(ccfg["seed"], "sensor", "pinhole", ccfg["calib_id"]),
        ph["rays_per_point"],
        fnumber=ph["fnumber"],
    )
    img.attrs.update(io.provenance(ccfg, seed))
    return img


def simulate_case(ccfg: Mapping[str, Any], *, progress: bool = False) -> dict[str, xr.DataArray | xr.Dataset]:
    """Everything the simulate stages produce for one case config.

    Seeds the first particle field, displaces it with the case's flow and
    ray-traces both exposures and the pinhole calibration image, with the
    seeds of the Snakemake rules (so this reproduces their outputs byte for
    byte). ``progress`` shows a bar per ray-traced image.

    Returns
    -------
    dict
        ``particles_a``, ``particles_b`` (Datasets) and ``image_a``,
        ``image_b``, ``pinhole`` (DataArrays named ``intensity``).
    """
    field_a = case_particles(ccfg)
    field_b = case_displaced(ccfg, field_a)
    return {
        "particles_a": field_a,
        "particles_b": field_b,
        "image_a": case_image(ccfg, field_a, "a", progress=progress),
        "image_b": case_image(ccfg, field_b, "b", progress=progress),
        "pinhole": case_pinhole(ccfg, progress=progress),
    }


def case_grid(ccfg: Mapping[str, Any], camera: PlenopticCamera | None = None) -> Any:
    """The reconstruction grid of a case (``grid`` section; the depth of its refocus marching)."""
    from lfstudy.reconstruct.grid import make_grid

    cam = camera if camera is not None else case_camera(ccfg)
    g = ccfg["grid"]
    return make_grid(
        cam,
        case_planes(ccfg, cam),
        voxel_xy=g["voxel_xy"],
        voxel_z=g["voxel_z"],
        spacing=g["spacing"],
        z_range=g["z_range"],
        max_bytes=g["max_bytes"],
    )


def case_volcal(ccfg: Mapping[str, Any], centers: xr.Dataset) -> xr.Dataset:
    """The dot-target volumetric calibration of a case's design (``volumetric_calibration``;
    :mod:`lfstudy.lightfield.volcal`, Hall et al. 2018).

    The card (dots ``spacing`` apart over the field of view; default 5 lenslet pitches/|M|) is
    imaged through the case's camera with its imperfections at ``n_depths`` depths evenly over
    the reconstruction grid's depth, with shot and read noise (seed from the study seed), then
    registered with the case's lenslet calibration ``centers`` and fitted.
    """
    from lfstudy.lightfield.registration import register
    from lfstudy.lightfield.volcal import fit_volumetric
    from lfstudy.simulate.dottarget import render_dot_target

    vc = ccfg["volumetric_calibration"]
    cam = case_camera(ccfg)
    grid = case_grid(ccfg, cam)
    depths = np.linspace(float(grid.z.min()), float(grid.z.max()), int(vc["n_depths"]))
    spacing = vc["spacing"] or 5.0 * cam.lenslet_pitch / abs(cam.magnification)
    rt = ccfg.get("raytrace", {})
    imgs = render_dot_target(
        cam,
        depths,
        spacing=float(spacing),
        photons=float(vc["photons"]),
        read_noise=float(vc["read_noise"]),
        seed=derive_seed(ccfg.get("seed", 0), "volumetric-calibration"),
        diffraction=bool(rt.get("diffraction", True)),
        imperfections=case_imperfections(ccfg),
        max_image_bytes=float(rt.get("max_image_bytes", 4e9)),
    )
    lfs = [register(imgs.isel(depth=k).drop_vars("depth"), centers, cam) for k in range(depths.size)]
    cal = fit_volumetric(lfs, depths, cam, spacing=float(spacing), order=int(vc["order"]))
    cal.attrs.update(io.provenance(ccfg, None))
    return cal


def case_stack(
    ccfg: Mapping[str, Any], lightfield: xr.DataArray, calibration: xr.Dataset | None = None
) -> xr.DataArray:
    """Light field → focal stack of a case, refocused onto the planes of its reconstruction grid.

    On a uniform grid every plane sits at a grid depth (refocusing at any t is
    exact, eqs 5.10–5.15), so the focal-stack methods and the others share one
    grid; with ``grid.spacing: planes`` the planes are the marching's own
    (Table 5.1). Lazy, one dask chunk per plane. With ``refocus.model: volumetric`` the
    planes are sampled through the dot-target ``calibration`` (:func:`case_volcal`) instead.
    """
    from lfstudy.lightfield.refocus import focal_stack

    cam = case_camera(ccfg)
    grid = case_grid(ccfg, cam)
    if ccfg["refocus"].get("model", "thin_lens") == "volumetric":
        from lfstudy.lightfield.volcal import volumetric_stack

        if calibration is None:
            raise ValueError(
                "refocus.model = 'volumetric' needs the dot-target calibration (volumetric_calibration; "
                "lfstudy.study.case.case_volcal)"
            )
        stack = volumetric_stack(lightfield, calibration, grid.z, grid.x, grid.y, camera=cam)
        stack.attrs.update(grid.attrs())
        return stack
    planes = case_planes(ccfg, cam) if grid.spacing == "planes" else cam.planes_at(grid.z)
    if grid.spacing == "planes" and planes.sizes["plane"] != grid.z.size:  # grid.z_range keeps some planes
        planes = planes.isel(plane=np.flatnonzero(np.isin(planes["z"].values, grid.z)))
    resize = bool(ccfg["refocus"]["resize"])
    stack = focal_stack(lightfield, cam, planes, resize=resize, x=grid.x, y=grid.y)
    stack.attrs.update(grid.attrs())
    return stack


def case_volume(
    ccfg: Mapping[str, Any],
    stack: xr.DataArray,
    lightfield: xr.DataArray | None = None,
    centers: xr.Dataset | None = None,
    *,
    progress: bool = False,
    calibration: xr.Dataset | None = None,
) -> xr.DataArray:
    """The particle volume of one frame with the case's reconstruction method (``reconstruct.method``)
    and its parameters (``reconstruct.<method>``), on the case's grid (``calibration``: as
    :func:`case_reconstruction`)."""
    return case_reconstruction(ccfg, stack, lightfield, centers, progress=progress, calibration=calibration)[0]


def case_reconstruction(
    ccfg: Mapping[str, Any],
    stack: xr.DataArray,
    lightfield: xr.DataArray | None = None,
    centers: xr.Dataset | None = None,
    *,
    progress: bool = False,
    calibration: xr.Dataset | None = None,
) -> tuple[xr.DataArray, xr.Dataset | None]:
    """:func:`case_volume` and, for a method that fits particles (``ipr``), the particle list the
    volume was rendered from, out of the same fit (:func:`lfstudy.reconstruct.reconstruct_particles`).

    With ``refocus.model: volumetric`` the methods that model the camera (``uses_calibration``: ``mart``,
    ``ipr``) place their beams through the dot-target ``calibration`` (:func:`case_volcal`; Hall et al. 2018), the
    same mapping the focal stack was sampled through: one switch for the whole chain. Under the
    thin-lens model a calibration is not used.

    Returns
    -------
    volume : xarray.DataArray
    particles : xarray.Dataset or None
        Over ``particle`` (x, y, z [mm], intensity, ...); None for a method that fits no particles.
    """
    from lfstudy.reconstruct import ReconstructionInputs, get_method, reconstruct_particles

    cam = case_camera(ccfg)
    grid = case_grid(ccfg, cam)
    r = ccfg["reconstruct"]
    method = r["method"]
    if ccfg["refocus"].get("model", "thin_lens") != "volumetric":
        calibration = None
    elif calibration is None and get_method(method).uses_calibration:
        raise ValueError(
            f"refocus.model = 'volumetric' with reconstruct.method = {method!r} needs the dot-target calibration "
            "(volumetric_calibration; lfstudy.study.case.case_volcal)"
        )
    inputs = ReconstructionInputs(
        stack=stack, lightfield=lightfield, centers=centers, camera=cam, grid=grid, calibration=calibration
    )
    vol, parts = reconstruct_particles(inputs, method, progress=progress, **dict(r.get(method, {})))
    vol.attrs.update({k: v for k, v in grid.attrs().items() if k not in vol.attrs})
    return vol, parts


def case_piv(ccfg: Mapping[str, Any], a: Any, b: Any, *, progress: bool = False) -> xr.Dataset:
    """3-D WIDIM PIV (ch. 6) between two volumes of a case, with its ``piv`` section.

    The result's attrs carry ``piv_seconds`` (the correlation's wall time).
    """
    import time

    from lfstudy.piv import widim
    from lfstudy.piv.engine import config_options

    p = ccfg["piv"]
    t0 = time.perf_counter()
    res = widim(a, b, **config_options(p), progress=progress, uncertainty=p.get("uncertainty", "correlation"))
    res.attrs["piv_seconds"] = time.perf_counter() - t0
    return res


def _tracks(
    ccfg: Mapping[str, Any],
    piv: xr.Dataset,
    particles_a: xr.Dataset,
    particles_b: xr.Dataset,
    voxel: tuple[float, float, float] | None,
) -> xr.Dataset:
    """The fitted particles of both frames paired about the WIDIM field (mutual nearest within
    ``piv.ptv_search`` voxels), the outlier tracks dropped by the median test: what ``ptv`` bins and
    ``paired`` renders."""
    from lfstudy.piv.ptv import SEARCH, match_particles, validate_tracks

    search = float(ccfg["piv"].get("ptv_search", SEARCH))
    tracks = match_particles(particles_a, particles_b, piv, search=search, voxel=voxel)
    return validate_tracks(tracks, voxel=tracks.attrs["voxel_mm"])


def volume_voxel(vol: xr.DataArray) -> tuple[float, float, float]:
    """A reconstructed volume's voxel size (dx, dy, dz) [mm], from its coordinates: the ``voxel`` that
    :func:`case_ptv` and :func:`case_paired_piv` take (the study's piv stage and ``lfstudy process`` alike)."""
    return tuple(float(np.median(np.abs(np.diff(vol[d].values)))) for d in ("x", "y", "z"))


def case_ptv(
    ccfg: Mapping[str, Any],
    piv: xr.Dataset,
    particles_a: xr.Dataset,
    particles_b: xr.Dataset,
    voxel: tuple[float, float, float] | None = None,
) -> xr.Dataset:
    """PTV of a case (``piv.particles: ptv``): the fitted particles of both frames paired about the
    case's WIDIM field, the outlier tracks dropped by the median test and the rest binned on its grid
    (:mod:`lfstudy.piv.ptv`).

    Parameters
    ----------
    ccfg : Mapping
        The case's config (its ``piv`` section: ``ptv_search``, ``ptv_order``, ``ptv_model_box``).
    piv : xarray.Dataset
        The case's WIDIM result (:func:`case_piv`): the predictor and the grid.
    particles_a, particles_b : xarray.Dataset
        The particle lists the reconstruction fitted (``volume_{a,b}.particles.zarr``).
    voxel : (dx, dy, dz), optional
        The reconstruction grid's voxel size [mm]; default the PIV grid's.

    Returns
    -------
    xarray.Dataset
        :func:`lfstudy.piv.ptv.bin_tracks`' result, with attrs ``piv_seconds`` (WIDIM's),
        ``ptv_rejected`` (tracks the median test dropped) and ``ptv_seconds`` (matching and binning).
    """
    import time

    from lfstudy.piv.ptv import MODEL_BOX, bin_tracks

    t0 = time.perf_counter()
    tracks = _tracks(ccfg, piv, particles_a, particles_b, voxel)
    res = bin_tracks(
        tracks,
        piv,
        voxel=voxel,
        order=int(ccfg["piv"].get("ptv_order", 1)),
        model_box=float(ccfg["piv"].get("ptv_model_box", MODEL_BOX)),
    )
    res.attrs["ptv_rejected"] = int(tracks.attrs["n_rejected"])
    res.attrs["ptv_seconds"] = time.perf_counter() - t0
    return res


#: ``piv.paired_max_sigma_z`` where unset [z voxels]: the paired PIV leaves out the fitted particles whose depth
#: uncertainty exceeds it. On the demo (uniform_x, 0.25 mm z voxels) 0.08 took IPR's RMS error 0.0143 -> 0.0101 mm
#: on M -0.8, pitch 0.0888 at seed 7 (where it was chosen) and 0.0207 -> 0.0115 at seed 8 (held out); the other
#: designs -19 to +9 %, the coarsest either way (0.0236 -> 0.0313, 0.0424 -> 0.0332); docs/config.md.
PAIRED_MAX_SIGMA_Z = 0.08


def _depth_known(particles: xr.Dataset, limit_mm: float) -> xr.Dataset:
    """The fitted particles whose depth uncertainty (``sigma_z``, the fit's covariance) is at most ``limit_mm``;
    a list without ``sigma_z`` (not a fit's) whole."""
    if "sigma_z" not in particles:
        return particles
    keep = np.asarray(particles["sigma_z"].values, dtype=float) <= limit_mm
    return particles if keep.all() else particles.isel(particle=np.nonzero(keep)[0])


def case_paired_piv(
    ccfg: Mapping[str, Any],
    piv: xr.Dataset,
    a: xr.DataArray,
    b: xr.DataArray,
    particles_a: xr.Dataset,
    particles_b: xr.Dataset,
    voxel: tuple[float, float, float] | None = None,
) -> xr.Dataset:
    """WIDIM on volumes of the particles that pair between the frames (``piv.particles: paired``).

    A fitted particle that has no partner in the other frame about the WIDIM field (mutual nearest
    within ``piv.ptv_search`` voxels and through the tracks' median test, as :func:`case_ptv` pairs
    them) is a ghost or a real particle fitted at the wrong place in one frame only: in the volumes it
    correlates with nothing, or with the wrong particle, and biases the vectors (on the coarse demo
    designs a lateral shift read as depth motion). The volumes are rendered again from the paired
    particles alone, each a Gaussian of :func:`particle_sigma` (half a voxel per axis where
    ``piv.particle_sigma`` is unset; :func:`lfstudy.reconstruct.truth.render_truth`), as :func:`oracle_volumes`
    renders the true particles, so that a perfect particle list gives the oracle; and WIDIM runs once more.

    Before the pairing, the particles whose depth the fit could not read (its ``sigma_z`` above
    ``piv.paired_max_sigma_z`` z voxels, :data:`PAIRED_MAX_SIGMA_Z` where unset) are left out: near the focal
    plane a particle's image hardly changes with depth (:mod:`lfstudy.reconstruct.ipr.bound`), so its depth
    error, independent in the two frames, would go into w.

    With ``piv.paired_weights`` ``depth`` (the default) each track weighs in the correlation by the inverse of
    the tracks' own displacement variance at its distance from the focal plane
    (:func:`lfstudy.piv.ptv.depth_weights`): each of its two particles is rendered with the root of that weight
    times its intensity. The fit's ``sigma_z`` misses most of the depth error near focus (the fit's choice of
    minimum, not the minimum's width), which the tracks' scatter shows. That scatter, over the tracks inside a
    vector's window, is also a floor of the vector's σ (``piv.paired_uncertainty``): the correlation's σ, read from
    the correlation plane, sees little of the depth error near focus.

    Parameters
    ----------
    ccfg : Mapping
        The case's config (its ``piv`` section: the WIDIM settings, ``ptv_search``, ``paired_max_sigma_z`` and
        ``paired_weights``).
    piv : xarray.Dataset
        WIDIM between the reconstructed volumes (:func:`case_piv`): the predictor of the pairing.
    a, b : xarray.DataArray
        The reconstructed volumes (coords, and the ``blob_sigma_mm`` that marks a particle method's volume).
    particles_a, particles_b : xarray.Dataset
        The particle lists the reconstruction fitted (``volume_{a,b}.particles.zarr``).
    voxel : (dx, dy, dz), optional
        The reconstruction grid's voxel size [mm]; default the PIV grid's for the pairing, the volume's for the
        depth-uncertainty limit and the particles' σ.

    Returns
    -------
    xarray.Dataset
        :func:`case_piv`'s result on the paired volumes; the first WIDIM's vectors kept as ``piv_u_mm``,
        ``piv_v_mm``, ``piv_w_mm``, ``piv_valid``; attrs ``particles`` ("paired"), ``paired_tracks``,
        ``paired_particles_a``, ``paired_particles_b`` (the fitted lists' sizes), ``paired_max_sigma_z_mm``
        and ``paired_depth_unknown_a``, ``paired_depth_unknown_b`` (the particles it left out),
        ``paired_rejected`` (tracks the median test dropped), ``particle_sigma_mm`` (σ z, y, x of the paired
        volumes' particles), ``paired_weights`` and the weights' bands (``paired_weight_depth_mm``: their median
        |z|; ``paired_weight_sd_mm``: the tracks' displacement scatter there; ``paired_weight_min``: the least
        weight), ``paired_uncertainty`` and ``paired_seconds`` (pairing and rendering). With ``piv.paired_uncertainty``
        ``tracks`` (the default, where WIDIM gives a σ) each vector's ``unc_<c>_mm`` is the larger of the correlation's
        (kept as ``unc_correlation_<c>_mm``) and the tracks' own (``unc_tracks_<c>_mm``,
        :func:`lfstudy.piv.ptv.track_sigma`), and ``unresolved`` is read against it.
    """
    import time

    from lfstudy.piv.ptv import PAIRED_UNCERTAINTY, PAIRED_WEIGHTS, depth_weights
    from lfstudy.reconstruct.truth import render_truth

    if a.attrs.get("blob_sigma_mm") is None:
        raise ValueError(
            "piv.particles = 'paired': the volumes carry no blob_sigma_mm (they are not a particle list's volumes)"
        )
    t0 = time.perf_counter()
    n_a, n_b = int(particles_a.sizes["particle"]), int(particles_b.sizes["particle"])
    vox = voxel if voxel is not None else volume_voxel(a)
    sig = particle_sigma(ccfg, vox)
    limit = float(ccfg["piv"].get("paired_max_sigma_z", PAIRED_MAX_SIGMA_Z)) * float(vox[2])
    particles_a, particles_b = (_depth_known(p, limit) for p in (particles_a, particles_b))
    tracks = _tracks(ccfg, piv, particles_a, particles_b, voxel)
    coords = {d: a[d].values for d in ("z", "y", "x")}
    weighting = str(ccfg["piv"].get("paired_weights", PAIRED_WEIGHTS[0]))
    if weighting not in PAIRED_WEIGHTS:
        raise ValueError(f"piv.paired_weights = {weighting!r}; allowed values are {PAIRED_WEIGHTS}")
    sigma_mode = str(ccfg["piv"].get("paired_uncertainty", PAIRED_UNCERTAINTY[0]))
    if sigma_mode not in PAIRED_UNCERTAINTY:
        raise ValueError(f"piv.paired_uncertainty = {sigma_mode!r}; allowed values are {PAIRED_UNCERTAINTY}")
    weights, bands = (
        depth_weights(tracks, voxel=tracks.attrs["voxel_mm"])
        if weighting == "depth"
        else (np.ones(tracks.sizes["track"]), {"depth_mm": [], "sd_mm": []})
    )
    # a correlation weighs a pair by the product of its two images: each image gets the root of the track's weight
    scale = np.sqrt(weights)

    def paired(vol: xr.DataArray, parts: xr.Dataset, rows: np.ndarray) -> xr.DataArray:
        sel = parts.isel(particle=rows)
        amp = sel["intensity"].values if "intensity" in sel else np.ones(len(rows))
        data = render_truth(coords, sel.assign(intensity=("particle", amp * scale)), sigma_mm=sig)
        return vol.copy(data=data.astype(vol.dtype)).assign_attrs(blob_sigma_mm=list(sig))

    va = paired(a, particles_a, tracks.index_a.values)
    vb = paired(b, particles_b, tracks.index_b.values)
    seconds = time.perf_counter() - t0
    res = case_piv(ccfg, va, vb)
    if sigma_mode == "tracks" and "unc_u_mm" in res:
        res = _with_track_sigma(res, tracks, weights, vox)
    for c in ("u", "v", "w"):
        res[f"piv_{c}_mm"] = piv[f"{c}_mm"].assign_attrs(long_name=f"{c} of WIDIM on the reconstructed volumes")
    res["piv_valid"] = piv["valid"]
    res.attrs.update(
        particles="paired",
        paired_tracks=int(tracks.sizes["track"]),
        paired_particles_a=n_a,
        paired_particles_b=n_b,
        paired_max_sigma_z_mm=limit,
        particle_sigma_mm=list(sig),
        paired_depth_unknown_a=n_a - int(particles_a.sizes["particle"]),
        paired_depth_unknown_b=n_b - int(particles_b.sizes["particle"]),
        paired_rejected=int(tracks.attrs["n_rejected"]),
        paired_weights=weighting,
        paired_weight_depth_mm=bands["depth_mm"],
        paired_weight_sd_mm=bands["sd_mm"],
        paired_weight_min=float(weights.min()) if len(weights) else 1.0,
        paired_uncertainty=sigma_mode,
        paired_seconds=seconds,
    )
    return res


def _with_track_sigma(
    res: xr.Dataset, tracks: xr.Dataset, weights: np.ndarray, vox: tuple[float, float, float]
) -> xr.Dataset:
    """The paired PIV result ``res`` with each vector's σ per component the larger of the correlation's and the
    tracks' own (:func:`lfstudy.piv.ptv.track_sigma`, the tracks weighed as in the correlation), both kept
    (``unc_correlation_<c>_mm``, ``unc_tracks_<c>_mm``), and the ``unresolved`` flag read again against that σ."""
    from lfstudy.piv.ptv import track_sigma
    from lfstudy.piv.resolution import unresolved

    wz, wy, wx = (float(k) for k in res.attrs["final_window"])
    window_mm = (wx * vox[0], wy * vox[1], wz * vox[2])
    st = track_sigma(tracks, res, window_mm, voxel=tracks.attrs["voxel_mm"], weights=weights)  # (3, z, y, x)
    st = np.stack([xr.DataArray(s, dims=("z", "y", "x")).transpose(*res["unc_u_mm"].dims).values for s in st])
    out = res.copy()
    for k, c in enumerate(("u", "v", "w")):
        old = res[f"unc_{c}_mm"]
        new = np.where(np.isfinite(old.values), np.fmax(old.values, st[k]), np.nan)
        scale = np.where(old.values > 0, new / np.where(old.values > 0, old.values, 1.0), 1.0)
        out[f"unc_{c}_mm"] = old.copy(data=new)
        out[f"unc_{c}"] = res[f"unc_{c}"].copy(data=res[f"unc_{c}"].values * scale)
        out[f"unc_correlation_{c}_mm"] = old.assign_attrs(
            long_name=f"standard uncertainty of the {c} displacement read from the correlation alone"
        )
        out[f"unc_tracks_{c}_mm"] = old.copy(data=st[k]).assign_attrs(
            long_name=f"standard uncertainty of the {c} displacement from the paired tracks' own scatter "
            "(NaN: no track in the window)"
        )
    if "unresolved" in res:  # the flag marks filtering likely above σ: the σ now stored
        dims = res["unresolved"].dims
        field = np.stack([res[c].transpose(*dims).values for c in ("w", "v", "u")])
        sigma = np.stack([out[f"unc_{c}"].transpose(*dims).values for c in ("w", "v", "u")])
        partial = res["partial"].transpose(*dims).values.astype(bool)
        valid = res["valid"].transpose(*dims).values.astype(bool)
        flag = unresolved(
            field,
            sigma,
            res.attrs["final_window"],
            res.attrs["final_spacing"],
            partial=partial,
            valid=valid & ~partial,
            significance=float(res.attrs.get("unresolved_significance", 0.0)),
        )
        out["unresolved"] = res["unresolved"].copy(data=flag)
    return out


def case_tracked_piv(
    ccfg: Mapping[str, Any],
    piv: xr.Dataset,
    a: xr.DataArray,
    b: xr.DataArray,
    particles_a: xr.Dataset,
    particles_b: xr.Dataset,
) -> xr.Dataset:
    """The WIDIM result ``piv`` of volumes ``a`` and ``b`` refined with the fitted particle lists as
    ``piv.particles`` asks: tracked and binned (``ptv``, :func:`case_ptv`) or paired and correlated again
    (``paired``, :func:`case_paired_piv`), on the volumes' voxel."""
    from lfstudy.piv.ptv import PARTICLE_MODES

    mode = ccfg["piv"].get("particles", "none")
    if mode not in PARTICLE_MODES:
        raise ValueError(f"piv.particles = {mode!r} tracks no particles; allowed values are {PARTICLE_MODES}")
    voxel = volume_voxel(a)
    if mode == "ptv":
        return case_ptv(ccfg, piv, particles_a, particles_b, voxel=voxel)
    return case_paired_piv(ccfg, piv, a, b, particles_a, particles_b, voxel=voxel)


def oracle_volumes(
    ccfg: Mapping[str, Any], particles_a: xr.Dataset, particles_b: xr.Dataset
) -> tuple[xr.DataArray, xr.DataArray]:
    """The true particle volumes of both frames on the case's reconstruction grid.

    Each particle is a Gaussian of :func:`particle_sigma` (half a voxel per axis where ``piv.particle_sigma`` is
    unset), integrated over the voxels of the grid (:func:`lfstudy.study.metrics.render_truth`): what a perfect
    particle reconstruction would hand to the PIV, rendered as the paired PIV renders the fitted particles
    (:func:`case_paired_piv`). Not Q's truth σ (:func:`truth_sigma`): its depth of focus, several z voxels on a
    fine z grid, would make the oracle read w short (:data:`PARTICLE_SIGMA`). DataArrays like a reconstructed
    volume (float32, the grid's coords and attrs, ``blob_sigma_mm``).

    The particles are lit as in the images (:func:`case_illuminated`; their diameters are in their
    intensities already): a perfect reconstruction returns the light each particle sent. A particle
    counts only with the part of its Gaussian that lies on the grid, so the depth margin's
    particles (``particles.depth_margin``), imaged but beyond the grid, are not in the truth.
    """
    from lfstudy.study.metrics import render_truth

    cam = case_camera(ccfg)
    grid = case_grid(ccfg, cam)
    sigma = particle_sigma(ccfg, grid.voxel_size()[::-1])
    coords = {"z": grid.z, "y": grid.y, "x": grid.x}

    def volume(p: xr.Dataset) -> xr.DataArray:
        data = render_truth(coords, case_illuminated(ccfg, p), sigma_mm=sigma).astype(np.float32)
        return grid.volume(data, method="truth", blob_sigma_mm=list(sigma))

    return volume(particles_a), volume(particles_b)


def oracle_piv(
    ccfg: Mapping[str, Any], particles_a: xr.Dataset, particles_b: xr.Dataset, *, progress: bool = False
) -> xr.Dataset:
    """The oracle of a case: its PIV (``piv`` section, :func:`case_piv`) on the true volumes of both
    frames (:func:`oracle_volumes`).

    The same grid and windows as the case, the best any reconstruction could hand to the PIV: its
    error is what the design's grid and PIV windows can resolve, and the case's error beyond it is
    the reconstruction's (:func:`lfstudy.study.metrics.error_budget`). No depth calibration applies:
    the volumes are true. The attrs carry ``oracle_seconds`` (rendering and PIV, wall time).
    """
    import time

    t0 = time.perf_counter()
    a, b = oracle_volumes(ccfg, particles_a, particles_b)
    res = case_piv(ccfg, a, b, progress=progress)
    res.attrs.update(
        oracle="the case's PIV on the true particle volumes (each particle a Gaussian of particle_sigma_mm)",
        particle_sigma_mm=a.attrs["blob_sigma_mm"],
        oracle_seconds=time.perf_counter() - t0,
    )
    return res


def case_depth_calibration(
    ccfg: Mapping[str, Any],
    centers: xr.Dataset,
    *,
    progress: bool = False,
    calibration: xr.Dataset | None = None,
) -> xr.Dataset:
    """The depth calibration of a case's design and processing (``depth_calibration`` section).

    A seeded volume of the case's density (its own seed, so never the case's
    particles) is imaged by the case's renderer and sensor, traversed by
    each of ``depth_calibration.shifts`` (z voxels) along +z and imaged again;
    every exposure goes through the case's registration, focal stack and
    reconstruction, each shifted one is correlated with the first by the case's
    PIV, and :func:`lfstudy.piv.depth.depth_response` reads the response per
    depth layer. Only the camera model and the lenslet calibration are used (what an
    experiment with a traverse has), never the case's flow. ``calibration``: the dot-target
    one (:func:`case_volcal`) where ``refocus.model`` is ``volumetric``.
    """
    from lfstudy.piv.depth import depth_response

    dc = ccfg["depth_calibration"]
    cam = case_camera(ccfg)
    grid = case_grid(ccfg, cam)
    step = float(np.median(np.diff(grid.z))) if grid.z.size > 1 else 1.0
    # seeds from the calibration's own location, whichever config (stage or full case) came in
    where = _stage_id(ccfg, "depthcal")
    shifts = sorted(float(v) for v in dc["shifts"])
    results = []
    for rep in range(int(dc.get("repeats", 1))):
        # the first volume keeps the seed of a single calibration; repeats get their own
        tag = ("depth-calibration", where) if rep == 0 else ("depth-calibration", where, rep)
        field = case_particles(ccfg, seed=derive_seed(ccfg["seed"], *tag))
        sim = where if rep == 0 else f"{where}/repeat~{rep}"
        imaging = {**ccfg, "stage_ids": {**ccfg.get("stage_ids", {}), "simulate": sim}}

        # the camera traverses: the light volume stays with the particles, lit before the shift
        lit = case_illuminated(ccfg, field)

        def volume(frame: str, shift: float, imaging=imaging, lit=lit) -> xr.DataArray:
            img = case_image(imaging, lit.assign(z=lit["z"] + shift), frame, progress=progress, illuminate=False)
            return render_frame(img, centers, ccfg, progress=progress, calibration=calibration)[2].load()

        ref = volume("calibration_0", 0.0)
        for i, s in enumerate(shifts):
            results.append((s * step, case_piv(ccfg, ref, volume(f"calibration_{i + 1}", s * step))))
    out = depth_response(results, min_gain=float(dc["min_gain"]))
    out["shift_voxels"] = ("shift", out["shift"].values / step, {"units": "voxel", "long_name": "traverse"})
    out.attrs.update(io.provenance(ccfg, None))
    return out


def render_volume(
    raw: xr.DataArray, centers: xr.Dataset, ccfg: Mapping[str, Any], *, progress: bool = False
) -> tuple[xr.DataArray, xr.DataArray, xr.DataArray]:
    """The chain raw image → light field → focal stack → volume of one case config
    (``progress``: the reconstruction's progress bar).

    Returns
    -------
    lightfield, stack, volume : xarray.DataArray
        The stack (rendered once, persisted) and the volume are on the case's
        reconstruction grid.
    """
    return render_frame(raw, centers, ccfg, progress=progress)[:3]


def render_frame(
    raw: xr.DataArray,
    centers: xr.Dataset,
    ccfg: Mapping[str, Any],
    *,
    progress: bool = False,
    calibration: xr.Dataset | None = None,
) -> tuple[xr.DataArray, xr.DataArray, xr.DataArray, xr.Dataset | None]:
    """:func:`render_volume` and the particle list of a method that fits particles
    (:func:`case_reconstruction`; None for the others); ``calibration``: the volumetric one
    (:func:`case_volcal`) where ``refocus.model`` is ``volumetric``."""
    from lfstudy.lightfield.registration import register

    lf = register(raw, centers, case_camera(ccfg))
    # persist: the reconstruction and the caller's write both read the stack
    stack = case_stack(ccfg, lf, calibration).persist()
    return (lf, stack, *case_reconstruction(ccfg, stack, lf, centers, progress=progress, calibration=calibration))
