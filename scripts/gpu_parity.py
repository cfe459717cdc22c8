#!/usr/bin/env python
"""Full-size parity: LeRobot's PyTorch π0.5 vs the converted pi0-jax model, on one GPU, fp32 and bf16.

What it does (one process, phases timed and printed):

1. Builds LeRobot's own ``PI05Policy`` at full ``pi05_base`` size (gemma_2b VLM + gemma_300m action expert, SigLIP
   So400m/14, vocab 257152, chunk 50, tokenizer_max_length 200, 32-dim actions) in float32, directly on the device,
   and re-randomises every parameter with a fixed seed (per-parameter generator seeded from the seed and a CRC32 of
   the name, on the device), including the ones LeRobot/HF zero- or one-initialise (RMSNorm weights, LayerNorms,
   biases, the adaRMS ``dense`` layers), using the rules of ``scripts/make_lerobot_fixtures.py``.  The text embedding
   gets std 1/sqrt(width), so that the embedding times sqrt(width) has unit scale (the fixture's 0.125 at width 64).
2. ``policy.save_pretrained`` (LeRobot's writer) to a local folder, then converts it with
   ``converters.convert(src, dst, dtype=...)`` into a float32 and a bfloat16 pi0-jax checkpoint.  The two
   conversions run in CPU-only subprocesses (JAX_PLATFORMS=cpu) while the GPU runs the PyTorch reference.
3. PyTorch reference on the same inputs (B=1, three cameras with the right wrist masked, a prompt of
   ``--prompt-len`` random token ids right-padded to 200, injected noise): LeRobot's ``sample_actions`` (10 Euler
   steps) with spies that capture the prefix embedding and the prefix KV cache (LeRobot's own code path, as in the
   fixture script).  First with ``dtype="float32"``, then in LeRobot's bf16 mode: the same module put into the state
   ``PI05Policy.from_pretrained(..., dtype="bfloat16")`` produces (LeRobot's ``to_bfloat16_for_selected_params`` then
   ``load_state_dict`` of the fp32 weights; see ``to_lerobot_bf16``): everything bf16 except the vision tower, the
   projector and the norm / adaRMS parameters, which keep their fp32 values; the top-level action/time projections
   stay fp32.
4. pi0-jax: ``pi0_jax.checkpoint.load_checkpoint`` of each conversion, ``embed_prefix``, ``fill_prefix_cache`` and
   ``sample_actions`` (10 steps) under ``jax.jit``.
5. Compares (prefix K/V over the valid rows only: the rows of the masked camera and of the prompt padding are
   computed from masked-out context and never attended to) and reports max abs error, max abs of the reference,
   relative L2 error and cosine similarity.  Writes ``parity.json`` (+ the actions, ``actions.npz``) to ``--out``
   and prints a markdown table.

Numerics: TF32 is OFF in torch (``torch.backends.cuda.matmul.allow_tf32 = False``,
``torch.backends.cudnn.allow_tf32 = False``, ``torch.set_float32_matmul_precision("highest")``) and JAX runs with
``jax_default_matmul_precision = "highest"``, so fp32 is real fp32 on both sides.  torch's bf16 GEMMs keep their
default (``allow_bf16_reduced_precision_reduction``), as LeRobot runs them.

Environment: needs torch + lerobot 0.6.1 + transformers 5.4-5.5 + jax/flax/orbax.  On the GPU image (transformers
5.17 is too new for LeRobot) the missing wheels are carried in ``.whl/`` and installed with ``--target /tmp/site``.
The ``--preset dummy_pi05`` flag runs the same pipeline at the tiny fixture sizes (CPU is enough).

Examples:
  python scripts/gpu_parity.py --out $OUT                                  # full size, on cuda
  python scripts/gpu_parity.py --preset dummy_pi05 --device cpu --out /tmp/parity_tiny
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import gc
import hashlib
import json
import os
import platform
import shutil
import subprocess
import sys
import time
import zlib
from pathlib import Path
from unittest import mock

# Before jax / torch are imported.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
# make_lerobot_fixtures (imported below for its tiny-size patches and init rules) pins these to 1 with setdefault.
os.environ.setdefault("OMP_NUM_THREADS", str(os.cpu_count() or 1))
os.environ.setdefault("MKL_NUM_THREADS", str(os.cpu_count() or 1))

import numpy as np  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))
sys.path.insert(0, str(REPO_ROOT / "scripts"))

CAMERAS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
CAMERA_MASK = (True, True, False)  # right wrist masked
MAX_DIM = 32
PRESETS = {
    # chunk, tokenizer_max_length, vocab, num image tokens per camera
    "pi05_base": dict(chunk=50, max_len=200, vocab=257152),
    "dummy_pi05": dict(chunk=10, max_len=200, vocab=1024),
}

T0 = time.perf_counter()
TIMES: dict[str, float] = {}


@contextlib.contextmanager
def phase(name: str):
    t = time.perf_counter()
    print(f"[{time.perf_counter() - T0:7.1f}s] >> {name}", flush=True)
    yield
    TIMES[name] = round(time.perf_counter() - t, 2)
    print(f"[{time.perf_counter() - T0:7.1f}s] << {name}: {TIMES[name]:.1f}s", flush=True)


# ---------------------------------------------------------------------------------------------------------
# Metrics
# ---------------------------------------------------------------------------------------------------------
def metrics(got, ref) -> dict[str, float]:
    got, ref = np.asarray(got, np.float64), np.asarray(ref, np.float64)
    assert got.shape == ref.shape, (got.shape, ref.shape)
    d = got - ref
    nr, ng = np.linalg.norm(ref), np.linalg.norm(got)
    return {
        "max_abs_err": float(np.abs(d).max()),
        "mean_abs_err": float(np.abs(d).mean()),
        "max_abs_ref": float(np.abs(ref).max()),
        "rel_l2": float(np.linalg.norm(d) / nr),
        "cosine": float(np.vdot(got, ref) / (ng * nr)),
        "finite": bool(np.isfinite(got).all()),
        "numel": int(ref.size),
    }


# ---------------------------------------------------------------------------------------------------------
# LeRobot side
# ---------------------------------------------------------------------------------------------------------
def param_init(fx, name: str, shape: tuple[int, ...]) -> tuple[float, float]:
    """The fixture script's rules, with the text embedding scaled to the width (1/sqrt(width); 0.125 at 64)."""
    if name.endswith("embed_tokens.weight"):
        return 0.0, float(shape[1]) ** -0.5
    return fx._param_init(name, shape)  # noqa: SLF001


