"""Simulation (thesis ch. 4): seeded particle fields, known flows and the plenoptic ray tracer.

Modules: :mod:`~lfstudy.simulate.particles` (sec. 4.3.2, 5.1; diameters, depth margin, illumination),
:mod:`~lfstudy.simulate.flows` (sec. 4.4; analytic flows, a gridded field from a
file, kinds of other packages), :mod:`~lfstudy.simulate.raytrace`
(sec. 4.1–4.3, App. A; the Monte-Carlo reference), :mod:`~lfstudy.simulate.exact`
(the expected image of the same model, without rays), :mod:`~lfstudy.simulate.imperfections`
(the camera imperfections only the imaging sees), :mod:`~lfstudy.simulate.sensor`
(photons, background light, shot and read noise, hot pixels, full well, ADC) and the 1-D teaching simulator
:mod:`~lfstudy.simulate.raytrace1d` (sec. 4.2). Import from this package:
the modules behind it may move.
"""

from __future__ import annotations

from lfstudy.simulate.exact import exact_memory_estimate, render_exact, render_pinhole_exact
from lfstudy.simulate.flows import (
    BlasiusBoundaryLayer,
    ChannelFlow,
    Flow,
    FlowError,
    GriddedFlow,
    HillVortex,
    LambOseenVortex,
    UniformFlow,
    VortexRing,
    available_kinds,
    displace,
    flow_from_config,
    integrate,
    true_displacement,
)
from lfstudy.simulate.imperfections import CameraImperfections, ImperfectionError
from lfstudy.simulate.particles import (
    ParticleError,
    illuminate,
    illumination_profile,
    make_field,
    particle_count,
    particle_diameters,
    pinhole_field,
    seed_particles,
)
from lfstudy.simulate.raytrace import (
    DEFAULT_CHUNKS,
    RaytraceError,
    angle_histograms,
    incidence_angle_bound,
    memory_estimate,
    quantize,
    ray_counts,
    render,
    render_pinhole,
    solid_angle,
    write_image,
)
from lfstudy.simulate.sensor import SensorError, apply_sensor, hot_pixel_mask, lenslet_background, sensor_noise_variance

__all__ = [
    "CameraImperfections",
    "ImperfectionError",
    "ParticleError",
    "particle_count",
    "seed_particles",
    "pinhole_field",
    "make_field",
    "particle_diameters",
    "illumination_profile",
    "illuminate",
    "FlowError",
    "Flow",
    "UniformFlow",
    "HillVortex",
    "LambOseenVortex",
    "VortexRing",
    "ChannelFlow",
    "BlasiusBoundaryLayer",
    "GriddedFlow",
    "available_kinds",
    "flow_from_config",
    "integrate",
    "displace",
    "true_displacement",
    "RaytraceError",
    "DEFAULT_CHUNKS",
    "solid_angle",
    "ray_counts",
    "memory_estimate",
    "render",
    "render_pinhole",
    "quantize",
    "angle_histograms",
    "incidence_angle_bound",
    "write_image",
    "render_exact",
    "render_pinhole_exact",
    "exact_memory_estimate",
    "SensorError",
    "apply_sensor",
    "sensor_noise_variance",
    "hot_pixel_mask",
    "lenslet_background",
]
