"""The three inference stages, the last two as one (`prefix_denoise`) or split after the first denoise step
(`prefix_first_step`, `denoise_rest`), and the fused program, as pure functions of (engine weights, inputs).

Static per compiled program: the config, batch size, the active cameras (a camera masked for every element is not
encoded at all), the prompt bucket length, num_steps, whether layers are unrolled, each stage's attention
(`Attention`) and the expert's kernels ("xla": `layers.suffix_layer`; "pallas": the fused kernels of
`pi0_jax.ops`, with the prefix cache in their layout; "auto": `paths.expert_path`). Masked-out tokens never advance
positions, so skipping them leaves every number as it was.
"""

from __future__ import annotations

import functools

import flax.struct
import jax
import jax.numpy as jnp

from pi0_jax import pi0
from pi0_jax.config import Pi0Config
from pi0_jax.engine import layers, paths, vision
from pi0_jax.engine.paths import Attention
from pi0_jax.gemma import rope_angles
from pi0_jax.ops import expert_kernels, layout
from pi0_jax.ops.formats import QArray
from pi0_jax.ops.matmul import input_scale

# π0's action in-projection folded into the time MLP's first product (`weights.fold_action_in`); False: the two
# products as the reference runs them (an A/B switch for probes, read when a program is traced)
FOLD_ACTION_IN = True
# The XLA expert's FP8 x FP8 GEMMs take their rows (B x S a step) in multiples of 16, as cuBLASLt's FP8 GEMM needs:
# otherwise XLA pads the e4m3 input of every such GEMM whose producer cannot take the pad (q/k/v's after the norm's
# Triton fusion, down's after the FP8 MLP kernel), two kernels a layer for π0's 408 rows at B = 8. Each element
# carries `fp8_row_pad` rows more through the step instead, masked as keys (an A/B switch, read when traced).
FP8_ROW_PAD = True


@flax.struct.dataclass
class PrefixCache:
    """k, v: per layer (B, P, K, H), post-RoPE (a tuple when unrolled, (L, ...) stacked when scanned); mask (B, P).
    With kernels="pallas", in the kernels' layout (`ops.layout.cache_kv`, `cache_mask`: keys and head dims padded)."""

    k: tuple | jax.Array
    v: tuple | jax.Array
    mask: jax.Array


def encode_images(config: Pi0Config, weights: dict, images: jax.Array, *, unroll: bool = False,
                  attention: Attention = Attention(), kernels: str = "xla") -> jax.Array:
    """images (C, B, H, W, 3) f32 in [-1, 1] for the C active cameras -> (B, C * 256, VLM width), camera-major.
    unroll: the weights' SigLIP blocks are per layer (a list), and so are the layers. kernels: `vision_norm`'s."""
    c, b = images.shape[:2]
    # batch-major (B * C images): a batch sharded over devices stays sharded; merging C-major would all-gather it
    flat = jnp.swapaxes(images, 0, 1).reshape(b * c, *images.shape[2:])
    tokens = vision.encode(config.siglip, weights["img"], flat, dtype=jnp.dtype(config.dtype), unroll=unroll,
                           attention=attention.vision, norm=paths.vision_norm(kernels, b * c))
    return tokens.reshape(b, -1, tokens.shape[-1])


def encode_images_head(config: Pi0Config, weights: dict, images: jax.Array, *, attention: Attention = Attention(),
                       kernels: str = "xla") -> tuple:
    """`encode_images` up to the blocks of weights["img"]["blocks"] (`vision.encode_head`; unrolled) -> (x, f):
    the first of the call's two vision programs where the tower is cut (`runtime.VISION_SPLIT`)."""
    c, b = images.shape[:2]
    flat = jnp.swapaxes(images, 0, 1).reshape(b * c, *images.shape[2:])
    return vision.encode_head(config.siglip, weights["img"], flat, dtype=jnp.dtype(config.dtype),
                              attention=attention.vision, norm=paths.vision_norm(kernels, b * c))


