"""A layer's four GEMMs and its norms for all 18 layers as ONE persistent Mosaic GPU kernel, the weights streamed
without a break.

Sessions 30-41 left the denoise step at the sum of its kernels' own latencies: each GEMM kernel pays 3-4 us of
ramp-up and tail whatever its work (`mgpu_gemm_probe.py --k-sweep`), a boundary inside XLA's command buffers costs
almost nothing, and a persistent kernel whose phases each start their weight stream after a barrier (Triton, session
30) or only a pipeline's depth before it (Mosaic GPU, gate/up alone, session 31) was level. What no probe had done:
stream the weights as one continuous sequence across phases and layers, as far ahead as shared memory holds, so that
only the activations wait at the grid barriers. The weights do not depend on the activations.

One CTA per SM (`--ctas`), two warpgroups:
  producer  walks the CTA's weight tiles (64 K rows x 64 columns, 8 KB) of every phase of every layer in order and
            copies each by TMA into a ring of `--ring` slots as soon as the compute warpgroup frees one; it never
            waits for a barrier, so it runs up to `ring` tiles ahead (14 slots on 128 CTAs are 14.7 MB, 42 % of a
            layer's 34.6 MB; with 4 activation tiles in flight that is 208 KB of shared memory a CTA)
  compute   for each phase: waits at the grid barrier (a GPU-scope semaphore from `pl.get_global`), brings its
            item's activation tiles by TMA (`--xdepth` deep), runs wgmma against the ring, writes its output, signals

Phases a layer (pi0's expert at B = 1: 64 rows, the attention left out, as `persistent_probe.py`):
  q    RMSNorm(h) @ w_qkv (1024 x 2560) -> qkv (bf16). h is the f32 residual: each tile is rounded to bf16 in
       registers on its way in and goes to wgmma as its register operand; the norm's squares are summed on the way
       too, and the product's rows are scaled by 1 / rms after the GEMM (`--norm`; the norm's weight taken as 1)
  o    qkv[:, :2048] @ w_out (2048 x 1024), K split `--splits` ways; each split's f32 product added into h by
       TMA's reduce-add (the residual and the split sum in one store)
  g    RMSNorm(h) @ w_gate_up (1024 x 2 x 4096, gate and up in blocks of 32) -> GELU-tanh(gate) * up (bf16)
  d    act @ w_down (4096 x 1024), K split, reduce-added into h

Against it, in one process on the same weights (kernel time per layer from a profiler trace): the engine's kernels
for the same four GEMMs (`persistent_probe.engine_chain`: its norms and RoPE included), XLA's chain, and XLA reading
every weight array once. Checked against XLA's chain (f32 accumulation, the model's roundings) and against itself
on a second call (with `--splits 1` bit-equal; split, the reduce-add's order moves the last bits).

What it showed (docs/BENCHMARKS.md, session 42; us a layer, kernel time):
  - H200: 22.2 with the norms and 4 activation tiles in flight (23.0 with 3; 19.6-20.1 without the norms) against
    28.3 for the engine's kernels, 34.1-34.7 for XLA's chain and 19.8-20.0 for XLA only reading each weight once;
    H100: 23.6-24.2 (3 tiles in flight) against 31.8 (XLA reading: 23.0).
  - Where it goes (with the norms, 3 tiles in flight): the grid barriers 3.0 (H200) and 3.5-4.3 (H100), the
    activation tiles 6.9 and 5.3; the weight stream alone 12.7 (2.7 TB/s) and 14.6 (2.4 TB/s). A ring of 4 slots
    instead of 16 costs 3.5 (H200, no activations or barriers).
  - The rounded residual written back to shared memory for wgmma (`--lhs smem`, a store and a fence a step) cost
    8.7; the norm's squares with the K steps unrolled took ptxas from 166 to 255 registers and spilled (46 against
    23 in a loop, `--loop`).

    python scripts/mgpu_layer_probe.py --out layer.json              # GPU (Hopper)
    python scripts/mgpu_layer_probe.py --out layer.json              # GPU (Hopper)
    python scripts/mgpu_layer_probe.py --cpu-check                   # Mosaic GPU's interpreter, small, 1 CTA
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
import time
import traceback
from pathlib import Path

import jax
import jax.experimental.pallas as pl
import jax.experimental.pallas.mosaic_gpu as plgpu
import jax.numpy as jnp
import numpy as np
from jax import lax

from pi0_jax.ops import mosaic_gemm
from pi0_jax.ops.mosaic_gemm import transforms as _t

sys.path.insert(0, str(Path(__file__).parent))
from mgpu_pdl_probe import interleave as pdl_interleave  # noqa: E402
from persistent_probe import engine_chain  # noqa: E402
from profile_engine import kernel_times  # noqa: E402

ROWS = TK = TN = 64   # rows (50 suffix tokens padded), a tile's K rows and its columns
UNITS = TN // 2   # GeGLU units a tile: gate and up alternate in blocks of 32 columns
EPS = 1e-6   # Gemma's RMSNorm


@dataclasses.dataclass(frozen=True)
class Dims:
    d: int = 1024     # width
    nq: int = 2560    # q/k/v columns
    a: int = 2048     # the out-projection's contraction (q's columns)
    f: int = 4096     # GeGLU units
    layers: int = 18


@dataclasses.dataclass(frozen=True)
class Phase:
    name: str
    k: int
    cols: int        # weight columns
    splits: int
    x: str           # "h" (f32 residual), "qkv" or "act" (bf16)
    out: str         # "store" (bf16), "add" (f32 reduce-add into h), "geglu"

    @property
    def items(self) -> int:
        return self.cols // TN * self.splits

    @property
    def steps(self) -> int:
        return self.k // self.splits // TK


def phases(dm: Dims, splits: int, order: str = "qogd") -> tuple:
    """A layer's phases in `order`: "qogd" (the layer), or "ogdq", the chain after a layer's attention (the
    out-projection on the attention's output, an input of the kernel, through the next layer's q/k/v)."""
    ps = {"q": Phase("q", dm.d, dm.nq, 1, "h", "store"),
          "o": Phase("o", dm.a, dm.d, splits, "att" if order == "ogdq" else "qkv", "add"),
          "g": Phase("g", dm.d, 2 * dm.f, 1, "h", "geglu"), "d": Phase("d", dm.f, dm.d, splits, "act", "add")}
    assert sorted(order) == sorted("qogd"), order
    return tuple(ps[n] for n in order)


def _mod(kk, n: int):
    """kk % n for a K step that is a Python int (unrolled) or traced (a loop)."""
    return kk % n if isinstance(kk, int) else lax.rem(kk, n)


def _when(cond, fn):
    """fn() where cond holds: a Python bool decides at trace time, a traced one in the kernel."""
    if isinstance(cond, bool):
        return fn() if cond else None
    return pl.when(cond)(fn)


def union(*refs):
    """Shared memory used by one phase or another: a RefUnion (the interpreter has none: apart there)."""
    return refs if jax.default_backend() == "cpu" else plgpu.RefUnion(*refs)


def signal(sem):
    """+1 on a GPU-scope semaphore (the interpreter of jax 0.10.2 lowers none; its one CTA needs none)."""
    if jax.default_backend() != "cpu":
        plgpu.semaphore_signal(sem, 1, memory_scope="gpu")


def wait(sem, target, decrement=False):
    """Wait until a GPU-scope semaphore reaches target (none in the interpreter, as `signal`)."""
    if jax.default_backend() != "cpu":
        plgpu.semaphore_wait(sem, target, decrement=decrement, memory_scope="gpu")


def add_into(y, dst, stage, bar, on_cpu: bool):
    """dst (GMEM) += y (f32) through the f32 staging tile `stage`, by TMA's reduce-add; in the interpreter (no
    reduce-add) its one CTA reads, adds and writes back alone, through `bar`."""
    plgpu.wait_smem_to_gmem(0, wait_read_only=True)   # the stage's last store has read it
    stage[...] = y
    plgpu.commit_smem()
    if on_cpu:
        plgpu.wait_smem_to_gmem(0)
        plgpu.copy_gmem_to_smem(dst, stage, bar)
        plgpu.barrier_wait(bar)
        stage[...] = stage[...] + y
        plgpu.commit_smem()
        plgpu.copy_smem_to_gmem(stage, dst)
    else:
        plgpu.copy_smem_to_gmem(stage, dst, reduction_op="add")


def copy_columns(src, dst, stage, bar, c, ctas: int, width: int):
    """dst <- src (GMEM, 64 rows), CTA c taking the 64-column tiles c, c + ctas, ... through `stage`."""
    @pl.loop(c, width // TN, step=ctas)
    def _(tile):
        cols = pl.ds(tile * TN, TN)
        plgpu.copy_gmem_to_smem(src.at[:, cols], stage, bar)
        plgpu.barrier_wait(bar)
        plgpu.copy_smem_to_gmem(stage, dst.at[:, cols])
        plgpu.wait_smem_to_gmem(0)


def drain(empty, ring: int, t):
    """The producer's last wait on each ring slot's release (positions t - ring .. t - 1), so that every phase of
    the barriers is observed before the kernel ends."""
    @pl.loop(jnp.maximum(t - ring, 0), t)
    def _(i):
        plgpu.barrier_wait(empty.at[lax.rem(i, ring)])


@functools.lru_cache(maxsize=None)
def layer_kernel(dm: Dims, ctas: int, ring: int, xdepth: int, splits: int, lhs: str = "regs", norm: str = "",
                 regs: int = 0, loop: bool = False, dtype=jnp.bfloat16, ablate: str = "", order: str = "qogd"):
    """(h0 f32 (64, d), w_qkv, w_out, w_gate_up (blocks of 32), w_down, each (L, K, N) in `dtype`) -> h (f32).
    lhs: how q's and g's GEMMs take the f32 residual's tiles, rounded: from registers ("regs": wgmma's register
    operand) or written back to shared memory ("smem"). norm: q's and g's GEMMs take RMSNorm(h) (its weight taken
    as 1): each row's sum of squares gathered from the tiles on their way to the GEMM, the product's rows scaled by
    1 / rms after it, so the norm costs no pass of its own; the squares of the f32 tile as loaded ("tile"), of the
    tile loaded in wgmma's layout ("load"), or of the bf16 operand ("rounded"); "" for no norm. regs: registers a
    thread of the compute warpgroup may use, the producer's cut to 40 (0: the compiler's default). loop: an item's
    K steps as a loop rather than unrolled (ptxas held 166 registers unrolled, and spilled at 255 with the norm's
    squares). dtype: bf16 on a GPU (f32 in the interpreter's check). ablate (timing only, the result is wrong): a
    comma list of "nobarrier" (no phase waits for the one before), "nox" (no activation tile is brought: every GEMM
    reads stale tiles), "noconv" (the residual's f32 tiles are brought but not rounded into the GEMM's operand),
    "x16" (q and g bring bf16 tiles, of q/k/v's buffer, as a bf16 copy of the residual would be), "nocopy" (h0
    is not copied into h first: the cost of that phase, which a kernel taking h in place would not have). order: the
    phases' (`phases`); with "ogdq" the kernel takes the attention's output (64, a) bf16 after h0 and returns
    (h, qkv): one launch a layer between the attention's kernels (`mgpu_step_probe.py --chain`)."""
    ablate = set(filter(None, ablate.split(",")))
    ps = phases(dm, splits, order)
    takes_att = order == "ogdq"
    bf16, f32 = dtype, jnp.float32
    n_phases = 1 + 4 * dm.layers   # a copy of h0 into h, then 4 a layer
    on_cpu = jax.default_backend() == "cpu"
    # Mosaic GPU's interpreter (jax 0.10.2) cannot lower semaphores; its one CTA never waits at a barrier
    assert ctas == 1 or not on_cpu, "the interpreter runs one CTA"

    def kernel(h0, *refs):
        att, (wq, wo, wg, wd, h, qkv, act) = (refs[0], refs[1:]) if takes_att else (None, refs)
        c = lax.axis_index("c")
        sem = None if on_cpu else pl.get_global(plgpu.SemaphoreType.REGULAR)
        weights = {"q": wq, "o": wo, "g": wg, "d": wd}

        def mine(ph):   # this CTA's items of a phase: c, c + ctas, ...
            return jnp.maximum(ph.items - c + ctas - 1, 0) // ctas

        @functools.partial(
            pl.run_scoped,
            w_ring=plgpu.SMEM((ring, TK, TN), bf16, transforms=_t(TN, bf16)),
            full=plgpu.Barrier(num_arrivals=1, num_barriers=ring),
            empty=plgpu.Barrier(num_arrivals=1, num_barriers=ring),
            xs=union(plgpu.SMEM((xdepth, ROWS, TK), f32, transforms=_t(TK, f32)),   # a phase's x
                     plgpu.SMEM((xdepth, ROWS, TK), bf16, transforms=_t(TK, bf16))),  # is one or other
            x_bar=plgpu.Barrier(num_arrivals=1, num_barriers=xdepth),
            x_op=plgpu.SMEM((2, ROWS, TK), bf16, transforms=_t(TK, bf16)),
            outs=union(plgpu.SMEM((ROWS, TN), bf16, transforms=_t(TN, bf16)),
                       plgpu.SMEM((ROWS, TN), f32, transforms=_t(TN, f32)),
                       plgpu.SMEM((ROWS, UNITS), bf16, transforms=_t(UNITS, bf16))),
            collective_axes="wg")
        def scope(w_ring, full, empty, xs, x_bar, x_op, outs):
            (x32, x16), (o16, o32, og) = xs, outs   # each phase's stores land before the next phase starts
            wg = lax.axis_index("wg")

            @pl.when(wg == 1)
            def producer():
                if regs:
                    plgpu.set_max_registers(40, action="decrease")

                def layer(l, t):
                    for ph in ps:
                        def item(m, t, ph=ph):
                            i = c + m * ctas
                            j, s = i // ph.splits, lax.rem(i, ph.splits)
                            for kk in range(ph.steps):
                                slot = lax.rem(t + kk, ring)

                                @pl.when(t + kk >= ring)
                                def _():
                                    plgpu.barrier_wait(empty.at[slot])
                                rows = pl.ds((s * ph.steps + kk) * TK, TK)
                                plgpu.copy_gmem_to_smem(weights[ph.name].at[l, rows, pl.ds(j * TN, TN)],
                                                        w_ring.at[slot], full.at[slot])
                            return t + ph.steps
                        t = lax.fori_loop(0, mine(ph), item, t)
                    return t
                drain(empty, ring, lax.fori_loop(0, dm.layers, layer, jnp.int32(0)))

            @pl.when(wg == 0)
            def compute():
                if regs:   # the accumulator, the norm's squares and a tile in flight, without spilling
                    plgpu.set_max_registers(regs, action="increase")

                if "nocopy" not in ablate:
                    copy_columns(h0, h, o32, x_bar.at[0], c, ctas, dm.d)   # h <- h0
                signal(sem)

                def f32_x(ph):   # whether the phase's activation tiles are the f32 residual's
                    return ph.x == "h" and "x16" not in ablate

                def x_copy(ph, s, kk):
                    if "nox" in ablate:
                        return
                    src = {"h": qkv if "x16" in ablate else h, "qkv": qkv, "act": act, "att": att}[ph.x]
                    xs_ = _mod(kk, xdepth)
                    dst = (x32 if f32_x(ph) else x16).at[xs_]
                    plgpu.copy_gmem_to_smem(src.at[:, pl.ds((s * ph.steps + kk) * TK, TK)], dst,
                                            x_bar.at[xs_])

                def layer(l, t):
                    for p, ph in enumerate(ps):
                        if "nobarrier" not in ablate:
                            wait(sem, (1 + 4 * l + p) * ctas)

                        def item(m, t, ph=ph):
                            i = c + m * ctas
                            j, s = i // ph.splits, lax.rem(i, ph.splits)
                            for kk in range(min(xdepth, ph.steps)):
                                x_copy(ph, s, kk)

                            @functools.partial(pl.run_scoped, acc=plgpu.ACC((ROWS, TN), f32))
                            def run(acc):
                                def step(kk, squares):   # squares: h's, summed over the K tiles (norm)
                                    xs_ = _mod(kk, xdepth)
                                    if "nox" not in ablate:
                                        plgpu.barrier_wait(x_bar.at[xs_])
                                    if f32_x(ph):   # the f32 residual, rounded as the GEMM's operand
                                        a_tile = x_op.at[_mod(kk, 2)]
                                        if not ablate & {"nox", "noconv"}:
                                            if norm == "load":
                                                tile = plgpu.load(x32.at[xs_], (), layout=plgpu.Layout.WGMMA)  # noqa
                                            else:
                                                tile = x32.at[xs_][...]
                                            rounded = tile.astype(bf16)
                                            if norm:   # elementwise here, one row reduction an item
                                                sq = rounded.astype(f32) if norm == "rounded" else tile
                                                squares = sq * sq if squares is None else squares + sq * sq
                                            if lhs == "regs":
                                                a_tile = rounded
                                            else:
                                                a_tile[...] = rounded
                                                plgpu.commit_smem()
                                        _when(kk + xdepth < ph.steps,   # its f32 slot is free once read
                                             lambda: x_copy(ph, s, kk + xdepth))
                                    else:
                                        a_tile = x16.at[xs_]
                                    slot = lax.rem(t + kk, ring)
                                    plgpu.barrier_wait(full.at[slot])
                                    plgpu.wgmma(acc, a_tile, w_ring.at[slot])
                                    plgpu.wgmma_wait(1)   # step kk - 1's wgmma is done: its tiles are free

                                    def release():
                                        plgpu.barrier_arrive(empty.at[lax.rem(t + kk - 1, ring)])
                                        if not f32_x(ph):
                                            _when(kk - 1 + xdepth < ph.steps, lambda: x_copy(ph, s, kk - 1 + xdepth))
                                    _when(kk > 0, release)
                                    return squares

                                if loop:   # one step's code in a loop: fewer registers live than unrolled
                                    squares = lax.fori_loop(0, ph.steps, step, jnp.zeros((ROWS, TK), f32)
                                                            if norm and f32_x(ph) else None)
                                else:
                                    squares = None
                                    for kk in range(ph.steps):
                                        squares = step(kk, squares)
                                plgpu.wgmma_wait(0)
                                plgpu.barrier_arrive(empty.at[lax.rem(t + ph.steps - 1, ring)])
                                plgpu.wait_smem_to_gmem(0, wait_read_only=True)   # the last item's store read
                                y = acc[...]
                                if squares is not None:
                                    y = y * lax.rsqrt(jnp.sum(squares, axis=1) * (1 / dm.d) + EPS)[:, None]
                                if ph.out == "store":
                                    o16[...] = y.astype(bf16)
                                    plgpu.commit_smem()
                                    plgpu.copy_smem_to_gmem(o16, qkv.at[:, pl.ds(j * TN, TN)])
                                elif ph.out == "add":
                                    add_into(y, h.at[:, pl.ds(j * TN, TN)], o32, x_bar.at[0], on_cpu)
                                else:
                                    og[...] = mosaic_gemm._gelu_product(y[:, :UNITS], y[:, UNITS:], bf16)
                                    plgpu.commit_smem()
                                    plgpu.copy_smem_to_gmem(og, act.at[:, pl.ds(j * UNITS, UNITS)])
                            return t + ph.steps
                        t = lax.fori_loop(0, mine(ph), item, t)
                        plgpu.wait_smem_to_gmem(0)   # this phase's stores have landed
                        signal(sem)
                    return t
                lax.fori_loop(0, dm.layers, layer, jnp.int32(0))

                @pl.when(c == 0)
                def _():   # every CTA signalled once a phase: take the count back, the next call starts at zero
                    wait(sem, n_phases * ctas, decrement=True)

    out = (jax.ShapeDtypeStruct((ROWS, dm.d), f32), jax.ShapeDtypeStruct((ROWS, dm.nq), bf16),
           jax.ShapeDtypeStruct((ROWS, dm.f), bf16))
    call = plgpu.kernel(kernel, out_type=out, grid=(ctas,), grid_names=("c",), num_threads=2, thread_name="wg",
                        kernel_name="persistent_layers",
                        compiler_params=plgpu.CompilerParams(lowering_semantics=plgpu.LoweringSemantics.Warpgroup),
                        **({"interpret": mosaic_gemm._interpret()} if on_cpu else {}))
    if takes_att:
        return jax.jit(lambda h0, att, ws: call(h0, att, *ws)[:2])
    return jax.jit(lambda h0, ws: call(h0, *ws)[0])


def interleave(w, f: int):
    """(L, K, 2F) [gate | up] -> gate and up alternating in blocks of UNITS columns, layer by layer."""
    return jax.vmap(functools.partial(pdl_interleave, hidden=f, units=UNITS))(w)


def reference(h, ws, dm: Dims, norm=False):
    """The chain in XLA: h f32; each GEMM's operand bf16 (norm: RMSNorm(h), as the model rounds it), f32
    accumulation."""
    bf16, f32 = ws[0].dtype, jnp.float32

    def operand(h):
        if norm:
            h = h * lax.rsqrt(jnp.mean(h * h, axis=-1, keepdims=True) + EPS)
        return h.astype(bf16)

    for l in range(dm.layers):
        wq, wo, wg, wd = (w[l] for w in ws)   # wg: [gate | up]
        qkv = jnp.dot(operand(h), wq, preferred_element_type=f32).astype(bf16)
        h = h + jnp.dot(qkv[:, :dm.a], wo, preferred_element_type=f32)
        gu = jnp.dot(operand(h), wg, preferred_element_type=f32)
        act = mosaic_gemm._gelu_product(gu[:, :dm.f], gu[:, dm.f:], bf16)
        h = h + jnp.dot(act, wd, preferred_element_type=f32)
    return h


def inputs(dm: Dims, seed: int = 0):
    """h0 and the weights at gains that keep 18 layers of residual sums in range."""
    ks = jax.random.split(jax.random.key(seed), 5)
    h0 = jax.random.normal(ks[0], (ROWS, dm.d), jnp.float32)
    shapes = [(dm.d, dm.nq), (dm.a, dm.d), (dm.d, 2 * dm.f), (dm.f, dm.d)]
    ws = [(jax.random.normal(k, (dm.layers, kk, n), jnp.float32) * (0.5 / np.sqrt(kk))).astype(jnp.bfloat16)
          for k, (kk, n) in zip(ks[1:], shapes)]
    return h0, ws


def _rel(got, want):
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    return float(np.linalg.norm(got - want) / max(np.linalg.norm(want), 1e-30))


def timed(fns: dict, res: dict, layers: int, iters: int, out: str) -> None:
    """Each fn()'s kernel time a layer, from a profiler trace of `iters` calls, into res["rows"]; res written to out."""
    for name, fn in fns.items():
        trace = kernel_times(fn, calls=iters)
        row = res["rows"].setdefault(name, {})
        row.update(kernel_us_per_layer=trace["kernel_ms"] * 1e3 / layers,
                   span_us_per_layer=trace.get("span_ms", float("nan")) * 1e3 / layers,
                   kernels_per_call=trace["kernels_per_call"], wall_ms=trace["wall_ms"],
                   by_name=trace["by_name"][:10])
        print(f"{name:50s} kernels {row['kernel_us_per_layer']:7.2f} us/layer, span "
              f"{row['span_us_per_layer']:7.2f}, {row['kernels_per_call']:.0f} kernels a call", flush=True)
    with open(out, "w") as f:
        json.dump(res, f, indent=1)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", help="JSON file to write (GPU run)")
    p.add_argument("--ctas", default="128", help="comma list of grid sizes, each at most the SM count "
                   "(default: %(default)s)")
    p.add_argument("--ring", default="14", help="comma list of weight ring depths in 8 KB tiles (default: %(default)s)")
    p.add_argument("--xdepth", type=int, default=4, help="activation tiles in flight (default: %(default)s)")
    p.add_argument("--splits", type=int, default=8, help="K splits of the out-projection and down "
                   "(default: %(default)s: 128 items each)")
    p.add_argument("--layers", type=int, default=18, help="layers of distinct weights (default: %(default)s)")
    p.add_argument("--norm", default="tile", help="comma list of none, tile, load, rounded: q's and g's GEMMs "
                   "on RMSNorm(h), its squares taken as `layer_kernel` says (default: %(default)s)")
    p.add_argument("--regs", default="0", help="comma list of the compute warpgroup's registers a thread, the "
                   "producer's cut to 40 (0: the compiler's default) (default: %(default)s)")
    p.add_argument("--loop", default="1", help="comma list of 0 / 1: an item's K steps unrolled (0) or a loop (1) "
                   "(default: %(default)s)")
    p.add_argument("--lhs", default="regs", help="comma list: q's and g's rounded residual tiles from registers "
                   "(regs) or shared memory (smem) (default: %(default)s)")
    p.add_argument("--ablate", action="append", default=[],
                   help="a variant with parts left out, for timing only (repeatable): a comma list of nobarrier, "
                        "nox, noconv, x16 (`layer_kernel`)")
    p.add_argument("--iters", type=int, default=30, help="traced calls per variant (default: %(default)s)")
    p.add_argument("--no-peers", action="store_true", help="only the persistent kernel")
    p.add_argument("--cpu-check", action="store_true",
                   help="Mosaic GPU's interpreter at small sizes on one CTA, against XLA, and exit")
    args = p.parse_args()
    if args.cpu_check:
        dm = Dims(d=128, nq=192, a=128, f=128, layers=2)
        h0, ws = inputs(dm)
        ws = [w.astype(jnp.float32) for w in ws]   # f32 on the interpreter: the check is to f32 rounding
        kws = [ws[0], ws[1], interleave(ws[2], dm.f), ws[3]]
        # lhs="smem" only: the interpreter of jax 0.10.2 takes no register operand for wgmma
        rel = {f"norm={norm} loop={loop}": _rel(
            layer_kernel(dm, 1, 4, 2, 2, "smem", norm, loop=loop, dtype=jnp.float32)(h0, kws),
            reference(h0, ws, dm, bool(norm))) for norm in ("", "tile") for loop in (False, True)}
        print(json.dumps({"rel_l2_vs_xla": rel}))
        sys.exit(0 if max(rel.values()) < 1e-5 else 1)
    if jax.default_backend() != "gpu" or not args.out:
        raise SystemExit("mgpu_layer_probe needs a GPU (Hopper) and --out (or --cpu-check)")
    dm = Dims(layers=args.layers)
    h0, ws = inputs(dm)
    kws = [ws[0], ws[1], interleave(ws[2], dm.f), ws[3]]
    want = {norm: np.asarray(jax.jit(lambda h, w, norm=norm: reference(h, w, dm, norm))(h0, ws))
            for norm in (False, True)}
    res = {"device": jax.devices()[0].device_kind, "jax": jax.__version__, "layers": dm.layers,
           "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()), "args": vars(args),
           "weight_mb_per_layer": sum(int(np.prod(w.shape[1:])) * 2 for w in ws) / 1e6, "rows": {}}
    fns = {}
    variants = [(int(c), int(r), m, "" if n == "none" else n, int(g), bool(int(o)), a)
                for c in args.ctas.split(",") for r in args.ring.split(",") for m in args.lhs.split(",")
                for n in args.norm.split(",") for g in args.regs.split(",") for o in args.loop.split(",")
                for a in [""] + args.ablate]
    for ctas, ring, lhs, norm, regs, loop, ablate in variants:
        name = f"persistent ctas={ctas} ring={ring} xdepth={args.xdepth} lhs={lhs}" + (f" norm={norm}" if norm else "")
        name += (f" regs={regs}" if regs else "") + (" loop" if loop else "")
        name += f" -{ablate}" if ablate else ""
        res["rows"][name] = {}
        try:
            fn = layer_kernel(dm, ctas, ring, args.xdepth, args.splits, lhs, norm, regs, loop, ablate=ablate)
            got, again = np.asarray(fn(h0, kws)), np.asarray(fn(h0, kws))
            if not ablate:   # an ablation's result is wrong by design
                res["rows"][name] = {"rel_l2_vs_xla": _rel(got, want[bool(norm)]),
                                     "rel_l2_second_call": _rel(again, got), "nan": int(np.isnan(got).sum())}
            fns[name] = functools.partial(fn, h0, kws)
        except Exception as e:   # a variant that fails to lower is a result, not the end of the run
            res["rows"][name] = {"error": f"{type(e).__name__}: {e}"[:3000]}
            traceback.print_exc()
        print(name, res["rows"][name], flush=True)
    if not args.no_peers:
        per_layer = [tuple(w[l] for w in ws) for l in range(dm.layers)]
        x0 = h0.astype(jnp.bfloat16)
        fns["engine kernels (norms and RoPE too)"] = functools.partial(engine_chain(dm.a, dm.d), x0, per_layer)
        fns["xla chain"] = functools.partial(jax.jit(lambda h, w: reference(h, w, dm)), h0, ws)
        fns["xla: each weight array read once"] = functools.partial(
            jax.jit(lambda ws: sum(jnp.sum(w, dtype=jnp.float32) for lw in ws for w in lw)), per_layer)
    timed(fns, res, dm.layers, args.iters, args.out)


if __name__ == "__main__":
    main()
