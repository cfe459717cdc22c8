"""Which path each compiled program takes, chosen per batch size and platform from measurements (docs/BENCHMARKS.md):
the action expert's kernels ("xla" or the fused Pallas kernels, `expert_path`), each stage's attention (`Attention`),
SigLIP's LayerNorm (`vision_norm`), the first denoise step beside the prefix fill (`first_step_overlap`), and what
those choices make of the prefix cache and π0's state token (`kernel_cache`, `cached_state`). `programs` builds the
programs these name.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from pi0_jax.config import Pi0Config
from pi0_jax.ops import mosaic_gemm, pallas_base
from pi0_jax.ops import matmul as quant

# The batch sizes at which kernels="auto" runs the expert's Pallas kernels on a GPU: measured faster than XLA at
# B = 1 and 2 and slower at B = 3 (π0.5), 4 and 8 (H200, docs/BENCHMARKS.md); their 64-row blocks stream the weights
# once per row block.
PALLAS_MAX_BATCH = 2

# The batch from which the denoise step's attention="auto" is cuDNN's fused kernel on a GPU (H200, docs/BENCHMARKS.md),
# below it XLA's ops (at B <= PALLAS_MAX_BATCH the Pallas expert, which has its own attention). π0.5: its denoise loop
# 7 % faster at B = 3 with a kv head's 8 query heads folded into its rows, 8-14 % at B = 4-64 before that fold (which
# took a further 3 % off at B = 8, 13 % at B = 64). π0, its state token once a call (`cached_state`): 16 % faster at
# B = 3, 28 % at B = 8 (it was 9 % slower at B = 3 while the state row ran as XLA's attention beside the kernel).
CUDNN_DENOISE_MIN_BATCH = 3
# The batches at which the denoise attention="auto" is the Pallas split-key kernel in the XLA expert's layers, at
# `expert_kernels.blocks_at`'s launch (docs/BENCHMARKS.md, "The Pallas attention in the XLA expert"). π0 (the kernel
# runs its state row in every step): the 10-step denoise 25 % faster than XLA's attention at B = 3, 28 / 19 / 9 %
# faster than cuDNN's at B = 4 / 8 / 16 with 8 warps (H200s), 4 warps 6-9 % faster again (H100), 18 % slower at
# B = 64; against cuDNN's with the state once a call, 22 / 18 / 8 % faster at B = 3 / 8 / 16 (H200s, session 40).
# π0.5: with 4 warps 19 / 6.5 % faster than cuDNN's at B = 4 / 8, 5 % slower at B = 16 (H100).
PALLAS_DENOISE_BATCHES_MASKED = range(3, 17)
PALLAS_DENOISE_BATCHES = range(4, 9)


KERNELS = ("auto", "xla", "pallas")
# SigLIP's LayerNorm kernel measured 3 % faster on the tower at 24 and 192 images, and no faster at 3 (H100, XLA's
# GEMMs; docs/BENCHMARKS.md, "SigLIP's LayerNorm as a kernel"): "auto" takes it where it was measured faster
VISION_NORM_MIN_IMAGES = 24
OVERLAPS = ("auto", "on", "off")
# The first denoise step beside the prefix fill (`first_step_overlap`): "auto" up to this batch. On H200s π0's call
# was 1.0-2.4 % faster at B = 1 (six machines) and π0.5's 2.3-3.5 % (two), and level at B = 2 (-0.4 %), 8 and 64,
# where it costs compile time and scratch memory for nothing. With the other steps' loop a program of its own
# (`Engine.call_stages`, session 45) π0's call is 1.3 % faster at B = 1 again and 1.7 % faster at B = 2 than without
# the overlap (H200; docs/BENCHMARKS.md)
OVERLAP_MAX_BATCH = 2
# The call's second program with its first denoise step beside the prefix fill (`first_step_overlap`) compiles with
# this: XLA's command buffers then run each kernel once the kernels whose buffers it reads are done, not in the
# scheduler's one order (XLA's default, "LHS")
CONCURRENT = {"xla_gpu_command_buffer_scheduling_mode": "CONCURRENT"}


def check_kernels(kernels: str) -> str:
    if kernels not in KERNELS:
        raise ValueError(f"kernels must be one of {KERNELS}, got {kernels!r}")
    return kernels


def check_overlap(overlap: str) -> str:
    if overlap not in OVERLAPS:
        raise ValueError(f"overlap must be one of {OVERLAPS}, got {overlap!r}")
    return overlap


def is_quantised(tree) -> bool:
    """Whether any weight in tree is quantised (an FP8 `QArray` or a calibration `Tap`)."""
    return any(quant.is_quant(x) for x in jax.tree.leaves(tree, is_leaf=quant.is_quant))


def expert_path(kernels: str, batch: int, expert_weights, platform: str | None = None) -> str:
    """The action expert's path for one program: "xla" or "pallas" as asked; "auto" picks the faster at this batch
    on this platform: the Pallas kernels on a GPU up to PALLAS_MAX_BATCH (with unrolled, unquantised layers; on a
    jax without Pallas's Triton backend, `pallas_base.TRITON`, only where all of them run on Mosaic GPU,
    `expert_kernels.TRITON_FREE`: bf16 on Hopper), else XLA (on a CPU the kernels run interpreted)."""
    if check_kernels(kernels) != "auto":
        return kernels
    if expert_weights is None:
        raise ValueError("kernels='auto' chooses the expert's path by its weights; without them pass 'xla' or "
                         "'pallas' (e.g. `Engine.kernels_for(batch)`)")
    platform = platform or jax.default_backend()
    unrolled = isinstance(expert_weights, (list, tuple))
    pallas = platform == "gpu" and batch <= PALLAS_MAX_BATCH and unrolled and not is_quantised(expert_weights)
    if pallas and not pallas_base.TRITON:
        bf16 = all(expert_weights[0][k].dtype == jnp.bfloat16 for k in ("qkv", "attn_out", "gate_up", "down"))
        pallas = bf16 and mosaic_gemm.hopper()
    return "pallas" if pallas else "xla"


def first_step_overlap(overlap: str, kernels: str, batch: int, expert_weights, platform: str | None = None) -> bool:
    """Whether the call's second program runs its first denoise step beside the prefix fill: the step after the
    fill (`prefix_first_step`, or `peel_first` in `prefix_denoise`; its layer i then waits for the cache's layer i
    alone), the program compiled with `CONCURRENT`, so the latency-bound step's kernels run in the compute-bound
    prefix's gaps. "on" / "off" as asked; "auto" up to OVERLAP_MAX_BATCH where the expert runs its Pallas kernels on
    a GPU (`expert_path`). On an H200 at B = 1 the call is 2.4 % (π0) and 3.5 % (π0.5) faster; at B = 8 and 64 level,
    and at B = 64 the program takes 4.5 GB more scratch (docs/BENCHMARKS.md, "The first denoise step beside the prefix
    fill"); at B = 2 1.7 % faster since the other steps' loop is a program of its own ("The denoise loop as a program
    of its own")."""
    if check_overlap(overlap) != "auto":
        return overlap == "on"
    platform = platform or jax.default_backend()
    return (platform == "gpu" and batch <= OVERLAP_MAX_BATCH
            and expert_path(kernels, batch, expert_weights, platform) == "pallas")


def overlap_options(options: dict | None, overlap: bool) -> dict | None:
    """A call's second program's compiler options: `options`, with `CONCURRENT` where it overlaps its first step."""
    return {**(options or {}), **CONCURRENT} if overlap else options


def vision_norm(kernels: str, images: int, platform: str | None = None) -> str:
    """SigLIP's residual adds and LayerNorms: "xla" or "pallas" (`ops.layer_norm`: one kernel where XLA runs two or
    three) as asked; "auto" the kernel on a GPU from VISION_NORM_MIN_IMAGES images per call, XLA's ops below (and
    on a CPU, where the kernel runs interpreted, and on a jax without Pallas's Triton backend)."""
    if check_kernels(kernels) != "auto":
        return kernels
    gpu = (platform or jax.default_backend()) == "gpu" and pallas_base.TRITON
    return "pallas" if gpu and images >= VISION_NORM_MIN_IMAGES else "xla"


@dataclasses.dataclass(frozen=True)
class Attention:
    """Each stage's attention: "xla" (the reference's ops: logits, softmax, weighted sum) or "cudnn" (one fused
    flash kernel, `ops.attention.fused`: cuDNN on a GPU, its XLA form elsewhere; masks by lengths, so the prefix
    fill puts each element's valid tokens first). Vision's may also be "pallas" (`ops.vision_attention`: q, k and v
    read in place from the fused GEMM's output). The denoise step's may also be "pallas" (the XLA expert's layers
    with the Pallas expert's split-key attention, `ops.expert_attention.attention`, over a cache in its layout; not
    differentiable) or "auto": "cudnn" from CUDNN_DENOISE_MIN_BATCH on, else "xla", but "pallas" at
    PALLAS_DENOISE_BATCHES (π0: PALLAS_DENOISE_BATCHES_MASKED) (`at_batch` resolves it; the programs do). It is
    unused by the Pallas expert, which has its own."""

    vision: str = "xla"
    prefix: str = "xla"
    denoise: str = "xla"

    def __post_init__(self):
        for stage, value in dataclasses.asdict(self).items():
            extra = {"vision": ("pallas",), "denoise": ("pallas", "auto")}.get(stage, ())
            if value not in ("xla", "cudnn", *extra):
                raise ValueError(f"attention for {stage} must be one of {('xla', 'cudnn', *extra)}, got {value!r}")

    def at_batch(self, batch: int, suffix_mask: bool = False, differentiable: bool = False) -> Attention:
        """The concrete choice of every stage for a program of this batch size; suffix_mask: the model's suffix
        masks some of its own keys (π0; π0.5's attends everywhere); differentiable: XLA's denoise attention (a
        program that differentiates the velocity, `guidance.guided_denoise`: the Pallas kernel has no VJP, and
        cuDNN's flash attention refused a backward pass at the suffix's sequence lengths on a GPU). On a jax without
        Pallas's Triton backend "pallas" is the kernel on Mosaic GPU (`expert_kernels.TRITON_FREE`: Hopper; "auto" is
        bf16 only), and elsewhere cuDNN's or XLA's."""
        if self.denoise != "auto":
            return self
        if differentiable:
            return dataclasses.replace(self, denoise="xla")
        kernel = PALLAS_DENOISE_BATCHES_MASKED if suffix_mask else PALLAS_DENOISE_BATCHES
        if batch in kernel and (pallas_base.TRITON or mosaic_gemm.hopper()):   # without Triton on Mosaic GPU
            return dataclasses.replace(self, denoise="pallas")
        return dataclasses.replace(self, denoise="cudnn" if batch >= CUDNN_DENOISE_MIN_BATCH else "xla")

    @classmethod
    def parse(cls, spec, platform: str | None = None, dtype: str = "bfloat16") -> Attention:
        """"xla" | "cudnn" (every stage) | "auto" (`AUTO_GPU` on a GPU for bfloat16 models, with cuDNN's vision
        attention on a jax without Pallas's Triton backend; else "xla": cuDNN's flash kernel takes no float32) |
        "vision=cudnn,prefix=xla" (unnamed stages "xla") | an Attention."""
        if isinstance(spec, cls):
            return spec
        if spec == "auto":
            if (platform or jax.default_backend()) != "gpu" or dtype != "bfloat16":
                return cls()
            return AUTO_GPU if pallas_base.TRITON else dataclasses.replace(AUTO_GPU, vision="cudnn")
        if spec in ("xla", "cudnn"):
            return cls(spec, spec, spec)
        fields = {f.name for f in dataclasses.fields(cls)}
        kw = {}
        for part in str(spec).split(","):
            stage, _, value = part.partition("=")
            if stage not in fields or not value:
                raise ValueError(f"attention: expected 'xla', 'cudnn', 'auto' or stage=impl pairs over {sorted(fields)}, "
                                 f"got {spec!r}")
            kw[stage] = value
        return cls(**kw)

    def __str__(self) -> str:
        return ",".join(f"{k}={v}" for k, v in dataclasses.asdict(self).items())


def attention_spec(spec: str) -> str:
    """`Attention.parse`'s check for command lines (argparse `type=`): returns spec unchanged, or raises."""
    Attention.parse(spec, platform="cpu")
    return spec


# attention="auto" on a GPU: per stage (and, in the denoise step, per batch), the faster (docs/BENCHMARKS.md): the
# Pallas vision attention beat cuDNN's at 3, 24 and 192 images (H100, 6 / 4 / 2 % of the tower): it needs no q/k/v
# copies
AUTO_GPU = Attention(vision="pallas", prefix="cudnn", denoise="auto")


def kernel_cache(kernels: str, attention: Attention, batch: int, expert_weights) -> bool:
    """Whether a program at this batch keeps its prefix cache in the expert kernels' layout (`ops.layout.cache_kv`):
    the Pallas expert's path, or the XLA expert's with the Pallas attention. `attention` resolved (`at_batch`)."""
    return expert_path(kernels, batch, expert_weights) == "pallas" or attention.denoise == "pallas"


def fused_suffix_attention(config: Pi0Config, attention: Attention, kernels: str, batch: int,
                           expert_weights) -> bool:
    """Whether the denoise step at this batch runs the XLA expert with the fused (cuDNN) attention, which reads the
    suffix-first key / value buffers of `programs.suffix_kv`."""
    fused = attention.at_batch(batch, suffix_mask=not config.pi05).denoise == "cudnn"
    return fused and expert_path(kernels, batch, expert_weights) != "pallas"


def cached_state(config: Pi0Config, attention: Attention, kernels: str, batch: int, expert_weights) -> bool:
    """Whether π0's state token runs through the expert once a call, before the denoise loop, instead of as a row of
    every step. Its row attends to the prefix and to itself alone (a causal block of its own, spec §5.4), so its keys
    and values at every layer depend on neither the noisy actions nor the flow time; the steps then run the action
    rows alone, unmasked, as π0.5's. On the XLA expert with XLA's or the fused attention: the Pallas expert and the
    Pallas attention lay their tables out for the row. `attention` resolved or not."""
    if config.pi05 or expert_path(kernels, batch, expert_weights) != "xla":
        return False
    return attention.at_batch(batch, suffix_mask=True).denoise in ("xla", "cudnn")
