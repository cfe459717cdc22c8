"""FP8 / FP4 quantisation: params -> params transforms plus the matmul op a quantised weight brings.

formats: QArray, FP8 / FP4 quantise-dequantise. hooks: the matmul dispatch, SigLIP's Dense hook, calibration taps.
schemes: which GEMMs each scheme quantises, calibration, checkpoint storage. report: accuracy vs bf16, the CLI.
"""

from pi0_jax.quant.formats import QArray, concat, fake_quant_fp4, quantize_fp4, quantize_fp8, rearrange

__all__ = ["QArray", "concat", "fake_quant_fp4", "quantize_fp4", "quantize_fp8", "rearrange"]
