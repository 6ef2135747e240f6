"""Mitsuba BSDFs as native materials: diffuse, mirror, glossy, dielectric;
wrappers (twosided, mask, bump maps, blends) unwrapped, and whatever is
approximated reported."""

from __future__ import annotations

import math

from ...assets import asset_header
from ...errors import SceneError
from .values import _Obj
from .xmltree import _Node

# Mitsuba 3's table of named indices of refraction.
IOR_NAMES = {
    "vacuum": 1.0, "helium": 1.000036, "hydrogen": 1.000132, "air": 1.000277,
    "carbon dioxide": 1.00045, "water": 1.3330, "acetone": 1.36, "ethanol": 1.361,
    "carbon tetrachloride": 1.461, "glycerol": 1.4729, "benzene": 1.501,
    "silicone oil": 1.52045, "bromine": 1.661, "water ice": 1.31, "fused quartz": 1.458,
    "pyrex": 1.470, "acrylic glass": 1.49, "polypropylene": 1.49, "bk7": 1.5046,
    "sodium chloride": 1.544, "amber": 1.55, "pet": 1.575, "diamond": 2.419,
}
# RGB (eta, k) of the conductors scenes name most, as Mitsuba's RGB modes see them.
CONDUCTORS = {
    "Ag": ((0.155265, 0.116723, 0.138342), (4.82835, 3.12225, 2.14696)),
    "Al": ((1.65746, 0.880369, 0.521229), (9.22387, 6.26952, 4.837)),
    "Au": ((0.143119, 0.374957, 1.44248), (3.98316, 2.38572, 1.60322)),
    "Cu": ((0.200438, 0.924033, 1.10221), (3.91295, 2.45285, 2.14219)),
    "Cr": ((4.36968, 2.9167, 1.6547), (5.20643, 4.23136, 3.75495)),
}


def _fresnel0(eta, k) -> list[float]:
    """A conductor's reflectance at normal incidence."""
    return [((n - 1) ** 2 + kk * kk) / ((n + 1) ** 2 + kk * kk) for n, kk in zip(eta, k)]


