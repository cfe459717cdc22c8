"""Compile the engine's programs for an H200 (or an H100) on a machine with no GPU: XLA's deviceless ahead-of-time
compile.

What it shows without a GPU: whether every kernel of the engine compiles for sm_90a (Pallas Triton and Mosaic GPU
through ptxas; their registers and spills a thread), the optimized HLO's kernel counts per program and per denoise step
(`profile_engine.count_ops`: fusions, library calls and copies, each one GPU kernel), and the GEMMs that are FP8. What
it cannot show: time. The GEMMs are not autotuned (no device to time them on), so where XLA's autotuner would pick
another tiling or split-K on a GPU the counts may differ by those kernels: compare them with a GPU run's
(`profile_engine.py`, `graph_probe.py`) before trusting a difference.

It needs the CUDA plugin of the installed jaxlib (`pip install "jax[cuda12]==$(python -c 'import jax;
print(jax.__version__)')"`; the GPU image's compiler, jax 0.11.2 with CUDA 13, is `pip install "jax[cuda13]==0.11.2"` in
a Python 3.12 environment), not a GPU or a driver (jax 0.12's needs the driver's library for cuDNN's attention, and
says so): the plugin's compiler is used, with the device described by
`TARGET` (an H200's figures; `--target h100` an H100 SXM's, whose lower memory bandwidth moves XLA's fusion cost
model: docs/BENCHMARKS.md, session 82), and jax's own device queries in the engine (`jax.devices()`,
`jax.default_backend()`) answer as that GPU would. The weights are shapes only (`pi0.param_shapes`; FP8 scales from
unit amaxes), so a full-size preset compiles in a few GB of host memory. Without the plugin, `abstract_engine` lowers
the programs for CUDA and stops there: `tests/test_hopper_lowering.py` lowers the engine's calls so, with every
kernel at its shapes.

    python3 scripts/deviceless.py --preset pi0_base --batch 1 --steps 10 --out deviceless.json
    python3 scripts/deviceless.py --target h100 --preset pi0_base --batch 1 --steps 10
    python3 scripts/deviceless.py --preset pi0_base --quant prefix-all --fp8-mlp-kernel on --batch 8
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np
from jax._src.cudnn import fused_attention_stablehlo as cudnn
from jax.experimental import topologies

sys.path.insert(0, str(Path(__file__).parent))
from profile_engine import count_ops, loop_invariant_kernels  # noqa: E402

from pi0_jax import benchmark, pi0  # noqa: E402
from pi0_jax.config import IMAGE_KEYS, get_config  # noqa: E402
from pi0_jax.engine import Engine, layers, programs, runtime  # noqa: E402
from pi0_jax.engine import weights as weights_lib  # noqa: E402
from pi0_jax.ops import expert_kernels, fp8_geglu  # noqa: E402
from pi0_jax.ops.formats import E4M3, QArray  # noqa: E402
from pi0_jax.quant import schemes  # noqa: E402

# an H200 SXM as XLA's GPU compiler reads a device (stream_executor.GpuTargetConfigProto, text format); the figures
# are the device's own (132 SMs, 227 KiB of shared memory a block, 4.8 TB/s, 50 MiB of L2, compute capability 9.0)
TARGET = """
gpu_device_info {
  threads_per_block_limit: 1024 threads_per_warp: 32 shared_memory_per_block: 49152 shared_memory_per_core: 233472
  threads_per_core_limit: 2048 core_count: 132 fpus_per_core: 128 block_dim_limit_x: 2147483647
  block_dim_limit_y: 65535 block_dim_limit_z: 65535 memory_bandwidth: 4800000000000 l2_cache_size: 52428800
  clock_rate_ghz: 1.98 device_memory_size: 151397597184 shared_memory_per_block_optin: 232448
  cuda_compute_capability { major: 9 minor: 0 } registers_per_core_limit: 65536 registers_per_block_limit: 65536
  driver_version: "13.0.0" runtime_version: "12.9.0" compile_time_toolkit_version: "12.9.0" dnn_version: "9.8.0"
}
platform_name: "CUDA"
dnn_version_info { major: 9 minor: 8 }
device_description_str: "NVIDIA H200"
"""


# an H100 SXM (80 GB HBM3): the H200's figures but its memory and 3.35 TB/s
H100 = (TARGET.replace("memory_bandwidth: 4800000000000", "memory_bandwidth: 3350000000000")
        .replace("device_memory_size: 151397597184", "device_memory_size: 85520809984")
        .replace('device_description_str: "NVIDIA H200"', 'device_description_str: "NVIDIA H100 80GB HBM3"'))
assert "3350000000000" in H100 and "85520809984" in H100 and "H100" in H100, "TARGET's figures changed: mend H100"
TARGETS = {"h200": (TARGET, "NVIDIA H200"), "h100": (H100, "NVIDIA H100 80GB HBM3")}


class TargetDevice:
    """What the engine asks of `jax.devices()[0]` (`ops.mosaic_gemm.hopper`, `ops.fp8_geglu`), as the H200 answers."""

    platform = "gpu"
    device_kind = "NVIDIA H200"
    compute_capability = "9.0"
    core_count = 132
    cudnn_version = 90800   # TARGET's dnn_version


def _module(name: str):
    """The module, or None where this jax has none of that name."""
    try:
        return importlib.import_module(name)
    except ImportError:
        return None


@contextlib.contextmanager
def as_target():
    """jax's device queries answer as the target GPU while programs are traced and lowered: the engine's, and
    those of jax's cuDNN attention (it asks the attached GPU's compute capability, 9.0 allowing a head dim of 256,
    and the installed cuDNN's version: `TARGET`'s, so that lowering alone needs no CUDA plugin)."""
    cc = tuple(map(int, TargetDevice.compute_capability.split(".")))
    names = ("check_compute_capability", "is_cuda_compute_capability_equal", "check_cudnn_version")
    saved = (jax.devices, jax.default_backend, *(getattr(cudnn, n) for n in names))
    jax.devices, jax.default_backend = (lambda *a, **k: [TargetDevice()]), (lambda: "gpu")
    cudnn.check_compute_capability = lambda c: cc >= tuple(map(int, c.split(".")))
    cudnn.is_cuda_compute_capability_equal = lambda c: cc == tuple(map(int, c.split(".")))
    cudnn.check_cudnn_version = lambda: TargetDevice.cudnn_version
    # Pallas Triton's lowering asks the default device (here the CPU) for its GPU: through jax._src.gpu_info in jax
    # 0.12, jax._src.pallas.triton.gpu_info in 0.11 (the GPU image's), neither in 0.10
    triton_gpu = next((m for m in map(_module, ("jax._src.gpu_info", "jax._src.pallas.triton.gpu_info")) if m), None)
    if triton_gpu:
        saved_info = triton_gpu.get_gpu_info
        triton_gpu.get_gpu_info = lambda: triton_gpu.GpuInfo(gpu_version=None, compute_capability=cc[0] * 10 + cc[1],
                                                              arch_name=TargetDevice.compute_capability)
    try:
        yield
    finally:
        jax.devices, jax.default_backend = saved[:2]
        for n, f in zip(names, saved[2:]):
            setattr(cudnn, n, f)
        if triton_gpu:
            triton_gpu.get_gpu_info = saved_info


def use_target(name: str) -> None:
    """Compile for `TARGETS[name]` from here on: XLA's device description and what `jax.devices()` answers."""
    global TARGET
    TARGET, TargetDevice.device_kind = TARGETS[name]


