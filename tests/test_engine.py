"""The compiled engine computes what the reference model computes, compiles once per static shape, and reuses the
persistent compilation cache across processes."""

import functools
import json
import subprocess
import sys
import textwrap

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax import pi0
from pi0_jax.config import IMAGE_KEYS, get_config
from pi0_jax.engine import Engine, layers, prompt_bucket
from pi0_jax.engine import weights as weights_lib
from test_model import make_obs, randomize

sample_ref = jax.jit(pi0.sample_actions, static_argnums=(0, 4))


@pytest.fixture(scope="module", params=["dummy", "dummy_pi05"])
def model(request):
    config = get_config(request.param)
    return config, randomize(pi0.param_shapes(config))   # every leaf redrawn: init values are never read


@pytest.mark.parametrize("unroll", [True, False])
def test_fused_and_staged_match_reference_f32(model, unroll):
    config, params = model
    obs = make_obs(config)
    noise = jax.random.normal(jax.random.key(1), (2, config.action_horizon, config.action_dim))
    ref = sample_ref(config, params, obs, noise, 3)
    engine = Engine(config, params, unroll=unroll, cache_dir=False)
    fused = engine.sample_actions(obs, jnp.array(noise), 3)
    image_tokens, cache, staged = engine.run_stages(obs, jnp.array(noise), 3)
    # f32: the same function up to matmul grouping (measured max abs error ~7e-7 on outputs of scale ~4)
    np.testing.assert_allclose(fused, ref, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(staged, ref, rtol=1e-5, atol=1e-5)
    ref_cache = pi0.fill_prefix_cache(config, params, obs)
    k = np.stack(cache.k) if unroll else np.asarray(cache.k)
    n = k.shape[2]  # the engine's prompt is cut to its bucket (32 here); the reference keeps all 48 slots
    assert n == 3 * 256 + 32
    valid = np.asarray(ref_cache.mask)[None, :, :n, None, None]
    np.testing.assert_allclose(np.where(valid, k, 0), np.where(valid, ref_cache.k[:, :, :n], 0), rtol=1e-5, atol=1e-5)


def test_the_call_keeps_its_noise(model):
    """The call's programs donate no input: the caller's noise survives the call and gives the same actions again
    (a donated buffer would be deleted here; CPU honours donation)."""
    config, params = model
    obs = make_obs(config)
    noise = jax.random.normal(jax.random.key(2), (2, config.action_horizon, config.action_dim))
    engine = Engine(config, params, cache_dir=False)
    first = np.asarray(engine.sample_actions(obs, noise, 2))
    assert not noise.is_deleted()
    np.testing.assert_array_equal(np.asarray(engine.sample_actions(obs, noise, 2)), first)


def test_bf16_matches_reference_bf16(model):
    config, params = model
    config = config.replace(dtype="bfloat16")
    params = jax.tree.map(lambda x: x.astype(jnp.bfloat16), params)
    obs = make_obs(config)
    noise = jax.random.normal(jax.random.key(1), (2, config.action_horizon, config.action_dim))
    ref = np.asarray(sample_ref(config, params, obs, noise, 10))
    got = np.asarray(Engine(config, params, cache_dir=False).sample_actions(obs, jnp.array(noise), 10))
    # bf16 rounds differently when matmuls are grouped differently: relative L2 ~3e-3 measured
    assert np.linalg.norm(got - ref) / np.linalg.norm(ref) < 1e-2


def test_masked_camera_and_padding_are_skipped_exactly(model):
    config, params = model
    obs = make_obs(config, valid_lens=(13, 21))
    last = IMAGE_KEYS[config.num_cameras - 1]
    obs = obs.replace(image_masks={**obs.image_masks, last: jnp.zeros((2,), bool)})
    engine = Engine(config, params, cache_dir=False)
    cameras, bucket = engine.plan(obs)
    assert cameras == IMAGE_KEYS[: config.num_cameras - 1] and bucket == 32 < config.max_token_len
    noise = jax.random.normal(jax.random.key(2), (2, config.action_horizon, config.action_dim))
    ref = sample_ref(config, params, obs, noise, 2)
    np.testing.assert_allclose(engine.sample_actions(obs, jnp.array(noise), 2), ref, rtol=1e-5, atol=1e-5)


def test_committed_actions_match_reference_and_come_back_exactly(model):
    """Training-time action conditioning: actions i < d ride clean at t = 0 (π0: the time-MLP input; π0.5: the
    per-token adaRMS modulation), the rest is sampled given them. The engine's denoise equals the reference sampler's,
    the committed actions come back bit for bit, and d = 0 is the plain sampler."""
    from pi0_jax.engine import paths, programs

    config, params = model
    obs = make_obs(config)
    h, a = config.action_horizon, config.action_dim
    noise = jax.random.normal(jax.random.key(1), (2, h, a))
    committed = jax.random.normal(jax.random.key(2), (2, h, a))
    d = jnp.array([3, 0])
    ref = np.asarray(jax.jit(pi0.sample_actions, static_argnums=(0, 4))(config, params, obs, noise, 3, committed, d))
    engine = Engine(config, params, cache_dir=False)
    cameras, bucket = engine.plan(obs)
    images, image_masks, tokens, token_mask, state = engine.pack(obs, cameras, bucket)
    w = engine.weights
    image_tokens = engine.executable("encode_images", 2, 3, cameras, bucket)(w, images)
    cache = engine.executable("fill_prefix_cache", 2, 3, cameras, bucket)(w, image_tokens, image_masks, tokens,
                                                                           token_mask)
    run = jax.jit(lambda c, s, n, x, k: programs.denoise(config, w, engine.schedule(3), c, s, n, num_steps=3,
                                                         unroll=True, unroll_steps=False, committed=x,
                                                         num_committed=k))
    got = np.asarray(run(cache, state, noise, committed, d))
    plain = np.asarray(run(cache, state, noise, committed, jnp.zeros(2, jnp.int32)))
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)      # element 1 (d = 0) against the plain reference
    np.testing.assert_array_equal(got[0, :3], np.asarray(committed)[0, :3])
    np.testing.assert_array_equal(got[1], plain[1])                   # d = 0 per element
    np.testing.assert_allclose(plain, sample_ref(config, params, obs, noise, 3), rtol=1e-5, atol=1e-5)  # = no prefix
    # the committed actions condition the rest: the same noise without them samples something else
    assert np.abs(got[0, 3:] - plain[0, 3:]).max() > 1e-3
    # the XLA expert on the Pallas attention: its cache in the kernels' layout
    attention = paths.Attention(denoise="pallas")
    kernel = Engine(config, params, attention=attention, cache_dir=False)
    cache = kernel.executable("fill_prefix_cache", 2, 3, cameras, bucket)(w, image_tokens, image_masks, tokens,
                                                                           token_mask)
    got = jax.jit(lambda c, s, n, x, k: programs.denoise(config, w, engine.schedule(3), c, s, n, num_steps=3,
                                                         unroll=True, unroll_steps=False, attention=attention,
                                                         committed=x, num_committed=k))(cache, state, noise,
                                                                                        committed, d)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("attention", ["cudnn", "vision=cudnn", "prefix=cudnn", "denoise=cudnn", "denoise=auto"])
