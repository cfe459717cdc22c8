"""An FP8 MLP's gate/up GEMM, GeGLU and the down GEMM's e4m3 input as one Pallas Mosaic GPU kernel (Hopper); and
the same kernel with GELU for SigLIP's MLP (`gelu`: fc1's GEMM, bias, GELU-tanh and fc2's e4m3 input).

XLA runs an FP8 Gemma MLP (`engine.layers._mlp` on `QArray` weights) as cuBLASLt's e4m3 GEMM into the activation
dtype, then one fusion that scales gate and up per column, computes GELU-tanh(gate) * up and quantises it for the
down GEMM. That fusion is a pass over the GEMM's whole output: in π0's FP8 prefix it costs a third of the gate/up
GEMM's time at B >= 8 and a quarter at B = 1 (H200, docs/BENCHMARKS.md, session 53). cuBLASLt takes only scalar
scales in an FP8 GEMM's epilogue, so the pass cannot join it there. Here it is the GEMM's epilogue.

The kernel is persistent: a CTA per SM walks (tile_m x tile_n) tiles of the output in a snake order; a producer
warpgroup streams x and weight tiles by TMA, `stages` deep; `wgs` compute warpgroups each own tile_n / wgs weight
columns (whole gate/up block pairs, `ops.layout.gate_up_block`) as an f32 wgmma accumulator over the whole K. e4m3
wgmma needs both operands K-major: x is (M, K) and the weight (2F, K), as the engine lays out FP8 weights.

Numerics: the accumulator times its column's f32 scale (act_scale x the weight's scale; up's columns also divided by
the down GEMM's activation scale, folded in), GELU-tanh(gate) * up in f32 (in the launch's form, `gelu_form`: by
default `gelu_folded`, `engine.layers.gelu_tanh`'s x sigmoid(2 z) with its constants folded), converted to e4m3
(nearest even, saturating at ±448). XLA's path rounds gate and up to the activation
dtype and divides after the product: in bf16 the two agree to that rounding, so an e4m3 output near a rounding
boundary may take the next e4m3 value.

On a GPU the last row tile may be ragged (TMA reads zeros past the end and drops stores there), once the rows are
a multiple of 8 (`run` pads them). Mosaic GPU's CPU interpreter (the tests) refuses a ragged tile, and has no
transposed wgmma operand: there the rows are padded to whole tiles and the weight streams as its (K, 2F) transpose,
so the interpreter checks the tiling, the pipeline and the epilogue; the GPU form (K-major operand, ragged rows) is
lowered for sm_90 on the CPU by the tests (`lowering_platforms`). Under a sharded jit each device runs it on its
own rows (`custom_partitioning`). The engine runs it in the prefix's FP8 MLPs on a Hopper GPU (`engine.layers.
FP8_GEGLU`): π0's FP8 prefix 8.6 % faster at B = 8 and 2.1 % at B = 1 (H200, docs/BENCHMARKS.md, session 56); and
from B = 8 in the action expert's and SigLIP's (session 57).

`gelu` takes a (N, K) weight whose N no tile divides (SigLIP's 4,304): on a GPU its last column tile is ragged (TMA
reads zero weight rows past N and drops stores there), and since a TMA layout's tiles must divide the array they
write, the output goes out 16 columns (16 bytes, unswizzled) at a time; the epilogue's (3, N) table (column scales,
bias, 1 / the next GEMM's activation scale) is padded to whole tiles. The interpreter pads N to whole tiles instead.
(Padding N to 4,352 for 64-column swizzled stores made the kernel slower: docs/BENCHMARKS.md, session 61.) Its
epilogue, GELU on every column after 9 K steps, costs as much as 40 % of the mainloop; its arithmetic is
`gelu_folded`, and a GPU's e4m3 conversion saturates by itself (`cvt.rn.satfinite`), so only the interpreter clamps.

Axis legend: M rows, K contraction, N2 = 2F fused gate/up columns, F hidden units.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect

import jax
import jax.experimental.pallas as pl
import jax.experimental.pallas.mosaic_gpu as plgpu
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.experimental.custom_partitioning import custom_partitioning

from pi0_jax.ops import formats, layout, mosaic_gemm
from pi0_jax.ops.formats import E4M3, QArray
from pi0_jax.ops.pallas_base import row_shardings

F32 = jnp.float32
MIN_K = 32   # an e4m3 wgmma's contraction
TMA_ROWS = 8   # a TMA copy's row tiling: a global array's rows are a multiple of it


def whole_index(load) -> tuple:
    """`plgpu.load`'s positional index of a whole ref: jax 0.10 needs one (()); jax 0.11 takes none (an index beside
    the ref is deprecated); jax 0.12 has no such parameter."""
    idx = inspect.signature(load).parameters.get("idx")
    return ((),) if idx is not None and idx.default is inspect.Parameter.empty else ()


_WHOLE = whole_index(plgpu.load)


@dataclasses.dataclass(frozen=True)
class Launch:
    """Rows and weight columns a CTA takes (tile_n: `wgs` compute warpgroups of whole gate/up block pairs), the
    contraction a pipeline step brings (128: one 128-byte swizzled row of e4m3), the TMA pipeline's depth, wgmma
    steps left in flight when the next is issued (`delay`; their tiles are released that many steps later), the tile
    order (`plgpu.planar_snake`: bands of `snake` tiles along dimension `minor`, 0 rows, 1 columns), and Mosaic GPU's
    approximate math (`approx`: the sigmoid's exp as one ex2.approx.f32, without the range reduction around it; its
    division is rcp.approx.f32 either way, as ptxas's input for sm_90a shows), and GELU-tanh's arithmetic folded
    (`folded`: `gelu_folded`), or written with one tanh (`tanh`: `gelu_half_tanh`; with approx one tanh.approx.f32,
    one MUFU instruction a value where the folded form takes two). `cluster`: CTAs in clusters of two on row tiles
    2i and 2i + 1 of one column tile, each bringing half of the weight tile a step and multicasting it to both (TMA
    multicast; cuBLASLt's kernels at these shapes run in 2 x 1 clusters): a CTA's reads from L2 fall by a third
    (GeGLU's 128 x 256 tiles) or a quarter; on a GPU only (the interpreter runs it without), and only where the
    rows fill the clusters (`clusters_pay`)."""

    tile_m: int = 128
    tile_n: int = 256
    tile_k: int = 128
    stages: int = 4
    wgs: int = 2
    delay: int = 0
    snake: int = 8
    minor: int = 0
    approx: bool = False
    folded: bool = False
    tanh: bool = False
    cluster: bool = False


def _tile_k(launch: Launch, k: int) -> int:
    """launch.tile_k halved until it divides K, not below an e4m3 wgmma's 32 (the caller checks that it divides)."""
    tile_k = launch.tile_k
    while k % tile_k and tile_k > MIN_K:
        tile_k //= 2
    return tile_k


def _fitted(launch: Launch, k: int, tile_k: int, tile_n: int, wgs: int) -> Launch:
    """launch with these tiles and warpgroups, its stages no more than K's steps and its delay under its stages."""
    stages = min(launch.stages, k // tile_k)
    return dataclasses.replace(launch, tile_k=tile_k, tile_n=tile_n, wgs=wgs, stages=stages,
                               delay=min(launch.delay, stages - 1))


def fit(launch: Launch, k: int, n2: int) -> Launch | None:
    """The launch for a (K, 2F) weight: tile_k halved until it divides K (not below an e4m3 wgmma's 32), then
    fewer compute warpgroups and fewer block pairs each until tile_n divides 2F (small shapes: the tests). None
    where nothing fits."""
    pair = 2 * layout.gate_up_block(n2 // 2)
    tile_k = _tile_k(launch, k)
    if k % tile_k or tile_k % MIN_K or n2 % pair:
        return None
    widest = launch.tile_n // launch.wgs // pair * pair   # a warpgroup's columns: whole block pairs
    for wgs in range(launch.wgs, 0, -1):
        wg_n = widest
        while wg_n >= pair and (n2 % (wgs * wg_n) or wg_n % pair):
            wg_n -= pair
        if wg_n >= pair:
            return _fitted(launch, k, tile_k, wgs * wg_n, wgs)
    return None


# The launch `geglu` fits to each weight (the engine's): 128 x 256 tiles in 4 stages, GELU folded with the exp's
# approximate form as `GELU_LAUNCH` computes it. π0's every-gemm call at B = 8 2.4 % faster than with session 56's
# epilogue (x sigmoid(2 z) with the exp's range reduction), its kernel time 3.5 % (H100, docs/BENCHMARKS.md, session
# 62). CTAs in clusters of two, with this and `GELU_LAUNCH`: π0's every-gemm call's kernels 0.7-1.8 % shorter at B = 64
# and 1.9-2.2 % at B = 8; its median 0.7-3.3 % shorter at B = 64, level at B = 8 (+0.1, +0.4 %; H200, session 66)
LAUNCH = Launch(folded=True, approx=True, cluster=True)


def _takes(w, nxt, fit_launch) -> bool:
    """w and the next GEMM's weight nxt both FP8 x FP8 (`QArray`s with activation scales), w a K-major (N, K) that
    `fit_launch(k, n)` fits, and on a GPU a Hopper one."""
    if not (isinstance(w, QArray) and isinstance(nxt, QArray) and w.act_scale is not None
            and nxt.act_scale is not None and w.q.ndim == 2 and w.contract == (-1,)):
        return False
    if fit_launch(w.q.shape[1], w.q.shape[0]) is None:
        return False
    return jax.default_backend() == "cpu" or mosaic_gemm.hopper()


def applies(w, down) -> bool:
    """Whether the kernel can take the MLP whose fused gate/up weight is `w` (2F, K) and down weight `down`."""
    return _takes(w, down, lambda k, n: fit(LAUNCH, k, n))


def column_scales(w: QArray, down_scale) -> jax.Array:
    """(2F,) f32: each weight column's output scale (act_scale x the weight's scale), up's columns divided by the
    down GEMM's activation scale, so that the kernel's GELU(gate) * up is the down GEMM's input before e4m3."""
    n2 = w.q.shape[0]
    scale = jnp.broadcast_to(formats.output_scale("...D,FD->...F", w).reshape(-1), (n2,))
    up = (jnp.arange(n2) // layout.gate_up_block(n2 // 2)) % 2 == 1
    return jnp.where(up, scale / jnp.asarray(down_scale, F32), scale)


# GELU-tanh's z = sqrt(2 / pi) (x + 0.044715 x^3)
_SQRT_2_PI, _CUBIC = 0.7978845608028654, np.float32(0.044715)


def gelu_tanh(x):
    """GELU-tanh in f32 as x sigmoid(2 z) (`engine.layers.gelu_tanh`'s form)."""
    z = np.float32(2 * _SQRT_2_PI) * (x + _CUBIC * x * x * x)
    return x * jax.nn.sigmoid(z)


# GELU-tanh(x) = x sigmoid(2 z) = x / (1 + 2^(x (A + B x^2))): the constants of z, its sign and log2(e) in two
_FOLD_A = np.float32(-2 * _SQRT_2_PI / np.log(2.0))
_FOLD_B = np.float32(_FOLD_A * _CUBIC)


def gelu_folded(x):
    """`gelu_tanh` with its constants folded: an exp2 of x (A + B x^2) (three f32 operations, where z and the exp's
    log2(e) take five), then the sigmoid's 1 / (1 + e) as jax lowers it (`lax.logistic`). The same function; its
    f32 result differs by rounding."""
    return x * (1.0 / (1.0 + jnp.exp2(x * (_FOLD_A + _FOLD_B * (x * x)))))


_HALF_TANH_A = np.float32(_SQRT_2_PI)
_HALF_TANH_B = np.float32(_HALF_TANH_A * _CUBIC)


def gelu_half_tanh(x):
    """GELU-tanh as its definition writes it, 0.5 x (1 + tanh(z)) with z = x (A + B x^2): one tanh, no division."""
    h = np.float32(0.5) * x
    return h + h * jnp.tanh(x * (_HALF_TANH_A + _HALF_TANH_B * (x * x)))


def gelu_form(launch: Launch | None):
    """The GELU-tanh a launch's epilogue computes (`gelu_half_tanh`, `gelu_folded` or `gelu_tanh`)."""
    if launch is None:
        return gelu_tanh
    return gelu_half_tanh if launch.tanh else gelu_folded if launch.folded else gelu_tanh


def reference(xq, w: QArray, down_scale, launch: Launch | None = None) -> jax.Array:
    """The kernel's numerics as XLA ops: f32 product, column scales, GeGLU in f32 (GELU in `launch`'s form; None:
    `gelu_tanh`), e4m3."""
    y = jnp.einsum("md,nd->mn", xq, w.q, preferred_element_type=F32) * column_scales(w, down_scale)
    gate, up = layout.split_gate_up(y)
    return jnp.clip(gelu_form(launch)(gate) * up, -formats.E4M3_MAX, formats.E4M3_MAX).astype(E4M3)


def geglu(xq, w: QArray, down_scale, launch: Launch | None = None, scales=None) -> jax.Array:
    """xq (M, K) e4m3 @ w (2F, K) e4m3 in gate/up block pairs -> (M, F) e4m3: GELU-tanh(gate) * up quantised with
    `down_scale` (the down GEMM's activation scale), as `reference` computes it. `applies(w, down)` must hold.
    launch: default `LAUNCH`. scales: `column_scales(w, down_scale)` made before (a loop's invariant), or None."""
    k, n2 = w.q.shape[1], w.q.shape[0]
    launch = fit(LAUNCH if launch is None else launch, k, n2)
    if launch is None or xq.shape[1] != k:
        raise ValueError(f"x {xq.shape} @ w {w.q.shape}.T: no launch of the FP8 GeGLU kernel fits")
    if scales is None:
        scales = column_scales(w, down_scale)
    elif scales.shape != (n2,):
        raise ValueError(f"the FP8 GeGLU kernel's column scales must be ({n2},), got {scales.shape}")
    if jax.default_backend() == "cpu":   # the interpreter (its host callbacks cannot be partitioned): N-major weight
        return run(xq, w.q.T, scales, launch, interpret=True)
    return _partitioned(xq, w.q, scales, launch)


def _row_partitioned(act: str, rule: str, replicated: tuple):
    """`run` with epilogue `act` as a `custom_partitioning` op: under a sharded jit (the simulator's batch mesh) each
    device runs the kernel on its own rows. XLA cannot split a kernel it does not know, and would otherwise gather
    every row onto every device. rule / replicated: the op's Shardy sharding rule and its factors kept whole."""

    @functools.partial(custom_partitioning, static_argnums=(3,))
    def partitioned(xq, wq, scales, launch: Launch):
        return run(xq, wq, scales, launch, act=act)

    def partition(launch, mesh, arg_shapes, result_shape):
        rows, full = row_shardings(mesh, arg_shapes[0].sharding)
        return mesh, lambda xq, wq, scales: run(xq, wq, scales, launch, act=act), rows, (rows, full, full)

    partitioned.def_partition(
        partition=partition,
        infer_sharding_from_operands=lambda launch, mesh, arg_shapes, result_shape: row_shardings(
            mesh, arg_shapes[0].sharding)[0],
        sharding_rule=rule, need_replication_factors=replicated)
    return partitioned


_partitioned = _row_partitioned("geglu", "m k, n k, n -> m f", ("k", "n", "f"))


# An FP8 GEMM with GELU in its epilogue (SigLIP's fc1 into fc2's e4m3 input). Tiles of 128 x 128 (two warpgroups of
# 64 columns) in 4 stages, GELU folded (`gelu_folded`) with the exp's approximate form: alone 15 % faster than session
# 57's 128 x 256 tiles in 3 stages at 6,144 rows (13 waves of 1,632 tiles on 132 SMs against 7 of 816, and no
# spills where the wider tile's epilogue spilled 36-52 bytes), 5.7 % at 49,152; π0's every-gemm call at B = 8 1.3 %
# faster (H100, docs/BENCHMARKS.md, session 61). At 256 columns, 4 stages need 232,528 bytes of shared memory, 80
# more than a Hopper block may have.
GELU_BLOCK = 64
GELU_LAUNCH = Launch(tile_n=128, stages=4, folded=True, approx=True, cluster=True)


def gelu_block(n: int) -> int:
    """`gelu`'s output columns a TMA store takes: the widest of 64, 32, 16 that divides N (a TMA layout's tiles
    must divide the array it writes: SigLIP's 4,304 columns take 16)."""
    return next(b for b in (GELU_BLOCK, 32, 16) if n % b == 0)


def fit_gelu(launch: Launch, k: int, n: int) -> Launch | None:
    """The launch for `gelu` on a (N, K) weight: tile_k as `fit`, column tiles of whole `GELU_BLOCK`s (one warpgroup
    where N fills no more than one's share). N need not divide: on a GPU the last column tile is ragged."""
    tile_k = _tile_k(launch, k)
    wgs = launch.wgs if n > launch.tile_n // launch.wgs else 1
    wg_n = launch.tile_n // launch.wgs
    if k % tile_k or tile_k % MIN_K or wg_n % GELU_BLOCK or n % 16:
        return None
    return _fitted(launch, k, tile_k, wgs * wg_n, wgs)


def gelu_applies(w, nxt) -> bool:
    """Whether `gelu` can take the GEMM of weight `w` (N, K) whose output feeds the GEMM of `nxt`."""
    return _takes(w, nxt, lambda k, n: fit_gelu(GELU_LAUNCH, k, n))


def gelu_table(w: QArray, bias, next_scale, columns: int) -> jax.Array:
    """(3, columns) f32, the epilogue's rows: each column's output scale, its bias, and 1 / the next GEMM's
    activation scale; zero past N (whole column tiles)."""
    n = w.q.shape[0]
    scale = jnp.broadcast_to(formats.output_scale("...D,FD->...F", w).reshape(-1), (n,))
    inv = jnp.broadcast_to(1 / jnp.asarray(next_scale, F32), (n,))
    return jnp.pad(jnp.stack([scale, bias.astype(F32), inv]), ((0, 0), (0, columns - n)))


def gelu_reference(xq, w: QArray, bias, next_scale, launch: Launch | None = None) -> jax.Array:
    """`gelu`'s numerics as XLA ops: f32 product, column scales, bias, GELU-tanh (in `launch`'s form; None:
    `gelu_tanh`), times 1 / next_scale, e4m3."""
    n = w.q.shape[0]
    s, b, inv = gelu_table(w, bias, next_scale, n)
    y = gelu_form(launch)(jnp.einsum("md,nd->mn", xq, w.q, preferred_element_type=F32) * s + b) * inv
    return jnp.clip(y, -formats.E4M3_MAX, formats.E4M3_MAX).astype(E4M3)


def gelu(xq, w: QArray, bias, next_scale, launch: Launch | None = None) -> jax.Array:
    """xq (M, K) e4m3 @ w (N, K) e4m3 -> (M, N) e4m3: GELU-tanh(the product's columns scaled, plus bias) quantised
    with `next_scale` (the next GEMM's activation scale), as `gelu_reference` computes it. `gelu_applies` must hold.
    launch: default `GELU_LAUNCH`."""
    n, k = w.q.shape
    launch = fit_gelu(GELU_LAUNCH if launch is None else launch, k, n)
    if launch is None or xq.shape[1] != k:
        raise ValueError(f"x {xq.shape} @ w {w.q.shape}.T: no launch of the FP8 GELU kernel fits")
    columns = -(-n // launch.tile_n) * launch.tile_n
    table = gelu_table(w, bias, next_scale, columns)
    if jax.default_backend() == "cpu":   # the interpreter: whole column tiles, the weight N-major
        wt = jnp.pad(w.q.T, ((0, 0), (0, columns - n)))
        return run(xq, wt, table, launch, interpret=True, act="gelu")[:, :n]
    return _partitioned_gelu(xq, w.q, table, launch)


_partitioned_gelu = _row_partitioned("gelu", "m k, n k, t c -> m n", ("k", "n", "t", "c"))


# A clustered launch's last cluster takes a tile past the rows where the row tiles are odd: π0's prefix at B = 1 (816
# rows, 7 tiles in 4 clusters) took 13 % longer in its GeGLU kernels, the FP8 call 2.2 %; the expert's 25 tiles at
# B = 64 ran clustered in a call 0.7-3.3 % faster (H200, session 66)
CLUSTER_MIN_ODD_TILES = 16


def clusters_pay(launch: Launch, m: int) -> bool:
    """Whether `launch`'s clusters of two are kept for m rows: an even count of row tiles, or enough of them that the
    last cluster's idle half is at most 1 / 18 of the work (17 tiles and more)."""
    tiles = -(-m // launch.tile_m)
    return launch.cluster and (tiles % 2 == 0 or tiles >= CLUSTER_MIN_ODD_TILES)


def run(xq, wq, scales, launch: Launch, *, interpret: bool = False, sms: int | None = None,
        act: str = "geglu") -> jax.Array:
    """The kernel on xq (M, K) e4m3, wq (2F, K) e4m3 ((K, 2F) when `interpret`) and (2F,) column scales
    (`column_scales`) -> (M, F) e4m3 (act "gelu": wq (N, K), the (3, whole tiles) `gelu_table` -> (M, N)), on `sms`
    CTAs (default: the GPU's SMs); `launch` fits the weight (`fit`). Rows are padded with zeros and cut back: to
    whole row tiles in the interpreter, and on a GPU to TMA's row tiling (its copies take a last row tile that is
    ragged, but not rows that are not a multiple of 8: the expert's 50 B rows at an odd B). A clustered launch runs
    without clusters where they do not pay (`clusters_pay`)."""
    if not interpret and sms is None:
        sms = jax.devices()[0].core_count
    m, k = xq.shape
    launch = dataclasses.replace(launch, cluster=clusters_pay(launch, m))
    step = launch.tile_m if interpret else TMA_ROWS
    mp = -(-m // step) * step
    xp = jnp.pad(xq, ((0, mp - m), (0, 0))) if mp != m else xq
    out = _call(mp, k, wq.shape[1] if interpret else wq.shape[0], launch, interpret, sms=sms or 1,
                act=act)(xp, wq, scales)
    return out[:m] if mp != m else out


@functools.lru_cache(maxsize=None)
def _call(m: int, k: int, n2: int, launch: Launch, interpret: bool, out: str = "e4m3", sms: int = 1,
          act: str = "geglu"):
    """The kernel for x (m, k), a (n2, k) weight ((k, n2) when `interpret`) and (n2,) column scales, on `sms` CTAs
    (the GPU's SMs; given, so that it lowers for a GPU on a CPU too: the tests). out: "e4m3" (the down GEMM's input),
    or, to tell a GPU run's parts apart (`scripts/fp8_geglu_probe.py`), "bf16" (GeGLU's product unquantised) or
    "product" (the raw GEMM in bf16, (m, n2), no epilogue but the store). act "gelu": the epilogue is `gelu`'s, the
    scales a (3, whole column tiles) table (`gelu_table`), the output (m, n2), n2 ragged on a GPU."""
    tm, tn, tk, wgs = launch.tile_m, launch.tile_n, launch.tile_k, launch.wgs
    wg_n = tn // wgs
    gelu = act == "gelu"
    gelu_fn = gelu_form(launch)

    def saturated(y):
        """y clamped to e4m3's range, as `formats.quantise`, where the cast does not saturate (the interpreter's): a
        GPU's e4m3 conversion saturates by itself (cvt.rn.satfinite, a NaN stays NaN)."""
        return jnp.minimum(jnp.maximum(y, -formats.E4M3_MAX), formats.E4M3_MAX) if interpret else y

    block = gelu_block(n2) if gelu else layout.gate_up_block(n2 // 2)
    pairs = wg_n // block if gelu else wg_n // (2 * block)   # gelu: the epilogue's column chunks
    m_iters, n_iters, k_iters = -(-m // tm), -(-n2 // tn), k // tk
    # row tiles 2i, 2i + 1 of a cluster share the weight tile's loads; with an odd count the last cluster's second
    # tile lies past the rows: TMA reads it as zeros and drops its stores
    clustered = launch.cluster and not interpret
    if clustered:
        m_iters = -(-m_iters // 2)
    out_dtype = {"e4m3": E4M3, "bf16": jnp.bfloat16, "product": jnp.bfloat16}[out]
    in_tr = mosaic_gemm.transforms(tk, E4M3)   # no swizzle below 32 bytes
    out_tr = ((plgpu.TilingTransform((8, block)),) if block * jnp.dtype(out_dtype).itemsize < 32
              else mosaic_gemm.transforms(block, out_dtype))

    def pipeline(body, context):
        spec = functools.partial(plgpu.BlockSpec, memory_space=plgpu.SMEM, transforms=in_tr,
                                 delay_release=launch.delay)
        w_spec = (spec((tk, tn), lambda kk: (kk, 0), transforms=mosaic_gemm.transforms(tn, E4M3)) if interpret
                  else spec((tn, tk), lambda kk: (0, kk), collective_axes=("cluster",) if clustered else ()))
        return plgpu.emit_pipeline_warp_specialized(
            body, grid=(k_iters,), memory_registers=40, in_specs=[spec((tm, tk), lambda kk: (0, kk)), w_spec],
            wg_axis="wg", num_compute_wgs=wgs, max_concurrent_steps=launch.stages, compute_context=context)

    def kernel(x_gmem, w_gmem, s_gmem, o_gmem):
        nothing = lambda *_, **__: None   # noqa: E731
        out_smem = (plgpu.SMEM((wgs, tm, block), out_dtype, transforms=out_tr) if out == "product"
                    else plgpu.SMEM((wgs, pairs, tm, block), out_dtype, transforms=out_tr))

        @functools.partial(pl.run_scoped, allocs=pipeline(nothing, nothing).get_allocations(x_gmem, w_gmem),
                           out_smem=out_smem, s_smem=plgpu.SMEM((wgs, 3, wg_n) if gelu else (wgs, wg_n), F32),
                           s_bar=plgpu.Barrier(num_barriers=wgs), collective_axes="wg")
        def scope(allocs, out_smem, s_smem, s_bar):
            wg = lax.axis_index("wg")

            @plgpu.nd_loop((m_iters * n_iters,), collective_axes="cluster_grid")
            def tiles(info):
                (lin,) = info.index
                mi, ni = plgpu.planar_snake(lin, (m_iters, n_iters), launch.minor, launch.snake)
                if clustered:
                    mi = mi * 2 + lax.axis_index("cluster")
                rows = pl.ds(mi * tm, tm)
                col0 = ni * tn + wg * wg_n
                # the output's column: no `//` on a traced index (its floor-division selects leave Mosaic GPU's
                # layout inference without a solution, jax 0.10.2)
                h_col0 = ni * (tn // 2) + wg * (wg_n // 2)

                def context(run):
                    plgpu.copy_gmem_to_smem(s_gmem.at[:, pl.ds(col0, wg_n)] if gelu else s_gmem.at[pl.ds(col0, wg_n)],
                                            s_smem.at[wg], s_bar.at[wg])

                    @functools.partial(pl.run_scoped, acc=plgpu.ACC((tm, wg_n), F32))
                    def _(acc):
                        run(acc)
                        plgpu.barrier_wait(s_bar.at[wg])
                        if out == "product":   # in column chunks of one block (shared memory is full)
                            y = acc[...].astype(out_dtype)
                            for c in range(wg_n // block):
                                plgpu.wait_smem_to_gmem(0, wait_read_only=True)
                                out_smem[wg] = y[:, c * block:(c + 1) * block]
                                plgpu.commit_smem()
                                plgpu.copy_smem_to_gmem(out_smem.at[wg],
                                                        o_gmem.at[rows, pl.ds(col0 + c * block, block)])
                            return
                        # the interpreter has no plgpu.load; on a GPU it gives the scales the accumulator's columns'
                        # layout
                        def row(ref):
                            v = ref[...] if interpret else plgpu.load(ref, *_WHOLE, layout=plgpu.Layout.WGMMA.reduce(0))
                            return lax.broadcast_in_dim(v, (tm, wg_n), [1])   # as jax's Mosaic kernels do

                        if gelu:
                            y = acc[...] * row(s_smem.at[wg, 0]) + row(s_smem.at[wg, 1])
                            y = saturated(gelu_fn(y) * row(s_smem.at[wg, 2]))
                            plgpu.wait_smem_to_gmem(0, wait_read_only=True)
                            for c in range(pairs):
                                out_smem[wg, c] = y[:, c * block:(c + 1) * block].astype(out_dtype)
                            plgpu.commit_smem()
                            for c in range(pairs):   # on a GPU, TMA drops the columns past n2
                                plgpu.copy_smem_to_gmem(out_smem.at[wg, c],
                                                        o_gmem.at[rows, pl.ds(col0 + c * block, block)])
                            return
                        y = acc[...] * row(s_smem.at[wg])
                        plgpu.wait_smem_to_gmem(0, wait_read_only=True)
                        for p in range(pairs):
                            h = gelu_fn(y[:, 2 * p * block:(2 * p + 1) * block]) * \
                                y[:, (2 * p + 1) * block:(2 * p + 2) * block]
                            if out == "e4m3":
                                h = saturated(h)
                            out_smem[wg, p] = h.astype(out_dtype)
                        plgpu.commit_smem()
                        for p in range(pairs):
                            plgpu.copy_smem_to_gmem(out_smem.at[wg, p],
                                                    o_gmem.at[rows, pl.ds(h_col0 + p * block, block)])

                def body(_, x_smem, w_smem, acc):
                    cols = pl.ds(wg * wg_n, wg_n)
                    plgpu.wgmma(acc, x_smem, w_smem.at[:, cols] if interpret
                                else w_smem.at[cols].transpose((1, 0)))
                    plgpu.wgmma_wait(launch.delay)
                    return acc

                w_cols = pl.ds(ni * tn, tn)
                pipeline(body, context)(x_gmem.at[rows, :], w_gmem.at[:, w_cols] if interpret
                                        else w_gmem.at[w_cols, :], allocations=allocs)
        plgpu.wait_smem_to_gmem(0, wait_read_only=True)

    params = plgpu.CompilerParams(lowering_semantics=plgpu.LoweringSemantics.Warpgroup,
                                  **({"approx_math": True} if launch.approx else {}))
    shape = (m, n2) if out == "product" or gelu else (m, n2 // 2)
    grid = 1 if interpret else sms // 2 if clustered else sms
    return plgpu.kernel(kernel, out_type=jax.ShapeDtypeStruct(shape, out_dtype), grid=(grid,),
                        grid_names=("cluster_grid",), num_threads=wgs + 1, thread_name="wg", compiler_params=params,
                        **({"cluster": (2,), "cluster_names": ("cluster",)} if clustered else {}),
                        kernel_name="fp8_gelu" if gelu else "fp8_geglu",
                        **({"interpret": mosaic_gemm._interpret()} if interpret else {}))
