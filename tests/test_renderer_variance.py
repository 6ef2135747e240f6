"""The var channels are a contract for every method: over seeds, the spread of
each pixel's estimate is what its var channel predicts (an independent
sampler), or at most that (a stratified one, whose var channel is the iid
formula and so an upper bound).

Per method: 8 seeds of a 32 x 32 cornell box, the green channel (the channels
of a pixel share their paths, so they are not independent of each other). Per
pixel the ratio of the 8 estimates' variance to the mean predicted variance;
the ratios are averaged over 4 x 4 blocks (neighbouring pixels of splatting
methods are correlated) and the blocks' mean is z-tested against 1 with the
blocks' own spread as its standard error. Halving every var channel moves z
to 8-35 for every method (checked when this test was written). MLT's error
shared by every pixel (the bootstrap's b) is tested on its own in
test_renderer_mlt test16.

Radiosity's var channels describe its display pass only: the form-factor
rays' noise is frozen into the solution, which depends on the seed, and is
not in them (measured here: the spread is 1.5x the prediction, z about 4).
Not tested here until the solution's variance is carried (an xfail that
passes at Z would be a test that cannot fail).
"""

from __future__ import annotations

import numpy as np
import pytest

from renderer import METHODS, RenderSpec, load_scene, render_serial

Z = 4.5
SEEDS = 8
METHOD_NAMES = [m.name for m in dict.fromkeys(METHODS.values())]


@pytest.fixture(scope="module")
def cornell():
    return load_scene("cornell-box")


def _spread_z(scene, method: str, sampler: str) -> tuple[float, float]:
    """(z of observed minus predicted per-pixel variance, observed / predicted)."""
    values, predicted = [], []
    for k in range(SEEDS):
        spec = RenderSpec(method=method, spp=16, depth=3, width=32, height=32, tile_size=32,
                          seed=500 + k, sampler=sampler)
        film = render_serial(scene, spec)
        values.append(film.mean()[..., 1])
        predicted.append(film.variance_of_mean()[..., 1])
    values, predicted = np.array(values), np.array(predicted)
    assert np.all(np.isfinite(predicted)), method
    observed, expected = values.var(axis=0, ddof=1), predicted.mean(axis=0)
    ratio = np.where(expected > 0, observed / np.maximum(expected, 1e-300), 1.0)
    blocks = ratio.reshape(8, 4, 8, 4).mean(axis=(1, 3)).ravel()
    z = (blocks.mean() - 1.0) / (blocks.std(ddof=1) / np.sqrt(blocks.size))
    return float(z), float(blocks.mean())


@pytest.mark.parametrize("method", [
    pytest.param(name, marks=pytest.mark.skip(
        reason="radiosity's var channels leave out the solution's form-factor noise "
               "(spread 1.5x the prediction): see the module doc")) if name == "radiosity"
    else name
    for name in METHOD_NAMES])
def test01_var_channels_predict_the_spread_over_seeds(cornell, method):
    """With the independent `random` sampler the spread matches the prediction."""
    z, ratio = _spread_z(cornell, method, "random")
    assert abs(z) <= Z, (method, z, ratio)


@pytest.mark.parametrize("method", METHOD_NAMES)
def test02_var_channels_bound_the_spread_of_a_stratified_sampler(cornell, method):
    """With the default (stratified) sampler the spread is at most the
    prediction: the iid formula of the var channels is an upper bound there."""
    z, ratio = _spread_z(cornell, method, RenderSpec().sampler)
    assert z <= Z, (method, z, ratio)