def test_fused_attention_matches_reference_with_holes_in_the_prefix(model, attention, monkeypatch):
    """The fused attention (cuDNN on a GPU; here its XLA form, the same code path) masks by lengths, so the prefix
    fill moves each element's valid tokens to the front. Element 1's last camera is masked (a hole mid-prefix) and
    the prompts are padded to different lengths: without the move the lengths would cut valid keys. "denoise=auto"
    is the fused kernel from CUDNN_DENOISE_MIN_BATCH on: lowered to this test's batch of 2, the prefix fill must see
    it too (the move). π0's state token then runs once a call, its keys in the fused attention's first slot."""
    from pi0_jax.engine import paths

    monkeypatch.setattr(paths, "CUDNN_DENOISE_MIN_BATCH", 2)
    config, params = model
    obs = make_obs(config, valid_lens=(13, 21))
    noise = jax.random.normal(jax.random.key(1), (2, config.action_horizon, config.action_dim))
    ref = sample_ref(config, params, obs, noise, 3)
    engine = Engine(config, params, attention=attention, cache_dir=False)
    np.testing.assert_allclose(engine.sample_actions(obs, jnp.array(noise), 3), ref, rtol=1e-5, atol=1e-5)
    _, cache, staged = engine.run_stages(obs, jnp.array(noise), 3)
    np.testing.assert_allclose(staged, ref, rtol=1e-5, atol=1e-5)
    mask = np.asarray(cache.mask)
    resolved = paths.Attention.parse(attention).at_batch(2, suffix_mask=not config.pi05)
    moved = (np.diff(mask.astype(np.int8), axis=1) <= 0).all()  # valid keys first: each row one run from the front
    assert moved == ("cudnn" in (resolved.prefix, resolved.denoise))
    assert mask.sum(1).tolist() == [3 * 256 + 13, 2 * 256 + 21]


def test_fused_denoise_writes_suffix_keys_in_place_of_copying_the_cache(model, monkeypatch):
    """With the fused attention the denoise loop carries suffix-first key / value buffers and writes each step's
    suffix keys into them (a dynamic_update_slice of the carry); nothing inside the loop concatenates a cache-sized
    array (that copied the cache every layer and step). The kernel gets no mask (cuDNN's masked kernel was slower
    than XLA's attention) and one head of G x T rows per kv head (the query heads folded); π0's state row, the one
    row that masks, runs once a call before the loop. The numbers are checked by the test above."""
    from pi0_jax.engine import layers, programs

    calls, fused = [], layers.attention.fused

    def spy(q, *args, **kw):
        calls.append((q.shape, kw))
        return fused(q, *args, **kw)

    monkeypatch.setattr(layers.attention, "fused", spy)
    config, params = model
    obs = make_obs(config)
    engine = Engine(config, params, attention="cudnn", cache_dir=False)
    cameras, bucket = engine.plan(obs)
    _, _, _, _, state = engine.pack(obs, cameras, bucket)
    noise = jnp.zeros((2, config.action_horizon, config.action_dim))
    _, cache, _ = engine.run_stages(obs, noise, 2)
    keys = cache.mask.shape[1] + config.suffix_len
    calls.clear()   # the stages above ran vision and the prefix: only the denoise program's calls count
    jaxpr = jax.make_jaxpr(lambda c, s, n: programs.denoise(
        config, engine.weights, engine.schedule(2), c, s, n, num_steps=2, unroll=True, unroll_steps=False,
        attention=engine.attention))(cache, state, noise)

    def eqns(j):   # every equation, nested jaxprs (the loop body, pjit calls) included
        for e in j.eqns:
            yield e
            for sub in jax.extend.core.jaxprs_in_params(e.params):
                yield from eqns(sub)

    (loop,) = [e for e in eqns(jaxpr.jaxpr) if e.primitive.name in ("scan", "while")]   # the step loop
    body = [e for sub in jax.extend.core.jaxprs_in_params(loop.params) for e in eqns(sub)]
    cache_sized = [e for e in body if any(getattr(v.aval, "shape", (0,) * 2)[1:2] == (keys,) for v in e.outvars)]
    assert not [e for e in cache_sized if e.primitive.name in ("concatenate", "pad")]
    writes = [e for e in cache_sized if e.primitive.name == "dynamic_update_slice"]
    assert len(writes) == 2 * config.action_expert.depth   # k and v of every layer
    expert = config.action_expert
    rows = (config.suffix_len - (not config.pi05)) * expert.num_heads // expert.num_kv_heads
    assert len(calls) == expert.depth
    assert {(shape[1:3], kw.get("mask")) for shape, kw in calls} == {((rows, expert.num_kv_heads), None)}


