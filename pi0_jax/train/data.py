"""Demonstrations -> host arrays, norm stats and the suite's tokenizer (what the jitted train step reads).

A demos directory is what `pi0_jax.sim.demos.write_demos` writes (meta.json + episode_*.npz). All episodes are
concatenated frame by frame into one `Dataset` (F frames):

  images   (F, 2, H, W, 3) uint8   camera 0 = agent view -> `base_0_rgb`, camera 1 = wrist -> `left_wrist_0_rgb`
  state    (F, 8) float32          raw (un-normalised) LIBERO state
  actions  (F, 7) float32          raw action taken at the frame
  end      (F,) int32              index one past the frame's episode's last frame: the action chunk of frame t is
                                   actions[min(t + k, end - 1)] for k < horizon (LeRobot repeats the last action
                                   past the episode end)
  task     (F,) int32              row of the prompt in `tokens` / `masks`
  tokens, masks  (P, L)            the tokenised prompts (π0 format), one row per prompt

The tokenizer is trained on the suite's instructions (`pi0_jax.sim.tasks.TASKS`), so it is a function of the suite
alone, not of which tasks a demos directory happens to hold.
"""

from __future__ import annotations

import dataclasses
import io
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import sentencepiece

from pi0_jax import normalize as nz
from pi0_jax.sim import tasks as _tasks   # also sets XLA:CPU flags (pi0_jax.sim) before a backend starts
from pi0_jax.tokenizer import PaligemmaTokenizer, clean_text

CAMERAS = ("agentview", "wrist")          # npz keys, in model slot order (base_0_rgb, left_wrist_0_rgb)


@dataclasses.dataclass(frozen=True)
class Dataset:
    images: np.ndarray
    state: np.ndarray
    actions: np.ndarray
    end: np.ndarray
    task: np.ndarray
    tokens: np.ndarray
    masks: np.ndarray
    prompts: tuple[str, ...]
    num_episodes: int

    @property
    def num_frames(self) -> int:
        return self.state.shape[0]

    @property
    def resolution(self) -> int:
        return self.images.shape[2]


# ---------------------------------------------------------------------------------------------------------------------
# Tokenizer.


def suite_prompts() -> tuple[str, ...]:
    return tuple(t.prompt for t in _tasks.TASKS)


def train_tokenizer(prompts: Sequence[str], vocab_size: int = 128) -> bytes:
    """A small SentencePiece model over `prompts`, PaliGemma-shaped: pad 0, eos 1, bos 2, unk 3, "\\n" one
    user-defined piece, identity normalisation, no dummy prefix. No byte fallback (it alone would take 256 ids), so
    the vocabulary stays <= vocab_size; text outside the prompts' characters maps to unk. Deterministic (one
    thread, fixed corpus order); `hard_vocab_limit=False` lets a small corpus yield fewer pieces."""
    corpus = sorted({clean_text(p) for p in prompts})
    buf = io.BytesIO()
    sentencepiece.SentencePieceTrainer.train(
        sentence_iterator=iter(corpus * 4), model_writer=buf, vocab_size=vocab_size, hard_vocab_limit=False,
        model_type="bpe", byte_fallback=False, user_defined_symbols=["\n"], character_coverage=1.0,
        normalization_rule_name="identity", add_dummy_prefix=False, remove_extra_whitespaces=False,
        pad_id=0, eos_id=1, bos_id=2, unk_id=3, num_threads=1, minloglevel=2)
    return buf.getvalue()


def tokenize_prompts(tokenizer_path: str | Path, prompts: Sequence[str], max_len: int) -> tuple[np.ndarray, np.ndarray]:
    """(P, max_len) int32 tokens and bool masks; raises if a prompt is truncated or holds an unknown piece."""
    tok = PaligemmaTokenizer(tokenizer_path, max_len)
    unk = tok._sp.unk_id()
    for p in prompts:
        ids = tok.prompt_ids(p)
        if len(ids) > max_len:
            raise ValueError(f"prompt {p!r} is {len(ids)} tokens, more than max_token_len {max_len}")
        if unk in ids:
            raise ValueError(f"prompt {p!r} holds pieces the tokenizer does not know: {tok._sp.encode(p, out_type=str)}")
    tokens, masks = zip(*(tok.tokenize(p) for p in prompts))
    return np.stack(tokens), np.stack(masks)


# ---------------------------------------------------------------------------------------------------------------------
# Episodes.