def target_devices(n: int = 1) -> list:
    """n described GPUs of one host (the CUDA plugin's topology), `TARGET`'s."""
    return topologies.get_topology_desc(platform="cuda", topology_name="h200", target_config=TARGET,
                                        topology=f"1x1x{n}").devices


def target_sharding():
    return jax.sharding.make_single_device_sharding(target_devices()[0])


COLLECTIVES = ("all-gather", "all-reduce", "reduce-scatter", "collective-permute", "all-to-all")


def fp8_mlp_sharded(rows: int = 816, devices: int = 2) -> dict:
    """The FP8 MLP kernel (`ops.fp8_geglu.geglu`, π0's prefix shapes) compiled on `devices` H200s with its rows
    split over them, as the simulator's batch mesh runs the engine: the collectives in the program (none: each
    device runs the kernel on its own rows, `custom_partitioning`) and the rows each device's kernel takes."""
    spec = jax.ShapeDtypeStruct
    mesh = jax.sharding.Mesh(np.array(target_devices(devices)), ("batch",))
    split, full = (jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(*a)) for a in (("batch", None), ()))
    k, n2 = 2048, 32768

    def mlp(xq, q, scale, act, down_scale):
        return fp8_geglu.geglu(xq, QArray(q, scale, act, (-1,), True), down_scale)

    with as_target():
        hlo = jax.jit(mlp).trace(
            spec((devices * rows, k), E4M3, sharding=split), spec((n2, k), E4M3, sharding=full),
            spec((n2, 1), np.float32, sharding=full), *(spec((), np.float32, sharding=full),) * 2).lower().compile()
        text = hlo.as_text()
    return {"devices": devices, "collectives": [c for c in COLLECTIVES if f" {c}(" in text or f"{c}-start(" in text],
            "kernel_rows": sorted(set(int(r) for r in re.findall(r"f8e4m3fn\[(\d+),16384\]", text)))}