class BsdfMapper:
    """BSDFs (a base of scene._Importer)."""

    def material(self, node: _Node) -> str:
        """The name of the native material a bsdf element maps to."""
        key = id(node)
        if key not in self.material_of:
            mat = self.bsdf(node)
            base = node.attrs.get("id") or self.anonymous("bsdf", node)
            name, i = base, 1
            while name in self.materials:
                i += 1
                name = f"{base}#{i}"
            self.materials[name] = mat
            self.material_of[key] = name
        return self.material_of[key]

    def bsdf(self, node: _Node) -> dict:
        self.enter(node)
        try:
            return self._bsdf(node)
        finally:
            self.map_stack.pop()

    def _nested_bsdf(self, obj: _Obj, node: _Node) -> tuple[dict, list[_Node]]:
        inner = obj.children("bsdf")
        if not inner:
            raise SceneError(f"a {obj.type} bsdf needs a nested bsdf", node.loc)
        return self.bsdf(inner[0]), inner

    def _bsdf(self, node: _Node) -> dict:
        obj = _Obj(self, node)
        t = obj.type
        if t == "twosided":
            mat, inner = self._nested_bsdf(obj, node)
            if len(inner) > 1:
                self.note(inner[1], "approximated: the back side uses the front side's bsdf "
                                    "(rayfarm's two-sided materials are the same on both sides)")
            mat = dict(mat)
            if mat["type"] != "dielectric":
                mat["twosided"] = True
            obj.finish(("bsdf",))
            return mat
        if t == "mask":
            opacity = self._opacity(obj, node)
            mat, inner = self._nested_bsdf(obj, node)
            inner_opacity = mat.get("opacity")
            if mat["type"] == "null" or opacity == 1.0:
                pass  # invisible already, or opaque
            elif inner_opacity is None:
                mat = {**mat, "opacity": opacity}
            elif not isinstance(opacity, dict) and not isinstance(inner_opacity, dict):
                mat = {**mat, "opacity": opacity * inner_opacity}  # a mask in a mask
            else:
                self.note(node, "approximated: the textured opacity of the nested mask is "
                                "replaced by this one")
                mat = {**mat, "opacity": opacity}
            obj.finish(("bsdf",))
            return mat
        if t in ("bumpmap", "normalmap", "coating", "roughcoating"):
            mat, _ = self._nested_bsdf(obj, node)
            what = {"bumpmap": "the bump map", "normalmap": "the normal map"}.get(
                t, "the dielectric coating")
            self.note(node, f"approximated: {what} is ignored, the nested bsdf renders without it")
            for key in list(obj.props):
                obj.ignore(key)
            obj.finish(("bsdf", "texture"))
            return mat
        if t == "blendbsdf":
            inner = obj.children("bsdf")
            if len(inner) != 2:
                raise SceneError("a blendbsdf needs two nested bsdfs", node.loc)
            weight = obj.scalar_or_texture("weight", 0.5)
            w = 0.5 if isinstance(weight, dict) else weight
            pick = 1 if w > 0.5 else 0
            self.note(node, f"approximated by its {'second' if pick else 'first'} bsdf alone "
                            f"(blend weight {'textured' if isinstance(weight, dict) else w})")
            mat = self.bsdf(inner[pick])
            obj.finish(("bsdf",))
            return mat
        if t in ("diffuse", "roughdiffuse"):
            mat = {"type": "diffuse", "albedo": obj.color("reflectance", 0.5)}
            if t == "roughdiffuse":
                alpha = obj.scalar_or_texture("alpha", 0.2)
                obj.ignore("use_fast_approx")
                self.note(node, "approximated as diffuse (Lambertian, reflectance = reflectance): "
                                f"the Oren-Nayar roughness alpha = {alpha} is ignored")
            obj.finish()
            return mat
        if t in ("plastic", "roughplastic", "pplastic"):
            mat = {"type": "diffuse", "albedo": obj.color("diffuse_reflectance", 0.5)}
            for key in ("int_ior", "ext_ior", "nonlinear", "alpha", "distribution",
                        "specular_reflectance", "sample_visible"):
                obj.ignore(key)
            self.note(node, "approximated as diffuse (reflectance = diffuse_reflectance): the "
                            "specular coating is dropped")
            obj.finish()
            return mat
        if t in ("conductor", "roughconductor"):
            return self._conductor(obj, node)
        if t in ("dielectric", "roughdielectric", "thindielectric"):
            return self._dielectric(obj, node)
        if t == "null":
            obj.finish()
            return {"type": "null"}  # the shape decides: left out, or a black emitter
        if t == "principled":
            base = obj.color("base_color", 0.5)
            metallic = obj.float("metallic", 0.0)
            rough = obj.float("roughness", 0.5)
            for key in list(obj.props):
                obj.ignore(key)
            if metallic > 0.5:
                alpha = min(max(rough * rough, 1e-3), 1.0)
                self.note(node, f"approximated as glossy (specular = base_color, roughness = "
                                f"roughness^2 = {alpha:g}): metallic {metallic} > 0.5")
                return {"type": "glossy", "specular": base, "roughness": alpha}
            self.note(node, "approximated as diffuse (reflectance = base_color): "
                            f"metallic {metallic} <= 0.5; the specular lobes are dropped")
            return {"type": "diffuse", "albedo": base}
        for key in list(obj.props):
            obj.ignore(key)
        self.note(node, f"approximated as diffuse (reflectance 0.5): rayfarm has no '{t}' bsdf")
        return {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}

    def _opacity(self, obj: _Obj, node: _Node):
        """A mask's opacity: a number in [0, 1] or a texture, whose value the
        renderer takes as Mitsuba 3's eval_1 does (the luminance of its RGB)."""
        opacity = obj.scalar_or_texture("opacity", 0.5)
        if isinstance(opacity, dict):
            image = self.textures[opacity["texture"]].get("image")
            if image in self.assets and asset_header(self.assets[image])["channels"] == 4:
                self.note(obj.props["opacity"], "the image's alpha channel is not read: as in "
                                                "Mitsuba 3, the opacity is the luminance of its "
                                                "colour")
            return opacity
        if not 0.0 <= opacity <= 1.0:
            clamped = min(max(opacity, 0.0), 1.0)
            self.note(node, f"approximated: opacity {opacity:g} clamped to {clamped:g}")
            opacity = clamped
        return opacity

    def _ior(self, obj: _Obj, key: str, default: str) -> float:
        n = obj.take(key)
        if n is None:
            return IOR_NAMES[default]
        if n.tag == "string":
            name = n.attrs.get("value", "").strip().lower()
            if name not in IOR_NAMES:
                raise SceneError(f"unknown index of refraction '{name}' (named ones: "
                                 f"{', '.join(sorted(IOR_NAMES))})", n.loc)
            return IOR_NAMES[name]
        v = self.float_of(n)
        if not v > 0:
            raise SceneError("an index of refraction must be > 0", n.loc)
        return v

    def _dielectric(self, obj: _Obj, node: _Node) -> dict:
        ior = self._ior(obj, "int_ior", "bk7") / self._ior(obj, "ext_ior", "air")
        notes = []
        if obj.type != "dielectric":
            obj.ignore("alpha")
            obj.ignore("alpha_u")
            obj.ignore("alpha_v")
            obj.ignore("distribution")
            obj.ignore("sample_visible")
            notes.append("a thin sheet rendered as the surface of a solid"
                         if obj.type == "thindielectric" else "its roughness is ignored")
        for key in ("specular_reflectance", "specular_transmittance"):
            n = obj.take(key)
            if n is not None and self.color_of(n, emitter=False, bounded=False,
                                               texture=True) != [1.0, 1.0, 1.0]:
                notes.append(f"{key} is ignored (rayfarm's glass reflects and transmits "
                             "all it does not absorb: none)")
        if ior < 1.0:
            notes.append(f"the relative index {ior:g} < 1 is inverted to {1 / ior:g}")
            ior = 1.0 / ior
        if ior > 4.0:
            notes.append(f"the relative index {ior:g} is clamped to 4")
            ior = 4.0
        if notes:
            self.note(node, f"approximated as smooth dielectric (ior = int_ior / ext_ior = "
                            f"{ior:g}): " + "; ".join(notes))
        obj.finish()
        return {"type": "dielectric", "ior": ior}

    def _conductor(self, obj: _Obj, node: _Node) -> dict:
        spec = obj.color("specular_reflectance", 1.0)
        notes = []
        material = obj.string("material", "none")
        ext = obj.float("ext_eta", 1.0) if not obj.has("ext_eta") or \
            obj.props["ext_eta"].tag != "string" else self._ior(obj, "ext_eta", "air")
        if obj.has("eta") or obj.has("k"):
            eta = obj.color("eta", 0.0, bounded=False, texture=False)
            k = obj.color("k", 1.0, bounded=False, texture=False)
            f0 = _fresnel0([e / ext for e in eta], [kk / ext for kk in k])
            notes.append(f"the conductor's Fresnel term of eta, k is approximated by its "
                         f"reflectance at normal incidence {[round(f, 4) for f in f0]}")
        elif material == "none":
            f0 = [1.0, 1.0, 1.0]
        elif material in CONDUCTORS:
            eta, k = CONDUCTORS[material]
            f0 = _fresnel0([e / ext for e in eta], [kk / ext for kk in k])
            notes.append(f"material '{material}': its Fresnel term is approximated by the "
                         f"reflectance at normal incidence {[round(f, 4) for f in f0]}")
        else:
            f0 = [1.0, 1.0, 1.0]
            notes.append(f"unknown conductor material '{material}' (known: none, "
                         f"{', '.join(sorted(CONDUCTORS))}): rendered as a perfect reflector")
        if isinstance(spec, dict):
            colour = spec
            if f0 != [1.0, 1.0, 1.0]:
                notes.append("the textured specular_reflectance is not scaled by the Fresnel "
                             "reflectance")
        else:
            colour = [min(max(s * f, 0.0), 1.0) for s, f in zip(spec, f0)]
        if obj.type == "conductor":
            mat = {"type": "mirror", "tint": colour}
            kind = "mirror (tint = specular_reflectance x reflectance)"
        else:
            distribution = (obj.string("distribution", "beckmann") or "").lower()
            obj.ignore("sample_visible")
            if obj.has("alpha_u") or obj.has("alpha_v"):
                au, av = obj.float("alpha_u", 0.1), obj.float("alpha_v", 0.1)
                alpha = math.sqrt(au * av)
                obj.ignore("alpha")
                if au != av:
                    notes.append(f"the anisotropic roughness ({au}, {av}) is rendered isotropic "
                                 f"with alpha = sqrt(alpha_u alpha_v) = {alpha:g}")
            else:
                alpha = obj.scalar_or_texture("alpha", 0.1)
            if distribution not in ("ggx", "beckmann"):
                notes.append(f"the {distribution} distribution is rendered as GGX of the same alpha")
            if isinstance(alpha, (int, float)) and alpha < 1e-3:
                mat = {"type": "mirror", "tint": colour if isinstance(colour, list) else
                       [1.0, 1.0, 1.0]}
                kind = "mirror"
                notes.append(f"alpha {alpha:g} is below rayfarm's smallest roughness 0.001")
            else:
                if isinstance(alpha, (int, float)) and alpha > 1.0:
                    notes.append(f"alpha {alpha:g} is clamped to 1")
                    alpha = 1.0
                mat = {"type": "glossy", "specular": colour, "roughness": alpha}
                if distribution == "beckmann":
                    mat["distribution"] = "beckmann"
                kind = (f"glossy ({'Beckmann' if distribution == 'beckmann' else 'GGX'}, "
                        "specular = specular_reflectance x reflectance)")
        if notes:
            self.note(node, f"approximated as {kind}: " + "; ".join(notes))
        obj.finish()
        return mat
