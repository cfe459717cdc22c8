"""LeRobot's PyTorch π0 / π0.5 (`lerobot` from PyPI) at the same preset, timed on the same device and inputs.

Random weights (LeRobot's own init), the LeRobot `dtype` matching ours (its bf16 mode keeps vision fp32, as it does
for users). Times `policy.model.sample_actions` (no pre/post-processing, as for pi0-jax), eager, and with
`torch.compile` when asked (mode `--torch-compile-mode`: "default"; LeRobot's own, "max-autotune", compiles for
longer than a 10-minute run allows at full size) in one of two scopes (`--torch-compile-scope`):

* `sample_actions`: the whole call is one compiled function, as LeRobot's `compile_model=True` does (the step loop
  is unrolled into the graph, so the first call compiles the vision tower, the prefix and every denoise step).
* `stages`: LeRobot's own per-stage methods that `sample_actions` calls are compiled in place, and the Euler loop
  over steps stays eager: `embed_prefix` (SigLIP on every camera slot and the prompt embedding), the prefix pass
  of the PaliGemma language model that fills the KV cache (`paligemma.model.language_model.forward`), and
  `denoise_step` (one step of the action expert against that cache). Each is one graph, compiled on the first call
  and reused by every later step and call.

Either scope sets `torch.set_float32_matmul_precision("high")` for the compiled rows, as LeRobot's `compile_model`
does (it makes the fp32 vision tower's matmuls TF32); the eager rows run with TF32 off. The row's `impl` names the
mode, the scope and that precision; a compiled row also counts the graphs Dynamo compiled while it ran (scope
`stages`: 3 at the first batch size, any more are recompiles; `sample_actions`: 1) and its graph breaks. Each row
is printed as one JSON line as soon as it is measured, so a run killed by a time limit still leaves the rows before
it in the log. LeRobot processes the whole padded prompt and every camera slot it is given; it gets the same
cameras and prompt as pi0-jax.
"""

from __future__ import annotations

import json
import time

import numpy as np

from pi0_jax.config import IMAGE_KEYS, Pi0Config

COMPILE_SCOPES = ("sample_actions", "stages")


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


def _sync(device: str) -> None:
    import torch

    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def _time(fn, inputs: list, iters: int, warmup: int, device: str = "cuda") -> dict:
    for i in range(warmup):
        fn(inputs[i % len(inputs)])
    _sync(device)
    times = []
    for i in range(iters):
        start = time.perf_counter()
        fn(inputs[i % len(inputs)])
        _sync(device)
        times.append((time.perf_counter() - start) * 1e3)
    return {"median_ms": float(np.median(times)), "p90_ms": float(np.percentile(times, 90)),
            "min_ms": float(np.min(times))}


def compile_model(model, scope: str, mode: str):
    """Wrap LeRobot's `PI0Pytorch` / `PI05Pytorch` in `torch.compile`; returns the function to call.

    `sample_actions`: the whole call, as LeRobot's `compile_model` does (the model is left as it is). `stages`:
    LeRobot's own methods that `sample_actions` calls are replaced on this instance by compiled versions of
    themselves, so `model.sample_actions` (returned) runs its Euler loop in Python and each stage as one graph.
    The precision is set to `high`, as LeRobot's `compile_model` sets it.
    """
    import torch

    if scope not in COMPILE_SCOPES:
        raise ValueError(f"torch.compile scope must be one of {COMPILE_SCOPES}, got {scope!r}")
    torch.set_float32_matmul_precision("high")
    if scope == "sample_actions":
        return torch.compile(model.sample_actions, mode=mode)
    model.embed_prefix = torch.compile(model.embed_prefix, mode=mode)
    language_model = model.paligemma_with_expert.paligemma.model.language_model  # the prefix pass only
    language_model.forward = torch.compile(language_model.forward, mode=mode)
    model.denoise_step = torch.compile(model.denoise_step, mode=mode)
    return model.sample_actions


def benchmark(config: Pi0Config, args, device: str = "cuda") -> list[dict]:
    """LeRobot timings at every --batch for the largest --steps; eager, then torch.compile if asked.

    Prints each row as one JSON line (flushed) as soon as it is measured.
    """
    import torch

    import lerobot

    torch.backends.cuda.matmul.allow_tf32 = False
    precision = torch.get_float32_matmul_precision()
    steps = max(args.steps)
    policy = _build(config, steps, device)
    model = policy.model
    scope = getattr(args, "torch_compile_scope", "stages")

    def call(fn, x):
        with torch.no_grad():
            if config.pi05:
                return fn(x["images"], x["img_masks"], x["lang_tokens"], x["lang_masks"], noise=x["noise"])
            return fn(x["images"], x["img_masks"], x["lang_tokens"], x["lang_masks"], x["state"], noise=x["noise"])

    # (name, factory): a compiled variant wraps the model only when its turn comes, after the eager rows.
    variants = [("eager", lambda: model.sample_actions)]
    if args.torch_compile:
        variants.append((f"torch.compile(mode={args.torch_compile_mode}, scope={scope}, fp32 matmul high)",
                         lambda: compile_model(model, scope, args.torch_compile_mode)))

    def graphs():  # Dynamo's graphs so far and its graph breaks (a recompile adds a graph)
        from torch._dynamo.utils import counters

        return counters["stats"]["unique_graphs"], sum(counters["graph_break"].values())

    rows = []
    try:
        for name, make in variants:
            fn = make()
            for batch in [b for b in args.batch if b in args.peer_batch]:
                before = graphs()
                sets = [_inputs(config, batch, args.cameras, args.prompt_tokens, args.seed + i, device)
                        for i in range(args.input_sets)]
                print(f"LeRobot {name} B={batch}: first call", flush=True)
                start = time.perf_counter()
                call(fn, sets[0])
                _sync(device)
                first_s = time.perf_counter() - start
                row = {"impl": f"LeRobot {lerobot.__version__} torch {torch.__version__} {name}",
                       "dtype": config.dtype, "batch": batch, "steps": steps, "first_call_s": first_s,
                       "total": _time(lambda x: call(fn, x), sets, args.peer_iters, args.warmup, device)}
                if name != "eager":  # the graphs compiled during this row, the timed calls' included
                    row["compiled_graphs"], row["graph_breaks"] = (a - b for a, b in zip(graphs(), before))
                print(json.dumps(row), flush=True)
                rows.append(row)
    finally:
        torch.set_float32_matmul_precision(precision)
    del policy, model, fn   # fn (a bound method or a compiled module) holds the model too
    if torch.device(device).type == "cuda":
        torch.cuda.empty_cache()
    return rows