def reinit_parameters(fx, module, seed: int) -> dict[str, list[float]]:
    import torch

    rules = {}
    assert len(list(module.named_parameters(remove_duplicate=False))) == len(list(module.named_parameters()))
    with torch.no_grad():
        for name, p in module.named_parameters():
            mean, std = param_init(fx, name, tuple(p.shape))
            g = torch.Generator(device=p.device).manual_seed(seed * 1_000_003 + zlib.crc32(name.encode()))
            r = torch.randn(p.shape, generator=g, device=p.device, dtype=torch.float32)
            p.copy_(r.mul_(std).add_(mean).to(p.dtype))
            del r
            rules[name] = [mean, std]
    return rules


def build_policy(fx, preset: str, device: str):
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.pi05 import modeling_pi05 as modeling
    from lerobot.policies.pi05.configuration_pi05 import PI05Config

    p = PRESETS[preset]
    cfg = PI05Config(device=device, dtype="float32", chunk_size=p["chunk"], n_action_steps=p["chunk"],
                     max_state_dim=MAX_DIM, max_action_dim=MAX_DIM, num_inference_steps=10,
                     tokenizer_max_length=p["max_len"], push_to_hub=False)
    tiny = preset.startswith("dummy")
    if tiny:
        cfg.paligemma_variant, cfg.action_expert_variant = fx.VLM_VARIANT, fx.EXPERT_VARIANT
    cfg.input_features = {
        **{f"observation.images.{c}": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 224, 224)) for c in CAMERAS},
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(8,)),
    }
    cfg.output_features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(7,))}
    shrink = fx.tiny_lerobot(modeling) if tiny else contextlib.nullcontext()
    # Allocate (and let HF initialise) directly on the device: a CPU init of 3.6B params is slow.
    with shrink, torch.device(device):
        policy = modeling.PI05Policy(cfg)
    policy.eval()
    return policy, modeling