def test_choices_on_a_jax_without_pallas_triton(monkeypatch):
    """JAX 0.11 deprecated Pallas's Triton backend, which most of the kernels run on. On a jax without it the package
    imports (a process whose jax has no `jax.experimental.pallas.triton`), the "auto" choices run XLA's and cuDNN's
    kernels on a GPU, and a kernel asked for by name raises before it is lowered. With it, the deprecation warning
    that every lowering raises is filtered once a kernel is called on a GPU, and only that warning."""
    import warnings

    from pi0_jax.engine import paths
    from pi0_jax.ops import expert_kernels as ek
    from pi0_jax.ops import pallas_base, vision_attention

    code = ("import sys; sys.modules['jax.experimental.pallas.triton'] = None\n"
            "import pi0_jax.benchmark, pi0_jax.engine, pi0_jax.policy\n"
            "from pi0_jax.ops import pallas_base\n"
            "assert not pallas_base.TRITON\n"
            "print(pi0_jax.engine.paths.Attention.parse('auto', platform='gpu'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "vision=cudnn,prefix=cudnn,denoise=auto"

    layers = [{k: jnp.zeros((4, 4)) for k in ("qkv", "attn_out", "gate_up", "down")}]
    assert pallas_base.TRITON and paths.expert_path("auto", 1, layers, platform="gpu") == "pallas"
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    with warnings.catch_warnings():
        pallas_base._quiet_deprecation.cache_clear()
        pallas_base.call(lambda o_ref: None, grid=(1,), out_shape=jax.ShapeDtypeStruct((16,), jnp.float32),
                         name="probe", num_warps=4, num_stages=2)
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always", UserWarning)
            warnings.warn("The Pallas Triton backend is deprecated and will be removed", DeprecationWarning)
            warnings.warn("The Pallas Triton backend is deprecated", UserWarning)   # another category: kept
        assert [w.category for w in seen] == [UserWarning]
    pallas_base._quiet_deprecation.cache_clear()

    monkeypatch.setattr(pallas_base, "TRITON", False)
    auto = paths.Attention.parse("auto", platform="gpu")
    assert auto.vision == "cudnn" and auto.prefix == paths.AUTO_GPU.prefix
    assert {auto.at_batch(b, suffix_mask=m).denoise for b in range(1, 65) for m in (True, False)} == {"xla", "cudnn"}
    for m in (True, False):   # π0 (its state token once a call) as π0.5: cuDNN's measured faster than XLA's from B = 3
        assert [auto.at_batch(b, suffix_mask=m).denoise for b in (2, 3)] == ["xla", "cudnn"]
    monkeypatch.setattr(paths.mosaic_gemm, "hopper", lambda: True)   # the kernel attention on Mosaic GPU
    for m, batches in ((True, paths.PALLAS_DENOISE_BATCHES_MASKED), (False, paths.PALLAS_DENOISE_BATCHES)):
        assert {b for b in range(1, 65) if auto.at_batch(b, suffix_mask=m).denoise == "pallas"} == set(batches)
    monkeypatch.setattr(paths.mosaic_gemm, "hopper", lambda: False)
    assert paths.expert_path("auto", 1, layers, platform="gpu") == "xla"   # f32: no Mosaic GPU kernel takes it
    # bf16 on a Hopper GPU: the Pallas expert on its Mosaic GPU kernels alone (`expert_kernels.TRITON_FREE`)
    bf16 = [{k: v.astype(jnp.bfloat16) for k, v in layers[0].items()}]
    for hopper in (True, False):
        monkeypatch.setattr(paths.mosaic_gemm, "hopper", lambda hopper=hopper: hopper)
        assert paths.expert_path("auto", 1, bf16, platform="gpu") == ("pallas" if hopper else "xla")
        assert paths.expert_path("auto", paths.PALLAS_MAX_BATCH + 1, bf16, platform="gpu") == "xla"
        assert paths.expert_path("auto", 1, bf16[0], platform="gpu") == "xla"   # stacked (scanned) layers
    assert ek.default_blocks() == ek.TRITON_FREE
    assert all(getattr(ek.TRITON_FREE, f"mosaic_{g}") for g in ("qkv", "mlp", "out", "down", "attention"))
    assert ek.TRITON_FREE.xla_merge
    assert paths.vision_norm("auto", 192, platform="gpu") == "xla"
    with pytest.raises(RuntimeError, match="'vision_attention' runs on Pallas's Triton backend"):
        vision_attention.attention(jnp.zeros((32, 48)), images=1, num_heads=1)


def test_attention_and_kernel_choices(monkeypatch):
    from pi0_jax.engine import guidance, paths
    from pi0_jax.ops import formats

    A = paths.Attention
    assert A.parse("auto", platform="cpu") == A() and A.parse("auto", platform="gpu") == paths.AUTO_GPU
    assert A.parse("auto", platform="gpu", dtype="float32") == A()  # cuDNN's flash kernel takes no float32
    assert A.parse("cudnn") == A("cudnn", "cudnn", "cudnn") and A.parse("prefix=cudnn") == A(prefix="cudnn")
    assert str(A.parse(str(paths.AUTO_GPU))) == str(paths.AUTO_GPU)
    big, small = paths.CUDNN_DENOISE_MIN_BATCH, paths.CUDNN_DENOISE_MIN_BATCH - 1   # measured: 3 faster, 1 slower
    assert paths.AUTO_GPU.at_batch(big) == A("pallas", "cudnn", "cudnn") and big <= 8
    assert paths.AUTO_GPU.at_batch(small) == A("pallas", "cudnn", "xla") and small >= 1
    assert A.parse("vision=pallas") == A(vision="pallas")
    at = functools.partial(paths.AUTO_GPU.at_batch, suffix_mask=True)   # π0: cuDNN's from the same batch on
    assert at(max(paths.PALLAS_DENOISE_BATCHES_MASKED) + 1).denoise == "cudnn"
    kernel = paths.PALLAS_DENOISE_BATCHES_MASKED   # π0: measured faster at 3-16, slower at 64
    assert {3, 4, 8, 16} <= set(kernel) and 64 not in kernel and A.parse("denoise=pallas") == A(denoise="pallas")
    assert [paths.AUTO_GPU.at_batch(b, suffix_mask=True).denoise for b in (2, 3, 16, 64)] == [
        "xla", "pallas", "pallas", "cudnn"]
    # π0.5: measured faster at 4 and 8, slower at 16 and 64
    assert [paths.AUTO_GPU.at_batch(b).denoise for b in (2, 3, 4, 8, 16, 64)] == [
        "xla", "cudnn", "pallas", "pallas", "cudnn", "cudnn"]
    # real-time chunking differentiates the velocity: XLA's attention at every batch (the Pallas kernel has no VJP;
    # cuDNN's flash backward failed on a GPU at the suffix's lengths, "Unsupported sequence length Q 40, KV 171")
    for mask in (True, False):
        assert {paths.AUTO_GPU.at_batch(b, suffix_mask=mask, differentiable=True).denoise
                for b in range(1, 65)} == {"xla"}
    with pytest.raises(ValueError, match="differentiates"):   # the Pallas kernel has no VJP
        guidance.guided_denoise(get_config("dummy"), None, None, None, None, jnp.zeros((4, 2, 2)), None, None,
                                num_steps=2, unroll=True, attention=A(denoise="pallas"))
    with monkeypatch.context() as m:   # nor cuDNN's at these lengths, on a GPU (on a CPU it is XLA's form)
        m.setattr(jax, "default_backend", lambda: "gpu")
        with pytest.raises(ValueError, match="not 'cudnn'"):
            guidance.guided_denoise(get_config("dummy"), None, None, None, None, jnp.zeros((4, 2, 2)), None, None,
                                    num_steps=2, unroll=True, attention=A.parse("cudnn"))
    assert A.parse("cudnn").at_batch(1) == A.parse("cudnn")
    for bad in ("flash", "prefix=flash", "decoder=cudnn", "prefix", "vision=auto", "prefix=pallas", "pallas"):
        with pytest.raises(ValueError, match="attention"):
            A.parse(bad)
    layers = [{"qkv": jnp.zeros((4, 4))}]
    assert paths.expert_path("auto", 1, layers, platform="gpu") == "pallas"
    assert paths.expert_path("auto", 2, layers, platform="gpu") == "pallas"
    assert paths.expert_path("auto", 4, layers, platform="gpu") == "xla"      # measured slower at B = 4 and 8
    assert paths.expert_path("auto", 1, layers, platform="cpu") == "xla"      # interpreted on a CPU
    assert paths.expert_path("auto", 1, layers[0], platform="gpu") == "xla"   # scanned layers
    quantised = [{"qkv": formats.quantize_fp8(jnp.ones((4, 4)))}]
    assert paths.expert_path("auto", 1, quantised, platform="gpu") == "xla"
    assert paths.expert_path("pallas", 8, layers, platform="cpu") == "pallas"
    with pytest.raises(ValueError, match="kernels must be"):
        paths.expert_path("triton", 1, layers)


def test_the_first_step_beside_the_prefix_is_the_same_call(model, monkeypatch):
    """overlap: the call's second program runs its first denoise step after the prefix fill (so its layer i waits
    for the cache's layer i alone) in XLA's CONCURRENT command-buffer mode, and the loop over the other steps is a
    third program in XLA's default order (one program with one step, as without the overlap): the same actions bit
    for bit; "auto" only at batch 1 and 2 on a GPU, where the expert runs its Pallas kernels."""
    import re

    from pi0_jax.engine import paths, runtime

    config, params = model
    obs = make_obs(config)
    noise = jax.random.normal(jax.random.key(4), (2, config.action_horizon, config.action_dim))
    got, trips, options = {}, {}, {}

    def compile(self, stage, parts, fn, args, opts=None):   # records each program's compiler options
        options[stage] = opts
        return jax.jit(fn).lower(*args).compile(opts)

    monkeypatch.setattr(runtime.ProgramStore, "compile", compile)

    def mode(stage):
        return (options.pop(stage) or {}).get("xla_gpu_command_buffer_scheduling_mode")

    for overlap in ("on", "off"):
        engine = Engine(config, params, cache_dir=False, overlap=overlap)
        got[overlap] = np.asarray(engine.sample_actions(obs, noise, 3))
        got[overlap, 1] = np.asarray(engine.sample_actions(obs, noise, 1))
        loop = engine.call_stages(2, 3)[-1]
        hlo = engine.executable(loop, 2, 3, *engine.plan(obs)).as_text()
        trips[overlap] = re.findall(r'known_trip_count":\{"n":"(\d+)"', hlo)
        assert engine.overlaps(2) == (overlap == "on")
        assert engine.call_stages(2, 1) == ("encode_images", "prefix_denoise")
        if overlap == "on":
            assert engine.call_stages(2, 3) == ("encode_images", "prefix_first_step", "denoise_rest")
            assert (mode("prefix_first_step"), mode("denoise_rest"), mode("prefix_denoise")) == ("CONCURRENT",
                                                                                              None, "CONCURRENT")
        else:
            assert engine.call_stages(2, 3) == ("encode_images", "prefix_denoise") and mode("prefix_denoise") is None
        assert mode("encode_images") is None and not options
    np.testing.assert_array_equal(got["on"], got["off"])
    np.testing.assert_array_equal(got["on", 1], got["off", 1])
    assert trips == {"on": ["2"], "off": ["3"]}
    assert not Engine(config, params, cache_dir=False).overlaps(1)   # auto: a CPU runs XLA's expert
    layers = [{"qkv": jnp.zeros((4, 4))}]
    gpu = functools.partial(paths.first_step_overlap, platform="gpu")
    assert gpu("auto", "auto", 1, layers) and paths.OVERLAP_MAX_BATCH == 2   # measured faster at 1 and 2
    assert gpu("auto", "auto", 2, layers) and not gpu("auto", "auto", 3, layers) and not gpu("auto", "xla", 1, layers)
    assert gpu("on", "xla", 64, layers) and not gpu("off", "auto", 1, layers)
    with pytest.raises(ValueError, match="overlap must be"):
        Engine(config, params, cache_dir=False, overlap="yes")


# what a loop body must not compute from its invariants alone: each is a kernel, or a transcendental or reducing pass,
# every trip (adds, casts, slices and reshapes of invariants are left out: XLA fuses them into their users)
COSTLY = {"sin", "cos", "tan", "exp", "exp2", "log", "pow", "sqrt", "rsqrt", "tanh", "logistic", "erf", "div",
          "reduce_sum", "reduce_max", "reduce_min", "argmax", "argmin", "cumsum", "sort", "dot_general",
          "pallas_call"}


def _subjaxprs(eqn):
    return [v.jaxpr if isinstance(v, jax.extend.core.ClosedJaxpr) else v for v in eqn.params.values()
            if isinstance(v, (jax.extend.core.ClosedJaxpr, jax.extend.core.Jaxpr))]


def _costly_invariants(jaxpr, alike: list, found: list) -> list:
    """Walk jaxpr with `alike` (its inputs alike in every trip or not), appending each COSTLY equation whose inputs
    are all alike to found; -> its outputs' alike. A call's body is walked with its inputs' flags."""
    flags = dict(zip(jaxpr.invars, alike)) | {v: True for v in jaxpr.constvars}

    def flag(v):
        return isinstance(v, jax.extend.core.Literal) or flags[v]

    for eqn in jaxpr.eqns:
        ins, subs = [flag(v) for v in eqn.invars], _subjaxprs(eqn)
        if eqn.primitive.name in ("pjit", "closed_call", "custom_jvp_call", "custom_vjp_call") and subs \
                and len(subs[0].invars) == len(ins):
            outs = _costly_invariants(subs[0], ins, found)
        else:
            outs = [all(ins)] * len(eqn.outvars)
            if all(ins) and eqn.primitive.name in COSTLY:
                found.append(f"{eqn.primitive.name} -> {', '.join(str(v.aval) for v in eqn.outvars)}")
        flags.update(zip(eqn.outvars, outs))
    return [flag(v) for v in jaxpr.outvars]


def _loop_operands(eqn) -> tuple[int, int]:
    """A while's or scan's count of body constants and carried values. jax 0.11's scan gives its operands as a tree
    (`ft_in`: constants, carry, xs), jax 0.10's the counts (`num_consts`, `num_carry`)."""
    if eqn.primitive.name == "while":
        return eqn.params["body_nconsts"], len(eqn.params["body_jaxpr"].jaxpr.outvars)
    if "ft_in" in eqn.params:
        consts, carry, _ = map(list, eqn.params["ft_in"].update(eqn.invars).unpack())
        return len(consts), len(carry)
    return eqn.params["num_consts"], eqn.params["num_carry"]


def loop_invariant_ops(jaxpr) -> list[list[str]]:
    """For each loop (while, scan) in a jaxpr, the COSTLY ops of its body whose inputs are the same in every trip:
    its constants, or carried values the body passes on unchanged. Work that could be made once before the loop (on a
    GPU each is a kernel every trip, as XLA does not hoist it: docs/BENCHMARKS.md, session 71)."""
    loops = []
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name in ("while", "scan"):
            body = eqn.params["body_jaxpr" if name == "while" else "jaxpr"].jaxpr
            consts, carry = _loop_operands(eqn)
            passed = [out is inp for out, inp in zip(body.outvars[:carry], body.invars[consts:consts + carry])]
            found = []
            _costly_invariants(body, [True] * consts + passed + [False] * (len(body.invars) - consts - carry), found)
            loops.append(found)
        for sub in _subjaxprs(eqn):
            loops += loop_invariant_ops(sub)
    return loops


def call_loop_invariants(engine, obs, batch: int, steps: int) -> list[list[str]]:
    """`loop_invariant_ops` of the engine's last program of a call (the one with the denoise loop), as traced."""
    from pi0_jax.engine.runtime import shapes

    stage = engine.call_stages(batch, steps)[-1]
    fn, args = engine._stage(stage, shapes(engine.stage_weights(stage)), batch, steps, *engine.plan(obs))
    return loop_invariant_ops(jax.make_jaxpr(fn)(*args).jaxpr)


@pytest.mark.parametrize("attention", ["xla", "denoise=cudnn"])
def test_the_denoise_loop_makes_nothing_alike_in_every_step(model, attention):
    """No costly op of the denoise loop reads only what is alike in every step. That (RoPE's angles at the suffix's
    positions, the fused attention's key lengths) is made once before the loop (`programs.step_invariants`): XLA
    does not hoist it, and on a GPU each was a kernel every step (docs/BENCHMARKS.md, session 71). Read from the
    engine's program as traced, with XLA's and the fused denoise attention. (Before: sin, cos, pow and div of the
    angles, and the key lengths' reduce_sum, in every step.)"""
    config, params = model
    loops = call_loop_invariants(Engine(config, params, cache_dir=False, attention=attention), make_obs(config), 2, 3)
    assert loops and not any(loops), loops


def test_the_state_token_runs_once_a_call(monkeypatch):
    """π0's state token attends to the prefix and to itself alone, so on the XLA expert it runs through the expert
    once a call (its keys and values after the prefix, or in the fused attention's first suffix slot) and each step
    runs the action rows alone: the same actions as with the state's row in every step, in float32, with XLA's and
    with the fused attention; π0.5 (state in the prompt), the Pallas expert and the Pallas attention keep their
    layout."""
    from pi0_jax.engine import paths, programs

    config = get_config("dummy")
    params = randomize(pi0.param_shapes(config))
    obs = make_obs(config)
    noise = jax.random.normal(jax.random.key(5), (2, config.action_horizon, config.action_dim))
    e = config.action_expert
    kv = [jnp.zeros((2, 5, e.num_kv_heads, e.head_dim))] * e.depth
    cache = programs.PrefixCache(kv, kv, jnp.ones((2, 5), bool))
    got, rows = {}, {}
    for once, attention in ((True, "xla"), (True, "denoise=cudnn"), (False, "xla")):
        with monkeypatch.context() as m:
            if not once:
                m.setattr(paths, "cached_state", lambda *a, **k: False)
            engine = Engine(config, params, cache_dir=False, attention=attention)
            got[once, attention] = np.asarray(engine.sample_actions(obs, noise, 3))
            fixed = programs.step_invariants(config, engine.weights, cache, jnp.zeros((2, config.action_dim)), 2,
                                             "xla", paths.Attention.parse(attention), unroll=True)
            rows[once, attention] = fixed["positions"].shape[1], fixed["state_kv"] is not None
            if not once:   # the fused attention has no suffix mask: it needs the state out of the steps
                with pytest.raises(ValueError, match="cached_state"):
                    Engine(config, params, cache_dir=False, attention="denoise=cudnn").sample_actions(obs, noise, 3)
    for attention in ("xla", "denoise=cudnn"):
        np.testing.assert_allclose(got[True, attention], got[False, "xla"], rtol=1e-5, atol=1e-5)
    h = config.action_horizon
    assert rows == {(True, "xla"): (h, True), (True, "denoise=cudnn"): (h, True), (False, "xla"): (h + 1, False)}
    A = paths.Attention
    assert paths.cached_state(config, A(), "xla", 2, None)
    assert not paths.cached_state(get_config("dummy_pi05"), A(), "xla", 2, None)
    assert not paths.cached_state(config, A(), "pallas", 1, None)
    assert not paths.cached_state(config, A(denoise="pallas"), "xla", 8, None)


def test_the_in_projection_is_folded_into_the_time_mlp(monkeypatch):
    """π0's action in-projection and the time MLP's action half are one product (`weights.fold_action_in`), its bias
    through the MLP's weight too: the same actions as the two products in float32 (`step_velocity` is the Pallas
    expert's as well); a fold that dropped the bias's path moves them far off."""
    from pi0_jax.engine import programs

    config = get_config("dummy")
    params = randomize(pi0.param_shapes(config))
    params["action_in_proj"]["bias"] = jax.random.normal(jax.random.key(3), params["action_in_proj"]["bias"].shape)
    obs = make_obs(config)
    noise = jax.random.normal(jax.random.key(5), (2, config.action_horizon, config.action_dim))
    got = {}
    for folded in (True, False):
        with monkeypatch.context() as m:
            m.setattr(programs, "FOLD_ACTION_IN", folded)
            engine = Engine(config, params, cache_dir=False)
            got[folded] = np.asarray(engine.sample_actions(obs, noise, 3))
    assert engine.weights["top"]["action_time_in"]["kernel"].shape == (config.action_dim, config.action_expert.width)
    np.testing.assert_allclose(got[True], got[False], rtol=1e-5, atol=1e-5)
    with monkeypatch.context() as m:   # the bias left out of the fold
        m.setattr(weights_lib, "fold_action_in", lambda c, p, f=weights_lib.fold_action_in: {
            **f(c, p), "bias": jnp.zeros(c.action_expert.width)})
        off = np.asarray(Engine(config, params, cache_dir=False).sample_actions(obs, noise, 3))
    assert not np.allclose(off, got[False], rtol=1e-3, atol=1e-3)


def test_the_vision_tower_as_two_programs(model, monkeypatch):
    """Where the tower has more blocks than `runtime.VISION_SPLIT`, the call runs it as two programs: the first on
    the patch embedding and those blocks, the second on the others, the final norm and the projection, each
    handed only its own weights; the same actions as one program, bit for bit."""
    from pi0_jax.engine import runtime

    config, params = model
    obs = make_obs(config)
    noise = jax.random.normal(jax.random.key(5), (2, config.action_horizon, config.action_dim))
    want = np.asarray(Engine(config, params, cache_dir=False).sample_actions(obs, noise, 3))
    monkeypatch.setattr(runtime, "VISION_SPLIT", 1)
    engine = Engine(config, params, cache_dir=False)
    assert engine.call_stages(2, 3)[:2] == ("vision_head", "vision_tail")
    np.testing.assert_array_equal(np.asarray(engine.sample_actions(obs, noise, 3)), want)
    blocks = engine.weights["img"]["blocks"]
    head, tail = (engine.stage_weights(s)["img"] for s in ("vision_head", "vision_tail"))
    ids = lambda tree: [id(x) for x in jax.tree.leaves(tree)]   # noqa: E731 (the same buffers, not copies)
    assert ids(head["blocks"]) == ids(blocks[:1]) and ids(tail["blocks"]) == ids(blocks[1:])
    assert set(head) | set(tail) == set(engine.weights["img"])
    assert not Engine(config, params, cache_dir=False, unroll=False).splits_vision()


def test_gemm_library_per_program():
    """gemm="auto": cuBLAS for the program that runs the vision tower alone and for the prefix fill without the
    denoise loop at a small batch, XLA's choice for the others; FP8 weights always cuBLAS; off a GPU always XLA's
    ops."""
    from pi0_jax.engine import runtime
    from pi0_jax.ops import formats, matmul

    plain, fp8 = {"w": jnp.ones((4, 4))}, {"w": formats.quantize_fp8(jnp.ones((4, 4)))}
    lib = functools.partial(matmul.library, platform="gpu")
    assert lib(plain, "auto", vision_tower=True) == "cublas" and lib(plain, "auto") == "xla"
    assert lib(plain, "xla", vision_tower=True) == "xla" and lib(plain, "cublas") == "cublas"
    assert lib(fp8, "auto") == lib(fp8, "xla") == "cublas"
    small, large = matmul.PREFIX_CUBLAS_MAX_BATCH, matmul.PREFIX_CUBLAS_MAX_BATCH + 1
    assert lib(plain, "auto", prefix_batch=small) == "cublas" and lib(plain, "auto", prefix_batch=large) == "xla"
    assert lib(plain, "xla", prefix_batch=1) == "xla"
    assert runtime.library_keywords("prefix_first_step", 1) == {"vision_tower": False, "prefix_batch": 1}
    assert runtime.library_keywords("denoise_rest", 1)["prefix_batch"] is None
    assert runtime.library_keywords("prefix_denoise", 1)["prefix_batch"] is None   # the loop: slower on cuBLAS
    assert matmul.library(plain, "cublas", platform="cpu") == "xla"
    assert matmul.compiler_options(plain, "auto", platform="gpu", vision_tower=True) == {
        "xla_gpu_enable_triton_gemm": False}
    assert matmul.compiler_options(plain, "auto", platform="gpu") is None
    with pytest.raises(ValueError, match="gemm must be"):
        matmul.library(plain, "triton", platform="gpu")


def test_a_slow_gpu_allocator_is_named_in_a_warning(monkeypatch):
    """XLA_PYTHON_CLIENT_ALLOCATOR=vmm or platform slows every call (measured on an H200): on a GPU the engine says
    so, naming the allocator; jax's default allocator, or any allocator off a GPU, passes without a word."""
    import warnings

    from pi0_jax.engine import runtime

    for allocator in ("vmm", "Platform"):
        monkeypatch.setenv("XLA_PYTHON_CLIENT_ALLOCATOR", allocator)
        with pytest.warns(RuntimeWarning, match=f"XLA_PYTHON_CLIENT_ALLOCATOR={allocator.lower()}: .* slower"):
            assert runtime.check_allocator("gpu") == allocator.lower()
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert runtime.check_allocator("cpu") is None
    for allocator in ("bfc", "default", ""):
        monkeypatch.setenv("XLA_PYTHON_CLIENT_ALLOCATOR", allocator)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert runtime.check_allocator("gpu") is None
    monkeypatch.delenv("XLA_PYTHON_CLIENT_ALLOCATOR")
    assert runtime.check_allocator("gpu") is None


def test_no_recompilation_when_only_values_change(model, monkeypatch):
    """New input values reuse the call's programs, and a call after the first does not walk the weights to choose
    them (`Engine.call_programs`: the walk cost the host 0.12 ms before every call's first kernel)."""
    from pi0_jax.engine import paths

    config, params = model
    engine = Engine(config, params, cache_dir=False)
    compiles, walks = [], []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, *_, **__: compiles.append(name) if name == "/jax/core/compile/backend_compile_duration" else None)
    choose = paths.first_step_overlap   # on a GPU it walks the expert's weights (`expert_path`)
    monkeypatch.setattr(paths, "first_step_overlap", lambda *a, **k: walks.append(1) or choose(*a, **k))
    for seed in range(3):
        obs = make_obs(config, seed=seed)
        noise = jax.random.normal(jax.random.key(seed), (2, config.action_horizon, config.action_dim))
        jax.block_until_ready(engine.sample_actions(obs, noise, 2))
        if seed == 0:
            first, walked = len(compiles), len(walks)
    assert engine.num_compiled == 2   # a call is two programs: the vision tower, then the prefix and denoise
    assert len(compiles) == first, "new input values triggered a recompilation"
    assert walked > 0 and len(walks) == walked, "a later call walked the weights to choose its programs"


