"""Accuracy of the quantisation schemes against the unquantised model, measured on the compiled engine's stages.

Per scheme: SigLIP output tokens (vision), prefix K/V per layer (prefix), actions with fixed noise (denoise), each as
cosine similarity against the unquantised model on the same realistic inputs; actions also as max abs error.
Stages are compiled once per distinct stage program: a scheme reuses the program (and the calibrated weights) of
the scheme that quantises the same GEMMs in that stage, e.g. `all` runs vision of `vision`, prefix of `prefix-all`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from pi0_jax.config import Pi0Config
from pi0_jax.quant import schemes as sch

STAGES = ("encode_images", "fill_prefix_cache", "denoise")
FP4_FORMATS = ("nvfp4", "mxfp4")
FP8_BAR = 0.999


def canonical(scheme: str, stage: str) -> str:
    """The scheme whose weights and program stand for `scheme` in `stage` ("bf16": nothing quantised there)."""
    groups = set(sch.SCHEMES[scheme]) if scheme in sch.SCHEMES else set()
    if stage == "encode_images":
        return "vision" if "vision" in groups else "bf16"
    if stage == "fill_prefix_cache":
        return "prefix-all" if "prefix-attn" in groups else ("prefix-mlp" if "prefix-mlp" in groups else "bf16")
    if "expert-act" in groups:
        return "every-gemm"
    return "expert-weights" if "expert" in groups else "bf16"


class Variants:
    """Engines per (canonical scheme, calibration method) and executables shared by stage program.

    FP4 variants ("nvfp4", "mxfp4") are dequantised weights: they run the unquantised programs."""

    def __init__(self, config: Pi0Config, params: dict, stats: dict | None, *, per_channel: bool = True):
        self.config, self.params, self.stats, self.per_channel = config, params, stats, per_channel
        self.engines: dict[tuple[str, str], object] = {}
        self.executables: dict[tuple, object] = {}

    def engine(self, name: str, method: str = "amax"):
        from pi0_jax.engine import Engine

        key = (name, method if name in sch.SCHEMES else "-")
        if key not in self.engines:
            if name in sch.SCHEMES:
                params = sch.quantize_params(self.params, name, (self.stats or {}).get(method),
                                             per_channel=self.per_channel)
            elif name in FP4_FORMATS:
                params = sch.fake_quant_fp4_params(self.params, name, "all")
            else:
                params = self.params
            self.engines[key] = Engine(self.config, params, kernels="xla", cache_dir=False)   # one cache layout
        return self.engines[key]

    def drop(self, name: str | None = None) -> None:
        """Free engines (`name`, or every one but bf16's); compiled programs are kept, so a rebuilt engine (same
        weights, quantised again) reuses them."""
        for key in [k for k in self.engines if (k[0] == name if name else k[0] != "bf16")]:
            del self.engines[key]

    def stage(self, scheme: str, stage: str, batch: int, steps: int, cameras, bucket, method: str = "amax"):
        """(compiled program, engine whose weights it takes) of `scheme` in `stage`."""
        name = canonical(scheme, stage) if scheme not in FP4_FORMATS else scheme
        engine = self.engine(name, method)
        prog = name if name not in FP4_FORMATS else "bf16"
        key = (prog, stage, batch, steps if stage == "denoise" else 0, tuple(cameras), bucket)
        if key not in self.executables:
            self.executables[key] = engine.executable(stage, batch, steps, cameras, bucket)
        return self.executables[key], engine

    def run(self, scheme: str, obs, noise, steps: int, method: str = "amax") -> dict:
        """The three stages chained for one observation batch -> numpy outputs."""
        base = self.engine("bf16")
        cameras, bucket = base.plan(obs)
        images, image_masks, tokens, token_mask, state = base.pack(obs, cameras, bucket)
        b = noise.shape[0]
        enc, e1 = self.stage(scheme, "encode_images", b, steps, cameras, bucket, method)
        pre, e2 = self.stage(scheme, "fill_prefix_cache", b, steps, cameras, bucket, method)
        den, e3 = self.stage(scheme, "denoise", b, steps, cameras, bucket, method)
        image_tokens = enc(e1.weights, images)
        cache = pre(e2.weights, image_tokens, image_masks, tokens, token_mask)
        actions = den(e3.weights, e3.schedule(steps), cache, state, jnp.array(noise, jnp.float32, copy=True))
        f64 = lambda x: np.asarray(x).astype(np.float64)  # noqa: E731  (on the host: no device copies)
        return {"vision": f64(image_tokens), "k": [f64(k) for k in cache.k], "v": [f64(v) for v in cache.v],
                "mask": np.asarray(cache.mask), "actions": f64(actions)}


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.ravel(a), np.ravel(b)
    denom = np.linalg.norm(a) * np.linalg.norm(b)
    return float(a @ b / denom) if denom > 0 else float(np.array_equal(a, b))


def compare(base: dict, out: dict) -> dict:
    """Metrics of `out` against `base` (both `Variants.run` outputs); K/V over valid prefix tokens only."""
    m = base["mask"]
    k_cos = [cosine(a[m], b[m]) for a, b in zip(base["k"], out["k"])]
    v_cos = [cosine(a[m], b[m]) for a, b in zip(base["v"], out["v"])]
    kv = np.minimum(k_cos, v_cos)
    return {"vision_cos": cosine(base["vision"], out["vision"]),
            "kv_cos_min": float(kv.min()), "kv_cos_mean": float(np.mean(k_cos + v_cos)),
            "kv_min_layer": int(kv.argmin()), "k_cos_per_layer": k_cos, "v_cos_per_layer": v_cos,
            "action_cos": cosine(base["actions"], out["actions"]),
            "action_max_abs": float(np.abs(base["actions"] - out["actions"]).max())}


def _mean_metrics(rows: list[dict]) -> dict:
    """Several evaluation batches: the worst cosine and the largest error over them (per layer likewise)."""
    out = {}
    for k, v in rows[0].items():
        if k.endswith("per_layer"):
            out[k] = np.min([r[k] for r in rows], axis=0).tolist()
        elif k == "kv_cos_mean":
            out[k] = float(np.mean([r[k] for r in rows]))
        elif k == "kv_min_layer":
            out[k] = rows[int(np.argmin([r["kv_cos_min"] for r in rows]))][k]
        else:
            out[k] = float(np.max([r[k] for r in rows]) if "abs" in k else np.min([r[k] for r in rows]))
    return out


def accuracy(variants: Variants, eval_set, steps: int, schemes=tuple(sch.SCHEMES), fp4=FP4_FORMATS,
             methods=("amax",)) -> list[dict]:
    """Rows {scheme, method, metrics...} over `eval_set` [(obs, noise)]; FP8 rows carry `pass` (K/V >= 0.999)."""
    base = [variants.run("bf16", obs, noise, steps) for obs, noise in eval_set]
    rows = []
    for scheme in schemes:
        for method in methods if set(sch.SCHEMES[scheme]) - sch.WEIGHT_ONLY else methods[:1]:
            outs = [variants.run(scheme, obs, noise, steps, method) for obs, noise in eval_set]
            m = _mean_metrics([compare(b, o) for b, o in zip(base, outs)])
            rows.append({"scheme": scheme, "format": "fp8_e4m3", "method": method, **m,
                         "pass": m["kv_cos_min"] >= FP8_BAR if canonical(scheme, "fill_prefix_cache") != "bf16"
                         or canonical(scheme, "encode_images") != "bf16" else None})
            variants.drop()  # bounded device memory at full size
    for fmt in fp4:
        outs = [variants.run(fmt, obs, noise, steps) for obs, noise in eval_set]
        rows.append({"scheme": "all (weights)", "format": fmt, "method": "-",
                     **_mean_metrics([compare(b, o) for b, o in zip(base, outs)]), "pass": None})
        variants.drop(fmt)
    return rows


def eval_set(config: Pi0Config, n: int, batch: int, seed: int, tokenizer=None):
    obs = sch.sample_observations(config, n, seed=seed, batch=batch, tokenizer=tokenizer)
    rng = np.random.default_rng(seed + 1)
    return [(o, jnp.asarray(rng.normal(size=(batch, config.action_horizon, config.action_dim)), jnp.float32))
            for o in obs]


def demo_tokenizer(config: Pi0Config):
    """A SentencePiece model packaged under pi0_jax/assets (real prompt tokens; ids above the vocab are clipped by
    the caller), or None: prompts are then random ids."""
    from pi0_jax.tokenizer import PaligemmaTokenizer

    found = sorted((Path(__file__).parents[1] / "assets").rglob("tokenizer.model"))
    return PaligemmaTokenizer(str(found[0]), config.max_token_len) if found else None


TABLE_HEADER = ("| scheme | format | calib | vision cos | K/V cos min (layer) | K/V cos mean | action cos | "
                "action max abs | K/V >= 0.999 |\n|---|---|---|---|---|---|---|---|---|")


def row_line(r: dict) -> str:
    ok = {True: "yes", False: "**no**", None: "-"}[r["pass"]]
    return (f"| {r['scheme']} | {r['format']} | {r['method']} | {r['vision_cos']:.6f} | {r['kv_cos_min']:.6f} "
            f"({r['kv_min_layer']}) | {r['kv_cos_mean']:.6f} | {r['action_cos']:.6f} | {r['action_max_abs']:.4f} "
            f"| {ok} |")


def markdown(rows: list[dict], title: str = "") -> str:
    return "\n".join(([title, ""] if title else []) + [TABLE_HEADER] + [row_line(r) for r in rows])


# -- CLI: pi0-jax quantize ------------------------------------------------------------------------------------------
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("src", help="a pi0-jax checkpoint directory, or preset:NAME for random weights of a preset")
    p.add_argument("dst", type=Path, help="the quantised checkpoint directory to write (atomically)")
    p.add_argument("--scheme", required=True, choices=sorted(sch.SCHEMES),
                   help="which GEMMs become FP8: prefix-mlp (VLM MLPs of the prefix), prefix-all (VLM q/k/v/o + "
                        "MLP), vision (SigLIP), prefix-vision (both), expert-weights (action expert, weight-only), all "
                        "(all four), every-gemm (prefix, SigLIP and the action expert, all FP8 x FP8: large batches)")
    p.add_argument("--calib-samples", type=int, default=8,
                   help="calibration observations (realistic synthetic inputs, fixed seed) (default: %(default)s)")
    p.add_argument("--calib-method", choices=["amax", "percentile"], default="amax",
                   help="static activation scale from the max |x| or a percentile of |x| (default: %(default)s)")
    p.add_argument("--percentile", type=float, default=99.99,
                   help="the percentile of |x| for --calib-method percentile (default: %(default)s)")
    p.add_argument("--per-tensor", action="store_true",
                   help="one weight scale per tensor (per layer) instead of one per output channel")
    p.add_argument("--dtype", default=None, help="cast the unquantised params to this dtype (default: as stored)")
    p.add_argument("--report", type=Path, default=None,
                   help="also write an accuracy report (JSON, and .md beside it): every scheme and FP4 emulation "
                        "vs the unquantised model on realistic inputs with fixed noise")
    p.add_argument("--eval-batches", type=int, default=2, help="report: evaluation batches (default: %(default)s)")
    p.add_argument("--eval-batch", type=int, default=2, help="report: batch size (default: %(default)s)")
    p.add_argument("--steps", type=int, default=10, help="report: denoise steps (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of random weights and inputs")
    p.add_argument("--overwrite", action="store_true", help="replace an existing DST")


def _load(src: str, dtype: str | None, seed: int):
    from pi0_jax import benchmark, checkpoint
    from pi0_jax.config import get_config

    if src.startswith("preset:"):
        config = get_config(src.split(":", 1)[1], **({"dtype": dtype} if dtype else {}))
        return config, benchmark.random_params(config, seed), {}
    config, params = checkpoint.load_checkpoint(src, dtype=dtype)
    if dtype:
        config = config.replace(dtype=dtype)
    root = Path(src)
    assets = {str(f.relative_to(root)): f for f in (root / "assets").rglob("*") if f.is_file()}
    if (root / "tokenizer.model").is_file():
        assets["tokenizer.model"] = root / "tokenizer.model"
    return config, params, assets


def main(args: argparse.Namespace) -> int:
    from pi0_jax import checkpoint

    config, params, assets = _load(args.src, args.dtype, args.seed)
    tok = demo_tokenizer(config)
    calib = sch.sample_observations(config, args.calib_samples, seed=args.seed + 1000, tokenizer=tok)
    stats = sch.calibrate(config, params, calib, percentile=args.percentile, num_steps=args.steps)
    qparams = sch.quantize_params(params, args.scheme, stats[args.calib_method], per_channel=not args.per_tensor)
    meta = {"quant": {"scheme": args.scheme, "calib_method": args.calib_method, "calib_samples": args.calib_samples,
                      "percentile": args.percentile, "per_channel": not args.per_tensor}}
    checkpoint.save_checkpoint(args.dst, qparams, config, assets=assets, extra_meta=meta, overwrite=args.overwrite)
    print(f"wrote {args.dst}: {len(sch.quantized_paths(qparams))} FP8 weight tensors ({args.scheme})")
    if args.report is not None:
        variants = Variants(config, params, stats, per_channel=not args.per_tensor)
        data = eval_set(config, args.eval_batches, args.eval_batch, args.seed + 2000, tok)
        rows = accuracy(variants, data, args.steps, methods=("amax", "percentile"))
        report = {"preset": config.name, "dtype": config.dtype, "steps": args.steps, "rows": rows,
                  "calib_samples": args.calib_samples, "percentile": args.percentile}
        args.report.parent.mkdir(parents=True, exist_ok=True)
        args.report.write_text(json.dumps(report, indent=2) + "\n")
        md = markdown(rows, f"{config.name} ({config.dtype}), {args.steps} steps, vs unquantised")
        args.report.with_suffix(".md").write_text(md + "\n")
        print("\n" + md)
    return 0
