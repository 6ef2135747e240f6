"""`sobol`: padded, Owen-scrambled Sobol' (pbrt-v4's PaddedSobolSampler).

Every 2D pair uses Sobol' dimensions 0 and 1 (the (0, 2)-sequence: van der
Corput and its Pascal-matrix partner), so no direction-number table is needed
beyond those two. Each pair of each pixel gets
- its own sample order: sample i of a block of n = spp samples uses
  sequence index j = block * spp + order(i), which decorrelates the pairs
  ("padding"). Pairs below n read one hashed permutation of [0, n) per
  pixel and block (Kensler's `permute`, pbrt's `PermutationElement`) at
  rotated positions, order(i) = perm((i + pair) mod n); pairs from n on
  (deep bounces at low spp) each have their own permutation;
- its own Owen scramble per coordinate, Burley's (2020) hash-based nested
  uniform scramble with the improved Laine-Karras hash pbrt-v4 uses
  (`FastOwenScrambler`). Owen scrambling keeps the net property and makes
  every point uniform on [0, 1)^2.

Drives: every 2D pair. spp: any; each pixel's points are the first spp of the
scrambled (0, 2)-sequence. For spp = 2^m they form a (0, m, 2)-net: one point
in every elementary interval 2^-a x 2^-b with a + b = m (tested); for other
spp the prefix is still well spread, the guarantee holds per power-of-two
block. 32-bit precision: indices are taken mod 2^32.

Cost (it is the default sampler, so it has to be cheap). A pair took about
17 ns (32 ns before the byte tables of dimension 1 and the scramble on
reversed bits, which give the same values; 5 ns for `random`'s two
hashes), half of it the padding permutation, Kensler's hash with its nine
multiplies, evaluated for every pair of every sample. Since 2026-11-26 the
pairs below n share a pixel's permutation at rotated positions, so the tile
kernels memoize it per row (`sample_pair_memo`, dispatch.memo_rows): one
hash per pixel and sample instead of one per pair (and since 2026-11-27
the path tracer's memo holds whole pair tables, below). On cornell-box
(64 spp, one thread) `sobol` went from 1.02 to 1.14 M samples/s (`random`
1.30 M);
its RMSE at 16, 64 and 256 spp and the coupling test
(tests/test_renderer_samplers.py test04_sobol_pairs_are_padded: two pairs'
coarse strata paired as by a random permutation) are unchanged within
their noise: two rotations of one random permutation are coupled like two
independent ones, since (perm(t), perm(t + d)) runs through a random
matching of [0, n) for every offset d != 0 mod n.

Pair tables (2026-11-27, fifth session, Intel Xeon with AVX-512): what a
`sobol` draw costs over `random` is its chain of about a hundred scalar
integer operations. Measured by ablation on cornell-box (32 spp, one
thread): with u1d/u2d answering `sobol` draws by `random`'s hash, the
render ran at `random`'s speed (1.17 s -> 0.96-0.98 s), so nothing but the
draws separates the two; without the pair key's hashing, the memo's
permutation or the Owen scramble, one at a time, 0 / 3 / 4-6 % faster, and
without all three as fast as `random`: the cost is the sum of the links,
not one of them (nor their latency, 2026-11-27's fourth session). So the
path tracer's memo now takes the tables layout (`sample_pair_memo`): a
pixel's first film pair claims a bank and computes every position's
sequence index (`permute_run`: for a power-of-two spp one branch-free,
vectorized loop) and Sobol' dimension 1; a pair's first draw fills its
whole table of packed points in one vectorized loop (`_fill_table`, about
1 ns a point); every draw after that is a load and two conversions, inline,
with everything else out of line (`_sample_pair_memo_slow`). Per draw, in
a loop over pixels, samples and 8 pairs: 4.0 ns with the tables' fills,
2.1 ns without (`random` 2.2 ns), against 7.9 ns for the entries layout.
The same films to the bit (the same integers, in another order);
cornell-box 64 spp on 2 threads +7 to +9 %, veach-mis +5 to +7 %
(interleaved runs). Measured and not kept on the way: LLVM's bitreverse
intrinsic for `reverse_bits32` (no change: LLVM already recognizes the
pattern), a 64-bit division less per vertex (the lanes keep their pixel
and sample index; within the noise, kept since it costs nothing).

Windows (2026-11-28): the tables covered every position of a block of spp
samples, so a unit that renders part of a pixel's samples (a progressive
pass) would have paid for all of them, and went with the entries layout:
that was most of what a progressive job cost over one pass (plan.py). A
tables-layout memo now takes the unit's window of samples (`mark_window`:
marks in the positions the window does not read, so the bank's header,
its layout and the inline draw are those of one pass), and a claim and a
table cover the window's positions only; the claim's permutation goes
through `permute_run`, which computes Kensler's permutation for a run of
positions without `permute`'s division per call (6.7 ns a position at
spp 176 instead of 13, 1.7 ns at 256 instead of 4.5). The same values
(tests/test_renderer_samplers.py test02, over windows). Measured on an
Intel Xeon with AVX-512, cornell-box 256x256, one thread, five pairs of
processes against the code before: progressive 176 spp -8.4 +- 0.3 %
(+4 % over one pass instead of +14 %), one pass 176 spp -1.9 +- 0.7 %,
one pass 64 spp -1.1 +- 0.7 %. A first try (a5c74c3, Zen 5) kept the
window in a longer bank header and checked it on the deeper pairs' path:
progressive -5 %, but one pass +3.6 +- 1.5 % at 64 spp, cause not found;
this version leaves one pass's layout and hot code as they were. What a
pass still pays: a claim computes TABLE_PAIRS - 1 positions more than its
samples (the pairs' rotations), and each table is filled from the
out-of-line draw once per pass instead of once per pixel.

Measured and not kept (2026-11-25): a permutation from the nested family
(i's bits scrambled top-down by the Laine-Karras hash on reversed bits, the
base-2 form of pbrt-v4's ZSobol index permutation, three multiplies) made a
pair 34 % cheaper and cornell-box renders 4-9 % faster, but it pairs the
strata of two pairs less randomly: on integrands coupling two pairs its MSE
was 1.3-2x Kensler's (test04_sobol_pairs_are_padded), on cornell-box 1-2 %
higher; not worth a weaker sampler. Two rounds of xor-multiply-xorshift
were cheaper still and failed that test, as did (2026-11-26) a
multiply-xorshift permutation with shifts scaled to n. u1d/u2d
(dispatch.py) call this module directly.

Measured and not kept (2026-11-27, cornell-box, 32 spp, one thread, three
interleaved pairs of processes against 2.05-2.15 M samples/s):
- The pairs of a packet's sixteen lanes in three loops over the lanes (keys
  and memo entries, the missing entries lane by lane, then the scrambled
  points), which LLVM vectorized with AVX-512 gathers and 64-bit
  multiplies: 1.90-1.94 M, slower. The same restructuring with the pairs
  still drawn lane by lane ran at the old speed, so the vector loops
  themselves lost: the gathers of the memo and the byte tables cost more
  than the scalar code they replaced.
- The pixel's part of the pair key (two of pair_key's three mix64) computed
  once per sample and carried by the lane: 1.95-2.03 M, slower. After
  inlining, the compiler already shares it between the pairs of a vertex;
  carrying it cost a load and a register.
- `sample_pair_memo` out of line (one copy of its code for the kernel's
  six call sites instead of six inlined ones): 1.83-1.87 M, slower; the
  calls cost more than the smaller hot code saved.
- Not hashing the sample's `random` key for other samplers (u1d/u2d read
  it only for `random`): within the noise (+0.4 %).
- A random digital shift (xor) instead of the Owen scramble: +3 % (the
  scramble's ten multiplies pipeline well), for a weaker randomization.
  What a pair costs is mostly its chain of dependent hashes (pair key,
  memo tag, scramble seed), about 9 ns against 2-3 ns for `random`'s two
  hashes (micro-benchmark with the kernels' settings; with Numba's
  reference counting on, as a plain @njit test harness has it, the memo
  array's increfs made the same code 15 ns).

Measured and not kept (2026-11-27, third session, AVX2 machine): whole-path
stratification, the one lever of the sampler race not measured before. cornell-box,
path-mis, depth 7, MSE against the 8192-spp reference (bench/throughput.py's
functions), mean of 4 seeds, standard error 2.5 / 0.9 / 0.5 % at 16 / 64 /
256 spp; changes against this sampler:
- 4D groups: the BSDF pair of bounce b and the light pair of bounce b + 1
  sharing one sample order, as Sobol' dimensions 0-1 and 2-3 (direction
  numbers derived here from x^2 + x + 1, m = 1, 3 and x^3 + x + 1,
  m = 1, 3, 1; the four dimensions are a (t, m, 4)-net with t = 2 at 16 and
  64 points, 3 at 256), each coordinate Owen-scrambled on its own, so the
  next vertex's light sample is stratified jointly with the direction that
  found the vertex: MSE +0.1 / -0.5 / -0.9 %, noise. The other way round
  (the light pair on dimensions 0-1): +1.7 / +1.0 % at 64 / 256. The film
  pair and the first light pair as one 4D group as well: -0.1 / -0.6 /
  -0.8 %.
- The pairs of bounces 3 and deeper from `random` (u1d/u2d's hash) instead:
  MSE +0.2 / 0.0 / +0.9 %, samples/s +1.5 % (one thread, 32 spp); of
  bounces 2 and deeper: +0.7 / +0.5 / +1.9 %, +2.5 %. Efficiency within
  ±1 % either way, for a sampler that would no longer be one sequence.
So the deep dimensions do not need stratifying, and stratifying two
vertices jointly gains nothing measurable: what `sobol` takes off deep
indirect light (its error divided by 1.2-1.4 against `random`,
bench/error_budget.py) comes from the first vertices' pairs, which every
deeper bounce inherits. On this scene, then, a full-dimensional
Owen-scrambled Sobol' has little left to gain (an inference from these two
experiments, not a measurement of it), and its higher dimensions' 2D
projections are weaker than the (0, 2)-sequence every pair uses here.

Measured and not kept (2026-11-28, third session, AMD EPYC Zen 4):
which pair gives `hammersley` its lower MSE at 64 spp. In the full
bench run `hammersley` has RMSE 0.00847 on cornell-box at 64 spp,
against 0.00879 for this sampler: 7 % less MSE, at a third less speed.
Method: cornell-box 256x256, path-mis, depth 7, MSE against the bench's
8192-spp reference, mean over 6 seeds (standard error 0.5-1.4 %) unless
a count is given. One pair of this sampler was replaced at a time, in
/tmp copies; none of this code is in the tree. The results:
- `sobol` itself: 7.65e-5 (7.63e-5 over 20 seeds). `hammersley`: 7.19e-5.
- No change:
  - the film pair from `hammersley`, biased as it is (7.71e-5) or
    shifted like its other pairs (7.63e-5), or from `multijitter`
    (7.74e-5);
  - the first vertex's light pair from `hammersley` (7.67e-5);
  - each pair with its own permutation instead of the rotated one (7.65e-5).
- All pairs after the film pair from `hammersley`: 7.15e-5.
- **Only the first vertex's BSDF pair (pair 2) from `hammersley`: 7.10e-5
  over 20 seeds, -6.9 +- 1.2 %.** At 16 spp -4.6 %, at 256 spp -3.8 %
  (6 seeds each, about 2 standard errors).
- What makes the difference is the net and its randomization together:
  - the Hammersley net Owen-scrambled in pair 2: no change (7.66e-5);
  - the Sobol' net with `hammersley`'s randomization in pair 2 (y
    digitally shifted, x its stratum plus one common offset): -2.4 %
    (7.44e-5);
  - every pair from pair 1 on digitally shifted instead of Owen-scrambled:
    -2.4 % at 64 spp, 0 at 16 and 256.
So on cornell-box, a Hammersley set with a random shift (x = (k + delta)
/ N, y = RI(k) xor r; each point is uniform, so it is unbiased) beats
Owen-scrambled Sobol' for the first bounce direction. At this sampler's
speed that would be about +7 % efficiency at 64 spp there.
The same change (pair 2 from `hammersley`) on other scenes at 64 spp
does not carry over, so it is not a change to make:
- door-ajar (128x128, 16 seeds): -1.4 +- 0.9 %;
- cornell-caustic (128x128, 16 seeds): +5.5 +- 3.5 %, worse;
- both against a 4096-spp `random` reference;
- veach-mis against such a reference: +-20 % over 8 seeds (heavy tails),
  no answer.

Measured and not kept (2026-11-27, fourth session, AVX-512 machine, Zen 5,
path-mis at 64 spp, 2 threads, interleaved pairs of processes): the pairs
drawn ahead of the shading. A pair is a chain of dependent multiplies
(pair key, memo tag, scramble seed, scramble), and inside a lane's shading
the lane's work waits for it. So the path tracer drew a vertex's three
pairs (light point, light pick with Russian roulette, BSDF direction) for
all sixteen lanes in one loop after the packet's traversal, where the
lanes' chains can overlap, and the shading read them back. The films were
the same to the bit, and the samples/s:
- cornell-box: `sobol` +2 to +6 %, `random` -3 to -10 %;
- veach-mis: `sobol` -5 to -8 %;
- cornell-box `halton` +1 to +2 %, `bluenoise` 0.
With `random` exempt (its two hashes drawn in the shading as before),
`sobol` gained 0 to +4 % and `random` still lost 3 to 6 %. So the chain's
latency is not where `sobol`'s cost over `random` (about 20 % of the
samples/s) goes, and the extra loop and lane rows cost what it saved.
"""