def test_each_program_takes_only_its_own_weights_and_the_call_equals_the_fused_program(model):
    """Every buffer a call takes costs the host before the first kernel runs: each stage program is compiled on its
    own weights (`STAGE_WEIGHTS`; the vision tower's halves on part of "img", `runtime.stage_tree`), and the call
    (vision, then prefix and denoise) equals the fused program."""
    from pi0_jax.engine import paths
    from pi0_jax.engine.runtime import STAGE_WEIGHTS

    config, params = model
    obs = make_obs(config)
    noise = jax.random.normal(jax.random.key(3), (2, config.action_horizon, config.action_dim))
    engine = Engine(config, params, cache_dir=False)
    cameras, bucket = engine.plan(obs)
    leaves = {k: len(jax.tree.leaves(v)) for k, v in engine.weights.items()}
    for stage, keys in STAGE_WEIGHTS.items():
        prog = engine.executable(stage, 2, 2, cameras, bucket)
        assert prog.keys == tuple(k for k in keys if k in engine.weights)
        # the compiled program's inputs: its weights' leaves, then the stage's other arguments
        weights_in = len(jax.tree.leaves(prog.compiled.args_info[0][0]))
        assert weights_in == len(jax.tree.leaves(engine.stage_weights(stage)))
        assert weights_in == sum(leaves[k] for k in prog.keys) or stage in ("vision_head", "vision_tail")
        assert weights_in < sum(leaves.values()) or stage == "infer"
    assert "img" not in engine.executable("prefix_denoise", 2, 2, cameras, bucket).keys
    fused = engine.executable("infer", 2, 2, cameras, bucket)(
        engine.weights, engine.schedule(2), *engine.pack(obs, cameras, bucket), jnp.array(noise))
    np.testing.assert_array_equal(engine.sample_actions(obs, jnp.array(noise), 2), fused)
    with pytest.raises(ValueError, match="chooses the expert's path by its weights"):
        paths.expert_path("auto", 1, None)


