"""Integrators: one module per family of rendering methods, and the table of
them. Each module defines its `Method`s in `METHODS` (a tuple) and knows
nothing of the registry's table; this module fills it, in the order `GET
/methods` lists them. Shared pieces that are not methods live beside them
(`tile`) or in renderer/kernels (BDPT's subpaths, which light tracing and
MLT use too, are `kernels/subpaths.py`) and renderer/samplers: no integrator
imports another."""

from ..registry import register_method
from . import bdpt, light, mlt, path, photon, radiosity, raster

for _module in (path, raster, bdpt, light, photon, radiosity, mlt):
    for _method in _module.METHODS:
        register_method(_method)
