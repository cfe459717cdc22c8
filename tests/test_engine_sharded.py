"""The engine's fused program on a batch-sharded mesh (two CPU devices in a child process, as the simulator's eval
runs it on several GPUs): samples are independent, so the partitioned program must hold no collective. Merging the
camera axis in front of the sharded batch axis (the vision tower's input) once made XLA all-gather every image; so
would the Pallas vision attention and LayerNorm, and the action expert's attention kernel, without their
partitioning rules."""

import os
import subprocess
import sys
import textwrap

CHILD = textwrap.dedent("""
    import sys
    import jax, jax.numpy as jnp, numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
    from pi0_jax import pi0
    from pi0_jax.config import get_config
    from pi0_jax.engine import paths, programs, weights
    from pi0_jax.engine.runtime import engine_weights
    from pi0_jax.sim.batching import collectives

    cfg = get_config("dummy_pi05")
    params = pi0.random_params(cfg, 0)
    w = engine_weights(cfg, params, unroll=True)
    sched = jax.jit(weights.precompute_schedule, static_argnums=(0, 2))(cfg, weights.schedule_params(cfg, params), 2)
    b, c, s, n = 4, cfg.num_cameras, cfg.image_size, cfg.max_token_len
    mesh = Mesh(np.array(jax.devices()), ("batch",))
    assert len(jax.devices()) == 2
    sh = lambda *spec: NamedSharding(mesh, P(*spec))
    images = jax.random.uniform(jax.random.key(0), (c, b, s, s, 3), minval=-1.0)
    args = (images, jnp.ones((c, b), bool), jnp.zeros((b, n), jnp.int32), jnp.ones((b, n), bool),
            jnp.zeros((b, cfg.action_dim)), jnp.zeros((b, cfg.action_horizon, cfg.action_dim)))
    shardings = (sh(), sh(), sh(None, "batch"), sh(None, "batch"), *(sh("batch"),) * 4)
    for attention in (paths.Attention(), paths.Attention(vision="pallas")):
        fn = jax.jit(lambda w, sc, *a: programs.infer(cfg, w, sc, *a, num_steps=2, unroll=True, unroll_steps=False,
                                                      attention=attention), in_shardings=shardings)
        print(attention.vision, "collectives", collectives(fn.lower(w, sched, *args).compile().as_text()))
        alone = jax.jit(lambda w, sc, *a: programs.infer(cfg, w, sc, *a, num_steps=2, unroll=True,
                                                         unroll_steps=False, attention=attention))
        np.testing.assert_allclose(fn(w, sched, *args), alone(w, sched, *args), rtol=1e-5, atol=1e-5)
    # π0's denoise on the Pallas attention in the XLA expert (auto at B = 3-16 on a GPU)
    cfg0 = get_config("dummy")
    params0 = pi0.random_params(cfg0, 0)
    w0 = engine_weights(cfg0, params0, unroll=True)
    sched0 = jax.jit(weights.precompute_schedule, static_argnums=(0, 2))(cfg0, weights.schedule_params(cfg0, params0),
                                                                        2)
    n0 = cfg0.max_token_len
    args0 = (*args[:2], jnp.zeros((b, n0), jnp.int32), jnp.ones((b, n0), bool), jnp.zeros((b, cfg0.action_dim)),
             jax.random.normal(jax.random.key(1), (b, cfg0.action_horizon, cfg0.action_dim)))
    run = lambda w, sc, *a: programs.infer(cfg0, w, sc, *a, num_steps=2, unroll=True, unroll_steps=False,
                                           attention=paths.Attention(denoise="pallas"))
    fn = jax.jit(run, in_shardings=shardings)
    print("denoise collectives", collectives(fn.lower(w0, sched0, *args0).compile().as_text()))
    alone0 = jax.jit(run)(w0, sched0, *args0)
    np.testing.assert_allclose(fn(w0, sched0, *args0), alone0, rtol=1e-5, atol=1e-5)
    # the same with the query heads folded into the kernel's rows (`blocks_at` folds from B = 8)
    import dataclasses
    from pi0_jax.ops import expert_kernels as ek
    at = ek.blocks_at
    ek.blocks_at = lambda batch: dataclasses.replace(at(batch), fold=True)
    fn = jax.jit(lambda w, sc, *a: run(w, sc, *a), in_shardings=shardings)
    print("folded collectives", collectives(fn.lower(w0, sched0, *args0).compile().as_text()))
    np.testing.assert_allclose(fn(w0, sched0, *args0), alone0, rtol=1e-5, atol=1e-5)
    ek.blocks_at = at
    # SigLIP's LayerNorm kernel (kernels="pallas"; the expert's GEMM kernels are for B <= 2 and not partitioned)
    enc = lambda w, im: programs.encode_images(cfg, w, im, unroll=True, kernels="pallas",
                                               attention=paths.Attention(vision="pallas"))
    sharded = jax.jit(enc, in_shardings=(None, sh(None, "batch")))
    print("layer_norm collectives", collectives(sharded.lower(w, images).compile().as_text()))
    np.testing.assert_allclose(sharded(w, images), jax.jit(enc)(w, images), rtol=1e-5, atol=1e-5)
    # with FP8 vision the kernels also take the GEMMs' scales and quantise their outputs
    from pi0_jax.quant import schemes
    calib = schemes.sample_observations(cfg, 1, seed=1)
    amax = schemes.calibrate(cfg, params, calib, "vision", percentile=None)["amax"]
    wq = engine_weights(cfg, schemes.quantize_params(params, "vision", amax), unroll=True)
    print("fp8 collectives", collectives(sharded.lower(wq, images).compile().as_text()))
    np.testing.assert_allclose(sharded(wq, images), jax.jit(enc)(wq, images), rtol=1e-5, atol=1e-5)
""")


def test_engine_program_on_a_batch_mesh_has_no_collectives():
    """π0.5 (adaRMS, no state token); π0's program differs only in the suffix, whose rows are per sample too."""
    # LLVM at -O0: the child takes 47 s instead of 61 on one core; the test reads its programs' HLO and results
    flags = "--xla_force_host_platform_device_count=2 --xla_backend_optimization_level=0"
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": flags}
    out = subprocess.run([sys.executable, "-c", CHILD], check=False, env=env, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "xla collectives 0" in out.stdout, out.stdout
    # the Pallas vision attention is a kernel XLA cannot split: without its own partitioning rule, 12 collectives here
    assert "pallas collectives 0" in out.stdout, out.stdout
    assert "layer_norm collectives 0" in out.stdout, out.stdout   # likewise for the LayerNorm kernel
    assert "denoise collectives 0" in out.stdout, out.stdout      # and the expert's attention kernel
    assert "folded collectives 0" in out.stdout, out.stdout       # also with its query heads folded into rows
    assert "fp8 collectives 0" in out.stdout, out.stdout
