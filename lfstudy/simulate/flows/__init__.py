"""Known flows and particle displacement (thesis sec. 4.4).

Flows are vectorised, steady velocity fields ``flow.velocity(x, y, z)`` in the
object frame (mm per unit time). Particles are displaced over Δt by classic
fourth-order Runge–Kutta with many sub-steps (the thesis used 1,000 Euler
sub-steps; RK4 converges far faster, see ``tests/test_particles_flows.py``).

Kinds (``flows.<name>.kind`` in a config, built by :func:`flow_from_config`):
``uniform`` and ``hill`` (Hill's spherical vortex, eqs 4.29–4.36), ``lamb_oseen``
(a Gaussian-core line vortex about any axis), ``vortex_ring`` (Biot–Savart of a
Gaussian-cored ring), ``channel`` (plane Poiseuille), ``blasius`` (laminar
flat-plate boundary layer), ``file`` (a gridded field from zarr or netCDF,
interpolated trilinearly) and kinds of other packages through the entry-point
group ``lfstudy.flows`` (see :mod:`lfstudy.simulate.flows._registry` and the
docs page *Flows*).
"""

from __future__ import annotations

from lfstudy.simulate.flows._analytic import (
    BlasiusBoundaryLayer,
    ChannelFlow,
    HillVortex,
    LambOseenVortex,
    UniformFlow,
    VortexRing,
    blasius_solution,
)
from lfstudy.simulate.flows._core import Flow, FlowError, displace, integrate, true_displacement
from lfstudy.simulate.flows._gridded import GriddedFlow, read_velocity_grid
from lfstudy.simulate.flows._registry import (
    BUILTIN,
    ENTRY_POINT_GROUP,
    available_kinds,
    check_flow_config,
    flow_from_config,
    flow_input_files,
    flow_parameters,
    flow_schema,
    get_flow_class,
    resolve_flow_paths,
)

__all__ = [
    "FlowError",
    "Flow",
    "UniformFlow",
    "HillVortex",
    "LambOseenVortex",
    "VortexRing",
    "ChannelFlow",
    "BlasiusBoundaryLayer",
    "GriddedFlow",
    "blasius_solution",
    "read_velocity_grid",
    "BUILTIN",
    "ENTRY_POINT_GROUP",
    "available_kinds",
    "get_flow_class",
    "flow_parameters",
    "flow_schema",
    "flow_from_config",
    "check_flow_config",
    "resolve_flow_paths",
    "flow_input_files",
    "integrate",
    "displace",
    "true_displacement",
]
