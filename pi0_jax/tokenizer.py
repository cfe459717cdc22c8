"""The PaliGemma SentencePiece tokenizer and the two π0 prompt formats (spec §9).

Formats (openpi `PaligemmaTokenizer.tokenize`; the text is cleaned the same way in both: `strip()`, then
"_" -> " ", then "\\n" -> " "; no lower-casing, unlike openpi's FAST tokenizer):

* π0 format (also π0.5 with `discrete_state_input=False`, e.g. `pi05_libero`):
  `encode(text, add_bos=True) + encode("\\n")`. The "\\n" is encoded on its own as the start-of-answer token
  (one token in the real model, a user-defined piece; believed id 108).
* π0.5 discrete-state format: the *normalised, un-padded* state is binned into 256 bins over [-1, 1],
  `disc = digitize(state, linspace(-1, 1, 257)[:-1]) - 1` (integers in [-1, 255]), and the whole string
  `"Task: {text}, State: {d1 d2 ...};\\nAction: "` is encoded once with BOS (no separate "\\n" encode).

Both are right-padded to `max_len` with the pad id (0 in the real model) and a False mask; longer prompts are
truncated with a logged warning, keeping the first `max_len` tokens (so the trailing "\\n" can be lost).
"""

from __future__ import annotations

import logging
import os

import numpy as np
import sentencepiece

logger = logging.getLogger(__name__)

# 256 bins over [-1, 1]: the left edges of linspace(-1, 1, 257), as openpi writes it.
STATE_BIN_EDGES = np.linspace(-1.0, 1.0, 256 + 1)[:-1]


def clean_text(prompt: str) -> str:
    return prompt.strip().replace("_", " ").replace("\n", " ")


def discretize_state(state: np.ndarray) -> np.ndarray:
    """(..., S) normalised state -> (..., S) int64 bin indices in [-1, 255] (below -1 -> -1; >= 0.9921875 -> 255)."""
    return np.digitize(np.asarray(state, np.float64), STATE_BIN_EDGES) - 1


def state_prompt(prompt: str, state: np.ndarray) -> str:
    """The π0.5 discrete-state prompt string for a 1-D normalised state."""
    state = np.asarray(state)
    if state.ndim != 1:
        raise ValueError(f"state must be 1-D (one observation), got shape {state.shape}")
    disc = " ".join(map(str, discretize_state(state).tolist()))
    return f"Task: {clean_text(prompt)}, State: {disc};\nAction: "


class PaligemmaTokenizer:
    """`tokenize(prompt, state=None) -> (tokens int32 (max_len,), mask bool (max_len,))`.

    `model_path` is a SentencePiece model file (openpi: gs://big_vision/paligemma_tokenizer.model, the same model as
    HF `google/paligemma-3b-pt-224`). Special ids are read from the model, never hard-coded.
    """

    def __init__(self, model_path: str | os.PathLike, max_len: int = 48):
        if not os.path.isfile(model_path):
            raise FileNotFoundError(f"SentencePiece model not found: {os.fspath(model_path)}")
        if max_len <= 0:
            raise ValueError(f"max_len must be positive, got {max_len}")
        self.model_path = os.fspath(model_path)
        self.max_len = max_len
        self._sp = sentencepiece.SentencePieceProcessor(model_file=self.model_path)

    @property
    def bos_id(self) -> int:
        return self._sp.bos_id()

    @property
    def eos_id(self) -> int:
        return self._sp.eos_id()

    @property
    def pad_id(self) -> int:
        # A model trained without a pad piece reports -1; openpi pads with 0 (its pad id) regardless.
        return max(self._sp.pad_id(), 0)

    @property
    def vocab_size(self) -> int:
        return self._sp.vocab_size()

    def encode(self, text: str, *, add_bos: bool = False) -> list[int]:
        return self._sp.encode(text, add_bos=add_bos)

    def decode(self, ids) -> str:
        return self._sp.decode([int(i) for i in ids])

    def prompt_ids(self, prompt: str, state: np.ndarray | None = None) -> list[int]:
        """The unpadded, untruncated token ids of a prompt in the π0 (state None) or π0.5 discrete-state format."""
        if state is not None:
            return self.encode(state_prompt(prompt, state), add_bos=True)
        return self.encode(clean_text(prompt), add_bos=True) + self.encode("\n")

    def tokenize(self, prompt, state: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """-> (tokens (max_len,) int32, mask (max_len,) bool). `prompt`: str, bytes or a 0-d numpy string array."""
        ids = self.prompt_ids(_as_str(prompt), state)
        n = len(ids)
        if n > self.max_len:
            logger.warning("Token length (%d) exceeds max length (%d), truncating. Consider increasing "
                           "max_token_len in the model config if this happens often.", n, self.max_len)
            ids, n = ids[: self.max_len], self.max_len
        tokens = np.full((self.max_len,), self.pad_id, np.int32)
        tokens[:n] = ids
        mask = np.zeros((self.max_len,), bool)
        mask[:n] = True
        return tokens, mask


def _as_str(prompt) -> str:
    # Prompts arrive as str over msgpack, but as 0-d arrays / bytes from datasets (openpi calls `.item()`).
    if isinstance(prompt, np.ndarray):
        prompt = prompt.item()
    if isinstance(prompt, bytes):
        prompt = prompt.decode("utf-8")
    if not isinstance(prompt, str):
        raise TypeError(f"prompt must be a string, got {type(prompt).__name__}")
    return prompt