def to_lerobot_bf16(policy) -> None:
    """Put the fp32 policy into exactly the state `PI05Policy.from_pretrained(<its checkpoint>, config with
    dtype="bfloat16")` gives, without re-reading the checkpoint: LeRobot's own `to_bfloat16_for_selected_params`
    (what construction with dtype="bfloat16" runs: everything bf16, then the vision tower, projector and norm params
    back to fp32, so their values are bf16-rounded), then `load_state_dict` of the fp32 weights (what from_pretrained
    does next: the fp32-kept params get their full fp32 values back, the others are rounded to bf16 on copy)."""
    import torch

    fp32_state = {k: v.detach().clone() for k, v in policy.state_dict().items()}
    policy.model.paligemma_with_expert.to_bfloat16_for_selected_params("bfloat16")
    policy.config.dtype = "bfloat16"
    res = policy.load_state_dict(fp32_state, strict=True)
    assert not res.missing_keys and not res.unexpected_keys, res
    del fp32_state
    if torch.cuda.is_available():
        torch.cuda.empty_cache()


def _t(x, device, dtype=None):
    import torch

    t = torch.from_numpy(np.ascontiguousarray(x)).to(device)
    return t if dtype is None else t.to(dtype)


def run_lerobot(policy, inp: dict, device: str) -> dict[str, np.ndarray]:
    """LeRobot's sample_actions on the inputs, spying on its prefix embedding and prefix KV cache."""
    import torch

    model = policy.model
    pwe = model.paligemma_with_expert
    batch = {
        f"observation.images.{c}": _t(inp["images"][i].astype(np.float32) / np.float32(255.0), device)
        .permute(0, 3, 1, 2) for i, c in enumerate(CAMERAS)
    }
    with torch.no_grad():
        images, _ = policy._preprocess_images(batch)  # noqa: SLF001  [0,1] -> [-1,1], NCHW, fp32
    img_masks = [_t(inp["image_masks"][i], device) for i in range(len(CAMERAS))]
    tokens = _t(inp["tokens"], device, torch.long)
    token_masks = _t(inp["token_masks"], device)
    noise = _t(inp["noise"], device)

    captured: dict = {}
    orig_embed_prefix, orig_pwe_forward = model.embed_prefix, pwe.forward

    def spy_embed_prefix(*a, **kw):
        res = orig_embed_prefix(*a, **kw)
        captured["prefix"] = res
        return res

    def spy_forward(*a, **kw):
        res = orig_pwe_forward(*a, **kw)
        if kw["inputs_embeds"][1] is None:
            captured["cache"] = res[1]
        return res

    with (torch.no_grad(), mock.patch.object(model, "embed_prefix", spy_embed_prefix),
          mock.patch.object(pwe, "forward", spy_forward)):
        actions = model.sample_actions(images, img_masks, tokens, token_masks, noise=noise)
    if device.startswith("cuda"):
        torch.cuda.synchronize()

    def np32(t):
        return t.detach().float().cpu().numpy()

    prefix_embs, prefix_pad_masks, _ = captured["prefix"]
    ks, vs = zip(*[(k, v) for k, v, *_ in captured["cache"]])  # each (B, K, P, H)
    return {
        "actions": np32(actions),
        "prefix_embs": np32(prefix_embs),
        "prefix_pad_masks": prefix_pad_masks.cpu().numpy(),
        "prefix_k": np.stack([np32(k.transpose(1, 2)) for k in ks]),  # (depth, B, P, K, H)
        "prefix_v": np.stack([np32(v.transpose(1, 2)) for v in vs]),
        "dtypes": {"actions": str(actions.dtype), "prefix_embs": str(prefix_embs.dtype), "prefix_k": str(ks[0].dtype)},
    }