import numpy as np

from ..kernels import kernel, kernel_inline
from ..registry import Sampler, register_sampler
from .common import (INV_2_32, MASK32, U1, U8, U16, U32, block_key, hash32, pair_key, permute,
                     permute_run, reverse_bits32, split_block)

SAMPLER_SOBOL = 7
_H1 = np.uint64(0x3D20ADEA)
_H2 = np.uint64(0x05526C56)
_H3 = np.uint64(0x53A22864)

register_sampler(Sampler(
    "sobol", SAMPLER_SOBOL,
    "Owen-scrambled Sobol' (0,2)-sequence, padded: every 2D pair with its own "
    "scramble and sample order (pbrt-v4 PaddedSobolSampler)."))


def _sobol1_bits_slow(j: int) -> int:
    """Sobol' dimension 1 at index j by its generator (the Pascal matrix mod 2):
    bit k of j adds column k, and column k+1 is column k xor itself >> 1."""
    x, v = 0, 1 << 31
    while j:
        if j & 1:
            x ^= v
        j >>= 1
        v ^= v >> 1
    return x


def _reversed_byte_tables() -> np.ndarray:
    """table[k, b] = the bit-reversed Sobol' dimension-1 value of b << 8k.

    The generator is linear over GF(2), so sobol1(j) is the xor of the values
    of j's bytes: four lookups instead of a loop over j's bits. Stored
    bit-reversed because the Owen scramble works on reversed bits (below)."""
    table = np.zeros((4, 256), dtype=np.uint64)
    for k in range(4):
        for b in range(256):
            table[k, b] = int(f"{_sobol1_bits_slow(b << (8 * k)):032b}"[::-1], 2)
    return table


