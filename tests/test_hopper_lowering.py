"""The engine's calls at full size lower for an H200 on this CPU (`scripts/deviceless.py` without the CUDA plugin:
the weights as shapes, jax's device queries answering as an H200): every Pallas Triton and Mosaic GPU kernel of the
default paths lowers at its real shapes, through Triton's lowering and Mosaic GPU's layout inference, which the
CPU interpreter of the other kernel tests does not run. And on a GPU the engine takes the paths it should: the kernel
calls of each program, by kind, are the design's (a path falling back to XLA, or a kernel added, changes them)."""

import collections
import re
import sys
from pathlib import Path

import pytest

from pi0_jax.config import IMAGE_KEYS, get_config
from pi0_jax.engine import layers, runtime

sys.path.insert(0, str(Path(__file__).parents[1] / "scripts"))
import deviceless  # noqa: E402

TRITON, MOSAIC, CUDNN = "__gpu$xla.gpu.triton", "mosaic_gpu_v2", "__cudnn$fmhaSoftmax"
# B = 1: vision's Pallas attention, a block's each over two programs (its LayerNorms are XLA's at 3 images); the
# prefix's cuDNN attention in 17 layers (the last layer's is dead code) with the first denoise step beside it; each
# step's expert: five Triton kernels a layer (q/k/v, the attention, its merge, the out-projection, down) and the
# Mosaic GPU gate/up. B = 8: vision's LayerNorms as kernels too (two a block and the final one); the XLA expert, with
# the Pallas split-key attention and its merge. In FP8 (`every-gemm`) the same kernels take e4m3 ends (the
# LayerNorms quantise, the attention scales its q/k/v and quantises); with `layers.FP8_GEGLU` the prefix's MLPs (the
# 17 live ones) run `ops.fp8_geglu`, and at B = 8 in `every-gemm` the expert's 18 and SigLIP's 27 fc1s too
B1 = {"vision_head": {TRITON: 9}, "vision_tail": {TRITON: 18},
      "prefix_first_step": {CUDNN: 17, TRITON: 90, MOSAIC: 18}, "denoise_rest": {TRITON: 90, MOSAIC: 18}}
B8 = {"vision_head": {TRITON: 27}, "vision_tail": {TRITON: 55}, "prefix_denoise": {CUDNN: 17, TRITON: 36}}
# (`every-gemm` without the FP8 MLP kernel and `prefix-all` with it lowered the same Triton kernels and a subset of
# the Mosaic GPU ones of `every-gemm` with it: dropped in session 66 for CI's time)
EXPECTED = {   # (preset, batch, FP8 scheme, FP8_GEGLU)
    ("pi0_base", 1, None, False): B1,
    ("pi05_base", 1, None, False): B1,
    ("pi0_base", 8, None, False): B8,
    ("pi0_base", 8, "every-gemm", True): {"vision_head": {TRITON: 27, MOSAIC: 9}, "vision_tail": {TRITON: 55, MOSAIC: 18},
                                          "prefix_denoise": {CUDNN: 17, TRITON: 36, MOSAIC: 35}},
}


@pytest.mark.parametrize("preset,batch,quant,fp8_mlp", list(EXPECTED))
def test_call_lowers_for_an_h200(preset, batch, quant, fp8_mlp, monkeypatch):
    monkeypatch.setattr(layers, "FP8_GEGLU", fp8_mlp)
    config = get_config(preset)
    got = {}
    with deviceless.as_target():
        engine = deviceless.abstract_engine(config, quant)
        for stage in engine.call_stages(batch, 10):
            program = engine.executable(stage, batch, 10, IMAGE_KEYS, runtime.prompt_bucket(48, config.max_token_len))
            got[stage] = dict(collections.Counter(re.findall(r"stablehlo.custom_call @([\w$.]+)", program.as_text())))
    assert got == EXPECTED[preset, batch, quant, fp8_mlp]


def test_kernel_counts_take_an_async_fusion_at_its_start():
    """XLA runs a dynamic slice of a contiguous block as an async fusion, a memcpy on the GPU (π0.5's step reads its
    adaRMS row so): one kernel, at its start; its done, the bitcast and the while are none."""
    from profile_engine import count_ops

    body = """%body.1 (p: (s32[], bf16[10,54,1024])) -> (s32[], bf16[10,54,1024]) {
  %p = (s32[], bf16[10,54,1024]{2,1,0}) parameter(0)
  %i = s32[] get-tuple-element(%p), index=0
  %t = bf16[10,54,1024]{2,1,0} get-tuple-element(%p), index=1
  %fusion-start = ((bf16[10,54,1024], s32[]), bf16[1,54,1024]{2,1,0}, u32[]) fusion-start(%t, %i), kind=kLoop, calls=%f
  %fusion-done = bf16[1,54,1024]{2,1,0} fusion-done(%fusion-start)
  %b = bf16[54,1024]{1,0} bitcast(%fusion-done)
  %loop_add_fusion = s32[] fusion(%i), kind=kLoop, calls=%g
  %c = (f32[8]{0}) custom-call(%b), custom_call_target="__gpu$xla.gpu.triton"
  %copy-start = (s32[], s32[], u32[]) copy-start(%i)
  %copy-done = s32[] copy-done(%copy-start)
  ROOT %r = (s32[], bf16[10,54,1024]{2,1,0}) tuple(%loop_add_fusion, %t)
}
"""
    assert count_ops(body)["body.1"] == {"fusion": 2, "custom-call": 1, "copy": 1, "while": 0, "other": 0}
    assert [row[:2] for row in deviceless.sequence(body, "body.1")] == [
        ["fusion-start", "kLoop"], ["loop_add_fusion", "kLoop"], ["c", "__gpu$xla.gpu.triton"],
        ["copy-start", "copy"]]