# ---------------------------------------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------------------------------------
def make_inputs(fx, seed: int, preset: str, prompt_len: int) -> dict[str, np.ndarray]:
    p = PRESETS[preset]
    rng = np.random.default_rng([seed, 5])
    images = fx.make_images(rng)[:, :1]  # (cams, B=1, 224, 224, 3) uint8 smooth colour waves + noise
    tokens = np.zeros((1, p["max_len"]), np.int32)
    tokens[0, :prompt_len] = rng.integers(2, p["vocab"], size=prompt_len)
    token_masks = np.zeros((1, p["max_len"]), bool)
    token_masks[0, :prompt_len] = True
    return dict(
        images=images,
        image_masks=np.array(CAMERA_MASK, bool)[:, None],  # (cams, B)
        tokens=tokens,
        token_masks=token_masks,
        noise=rng.normal(size=(1, p["chunk"], MAX_DIM)).astype(np.float32),
    )


# ---------------------------------------------------------------------------------------------------------
# JAX side
# ---------------------------------------------------------------------------------------------------------
def run_jax(ckpt: Path, inp: dict, num_steps: int) -> tuple[dict[str, np.ndarray], dict]:
    import jax
    import jax.numpy as jnp

    from pi0_jax import checkpoint, pi0
    from pi0_jax.config import IMAGE_KEYS

    info: dict = {}
    t = time.perf_counter()
    config, params = checkpoint.load_checkpoint(ckpt)
    params = jax.device_put(params)
    jax.block_until_ready(params)
    info["load_s"] = round(time.perf_counter() - t, 2)
    info["config"] = config.to_json()
    info["param_dtypes"] = sorted({str(x.dtype) for x in jax.tree.leaves(params)})
    info["num_params"] = int(sum(x.size for x in jax.tree.leaves(params)))

    images = inp["images"].astype(np.float32) / np.float32(255.0) * 2 - 1
    obs = pi0.Observation(
        images={k: jnp.asarray(images[i]) for i, k in enumerate(IMAGE_KEYS)},
        image_masks={k: jnp.asarray(inp["image_masks"][i]) for i, k in enumerate(IMAGE_KEYS)},
        state=jnp.zeros((1, config.action_dim), jnp.float32),  # π0.5: not an input of the network
        tokenized_prompt=jnp.asarray(inp["tokens"], jnp.int32),
        tokenized_prompt_mask=jnp.asarray(inp["token_masks"]),
    )
    noise = jnp.asarray(inp["noise"])
    embed = jax.jit(pi0.embed_prefix, static_argnums=0)
    fill = jax.jit(pi0.fill_prefix_cache, static_argnums=0)
    sample = jax.jit(pi0.sample_actions, static_argnums=(0, 4))
    out = {}
    t = time.perf_counter()
    tokens, mask, _ = embed(config, params, obs)
    out["prefix_embs"] = np.asarray(jnp.asarray(tokens, jnp.float32))
    out["prefix_pad_masks"] = np.asarray(mask)
    cache = fill(config, params, obs)
    out["prefix_k"] = np.asarray(jnp.asarray(cache.k, jnp.float32))
    out["prefix_v"] = np.asarray(jnp.asarray(cache.v, jnp.float32))
    info["kv_dtype"] = str(cache.k.dtype)
    del cache, tokens
    info["prefix_compile_and_run_s"] = round(time.perf_counter() - t, 2)
    t = time.perf_counter()
    actions = sample(config, params, obs, noise, num_steps)
    out["actions"] = np.asarray(actions)
    info["sample_compile_and_run_s"] = round(time.perf_counter() - t, 2)
    t = time.perf_counter()
    jax.block_until_ready(sample(config, params, obs, noise, num_steps))
    info["sample_rerun_s"] = round(time.perf_counter() - t, 4)
    try:
        stats = jax.devices()[0].memory_stats() or {}
        info["peak_bytes_in_use"] = int(stats.get("peak_bytes_in_use", 0))
    except Exception:  # noqa: BLE001  (CPU backends have no memory stats)
        pass
    del params
    gc.collect()
    return out, info