def load_demos(demos_dir: str | Path, prompts: Sequence[str], tokenizer_path: str | Path, max_token_len: int,
               *, max_episodes: int | None = None, log=print) -> Dataset:
    """Read every episode listed in `demos_dir/meta.json` into one Dataset. `prompts` fixes the token table's row
    order (an episode whose prompt is not in it is an error)."""
    demos_dir = Path(demos_dir)
    meta = json.loads((demos_dir / "meta.json").read_text())
    rows = meta["episodes"][:max_episodes]
    if not rows:
        raise ValueError(f"{demos_dir}/meta.json lists no episodes")
    row_of = {p: i for i, p in enumerate(prompts)}
    lengths = [int(r["length"]) for r in rows]
    n, res = sum(lengths), int(meta["resolution"])
    images = np.empty((n, len(CAMERAS), res, res, 3), np.uint8)   # preallocated: the full suite is ~10 GB
    state = np.empty((n, _tasks.STATE_DIM), np.float32)
    actions = np.empty((n, _tasks.ACTION_DIM), np.float32)
    end = np.empty((n,), np.int32)
    task = np.empty((n,), np.int32)
    start = 0
    for i, (row, length) in enumerate(zip(rows, lengths)):
        with np.load(demos_dir / row["file"]) as ep:
            stop = start + length
            for c, cam in enumerate(CAMERAS):
                images[start:stop, c] = ep[cam]
            state[start:stop], actions[start:stop] = ep["state"], ep["actions"]
            prompt = str(ep["prompt"])
        if prompt not in row_of:
            raise ValueError(f"{row['file']}: prompt {prompt!r} is not one of the suite's")
        end[start:stop], task[start:stop] = stop, row_of[prompt]
        start = stop
        if log and (i + 1) % 100 == 0:
            log(f"loaded {i + 1}/{len(rows)} episodes")
    tokens, masks = tokenize_prompts(tokenizer_path, prompts, max_token_len)
    return Dataset(images=images, state=state, actions=actions, end=end, task=task, tokens=tokens, masks=masks,
                   prompts=tuple(prompts), num_episodes=len(rows))


def norm_stats(ds: Dataset) -> dict[str, nz.NormStats]:
    """openpi NormStats (mean, population std, q01, q99) of the state and of the action over every frame.

    openpi's RunningStats estimates the quantiles from a histogram; these are exact (numpy's linear quantiles)."""
    def stats(x: np.ndarray) -> nz.NormStats:
        x = x.astype(np.float64)
        return nz.NormStats(mean=x.mean(0), std=x.std(0), q01=np.quantile(x, 0.01, axis=0),
                            q99=np.quantile(x, 0.99, axis=0))

    return {nz.STATE: stats(ds.state), nz.ACTIONS: stats(ds.actions)}


def synthetic_demos(out_dir: str | Path, *, episodes: int = 4, length: int = 12, resolution: int = 16,
                    seed: int = 0) -> Path:
    """A tiny demos directory in write_demos' layout, for tests and CPU smoke runs: every episode is one suite
    task with a smooth random action sequence, and its images encode the task (a per-task colour) plus noise, so a
    model can learn the mapping."""
    rng = np.random.default_rng(seed)
    prompts = suite_prompts()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for e in range(episodes):
        t = e % len(prompts)
        colour = rng.integers(0, 256, 3) if e >= len(prompts) else np.array([(37 * t) % 256, (91 * t) % 256, 128])
        img = np.clip(colour + rng.normal(0, 20, (length, resolution, resolution, 3)), 0, 255).astype(np.uint8)
        phase = np.linspace(0, np.pi, length)[:, None]
        actions = np.tanh(np.sin(phase * (1 + np.arange(7)) + t)).astype(np.float32)
        state = np.cumsum(np.pad(actions, ((0, 0), (0, 1))) * 0.05, 0).astype(np.float32) + rng.normal(0, 0.01, 8)
        name = f"episode_{e:06d}.npz"
        np.savez(out / name, agentview=img, wrist=img[:, ::-1], state=state.astype(np.float32), actions=actions,
                 prompt=np.array(prompts[t]), task=np.array(f"task{t}"), init_state=np.int32(e),
                 success=np.bool_(True), length=np.int32(length))
        rows.append({"file": name, "task": f"task{t}", "prompt": prompts[t], "init_state": e, "success": True,
                     "length": length})
    meta = {"format": "pi0_jax.sim demos v1", "suite": "synthetic", "fps": 20, "resolution": resolution,
            "episodes": rows}
    (out / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return out