_REV_SOBOL1 = _reversed_byte_tables()
_BYTE = np.uint64(0xFF)


@kernel_inline
def _reversed_sobol1(j):
    """reverse_bits32(sobol_bits(j, 1)) by table, for j < 2^32."""
    x = _REV_SOBOL1[0, j & _BYTE]
    j >>= U8
    if j != 0:
        x ^= _REV_SOBOL1[1, j & _BYTE]
        j >>= U8
        if j != 0:
            x ^= _REV_SOBOL1[2, j & _BYTE] ^ _REV_SOBOL1[3, (j >> U8) & _BYTE]
    return x


@kernel
def sobol_bits(j, d):
    """The 32-bit fraction of Sobol' dimension `d` (0 or 1) at index `j`."""
    bits = np.uint64(j) & MASK32
    if d == 0:
        return reverse_bits32(bits)
    return reverse_bits32(_reversed_sobol1(bits))


@kernel_inline
def _scramble_reversed(x, seed):
    """The Laine-Karras style hash of Burley (2020) on bit-reversed bits: a
    nested uniform scramble of the fraction whose reversed bits are `x`."""
    s = np.uint64(seed) & MASK32
    x ^= (x * _H1) & MASK32
    x = (x + s) & MASK32
    x = (x * ((s >> U16) | U1)) & MASK32
    x ^= (x * _H2) & MASK32
    x ^= (x * _H3) & MASK32
    return x


