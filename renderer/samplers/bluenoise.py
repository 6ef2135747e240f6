"""`bluenoise`: Mitchell's best-candidate progressive sequence, toroidally shifted.

A table of TABLE_SIZE points on the unit torus is built once, deterministically
(a fixed hash, no global RNG): point n is the best of CANDIDATES uniform
candidates, the one farthest (toroidal distance) from the n points before it
(Mitchell 1991). Every prefix of the table is then a blue-noise set: few
points close together, little power at low frequencies. The table is cached
in this package's __pycache__ (recomputed if missing or damaged: about a
second) and frozen into the kernels as a constant.

Per pixel and 2D pair: a random toroidal (Cranley-Patterson) shift, which
keeps toroidal distances and so the blue-noise spectrum and makes every
point uniform over the pixel, and a hashed permutation of the sample order
within the block, which decorrelates the pairs.

Drives: every 2D pair. spp <= TABLE_SIZE: the first spp table points, any
spp. spp > TABLE_SIZE: blocks of TABLE_SIZE samples (the last one shorter),
each the table's prefix with its own shift and order.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from ..kernels import kernel
from ..registry import Sampler, register_sampler
from .common import block_key, hash_u01, pair_key, permute, split_block

SAMPLER_BLUENOISE = 8
TABLE_SIZE = 1024
CANDIDATES = 64

register_sampler(Sampler(
    "bluenoise", SAMPLER_BLUENOISE,
    "Blue noise: Mitchell's best-candidate progressive sequence with a random "
    "toroidal shift per pixel and 2D pair."))


def _splitmix(counter: np.ndarray) -> np.ndarray:
    z = counter * np.uint64(0x9E3779B97F4A7C15) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def build_table(size: int = TABLE_SIZE, candidates: int = CANDIDATES) -> np.ndarray:
    """Mitchell's best-candidate sequence on the torus: (size, 2) float64 in [0, 1)."""
    counters = np.arange(2 * size * candidates, dtype=np.uint64)
    with np.errstate(over="ignore"):
        uniforms = (_splitmix(counters) >> np.uint64(11)).astype(np.float64) * 2.0 ** -53
    cands = uniforms.reshape(size, candidates, 2)
    points = np.empty((size, 2))
    points[0] = cands[0, 0]
    for n in range(1, size):
        d = np.abs(cands[n][:, None, :] - points[None, :n, :])
        d = np.minimum(d, 1.0 - d)
        nearest = (d * d).sum(axis=2).min(axis=1)
        points[n] = cands[n, int(np.argmax(nearest))]
    return points


def _load_table() -> np.ndarray:
    # Named by this file's hash: any edit to the construction rebuilds the table.
    source = Path(__file__).resolve()
    digest = hashlib.sha256(source.read_bytes()).hexdigest()[:16]
    path = source.parent / "__pycache__" / f"bluenoise_{TABLE_SIZE}_{digest}.npy"
    try:
        table = np.load(path)
        if table.shape == (TABLE_SIZE, 2) and table.dtype == np.float64 and \
                np.all((table >= 0.0) & (table < 1.0)):
            return table
    except (OSError, ValueError):
        pass
    table = build_table()
    try:
        path.parent.mkdir(exist_ok=True)
        tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npy")
        np.save(tmp, table)
        tmp.replace(path)
        for stale in path.parent.glob("bluenoise_*.npy"):
            if stale != path and not stale.name.endswith(".tmp.npy"):
                stale.unlink(missing_ok=True)
    except OSError:
        pass  # read-only install: keep it in memory
    return table


TABLE = _load_table()


@kernel
def sample_pair(seed, pixel, index, spp, pair):
    size = spp if spp < TABLE_SIZE else TABLE_SIZE
    b, i, n = split_block(index, spp, size)
    key = block_key(pair_key(seed, pixel, pair, 8), b)
    j = permute(i, n, key)
    u = TABLE[j, 0] + hash_u01(key, 1)
    v = TABLE[j, 1] + hash_u01(key, 2)
    if u >= 1.0:
        u -= 1.0
    if v >= 1.0:
        v -= 1.0
    return u, v