def encode_images_tail(config: Pi0Config, weights: dict, x, f, *, cameras: int, attention: Attention = Attention(),
                       kernels: str = "xla") -> jax.Array:
    """`encode_images` from `encode_images_head`'s (x, f), over the other blocks, the final norm and the projection
    (`vision.encode_tail`) -> (B, C * 256, VLM width). cameras: C, the active cameras."""
    tokens = vision.encode_tail(config.siglip, weights["img"], x, f, dtype=jnp.dtype(config.dtype),
                                attention=attention.vision, norm=paths.vision_norm(kernels, x.shape[0]))
    return tokens.reshape(x.shape[0] // cameras, -1, tokens.shape[-1])


def fill_prefix_cache(config: Pi0Config, weights: dict, image_tokens, image_masks, tokens, token_mask, *,
                      unroll: bool, kernels: str = "xla", attention: Attention = Attention()) -> PrefixCache:
    """image_tokens (B, C*256, D); image_masks (C, B) bool; tokens / token_mask (B, L). The prefix is bidirectional.

    With a fused attention in the prefix or the denoise step (masks by lengths), each element's valid tokens are
    moved to the front first, in order: positions are computed before and travel with them, and attention does
    not depend on the order of its keys, so the cache holds the same keys, in that order, with a run of a mask."""
    dtype = jnp.dtype(config.dtype)
    attention = attention.at_batch(image_tokens.shape[0], suffix_mask=not config.pi05)
    n_img = image_tokens.shape[1] // image_masks.shape[0]
    text = weights["embedding"][tokens]
    text = text * jnp.sqrt(config.paligemma.width).astype(text.dtype)  # sqrt(width) cast to the table dtype first
    x = jnp.concatenate([image_tokens.astype(dtype), text.astype(dtype)], axis=1)
    mask = jnp.concatenate([jnp.repeat(image_masks.T, n_img, axis=1), token_mask], axis=1)
    positions = jnp.cumsum(mask, axis=1) - 1
    kv_len = None
    if "cudnn" in (attention.prefix, attention.denoise):
        # A stable partition, valid first, as counts: the j-th valid token is the one with j valid tokens before it
        # (positions), the j-th padded one the one with j padded before it. One reduction for XLA's 8-10 µs sort.
        rank = jnp.arange(mask.shape[1], dtype=positions.dtype)
        n = jnp.sum(mask, axis=1, keepdims=True, dtype=positions.dtype)
        before = jnp.where((rank < n)[:, :, None], positions[:, None, :] < rank[:, None],
                           (rank - positions - 1)[:, None, :] < (rank - n)[:, :, None])
        order = jnp.sum(before, axis=2, dtype=positions.dtype)
        x = jnp.take_along_axis(x, order[..., None], axis=1)
        positions, mask = (jnp.take_along_axis(a, order, axis=1) for a in (positions, mask))
        if attention.prefix == "cudnn":
            kv_len = n[:, 0].astype(jnp.int32)
    attn_mask = mask[:, None, :] & mask[:, :, None]
    kernel = paths.kernel_cache(kernels, attention, x.shape[0], weights.get("expert"))
    keys = layout.cache_len(x.shape[1]) if kernel else None   # each layer writes its cache padded
    angles = rope_angles(positions, config.paligemma.head_dim)   # once for every layer
    layer = functools.partial(layers.prefix_layer, config.paligemma, angles=angles, mask=attn_mask, kv_len=kv_len,
                              keys=keys)
    _, (k, v) = layers.run_layers(layer, weights["vlm"], x, unroll=unroll)
    if kernel:  # once per call: no step pads
        head_dim = config.paligemma.head_dim
        k, v = (jax.tree.map(lambda a: layout.cache_kv(a, head_dim), c) for c in (k, v))
        mask = layout.cache_mask(mask)
    return PrefixCache(k=k, v=v, mask=mask)


def _dense(p, x):
    return x @ p["kernel"] + p["bias"]


def suffix_kv(config: Pi0Config, cache: PrefixCache, state_kv: tuple | None = None) -> tuple:
    """The fused attention's keys and values, per layer [S suffix slots | prefix cache] (B, S + P, K, H): made once
    per call, and each step writes its suffix keys into the slots. As a loop carry that is in place; concatenating
    [suffix | cache] copied the whole cache every layer and step (13.4 of 72 ms of π0.5's denoise at B = 64, H200).
    Per layer tuples when unrolled, (L, ...) stacked when scanned, as the cache. state_kv: π0's state keys and
    values (`paths.cached_state`), written into slot 0 here, so that the steps fill slots 1 to S - 1."""
    def slots(c):
        pad = [(0, 0)] * c.ndim
        pad[-3] = (config.suffix_len, 0)
        return jnp.pad(c, pad)

    bufs = tuple(jax.tree.map(slots, c) for c in (cache.k, cache.v))
    if state_kv is None:
        return bufs
    return tuple(jax.tree.map(lambda b, s: b.at[..., :1, :, :].set(s.astype(b.dtype)), buf, kv)
                 for buf, kv in zip(bufs, state_kv))


def _state_kv(config: Pi0Config, weights: dict, cache: PrefixCache, state_token, position, *, unroll: bool):
    """π0's state token (B, D) at `position` (B, 1) through the expert's layers over the cache: its keys and values
    at each layer, (B, 1, K, H) per layer as the cache's own."""
    x = state_token[:, None, :].astype(jnp.dtype(config.dtype))
    own = jnp.ones((x.shape[0], 1, 1), bool)
    angles = rope_angles(position, config.action_expert.head_dim)

    def layer(w, x, k, v):
        return layers.suffix_layer(config.action_expert, w, x, angles, k, v, cache.mask[:, None, :], own)

    _, (k, v) = layers.run_layers(layer, weights["expert"], x, [cache.k, cache.v], unroll=unroll)
    return k, v


def step_inputs(config: Pi0Config, weights: dict, cache: PrefixCache, state, batch: int, kernels: str,
                attention: Attention, *, unroll: bool) -> tuple[dict, PrefixCache, tuple | None]:
    """(fixed, cache, kv), made once before a denoise loop: `step_invariants`, then what the steps attend to besides
    their own rows: with the fused attention (`paths.fused_suffix_attention`) the prefix cache and `suffix_kv`'s
    buffers, with π0's state in slot 0 when it ran once a call; else the prefix cache, with the state's keys after
    it, and None."""
    fixed = step_invariants(config, weights, cache, state, batch, kernels, attention, unroll=unroll)
    state_kv = fixed["state_kv"]
    if paths.fused_suffix_attention(config, attention, kernels, batch, weights["expert"]):
        return fixed, cache, suffix_kv(config, cache, state_kv)
    if state_kv is None:
        return fixed, cache, None
    k, v = (jax.tree.map(lambda c, s: jnp.concatenate([c, s.astype(c.dtype)], axis=-3), c, s)
            for c, s in zip((cache.k, cache.v), state_kv))
    return fixed, PrefixCache(k=k, v=v, mask=jnp.pad(cache.mask, ((0, 0), (0, 1)), constant_values=True)), None


def step_invariants(config: Pi0Config, weights: dict, cache: PrefixCache, state, batch: int, kernels: str,
                    attention: Attention, *, unroll: bool) -> dict:
    """What every denoise step of one call computes alike, made once before the loop rather than in each step (XLA
    sinks constants into a loop's body but does not hoist what is computed from the call's inputs or weights, so
    anything of this kind left in the step is a kernel every step): "state" π0's state token (B, D) in f32 (π0.5:
    None), "state_kv" its keys and values per layer where it runs once a call (`paths.cached_state`; else None),
    "positions" (B, S) and "suffix_mask" (B, S, S) of the rows a step runs (S without the state's row where it ran
    once), "tables" `layers.pallas_tables` for a cache in the kernels' layout (`paths.kernel_cache`), else None; for
    the XLA expert (else None): "angles" RoPE's (sin, cos) at `positions`, with `fp8_row_pad`'s rows, "kv_len" (B,)
    the fused denoise attention's key lengths (`layers.suffix_layer`), "mlp_scales" per layer the FP8 MLP kernel's
    column scales (`layers.expert_mlp_scales`)."""
    ar_state = [] if config.pi05 else [True]   # π0's state token: a causal block of its own before the actions
    s = len(ar_state) + config.action_horizon
    ar = jnp.asarray(ar_state + [True] + [False] * (config.action_horizon - 1))
    suffix_mask = jnp.broadcast_to(pi0.make_attn_mask(jnp.ones((1, s), bool), ar), (batch, s, s))
    positions = jnp.sum(cache.mask, axis=-1, keepdims=True) + jnp.arange(s)[None, :]
    tables = None
    if paths.kernel_cache(kernels, attention.at_batch(batch, suffix_mask=not config.pi05), batch, weights["expert"]):
        xla_expert = paths.expert_path(kernels, batch, weights["expert"]) == "xla"   # the kernel's launch in its layers
        tables = layers.pallas_tables(config.action_expert, positions, cache.mask, suffix_mask,
                                      expert_kernels.attention_blocks(batch, xla_expert))
    state_token = None if config.pi05 else _dense(weights["top"]["state_proj"], state)
    state_kv = None
    if paths.cached_state(config, attention, kernels, batch, weights["expert"]):
        state_kv = _state_kv(config, weights, cache, state_token, positions[:, :1], unroll=unroll)
        positions, suffix_mask = positions[:, 1:], suffix_mask[:, 1:, 1:]
    angles = kv_len = mlp_scales = None
    if paths.expert_path(kernels, batch, weights["expert"]) == "xla":
        at_batch = attention.at_batch(batch, suffix_mask=not config.pi05)
        pad = fp8_row_pad(config, weights, batch, positions.shape[1], at_batch)
        angles = rope_angles(jnp.pad(positions, ((0, 0), (0, pad)), mode="edge"), config.action_expert.head_dim)
        if at_batch.denoise == "cudnn":
            kv_len = (config.suffix_len + jnp.sum(cache.mask, axis=-1)).astype(jnp.int32)
        mlp_scales = layers.expert_mlp_scales(weights["expert"], batch * (positions.shape[1] + pad))
    return {"state": state_token, "state_kv": state_kv, "positions": positions, "suffix_mask": suffix_mask,
            "tables": tables, "angles": angles, "kv_len": kv_len, "mlp_scales": mlp_scales}


def fp8_row_pad(config: Pi0Config, weights: dict, batch: int, s: int, attention: Attention) -> int:
    """Rows to add to each element's s suffix rows (`FP8_ROW_PAD`) so that the XLA expert's batch x s rows become the
    multiple of 16 XLA pads its FP8 x FP8 GEMMs to, with no more GEMM rows than that pad. Only π0's rows with the
    Pallas attention, whose tables mask every key past s (their padded suffix), and only where those tables' padded
    suffix and query rows stay as laid out for s (`layers.query_rows`); 0 elsewhere."""
    if not FP8_ROW_PAD or config.pi05 or attention.denoise != "pallas" or (batch * s) % 16 == 0:
        return 0
    leaves = jax.tree.leaves(weights["expert"], is_leaf=lambda v: isinstance(v, QArray))
    rows = -(-batch * s // 16) * 16
    if rows % batch or not any(input_scale(w) is not None for w in leaves):
        return 0
    blocks, cfg, padded = expert_kernels.blocks_at(batch), config.action_expert, rows // batch
    if layout.suffix_rows(padded) != layout.suffix_rows(s) or \
            layers.query_rows(cfg, padded, blocks) != layers.query_rows(cfg, s, blocks):
        return 0
    return padded - s


def step_velocity(config: Pi0Config, weights: dict, sched: dict, step: jax.Array, cache: PrefixCache, fixed: dict,
                  x_t, kv, *, unroll: bool, attention: Attention, kernels: str, frozen: jax.Array | None) -> tuple:
    """One denoise step's velocity v(x_t, t_step) -> (v, kv). cache, kv: `step_inputs`'; kv, the suffix-first
    buffers of `suffix_kv` (exactly when `paths.fused_suffix_attention`, else None), comes back with this step's
    suffix keys written in. fixed: `step_invariants`. frozen (B, H) or None: committed actions, at flow time 0."""
    dtype = jnp.dtype(config.dtype)
    top, b = weights["top"], x_t.shape[0]
    attention = attention.at_batch(b, suffix_mask=not config.pi05)

    def at_step(key):   # the schedule row of `key` for every action: (1, 1, ...) or, with `frozen`, (B, H, ...)
        now = jax.lax.dynamic_index_in_dim(sched[key], step, keepdims=False, allow_negative_indices=False)[None, None]
        if frozen is None:
            return now
        where = frozen.reshape(frozen.shape + (1,) * (now.ndim - 2))
        return jnp.where(where, sched["committed"][key][0][None, None], now)

    if config.pi05:
        x = _dense(top["action_in_proj"], x_t)  # f32: the projections run in the promoted dtype
        mods = (at_step("mods_attn"), at_step("mods_ffw"))  # (B or 1, H or 1, L, 3D) each
    else:
        if FOLD_ACTION_IN:   # the in-projection inside the time MLP's first product (`weights.fold_action_in`)
            h = _dense(top["action_time_in"], x_t) + at_step("time_in")
        else:
            w_in = top["action_time_mlp_in"]["kernel"]
            h = _dense(top["action_in_proj"], x_t) @ w_in[: config.action_expert.width].astype(jnp.float32)
            h = h + at_step("time_in")
        x = _dense(top["action_time_mlp_out"], jax.nn.swish(h))
        if fixed["state_kv"] is None:
            x = jnp.concatenate([fixed["state"][:, None, :], x], axis=1)
        mods = None
    x = x.astype(dtype)
    s = x.shape[1]
    positions, suffix_mask = fixed["positions"], fixed["suffix_mask"]
    final_mod = at_step("mods_final") if config.pi05 else None

    if paths.expert_path(kernels, b, weights["expert"]) == "pallas":
        if frozen is not None:
            raise ValueError("committed actions (training-time action conditioning) run on the XLA expert path")
        # π0.5's adaRMS tables whole, read at the step's rows by the kernels (`expert_kernels.Step`)
        x = layers.suffix_layers_pallas(config.action_expert, weights["expert"], x, positions, cache.k, cache.v,
                                        cache.mask, suffix_mask, None if mods is None else
                                        (sched["mods_attn"], sched["mods_ffw"]), tables=fixed["tables"], step=step)
        return _top(config, weights, final_mod, x), kv

    kv_len = None
    if attention.denoise == "pallas":   # the kernel's masks: prefix (B, Pp), suffix (B Sp, Sp), int32
        prefix_mask, suffix_mask = fixed["tables"][2:]
    else:
        prefix_mask = jnp.broadcast_to(cache.mask[:, None, :], (b, s, cache.mask.shape[1]))
    slot = config.suffix_len - s   # 1 where π0's state ran once a call and holds the suffix's first slot
    if attention.denoise == "cudnn":   # no suffix mask: the action rows, and π0.5's, see every suffix key
        if not (config.pi05 or slot):
            raise ValueError("the fused denoise attention takes π0's state token once a call (`paths.cached_state`)")
        kv_len = fixed["kv_len"]

    pad = fp8_row_pad(config, weights, b, s, attention)
    if pad:   # rows past s: zeros, at the last position (`step_invariants`' angles), masked as keys by the kernel's
        x = jnp.pad(x, ((0, 0), (0, pad), (0, 0)))   # tables; cut after the layers

    def layer(w, x, k, v, scales, *mod):
        m = None if mods is None else mod
        x, k, v = layers.suffix_layer(config.action_expert, w, x, fixed["angles"], k, v, prefix_mask, suffix_mask, m,
                                      kv_len, kernel=attention.denoise == "pallas", slot=slot, mlp_scales=scales)
        return (x, k, v) if kv_len is not None else (x,)

    per_layer = [cache.k, cache.v] if kv is None else list(kv)
    per_layer.append(fixed["mlp_scales"])
    if mods is not None:   # layer axis first: (L, B or 1, H or 1, 3D)
        per_layer += [_by_layer(jnp.moveaxis(m, 2, 0), unroll) for m in mods]
    x, outs = layers.run_layers(layer, weights["expert"], x, per_layer, unroll=unroll)
    return _top(config, weights, final_mod, x[:, :s]), (None if kv is None else tuple(outs))


def _top(config, weights, final_mod, x):
    """The expert's final norm (π0.5: adaRMS with `final_mod`) and the action output projection."""
    if config.pi05:
        x, _ = layers.rms_norm(x, mod=final_mod)
    else:
        x, _ = layers.rms_norm(x, weights["final_norm_1"])
    return _dense(weights["top"]["action_out_proj"], x[:, -config.action_horizon:])


def _by_layer(x, unroll):
    return tuple(x[i] for i in range(x.shape[0])) if unroll else x


def denoise(config: Pi0Config, weights: dict, sched: dict, cache: PrefixCache, state, noise, *, num_steps: int,
            unroll: bool, unroll_steps: bool, attention: Attention = Attention(), kernels: str = "xla",
            committed: jax.Array | None = None, num_committed: jax.Array | None = None,
            peel_first: bool = False) -> jax.Array:
    """num_steps Euler steps from noise (t = 1) to actions (t = 0): a fixed trip count for a Python int, a while
    loop for a traced int32 (then `sched` must hold at least num_steps entries). With `committed` (B, H, action_dim)
    and `num_committed` d (B,): actions i < d are given, clean at every step and returned as given (training-time
    action conditioning, as `pi0.sample_actions`). peel_first: the first step outside the loop, in the program's
    own sequence, where its layer i depends on the cache's layer i alone (not on the whole prefix fill)."""
    if not isinstance(num_steps, int):
        unroll_steps = None
    x = noise.astype(jnp.float32)
    frozen = None
    if num_committed is not None:
        frozen = pi0.committed_mask(config.action_horizon, num_committed)
        x = jnp.where(frozen[..., None], committed.astype(jnp.float32), x)

    fixed, cache, kv = step_inputs(config, weights, cache, state, x.shape[0], kernels, attention, unroll=unroll)
    step = _euler_step(config, weights, sched, cache, fixed, num_steps, unroll=unroll, attention=attention,
                       kernels=kernels, frozen=frozen)
    carry, first = (x, kv), 0
    if peel_first and isinstance(num_steps, int) and num_steps > 0:
        carry, first = step(0, carry), 1
    return jax.lax.fori_loop(first, num_steps, step, carry, unroll=unroll_steps)[0]


def _euler_step(config, weights, sched, cache, fixed, num_steps, *, unroll, attention, kernels, frozen=None):
    """The loop body of `denoise`: (i, (x_t, kv)) -> (x_t + dt v, kv), dt = -1 / num_steps."""
    dt = -1.0 / num_steps
    if not isinstance(num_steps, int):
        dt = jnp.asarray(dt, jnp.float32)   # f32 as the reference's traced dt

    def step(i, carry):   # the suffix-first buffers ride in the carry, so each step fills their slots in place
        x_t, kv = carry
        v, kv = step_velocity(config, weights, sched, i, cache, fixed, x_t, kv, unroll=unroll, attention=attention,
                              kernels=kernels, frozen=frozen)
        x_next = x_t + dt * v  # dt * v in v's dtype, then promoted to f32: as the reference
        return (x_next if frozen is None else jnp.where(frozen[..., None], x_t, x_next)), kv

    return step


def prefix_first_step(config: Pi0Config, weights: dict, sched: dict, image_tokens, image_masks, tokens, token_mask,
                      state, noise, *, num_steps: int, unroll: bool, attention: Attention = Attention(),
                      kernels: str = "xla") -> tuple:
    """The call's second program where its denoise loop is a program of its own (`denoise_rest`): the prefix cache
    and the first denoise step, whose layer i waits for the cache's layer i alone. -> (x after the first step, the
    suffix-first buffers or None, the cache and the step invariants the other steps read: `denoise_rest`'s inputs)."""
    cache = fill_prefix_cache(config, weights, image_tokens, image_masks, tokens, token_mask, unroll=unroll,
                              kernels=kernels, attention=attention)
    fixed, cache, kv = step_inputs(config, weights, cache, state, noise.shape[0], kernels, attention, unroll=unroll)
    step = _euler_step(config, weights, sched, cache, fixed, num_steps, unroll=unroll, attention=attention,
                       kernels=kernels)
    x, kv = step(0, (noise.astype(jnp.float32), kv))
    return x, kv, cache, fixed


def denoise_rest(config: Pi0Config, weights: dict, sched: dict, x, kv, cache: PrefixCache, fixed: dict, *,
                 num_steps: int, unroll: bool, unroll_steps: bool, attention: Attention = Attention(),
                 kernels: str = "xla") -> jax.Array:
    """Denoise steps 1 .. num_steps - 1 from `prefix_first_step`'s outputs: the call's third program."""
    step = _euler_step(config, weights, sched, cache, fixed, num_steps, unroll=unroll, attention=attention,
                       kernels=kernels)
    return jax.lax.fori_loop(1, num_steps, step, (x, kv), unroll=unroll_steps)[0]


def prefix_denoise(config: Pi0Config, weights: dict, sched: dict, image_tokens, image_masks, tokens, token_mask,
                   state, noise, *, num_steps: int, unroll: bool, unroll_steps: bool,
                   attention: Attention = Attention(), kernels: str = "xla", peel_first: bool = False) -> jax.Array:
    """The prefix cache from `encode_images`' tokens, then the denoise loop: a call's second program."""
    cache = fill_prefix_cache(config, weights, image_tokens, image_masks, tokens, token_mask, unroll=unroll,
                              kernels=kernels, attention=attention)
    return denoise(config, weights, sched, cache, state, noise, num_steps=num_steps, unroll=unroll,
                   unroll_steps=unroll_steps, attention=attention, kernels=kernels, peel_first=peel_first)


def infer(config: Pi0Config, weights: dict, sched: dict, images, image_masks, tokens, token_mask, state, noise, *,
          num_steps: int, unroll: bool, unroll_steps: bool, attention: Attention = Attention(),
          kernels: str = "xla") -> jax.Array:
    """The fused program: vision -> prefix cache -> denoise, one XLA executable (the pipeline inside a larger
    program, as the simulator's rollout; the engine's own call runs `encode_images` and `prefix_denoise`)."""
    image_tokens = encode_images(config, weights, images, unroll=unroll, attention=attention, kernels=kernels)
    return prefix_denoise(config, weights, sched, image_tokens, image_masks, tokens, token_mask, state, noise,
                          num_steps=num_steps, unroll=unroll, unroll_steps=unroll_steps, attention=attention,
                          kernels=kernels)