@kernel
def owen_scramble(v, seed):
    """Nested uniform (Owen) scramble of the 32-bit fraction `v` (Burley 2020)."""
    return reverse_bits32(_scramble_reversed(reverse_bits32(v), seed))


# Salt of the pixel's shared sample order (pair_key's salts 7 = each pair's own keys).
_ORDER_SALT = 9
# The memo (`sample_pair_memo`) holds one pixel's order for spp up to this.
MEMO_MAX_SPP = 4096
# Banks of the memo, pixels taking turns (a power of two; sample_pair_memo).
# Measured and not kept (2026-11-29, AMD EPYC Zen 5, cornell-box 128x128,
# one thread, interleaved pairs of processes, the same film bytes): 8 banks,
# so that fewer pixels evict each other while a row's ring (path.RING, 256
# items: four pixels at 64 spp, sixteen at 16) runs ahead of its oldest
# item: 16 spp -1.0 %, 64 spp -1.3 % and -2.5 % (six and ten pairs), 256 spp
# -1.7 % time. About the noise, for twice the memo (8 MiB a thread at
# MEMO_MAX_SPP, where dispatch.MEMO_MAX_BYTES would then take 16 threads).
MEMO_BANKS = 4


@kernel_inline
def _order_key(seed, pixel, b):
    return block_key(pair_key(seed, pixel, 0, _ORDER_SALT), b)


