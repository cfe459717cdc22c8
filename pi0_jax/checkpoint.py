"""Checkpoints: our converted format and openpi's orbax `params/` directory (the same param tree).

Layout of a pi0-jax checkpoint directory:
  config.json     {"format": "pi0-jax", "format_version": 1, "model": Pi0Config fields, "params_dtype": ..., ...}
  params/         orbax PyTree checkpoint {"params": tree}: the layout openpi writes, so each side reads the other
  assets/         norm stats (openpi norm_stats.json and/or LeRobot processor files), carried over verbatim
  tokenizer.model optional SentencePiece model

Every write goes to a temp directory beside the destination and is renamed into place, so a failure leaves nothing.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp
from flax import traverse_util

from pi0_jax import pi0
from pi0_jax.config import PRESETS, Pi0Config

FORMAT = "pi0-jax"
FORMAT_VERSION = 1


@contextlib.contextmanager
def atomic_directory(dst: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temp dir beside `dst`; on success rename it to `dst`, on any error remove it.

    With overwrite, an existing `dst` is moved aside first and only deleted once the new one is in place.
    """
    dst = Path(dst).absolute()
    if dst.exists() and not overwrite:
        raise FileExistsError(f"destination {dst} already exists (pass overwrite / --overwrite to replace it)")
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.tmp-", dir=dst.parent))
    umask = os.umask(0)
    os.umask(umask)
    tmp.chmod(0o777 & ~umask)  # mkdtemp makes it 0700; the checkpoint should be as readable as any new directory
    try:
        yield tmp
        old = None
        if dst.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{dst.name}.old-", dir=dst.parent))
            os.replace(dst, old / "x")
        os.replace(tmp, dst)
        if old is not None:
            shutil.rmtree(old)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def save_params(path: str | os.PathLike, params: Mapping) -> None:
    """Write an orbax PyTree checkpoint {"params": params} at `path` (which must not exist)."""
    params = jax.tree.map(lambda x: x if isinstance(x, (np.ndarray, jax.Array)) else np.asarray(x), dict(params))
    with ocp.PyTreeCheckpointer() as ckptr:
        ckptr.save(Path(path).absolute(), {"params": params})


def restore_params(path: str | os.PathLike, *, dtype: str | None = None) -> dict:
    """Read an orbax `params/` directory (ours or openpi's) as a nested dict of numpy arrays.

    Training-saved openpi checkpoints wrap every leaf in a trailing `value` key; it is stripped.
    """
    path = Path(path).absolute()
    if not path.is_dir():
        raise FileNotFoundError(f"no orbax params directory at {path}")
    with ocp.PyTreeCheckpointer() as ckptr:
        meta = ckptr.metadata(path)
        tree = meta.item_metadata.tree if hasattr(meta, "item_metadata") else meta
        if "params" not in tree:
            raise ValueError(f"{path} holds no top-level 'params' key (found {sorted(tree)})")
        item = {"params": tree["params"]}
        restore_args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray, dtype=dtype), item)
        params = ckptr.restore(path, args=ocp.args.PyTreeRestore(item=item, restore_args=restore_args))["params"]
    flat = traverse_util.flatten_dict(params)
    if flat and all(k[-1] == "value" for k in flat):
        flat = {k[:-1]: v for k, v in flat.items()}
    return traverse_util.unflatten_dict(flat)


def _shape(x) -> tuple:
    return tuple(x.shape) if hasattr(x, "shape") else np.shape(x)  # also a quantised leaf (quant.QArray)


def check_params(config: Pi0Config, params: Mapping) -> None:
    """Raise a ValueError naming every missing, unexpected or mis-shaped leaf."""
    want = traverse_util.flatten_dict(pi0.param_shapes(config), sep="/")
    have = traverse_util.flatten_dict(dict(params), sep="/")
    problems = [f"missing {k} {want[k].shape}" for k in sorted(set(want) - set(have))]
    problems += [f"unexpected {k} {_shape(have[k])}" for k in sorted(set(have) - set(want))]
    problems += [
        f"shape of {k}: {_shape(have[k])}, expected {want[k].shape}"
        for k in sorted(set(want) & set(have)) if tuple(_shape(have[k])) != tuple(want[k].shape)
    ]
    if problems:
        raise ValueError(f"params do not match preset {config.name!r}:\n  " + "\n  ".join(problems))


