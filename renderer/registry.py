"""The one registry of rendering methods and pixel samplers: a plain table.

Every list of valid names anywhere in rayfarm (the API's validation, `GET
/methods`, the CLI's choices) is read from here. A method declares its
options as a table (name, type, default, allowed values, meaning) the way
Mitsuba's plugins do; unknown options are refused with their names.

The table is filled by `renderer/integrators/__init__.py` (the methods) and
the sampler modules (renderer/samplers/) when the `renderer` package is
imported; this module imports neither. A plugin never looks itself up here:
the `Method` hands its callables their checked options.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

from .errors import SpecError

__all__ = ["Option", "Method", "Sampler", "METHODS", "SAMPLERS", "register_method",
           "register_sampler", "shading_features"]


@dataclass(frozen=True)
class Option:
    name: str
    type: type
    default: Any
    description: str
    choices: tuple | None = None
    bounds: tuple | None = None  # (lowest, highest) allowed number, either may be None
    # A last check of the value: returns an error message, or None if it is fine
    # (for what choices and bounds cannot say, like BDPT's 's=K').
    check: Callable[[Any], str | None] | None = None


def _check_bounds(name: str, opt: Option, value: Any) -> None:
    lo, hi = opt.bounds
    kinds = int if opt.type is int else (int, float)
    if isinstance(value, bool) or not isinstance(value, kinds):
        what = "an integer" if opt.type is int else "a number"
        raise SpecError(f"options.{name}", f"must be {what}, got {value!r}")
    if not math.isfinite(value):  # NaN passes every comparison below; inf is no size
        raise SpecError(f"options.{name}", f"must be a finite number, got {value!r}")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise SpecError(f"options.{name}", f"must be between {lo} and {hi}, got {value!r}")


@dataclass(frozen=True)
class Method:
    """A rendering method: `run(scene, spec, unit, inputs, options) -> PartialFilm`,
    where `inputs` maps the indices in `unit.needs` to those units' films and
    `options` are the job's options checked against the method's table, with
    defaults (`check_options`).

    `plan(spec, progressive, options) -> list[Unit]` cuts a job into units:
    the tile plan (image tiles x sample passes, `renderer.plan.plan`) or, for
    methods of other families, a DAG (renderer/plan.py); `phases` names their
    unit kinds in the order they run, for the dashboard.

    `check_scene(spec, doc, options)`, if given, checks what the options mean
    on one scene (a resolved document) and raises `SpecError`:
    `RenderSpec.validate` calls it when it is handed the scene, so a job that
    could only fail on the farm is refused at submission.

    `warm_options` are option sets whose kernels the defaults do not compile
    (photon's `photonmap` mode: a k-NN kernel of its own, 38 s to compile on
    a 2-core machine): `renderer.warm_up` renders each of them too, so no
    unit of any job compiles in a render process. `warm_base` holds options
    every warm-up render adds: the same kernels for less work (radiosity: a
    coarse mesh and few form-factor rays, since warm-up runs in every render
    process's start).
    """

    name: str
    description: str
    run: Callable
    plan: Callable
    options: tuple[Option, ...] = ()
    family: str = "tile"  # how jobs split: "tile", "splat", "chains", "photons", "radiosity"
    aliases: tuple[str, ...] = field(default=())
    phases: tuple[str, ...] = ("tile",)
    check_scene: Callable | None = None
    warm_options: tuple[dict, ...] = field(default=(), compare=False)
    warm_base: dict = field(default_factory=dict, compare=False)
    # What a scene may use that this method does not render, each with the
    # reason: {"textures": why, ...} (keys of `shading_features`); a job of
    # a scene using one is refused at submission, naming it.
    unsupported: dict = field(default_factory=dict, compare=False)
    # The AOV layers (film.py) its films carry beyond the beauty, var and
    # samples, and, when there are none, why: what GET /methods says.
    aovs: tuple[str, ...] = ()
    aov_note: str = "writes no albedo, normal or depth layers yet"

    def render(self, scene, spec, unit, inputs: dict | None = None):
        """Run one unit of a job of this method (its options checked here)."""
        return self.run(scene, spec, unit, inputs or {}, self.check_options(spec.options))

    def make_plan(self, spec, progressive: bool = False) -> list:
        return self.plan(spec, progressive, self.check_options(spec.options))

    def check(self, spec, doc: dict) -> None:
        """`check_scene` with the checked options, if the method has one;
        and the scene's shading features against `unsupported`."""
        for feature in shading_features(doc):
            if feature in self.unsupported:
                raise SpecError("method", f"method '{self.name}' does not render "
                                          f"{feature} ({self.unsupported[feature]}); this "
                                          "scene uses them: choose another method")
        if self.check_scene is not None:
            self.check_scene(spec, doc, self.check_options(spec.options))

    def check_options(self, options: dict) -> dict:
        known = {o.name: o for o in self.options}
        unknown = sorted(set(options) - set(known))
        if unknown:
            allowed = ", ".join(known) or "none"
            raise SpecError("options", f"unknown option(s) for method '{self.name}': "
                                       f"{', '.join(unknown)} (allowed: {allowed})")
        out = {}
        for name, opt in known.items():
            value = options.get(name, opt.default)
            if opt.choices is not None and value not in opt.choices:
                raise SpecError(f"options.{name}", f"must be one of {', '.join(map(str, opt.choices))}, "
                                                   f"got {value!r}")
            if opt.bounds is not None:
                _check_bounds(name, opt, value)
            if opt.check is not None and name in options:
                problem = opt.check(value)
                if problem:
                    raise SpecError(f"options.{name}", problem)
            out[name] = value
        return out

    def describe(self) -> dict:
        return {"name": self.name, "aliases": list(self.aliases), "description": self.description,
                "family": self.family, "phases": list(self.phases),
                "aovs": list(self.aovs), "aov_note": None if self.aovs else self.aov_note,
                "options": [{"name": o.name, "type": o.type.__name__, "default": o.default,
                             "choices": list(o.choices) if o.choices else None,
                             "bounds": list(o.bounds) if o.bounds else None,
                             "description": o.description} for o in self.options]}


def shading_features(doc: dict) -> list[str]:
    """What a resolved scene document asks of shading beyond constant
    one-sided opaque materials: "textures", "textured glossy inputs",
    "two-sided materials", "opacity masks". (Vertex normals live in the mesh
    assets, not in the document: every method takes them, radiosity as flat
    patches.)"""
    out = []
    mats = doc.get("materials", {}).values()
    if any(isinstance(v, dict) for m in mats for v in m.values()):
        out.append("textures")
    if any(m["type"] == "glossy" and (isinstance(m.get("specular"), dict)
                                      or isinstance(m.get("roughness"), dict)) for m in mats):
        out.append("textured glossy inputs")
    if any(m.get("twosided") for m in mats):
        out.append("two-sided materials")
    if any("opacity" in m for m in mats):
        out.append("opacity masks")
    return out


@dataclass(frozen=True)
class Sampler:
    name: str
    id: int  # the integer the kernels switch on
    description: str

    def describe(self) -> dict:
        return {"name": self.name, "description": self.description}


METHODS: dict[str, Method] = {}
SAMPLERS: dict[str, Sampler] = {}


def register_method(method: Method) -> Method:
    for name in (method.name, *method.aliases):
        if name in METHODS:
            raise ValueError(f"method {name!r} registered twice")
        METHODS[name] = method
    return method


def register_sampler(sampler: Sampler) -> Sampler:
    if sampler.name in SAMPLERS:
        raise ValueError(f"sampler {sampler.name!r} registered twice")
    SAMPLERS[sampler.name] = sampler
    return sampler
