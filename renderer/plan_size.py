"""How many work units a job's plan has, counted without building them.

    plan_size(spec, progressive) == len(METHODS[spec.method].make_plan(spec, progressive))

The service counts a job's units before it accepts the job (admission), and
the planners build a Python object per unit: a plan of hundreds of thousands
of units took seconds of CPU (and the GIL of the service that planned it)
only to be counted, a photon job with one iteration per gather unit (a gather
unit per tile and iteration) millions. Tile, BDPT, radiosity and photon plans
are counted from their shape, as `renderer.plan.count_units` counts tiles x
passes; a plan this module does not know (light tracing, MLT: a few dozen
units whatever the job) is built and measured.
"""

from __future__ import annotations

from .plan import count_units
from .registry import METHODS
from .spec import RenderSpec

__all__ = ["plan_size"]


def plan_size(spec: RenderSpec, progressive: bool = False) -> int:
    """len(METHODS[spec.method].make_plan(spec, progressive)); raises what
    `make_plan` raises for options it refuses (`SpecError`)."""
    from .integrators import bdpt, photon, radiosity, tile

    method = METHODS[spec.method]
    options = method.check_options(spec.options)
    if method.plan is tile.tile_plan:
        return count_units(spec, progressive)
    if method.plan is radiosity.plan_radiosity:  # the solve unit, then the tile plan
        return 1 + count_units(spec, progressive)
    if method.plan is bdpt.plan_bdpt:
        units = count_units(spec, progressive, small_passes=True)
        if units < bdpt.MIN_BATCHES and not progressive:
            units = count_units(spec, True, small_passes=True)
        return units
    if method.plan is photon.plan_photon:
        options = photon._typed(options)
        photons = photon.photons_per_iteration(spec, options)
        ranges = max(1, -(-photons // photon.PHOTON_UNIT_MAX))  # photon units of an iteration
        tiles = -(-spec.width // spec.tile_size) * -(-spec.height // spec.tile_size)
        if options["mode"] == photon.PHOTONMAP:  # one map, then one gather round
            return ranges + tiles
        rounds = -(-spec.spp // photon._iterations_per_unit(spec, options))
        return spec.spp * ranges + rounds * tiles
    return len(method.make_plan(spec, progressive))