@kernel_inline
def _pair_values(j, key):
    """The pair's scrambled Sobol' point at sequence index j."""
    # dimension 0 is the van der Corput sequence, the reversed bits of j: the
    # scramble works on reversed bits, so j goes in as it is; the two
    # coordinates are scrambled by the high half of `key` and one more hash
    u = float(reverse_bits32(_scramble_reversed(j, hash32(key, 1)))) * INV_2_32
    v = float(reverse_bits32(_scramble_reversed(_reversed_sobol1(j), key >> U32))) * INV_2_32
    return u, v


@kernel_inline
def _rotated(i, pair, n):
    """(i + pair) mod n, for i < n and pair < n."""
    t = i + pair
    return t - n if t >= n else t


@kernel_inline
def _sample_order(seed, pixel, b, i, n, pair, key):
    """order(i) of pair `pair` in block b of length n (see `sample_pair`)."""
    if pair < n:
        return permute(_rotated(i, pair, n), n, _order_key(seed, pixel, b))
    return permute(i, n, block_key(key, b))


@kernel_inline
def sample_pair(seed, pixel, index, spp, pair):
    """Pair `pair` of sample `index`: the scrambled point at j = b * spp + order(i).

    The sample order (padding): pairs below n (the block's length) read one
    hashed permutation of [0, n) per pixel and block at rotated positions,
    order(i) = perm((i + pair) mod n); later pairs each have their own
    permutation, perm_pair(i). Each pair's point set is the whole block
    either way; the rotation gives two pairs' orders the coupling of a
    random permutation (tests/test_renderer_samplers.py test04), and one
    pixel's permutation serves all its pairs, so a kernel can memoize it
    (`sample_pair_memo`) instead of hashing every pair of every sample."""
    b, i, n = split_block(index, spp, spp)
    key = pair_key(seed, pixel, pair, 7)
    p = _sample_order(seed, pixel, b, i, n, pair, key)
    return _pair_values(np.uint64(b * (spp if spp > 0 else 1) + p) & MASK32, key)


# Pairs below this get a table per pixel and block in the memo's table
# layout (`sample_pair_memo`): the film pair and the pairs of the first
# seven vertices (pairs 1 + 4 b + 0..3 for b <= 6, samplers/dispatch.py),
# every pair a path of the benchmarks' depth 7 draws. Deeper pairs go
# through the out-of-line draw. Until 2026-11-29 this was 17 (four
# vertices): deeper pairs are drawn by fewer paths, and 13 and 29 had
# measured within a few percent of 17 on cornell-box (on an Intel Xeon,
# 2026-11-28, with the survival scale 2: 64 spp -0.3 +- 0.5 %, 256 spp
# -2.2 +- 0.6 %), not worth the memo's 1.6x memory then, when it was one
# memo per image row. It is one per Numba thread since (integrators/
# tile.py), a bank of 64 spp is 16 kB with 29 tables. Measured with 29
# (2026-11-29, AMD EPYC Zen 5, 128x128, one thread, interleaved pairs of
# processes, the same film bytes): cornell-box 64 spp -3.3 % time (ten
# pairs), 256 spp -4.0 % (six), veach-mis 64 spp -2.3 % (eight); the
# windows of a progressive 507-spp job (eight pairs) [0, 8) -1.9 %,
# [8, 16) -0.5 %, [64, 128) -7.4 %. A path that reaches the fifth vertex
# draws about ten pairs past the fourth, each some 10 ns out of line
# against a load from a table filled at a fraction of a nanosecond a point.
TABLE_PAIRS = 29