def test_prompt_buckets():
    assert [prompt_bucket(n, 200) for n in (0, 16, 17, 48, 49, 199)] == [16, 16, 32, 48, 64, 200]
    assert prompt_bucket(40, 48) == 48


_CHILD = textwrap.dedent("""
    import json, sys, jax
    import numpy as np
    hits = []
    jax.monitoring.register_event_listener(lambda name, **kw: hits.append(name))
    sys.path.insert(0, sys.argv[2])
    from pi0_jax import pi0
    from pi0_jax.config import get_config
    from pi0_jax.engine import Engine, store
    from test_model import make_obs
    store.PLATFORMS = ("cpu",)   # off on a CPU by default; here the two programs are all this process compiles
    config = get_config("dummy")
    params = jax.tree.map(lambda s: jax.numpy.full(s.shape, 0.01, s.dtype), pi0.param_shapes(config))
    engine = Engine(config, params, cache_dir=sys.argv[1])
    obs = make_obs(config)
    noise = np.random.default_rng(0).standard_normal((2, config.action_horizon, config.action_dim), np.float32)
    actions = np.asarray(engine.sample_actions(obs, noise, 2))
    print(json.dumps({"hits": hits.count("/jax/compilation_cache/cache_hits"),
                      "misses": hits.count("/jax/compilation_cache/cache_misses"),
                      "stored": engine.store.loaded, "actions": actions.ravel().tolist()}))
""")


