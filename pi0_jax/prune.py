"""`pi0-jax prune SRC DST --drop-layers 1,2`: a checkpoint without some transformer layers.

π0's two Gemma experts are one stack: layer i of the action expert attends to the prefix K/V that layer i of the VLM
wrote (joint attention), and the param tree holds both as one scanned subtree (`PaliGemma/llm/layers/*`, `*_1` the
expert) whose leaves have a leading layer axis. So a layer is dropped from both towers at once; the config requires
equal depths, and dropping a VLM layer alone (or an expert layer alone) is not a model this architecture has. SigLIP,
the embeddings and the projections are kept whole. The slicing is distillation's (`train.distill.slice_layers`,
`student_config`: the `<variant>_<n>l` Gemma variants of pi0_jax/config.py).

DST is written atomically (`checkpoint.save_checkpoint`) with SRC's dtype, its tokenizer.model and every file under
assets/ (norm stats) copied, and config.json recording the source, the dropped and kept layers and SRC's num_steps.
Dropping no layers writes the same model (the same actions, bit for bit). A short recovery fine-tune is
`pi0-jax distill` (its --layers keeps evenly spaced layers, the first and last included: for the 4-layer pi0_small,
--layers 2 keeps 0 and 3 = --drop-layers 1,2); distilling into arbitrary kept layers is not wired up.
"""

from __future__ import annotations

import argparse
from pathlib import Path

DESCRIPTION = __doc__


def parse_layers(spec: str | None) -> tuple[int, ...]:
    """"1,2" -> (1, 2); "" / "none" / None -> ()."""
    if spec is None or spec.strip().lower() in ("", "none"):
        return ()
    out = tuple(sorted({int(x) for x in spec.split(",") if x.strip()}))
    return out


def prune(src: str | Path, dst: str | Path, drop: tuple[int, ...], *, overwrite: bool = False) -> Path:
    """Write DST = SRC without layers `drop` (indices into SRC's depth) of both Gemma towers. -> DST."""
    from pi0_jax import checkpoint
    from pi0_jax.train.distill import slice_layers, student_config

    src = Path(src)
    meta = checkpoint.read_meta(src)
    if "quant" in meta:
        raise ValueError(f"{src} is quantised: prune the full-precision checkpoint, then quantise")
    config, params = checkpoint.load_checkpoint(src)
    depth = config.paligemma.depth
    bad = [i for i in drop if not 0 <= i < depth]
    if bad:
        raise ValueError(f"--drop-layers {list(bad)}: {config.name} has layers 0..{depth - 1}")
    keep = tuple(i for i in range(depth) if i not in drop)
    if not keep:
        raise ValueError("cannot drop every layer")
    pruned = student_config(config, len(keep)) if drop else config
    if drop:
        pruned = pruned.replace(name=f"{config.name}_drop{'-'.join(map(str, drop))}")
        params = slice_layers(params, keep)
    assets = {}
    if (src / "tokenizer.model").is_file():
        assets["tokenizer.model"] = src / "tokenizer.model"
    for f in sorted((src / "assets").rglob("*")) if (src / "assets").is_dir() else ():
        if f.is_file():
            assets[str(f.relative_to(src))] = f
    extra = {k: v for k, v in meta.items() if k not in ("format", "format_version", "model", "params_dtype")}
    extra["pruned"] = {"source": str(src.absolute()), "source_model": config.name, "dropped_layers": list(drop),
                       "kept_layers": list(keep), "source_depth": depth}
    return checkpoint.save_checkpoint(dst, params, pruned, assets=assets, extra_meta=extra, overwrite=overwrite)


def add_prune_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("prune", help="drop transformer layers from a checkpoint (both Gemma towers)",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("src", type=Path, metavar="SRC", help="a pi0-jax checkpoint directory")
    p.add_argument("dst", type=Path, metavar="DST", help="the output checkpoint directory (written atomically)")
    p.add_argument("--drop-layers", required=True, metavar="I,J,..",
                   help="comma list of layer indices (0-based) to drop from both the VLM and the action expert; "
                        "'none' drops nothing (a copy)")
    p.add_argument("--overwrite", action="store_true", help="replace DST if it exists")
    p.set_defaults(func=_run)
    return p


def _run(args: argparse.Namespace) -> int:
    from pi0_jax import checkpoint
    from pi0_jax.config import Pi0Config

    out = prune(args.src, args.dst, parse_layers(args.drop_layers), overwrite=args.overwrite)
    meta = checkpoint.read_meta(out)
    cfg = Pi0Config.from_json(meta["model"])
    print(f"wrote {out}: {cfg.name}, {cfg.paligemma.depth} layers (kept {meta['pruned']['kept_layers']} of "
          f"{meta['pruned']['source_depth']})")
    return 0