# ---------------------------------------------------------------------------------------------------------
# Conversion (CPU-only subprocesses, so they overlap the torch GPU work)
# ---------------------------------------------------------------------------------------------------------
CONVERT_SNIPPET = (
    "import logging, sys, time; logging.basicConfig(level=logging.INFO, format='%(asctime)s %(message)s'); "
    "sys.path.insert(0, sys.argv[1]); import converters; t = time.perf_counter(); "
    "converters.convert(sys.argv[2], sys.argv[3], dtype=sys.argv[4]); "
    "print(f'converted {sys.argv[4]} in {time.perf_counter() - t:.1f}s', flush=True)"
)


def start_conversion(src: Path, dst: Path, dtype: str, log: Path) -> subprocess.Popen:
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "CUDA_VISIBLE_DEVICES": ""}
    return subprocess.Popen([sys.executable, "-c", CONVERT_SNIPPET, str(REPO_ROOT), str(src), str(dst), dtype],
                            stdout=log.open("w"), stderr=subprocess.STDOUT, env=env)


def wait_conversion(proc: subprocess.Popen, log: Path, dtype: str) -> None:
    rc = proc.wait()
    lines = log.read_text().splitlines()
    keep = [ln for ln in lines if any(w in ln for w in ("converting", "wrote", "converted", "ignoring"))]
    shown = lines[-40:] if rc != 0 else keep[:3] + (["..."] if len(keep) > 6 else []) + keep[-3:]
    print(f"--- converter log ({dtype}, {len(lines)} lines, excerpt) ---\n" + "\n".join(shown), flush=True)
    if rc != 0:
        raise SystemExit(f"conversion to {dtype} failed with exit code {rc}")


