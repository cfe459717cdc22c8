"""FP8 / FP4 quantisation: params -> params transforms.

schemes: which GEMMs each scheme quantises, calibration. report: accuracy vs bf16, the CLI. The number formats
(`QArray`, FP8 / FP4 quantise-dequantise, checkpoint storage) and the one matmul entry point they plug into live
lower in the house, in `pi0_jax.ops` (formats, matmul), where the model, the engine and checkpoints import them.
"""

from pi0_jax.ops.formats import QArray, concat, fake_quant_fp4, quantize_fp4, quantize_fp8, rearrange

__all__ = ["QArray", "concat", "fake_quant_fp4", "quantize_fp4", "quantize_fp8", "rearrange"]
