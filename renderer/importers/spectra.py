"""Spectra and colours to linear sRGB, as Mitsuba 3 converts them in its RGB modes.

A spectrum given as wavelength:value pairs is integrated against the CIE 1931
matching functions (1000 steps from 360 to 830 nm, piecewise linear between
the given wavelengths, zero outside them), then XYZ goes to linear sRGB with
Mitsuba's matrix. Reflectances (and other non-emitted quantities) are
weighted by the D65 illuminant, so a constant spectrum is the grey of its
value; emitted spectra are not, and are normalised so that a constant
spectrum has a luminance equal to its value. Reflectances are clipped to
[0, 1], everything else to >= 0.
"""

from __future__ import annotations

import math

import numpy as np

from . import cie

__all__ = ["spectrum_to_rgb", "uniform_to_rgb", "xyz_to_srgb", "srgb_to_linear", "blackbody"]

_XYZ_TO_SRGB = np.array([[3.240479, -1.537150, -0.498535],
                         [-0.969256, 1.875991, 0.041556],
                         [0.055648, -0.204043, 1.057311]])
_STEPS = 1000
_GRID = np.linspace(cie.WAVELENGTH_MIN, cie.WAVELENGTH_MAX, _STEPS)
_TABLE_WL = np.arange(cie.WAVELENGTH_MIN, cie.WAVELENGTH_MAX + 0.5 * cie.WAVELENGTH_STEP,
                      cie.WAVELENGTH_STEP)
_CMF = np.stack([np.interp(_GRID, _TABLE_WL, t) for t in (cie.CIE_X, cie.CIE_Y, cie.CIE_Z)])
_D65 = np.interp(_GRID, _TABLE_WL, cie.D65)


def xyz_to_srgb(xyz) -> np.ndarray:
    return _XYZ_TO_SRGB @ np.asarray(xyz, dtype=np.float64)


def spectrum_to_rgb(wavelengths, values, *, emitter: bool, bounded: bool) -> list[float]:
    """Linear sRGB of a piecewise-linear spectrum (see the module doc)."""
    wl = np.asarray(wavelengths, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    inside = (_GRID >= wl[0]) & (_GRID <= wl[-1])
    sampled = np.where(inside, np.interp(_GRID, wl, v), 0.0)
    weight = np.ones_like(_GRID) if emitter else _D65
    xyz = (_CMF * (sampled * weight)).sum(axis=1) / (_CMF[1] * weight).sum()
    rgb = xyz_to_srgb(xyz)
    rgb = np.clip(rgb, 0.0, 1.0) if bounded else np.maximum(rgb, 0.0)
    return [float(c) for c in rgb]


def uniform_to_rgb(value: float, *, emitter: bool) -> list[float]:
    """A constant spectrum: its grey, except that Mitsuba 3 gives an emitted
    one the sRGB of equal-energy white (XYZ = 1, 1, 1), slightly purple."""
    if emitter:
        return [float(c) * value for c in xyz_to_srgb([1.0, 1.0, 1.0])]
    return [value, value, value]


def srgb_to_linear(c: float) -> float:
    """One sRGB-encoded component in [0, 1] to linear."""
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


def blackbody(temperature: float) -> tuple[np.ndarray, np.ndarray]:
    """Planck's law at `temperature` kelvin on the 5 nm grid, in
    W / (m^2 sr nm): the spectral radiance of a black body."""
    h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
    lam = _TABLE_WL * 1e-9
    with np.errstate(over="ignore"):
        radiance = (2 * h * c * c) / (lam ** 5 * np.expm1(h * c / (lam * k * temperature)))
    return _TABLE_WL.copy(), radiance * 1e-9


def _check() -> None:  # pragma: no cover - a sanity check for developers
    assert np.allclose(spectrum_to_rgb([360, 830], [0.5, 0.5], emitter=False, bounded=True),
                       0.5, atol=2e-3)
    assert math.isclose(sum(_CMF[1]) / _STEPS * 470, 106.86, rel_tol=1e-2)