def abstract_engine(config, quant: str | None, sharding=None, dump: Path | None = None, **engine_kw) -> Engine:
    """An Engine whose weights are shapes (`store.compile` replaced): its programs compiled for the target's device
    (`sharding`: `target_sharding`, which takes the CUDA plugin; XLA's dump, its PTX included, into `dump`), or
    without one lowered for CUDA only (each program a `jax.stages.Lowered`: no plugin needed, the tests)."""
    params = pi0.param_shapes(config)
    if quant:   # unit amaxes, shaped as `schemes.calibrate` gives them: a layer's each where the weight is stacked
        depth = {"img": config.siglip.depth, "vlm": config.paligemma.depth, "expert": config.action_expert.depth}
        amax = {key: np.ones(() if key == "img/head" else depth[key.split("/")[0]], np.float32)
                for *_, key in schemes._leaves(quant)}
        params = jax.eval_shape(lambda p: schemes.quantize_params(p, quant, amax), params)
    build = runtime.engine_weights
    runtime.engine_weights = lambda cfg, p, **kw: jax.eval_shape(lambda q: build(cfg, q, **kw), p)
    try:
        engine = Engine(config, params, cache_dir=False, **engine_kw)
    finally:
        runtime.engine_weights = build
    engine.schedule = lambda n: jax.eval_shape(lambda p: weights_lib.precompute_schedule(config, p, n),
                                               engine._schedule_params)
    if sharding is None:
        engine.store.compile = lambda name, parts, fn, args, options=None: (
            jax.jit(fn).trace(*args).lower(lowering_platforms=("cuda",)))
    else:
        dumped = {} if dump is None else {"xla_dump_to": str(dump)}
        engine.store.compile = lambda name, parts, fn, args, options=None: (
            jax.jit(fn, in_shardings=sharding, out_shardings=sharding).lower(*args).compile(
                {**(options or {}), **dumped}))
    return engine


def ptxas_figures(kernel: str, text: str) -> dict:
    """A kernel's registers and spill bytes a thread from ptxas's -v output."""
    regs = re.search(r"Used (\d+) registers", text)
    spill = re.search(r"(\d+) bytes spill stores, (\d+) bytes spill loads", text)
    return {"kernel": kernel, "registers": int(regs.group(1)) if regs else None,
            "spill_store_bytes": int(spill.group(1)) if spill else None,
            "spill_load_bytes": int(spill.group(2)) if spill else None}


