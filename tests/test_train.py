"""pi0_jax.train on CPU: the loss goes down, resume is bit-identical, the export loads as a Policy, the tokenizer
covers the suite, the norm stats are numpy's. One module fixture trains once (the step compiles once per process)."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax import normalize as nz
from pi0_jax import pi0
from pi0_jax.tokenizer import PaligemmaTokenizer
from pi0_jax.train import augment, data, step, trainer
from pi0_jax.train.config import get_train_config

STEPS = 20
CFG = get_train_config("dummy_smoke", steps=STEPS, log_every=5, save_every=10, augment=False)


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    # 56 px like the model: no resize; 11 episodes, one per suite prompt, each its own colour
    return data.synthetic_demos(tmp_path_factory.mktemp("demos"), episodes=11, length=16, resolution=56)


def _train_cli(demos, out):
    """20 steps through `pi0-jax train` (the same TrainConfig as CFG, so the jitted step is shared)."""
    from pi0_jax import cli

    assert cli.main(["train", "--config", "dummy_smoke", "--demos", str(demos), "--out", str(out), "--steps", str(STEPS),
                     "--log-every", "5", "--save-every", "10", "--no-augment"]) == 0
    return out, json.loads((out / "train_config.json").read_text())


def test_train_resume_export(demos, tmp_path):
    """One test, so that one xdist worker compiles the train step once: the loss goes down, an interrupted and
    resumed run is bit-identical to the straight one, and the export loads as a Policy."""
    straight = _train_cli(demos, tmp_path / "straight")
    _check_loss_decreases(demos, straight)
    _check_resume_is_bit_identical(demos, straight, tmp_path / "resumed")
    _check_export_loads_as_policy(straight, demos)


def _state(out, step_count):
    model = CFG.model_config
    template = jax.eval_shape(lambda: step.init_state(CFG, model))
    return trainer.restore_state(out / "train_state" / f"{step_count:08d}", template, step.replicated(step.make_mesh()))


def _check_loss_decreases(demos, straight):
    out, _ = straight
    model, cfg = CFG.model_config, CFG.replace(augment=False)
    ds = data.load_demos(demos, data.suite_prompts(), out / "tokenizer.model", model.max_token_len, log=None)
    dev = step.device_data(ds, data.norm_stats(ds), step.make_mesh())
    init = step.init_state(CFG, model).params
    final = _state(out, STEPS)
    loss = jax.jit(lambda p, k: step.batch_loss(cfg, model, p, dev, k))
    keys = [jax.random.key(100 + i) for i in range(4)]   # the same 4 fixed batches (frames, noise, t) for both
    before = np.mean([float(loss(init, k)) for k in keys])
    after = np.mean([float(loss(final.params, k)) for k in keys])
    after_ema = np.mean([float(loss(final.ema, k)) for k in keys])
    assert after < 0.7 * before, (before, after)
    assert after_ema < 0.8 * before, (before, after_ema)
    log = json.loads((out / "train_log.json").read_text())["log"]
    assert [r["step"] for r in log] == [5, 10, 15, 20]
    assert all(np.isfinite(r["loss"]) and r["samples_per_s"] > 0 for r in log)
    assert (out / "loss.png").stat().st_size > 1000


def _check_resume_is_bit_identical(demos, straight, tmp_path):
    out, _ = straight
    first = trainer.train(CFG, demos, tmp_path, stop_at=10, log=lambda _: None)
    assert first["stopped_at"] == 10 and not (tmp_path / "checkpoint").exists()
    with pytest.raises(FileExistsError):
        trainer.train(CFG, demos, tmp_path, log=lambda _: None)      # no silent restart over a run
    trainer.train(CFG, demos, tmp_path, resume=True, log=lambda _: None)
    a, b = jax.tree.leaves(_state(out, STEPS)), jax.tree.leaves(_state(tmp_path, STEPS))
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert np.asarray(x).tobytes() == np.asarray(y).tobytes()
    # the comparison can fail: the state 10 steps earlier differs
    c = jax.tree.leaves(_state(tmp_path, 10))
    assert any(np.asarray(x).tobytes() != np.asarray(z).tobytes() for x, z in zip(a, c))
    log_a = json.loads((out / "train_log.json").read_text())["log"]
    log_b = json.loads((tmp_path / "train_log.json").read_text())["log"]
    assert [r["loss"] for r in log_a] == [r["loss"] for r in log_b]


def _check_export_loads_as_policy(straight, demos):
    from pi0_jax.policy import Policy

    out, train_config = straight
    assert train_config["train"] == CFG.to_json()
    policy = Policy.from_checkpoint(out / "checkpoint")
    assert policy.action_dims == 7 and policy.config.num_cameras == 2
    ep = np.load(demos / "episode_000003.npz")
    result = policy.infer({"observation/image": ep["agentview"][0], "observation/wrist_image": ep["wrist"][0],
                           "observation/state": ep["state"][0], "prompt": str(ep["prompt"])})
    assert result["actions"].shape == (CFG.model_config.action_horizon, 7)
    assert np.isfinite(result["actions"]).all()
    meta = json.loads((out / "checkpoint" / "config.json").read_text())
    assert meta["weights"] == "ema" and meta["step"] == STEPS
    stats = nz.load_openpi_norm_stats(out / "checkpoint" / "assets" / trainer.ASSET_ID / "norm_stats.json")
    np.testing.assert_array_equal(stats["actions"].mean, nz.load_openpi_norm_stats(out / "norm_stats.json")["actions"].mean)


def test_init_fine_tunes_a_checkpoint_to_another_horizon(demos, tmp_path):
    """`pi0-jax train --init CKPT --horizon 12`: the run starts from CKPT's weights (with a zero learning rate and no
    EMA the export equals them; CKPT was drawn from another seed than the run's, so a fresh init would not), keeps
    CKPT's tokenizer and norm stats, and exports a model that samples 12-action chunks. The optimiser and --keep flags
    reach the trainer's config."""
    from pi0_jax import checkpoint as ckpt_lib
    from pi0_jax import cli
    from pi0_jax.policy import Policy

    src_cfg = CFG.replace(seed=7)
    src = tmp_path / "src"
    src.mkdir()
    (src / "tokenizer.model").write_bytes(data.train_tokenizer(data.suite_prompts()))
    model = src_cfg.model_config
    ds = data.load_demos(demos, data.suite_prompts(), src / "tokenizer.model", model.max_token_len, log=None)
    stats = data.norm_stats(ds)
    stats["state"] = dataclasses.replace(stats["state"], mean=stats["state"].mean + 1.0)   # not what the demos give
    nz.save_openpi_norm_stats(src / "norm_stats.json", stats)
    ckpt = trainer.export(src_cfg, step.init_state(src_cfg, model), src)

    out = tmp_path / "run"
    assert cli.main(["train", "--config", "dummy_smoke", "--demos", str(demos), "--out", str(out), "--init", str(ckpt),
                     "--horizon", "12", "--max-delay", "3", "--steps", "2", "--lr", "0", "--ema", "0",
                     "--decay-lr", "0", "--clip-norm", "0.5", "--weight-decay", "0", "--b2", "0.9", "--keep", "1",
                     "--log-every", "1", "--save-every", "1", "--no-augment"]) == 0
    got_cfg, got = ckpt_lib.load_checkpoint(out / "checkpoint")
    _, want = ckpt_lib.load_checkpoint(ckpt)
    assert got_cfg.action_horizon == 12 and model.action_horizon != 12
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(got), jax.tree.leaves(want)):
        np.testing.assert_array_equal(a, b, err_msg=jax.tree_util.keystr(path))
    assert (out / "tokenizer.model").read_bytes() == (src / "tokenizer.model").read_bytes()
    np.testing.assert_array_equal(nz.load_openpi_norm_stats(out / "norm_stats.json")["state"].mean,
                                  stats["state"].mean)
    saved = json.loads((out / "train_config.json").read_text())
    assert saved["init"] == str(ckpt.absolute()) and saved["train"]["max_delay"] == 3
    # the optimiser flags (none at the preset's value) reach the trainer's TrainConfig; --keep 1 leaves 1 of 2 states
    assert {k: saved["train"][k] for k in ("decay_lr", "clip_norm", "weight_decay", "b2", "keep")} == {
        "decay_lr": 0.0, "clip_norm": 0.5, "weight_decay": 0.0, "b2": 0.9, "keep": 1}
    assert [p.name for p in (out / "train_state").iterdir()] == ["00000002"]
    ep = np.load(demos / "episode_000003.npz")
    result = Policy.from_checkpoint(out / "checkpoint").infer(
        {"observation/image": ep["agentview"][0], "observation/wrist_image": ep["wrist"][0],
         "observation/state": ep["state"][0], "prompt": str(ep["prompt"])})
    assert result["actions"].shape == (12, 7)


