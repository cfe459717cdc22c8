"""A chain of the denoise step's gate/up + GeGLU kernel (Mosaic GPU), each reading the previous one's output: where a
kernel's time goes, and what programmatic dependent launch (PDL), a persistent kernel, and CTAs of half the work do.

Session 30 measured what a step kernel costs whatever its work: 3-4 us (`mgpu_gemm_probe.py --k-sweep`), paid ~9.7
times a layer. A kernel's weights do not depend on the kernel before it, only its activations do: with PDL
(`plgpu.griddepcontrol_launch_dependents` early in a kernel, `griddepcontrol_wait` in the next before it touches
what the first wrote) the next kernel could stream its weights while the first finishes.

One kernel: 64 rows of x (64, hidden) read as x[:, :k], @ a (k, 2 hidden) gate/up weight, GELU-tanh(gate) * up ->
(64, hidden); k 1024 and hidden 4096 are the expert's. Variants (`--modes`):
  base       x and w pipelined together, 64 units a CTA (two accumulators), no PDL: the engine's kernel until
             session 31
  pdl        base, both warpgroups wait for the previous kernel first, dependents launched at the start
  whole      x brought whole into shared memory by the compute warpgroup, only w pipelined, no PDL
  whole_pdl  whole, the producer streams w at once, the compute warpgroup waits for the previous kernel before it
             brings x; dependents launched at the start
  pair       32 units a CTA from ONE 64-column accumulator over gate and up interleaved in blocks of 32 (twice the
             CTAs, half the wgmma work each; split in registers): the engine's kernel since session 31
  pair_smem  pair, the accumulator split through shared memory
  --persistent  the whole chain as one kernel: grid barriers (a `pl.get_global` semaphore), the producer streaming
             one layer's weights after another (`pipeline_state`), x brought whole after each barrier
Each runs as a chain of `--layers` kernels on distinct weights in one jit; each kernel is checked against itself run
alone on what the chain gave it (bit-equal unless it read its input too early) and the first against XLA's product;
timed (host, interleaved) and traced (device span and busy time per kernel, and how long kernels overlapped).

What it showed (H200, jax 0.11.2, session 31; docs/BENCHMARKS.md, "PDL, a Mosaic GPU grid barrier, a persistent
chain, and gate/up on 128 CTAs"): PDL does nothing inside XLA's command buffers (no kernel overlapped); with command
buffers off it overlaps kernels by 2.8-5.3 us, but the chain is then host-bound. The persistent chain is bit-equal
and 9 % faster a layer (7.79 against 8.53 us). A CTA's 16 pipeline steps, not the bytes in flight, bound the kernel:
4 stages are as fast as 8, 32 CTAs are as slow per layer as 64; `pair` takes 6.8-6.9 us against 8.5.

GPU only (Hopper; PDL needs the Mosaic GPU runtime). `--cpu-check` runs base, whole and the pair modes in Mosaic GPU's
interpreter at a small shape (the persistent kernel does not run in the interpreter of jax 0.10.2).

    python scripts/mgpu_pdl_probe.py --out mgpu_pdl.json [--persistent] [--modes base,pair]
"""

from __future__ import annotations

import argparse
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

sys.path.insert(0, str(Path(__file__).parent))
from bench_kernels import interleaved_ms  # noqa: E402
from profile_engine import gpu_kernels, kernel_times, traced  # noqa: E402

ROWS, TK = mosaic_gemm.ROWS, mosaic_gemm.TK
MODES = ("base", "pdl", "whole", "whole_pdl", "pair", "pair_smem", "pair_mc2", "pair_mc4")


