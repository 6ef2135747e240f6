"""Mitsuba emitters as native lights: a shape's area emitter, point lights
(spots approximated by them); the others reported and left out."""

from __future__ import annotations

from .values import _Obj
from .xmltree import _Node


class EmitterMapper:
    """Emitters (a base of scene._Importer)."""

    def area_emitter(self, node: _Node) -> dict | None:
        obj = _Obj(self, node)
        if obj.type != "area":
            self.note(node, f"ignored: a shape's emitter must be 'area' for rayfarm, not "
                            f"'{obj.type}'")
            for key in list(obj.props):
                obj.ignore(key)
            return None
        radiance = obj.color("radiance", 1.0, emitter=True, bounded=False, texture=True)
        if isinstance(radiance, dict):
            self.note(obj.props["radiance"], "approximated: a textured radiance is rendered as "
                                             "a constant 1")
            radiance = [1.0, 1.0, 1.0]
        obj.ignore("sampling_weight", "ignored: rayfarm chooses lights by its own weights")
        obj.finish()
        return {"type": "area", "radiance": radiance}

    def emitter(self, node: _Node) -> dict | None:
        obj = _Obj(self, node)
        t = obj.type
        if t in ("point", "spot"):
            m = obj.transform("to_world")
            position = obj.point("position", m[:3, 3].tolist())
            intensity = obj.color("intensity", 1.0, emitter=True, bounded=False, texture=False)
            obj.ignore("sampling_weight", "ignored: rayfarm chooses lights by its own weights")
            if t == "spot":
                for key in ("cutoff_angle", "beam_width", "texture"):
                    obj.ignore(key)
                self.note(node, "approximated as a point light: the cone is ignored, it lights "
                                "every direction with its intensity")
            obj.finish(("texture",))
            return {"type": "point", "position": [float(c) for c in position],
                    "intensity": intensity}
        for key in list(obj.props):
            obj.ignore(key)
        reason = ("an area emitter needs a shape" if t == "area" else
                  f"rayfarm has no '{t}' light yet")
        self.note(node, f"ignored: {reason}; the scene renders without it")
        return None
