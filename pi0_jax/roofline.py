"""Each stage's work and its floor on the device: the FLOPs of its GEMMs and attention products, the bytes it must
read, and the time those take at the device's peaks.

The work is what the engine's programs compute at a call's shapes (every camera's patches, the prompt at its bucket,
masked keys included: the kernels compute them), counted from the config; a test checks that it equals the dot
products of the engine's stage programs traced at test sizes, after dead-code elimination. Per element:

  vision   per image: the patch embedding, per block q/k/v, out, fc1, fc2 and the two attention products over its
           patches, then the head into the language model's width
  prefix   T = patches + bucket rows: per layer q/k/v, attention over the T keys, out, gate/up, down; the last layer
           only q/k/v (its keys and values are all the cache needs: XLA drops the rest)
  denoise  per step the A = horizon action rows through every expert layer, attending over the cache and their own
           keys, and the action projections (π0: the folded in-projection and the time MLP's out-projection). π0's
           state token runs once a call, like a prefix row of its own: its keys join the cache (the floor counts its
           weights as read with the first step's)
  call     the stages one after another: the sum of their floors

Bytes are the weights a stage reads once (each denoise step reads the expert's again) and, per step, the prefix cache:
the traffic no fusion removes; activations are left out. The floor is the larger of FLOPs at the peak rate of their
GEMMs' format (FP8 x FP8 GEMMs at the FP8 peak, the rest at bf16's; attention in bf16) and bytes at the memory's
bandwidth. Peaks are the data sheet's dense figures (no sparsity) for the devices named in `PEAKS`; on others there
is no floor.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from pi0_jax.config import Pi0Config
from pi0_jax.ops.formats import QArray


@dataclasses.dataclass(frozen=True)
class Peaks:
    """A device's dense tensor-core peaks (FLOP/s) and memory bandwidth (bytes/s)."""

    bf16: float
    fp8: float
    memory: float


# NVIDIA's data sheets (SXM unless named); matched in this order against jax's device_kind
PEAKS: tuple[tuple[str, Peaks | None], ...] = (
    ("GH200", None),   # its memory differs by model: no single figure
    ("H200", Peaks(989.4e12, 1978.9e12, 4.8e12)),
    ("H100 NVL", Peaks(835e12, 1671e12, 3.9e12)),
    ("H100 PCIe", Peaks(756e12, 1513e12, 2.0e12)),
    ("H100", Peaks(989.4e12, 1978.9e12, 3.35e12)),
)


def peaks_of(device_kind: str) -> Peaks | None:
    """The peaks of a device by its name (`jax.Device.device_kind`), None where `PEAKS` has none."""
    return next((p for name, p in PEAKS if name in device_kind), None)


def gemm_formats(weights: dict) -> dict[str, tuple[bool, int]]:
    """Each two-dimensional weight of the engine's tree by name, the GEMMs' among them ("vlm/gate_up", "img/qkv",
    "top/action_out_proj", ...: layers and blocks share one): (FP8 x FP8 product, bytes an element). FP8 weights with
    no activation scale are weight-only."""
    out = {}

    def put(name, w):
        out[name] = (w.act_scale is not None, 1) if isinstance(w, QArray) else (False, w.dtype.itemsize)

    for tower in ("vlm", "expert"):
        for name, w in weights[tower][0].items():
            if w.ndim == 2:
                put(f"{tower}/{name}", w)
    for name, w in weights["img"]["blocks"][0].items():
        if w.ndim == 2:
            put(f"img/{name}", w)
    put("img/embedding", weights["img"]["embedding"]["kernel"])
    put("img/head", weights["img"]["head"]["kernel"])
    for name, layer in weights["top"].items():
        put(f"top/{name}", layer["kernel"])
    return out


@dataclasses.dataclass
class Work:
    """A stage's work: GEMM FLOPs and weight elements by GEMM name, attention FLOPs, other bytes (the cache)."""

    gemm_flops: dict[str, float] = dataclasses.field(default_factory=dict)
    weight_elems: dict[str, float] = dataclasses.field(default_factory=dict)
    attention_flops: float = 0.0
    other_bytes: float = 0.0

    def gemm(self, name: str, rows: float, k: int, n: int, count: int = 1, reads: int = 1):
        """count GEMMs (rows, k) @ (k, n) of one weight shape, whose weights are read `reads` times each."""
        self.gemm_flops[name] = self.gemm_flops.get(name, 0.0) + 2.0 * rows * k * n * count
        self.weight_elems[name] = self.weight_elems.get(name, 0.0) + float(k * n * count * reads)

    def attention(self, queries: float, keys: int, width: int, count: int = 1):
        """count layers of q kᵀ and p v: `queries` rows against `keys`, over `width` = heads x head dim."""
        self.attention_flops += 2 * 2.0 * queries * keys * width * count

    def flops(self) -> float:
        return sum(self.gemm_flops.values()) + self.attention_flops


def vision_work(config: Pi0Config, images: int) -> Work:
    """The SigLIP tower and its head over `images` images."""
    v, w = config.siglip, config.siglip.width
    r = images * v.num_patches
    work = Work()
    work.gemm("img/embedding", r, v.patch_size**2 * 3, w)
    work.gemm("img/qkv", r, w, 3 * w, v.depth)
    work.gemm("img/out", r, w, w, v.depth)
    work.gemm("img/fc1", r, w, v.mlp_dim, v.depth)
    work.gemm("img/fc2", r, v.mlp_dim, w, v.depth)
    work.attention(r, v.num_patches, w, v.depth)
    work.gemm("img/head", r, w, config.paligemma.width)
    return work


