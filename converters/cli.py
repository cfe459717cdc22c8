"""`pi0-jax convert SRC DST`: the argparse front end over `converters.convert`.

`add_convert_parser(subparsers)` is what `pi0_jax/cli.py` wires in; `python -m converters SRC DST` runs it alone.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

DESCRIPTION = """\
Convert a PyTorch π0 / π0.5 checkpoint, written by openpi's PyTorch port or by LeRobot, into a pi0-jax
checkpoint: DST/config.json (model config, dtype, provenance), DST/params/ (orbax, openpi's JAX param tree) and
DST/assets/ (norm stats carried over: openpi assets/**/norm_stats.json, LeRobot policy_*processor* files).

The model (π0 or π0.5, sizes, action horizon, prompt length) is read from SRC/config.json and the tensors
themselves, never from folder names. Every source tensor is used or explicitly ignored (the action expert's
unused lm_head), every shape is checked, and NaN/Inf are refused. DST is written to a temporary directory and
renamed into place, so a failed conversion leaves nothing behind.
"""


def add_convert_parser(subparsers) -> argparse.ArgumentParser:
    """Add the `convert` subcommand to an argparse subparsers object; returns its parser (func=run)."""
    from pi0_jax.config import PRESETS  # light: no jax import

    p = subparsers.add_parser("convert", help="convert a PyTorch (openpi / LeRobot) checkpoint to pi0-jax",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_arguments(p, sorted(PRESETS))
    return p


def _add_arguments(p: argparse.ArgumentParser, presets: list[str]) -> None:
    p.add_argument("src", metavar="SRC", type=Path,
                   help="a directory holding model.safetensors or a sharded model.safetensors.index.json (plus "
                        "config.json and norm stats), or one of those files")
    p.add_argument("dst", metavar="DST", type=Path, help="the pi0-jax checkpoint directory to create")
    p.add_argument("--dtype", choices=("bfloat16", "float32"), default="bfloat16",
                   help="dtype every param is stored in, and the model's compute dtype (default: %(default)s); "
                        "source tensors may be any mix of fp32/bf16/fp16")
    p.add_argument("--preset", choices=presets, default=None, metavar="NAME",
                   help="use this preset instead of detecting one (" + ", ".join(presets) + "); it must fit the "
                        "tensors. Without it, horizon and prompt length come from SRC/config.json")
    p.add_argument("--overwrite", action="store_true",
                   help="replace DST if it exists (only a pi0-jax checkpoint or an empty directory); the old one is "
                        "removed only after the new one is in place")
    p.add_argument("--allow-pickle", action="store_true",
                   help="accept a torch pickle (.pt/.pth/.bin) as SRC. Pickles can run code when loaded, so they "
                        "are refused by default; this needs torch installed and uses torch.load(weights_only=True)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run a parsed `convert` command. Returns the exit status: 0, or 1 with the error on stderr."""
    from converters.convert import convert
    from converters.errors import ConversionError

    # Our progress and "ignoring <key>: <reason>" lines on stderr, without turning on every library's INFO logs.
    log = logging.getLogger("converters")
    if not log.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        log.addHandler(handler)
        log.setLevel(logging.INFO)
        log.propagate = False
    try:
        dst = convert(args.src, args.dst, dtype=args.dtype, preset=args.preset, overwrite=args.overwrite,
                      allow_pickle=args.allow_pickle)
    except ConversionError as e:
        print(f"pi0-jax convert: error: {e}", file=sys.stderr)
        return 1
    print(f"wrote {dst}")
    return 0


def main(argv: list[str] | None = None) -> int:
    from pi0_jax.config import PRESETS

    parser = argparse.ArgumentParser(prog="python -m converters", description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_arguments(parser, sorted(PRESETS))
    args = parser.parse_args(argv)
    return args.func(args)
