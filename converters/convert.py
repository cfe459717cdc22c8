"""`convert(src, dst)`: a PyTorch π0 / π0.5 checkpoint (openpi's PyTorch port or LeRobot) -> a pi0-jax checkpoint.

Order of work, so that bad input fails before anything heavy happens and nothing is ever half-written:
  1. check DST (exists? overlaps SRC?);
  2. read the safetensors headers (no tensor data) and the source config.json;
  3. detect the model (detect.py) and check every key and shape against the table (table.py);
  4. read the tensors one at a time (NaN/Inf checked per tensor), cast, and fill the param tree;
  5. hand the tree, the config and the carried-over assets to `checkpoint.save_checkpoint`, which writes a temp
     directory beside DST and renames it into place.
Peak memory is about one copy of the output params plus one source tensor.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from converters import detect as _detect
from converters import table as _table
from converters.errors import ConversionError
from converters.source import TensorSource

log = logging.getLogger(__name__)

DTYPES = ("bfloat16", "float32")
LEROBOT_PROCESSOR_GLOBS = ("policy_preprocessor*.json", "policy_postprocessor*.json",
                           "policy_preprocessor*.safetensors", "policy_postprocessor*.safetensors")


def convert(src: str | os.PathLike, dst: str | os.PathLike, *, dtype: str = "bfloat16", preset: str | None = None,
            overwrite: bool = False, allow_pickle: bool = False) -> Path:
    """Convert SRC (a directory or file; see `source.locate`) into a pi0-jax checkpoint directory DST.

    dtype: every param is stored in this dtype ("bfloat16" or "float32"); it is also the config's compute dtype.
    preset: a name in `pi0_jax.config.PRESETS` to use instead of detection (it must fit the tensors).
    overwrite: replace an existing DST (only a pi0-jax checkpoint or an empty directory), atomically.
    allow_pickle: accept a torch pickle (.pt/.pth/.bin), read with torch.load(weights_only=True).
    Returns DST. Raises ConversionError naming the key, file or shape at fault; DST is then left untouched.
    """
    if dtype not in DTYPES:
        raise ConversionError(f"dtype must be one of {DTYPES}, got {dtype!r}")
    src, dst = Path(src).expanduser().absolute(), Path(dst).expanduser().absolute()
    _check_destination(src, dst, overwrite)
    src_dir = src if src.is_dir() else src.parent

    with TensorSource(src, allow_pickle=allow_pickle) as source:
        header = {k: e.shape for k, e in source.entries.items()}
        origin = {k: f"{e.raw_key!r} in {e.file.name!r}" for k, e in source.entries.items()}
        src_cfg, cfg_path = _detect.read_source_config(src_dir)
        lerobot = bool(source.had_prefix or (src_cfg is not None and "type" in src_cfg)
                       or any(src_dir.glob("policy_preprocessor*.json")))
        try:
            _refuse_unsupported(src_cfg, cfg_path)
            config, evidence = _detect.detect(header, src_cfg, lerobot=lerobot, dtype=dtype, preset=preset)
            plan = _table.make_plan(config, header, origin)
        except ConversionError as e:  # name the source in every message about its keys and shapes
            raise ConversionError(f"{str(src)!r}: {e}") from e
        for key, reason in sorted(plan.ignored.items()):
            log.info("ignoring %s: %s", key, reason)
        log.info("converting %s (%d tensors) as %s to %s", src, len(header), config.name, dtype)
        out_dtype = _np_dtype(dtype)
        flat = {step.rule.target: _table.run_step(step, source.get, out_dtype) for step in plan.steps}
        source_dtypes = sorted({e.dtype for e in source.entries.values()})
        files = [str(f) for f in source.files]

    assets = collect_assets(src_dir, cfg_path)
    meta: dict[str, Any] = {
        "source": str(src),
        "source_format": "lerobot" if lerobot else "openpi-pytorch",
        "source_files": files,
        "source_dtypes": source_dtypes,
        "source_config": str(cfg_path) if cfg_path else None,
        "detected": evidence,
        "ignored_keys": dict(sorted(plan.ignored.items())),
        "assets": sorted(assets),
    }
    from pi0_jax.checkpoint import save_checkpoint

    try:
        save_checkpoint(dst, _table.unflatten(flat), config, assets=assets, extra_meta=meta, overwrite=overwrite)
    except FileExistsError as e:  # DST appeared while we were converting
        raise ConversionError(f"destination {str(dst)!r} already exists; pass --overwrite to replace it") from e
    log.info("wrote %s", dst)
    return dst


def _np_dtype(name: str) -> np.dtype:
    import ml_dtypes

    return np.dtype(ml_dtypes.bfloat16) if name == "bfloat16" else np.dtype(np.float32)


def _check_destination(src: Path, dst: Path, overwrite: bool) -> None:
    rsrc, rdst = src.resolve(), dst.resolve()
    if rdst == rsrc or rdst in rsrc.parents:
        raise ConversionError(f"destination {str(dst)!r} is the source or contains it; choose another DST")
    if not (dst.exists() or dst.is_symlink()):
        return
    if not overwrite:
        raise ConversionError(f"destination {str(dst)!r} already exists; pass --overwrite to replace it")
    # --overwrite replaces DST wholesale, so only ever replace something this tool could have written.
    is_ours = dst.is_dir() and (not any(dst.iterdir())
                                or ((dst / "config.json").is_file() and (dst / "params").is_dir()))
    if not is_ours:
        raise ConversionError(f"refusing to overwrite {str(dst)!r}: it is not a pi0-jax checkpoint (config.json + "
                              f"params/) or an empty directory")


def _refuse_unsupported(src_cfg, cfg_path) -> None:
    """LeRobot features whose weights the JAX model has no place for: converting would silently change the model."""
    for field in ("use_visual_memory", "use_proprioceptive_memory"):
        if src_cfg and src_cfg.get(field):
            raise ConversionError(f"{str(cfg_path)!r} sets {field}=true, which pi0-jax does not support")


def collect_assets(src_dir: Path, cfg_path: Path | None) -> dict[str, Path]:
    """Files carried over verbatim, as {path inside DST: source file}.

    openpi: `assets/**/norm_stats.json` keeps its relative path. LeRobot: the `policy_{pre,post}processor*` JSON
    and safetensors stats files go to `assets/`. A `tokenizer.model` goes to the checkpoint root, and the source
    config.json to `assets/source_config.json` (LeRobot keeps its normalisation mapping there).
    """
    assets: dict[str, Path] = {}
    if (src_dir / "assets").is_dir():
        for p in sorted((src_dir / "assets").rglob("norm_stats.json")):
            assets[f"assets/{p.relative_to(src_dir / 'assets').as_posix()}"] = p
    for pattern in LEROBOT_PROCESSOR_GLOBS:
        for p in sorted(src_dir.glob(pattern)):
            assets[f"assets/{p.name}"] = p
    if (src_dir / "tokenizer.model").is_file():
        assets["tokenizer.model"] = src_dir / "tokenizer.model"
    if cfg_path is not None:
        assets["assets/source_config.json"] = cfg_path
    return assets


__all__ = ["DTYPES", "collect_assets", "convert"]
