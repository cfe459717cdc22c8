"""Low-level ops the model, engine and quant modules build on.

matmul: the one entry point of every weighted matmul (plain, FP8 `QArray`, calibration `Tap`) and SigLIP's Dense
hook. attention: fused (flash) attention, cuDNN's kernel on a GPU. formats: FP8 / FP4 number formats, `QArray`,
its checkpoint storage. expert_kernels, expert_attention, layout: the action expert's fused Pallas kernels (its
GEMMs with their launch, its split-key attention) and their data layout; mosaic_attention: that attention on Mosaic
GPU;
mosaic_gemm: a TMA-pipelined Mosaic GPU GEMM (Hopper) the expert's gate/up runs on, with GeGLU in its epilogue;
fp8_geglu: an FP8 MLP's gate/up GEMM, GeGLU and the down GEMM's e4m3 input as one Mosaic GPU kernel (the prefix's
MLPs on Hopper);
vision_attention: SigLIP's attention as a Pallas kernel that reads q, k, v in place; layer_norm: SigLIP's residual
add and LayerNorm as one Pallas kernel; pallas_base: what those kernels share (block sizes, the call).
"""
