"""Issue 15 (the origin roadmap, measured): latency with sync / naive / rtc execution, prefix reuse, layer dropping,
on the embedded trained pi0_small (pi0_jax/sim/realtime.py, pi0_jax/prune.py).

* One jitted rollout steps every policy variant side by side on copies of the same episodes (same initial states,
  same policy noise), so the physics compiles once: with D = 0 naive and rtc execute exactly the synchronous
  policy's actions (conditioned takes the plain path at D = 0 by construction), and so does prefix reuse with
  K = 1 (through the reuse path); an auto rule that never fires reuses the first plan's prefix (the same first
  chunk, a different second one); naive, rtc and conditioned with D = 2 hold still, then switch at index D, then
  execute the previous chunk's committed actions while the next one is computed; rtc's and conditioned's new chunks
  start with exactly those committed actions, and rtc's guided overlap lies closer to the previous chunk than the
  unguided (naive) sample from the same noise and observation; with its guidance clip β = 0, rtc samples naive's
  chunk (to f32 rounding), and `--rtc-beta` reaches the policy.
* The same rollout through the reference sampler (pi0.sample_actions, issue 14) equals the engine's: the same noise
  gives the same actions, so the same states, success flags and episode lengths.
* `pi0-jax eval --execution --latency-steps --reuse-prefix` end to end, with the recompute fraction of K = 2 in
  eval_info.
* `pi0-jax prune`: with no layers dropped it writes the original's config and every parameter bit for bit (so the
  same actions: the rollout's programs depend on nothing else); dropping layers 1, 2 writes a 2-layer model that
  loads and holds exactly the original's layers 0 and 3, with its tokenizer and norm stats.
"""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pi0_jax
from pi0_jax import checkpoint, cli
from pi0_jax import normalize as nz
from pi0_jax.policy import find_tokenizer
from pi0_jax.sim import policies
from pi0_jax.sim.env import Env
from pi0_jax.sim.realtime import Realtime, rtc_weights
from pi0_jax.sim.render import RenderConfig
from pi0_jax.tokenizer import PaligemmaTokenizer

EMBEDDED = Path(pi0_jax.__file__).parent / "assets" / "pi0_small"
TASKS = ("goal/red_block_on_plate", "object/blue_block_in_bowl")
RES, NUM_STEPS, R, D, REPLANS = 32, 3, 5, 2, 2

VARIANTS = {
    "plain": None,                                     # today's policy: the fused program, chunk as its state
    "naive0": Realtime("naive", 0),
    "rtc0": Realtime("rtc", 0),
    "reuse1": Realtime("sync", 0, "1"),
    "never": Realtime("sync", 0, "auto:1e9"),          # auto rule that never fires after the first plan
    "naive2": Realtime("naive", D),
    "rtc2": Realtime("rtc", D),
    "rtc2b0": Realtime("rtc", D, rtc_beta=0.0),        # no guidance: naive's sample, through the guided program
    "cond2": Realtime("conditioned", D),
    "reference": None,                                 # "plain" through the reference sampler instead of the engine
}
SAMPLER = {"reference": "reference"}                   # the others: the engine


def _chunk(ps):
    return ps if isinstance(ps, jax.Array) else ps["chunk"]


@pytest.fixture(scope="module")
def pruned(tmp_path_factory):
    root = tmp_path_factory.mktemp("pruned")
    assert cli.main(["prune", str(EMBEDDED), str(root / "none"), "--drop-layers", "none"]) == 0
    assert cli.main(["prune", str(EMBEDDED), str(root / "p2"), "--drop-layers", "1,2"]) == 0
    return root