@kernel_inline
def _table_bank_width(n):
    """A bank of the tables layout: its tag, a tag per pair table, the
    positions' sequence indices and Sobol' dimension 1, the pair tables."""
    return 1 + TABLE_PAIRS + (2 + TABLE_PAIRS) * n


@kernel_inline
def _table_start(base, pair, n):
    """Where pair `pair`'s table starts in the bank at `base`."""
    return base + 1 + TABLE_PAIRS + (2 + pair) * n


def memo_bank_width(spp: int, tables: bool) -> int:
    """int64 entries of one bank of `sample_pair_memo`'s memo (module doc)."""
    return _table_bank_width(spp) if tables else 2 * spp


# A window (`mark_window`): a unit that renders the samples [lo, hi) of a
# pixel's block, part of them, needs the positions lo + k + pair mod n of
# its m = hi - lo samples for the pairs below TABLE_PAIRS, a span of
# m + TABLE_PAIRS - 1 positions from lo. Such a memo marks every position
# outside the span, in every bank, with -(hi + 1) in the sequence indices
# (which are never negative), and a claim then computes the span only.
# Position lo - 1 mod n lies outside the span, and a pixel's first draw is
# its sample lo, so a claim finds the window at the position before its
# sample; the claim hands it to the pair tables in their tags (negative:
# `_window_code`), and a deeper pair that meets a mark computes its point
# itself. Nothing of this is on the inline draw (`sample_pair_memo`).
_WINDOW_BITS = 13  # MEMO_MAX_SPP < 2 ** _WINDOW_BITS


@kernel_inline
def window_span(spp, lo, hi):
    """Positions a tables-layout claim computes for the window [lo, hi) of a
    block of spp samples: the window's span, or spp if the span would take
    every position (then the memo keeps no marks: a whole claim). The rule
    of both `mark_window` and `_claim_bank`."""
    span = hi - lo + TABLE_PAIRS - 1
    return span if 0 <= lo < hi <= spp and span < spp else spp


def mark_window(memos: np.ndarray, spp: int, lo: int, hi: int) -> None:
    """Give tables-layout memo rows the window [lo, hi): the samples their
    kernel draws, each pixel's in order from lo (see the comment above)."""
    span = window_span(spp, lo, hi)
    if span == spp:
        return
    bw = memo_bank_width(spp, True)
    banks = memos.reshape(memos.shape[0], MEMO_BANKS, bw)
    outside = (np.arange(spp) - lo) % spp >= span
    seq = banks[:, :, 1 + TABLE_PAIRS:1 + TABLE_PAIRS + spp]
    seq[:, :, outside] = -(hi + 1)


@kernel_inline
def _window_code(lo, hi):
    """A pair-table tag that is no tag: the table's window to fill (< 0)."""
    return -1 - (lo + (hi << _WINDOW_BITS))


