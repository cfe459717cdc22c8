"""LeRobot's PyTorch π0 / π0.5 (`lerobot` from PyPI) at the same preset, timed on the same device and inputs.

Random weights (LeRobot's own init), the LeRobot `dtype` matching ours (its bf16 mode keeps vision fp32, as it does
for users). Times `policy.model.sample_actions` (no pre/post-processing, as for pi0-jax), eager, and with
`torch.compile` when asked (mode `--torch-compile-mode`, default LeRobot's own `max-autotune`). LeRobot processes
the whole padded prompt and every camera slot it is given; it gets the same cameras and prompt as pi0-jax.
"""

from __future__ import annotations

import time

import numpy as np

from pi0_jax.config import IMAGE_KEYS, Pi0Config


def _build(config: Pi0Config, num_steps: int, device: str):
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature

    if config.pi05:
        from lerobot.policies.pi05 import modeling_pi05 as modeling
        from lerobot.policies.pi05.configuration_pi05 import PI05Config as Config
    else:
        from lerobot.policies.pi0 import modeling_pi0 as modeling
        from lerobot.policies.pi0.configuration_pi0 import PI0Config as Config
    cfg = Config(device=device, dtype=config.dtype, chunk_size=config.action_horizon,
                 n_action_steps=config.action_horizon, max_state_dim=config.action_dim,
                 max_action_dim=config.action_dim, num_inference_steps=num_steps,
                 tokenizer_max_length=config.max_token_len, push_to_hub=False)
    cfg.input_features = {
        **{f"observation.images.{k}": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 224, 224))
           for k in IMAGE_KEYS[: config.num_cameras]},
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(8,)),
    }
    cfg.output_features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(7,))}
    with torch.device(device):
        policy = (modeling.PI05Policy if config.pi05 else modeling.PI0Policy)(cfg)
    return policy.eval()


def _inputs(config: Pi0Config, batch: int, cameras: int, prompt_tokens: int, seed: int, device: str):
    import torch

    rng = np.random.default_rng(seed)
    L = config.max_token_len
    mask = np.broadcast_to(np.arange(L)[None] < min(prompt_tokens, L), (batch, L))
    t = lambda x, dtype=None: torch.from_numpy(np.ascontiguousarray(x)).to(device, dtype)  # noqa: E731
    return {
        "images": [t(rng.uniform(-1, 1, (batch, 3, 224, 224)).astype(np.float32)) for _ in range(config.num_cameras)],
        "img_masks": [t(np.full((batch,), i < cameras)) for i in range(config.num_cameras)],
        "lang_tokens": t(np.where(mask, rng.integers(2, config.vocab_size, (batch, L)), 0), torch.long),
        "lang_masks": t(mask.copy()),
        "state": t(rng.normal(size=(batch, config.action_dim)).astype(np.float32)),
        "noise": t(rng.normal(size=(batch, config.action_horizon, config.action_dim)).astype(np.float32)),
    }


def _time(fn, inputs: list, iters: int, warmup: int) -> dict:
    import torch

    for i in range(warmup):
        fn(inputs[i % len(inputs)])
    torch.cuda.synchronize()
    times = []
    for i in range(iters):
        start = time.perf_counter()
        fn(inputs[i % len(inputs)])
        torch.cuda.synchronize()
        times.append((time.perf_counter() - start) * 1e3)
    return {"median_ms": float(np.median(times)), "p90_ms": float(np.percentile(times, 90)),
            "min_ms": float(np.min(times))}


def benchmark(config: Pi0Config, args) -> list[dict]:
    """LeRobot timings at every --batch for the largest --steps; eager, then torch.compile if asked."""
    import torch

    import lerobot

    device = "cuda"
    torch.backends.cuda.matmul.allow_tf32 = False
    steps = max(args.steps)
    policy = _build(config, steps, device)
    model = policy.model

    def call(fn, x):
        with torch.no_grad():
            if config.pi05:
                return fn(x["images"], x["img_masks"], x["lang_tokens"], x["lang_masks"], noise=x["noise"])
            return fn(x["images"], x["img_masks"], x["lang_tokens"], x["lang_masks"], x["state"], noise=x["noise"])

    variants = [("eager", model.sample_actions)]
    if args.torch_compile:
        variants.append((f"torch.compile({args.torch_compile_mode})",
                         torch.compile(model.sample_actions, mode=args.torch_compile_mode)))
    rows = []
    for name, fn in variants:
        for batch in [b for b in args.batch if b in args.peer_batch]:
            sets = [_inputs(config, batch, args.cameras, args.prompt_tokens, args.seed + i, device)
                    for i in range(args.input_sets)]
            start = time.perf_counter()
            call(fn, sets[0])
            torch.cuda.synchronize()
            first_s = time.perf_counter() - start
            rows.append({"impl": f"LeRobot {lerobot.__version__} torch {torch.__version__} {name}",
                         "dtype": config.dtype, "batch": batch, "steps": steps, "first_call_s": first_s,
                         "total": _time(lambda x: call(fn, x), sets, args.peer_iters, args.warmup)})
    del policy, model
    torch.cuda.empty_cache()
    return rows