@pytest.fixture(scope="module")
def rollout():
    """Every variant on the same 2 episodes for REPLANS plans of R steps: executed actions (steps, V, m, 7), each
    plan's chunk per variant (REPLANS, V, m, H, 7), and the final policy states."""
    config, params = checkpoint.load_checkpoint(EMBEDDED, dtype="float32")
    config = config.replace(dtype="float32")
    tok = PaligemmaTokenizer(find_tokenizer(EMBEDDED), config.max_token_len)
    normalizer = nz.load_normalizer(EMBEDDED, use_quantiles=False)
    env = Env(TASKS, RenderConfig(RES, RES))
    pols = [policies.model_policy(config, params, tok, normalizer, env, num_steps=NUM_STEPS, realtime=rt,
                                  replan_steps=R, sampler=SAMPLER.get(name, "engine")) for name, rt in VARIANTS.items()]
    m, v = len(TASKS), len(VARIANTS)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), m), jnp.arange(m), jnp.array([2, 9]))
    qpos0 = np.asarray(state.data.qpos)
    state = jax.tree.map(lambda x: jnp.concatenate([x] * v), state)      # variant-major copies
    keys = jax.random.split(jax.random.key(1), m)

    def part(tree, i):
        return jax.tree.map(lambda x: x[i * m:(i + 1) * m], tree)

    def run(params_all, state, keys):
        def replan(carry, _):
            state, pss, keys = carry
            split = jax.vmap(jax.random.split)(keys)
            keys, sub = split[:, 0], split[:, 1]
            obs = jax.vmap(env.observe)(state)
            pss = tuple(p.plan(pp, ps, part(obs, i), part(state, i), sub)
                        for i, (p, pp, ps) in enumerate(zip(pols, params_all, pss)))

            def inner(c, k):
                state, pss = c
                acts = [p.act(ps, part(state, i), k)[0] for i, (p, ps) in enumerate(zip(pols, pss))]
                state = jax.vmap(env.step)(state, jnp.concatenate(acts))
                return (state, pss), jnp.stack(acts)

            (state, pss), acts = jax.lax.scan(inner, (state, pss), jnp.arange(R))
            return (state, pss, keys), (acts, jnp.stack([_chunk(ps) for ps in pss]))

        pss = tuple(p.init(m) for p in pols)
        (state, pss, _), (acts, chunks) = jax.lax.scan(replan, (state, pss, keys), None, length=REPLANS)
        return acts.reshape((-1,) + acts.shape[2:]), chunks, state, pss

    # The ten variants' rollout is one large program whose XLA:CPU compile is most of this module's time; like the
    # module's other programs it compiles with LLVM at -O0 (conftest.py: about 35 s instead of 80, and it runs 2 s
    # slower). The test compares variants inside this program.
    acts, chunks, state, pss = jax.jit(run)(tuple(p.params for p in pols), state, keys)
    return {"acts": np.asarray(acts), "chunks": np.asarray(chunks), "state": state, "pss": pss, "qpos0": qpos0,
            "index": {k: i for i, k in enumerate(VARIANTS)}, "horizon": config.action_horizon}


def test_zero_latency_modes_and_reuse_every_plan_equal_the_sync_policy(rollout):
    acts, ix, state = rollout["acts"], rollout["index"], rollout["state"]
    done = np.asarray(state.success).reshape(len(VARIANTS), -1)
    for name in ("naive0", "rtc0", "reuse1"):
        np.testing.assert_array_equal(acts[:, ix[name]], acts[:, ix["plain"]], err_msg=name)
        np.testing.assert_array_equal(done[ix[name]], done[ix["plain"]], err_msg=name)
    assert np.abs(acts[:, ix["plain"]]).max() > 0.05          # the policy moves: equality is not vacuous


def test_reference_sampler_rollout_equals_the_engine_rollout(rollout):
    """Issue 14: the embedded trained model's rollout with the engine policy equals the rollout with the reference
    sampler: the same noise gives the same actions, so the same states, success flags and episode lengths."""
    acts, ix, state = rollout["acts"], rollout["index"], rollout["state"]
    eng, ref = ix["plain"], ix["reference"]

    def per_variant(x):
        x = np.asarray(x)
        return x.reshape((len(VARIANTS), -1) + x.shape[1:])

    qpos = per_variant(state.data.qpos)
    assert np.abs(qpos[eng] - rollout["qpos0"]).max() > 1e-3   # the arm moved: the policy's actions were executed
    np.testing.assert_allclose(acts[:, ref], acts[:, eng], atol=1e-4)
    np.testing.assert_allclose(qpos[ref], qpos[eng], atol=1e-4)
    np.testing.assert_array_equal(per_variant(state.success)[ref], per_variant(state.success)[eng])
    np.testing.assert_array_equal(per_variant(state.length)[ref], per_variant(state.length)[eng])


def test_prefix_reuse_keeps_the_cached_prefix(rollout):
    chunks, ix, pss = rollout["chunks"], rollout["index"], rollout["pss"]
    np.testing.assert_array_equal(chunks[0, ix["never"]], chunks[0, ix["plain"]])   # plan 0 computes the prefix
    assert np.abs(chunks[1, ix["never"]] - chunks[1, ix["plain"]]).max() > 1e-4     # plan 1 reuses plan 0's
    never = pss[ix["never"]]
    np.testing.assert_array_equal(np.asarray(never["recomputed"]), 1)   # of REPLANS plans
    np.testing.assert_array_equal(np.asarray(never["plans"]), REPLANS)


