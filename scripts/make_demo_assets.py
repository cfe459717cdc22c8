"""Regenerate the embedded demo model under pi0_jax/assets/demo/ (what `pi0-jax demo` converts and runs).

Until a trained policy exists, the demo model is the tiny random-weight π0.5 that LeRobot itself saved for the parity
fixtures (tests/fixtures/lerobot_pi05, written by scripts/make_lerobot_fixtures.py), plus a small SentencePiece
tokenizer trained here on LIBERO-style instructions (deterministic: one thread, fixed corpus).

    python scripts/make_demo_assets.py            # after scripts/make_lerobot_fixtures.py
"""

from __future__ import annotations

import argparse
import io
import shutil
from pathlib import Path

import sentencepiece

ROOT = Path(__file__).resolve().parents[1]
FILES = ("config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json")

INSTRUCTIONS = [
    "pick up the black bowl between the plate and the ramekin and place it on the plate",
    "pick up the black bowl next to the cookie box and place it on the plate",
    "pick up the alphabet soup and place it in the basket",
    "put both the alphabet soup and the tomato sauce in the basket",
    "open the top drawer and put the bowl inside",
    "put the bowl on top of the cabinet",
    "turn on the stove and put the moka pot on it",
    "push the plate to the front of the stove",
    "pick up the red block next to the bowl and place it on the plate",
    "stack the green block on the blue block",
    "Task: put the cream cheese in the bowl, State: 12 255 0 128 7 64 200 3;\nAction: ",
    "0123456789 ,;:. _-",
]


def train_tokenizer(vocab_size: int = 320) -> bytes:
    """A PaliGemma-shaped SentencePiece model: pad 0, eos 1, bos 2, "\\n" one piece, digits split, byte fallback."""
    buf = io.BytesIO()
    sentencepiece.SentencePieceTrainer.train(
        sentence_iterator=iter(INSTRUCTIONS * 8), model_writer=buf, vocab_size=vocab_size, hard_vocab_limit=False,
        model_type="bpe", byte_fallback=True, split_digits=True, user_defined_symbols=["\n"],
        normalization_rule_name="identity", add_dummy_prefix=False, remove_extra_whitespaces=False,
        pad_id=0, eos_id=1, bos_id=2, unk_id=3, num_threads=1, minloglevel=2)
    return buf.getvalue()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--fixture", type=Path, default=ROOT / "tests/fixtures/lerobot_pi05",
                   help="LeRobot-saved tiny π0.5 checkpoint to embed (default: %(default)s)")
    p.add_argument("--out", type=Path, default=ROOT / "pi0_jax/assets/demo", help="default: %(default)s")
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for name in FILES:
        shutil.copyfile(args.fixture / name, args.out / name)
    for stats in args.fixture.glob("policy_*processor_step_*.safetensors"):
        shutil.copyfile(stats, args.out / stats.name)
    (args.out / "tokenizer.model").write_bytes(train_tokenizer())
    print(f"wrote {sorted(p.name for p in args.out.iterdir())} to {args.out}")


if __name__ == "__main__":
    main()
