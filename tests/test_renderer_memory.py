"""renderer/memory.py's figures against what the renderer does: a unit's film
is the layout's bytes (camera sums, AOVs, jackknife sums, whole-frame
splats, SPPM's state), and what a render process allocates for a unit grows
with its pixels no faster than the figure for it (tracemalloc: numpy
reports its arrays), and not a lot slower either. A local pool keeps no
film it handed over."""

from __future__ import annotations

import pickle
import tracemalloc

import pytest

from renderer import METHODS, PartialFilm, RenderSpec, load_scene
from renderer.memory import job_memory
from renderer.runtime import run_unit

# method -> (options, the unit kinds whose films grow with the frame)
METHOD_UNITS = {
    "path-mis": ({}, {"tile"}),
    "raster": ({}, {"tile"}),
    "bdpt": ({}, {"tile"}),
    "light": ({}, {"splat"}),
    "mlt": ({"chains": 16}, {"chains"}),
    "photon": ({}, {"gather"}),
    "radiosity": ({}, {"tile"}),
}


@pytest.fixture(scope="module")
def cornell():
    return load_scene("cornell-box")


def largest_unit(scene, spec: RenderSpec, kinds: set[str]) -> tuple[int, int]:
    """(traced peak, film bytes) of the job's unit of `kinds` that allocates
    the most: its inputs as bytes and decoded, its render, its film's bytes
    and the pipe's pickled message, as a render process has them."""
    films: dict[int, PartialFilm] = {}
    worst = (0, 0)
    for unit in METHODS[spec.method].make_plan(spec, False):
        traced = unit.kind in kinds
        if traced:
            tracemalloc.start()
        wire = {i: films[i].to_bytes() for i in unit.needs}
        film = run_unit(scene, spec, unit, {i: PartialFilm.from_bytes(b) for i, b in wire.items()})
        data = film.to_bytes()
        del film, wire
        message = pickle.dumps((True, data, None))
        del message
        if traced:
            worst = max(worst, (tracemalloc.get_traced_memory()[1], len(data)))
            tracemalloc.stop()
        films[unit.index] = PartialFilm.from_bytes(data)
    return worst


@pytest.mark.parametrize("method", sorted(METHOD_UNITS))
def test01_a_units_film_and_peak_follow_the_layout(method, cornell):
    options, kinds = METHOD_UNITS[method]
    measured = {}
    for size in (48, 96):  # one tile: the unit is the frame
        spec = RenderSpec(method=method, width=size, height=size, tile_size=size, spp=2,
                          depth=3, options=options).validate()
        peak, film_bytes = largest_unit(cornell, spec, kinds)
        mem = job_memory(spec)
        # the film is the layout's bytes, up to the header and small artefacts
        assert abs(film_bytes - mem.unit_film) <= 4096 + 0.01 * film_bytes, (
            size, film_bytes, mem.unit_film)
        assert peak <= mem.unit, (size, peak, mem.unit)
        measured[size] = (peak, mem.unit, size * size)
    (p1, u1, n1), (p2, u2, n2) = measured[48], measured[96]
    grows, figured = (p2 - p1) / (n2 - n1), (u2 - u1) / (n2 - n1)
    assert grows <= figured <= 4 * grows + 64, (grows, figured)  # bytes a pixel


def test02_a_pool_keeps_no_film_it_handed_over():
    """The slot thread that received a unit's film waits for the next unit
    without it (it used to keep the last film and inputs: a 2048^2 tile's
    470 MB stayed in the service after its job)."""
    import gc

    from renderer import LocalPool, plan, resolve_document
    from renderer.runtime import scene_text

    spec = RenderSpec(method="raster", width=512, height=512, tile_size=512, spp=1, depth=1)
    key, text = scene_text(resolve_document("cornell-box"))
    with LocalPool(1) as pool:
        tracemalloc.start()
        try:
            future = pool.submit(key, text, spec.to_dict(), plan(spec)[0].to_dict())
            size = len(future.result(timeout=300))
            del future
            gc.collect()
            held = tracemalloc.get_traced_memory()[0]
        finally:
            tracemalloc.stop()
    assert size > 20_000_000 and held < size // 4, (size, held)


@pytest.mark.parametrize("method", sorted(METHOD_UNITS))
def test03_the_stored_figure_bounds_the_films_a_job_leaves(method, cornell):
    """`JobMemory.stored`, which admission holds against a role's store limit,
    is at least the bytes of every unit film a job leaves in the store (but a
    radiosity solution, which is the scene's), and not far above them:
    photon maps are figured at 4 records a photon, cornell-box leaves about
    one. BDPT's every tile of every pass carries the frame's splats."""
    options, _ = METHOD_UNITS[method]
    spec = RenderSpec(method=method, width=48, height=32, tile_size=16, spp=8, depth=3,
                      options=options).validate()
    for progressive in (False, True):
        films: dict[int, bytes] = {}
        for unit in METHODS[method].make_plan(spec, progressive):
            inputs = {i: PartialFilm.from_bytes(films[i]) for i in unit.needs}
            films[unit.index] = run_unit(cornell, spec, unit, inputs).to_bytes()
        kinds = {u.index: u.kind for u in METHODS[method].make_plan(spec, progressive)}
        stored = sum(len(b) for i, b in films.items() if kinds[i] != "solve")
        figure = job_memory(spec, progressive=progressive).stored
        headers = 4096 * len(films)  # a film's header and small artefacts
        assert stored <= figure + headers, (progressive, stored, figure)
        assert figure <= 4 * stored, (progressive, stored, figure)