def test_latency_switches_chunks_at_the_delay(rollout):
    acts, chunks, ix = rollout["acts"], rollout["chunks"], rollout["index"]
    hold = np.zeros(7, np.float32)
    hold[6] = -1.0
    for name in ("naive2", "rtc2", "cond2"):
        a, c = acts[:, ix[name]], chunks[:, ix[name]]
        np.testing.assert_array_equal(a[:D], np.broadcast_to(hold, a[:D].shape))   # no chunk yet: hold still
        for j in range(REPLANS):
            t = j * R
            np.testing.assert_array_equal(a[t + D: t + R], c[j][:, D:R].transpose(1, 0, 2))
            if j:
                np.testing.assert_array_equal(a[t: t + D], c[j - 1][:, R:R + D].transpose(1, 0, 2))


def test_rtc_freezes_the_committed_prefix_and_guides_the_overlap(rollout):
    chunks, ix, h = rollout["chunks"], rollout["index"], rollout["horizon"]
    rtc, naive = chunks[:, ix["rtc2"]], chunks[:, ix["naive2"]]
    np.testing.assert_array_equal(rtc[0], naive[0])          # first plan: nothing committed, same sample
    for j in range(1, REPLANS):
        np.testing.assert_array_equal(rtc[j][:, :D], rtc[j - 1][:, R:R + D])
    # plan 1 sees the same observation and noise in both (identical trajectories so far): guidance alone pulls the
    # overlap (weights 0.49, 0.19, 0.04 here) towards the previous chunk; measured 0.62x unweighted
    w = rtc_weights(h, D, R)[D: h - R]
    assert w.min() > 0

    def err(c):
        return float((np.abs(c[1][:, D: h - R] - c[0][:, R + D:]).mean(axis=(0, 2)) * w).sum() / w.sum())

    assert err(rtc) < 0.8 * err(naive), (err(rtc), err(naive))
    # β = 0: the guided program's update is the plain one, so its chunks are naive's after the frozen prefix
    unguided = chunks[:, ix["rtc2b0"]]
    np.testing.assert_allclose(unguided[1][:, D:], naive[1][:, D:], rtol=0, atol=1e-5)
    assert np.abs(rtc[1][:, D:] - naive[1][:, D:]).max() > 1e-3


def test_rtc_beta_reaches_the_policy(monkeypatch, tmp_path):
    """`pi0-jax eval --rtc-beta` travels through EvalConfig into the model policy's Realtime; a negative clip is
    refused by name."""
    from pi0_jax.sim import evaluate as evaluate_mod

    seen = {}

    class Stop(Exception):
        pass

    def capture(spec, env, replan_steps, **kw):
        seen["realtime"] = kw["realtime"]
        raise Stop

    monkeypatch.setattr(evaluate_mod, "make_policy", capture)
    with pytest.raises(Stop):
        cli.main(["eval", "--policy", str(EMBEDDED), "--suite", TASKS[0], "--episodes-per-task", "1", "--batch", "1",
                  "--steps", "5", "--videos", "0", "--execution", "rtc", "--latency-steps", "2", "--rtc-beta", "0.5",
                  "--output-dir", str(tmp_path), "--no-progress"])
    assert seen["realtime"] == Realtime("rtc", 2, None, 0.5)
    with pytest.raises(ValueError, match="rtc_beta"):
        Realtime("rtc", 2, rtc_beta=-1.0)


def test_conditioned_chunks_start_with_the_committed_actions(rollout):
    """Training-time action conditioning: every plan's chunk starts with exactly the D actions committed while it was
    computed (the first plan: the hold chunk), and the model samples the rest given them (the embedded model was not
    trained so: this checks the plumbing, not the benefit)."""
    chunks, ix = rollout["chunks"], rollout["index"]
    cond, naive = chunks[:, ix["cond2"]], chunks[:, ix["naive2"]]
    hold = np.zeros(7, np.float32)
    hold[6] = -1.0
    np.testing.assert_array_equal(cond[0][:, :D], np.broadcast_to(hold, cond[0][:, :D].shape))
    for j in range(1, REPLANS):
        np.testing.assert_array_equal(cond[j][:, :D], cond[j - 1][:, R:R + D])
    assert np.abs(cond[0][:, D:] - naive[0][:, D:]).max() > 1e-3     # same noise and frames, conditioned otherwise