def ptxas_info(root: Path) -> list[dict]:
    """Mosaic GPU's kernels as ptxas built them (MOSAIC_GPU_DUMP_PTXAS): registers, spills, barriers."""
    rows = []
    for path in sorted(root.glob("*.ptxas")):
        text = path.read_text()
        rows.append({**ptxas_figures(path.stem, text),
                     "serialised_wgmma": "serialized" in text,   # ptxas's "wgmma.mma_async ... serialized"
                     "notes": re.findall(r"\((C\d+)\) ([^\n]+)", text)})
    return rows


def ptxas_binary() -> str | None:
    """The CUDA toolkit's ptxas that jax's CUDA wheels bring (`nvidia-cuda-nvcc`), else one on PATH."""
    try:
        import nvidia.cuda_nvcc
        found = Path(next(iter(nvidia.cuda_nvcc.__path__))) / "bin" / "ptxas"
        if found.exists():
            return str(found)
    except (ImportError, StopIteration):
        pass
    return shutil.which("ptxas")


def pallas_names(hlo: str) -> set:
    """The Pallas kernels an optimized HLO text calls (jax names each pallas_call's op after its kernel)."""
    return set(re.findall(r'op_name="[^"]*/(\w+)/pallas_call"', hlo))


def triton_ptxas(root: Path, names: set) -> list[dict]:
    """The Pallas Triton kernels of XLA's PTX dump (`xla_dump_to`) as ptxas builds them for sm_90a: registers and
    spills a thread (past 255 registers a kernel spills to local memory: docs/BENCHMARKS.md, session 60). One row
    per kernel and build (a program's copy of a kernel may differ)."""
    ptxas = ptxas_binary()
    rows = {}
    for path in sorted(root.glob("*.ptx")) if ptxas else ():
        entries = re.findall(r"\.entry (\w+)\(", path.read_text())
        if len(entries) != 1 or entries[0] not in names:
            continue
        with tempfile.NamedTemporaryFile(suffix=".cubin") as cubin:
            text = subprocess.run([ptxas, "-arch=sm_90a", "-v", str(path), "-o", cubin.name], capture_output=True,
                                  text=True).stderr
        row = ptxas_figures(entries[0], text)
        rows[tuple(row.values())] = row
    return sorted(rows.values(), key=lambda r: r["kernel"])


def kinds(hlo: str) -> dict:
    """Library and kernel calls by kind in an optimized HLO text."""
    targets = re.findall(r'custom_call_target="([^"]+)"', hlo)
    return {"fp8_gemms": sum("f8" in t for t in targets), "cublas_gemms": sum("cublas" in t for t in targets),
            "mosaic_gpu": sum("mosaic_gpu" in t for t in targets), "triton": sum("triton" in t for t in targets),
            "triton_gemm_fusions": len(re.findall(r'"kind":"__triton(?:_nested)?_gemm', hlo))}


def kernels(counts: dict) -> int:
    """The kernels of a computation's `count_ops` row: all but its while loops (a loop's body is counted apart)."""
    return sum(n for kind, n in counts.items() if kind != "while")