def save_checkpoint(
    dst: str | os.PathLike,
    params: Mapping,
    config: Pi0Config,
    *,
    assets: Mapping[str, bytes | str | os.PathLike] | None = None,
    extra_meta: Mapping[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a pi0-jax checkpoint atomically. `assets` maps relative paths under assets/ (or `tokenizer.model`)
    to file contents (bytes) or source files. Quantised leaves (`pi0_jax.ops.formats.QArray`) are stored as their
    fields, described under the metadata's "quant" key."""
    from pi0_jax.ops import formats as quant_schemes

    check_params(config, params)
    leaves = jax.tree.leaves(dict(params), is_leaf=lambda x: isinstance(x, quant_schemes.QArray))
    dtypes = sorted({str(np.dtype(x.dtype)) for x in leaves if not isinstance(x, quant_schemes.QArray)})
    params, qleaves = quant_schemes.to_storage(dict(params))
    if qleaves:
        extra_meta = {**(extra_meta or {}), "quant": {**dict((extra_meta or {}).get("quant", {})), "leaves": qleaves}}
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "model": config.to_json(),
        "params_dtype": dtypes[0] if len(dtypes) == 1 else dtypes,
        **(extra_meta or {}),
    }
    with atomic_directory(dst, overwrite=overwrite) as tmp:
        save_params(tmp / "params", params)
        for rel, content in (assets or {}).items():
            rel_path = Path(rel)
            if rel_path.is_absolute() or ".." in rel_path.parts:
                raise ValueError(f"asset path {rel!r} must be relative and inside the checkpoint")
            target = tmp / (rel_path if rel_path.parts[0] in ("assets", "tokenizer.model") else "assets" / rel_path)
            target.parent.mkdir(parents=True, exist_ok=True)
            if isinstance(content, bytes):
                target.write_bytes(content)
            else:
                shutil.copyfile(content, target)
        (tmp / "config.json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
    return Path(dst)


def read_meta(path: str | os.PathLike) -> dict:
    cfg_path = Path(path) / "config.json"
    if not cfg_path.is_file():
        raise FileNotFoundError(f"{cfg_path} not found: not a pi0-jax checkpoint (convert one with `pi0-jax convert`)")
    meta = json.loads(cfg_path.read_text())
    if meta.get("format") != FORMAT:
        raise ValueError(f"{cfg_path} is not a pi0-jax config (format={meta.get('format')!r})")
    return meta


def load_checkpoint(path: str | os.PathLike, *, dtype: str | None = None) -> tuple[Pi0Config, dict]:
    """Load (config, params) from a pi0-jax checkpoint directory; `dtype` casts the params on read."""
    meta = read_meta(path)
    config = Pi0Config.from_json(meta["model"])
    if "quant" not in meta:
        params = restore_params(Path(path) / "params", dtype=dtype)
    else:  # quantised leaves keep their storage dtypes; the rest is cast
        from pi0_jax.ops import formats as quant_schemes

        params = restore_params(Path(path) / "params")
        if dtype is not None:
            qpaths = tuple(meta["quant"]["leaves"])
            flat = traverse_util.flatten_dict(params, sep="/")
            params = traverse_util.unflatten_dict(
                {k: v if k.rsplit("/", 1)[0] in qpaths else v.astype(dtype) for k, v in flat.items()}, sep="/")
        params = quant_schemes.from_storage(params, meta["quant"]["leaves"])
    check_params(config, params)
    return config, params


def match_preset(params: Mapping, **overrides: Any) -> Pi0Config:
    """The first preset whose param tree has exactly these shapes (openpi params carry no config)."""
    have = {k: tuple(np.shape(v)) for k, v in traverse_util.flatten_dict(dict(params), sep="/").items()}
    for config in PRESETS.values():
        config = config.replace(**overrides)
        want = {k: tuple(v.shape) for k, v in traverse_util.flatten_dict(pi0.param_shapes(config), sep="/").items()}
        if want == have:
            return config
    raise ValueError(f"the params match no preset in {sorted(PRESETS)}; pass the preset explicitly")


def load_openpi_params(path: str | os.PathLike, *, preset: str | None = None, dtype: str | None = None,
                       **overrides: Any) -> tuple[Pi0Config, dict]:
    """Load an openpi JAX checkpoint (`<ckpt>/params` or the `params` dir itself) without conversion."""
    path = Path(path)
    params_dir = path / "params" if (path / "params").is_dir() else path
    params = restore_params(params_dir, dtype=dtype)
    if preset is not None:
        config = PRESETS[preset].replace(**overrides)
    else:
        config = match_preset(params, **overrides)
    check_params(config, params)
    return config, params