# ---------------------------------------------------------------------------------------------------------
# Reporting
# ---------------------------------------------------------------------------------------------------------
def tree_digest() -> str:
    """sha256 over the sources that define the numbers (pi0_jax/, converters/, this script)."""
    h = hashlib.sha256()
    files = sorted([*REPO_ROOT.glob("pi0_jax/**/*.py"), *REPO_ROOT.glob("converters/**/*.py"), Path(__file__)])
    for f in files:
        h.update(str(f.relative_to(REPO_ROOT)).encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def environment(device: str) -> dict:
    import importlib.metadata as md

    env = {"python": platform.python_version(), "platform": platform.platform(), "hostname": platform.node()}
    for pkg in ("torch", "jax", "jaxlib", "flax", "orbax-checkpoint", "transformers", "lerobot", "numpy",
                "tokenizers", "safetensors", "ml_dtypes"):
        try:
            env[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            env[pkg] = None
    if device.startswith("cuda"):
        try:
            env["nvidia_smi"] = subprocess.run(
                ["nvidia-smi", "--query-gpu=name,memory.total,driver_version", "--format=csv,noheader"],
                capture_output=True, text=True, timeout=30).stdout.strip()
        except Exception as e:  # noqa: BLE001
            env["nvidia_smi"] = f"unavailable: {e}"
    return env


def table(results: dict) -> str:
    lines = ["| comparison | quantity | max abs err | max abs ref | rel L2 err | cosine |",
             "|---|---|---|---|---|---|"]
    for comp, quantities in results.items():
        for q, m in quantities.items():
            lines.append(f"| {comp} | {q} | {m['max_abs_err']:.3e} | {m['max_abs_ref']:.3e} | {m['rel_l2']:.3e} | "
                         f"{m['cosine']:.8f} |")
    return "\n".join(lines)


def compare(got: dict, ref: dict, valid: np.ndarray) -> dict[str, dict]:
    """valid: (B, P) prefix rows anyone can attend to (valid camera tokens and prompt tokens)."""
    out = {"actions": metrics(got["actions"], ref["actions"])}
    b, p = np.nonzero(valid)
    out["prefix_k (valid rows)"] = metrics(got["prefix_k"][:, b, p], ref["prefix_k"][:, b, p])
    out["prefix_v (valid rows)"] = metrics(got["prefix_v"][:, b, p], ref["prefix_v"][:, b, p])
    out["prefix_embs (valid rows)"] = metrics(got["prefix_embs"][b, p], ref["prefix_embs"][b, p])
    return out


# ---------------------------------------------------------------------------------------------------------
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--preset", choices=sorted(PRESETS), default="pi05_base")
    ap.add_argument("--device", default="cuda", help="torch device for LeRobot (JAX uses its default backend)")
    ap.add_argument("--out", type=Path, default=Path(os.environ.get("OUT", REPO_ROOT / "out" / "gpu_parity")))
    ap.add_argument("--work-dir", type=Path, default=None,
                    help="where the LeRobot checkpoint and the conversions go (default: /dev/shm/pi0_parity if it "
                    "has 48 GB free, else /tmp/pi0_parity); removed at the end unless --keep")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--prompt-len", type=int, default=20)
    ap.add_argument("--num-steps", type=int, default=10)
    ap.add_argument("--commit", default=None, help="git commit to record (the device copy has no .git)")
    ap.add_argument("--serial-convert", action="store_true", help="convert after the torch runs, in-process order")
    ap.add_argument("--keep", action="store_true")
    args = ap.parse_args(argv)

    import torch

    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    torch.set_float32_matmul_precision("highest")
    import make_lerobot_fixtures as fx  # tiny-size patches, init rules, image generator

    args.out.mkdir(parents=True, exist_ok=True)
    if args.work_dir is None:
        shm = Path("/dev/shm")
        free = shutil.disk_usage(shm).free if shm.is_dir() else 0
        need = 48e9 if args.preset == "pi05_base" else 1e8
        args.work_dir = shm / "pi0_parity" if free > need else Path("/tmp/pi0_parity")
    work = args.work_dir
    for d in ("/dev/shm", "/tmp", str(REPO_ROOT)):
        if Path(d).is_dir():
            u = shutil.disk_usage(d)
            print(f"  {d}: {u.free / 1e9:.1f} GB free of {u.total / 1e9:.1f} GB", flush=True)
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)

    commit = args.commit
    if commit is None:
        try:
            commit = subprocess.run(["git", "-C", str(REPO_ROOT), "rev-parse", "HEAD"], capture_output=True,
                                    text=True).stdout.strip() or None
        except OSError:
            commit = None
    record: dict = {
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([Path(sys.executable).name, "scripts/gpu_parity.py", *(argv or sys.argv[1:])]),
        "commit": commit, "source_digest": tree_digest(), "preset": args.preset, "seed": args.seed,
        "prompt_len": args.prompt_len, "num_steps": args.num_steps, "camera_mask": list(CAMERA_MASK),
        "work_dir": str(work), "environment": environment(args.device),
        "numerics": {"torch_allow_tf32_matmul": torch.backends.cuda.matmul.allow_tf32,
                     "torch_allow_tf32_cudnn": torch.backends.cudnn.allow_tf32,
                     "torch_float32_matmul_precision": torch.get_float32_matmul_precision(),
                     "torch_bf16_reduced_precision_reduction":
                         torch.backends.cuda.matmul.allow_bf16_reduced_precision_reduction,
                     "jax_default_matmul_precision": "highest"},
    }
    import transformers

    print(f"transformers {transformers.__version__} from {Path(transformers.__file__).parent}; torch "
          f"{torch.__version__}; device {args.device}; work dir {work}", flush=True)
    if args.device.startswith("cuda"):
        record["environment"]["torch_device_name"] = torch.cuda.get_device_name()
        print(record["environment"]["nvidia_smi"], flush=True)

    # 1. LeRobot policy, random weights, saved by LeRobot.
    with phase("build LeRobot PI05Policy (fp32) + re-randomise"):
        policy, _ = build_policy(fx, args.preset, args.device)
        record["init_rules_count"] = len(reinit_parameters(fx, policy, args.seed))
        record["num_torch_params"] = int(sum(p.numel() for p in policy.parameters()))
        assert all(p.dtype == torch.float32 for p in policy.parameters())
        assert all(p.device.type == torch.device(args.device).type for p in policy.parameters())
    print(f"  torch params: {record['num_torch_params'] / 1e9:.3f} B", flush=True)
    src = work / "lerobot"
    with phase("LeRobot save_pretrained"):
        policy.save_pretrained(src)
    record["lerobot_checkpoint_bytes"] = sum(f.stat().st_size for f in src.iterdir())

    dsts = {d: work / f"jax_{d}" for d in ("float32", "bfloat16")}
    logs = {d: work / f"convert_{d}.log" for d in dsts}
    procs = {}
    if not args.serial_convert:
        t_conv = time.perf_counter()
        procs = {d: start_conversion(src, dsts[d], d, logs[d]) for d in dsts}

    # 2. PyTorch reference, fp32 then LeRobot's bf16 mode.
    inp = make_inputs(fx, args.seed, args.preset, args.prompt_len)
    ref = {}
    with phase("LeRobot fp32 sample_actions"):
        ref["float32"] = run_lerobot(policy, inp, args.device)
    with phase("LeRobot -> bf16 mode + sample_actions"):
        to_lerobot_bf16(policy)
        record["lerobot_bf16_param_dtypes"] = {
            str(dt): int(sum(p.numel() for p in policy.parameters() if p.dtype == dt))
            for dt in {p.dtype for p in policy.parameters()}}
        ref["bfloat16"] = run_lerobot(policy, inp, args.device)
    if args.device.startswith("cuda"):
        record["torch_peak_bytes"] = int(torch.cuda.max_memory_allocated())
    del policy
    gc.collect()
    if args.device.startswith("cuda"):
        torch.cuda.empty_cache()
    valid = ref["float32"]["prefix_pad_masks"]
    assert valid.sum() == sum(CAMERA_MASK) * 256 + args.prompt_len, valid.sum()

    # 3. Conversions.
    with phase("wait for / run conversions"):
        if args.serial_convert:
            t_conv = time.perf_counter()
            for d in dsts:
                proc = start_conversion(src, dsts[d], d, logs[d])
                wait_conversion(proc, logs[d], d)
        else:
            for d, proc in procs.items():
                wait_conversion(proc, logs[d], d)
        record["conversion_wall_s"] = round(time.perf_counter() - t_conv, 1)
        for d in dsts:
            shutil.copyfile(logs[d], args.out / logs[d].name)
    if not args.keep:
        shutil.rmtree(src)

    # 4. pi0-jax.
    import jax

    jax.config.update("jax_default_matmul_precision", "highest")
    record["environment"]["jax_devices"] = [f"{d.platform}:{d.device_kind}" for d in jax.devices()]
    ours, jax_info = {}, {}
    for d in dsts:
        with phase(f"pi0-jax {d}: load + prefix + sample_actions"):
            ours[d], jax_info[d] = run_jax(dsts[d], inp, args.num_steps)
        np.testing.assert_array_equal(ours[d]["prefix_pad_masks"], valid)
        if not args.keep:
            shutil.rmtree(dsts[d])
    record["jax"] = jax_info
    record["lerobot_dtypes"] = {d: ref[d]["dtypes"] for d in ref}

    # 5. Compare.
    results = {
        "fp32: pi0-jax fp32 vs LeRobot fp32": compare(ours["float32"], ref["float32"], valid),
        "bf16: pi0-jax bf16 vs LeRobot bf16": compare(ours["bfloat16"], ref["bfloat16"], valid),
        "bf16 error: pi0-jax bf16 vs LeRobot fp32": compare(ours["bfloat16"], ref["float32"], valid),
        "bf16 error (context): LeRobot bf16 vs LeRobot fp32": compare(ref["bfloat16"], ref["float32"], valid),
    }
    record["results"] = results
    record["phase_seconds"] = TIMES
    record["total_seconds"] = round(time.perf_counter() - T0, 1)
    (args.out / "parity.json").write_text(json.dumps(record, indent=1) + "\n")
    np.savez_compressed(args.out / "actions.npz", noise=inp["noise"], tokens=inp["tokens"],
                        **{f"lerobot_{d}": ref[d]["actions"] for d in ref},
                        **{f"pi0jax_{d}": ours[d]["actions"] for d in ours})
    md = table(results)
    (args.out / "parity.md").write_text(md + "\n")
    print("\nphase seconds:", json.dumps(TIMES), f"total {record['total_seconds']}s")
    print(f"\n## {args.preset} parity, {record['environment'].get('torch_device_name', args.device)}\n")
    print(md)
    bad = [f"{c} / {q}" for c, qs in results.items() for q, m in qs.items() if not m["finite"]]
    if bad:
        print("NON-FINITE:", bad)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
