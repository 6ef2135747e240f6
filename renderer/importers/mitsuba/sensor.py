"""The Mitsuba sensor as the native camera: perspective and thin-lens
projections, the film's size and reconstruction filter; the sampler is
reported (the job decides); a default camera for a scene without one."""

from __future__ import annotations

import math

import numpy as np

from ...errors import SceneError
from .values import _numbers, _Obj, look_at
from .xmltree import _Node


class SensorMapper:
    """The sensor, its film and filter (a base of scene._Importer)."""

    def camera(self, node: _Node) -> dict:
        obj = _Obj(self, node)
        t = obj.type
        if t not in ("perspective", "thinlens"):
            raise SceneError(f"unsupported sensor type '{t}' (rayfarm renders perspective and "
                             "thinlens cameras; another projection would be misread)", node.loc)
        cam: dict = {"type": t, "to_world": self.sensor_to_world(obj)}
        films = obj.children("film")
        width, height = 768, 576
        filt: dict = {"type": "gaussian", "stddev": 0.5}
        if films:
            try:
                width, height, filt = self.film(films[0])
            except SceneError as exc:  # a film is never a reason to refuse the file
                self.note(films[0], f"ignored ({exc}): a 768x576 film with a gaussian filter "
                                    "is used")
        if obj.has("fov") and obj.has("focal_length"):
            raise SceneError("give either fov or focal_length, not both", node.loc)
        if obj.has("fov"):
            cam["fov"] = obj.float("fov")
            axis = (obj.string("fov_axis", "x") or "").lower()
            if axis not in ("x", "y", "smaller", "larger", "diagonal"):
                raise SceneError(f"unknown fov_axis '{axis}' (allowed: x, y, smaller, larger, "
                                 "diagonal)", obj.props["fov_axis"].loc)
            cam["fov_axis"] = axis
        else:
            text = obj.string("focal_length", "50mm") or ""
            value = _numbers(text.strip().removesuffix("mm"), node, "focal_length")
            if len(value) != 1 or not value[0] > 0:
                raise SceneError("focal_length must be a length like '50mm'", node.loc)
            cam["fov"] = math.degrees(2 * math.atan(math.hypot(36.0, 24.0) / (2 * value[0])))
            cam["fov_axis"] = "diagonal"
        if t == "thinlens":
            for key, alias in (("aperture_radius", "aperture_radius"),
                               ("focus_distance", "focus_distance")):
                v = obj.float(key)
                if v is None:
                    raise SceneError(f"a thinlens sensor needs {alias}", node.loc)
                cam[key] = v
        for key in ("near_clip", "far_clip"):
            obj.ignore(key, "ignored: rayfarm's camera does not clip")
        for key in ("shutter_open", "shutter_close", "shutter_open_time"):
            obj.ignore(key, "ignored: rayfarm renders no motion blur")
        for key in ("principal_point_offset_x", "principal_point_offset_y"):
            obj.ignore(key, "ignored: rayfarm's image centre is the principal point")
        for s in obj.children("sampler"):
            try:
                self.sampler(s)
            except SceneError as exc:  # the job's spp decides anyway
                self.note(s, f"ignored ({exc})")
        for ch in obj.children("medium"):
            self.note(ch, "ignored: rayfarm renders no participating media")
        cam.update({"width": width, "height": height, "filter": filt})
        obj.finish(("film", "sampler", "medium"))
        return cam

    def sensor_to_world(self, obj: _Obj) -> list:
        """The sensor's to_world: a rotation (or a mirror) and a translation.
        Mitsuba 3 refuses a scale there; a uniform or per-axis scale is divided
        out (reported), a shear refused."""
        m = obj.transform("to_world")
        r = m[:3, :3]
        if np.allclose(r.T @ r, np.eye(3), atol=1e-4):
            return m.tolist()
        lengths = np.linalg.norm(r, axis=0)
        if not np.all(lengths > 0):
            raise SceneError("the sensor's to_world is singular", obj.props["to_world"].loc)
        r = r / lengths
        if not np.allclose(r.T @ r, np.eye(3), atol=1e-4):
            raise SceneError("the sensor's to_world shears: a camera's transform must be a "
                             "rotation (or a mirror) and a translation", obj.props["to_world"].loc)
        self.note(obj.props["to_world"], f"approximated: its scale {lengths.round(6).tolist()} "
                                         "is divided out (a camera's transform has none; "
                                         "Mitsuba 3 refuses it)")
        m = m.copy()
        m[:3, :3] = r
        return m.tolist()

    def sampler(self, node: _Node) -> None:
        obj = _Obj(self, node)
        spp = obj.int("sample_count", None)
        self.note(node, "ignored: the job's sampler and spp decide" +
                  (f" (the file asks for {spp} samples per pixel)" if spp is not None else ""))
        for key in list(obj.props):
            obj.ignore(key)

    def film(self, node: _Node) -> tuple[int, int, dict]:
        obj = _Obj(self, node)
        width, height = obj.int("width", 768), obj.int("height", 576)
        if not (1 <= width <= 8192 and 1 <= height <= 8192):
            raise SceneError(f"the film's size {width}x{height} is outside 1 to 8192", node.loc)
        if obj.type not in ("hdrfilm", "ldrfilm", "specfilm"):
            self.note(node, f"approximated as hdrfilm: rayfarm has no '{obj.type}' film")
        elif obj.type == "ldrfilm":
            self.note(node, "approximated: rayfarm writes an HDR EXR (and a tonemapped PNG "
                            "preview) instead of a low dynamic range image")
        for key in ("crop_offset_x", "crop_offset_y", "crop_width", "crop_height"):
            obj.ignore(key, "ignored: rayfarm renders the whole frame")
        for key in ("filename", "file_format", "pixel_format", "component_format", "gamma",
                    "banner", "high_quality_edges", "exposure", "tonemap_method", "attach_log",
                    "sample_border", "rfilter"):
            obj.ignore(key, "ignored: the job decides the output; rayfarm writes an EXR")
        filt = {"type": "gaussian", "stddev": 0.5}
        filters = obj.children("rfilter")
        if filters:
            filt = self.rfilter(filters[0])
        obj.finish(("rfilter",))
        return width, height, filt

    def rfilter(self, node: _Node) -> dict:
        obj = _Obj(self, node)
        t = obj.type
        if t == "box":
            r = obj.float("radius", 0.5)
            if r != 0.5:
                self.note(obj.props["radius"], "ignored: rayfarm's box filter is one pixel wide")
            out = {"type": "box"}
        elif t == "tent":
            out = {"type": "tent", "radius": self._clamped(obj, "radius", 1.0, 0.01, 8.0)}
        elif t == "gaussian":
            out = {"type": "gaussian", "stddev": self._clamped(obj, "stddev", 0.5, 0.01, 2.0)}
        else:
            for key in list(obj.props):
                obj.ignore(key)
            self.note(node, f"approximated as a gaussian of stddev 0.5: rayfarm has no '{t}' "
                            "filter")
            out = {"type": "gaussian", "stddev": 0.5}
        obj.finish()
        return out

    def _clamped(self, obj: _Obj, key: str, default: float, lo: float, hi: float) -> float:
        v = obj.float(key, default)
        if not lo <= v <= hi:
            clamped = min(max(v, lo), hi)
            self.note(obj.props[key], f"clamped to {clamped:g}: rayfarm's filters take {lo:g} "
                                      f"to {hi:g} pixels")
            return clamped
        return v

    def default_camera(self, scene: _Node) -> dict:
        """Mitsuba 3's camera for a scene without one: fov 45 along x, looking
        along +z at the bounds' centre from far enough to see them."""
        if not self.bounds:
            raise SceneError("the scene has no sensor, and no geometry whose bounds could frame "
                             "a default camera", scene.loc)
        pts = np.concatenate(self.bounds)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        center, extent = (lo + hi) / 2, float(np.max(hi - lo))
        distance = extent / (2 * math.tan(math.radians(45 / 2)))
        origin = [center[0], center[1], lo[2] - distance]
        self.note(scene, "no sensor: a default perspective camera (fov 45) looks along +z at the "
                         "scene's bounds, as Mitsuba 3 frames it")
        return {"type": "perspective",
                "to_world": look_at(origin, center, [0.0, 1.0, 0.0]).tolist(),
                "fov": 45.0, "fov_axis": "x", "width": 768, "height": 576,
                "filter": {"type": "gaussian", "stddev": 0.5}}