def sequence(hlo: str, computation: str) -> list[list[str]]:
    """A computation's kernels in order (a loop body: one denoise step), each as [instruction name without its
    number, what runs it (a custom call's target, else the fusion's kind), the op it came from (jax's name, its
    last two parts)]: where each of a step's kernels comes from."""
    lines = hlo.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"%{computation} "))
    rows = []
    for line in lines[start + 1:]:
        if line.startswith("}"):
            break
        m = re.search(r"^\s*(?:ROOT )?%([\w.\-]+) = .*?\b(fusion|custom-call|copy)(?:-start)?\(", line)
        if m:
            how = (re.search(r'custom_call_target="([^"]+)"', line) or re.search(r'"kind":"(\w+)"', line)
                   or re.search(r"kind=(k\w+)", line))
            op = re.search(r'op_name="([^"]+)"', line)
            rows.append([re.sub(r"[._]\d+", "", m.group(1)), how.group(1) if how else m.group(2),
                         "/".join(op.group(1).split("/")[-2:]) if op else ""])
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--target", choices=sorted(TARGETS), default="h200",
                   help="the GPU compiled for: its figures go to XLA's cost model (default: %(default)s)")
    p.add_argument("--preset", default="pi0_base", help="model preset (default: %(default)s)")
    p.add_argument("--batch", type=int, default=1, help="batch size (default: %(default)s)")
    p.add_argument("--steps", type=int, default=10, help="denoise steps (default: %(default)s)")
    p.add_argument("--cameras", type=int, default=3, help="active cameras (default: %(default)s)")
    p.add_argument("--prompt", type=int, default=48,
                   help="prompt tokens, compiled at their bucket (default: %(default)s)")
    p.add_argument("--quant", default=None, help="FP8 scheme (quant.schemes), e.g. prefix-all, every-gemm; "
                                                 "scales from unit amaxes (default: bf16)")
    p.add_argument("--kernels", default="auto", help="the engine's kernels: auto, xla, pallas (default: %(default)s)")
    p.add_argument("--attention", default="auto", help="the engine's attention (default: %(default)s)")
    p.add_argument("--fp8-mlp-kernel", choices=("auto", "on", "off"), default="auto",
                   help="FP8 MLPs on `ops.fp8_geglu`'s kernels (engine.layers.FP8_GEGLU: the prefix's, the expert's and "
                        "SigLIP's fc1 from their row thresholds): auto = as the engine "
                        "on the target (an H200: on), on, off (default: %(default)s)")
    p.add_argument("--fp8-row-pad", choices=("on", "off"), default="on",
                   help="the FP8 expert's step rows padded to a multiple of 16 (engine.programs.FP8_ROW_PAD; "
                        "default: %(default)s)")
    p.add_argument("--pack-attention", choices=("on", "off"), default="on",
                   help="the XLA expert's folded attention input as one buffer (engine.layers.PACK_ATTENTION_INPUT; "
                        "default: %(default)s)")
    p.add_argument("--merge-ends", choices=("on", "off"), default="on",
                   help="the XLA expert's attention merge cutting pad rows and quantising for an FP8 out-projection "
                        "(engine.layers.ATTENTION_ENDS_IN_MERGE; default: %(default)s)")
    p.add_argument("--fold-from", type=int, default=None,
                   help="the batch from which the XLA expert's attention folds a kv head's query heads into its rows "
                        "(ops.expert_kernels.FOLD_FROM; default: the engine's)")
    p.add_argument("--out", type=Path, default=None, help="JSON of counts per program (default: print only)")
    p.add_argument("--hlo", type=Path, default=None, help="a folder to write each program's optimized HLO to")
    p.add_argument("--fp8-mlp-sharded", action="store_true",
                   help="also compile the FP8 MLP kernel on two H200s with its rows split (`fp8_mlp_sharded`)")
    p.add_argument("--sequence", action="store_true",
                   help="print each loop body's kernels in order (the JSON has them either way)")
    args = p.parse_args(argv)

    os.environ.setdefault("JAX_PLATFORMS", "cpu")   # the CUDA plugin is loaded for its compiler, not for a device
    os.environ.setdefault("JAX_SKIP_CUDA_CONSTRAINTS_CHECK", "1")   # its check needs a driver
    use_target(args.target)
    config = get_config(args.preset)
    cameras = IMAGE_KEYS[:args.cameras]
    bucket = runtime.prompt_bucket(args.prompt, config.max_token_len)
    layers.FP8_GEGLU = {"auto": "auto", "on": True, "off": False}[args.fp8_mlp_kernel]
    programs.FP8_ROW_PAD = args.fp8_row_pad == "on"
    layers.PACK_ATTENTION_INPUT = args.pack_attention == "on"
    layers.ATTENTION_ENDS_IN_MERGE = args.merge_ends == "on"
    if args.fold_from is not None:
        expert_kernels.FOLD_FROM = args.fold_from
    sharding = target_sharding()
    results = {"target": TargetDevice.device_kind, "jax": jax.__version__, "commit": benchmark._git_commit(),
               "source": benchmark.source_digest(), "args": {k: str(v) for k, v in vars(args).items()},
               "programs": []}
    with tempfile.TemporaryDirectory() as dump, as_target():
        os.environ.update(MOSAIC_GPU_DUMP_PTXAS="1", MOSAIC_GPU_DUMP_TO=dump)
        engine = abstract_engine(config, args.quant, sharding, dump=Path(dump) / "xla", kernels=args.kernels,
                                 attention=args.attention)
        names = set()
        for stage in engine.call_stages(args.batch, args.steps):
            start = time.perf_counter()
            try:
                program = engine.executable(stage, args.batch, args.steps, cameras, bucket)
            except jax.errors.JaxRuntimeError as e:
                if "deviceless cuDNN" not in str(e):
                    raise
                # jax 0.12's XLA builds cuDNN's graphs through the driver's library even when deviceless
                raise SystemExit(f"{stage}: this jaxlib ({jax.__version__}) compiles cuDNN's fused attention only "
                                 "with a CUDA driver (libcuda.so.1); without one, compile the stages' attention on "
                                 "other kernels (e.g. --attention vision=pallas,prefix=xla,denoise=auto), or use "
                                 "jax 0.11.2's plugin") from e
            hlo = program.as_text()
            if args.hlo:
                args.hlo.mkdir(parents=True, exist_ok=True)
                (args.hlo / f"{stage}.hlo").write_text(hlo)
            counts = count_ops(hlo)
            names |= pallas_names(hlo)
            loops = set(re.findall(r"while\(.*?body=%([\w.\-]+)", hlo))
            bodies = {k: v for k, v in counts.items() if k in loops}
            entry = next(v for k, v in counts.items() if k.startswith("ENTRY"))
            row = {"stage": stage, "compile_s": round(time.perf_counter() - start, 1), **kinds(hlo),
                   "entry_kernels": kernels(entry), "loop_bodies": {k: kernels(v) for k, v in bodies.items()},
                   "counts": {"ENTRY": entry, **bodies}, "loop_sequences": {k: sequence(hlo, k) for k in bodies},
                   "loop_invariant": loop_invariant_kernels(hlo)}
            results["programs"].append(row)
            for body, kernels_in_order in row["loop_sequences"].items() if args.sequence else ():
                print(f"  {body}:")
                for name, how, op in kernels_in_order:
                    print(f"    {name:32} {how:28} {op}")
            print(f"{stage}: {row['entry_kernels']} kernels outside loops, loop bodies {row['loop_bodies']}, "
                  f"FP8 GEMMs {row['fp8_gemms']}, Mosaic GPU {row['mosaic_gpu']}, Triton {row['triton']} "
                  f"({row['compile_s']} s)", flush=True)
            for body, same in row["loop_invariant"].items():
                if same:
                    listed = ", ".join(f"{n} ({op.split('/')[-1]})" for n, op in same)
                    print(f"  {body}: {len(same)} kernels alike in every trip: {listed}")
        results["mosaic_gpu_kernels"] = ptxas_info(Path(dump))
        results["triton_kernels"] = triton_ptxas(Path(dump) / "xla", names)
    for k in results["mosaic_gpu_kernels"]:
        print(f"  {k['kernel']}: {k['registers']} registers, spills {k['spill_store_bytes']} / "
              f"{k['spill_load_bytes']} B{', wgmma serialised' if k['serialised_wgmma'] else ''}")
    for k in results["triton_kernels"]:
        print(f"  {k['kernel']} (Triton): {k['registers']} registers, spills {k['spill_store_bytes']} / "
              f"{k['spill_load_bytes']} B")
    if names and not results["triton_kernels"]:
        print("  Triton kernels' registers: no ptxas found" if ptxas_binary() is None else
              "  Triton kernels' registers: none of the Pallas kernels was found in XLA's PTX dump")
    if args.fp8_mlp_sharded:
        results["fp8_mlp_sharded"] = fp8_mlp_sharded()
        print(f"FP8 MLP kernel on 2 devices: {results['fp8_mlp_sharded']}")
    if args.out:
        args.out.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