def _layers(work: Work, tower: str, g, rows: float, keys: int, full: int, last_qkv: bool, reads: int = 1):
    """`full` whole layers of rows attending over `keys`, then (last_qkv) one layer of q/k/v alone."""
    qkv = (g.num_heads + 2 * g.num_kv_heads) * g.head_dim
    width = g.num_heads * g.head_dim
    work.gemm(f"{tower}/qkv", rows, g.width, qkv, full + last_qkv, reads)
    work.gemm(f"{tower}/attn_out", rows, width, g.width, full, reads)
    work.gemm(f"{tower}/gate_up", rows, g.width, 2 * g.mlp_dim, full, reads)
    work.gemm(f"{tower}/down", rows, g.mlp_dim, g.width, full, reads)
    work.attention(rows, keys, width, full)


def prefix_work(config: Pi0Config, batch: int, tokens: int) -> Work:
    """The prefix fill: `tokens` rows an element (patches and the prompt's bucket)."""
    work = Work()
    _layers(work, "vlm", config.paligemma, batch * tokens, tokens, config.paligemma.depth - 1, True)
    return work


def denoise_work(config: Pi0Config, batch: int, tokens: int, steps: int) -> Work:
    """`steps` denoise steps over a prefix cache of `tokens` keys an element, π0's state token once."""
    g, a, adim = config.action_expert, config.action_horizon, config.action_dim
    work = Work()
    keys = tokens
    if not config.pi05:   # the state token: once a call, a row whose keys and values join the cache; its layers'
        work.gemm("top/state_proj", batch, adim, g.width)   # weights are the first step's (no read of their own)
        _layers(work, "expert", g, batch, tokens + 1, g.depth - 1, True, reads=0)
        keys += 1
    rows = batch * a * steps
    _layers(work, "expert", g, rows, keys + a, g.depth, False, reads=steps)
    kv = config.paligemma.num_kv_heads * config.paligemma.head_dim
    work.other_bytes = float(jnp.dtype(config.dtype).itemsize * batch * g.depth * keys * 2 * kv * steps)   # the cache's k and v, every step
    if config.pi05:
        work.gemm("top/action_in_proj", rows, adim, g.width, reads=steps)
    else:   # the in-projection folded into the time MLP's first layer (its time half is made once a step count)
        work.gemm("top/action_time_in", rows, adim, g.width, reads=steps)
        work.gemm("top/action_time_mlp_out", rows, g.width, g.width, reads=steps)
    work.gemm("top/action_out_proj", rows, g.width, adim, reads=steps)
    return work


def call_work(config: Pi0Config, batch: int, cameras: int, bucket: int, steps: int) -> dict[str, Work]:
    """Each stage's work in a call: vision, prefix, denoise (all `steps`)."""
    tokens = cameras * config.siglip.num_patches + bucket
    return {"vision": vision_work(config, batch * cameras), "prefix": prefix_work(config, batch, tokens),
            "denoise": denoise_work(config, batch, tokens, steps)}


def floor(work: Work, formats: dict[str, tuple[bool, int]], peaks: Peaks | None, ms: float | None) -> dict:
    """A stage's work against the device: TFLOP (and the FP8 GEMMs' share), GB read, the floor in ms and what sets
    it, and the measured time's fraction of it (`ms`: the stage's median, None: none). A GEMM not in `formats` is
    bf16."""
    fmt = {name: formats.get(name, (False, 2)) for name in work.gemm_flops}
    fp8 = sum(f for name, f in work.gemm_flops.items() if fmt[name][0])
    nbytes = work.other_bytes + sum(e * fmt[name][1] for name, e in work.weight_elems.items())
    out = {"tflop": work.flops() / 1e12, "tflop_fp8": fp8 / 1e12, "gb": nbytes / 1e9}
    if ms:
        out["ms"] = ms
    if peaks is not None:
        compute = fp8 / peaks.fp8 + (work.flops() - fp8) / peaks.bf16
        memory = nbytes / peaks.memory
        out.update(floor_ms=1e3 * max(compute, memory), bound="compute" if compute >= memory else "memory")
        if ms:
            out["of_floor"] = out["floor_ms"] / ms
    return out


def row_figures(config: Pi0Config, formats: dict, device_kind: str, row: dict) -> dict:
    """A benchmark row's roofline: each stage against its median in the row, and the call (the stages one after
    another: the sum of their floors) against the row's total."""
    peaks = peaks_of(device_kind)
    works = call_work(config, row["batch"], row["cameras"], row["prompt_bucket"], row["steps"])
    stages = {name: floor(w, formats, peaks, row[name]["median_ms"]) for name, w in works.items()}
    call = {k: sum(s[k] for s in stages.values()) for k in ("tflop", "tflop_fp8", "gb")}
    total = row.get("total", {}).get("median_ms")
    if total:
        call["ms"] = total
    if peaks is not None:
        call["floor_ms"] = sum(s["floor_ms"] for s in stages.values())
        if total:
            call["of_floor"] = call["floor_ms"] / total
    out = {"stages": {**stages, "call": call}}
    if peaks is not None:
        out["peaks"] = {"bf16_tflops": peaks.bf16 / 1e12, "fp8_tflops": peaks.fp8 / 1e12,
                        "memory_tbs": peaks.memory / 1e12}
    return out
