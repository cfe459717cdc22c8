"""FP8 / FP4 quantisation: params -> params transforms.

schemes: which GEMMs each scheme quantises, calibration. report: accuracy vs bf16, the CLI. The number formats
(`QArray`, FP8 / FP4 quantise-dequantise, checkpoint storage) and the one matmul entry point they plug into live
lower in the house, in `pi0_jax.ops` (formats, matmul), where the model, the engine and checkpoints import them.
"""