def test_a_second_process_loads_the_programs_without_compiling(tmp_path):
    """The call's two programs come back from the program store (no tracing); what else the engine compiles (its
    weights' layout, the schedule) comes from XLA's persistent cache; the actions are the first process's."""
    tests_dir = str(__import__("pathlib").Path(__file__).parent)
    runs = []
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", _CHILD, str(tmp_path / "xla"), tests_dir], check=True,
                             capture_output=True, text=True).stdout
        runs.append(json.loads(out.strip().splitlines()[-1]))
    assert runs[0]["misses"] >= 1 and runs[0]["stored"] == 0
    assert runs[1]["stored"] == 2, runs[1]["stored"]
    assert runs[1]["hits"] >= 1 and runs[1]["misses"] == 0, runs
    assert len(list((tmp_path / "xla" / "programs").glob("*.pkl"))) == 2
    np.testing.assert_array_equal(runs[0]["actions"], runs[1]["actions"])


def test_the_geglu_product_is_formed_in_f32_from_the_rounded_halves():
    """`layers._mlp` in bf16 forms gelu(gate) * up as the product of the two bf16 values in f32, rounded to bf16 once:
    the dtype's own product (exact in f32). In that form XLA's cost model for an H100 reads the gate half inside the
    GeGLU pass; with the product in bf16 it wrote the gate half out in a pass of its own, 17 a prefix fill
    (docs/BENCHMARKS.md, sessions 82-83). No CPU test sees that GPU fusion; this one sees the form it needs."""
    d, f = 8, 16
    w = {"gate_up": jnp.ones((d, 2 * f), jnp.bfloat16), "down": jnp.ones((f, d), jnp.bfloat16)}
    jaxpr = jax.make_jaxpr(layers._mlp)(jnp.ones((1, 4, d), jnp.bfloat16), w).jaxpr
    made = {v: e for e in jaxpr.eqns for v in e.outvars}

    def op(v, name, dtype):
        e = made[v]
        assert e.primitive.name == name and e.outvars[0].aval.dtype == dtype, (e, name, dtype)
        return e

    down = [e for e in jaxpr.eqns if e.primitive.name == "dot_general"][-1]
    product = made[op(down.invars[0], "convert_element_type", jnp.bfloat16).invars[0]]
    assert product.primitive.name == "mul" and product.outvars[0].aval.dtype == jnp.float32, product
    for v in product.invars:   # gelu(gate) and up, each a bf16 value widened
        assert op(v, "convert_element_type", jnp.float32).invars[0].aval.dtype == jnp.bfloat16


def test_the_engines_gelu_is_jaxs_tanh_gelu():
    """`layers.gelu_tanh` (x sigmoid(2 z), the engine's GeGLU) is jax's GELU-tanh to f32 rounding, saturating alike
    (0 far left, x far right, no NaN from x³ overflowing); in bf16 within a rounding step of the f32 value of the
    same inputs (where jax's form, 1 + tanh z, cancels to 0 on the far left)."""
    x = jnp.concatenate([jnp.linspace(-12, 12, 20001, dtype=jnp.float32), jnp.array([-3e38, -1e20, 1e20, 3e38])])
    want = jax.nn.gelu(x, approximate=True)
    np.testing.assert_allclose(layers.gelu_tanh(x), want, rtol=1e-6, atol=1e-6)
    xb = x.astype(jnp.bfloat16)
    exact = jax.nn.gelu(xb.astype(jnp.float32), approximate=True)
    np.testing.assert_allclose(np.asarray(layers.gelu_tanh(xb), np.float32), exact, rtol=2.0**-7, atol=2.0**-9)