def test_delayed_expert_executes_its_actions_d_steps_late():
    """scripts/expert_latency.py's policy: the expert's action from the state at step t runs at t + D (hold still
    before), and a lower gain commands proportionally less motion."""
    env = Env(TASKS[:1], RenderConfig(RES, RES))
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), 1), jnp.zeros(1, jnp.int32),
                                         jnp.zeros(1, jnp.int32))
    now, late, slow = (policies.expert_policy(env, d, g) for d, g in ((0, 1.5), (3, 1.5), (0, 0.5)))
    want, _ = jax.jit(now.act)(now.init(1), state, 0)
    act = jax.jit(late.act)
    ps, got = late.init(1), []
    for k in range(5):        # the same state every step: the expert's phase does not move on
        a, ps = act(ps, state, k)
        got.append(np.asarray(a[0]))
    hold = np.zeros(7, np.float32)
    hold[6] = -1.0
    np.testing.assert_array_equal(np.stack(got[:3]), np.broadcast_to(hold, (3, 7)))
    np.testing.assert_array_equal(got[3], np.asarray(want[0]))
    assert np.abs(np.asarray(want[0, :3])).max() > 0.05                     # it moves: the check is not vacuous
    third, _ = jax.jit(slow.act)(slow.init(1), state, 0)
    rot, rot_third = np.asarray(want[0, 3:6]), np.asarray(third[0, 3:6])
    assert 0.01 < np.abs(rot).max() < 0.8                                   # below the clip: the gain scales linearly
    np.testing.assert_allclose(rot_third, rot / 3, rtol=1e-5)


def test_rtc_weights_follow_the_paper():
    w = rtc_weights(10, 2, 5)
    assert w[:2].tolist() == [1.0, 1.0] and (w[5:] == 0).all()
    assert 1.0 > w[2] > w[3] > w[4] > 0.0


@pytest.mark.optimized   # its time is MJX's run
def test_eval_cli_latency_execution_reuse(tmp_path, capsys):
    out = tmp_path / "eval"
    assert cli.main(["eval", "--policy", str(EMBEDDED), "--suite", TASKS[0], "--episodes-per-task", "2",
                     "--batch", "2", "--steps", "10", "--resolution", str(RES), "--videos", "0", "--num-steps",
                     str(NUM_STEPS), "--dtype", "float32", "--execution", "naive", "--latency-steps", "4",
                     "--reuse-prefix", "2", "--output-dir", str(out), "--no-progress"]) == 0
    info = json.loads((out / "eval_info.json").read_text())
    rt = info["realtime"]
    assert (rt["execution"], rt["latency_steps"], rt["latency_ms"], rt["reuse_prefix"]) == ("naive", 4, 200.0, "2")
    assert rt["plans"] == 4 and rt["prefix_recompute_fraction"] == 0.5      # 2 episodes x plans at steps 0, 5
    assert [e["length"] for e in info["per_episode"]] == [10, 10]           # one env step per control step
    assert "200 ms" in capsys.readouterr().out
    with pytest.raises(ValueError, match="replan_steps"):
        cli.main(["eval", "--policy", str(EMBEDDED), "--suite", TASKS[0], "--episodes-per-task", "1", "--batch",
                  "1", "--steps", "5", "--videos", "0", "--execution", "naive", "--latency-steps", "6",
                  "--no-progress"])
    for flags, field in ((["--latency-steps", "-1"], "latency_steps"), (["--rtc-beta", "-1"], "rtc_beta"),
                         (["--reuse-prefix", "auto:x"], "auto:x")):   # out of range: a line, no traceback
        with pytest.raises(SystemExit, match=f"pi0-jax eval: .*{field}"):
            cli.main(["eval", "--policy", str(tmp_path / "not_loaded"), "--execution", "rtc", *flags])