def test_max_delay_gives_the_first_actions_clean_and_leaves_them_out_of_the_loss():
    """Training-time action conditioning: the first d actions ride at t = 0, where x_t is the clean action whatever
    the noise, and the loss skips them; so the noise drawn for them changes nothing, while without it it does."""
    model = CFG.model_config
    params = pi0.random_params(model, 0)
    obs = pi0.fake_observation(model, 4)
    h, a = model.action_horizon, model.action_dim
    actions, noise, other = (jax.random.normal(jax.random.key(i), (4, h, a)) for i in range(3))
    t = jnp.full((4,), 0.7)
    rng = jax.random.key(5)
    d = jax.random.randint(rng, (4,), 0, 4)
    assert int(d.min()) < 3 and int(d.max()) > 0       # this draw exercises both ends
    mixed = jnp.where((jnp.arange(h) < d[:, None])[..., None], other, noise)   # new noise under the given actions
    loss = jax.jit(step.flow_loss, static_argnums=(0, 1))
    cond = CFG.replace(max_delay=3)
    assert float(loss(cond, model, params, obs, actions, noise, t, rng)) == pytest.approx(
        float(loss(cond, model, params, obs, actions, mixed, t, rng)), rel=1e-6)
    assert abs(float(loss(CFG, model, params, obs, actions, noise, t, rng))
               - float(loss(CFG, model, params, obs, actions, mixed, t, rng))) > 1e-4