@kernel
def _claim_bank(memo, base, tag, seed, pixel, b, n, spp, i):
    """Bank `base` now holds pixel `pixel`'s block b: the sequence index
    J[t] = b spp + perm(t) and its reversed Sobol' dimension 1 at every
    position t, or, for a memo with a window (`mark_window`) claimed at its
    first sample i, at the window's span only; then the pair tables that
    the bank's previous pixel drew (its tags still say which), filled here
    in one go, the others left to their first draw. Out of line: once per
    pixel and block.

    Why (2026-11-29, fourth session, AMD EPYC Zen 5, 128x128, one thread,
    interleaved pairs of processes, the same film bytes): a table filled at
    its pair's first draw makes that draw leave the inline path (a missed
    branch, two calls) in the middle of the lanes' shading, 22 times a
    pixel on cornell-box. Filled here: cornell-box 16 / 64 / 256 spp -7.4 /
    -4.4 / -0.7 % time (a pixel's fixed cost, so it weighs most at low spp),
    veach-mis 64 spp -3.2 %. Every table filled, drawn or not: 1.5 +- 1.4 %
    faster still at 64 spp, noise, and `direct` would pay for 29 a pixel.
    Before: `sobol`'s draws answered by `random`'s hash, -9.2 +- 1.1 %;
    its tables computed but `random`'s values used, as slow as `sobol`: the
    cost was the sampler's work, not where its points send the packets."""
    prev = memo[base]  # the previous pixel's tag (0: none yet)
    drawn = 0  # the tables it drew: those that carry its tag
    for k in range(TABLE_PAIRS if prev > 0 else 0):
        if memo[base + 1 + k] == prev:
            drawn |= 1 << k
    memo[base] = tag
    jo = base + 1 + TABLE_PAIRS
    key = _order_key(seed, pixel, b)
    first, span, code = 0, n, 0
    mark = memo[jo + _rotated(i, n - 1, n)]  # position i - 1 mod n
    if mark < 0 and b == 0:
        hi = -mark - 1
        if window_span(n, i, hi) < n:
            first, span, code = i, window_span(n, i, hi), _window_code(i, hi)
    for k in range(TABLE_PAIRS):
        memo[base + 1 + k] = code
    _claim_run(memo[jo:jo + n], memo[jo + n:jo + 2 * n], first, min(span, n - first),
               n, key, b, spp)
    if first + span > n:  # the span wraps around the block
        _claim_run(memo[jo:jo + n], memo[jo + n:jo + 2 * n], 0, first + span - n,
                   n, key, b, spp)
    for k in range(min(TABLE_PAIRS, n)):
        if (drawn >> k) & 1:
            _fill_table(memo, base, tag, k, n, pair_key(seed, pixel, k, 7))


@kernel_inline
def _claim_run(seq, dim1, t0, m, n, key, b, spp):
    """`_claim_bank` at the positions [t0, t0 + m)."""
    permute_run(n, key, t0, seq[t0:t0 + m])
    for t in range(t0, t0 + m):
        j = np.uint64(b * spp + seq[t]) & MASK32
        seq[t] = np.int64(j)
        dim1[t] = np.int64(_reversed_sobol1(j))


@kernel
def _fill_table(memo, base, tag, pair, n, key):
    """Pair `pair`'s scrambled points at every position of the bank's block,
    or at the positions its window reads (lo + pair + k mod n, k < hi - lo)
    if its tag holds one (`_window_code`), packed (u bits << 32 | v bits):
    one loop of integer arithmetic over the positions, which LLVM
    vectorizes, instead of one hash chain per draw."""
    t0, m = 0, n
    code = memo[base + 1 + pair]
    if code < 0:
        lo = (-code - 1) & ((1 << _WINDOW_BITS) - 1)
        t0, m = _rotated(lo, pair, n), ((-code - 1) >> _WINDOW_BITS) - lo
    _fill_run(memo, base, pair, n, key, t0, min(m, n - t0))
    if t0 + m > n:  # the window wraps around the block
        _fill_run(memo, base, pair, n, key, 0, t0 + m - n)
    memo[base + 1 + pair] = tag


@kernel_inline
def _fill_run(memo, base, pair, n, key, t0, m):
    """`_fill_table` at the positions [t0, t0 + m)."""
    jo = base + 1 + TABLE_PAIRS + t0
    to = _table_start(base, pair, n) + t0
    s1 = hash32(key, 1)
    s2 = key >> U32
    # slices, not offsets into memo: indices LLVM can tell are in bounds and
    # non-negative, or the loop stays scalar
    seq, dim1, out = memo[jo:jo + m], memo[jo + n:jo + n + m], memo[to:to + m]
    for t in range(m):
        u = reverse_bits32(_scramble_reversed(np.uint64(seq[t]), s1))
        v = reverse_bits32(_scramble_reversed(np.uint64(dim1[t]), s2))
        out[t] = np.int64((u << U32) | v)