def test_prune_drops_layers_and_nothing_changes_nothing(pruned, tmp_path):
    from pi0_jax.train.distill import slice_layers

    _, full = checkpoint.load_checkpoint(EMBEDDED)
    same_config, same = checkpoint.load_checkpoint(pruned / "none")
    assert same_config == checkpoint.load_checkpoint(EMBEDDED)[0]
    assert jax.tree.structure(same) == jax.tree.structure(full)
    for a, b in zip(jax.tree.leaves(same), jax.tree.leaves(full)):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    meta = checkpoint.read_meta(pruned / "p2")
    assert meta["pruned"]["kept_layers"] == [0, 3] and meta["model"]["paligemma_variant"] == "gemma_small_2l"
    assert (pruned / "p2" / "tokenizer.model").is_file()
    assert (pruned / "p2" / "assets" / "mjx_suite" / "norm_stats.json").is_file()
    # the pruned checkpoint loads (shapes checked against its 2-layer config) and holds the original's layers 0, 3
    config, params = checkpoint.load_checkpoint(pruned / "p2")
    assert config.paligemma.depth == config.action_expert.depth == 2
    flat, want = jax.tree_util.tree_flatten_with_path(params)[0], slice_layers(full, (0, 3))
    assert len(flat) == len(jax.tree.leaves(want))
    for (path, a), b in zip(flat, jax.tree.leaves(want)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=jax.tree_util.keystr(path))
    assert any(np.shape(a) != np.shape(b) for a, b in zip(jax.tree.leaves(full), jax.tree.leaves(want)))
    with pytest.raises(ValueError, match="layers 0..3"):
        cli.main(["prune", str(EMBEDDED), str(tmp_path / "bad"), "--drop-layers", "4"])


def test_roadmap_grid_cells_and_cost(tmp_path):
    """scripts/roadmap_grid.py: KIND[-dD][-rR][-bBETA][@N] names parse into the eval settings they claim, the cost per
    control step divides by the cell's own replan interval (the 2.31x row of RESULTS.md), and a chart is written
    only where it has points (no cost chart without timings, no delay chart without a delayed cell)."""
    import importlib.util
    import sys
    from types import SimpleNamespace

    path = Path(__file__).parents[1] / "scripts" / "roadmap_grid.py"
    sys.path.insert(0, str(path.parent))
    try:
        spec = importlib.util.spec_from_file_location("roadmap_grid", path)
        grid = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(grid)
    finally:
        sys.path.remove(str(path.parent))
    args = SimpleNamespace(latency_steps=4, num_steps=10, replan_steps=5, auto_threshold=0.1, rtc_beta=5.0)
    assert grid.cell_spec("sync-r6@1", args) == {"kind": "sync", "execution": "sync", "latency_steps": 0,
                                                 "reuse_prefix": None, "num_steps": 1, "replan_steps": 6}
    assert grid.cell_spec("rtc-d1", args)["latency_steps"] == 1 and grid.cell_spec("rtc", args)["latency_steps"] == 4
    assert grid.cell_spec("reuse2@1", args)["reuse_prefix"] == "2"
    assert grid.cell_spec("rtc", args)["rtc_beta"] == 5.0 and grid.cell_spec("rtc-d1-b0.5", args)["rtc_beta"] == 0.5
    for bad in ("sync-d2", "naive-x3", "reuse", "naive-d", "naive-b1", "rtc-b", "rtc-b1.2.3"):
        with pytest.raises(SystemExit):
            grid.cell_spec(bad, args)
    t = {"full": {"vision": 3.74, "prefix": 5.23, "denoise_at": {"1": 2.40, "10": 12.93}}}
    base = {"kind": "sync", "num_steps": 10}
    fast = {"kind": "sync", "num_steps": 1, "replan_steps": 6}
    assert grid.cost_per_step(base, t, 5) == pytest.approx((3.74 + 5.23 + 12.93) / 5)
    assert grid.cost_per_step(base, t, 5) / grid.cost_per_step(fast, t, 5) == pytest.approx(2.31, abs=0.01)
    assert grid.guess_key(fast, {"replan_steps": 5}) == "chunk"
    rows = [{"cell": "sync", "kind": "sync", "num_steps": 10, "latency_steps": 0, "latency_ms": 0.0,
             "pc_success": 90.0, "ci95": [87.0, 92.0]},
            {"cell": "rtc-d1-b1", "kind": "rtc", "rtc_beta": 1.0, "num_steps": 10, "latency_steps": 1,
             "latency_ms": 50.0, "pc_success": 80.0, "ci95": [76.0, 83.0]}]
    result = {"rows": rows[:1], "timing": None, "num_steps": 10, "replan_steps": 5, "episodes": 550,
              "checkpoint_model": "pi0_small", "device": "cpu"}
    assert not grid.chart(result, tmp_path / "cost.png") and not grid.delay_chart(result, tmp_path / "delay.png")
    assert not (tmp_path / "cost.png").exists() and not (tmp_path / "delay.png").exists()
    result["rows"] = rows
    assert grid.delay_chart(result, tmp_path / "delay.png") and (tmp_path / "delay.png").stat().st_size > 10_000