def _transforms(minor, dtype):
    size = jnp.dtype(dtype).itemsize
    swizzle = plgpu.find_swizzle(minor * size * 8)
    return plgpu.TilingTransform((8, swizzle // size)), plgpu.SwizzleTransform(swizzle)


def _pipeline(body, context, steps, stages, in_specs, state=None):
    """A warp-specialised pipeline: one compute warpgroup, a producer warpgroup streaming `in_specs` `stages` deep."""
    return plgpu.emit_pipeline_warp_specialized(
        body, grid=(steps,), memory_registers=40, wg_axis="wg", num_compute_wgs=1, max_concurrent_steps=stages,
        compute_context=context, in_specs=in_specs, pipeline_state=state)


def _launch(kernel, out_shape, ctas: int, name: str, cluster: int = 1):
    """A Mosaic GPU kernel of `ctas` CTAs (a compute and a producer warpgroup each), in clusters of `cluster` along
    axis "c" (then "n" counts clusters); Mosaic GPU's interpreter on CPU."""
    on_cpu = jax.default_backend() == "cpu"
    clusters = dict(cluster=(cluster,), cluster_names=("c",)) if cluster > 1 else {}
    return plgpu.kernel(kernel, out_type=jax.ShapeDtypeStruct(out_shape, jnp.bfloat16), grid=(ctas // cluster,),
                        grid_names=("n",), num_threads=2, thread_name="wg", kernel_name=name, **clusters,
                        compiler_params=plgpu.CompilerParams(lowering_semantics=plgpu.LoweringSemantics.Warpgroup),
                        **({"interpret": mosaic_gemm._interpret()} if on_cpu else {}))


def _bring_x(src, x_smem, x_bar, steps: int):
    """x (64, steps x TK) from GMEM into the (steps, 64, TK) tiles of x_smem, all copies on one barrier."""
    for i in range(steps):
        plgpu.copy_gmem_to_smem(src.at[:, pl.ds(i * TK, TK)], x_smem.at[i], x_bar)
    plgpu.barrier_wait(x_bar)


def _geglu_into(run, cols: int, out_smem, out_gmem):
    """Run the pipeline into a gate and an up accumulator (64 x cols each), then GELU-tanh(gate) * up to out_gmem."""
    acc = plgpu.ACC((ROWS, cols), jnp.float32)

    @functools.partial(pl.run_scoped, accs=(acc, acc))
    def accumulate(accs):
        run(accs)
        out_smem[...] = mosaic_gemm._gelu_product(accs[0][...], accs[1][...], out_smem.dtype)
        plgpu.commit_smem()
        plgpu.copy_smem_to_gmem(out_smem, out_gmem)
        plgpu.wait_smem_to_gmem(0)


def _pair_into(run, cols: int, out_smem, out_gmem, acc_smem=None):
    """Run the pipeline into one (64 x cols) accumulator of [gate | up] for cols / 2 units, then GELU-tanh(gate) * up
    to out_gmem; the halves split in registers, or through acc_smem (f32, 64 x cols) where one is given."""
    units = cols // 2

    @functools.partial(pl.run_scoped, acc=plgpu.ACC((ROWS, cols), jnp.float32))
    def accumulate(acc):
        run(acc)
        if acc_smem is None:
            y = acc[...]
            g, u = y[:, :units], y[:, units:]
        else:
            acc_smem[...] = acc[...]
            g, u = acc_smem[:, :units], acc_smem[:, units:]
        out_smem[...] = mosaic_gemm._gelu_product(g, u, out_smem.dtype)
        plgpu.commit_smem()
        plgpu.copy_smem_to_gmem(out_smem, out_gmem)
        plgpu.wait_smem_to_gmem(0)


@functools.lru_cache(maxsize=None)
def chain_kernel(k: int, hidden: int, width: int, mode: str, cols: int = 64, stages: int = 6):
    """x (64, width) [:, :k] @ w (k, 2 hidden) -> GeGLU (64, hidden), as `mode` says."""
    whole, pdl = mode.startswith("whole"), mode.endswith("pdl")
    dtype, steps = jnp.bfloat16, k // TK
    spec = functools.partial(plgpu.BlockSpec, memory_space=plgpu.SMEM)
    w_spec = spec((TK, cols), lambda kk: (kk, 0), transforms=_transforms(cols, dtype))
    x_spec = spec((ROWS, TK), lambda kk: (0, kk), transforms=_transforms(TK, dtype))

    def pipeline(body, context):
        return _pipeline(body, context, steps, stages, [w_spec, w_spec] if whole else [x_spec, w_spec, w_spec])

    def kernel(x_gmem, w_gmem, o_gmem):
        j = lax.axis_index("n")
        w_tiles = (w_gmem.at[:, pl.ds(j * cols, cols)], w_gmem.at[:, pl.ds(hidden + j * cols, cols)])
        srcs = w_tiles if whole else (x_gmem.at[:, pl.ds(0, k)], *w_tiles)
        scratch = dict(allocs=pipeline(None, None).get_allocations(*srcs),
                       out_smem=plgpu.SMEM((ROWS, cols), dtype, transforms=_transforms(cols, dtype)))
        if whole:
            scratch.update(x_smem=plgpu.SMEM((steps, ROWS, TK), dtype, transforms=_transforms(TK, dtype)),
                           x_bar=plgpu.Barrier(num_arrivals=steps))

        @functools.partial(pl.run_scoped, **scratch, collective_axes="wg")
        def scope(allocs, out_smem, x_smem=None, x_bar=None):
            if pdl:
                if not whole:   # both warpgroups read x: both wait for the kernel that wrote it
                    plgpu.griddepcontrol_wait()
                plgpu.griddepcontrol_launch_dependents()

            def context(run):
                if whole:
                    if pdl:
                        plgpu.griddepcontrol_wait()
                    _bring_x(x_gmem, x_smem, x_bar, steps)
                _geglu_into(run, cols, out_smem, o_gmem.at[:, pl.ds(j * cols, cols)])

            def step(idx, *refs):
                if whole:
                    (w_gate, w_up), accs, x = refs[:2], refs[2], x_smem.at[idx[0]]
                else:
                    x, w_gate, w_up, accs = refs
                plgpu.wgmma(accs[0], x, w_gate)
                plgpu.wgmma(accs[1], x, w_up)
                plgpu.wgmma_wait(0)
                return accs

            pipeline(step, context)(*srcs, allocations=allocs)

    return _launch(kernel, (ROWS, hidden), hidden // cols, f"chain_{mode}")


def interleave(w, hidden: int, units: int):
    """(k, 2 hidden) [gate | up] -> blocks of `units` gate columns, each followed by its `units` up columns."""
    k = w.shape[0]
    g, u = w[:, :hidden].reshape(k, -1, 1, units), w[:, hidden:].reshape(k, -1, 1, units)
    return jnp.concatenate([g, u], axis=2).reshape(k, 2 * hidden)


@functools.lru_cache(maxsize=None)
def pair_kernel(k: int, hidden: int, mode: str, units: int = 32, stages: int = 6):
    """GeGLU for `units` hidden units a CTA (hidden / units CTAs: 128 for the expert) from ONE (64 x 2 units)
    accumulator over the interleaved weight (`interleave`): half the wgmma work of a 64-unit CTA and twice the CTAs.
    The accumulator's halves are split in registers (`pair`) or through shared memory (`pair_smem`); `pair_mc2` /
    `pair_mc4`: clusters of 2 / 4 CTAs that share each x tile by one multicast copy (x is read from L2 once a cluster
    instead of once a CTA)."""
    dtype, steps, cols = jnp.bfloat16, k // TK, 2 * units
    spec = functools.partial(plgpu.BlockSpec, memory_space=plgpu.SMEM)
    w_spec = spec((TK, cols), lambda kk: (kk, 0), transforms=_transforms(cols, dtype))
    cluster = int(mode[len("pair_mc"):]) if mode.startswith("pair_mc") else 1
    x_spec = spec((ROWS, TK), lambda kk: (0, kk), transforms=_transforms(TK, dtype),
                  **({"collective_axes": ("c",)} if cluster > 1 else {}))

    def pipeline(body, context):
        return _pipeline(body, context, steps, stages, [x_spec, w_spec])

    def kernel(x_gmem, w_gmem, o_gmem):
        j = lax.axis_index("n") * cluster + (lax.axis_index("c") if cluster > 1 else 0)
        srcs = (x_gmem.at[:, pl.ds(0, k)], w_gmem.at[:, pl.ds(j * cols, cols)])
        scratch = dict(allocs=pipeline(None, None).get_allocations(*srcs),
                       out_smem=plgpu.SMEM((ROWS, units), dtype, transforms=_transforms(units, dtype)))
        if mode == "pair_smem":
            scratch["acc_smem"] = plgpu.SMEM((ROWS, cols), jnp.float32)

        @functools.partial(pl.run_scoped, **scratch, collective_axes="wg")
        def scope(allocs, out_smem, acc_smem=None):
            def context(run):
                _pair_into(run, cols, out_smem, o_gmem.at[:, pl.ds(j * units, units)], acc_smem)

            def step(idx, x, w, acc):
                plgpu.wgmma(acc, x, w)
                plgpu.wgmma_wait(0)
                return acc

            pipeline(step, context)(*srcs, allocations=allocs)

    return _launch(kernel, (ROWS, hidden), hidden // units, f"chain_{mode}", cluster)


@functools.lru_cache(maxsize=None)
def persistent_kernel(layers: int, k: int, hidden: int, cols: int = 64, stages: int = 4, pair: bool = False):
    """The whole chain as one kernel: a CTA per `cols` hidden units runs every layer, the layers separated by a grid
    barrier (a GPU-scope semaphore from `pl.get_global`). The producer warpgroup streams the weights of one layer
    after another as pipeline slots free up (`pipeline_state`: a pipeline of pipelines), so the next layer's first
    tiles are in flight while the compute warpgroup finishes this layer and waits at the barrier; after it, the
    compute warpgroup brings x (the previous layer's output, ping-ponged between o's two halves) whole. pair: each
    CTA takes one block pair of the interleaved weight (`pair_kernel`'s layout), cols / 2 units, on twice the CTAs."""
    dtype, steps = jnp.bfloat16, k // TK
    units = cols // 2 if pair else cols
    ctas = hidden // units
    spec = functools.partial(plgpu.BlockSpec, memory_space=plgpu.SMEM)
    w_spec = spec((TK, cols), lambda kk: (kk, 0), transforms=_transforms(cols, dtype))

    def pipeline(body, context, state):
        return _pipeline(body, context, steps, stages, [w_spec] if pair else [w_spec, w_spec], state)

    def kernel(x_gmem, w_gmem, o_gmem):   # w (layers, k, 2 hidden); o (2, 64, hidden)
        j = lax.axis_index("n")
        sem = pl.get_global(plgpu.SemaphoreType.REGULAR)

        def tiles(p):
            if pair:
                return (w_gmem.at[p, :, pl.ds(j * cols, cols)],)
            return (w_gmem.at[p, :, pl.ds(j * cols, cols)], w_gmem.at[p, :, pl.ds(hidden + j * cols, cols)])

        @functools.partial(pl.run_scoped, allocs=pipeline(None, None, None).get_allocations(*tiles(0)),
                           out_smem=plgpu.SMEM((ROWS, units), dtype, transforms=_transforms(units, dtype)),
                           x_smem=plgpu.SMEM((steps, ROWS, TK), dtype, transforms=_transforms(TK, dtype)),
                           x_bar=plgpu.Barrier(num_arrivals=steps), collective_axes="wg")
        def scope(allocs, out_smem, x_smem, x_bar):
            @pl.loop(0, layers)
            def layer(p):
                state = jnp.where(p == 0, plgpu.PipelinePipeline.START, plgpu.PipelinePipeline.STEADY)
                state = jnp.where(p == layers - 1, plgpu.PipelinePipeline.STOP, state)

                def context(run):
                    @pl.when(p == 0)
                    def _():
                        _bring_x(x_gmem, x_smem, x_bar, steps)

                    @pl.when(p > 0)
                    def _():
                        plgpu.semaphore_wait(sem, p * ctas, decrement=False, memory_scope="gpu")
                        _bring_x(o_gmem.at[lax.rem(p + 1, 2)], x_smem, x_bar, steps)
                    out = o_gmem.at[lax.rem(p, 2), :, pl.ds(j * units, units)]
                    (_pair_into if pair else _geglu_into)(run, cols, out_smem, out)
                    plgpu.semaphore_signal(sem, 1, memory_scope="gpu")

                def step(idx, *ws_accs):
                    x, (ws, accs) = x_smem.at[idx[0]], (ws_accs[:-1], ws_accs[-1])
                    for w, acc in zip(ws, accs if isinstance(accs, tuple) else (accs,)):
                        plgpu.wgmma(acc, x, w)
                    plgpu.wgmma_wait(0)
                    return accs

                pipeline(step, context, state)(*tiles(p), allocations=allocs)

            @pl.when((j == 0) & (lax.axis_index("wg") == 0))
            def _():   # every CTA signalled once a layer: take the count back, so the next call starts at zero
                plgpu.semaphore_wait(sem, layers * ctas, decrement=True, memory_scope="gpu")

    call = _launch(kernel, (2, ROWS, hidden), ctas, "chain_persistent_pair" if pair else "chain_persistent")
    return jax.jit(lambda x, w: call(x, w)[(layers - 1) % 2])   # w: the layers' weights stacked


def reference_chain(x, ws, k, hidden):
    for w in ws:
        y = jnp.dot(x[:, :k], w, preferred_element_type=jnp.float32)
        x = mosaic_gemm._gelu_product(y[:, :hidden], y[:, hidden:], x.dtype)
    return x


def chain(mode, k, hidden, width, cols, stages, keep=False):
    """The chain as one jit; keep: return every kernel's output (for the check). The pair modes take the weights
    interleaved (`prepare`)."""
    call = (pair_kernel(k, hidden, mode, cols // 2, stages) if mode.startswith("pair")
            else chain_kernel(k, hidden, width, mode, cols, stages))

    def run(x, ws):
        outs = []
        for w in ws:
            x = call(x, w)
            outs.append(x)
        return outs if keep else x
    return jax.jit(run)


def prepare(mode, ws, hidden, cols):
    """The weights as `mode`'s kernel reads them."""
    return [interleave(w, hidden, cols // 2) for w in ws] if mode.startswith("pair") else ws


def inputs(k, hidden, layers, seed=0):
    """x and `layers` weights at unit gain. GeGLU is quadratic, so a chain's activations shrink towards zero: the
    check runs 6 kernels, where they have not yet."""
    kx, kw = jax.random.split(jax.random.key(seed))
    x = jax.random.normal(kx, (ROWS, hidden), jnp.float32).astype(jnp.bfloat16)
    ws = [(jax.random.normal(w, (k, 2 * hidden), jnp.float32) * k**-0.5).astype(jnp.bfloat16)
          for w in jax.random.split(kw, layers)]
    return x, ws


def _rel(got, want):
    return float(np.linalg.norm(got - want) / max(np.linalg.norm(want), 1e-30))


def check(mode, k, hidden, layers, cols, stages):
    """Each kernel of the chain against the same kernel run alone on what the chain gave it (bit-equal unless a
    kernel read its input before the previous one had written it), and the first against XLA's f32 product."""
    x, ws = inputs(k, hidden, layers)
    kws = prepare(mode, ws, hidden, cols)
    outs = [np.asarray(o, np.float32) for o in chain(mode, k, hidden, hidden, cols, stages, keep=True)(x, kws)]
    one = chain(mode, k, hidden, hidden, cols, stages)
    ins = [x] + [jnp.asarray(o, jnp.bfloat16) for o in outs[:-1]]
    alone = [np.asarray(one(i, [w]), np.float32) for i, w in zip(ins, kws)]
    want = np.asarray(reference_chain(x, ws[:1], k, hidden), np.float32)
    return {"first_vs_xla": _rel(outs[0], want),
            "max_abs_vs_alone": max(float(np.abs(a - o).max()) for a, o in zip(alone, outs)),
            "out_abs_max": [float(np.abs(o).max()) for o in (outs[0], outs[-1])],
            "nan": int(sum(np.isnan(o).sum() for o in outs))}


def overlap(fn, calls: int = 3) -> dict:
    """From a trace: how long each kernel ran while the one before it still ran (PDL's early launch shows here)."""
    events, threads, gpu, _ = traced(fn, calls)
    kernels = sorted(gpu_kernels(events, threads, gpu))
    over = [max(0.0, (ts0 + d0) - ts1) for (ts0, d0, _), (ts1, _, _) in zip(kernels, kernels[1:])]
    return {"overlap_us_per_kernel": float(np.sum(over)) / max(len(kernels), 1),
            "overlapping_kernels": int(sum(o > 0 for o in over))}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", help="JSON file to write (GPU run)")
    p.add_argument("--layers", type=int, default=18, help="kernels in a chain (default: %(default)s)")
    p.add_argument("--iters", type=int, default=50, help="timed calls per variant (default: %(default)s)")
    p.add_argument("--modes", default=",".join(MODES), help="comma list of variants (default: %(default)s)")
    p.add_argument("--stages", type=int, default=6, help="weight pipeline depth of base and pdl (default: %(default)s)")
    p.add_argument("--whole-stages", type=int, default=4,
                   help="weight pipeline depth of whole and whole_pdl, whose x takes 128 KB of shared memory "
                        "(default: %(default)s)")
    p.add_argument("--k", type=int, default=1024, help="contraction rows (default: %(default)s, the expert's width)")
    p.add_argument("--hidden", type=int, default=4096,
                   help="GeGLU units, hidden / cols CTAs (default: %(default)s, the expert's MLP)")
    p.add_argument("--cols", type=int, default=64, help="hidden units a CTA (default: %(default)s)")
    p.add_argument("--persistent", action="store_true",
                   help="also the chain as one persistent kernel with grid barriers (`persistent_kernel`)")
    p.add_argument("--cpu-check", action="store_true",
                   help="check base and whole in the CPU interpreter at k=128, hidden=128, 3 layers, and exit")
    args = p.parse_args()
    modes = args.modes.split(",")
    if args.cpu_check:
        rows = {mode: check(mode, 128, 128, 3, 64, 2) for mode in ("base", "whole", "pair", "pair_smem")}
        print(json.dumps(rows))
        sys.exit(0 if all(r["first_vs_xla"] < 1e-2 and r["max_abs_vs_alone"] == 0 for r in rows.values()) else 1)
    if jax.default_backend() != "gpu" or not args.out:
        raise SystemExit("mgpu_pdl_probe needs a GPU (Hopper) and --out (or --cpu-check)")
    k, hidden = args.k, args.hidden
    res = {"device": jax.devices()[0].device_kind, "jax": jax.__version__, "layers": args.layers,
           "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()), "shape": [ROWS, k, 2 * hidden],
           "stages": args.stages, "cols": args.cols, "rows": {}}
    x, ws = inputs(k, hidden, args.layers)
    xla = jax.jit(lambda x, ws: reference_chain(x, ws, k, hidden))
    fns = {"xla": functools.partial(xla, x, ws)}
    for mode in modes:
        stages = args.whole_stages if mode.startswith("whole") else args.stages
        try:
            res["rows"][mode] = check(mode, k, hidden, 6, args.cols, stages)
            print(mode, res["rows"][mode], flush=True)
            fns[mode] = functools.partial(chain(mode, k, hidden, hidden, args.cols, stages), x,
                                          prepare(mode, ws, hidden, args.cols))
        except Exception as e:   # a variant that fails to lower is a result, not the end of the run
            res["rows"][mode] = {"error": f"{type(e).__name__}: {e}"[:2000]}
            traceback.print_exc()
    if args.persistent:
        try:
            cx, cws = inputs(k, hidden, 6)
            base = np.asarray(chain("base", k, hidden, hidden, args.cols, args.stages)(cx, cws), np.float32)
            whole_chain = persistent_kernel(6, k, hidden, args.cols, args.whole_stages)
            got = np.asarray(whole_chain(cx, jnp.stack(cws)), np.float32)
            again = np.asarray(whole_chain(cx, jnp.stack(cws)), np.float32)
            res["rows"]["persistent"] = {"max_abs_vs_base": float(np.abs(got - base).max()),
                                         "max_abs_second_call": float(np.abs(again - base).max()),
                                         "out_abs_max": float(np.abs(base).max())}
            print("persistent", res["rows"]["persistent"], flush=True)
            fns["persistent"] = functools.partial(
                persistent_kernel(args.layers, k, hidden, args.cols, args.whole_stages), x, jnp.stack(ws))
            pair_chain = persistent_kernel(6, k, hidden, args.cols, args.whole_stages, True)
            got = np.asarray(pair_chain(cx, jnp.stack(prepare("pair", cws, hidden, args.cols))), np.float32)
            res["rows"]["persistent_pair"] = {"max_abs_vs_base": float(np.abs(got - base).max())}
            print("persistent_pair", res["rows"]["persistent_pair"], flush=True)
            fns["persistent_pair"] = functools.partial(
                persistent_kernel(args.layers, k, hidden, args.cols, args.whole_stages, True), x,
                jnp.stack(prepare("pair", ws, hidden, args.cols)))
        except Exception as e:
            res["rows"]["persistent"] = {"error": f"{type(e).__name__}: {e}"[:2000]}
            traceback.print_exc()
    ms = interleaved_ms(fns, args.iters)
    for name, fn in fns.items():
        row = res["rows"].setdefault(name, {})
        trace = kernel_times(fn, calls=5)
        row.update(host_ms=ms[name], host_us_per_kernel=ms[name] * 1e3 / args.layers,
                   span_us_per_kernel=trace["span_ms"] * 1e3 / args.layers, kernels_per_call=trace["kernels_per_call"],
                   busy_us_per_kernel=trace["kernel_ms"] * 1e3 / args.layers, **overlap(fn))
        print(name, {key: round(v, 3) if isinstance(v, float) else v for key, v in row.items()}, flush=True)
    with open(args.out, "w") as f:
        json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
