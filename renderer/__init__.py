"""rayfarm's renderer: a library on its own.

Scene documents, the method and sampler registry, the job compiler (`plan`),
the unit runner and the film merge, and a local process-pool executor::

    from renderer import RenderSpec, render
    film = render("cornell-box", RenderSpec(method="path", spp=64, depth=7))
    film.write_exr("cornell.exr", {"method": "path"})
"""

from .errors import RenderError, SceneError, SpecError
from .film import Film, PartialFilm, merge, read_exr, sample_blocks
from .local import LocalPool, RenderProcessDied, UnitStopped, process_death, render
from .plan import Unit, plan
from .registry import METHODS, SAMPLERS
from . import integrators  # noqa: F401,E402 (fills the registry's table)
from .runtime import execute_unit, render_serial, run_plan, run_unit, scene_text, warm_up
from .scene import Scene, build_scene, load_scene
from .scene_format import builtin_scene_names, resolve_document, scene_hash
from .spec import BOUNDS, DEFAULT_MAX_WORK, RenderSpec

__all__ = [
    "BOUNDS", "DEFAULT_MAX_WORK", "Film", "LocalPool", "METHODS", "PartialFilm", "RenderError",
    "RenderProcessDied", "RenderSpec", "SAMPLERS", "Scene", "SceneError", "SpecError", "Unit", "build_scene",
    "builtin_scene_names", "execute_unit", "load_scene", "merge", "plan", "process_death", "read_exr", "render",
    "render_serial", "resolve_document", "run_plan", "run_unit", "sample_blocks", "scene_hash", "scene_text", "UnitStopped", "warm_up",
]