@pytest.mark.parametrize("flag, value", [("--clip-norm", "0"), ("--weight-decay", "-0.1"), ("--b2", "1"),
                                         ("--keep", "0"), ("--lr", "-1"), ("--decay-lr", "-1")])
def test_cli_rejects_an_optimiser_flag_out_of_range(flag, value, tmp_path):
    from pi0_jax import cli

    with pytest.raises(SystemExit, match=f"pi0-jax train: {flag[2:].replace('-', '_')} must"):   # no traceback
        cli.main(["train", "--config", "dummy_smoke", "--demos", str(tmp_path), "--out", str(tmp_path), flag, value])


def test_cli_help_explains_every_flag(capsys, cli_options):
    from pi0_jax import cli

    with pytest.raises(SystemExit) as e:
        cli.main(["train", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    flags = ("--config", "--demos", "--out", "--resume", "--steps", "--batch", "--lr", "--warmup", "--ema",
             "--no-augment", "--seed", "--log-every", "--save-every", "--stop-at", "--max-episodes", "--init",
             "--horizon", "--max-delay", "--decay-lr", "--clip-norm", "--weight-decay", "--b2", "--keep")
    for flag in flags:
        assert flag in out
    cli_options("train", flags)     # each flag defined by the parser, every option with help
    assert "pi0_small_suite" in out


def test_tokenizer_covers_suite(tmp_path):
    from pi0_jax.config import get_config

    prompts = data.suite_prompts()
    model_bytes = data.train_tokenizer(prompts, 128)
    assert model_bytes == data.train_tokenizer(prompts, 128)        # deterministic
    path = tmp_path / "tokenizer.model"
    path.write_bytes(model_bytes)
    max_len = get_config("pi0_small").max_token_len
    tok = PaligemmaTokenizer(path, max_len)
    assert tok.vocab_size <= 128 and (tok.pad_id, tok.eos_id, tok.bos_id) == (0, 1, 2)
    assert len(tok.encode("\n")) == 1
    tokens, masks = data.tokenize_prompts(path, prompts, max_len)
    assert tokens.shape == (len(prompts), max_len) and masks[:, 0].all() and not masks[:, -1].any()
    assert len({tuple(t) for t in tokens}) == len(prompts)              # every prompt distinct
    for p, t, m in zip(prompts, tokens, masks):
        assert tok.decode(t[m][1:-1]) == p
    with pytest.raises(ValueError, match="does not know"):
        data.tokenize_prompts(path, ["pick up the 7 zebras"], max_len)
    with pytest.raises(ValueError, match="max_token_len"):
        data.tokenize_prompts(path, [" ".join(prompts)], max_len)


def test_norm_stats_and_chunks(tmp_path):
    demos = data.synthetic_demos(tmp_path / "d", episodes=3, length=7, resolution=8)
    tok = tmp_path / "tok.model"
    tok.write_bytes(data.train_tokenizer(data.suite_prompts()))
    ds = data.load_demos(demos, data.suite_prompts(), tok, 32, log=None)
    raw = [np.load(demos / f"episode_{i:06d}.npz") for i in range(3)]
    actions = np.concatenate([r["actions"] for r in raw]).astype(np.float64)
    stats = data.norm_stats(ds)
    np.testing.assert_allclose(stats["actions"].mean, actions.mean(0), rtol=1e-12)
    np.testing.assert_allclose(stats["actions"].std, actions.std(0), rtol=1e-12)
    np.testing.assert_allclose(stats["actions"].q99, np.percentile(actions, 99, axis=0), rtol=1e-12)
    np.testing.assert_array_equal(ds.end, np.repeat([7, 14, 21], 7))
    np.testing.assert_array_equal(ds.images[8, 1], raw[1]["wrist"][1])
    # round trip through the openpi file that Policy / the sim policy read (z-score for π0)
    nz.save_openpi_norm_stats(tmp_path / "ns.json", stats)
    normalizer = nz.load_normalizer(tmp_path / "ns.json", use_quantiles=False)
    x = ds.state[:5]
    np.testing.assert_allclose(normalizer.normalize("state", x), (x - stats["state"].mean) / (stats["state"].std + 1e-6))

    # batch assembly: the chunk repeats the episode's last action past its end, normalised as openpi; the state
    # column 0 is replaced by the frame index so each batch row names its frame
    marked = dataclasses.replace(ds, state=np.repeat(np.arange(ds.num_frames, dtype=np.float32)[:, None], 8, 1))
    mstats = data.norm_stats(marked)
    model = get_train_config("dummy_smoke").model_config
    cfg = get_train_config("dummy_smoke", batch_size=64, augment=False)
    dev = step.device_data(marked, mstats, step.make_mesh())
    obs, chunk = step.make_batch(cfg, model, dev, jax.random.key(0), lambda x: x)
    assert chunk.shape == (64, model.action_horizon, model.action_dim)
    assert obs.images["base_0_rgb"].shape == (64, 56, 56, 3)             # 8 px demos resized with pad to 56
    np.testing.assert_array_equal(np.asarray(chunk)[..., 7:], 0)
    un = np.asarray(chunk)[..., :7] * (mstats["actions"].std + 1e-6) + mstats["actions"].mean
    frames = np.rint(np.asarray(obs.state)[:, 0] * (mstats["state"].std[0] + 1e-6) + mstats["state"].mean[0])
    assert len(set(frames.tolist())) > 10
    for b, idx in enumerate(frames.astype(int)):
        want = ds.actions[np.minimum(idx + np.arange(model.action_horizon), ds.end[idx] - 1)]
        np.testing.assert_allclose(un[b], want, atol=1e-5)
        np.testing.assert_array_equal(np.asarray(obs.tokenized_prompt)[b], ds.tokens[ds.task[idx]])
    assert (ds.end[frames.astype(int)] - frames < model.action_horizon).any()   # some chunks do run past the end


def test_augment_changes_images_within_range():
    x = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (4, 32, 32, 3)), jnp.float32)
    y = augment.augment(jax.random.key(0), x, geometric=True)
    z = augment.augment(jax.random.key(0), x, geometric=False)
    assert y.shape == x.shape and float(jnp.abs(y).max()) <= 1.0 + 1e-6
    assert float(jnp.abs(y - x).mean()) > 0.05 and float(jnp.abs(y - z).mean()) > 0.01
    # the geometric map on ramps (channel 0 = the pixel centre's row, 1 = its column): bilinear sampling keeps a
    # linear image linear, so each output channel is a plane whose slopes are the map's: CROP times a rotation
    # by at most MAX_ROTATE_DEG (a transposed or mirrored sampler or a wrong scale fails), offset by a crop
    # corner inside the image
    yy, xx = np.meshgrid(np.arange(32) + 0.5, np.arange(32) + 0.5, indexing="ij")
    img = jnp.asarray(np.stack([yy, xx, np.zeros_like(yy)], -1) / 64, jnp.float32)
    inner = (slice(6, 26), slice(6, 26))            # away from the zero fill that rotation brings into the corners
    basis = np.stack([yy[inner].ravel(), xx[inner].ravel(), np.ones(400)], 1)
    angles = []
    for seed in range(4):
        out = np.asarray(augment.crop_resize_rotate(jax.random.key(seed), img), np.float64) * 64
        assert out.shape == img.shape
        (ay, ax, a0), res_a, *_ = np.linalg.lstsq(basis, out[inner][..., 0].ravel(), rcond=None)
        (by, bx, b0), res_b, *_ = np.linalg.lstsq(basis, out[inner][..., 1].ravel(), rcond=None)
        assert max(res_a[0], res_b[0]) < 1e-3                                  # planes: linear interpolation
        np.testing.assert_allclose([ay, ax, np.hypot(ay, ax)], [bx, -by, augment.CROP], atol=1e-4)
        angles.append(np.degrees(np.arctan2(by, bx)))
        c, s, half = bx / augment.CROP, by / augment.CROP, 16.0
        off = np.array([a0, b0]) - augment.CROP * np.array([half * (1 - c) + s * half, half * (1 - c) - s * half])
        assert (off >= -1e-4).all() and (off <= 32 * (1 - augment.CROP) + 1e-4).all(), off
    assert max(map(abs, angles)) <= augment.MAX_ROTATE_DEG + 1e-3 and np.ptp(angles) > 0.5
