"""A test helper for MLT's mutations (moved out of the renderer): chains of
`run_chain`'s exact Metropolis steps on toy integrands over [0, 1)^3. Not
cached on disk (Numba's cache of a tests/ module would not notice a change in
the renderer's kernels it calls)."""

from __future__ import annotations

from numba import njit

from renderer.integrators.mlt import _acceptance, _mutate, _restore
from renderer.kernels.rng import STREAM_CHAINS, stream_key, uniform

TOY_CONSTANT, TOY_RAMP = 0, 1


@njit(error_model="numpy")
def _toy_integrand(kind, x):
    """Test integrands on [0, 1)^3 (x[2] is read by none: it must stay uniform):
    constant 1, or (0.2 + x0) (0.2 + x1^2) with x0 < 0.8 (zero beyond)."""
    if kind == TOY_CONSTANT:
        return 1.0
    if x[0] >= 0.8:
        return 0.0
    return (0.2 + x[0]) * (0.2 + x[1] * x[1])


@njit(error_model="numpy")
def toy_chains(seed, n_chains, mutations, large_step, sigma, perturbation, kind, x0,
               x, last_mod, x_backup, mod_backup, out):
    """For tests of the mutation kernel: run `n_chains` independent chains
    of `mutations` Metropolis steps (run_chain's exact steps) on a toy
    integrand over [0, 1)^3, chain c from the state x0[c], and write each
    chain's final state to out[c]. x, x_backup (float) and last_mod, mod_backup
    (int64) are buffers of 3."""
    dims = 3
    for c in range(n_chains):
        key = stream_key(seed, STREAM_CHAINS, c)
        for k in range(dims):
            x[k] = x0[c, k]
            last_mod[k] = 0
        cy = _toy_integrand(kind, x)
        iteration, last_large, ctr = 0, 0, 1
        for _ in range(mutations):
            iteration += 1
            large = uniform(key, ctr) < large_step
            ctr = _mutate(x, last_mod, x_backup, mod_backup, 0, dims, iteration, last_large,
                          large, sigma, perturbation, key, ctr + 1)
            py = _toy_integrand(kind, x)
            if uniform(key, ctr) < _acceptance(py, cy):
                cy = py
                if large:
                    last_large = iteration
            else:
                iteration = _restore(x, last_mod, x_backup, mod_backup, dims, iteration)
            ctr += 1
        for k in range(dims):
            out[c, k] = x[k]