@kernel_inline
def sample_pair_memo(seed, pixel, index, spp, pair, memo):
    """`sample_pair`, with the pixel's permutation memoized in `memo` (int64,
    MEMO_BANKS banks of `memo_bank_width` entries; any other length: no
    memo), bit for bit the same values (tested). A pixel uses bank pixel mod
    MEMO_BANKS: the path tracer's packets run the last samples of one pixel
    beside the first of the next ones, and with one bank they evicted each
    other's entries (sobol cost a quarter of the samples/s instead of a
    tenth). A tag names the pixel and block an entry was computed for, so
    the memo needs no clearing between pixels or units and a stale entry is
    never read. Two layouts:

    - entries (width 2 spp): each position's tag and permuted index, filled
      as draws need them;
    - tables (memo_bank_width(spp, True), for kernels that draw a pixel's
      samples in order, the film pair first, and only the samples of
      their window (`mark_window`): the tile kernels, integrators/tile.py):
      a pixel's first film pair (pair 0) claims the bank and computes the
      sequence index and Sobol' dimension 1 of every position its window
      reads (`_claim_bank`), and the points of the pairs below TABLE_PAIRS
      that the bank's previous pixel drew, each pair's in one vectorized
      loop (`_fill_table`); the first draw of any other such pair fills its
      table the same way, and each draw reads its packed point. A draw
      whose pixel lost the bank to a later one (packets run a few pixels
      at once) computes its point itself. A pair's draw was a chain of
      about a hundred scalar integer operations (pair key, memo tag, two
      scrambles, bit reversals); from a table it is a load and two
      conversions."""
    b, i, n = split_block(index, spp, spp)
    if pair < n and b < 1 << 20:  # (tags stay unique)
        w = memo.shape[0]
        tag = (np.int64(pixel) << 20) + b + 1
        bw = _table_bank_width(n)
        if pair < TABLE_PAIRS and w == MEMO_BANKS * bw:
            base = bw * (pixel & (MEMO_BANKS - 1))
            # (a claim resets every table's tag before it fills any, so a
            # table with the pixel's tag is in the pixel's bank; one load
            # less, alone -0.2 +- 1.6 % time, noise)
            if memo[base + 1 + pair] == tag:
                x = np.uint64(memo[_table_start(base, pair, n) + _rotated(i, pair, n)])
                return float(x >> U32) * INV_2_32, float(x & MASK32) * INV_2_32
        elif w == 2 * MEMO_BANKS * n:  # the entries layout: as it was, inline
            t = 2 * n * (pixel & (MEMO_BANKS - 1)) + _rotated(i, pair, n)
            if memo[t] == tag:
                p = memo[n + t]
            else:
                p = _sample_order(seed, pixel, b, i, n, pair, 0)
                memo[t] = tag
                memo[n + t] = p
            return _pair_values(np.uint64(b * (spp if spp > 0 else 1) + p) & MASK32,
                                pair_key(seed, pixel, pair, 7))
    return _sample_pair_memo_slow(seed, pixel, index, spp, pair, memo)


@kernel
def _sample_pair_memo_slow(seed, pixel, index, spp, pair, memo):
    """`sample_pair_memo` but for the inline cases (a pair's table ready, an
    entries-layout draw): out of line, so that the tile kernels inline only
    those."""
    b, i, n = split_block(index, spp, spp)
    if pair < n and b < 1 << 20:  # (tags stay unique)
        w = memo.shape[0]
        tag = (np.int64(pixel) << 20) + b + 1
        bw = _table_bank_width(n)
        if w == MEMO_BANKS * bw:
            base = bw * (pixel & (MEMO_BANKS - 1))
            if pair == 0 and memo[base] != tag:
                _claim_bank(memo, base, tag, seed, pixel, b, n, spp, i)
            if memo[base] == tag:
                t = _rotated(i, pair, n)
                jo = base + 1 + TABLE_PAIRS
                if pair < TABLE_PAIRS:
                    if memo[base + 1 + pair] != tag:
                        _fill_table(memo, base, tag, pair, n, pair_key(seed, pixel, pair, 7))
                    x = np.uint64(memo[_table_start(base, pair, n) + t])
                    return float(x >> U32) * INV_2_32, float(x & MASK32) * INV_2_32
                if memo[jo + t] >= 0:  # (not a window's mark: mark_window)
                    key = pair_key(seed, pixel, pair, 7)
                    u = reverse_bits32(_scramble_reversed(np.uint64(memo[jo + t]),
                                                          hash32(key, 1)))
                    v = reverse_bits32(_scramble_reversed(np.uint64(memo[jo + n + t]),
                                                          key >> U32))
                    return float(u) * INV_2_32, float(v) * INV_2_32
    key = pair_key(seed, pixel, pair, 7)
    p = _sample_order(seed, pixel, b, i, n, pair, key)
    return _pair_values(np.uint64(b * (spp if spp > 0 else 1) + p) & MASK32, key)
