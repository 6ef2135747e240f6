"""Materials: glTF's metallic-roughness model mapped onto rayfarm's
materials, with its textures decoded, factors baked in, stored as assets."""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ...assets import asset_digest, encode_texture
from ...errors import SceneError
from ...scene_format import MAX_COORDINATE, MAX_RADIANCE, MIN_ROUGHNESS
from ...textures import read_texture
from .container import _Container

MAX_TEXTURE_BYTES = 512 * 1024 * 1024  # texture assets made, all together
FILTER_NEAREST = 9728
WRAP_REPEAT = 10497
IMAGE_SUFFIX = {"image/png": ".png", "image/jpeg": ".jpg"}


class _Materials(_Container):
    # -- materials ------------------------------------------------------------

    def material(self, mi: int | None) -> tuple[str, dict, list[float] | None, bool]:
        """(native name, native material, area radiance or None, two-sided)."""
        key = -1 if mi is None else mi
        if key in self.materials:
            return self.materials[key]
        if mi is None:
            m, ptr, label = {}, "/materials/default", "default"
            self.note(ptr, "a primitive without a material gets glTF's default material "
                      "(white, metallic 1, roughness 1): a rough white conductor")
        else:
            m, ptr = self.item("materials", mi)
            label = self.get(m, "name", ptr, "str") or f"material{mi}"
        name = label if label not in self.material_names else f"{label}#{key}"
        while name in self.material_names:
            name += "'"
        self.material_names.add(name)
        what = f'"{label}"'
        pbr = self.obj(self.get(m, "pbrMetallicRoughness", ptr, "obj", default={}),
                       f"{ptr}/pbrMetallicRoughness")
        pptr = f"{ptr}/pbrMetallicRoughness"
        base = self.numbers(pbr, "baseColorFactor", pptr, 4, [1, 1, 1, 1], 0, 1)
        metallic = self.number(pbr, "metallicFactor", pptr, 1.0, 0, 1)
        rough = self.number(pbr, "roughnessFactor", pptr, 1.0, 0, 1)
        self.other_extensions(pbr, pptr, (), what)
        double = self.get(m, "doubleSided", ptr, "bool", default=False)
        alpha_mode = self.get(m, "alphaMode", ptr, "str", default="OPAQUE")
        if alpha_mode not in ("OPAQUE", "MASK", "BLEND"):
            raise self.fail(f"unknown alphaMode {alpha_mode!r}", f"{ptr}/alphaMode")
        cutoff = self.number(m, "alphaCutoff", ptr, 0.5, 0, math.inf)
        for tex in ("normalTexture", "occlusionTexture"):
            if tex in m:
                self.texture_info(m, tex, ptr)  # validated, then reported
                self.note(f"{ptr}/{tex}", "ignored: " + (
                    "rayfarm has no normal mapping yet" if tex == "normalTexture" else
                    "a path tracer computes occlusion itself"), what)
        handled = ("KHR_materials_emissive_strength", "KHR_materials_transmission",
                   "KHR_materials_ior")
        self.other_extensions(m, ptr, handled, what)

        base_tex = self.texture_info(pbr, "baseColorTexture", pptr)
        mr_tex = self.texture_info(pbr, "metallicRoughnessTexture", pptr)
        base_img = self.texels(base_tex, raw=False) if base_tex else None
        mr_img = self.texels(mr_tex, raw=True) if mr_tex else None

        transmission = 0.0
        tx = self.extension(m, ptr, "KHR_materials_transmission")
        if tx is not None:
            xptr = f"{ptr}/extensions/KHR_materials_transmission"
            transmission = self.number(tx, "transmissionFactor", xptr, 0.0, 0, 1)
            if "transmissionTexture" in tx:
                self.texture_info(tx, "transmissionTexture", xptr)
                self.note(xptr, "transmissionTexture ignored: transmissionFactor is used "
                          "everywhere", what)
        ior = 1.5
        ix = self.extension(m, ptr, "KHR_materials_ior")
        if ix is not None:
            ior = self.number(ix, "ior", f"{ptr}/extensions/KHR_materials_ior", 1.5, 0, 10)
            if ior == 0:  # the extension's way of saying "no refraction": an ior of 1
                ior = 1.0

        metal_mean = metallic
        if mr_img is not None:
            metal_tex = metallic * mr_img[..., 2 if mr_img.shape[2] >= 3 else 0]
            metal_mean = float(metal_tex.mean())
            if metal_tex.min() < 0.5 <= metal_tex.max():
                self.note(pptr, "metallicRoughnessTexture: metallic varies across the texture; "
                          f"the whole surface is approximated as "
                          f"{'metal' if metal_mean >= 0.5 else 'non-metal'} (mean "
                          f"{metal_mean:.2f})", what)
        out: dict[str, Any]
        if transmission >= 0.5:
            if not 1.0 <= ior <= 4.0:
                self.note(ptr, f"ior {ior:g} clamped into [1, 4]", what)
                ior = min(max(ior, 1.0), 4.0)
            out = {"type": "dielectric", "ior": ior}
            self.note(ptr, f"approximated as a smooth dielectric (ior {ior:g}): "
                      "baseColor, roughness and metallic are not rendered"
                      + (f"; transmission {transmission:g} rounded to 1" if transmission < 1
                         else ""), what)
        else:
            if transmission > 0:
                self.note(ptr, f"transmission {transmission:g} rounded to 0 (opaque)", what)
            colour: Any = base[:3]
            if base_img is not None:
                colour = self.baked(base_tex, "base_color", np.clip(
                    _rgb(base_img) * np.asarray(base[:3], np.float32), 0, 1), name)
            if metal_mean >= 0.5:
                out = {"type": "glossy", "specular": colour,
                       "roughness": self.roughness(rough, mr_img, mr_tex, name, what, ptr)}
                if metal_mean < 1:
                    self.note(ptr, f"metallic {metal_mean:.2f} approximated as 1: a GGX conductor "
                              "(specular = baseColor, alpha = roughness^2)", what)
            else:
                out = {"type": "diffuse", "albedo": colour}
                self.note(ptr, "approximated as diffuse (albedo = baseColor): the dielectric "
                          "specular layer of the metallic-roughness model is not rendered"
                          + (f"; metallic {metal_mean:.2f} rounded to 0" if metal_mean > 0
                             else ""), what)
            if double:
                out["twosided"] = True
            out.update(self.opacity(alpha_mode, cutoff, base[3], base_img, base_tex, name, what,
                                    ptr))
        if out["type"] == "dielectric" and alpha_mode != "OPAQUE":
            self.note(ptr, f"alphaMode {alpha_mode} ignored on a transmissive material", what)
        emission = self.emission(m, ptr, name, what, double)
        if emission is not None and "opacity" in out:
            out = {k: v for k, v in out.items() if k not in ("opacity", "opacity_cutoff")}
            self.note(ptr, f"alphaMode {alpha_mode} ignored on an emissive material (rayfarm's "
                      "area lights have no masks)", what)
        self.materials[key] = (name, out, emission, double)
        return self.materials[key]

    def roughness(self, rough: float, mr_img, mr_tex, name: str, what: str, ptr: str):
        """The GGX alpha: glTF's roughness squared, at least MIN_ROUGHNESS."""
        if mr_img is not None:
            g = mr_img[..., 1 if mr_img.shape[2] >= 3 else 0]
            alpha = np.clip((rough * g) ** 2, MIN_ROUGHNESS, 1.0).astype(np.float32)
            if (rough * g).min() ** 2 < MIN_ROUGHNESS:
                self.note(ptr, f"roughness below {math.sqrt(MIN_ROUGHNESS):.3f} raised to it "
                          f"(GGX alpha {MIN_ROUGHNESS:g})", what)
            return self.baked(mr_tex, "roughness", alpha[..., None], name)
        alpha = rough * rough
        if alpha < MIN_ROUGHNESS:
            self.note(ptr, f"roughness {rough:g} raised to {math.sqrt(MIN_ROUGHNESS):.4f} "
                      f"(GGX alpha {MIN_ROUGHNESS:g}, the least rayfarm renders)", what)
            alpha = MIN_ROUGHNESS
        return alpha

    def opacity(self, mode: str, cutoff: float, alpha: float, img, tex, name: str, what: str,
                ptr: str) -> dict:
        """The native material's mask fields ({} when opaque): alpha is the
        base colour's alpha times its texture's (linear) alpha channel."""
        if mode == "OPAQUE":
            return {}
        a = np.asarray(alpha if img is None or img.shape[2] not in (2, 4)
                       else img[..., -1] * alpha, np.float32)
        if mode == "MASK":
            self.note(ptr, f"alphaMode MASK: opaque where alpha >= {cutoff:g} (after filtering), "
                      "cut out elsewhere", what)
            if a.min() >= cutoff:  # so is any filtered value: opaque
                return {}
            if a.max() < cutoff or a.ndim == 0:
                return {"opacity": 0.0}
            return {"opacity": self.baked(tex, "opacity", a[..., None], name),
                    "opacity_cutoff": cutoff}
        self.note(ptr, "alphaMode BLEND approximated as opacity = alpha (a stochastic mask, "
                  "as Mitsuba's mask)", what)
        if a.min() >= 1:
            return {}
        if a.ndim == 0:
            return {"opacity": float(a)}
        return {"opacity": self.baked(tex, "opacity", a[..., None], name)}

    def emission(self, m: dict, ptr: str, name: str, what: str, double: bool):
        factor = self.numbers(m, "emissiveFactor", ptr, 3, [0, 0, 0], 0, 1)
        strength = 1.0
        sx = self.extension(m, ptr, "KHR_materials_emissive_strength")
        if sx is not None:
            strength = self.number(sx, "emissiveStrength",
                                   f"{ptr}/extensions/KHR_materials_emissive_strength", 1.0, 0,
                                   MAX_RADIANCE)
        tex = self.texture_info(m, "emissiveTexture", ptr)
        rgb = np.asarray(factor) * strength
        if tex is not None and rgb.max() > 0:
            mean = _rgb(self.texels(tex, raw=False)).reshape(-1, 3).mean(axis=0)
            rgb = rgb * mean
            self.note(f"{ptr}/emissiveTexture", "approximated: the area light's radiance is "
                      f"emissiveFactor x the texture's mean ({', '.join(f'{c:.3g}' for c in mean)})",
                      what)
        if rgb.max() <= 0:
            return None
        if rgb.max() > MAX_RADIANCE:
            raise self.fail(f"emitted radiance {rgb.max():g} exceeds {MAX_RADIANCE:g}", ptr)
        if double:
            self.note(ptr, "emission from the front side only (rayfarm's area lights are "
                      "one-sided)", what)
        return [float(c) for c in rgb]

    # -- textures -------------------------------------------------------------

    def texture_info(self, o: dict, key: str, ptr: str) -> dict | None:
        """A textureInfo, resolved: texture and image indices, sampler, uv transform."""
        if key not in o:
            return None
        tptr = f"{ptr}/{key}"
        info = self.obj(o[key], tptr)
        ti = self.index(info, "index", tptr, "textures", required=True)
        tex_coord = self.get(info, "texCoord", tptr, "int", default=0)
        for field in ("scale", "strength"):
            if field in info:
                self.get(info, field, tptr, "number")
        tx = self.extension(info, tptr, "KHR_texture_transform")
        scale, offset = [1.0, 1.0], [0.0, 0.0]
        if tx is not None:
            xptr = f"{tptr}/extensions/KHR_texture_transform"
            offset = self.numbers(tx, "offset", xptr, 2, [0, 0], -MAX_COORDINATE, MAX_COORDINATE)
            scale = self.numbers(tx, "scale", xptr, 2, [1, 1], -MAX_COORDINATE, MAX_COORDINATE)
            rotation = self.number(tx, "rotation", xptr, 0.0)
            if rotation != 0:
                self.note(xptr, f"rotation {rotation:g} ignored (offset and scale are used)")
            tex_coord = self.get(tx, "texCoord", xptr, "int", default=tex_coord)
        self.other_extensions(info, tptr, ("KHR_texture_transform",), "")
        if tex_coord != 0:
            self.note(tptr, f"texCoord {tex_coord} approximated by TEXCOORD_0 (the only UV set "
                      "rayfarm reads)")
        t, texptr = self.item("textures", ti)
        source = self.index(t, "source", texptr, "images")
        if source is None:
            for ext in self.get(t, "extensions", texptr, "obj", default={}).values():
                if isinstance(ext, dict) and "source" in ext:
                    raise self.fail(f"the texture's image is only given by an extension "
                                    f"({', '.join(t['extensions'])}), which this importer "
                                    "does not read", texptr)
            raise self.fail("the texture has no source image", texptr)
        self.other_extensions(t, texptr, (), "")
        filt, wrap = "bilinear", True
        si = self.index(t, "sampler", texptr, "samplers")
        if si is not None:
            s, sptr = self.item("samplers", si)
            if self.get(s, "magFilter", sptr, "int") == FILTER_NEAREST:
                filt = "nearest"
            for w in ("wrapS", "wrapT"):
                mode = self.get(s, w, sptr, "int", default=WRAP_REPEAT)
                if mode != WRAP_REPEAT:
                    wrap = False
            if not wrap:
                self.note(sptr, "clamped or mirrored wrapping approximated by repeat")
        return {"image": source, "filter": filt, "uv_scale": scale, "uv_offset": offset,
                "ptr": tptr}

    def texels(self, info: dict, raw: bool) -> np.ndarray:
        key = (info["image"], raw)
        if key in self.images:
            return self.images[key]
        img, iptr = self.item("images", info["image"])
        uri = self.get(img, "uri", iptr, "str")
        if uri is not None and not uri.startswith("data:"):
            f = self.local_file(uri, f"{iptr}/uri")
            texels = self.decode(f, raw, iptr, f.relative_to(self.root).as_posix())
        else:
            if uri is not None:
                data, mime = self.data_uri(uri, f"{iptr}/uri")
            else:
                bv = self.index(img, "bufferView", iptr, "bufferViews", required=True)
                view, _, _ = self.view(bv)
                data = bytes(view)
                mime = self.get(img, "mimeType", iptr, "str", required=True)
            if mime not in IMAGE_SUFFIX:
                raise self.fail(f"image type {mime!r} is not read (PNG and JPEG are)", iptr)
            with tempfile.TemporaryDirectory(prefix="rayfarm-gltf-") as tmp:
                f = Path(tmp) / f"image{IMAGE_SUFFIX[mime]}"
                f.write_bytes(data)
                texels = self.decode(f, raw, iptr, f"{self.name}#{iptr}")
        texels = np.asarray(texels, dtype=np.float32)
        if texels.ndim == 2:
            texels = texels[..., None]
        if texels.ndim != 3 or texels.shape[2] not in (1, 2, 3, 4) or texels.size == 0:
            raise self.fail(f"unexpected image shape {texels.shape}", iptr)
        if not np.all(np.isfinite(texels)):
            raise self.fail("the image holds values that are not finite", iptr)
        self.images[key] = texels
        return texels

    def decode(self, f: Path, raw: bool, ptr: str, name: str) -> np.ndarray:
        self.count_bytes(f.stat().st_size, ptr)
        try:
            return read_texture(f, raw=raw, name=name)
        except SceneError as exc:
            raise self.fail(exc.message, ptr) from None

    def baked(self, info: dict, purpose: str, texels: np.ndarray, material: str) -> dict:
        """A bitmap texture entry for `texels` (the glTF factors already
        multiplied in), named after the material and its input."""
        self.texture_bytes += texels.size * 4
        if self.texture_bytes > MAX_TEXTURE_BYTES:
            raise self.fail(f"the textures of the scene's materials exceed {MAX_TEXTURE_BYTES} "
                            "bytes of texels", info["ptr"])
        blob = encode_texture(np.ascontiguousarray(texels, dtype=np.float32))
        digest = asset_digest(blob)
        self.assets[digest] = blob
        entry = {"type": "bitmap", "image": digest, "filter": info["filter"]}
        if info["uv_scale"] != [1.0, 1.0]:
            entry["uv_scale"] = info["uv_scale"]
        if info["uv_offset"] != [0.0, 0.0]:
            entry["uv_offset"] = info["uv_offset"]
        key = (digest, json.dumps(entry, sort_keys=True))
        if key not in self.texture_keys:
            name = f"{material}.{purpose}"
            while name in self.textures:
                name += "'"
            self.texture_keys[key] = name
            self.textures[name] = entry
        return {"texture": self.texture_keys[key]}


def _rgb(texels: np.ndarray) -> np.ndarray:
    c = texels.shape[2]
    return texels[..., :3] if c >= 3 else np.repeat(texels[..., :1], 3, axis=2)
