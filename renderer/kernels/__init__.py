"""Numba kernels over the structure-of-arrays scene: private building blocks.

Every kernel is compiled with `kernel` (``njit(cache=True, error_model="numpy")``:
cached on disk, and IEEE semantics for division so a zero ray component gives
an infinite inverse instead of an exception).

Numba's on-disk cache only checks the source file of the function it caches,
so a change in a callee in another file would leave a stale caller behind.
`_invalidate_stale_cache` guards against that: it hashes every kernel source
file (kernels/, integrators/, samplers/, bvh.py) and drops the package's cached kernels when the hash changes.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from numba import njit
from numba.core import config, codegen

__all__ = ["kernel", "kernel_inline", "kernel_parallel", "cache_is_empty"]

# `_nrt=False` turns off Numba's reference counting in the kernels. Kernels
# allocate nothing (callers pass every buffer in), and with the runtime on,
# each use of the SceneArrays tuple increfs and decrefs all of its arrays
# through atomic calls: measured 586 ns per light sample instead of 55 ns.
kernel = njit(cache=True, error_model="numpy", _nrt=False)
# For functions that take the whole SceneArrays tuple and are called per
# bounce: inlined at Numba IR level as well.
kernel_inline = njit(cache=True, error_model="numpy", _nrt=False, inline="always")
kernel_parallel = njit(cache=True, error_model="numpy", _nrt=False, parallel=True)
# No fastmath. Measured (2026-11-27, AMD EPYC Zen 3, AVX2, cornell-box 32 spp,
# one thread, interleaved runs): fastmath={"contract"} (fused multiply-adds)
# 0 to +2 %, within the runs' spread, and every film's last bits change;
# adding "arcp" gave the same bytes and no more speed. The other flags
# ("nnan", "ninf", "nsz", "reassoc") would break the slab test's infinities,
# the branchless frame's copysign and the error bounds the robust traversal
# and the ray offsets rely on.


def _full_width_vectors() -> None:
    """Let LLVM use the whole AVX-512 register on Intel CPUs too.

    LLVM tunes Intel's AVX-512 server and client cores (Skylake-X on) with
    `prefer-256-bit`: its vectorizers stop at 256-bit ymm registers (to keep
    the core out of its lower AVX-512 clock), while on AMD's Zen 4 and Zen 5
    they take 512-bit zmm registers. The packet traversal's lane loops over
    PACKET = 16 float64 lanes then take four registers per value on an Intel
    Xeon instead of two (kernels/packet.py). Turning the preference off is a
    tuning choice of the code generator, not of the arithmetic: every lane
    computes what it computed, so the images are the same bytes (no
    fastmath: nothing is reassociated or fused).

    Measured on 2026-11-29 (an Intel Xeon with AVX-512 that LLVM takes for
    `rocketlake`), the same film bytes both ways:
    - bench/throughput.py's cornell-box and veach-mis rows (2 threads,
      256 pixels wide), two runs each way, alternated: cornell-box
      3.13 / 3.31 / 3.26 and 3.11 / 3.26 / 3.29 M samples/s at 16 / 64 /
      256 spp with ymm, 3.28 / 3.54 / 3.56 and 3.08 / 3.29 / 3.39 M with
      zmm (+4 % on average); veach-mis 3.84 / 4.17 / 4.19 and 3.83 / 4.14 /
      4.24 against 3.94 / 4.19 / 4.17 and 3.89 / 4.06 / 4.18 (the same);
    - one thread, 128 x 128 at 256 spp, six interleaved pairs of
      processes: cornell-box -3.0 %, veach-mis +1.8 % time.
    The packet kernel went from 1818 ymm and no zmm operands to 922 zmm.
    The full bench after it (docs/throughput.md) gave cornell-box 3.20 /
    3.38 / 3.49 M samples/s against 2.86 / 3.14 / 3.29 M an hour before,
    with Mitsuba 4-8 % faster in the second run too: the machine drifts, the
    alternated runs above are the comparison. Only that one Intel machine
    was measured: on the older Skylake-SP cores, whose clock drops further
    under 512-bit arithmetic, measure before trusting it
    (NUMBA_CPU_FEATURES, below, overrides it).

    On AMD's Zen 4, whose 512-bit units are two 256-bit halves, the wide
    registers still pay: with `+prefer-256-bit` forced (ymm), cornell-box
    128 x 128 at 64 spp on one thread took 6.8 % longer (six interleaved
    pairs of processes, 2026-11-29, the same film bytes). Numba's SLP
    vectorizer (NUMBA_SLP_VECTORIZE=1, off by default), which could pack the
    shading's scalar x, y, z arithmetic, measured the same way there:
    +0.1 % median, the same bytes; left off.

    A user who sets NUMBA_CPU_NAME or NUMBA_CPU_FEATURES keeps their choice;
    a process that compiled with Numba before importing the renderer keeps
    the code generator it made. Numba's cache keys its entries by the CPU
    name and features, so kernels cached under the other setting are
    compiled again, not reused."""
    if config.CPU_NAME is not None or config.CPU_FEATURES is not None:
        return
    features = codegen.get_host_cpu_features()
    if "+avx512f" in features.split(","):
        config.CPU_FEATURES = features + ",-prefer-256-bit"


_full_width_vectors()

_PACKAGE = Path(__file__).resolve().parent.parent  # the renderer package


def _cached_files(suffix: str) -> list[Path]:
    """The package's files of Numba's on-disk cache: index (nbi) or data (nbc)."""
    return list(_PACKAGE.rglob(f"__pycache__/*.{suffix}"))


def _invalidate_stale_cache() -> None:
    root = _PACKAGE
    sources = sorted([*root.glob("kernels/*.py"), *root.glob("integrators/*.py"),
                      *root.glob("samplers/*.py"), root / "bvh.py"])
    digest = hashlib.sha256()
    for src in sources:
        digest.update(src.name.encode())
        digest.update(src.read_bytes())
    stamp_text = digest.hexdigest()
    stamp = root / "__pycache__" / "kernels.stamp"
    try:
        if stamp.exists() and stamp.read_text() == stamp_text:
            return
        for cached in _cached_files("nbi") + _cached_files("nbc"):
            cached.unlink(missing_ok=True)
        stamp.parent.mkdir(exist_ok=True)
        tmp = stamp.with_suffix(".tmp")
        tmp.write_text(stamp_text)
        tmp.replace(stamp)
    except OSError:
        pass  # a read-only install simply keeps (and trusts) its cache


_invalidate_stale_cache()


def cache_is_empty() -> bool:
    """True when Numba's on-disk cache holds no kernel of the package: a
    fresh checkout, or a source change `_invalidate_stale_cache` just acted
    on (it drops all of them at once, so the cache is warm or cold as a
    whole). `renderer.warm_up` then compiles in parallel from the start.
    With NUMBA_CACHE_DIR set the cache is elsewhere: False, not known."""
    from numba.core import config

    if config.CACHE_DIR:
        return False
    return not _cached_files("nbi")
