"""pi0_jax.train.distill on CPU with a dummy_smoke teacher (random init, exported as `pi0-jax train` exports): the
loss goes down, the exported student loads and samples with its recorded step count, the layer-sliced student holds
the teacher's chosen layers, and the loss is ~0 for a student that is its teacher (the control)."""

import json

import jax
import numpy as np
import pytest
from flax import traverse_util

from pi0_jax import checkpoint as ckpt_lib
from pi0_jax import normalize as nz
from pi0_jax import pi0
from pi0_jax.sim.cli import default_num_steps
from pi0_jax.train import data, distill, step, trainer
from pi0_jax.train.config import get_distill_config, get_train_config

TEACHER_CFG = get_train_config("dummy_smoke")
STEPS = 10


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    return data.synthetic_demos(tmp_path_factory.mktemp("demos"), episodes=11, length=16, resolution=56)


@pytest.fixture(scope="module")
def teacher(demos, tmp_path_factory):
    """OUT/checkpoint of an (untrained) dummy_smoke run: the trainer's export with its tokenizer and norm stats."""
    out = tmp_path_factory.mktemp("teacher")
    (out / "tokenizer.model").write_bytes(data.train_tokenizer(data.suite_prompts()))
    model = TEACHER_CFG.model_config
    ds = data.load_demos(demos, data.suite_prompts(), out / "tokenizer.model", model.max_token_len, log=None)
    nz.save_openpi_norm_stats(out / "norm_stats.json", data.norm_stats(ds))
    return trainer.export(TEACHER_CFG, step.init_state(TEACHER_CFG, model), out)


def _device_data(teacher, demos):
    """The demos as a distillation sees them: the teacher's tokenizer and norm stats."""
    ds = data.load_demos(demos, data.suite_prompts(), teacher / "tokenizer.model",
                        TEACHER_CFG.model_config.max_token_len, log=None)
    stats = nz.load_openpi_norm_stats(teacher / "assets" / trainer.ASSET_ID / "norm_stats.json")
    return step.device_data(ds, stats, step.make_mesh())


def _load(path):
    """(config, params as jax arrays: a jitted closure indexes the embedding table with a tracer)"""
    model, params = ckpt_lib.load_checkpoint(path)
    return model, jax.device_put(params)


def test_distill_cli_two_layers_one_step(teacher, demos, tmp_path):
    """`pi0-jax distill` into 2 of 3 layers and 1 step: the loss on fixed batches goes down, the export loads with
    load_checkpoint, records its provenance and num_steps (eval's default), resumes exactly, and samples. One test,
    so that the step compiles once."""
    from pi0_jax import cli

    out = tmp_path / "student"
    assert cli.main(["distill", "--config", "dummy_distill", "--teacher", str(teacher), "--demos", str(demos),
                     "--out", str(out), "--layers", "2", "--student-steps", "1", "--steps", str(STEPS),
                     "--no-augment"]) == 0
    cfg = get_distill_config("dummy_distill", layers=2, student_steps=1, steps=STEPS, augment=False)
    t_model, t_params = _load(teacher)
    s_model, s_params = _load(out / "checkpoint")
    assert (s_model.paligemma_variant, s_model.action_expert_variant) == ("dummy_2l", "dummy_expert_2l")
    # everything else is the teacher's
    assert s_model.replace(name="dummy", paligemma_variant="dummy", action_expert_variant="dummy_expert") == t_model

    # the same 4 fixed batches (frames, noise) for the teacher-initialised student and the exported (EMA) one
    dev = _device_data(teacher, demos)
    loss = jax.jit(lambda p, k: distill.batch_loss(cfg, t_model, s_model, t_params, p, dev, k))
    keys = [jax.random.key(100 + i) for i in range(4)]
    before = np.mean([float(loss(distill.slice_layers(t_params, (0, 2)), k)) for k in keys])
    after = np.mean([float(loss(s_params, k)) for k in keys])
    assert before > 0.1 and after < 0.7 * before, (before, after)

    meta = ckpt_lib.read_meta(out / "checkpoint")
    assert meta["num_steps"] == 1 and meta["step"] == STEPS and meta["weights"] == "ema"
    assert meta["distill"] == {"teacher": str(teacher.absolute()), "teacher_steps": 10, "student_steps": 1,
                               "layers": 2, "teacher_layers": [0, 2]}
    assert default_num_steps(str(out / "checkpoint")) == 1 and default_num_steps(str(teacher)) == 10
    assert (out / "checkpoint" / "tokenizer.model").read_bytes() == (teacher / "tokenizer.model").read_bytes()
    rel = f"assets/{trainer.ASSET_ID}/norm_stats.json"
    assert (out / "checkpoint" / rel).read_text() == (teacher / rel).read_text()
    log = json.loads((out / "train_log.json").read_text())["log"]
    assert [r["step"] for r in log] == [2, 4, 6, 8, 10] and all(np.isfinite(r["loss"]) for r in log)
    assert (out / "loss.png").stat().st_size > 1000

    # interrupted at step 6 and resumed (the same compiled step): the same exported weights, bit for bit
    resumed = tmp_path / "resumed"
    assert "stopped_at" in distill.distill(cfg, teacher, demos, resumed, stop_at=6, log=lambda _: None)
    distill.distill(cfg, teacher, demos, resumed, resume=True, log=lambda _: None)
    _, r_params = ckpt_lib.load_checkpoint(resumed / "checkpoint")
    for a, b in zip(jax.tree.leaves(s_params), jax.tree.leaves(r_params)):
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes()

    noise = jax.random.normal(jax.random.key(0), (2, s_model.action_horizon, s_model.action_dim))
    actions = jax.jit(pi0.sample_actions, static_argnums=(0, 4))(s_model, s_params, pi0.fake_observation(s_model, 2),
                                                                 noise, meta["num_steps"])
    assert actions.shape == (2, s_model.action_horizon, s_model.action_dim) and np.isfinite(actions).all()


def test_layer_slicing(teacher):
    assert distill.layer_indices(4, 2) == (0, 3)
    assert distill.layer_indices(18, 4) == (0, 6, 11, 17)
    assert distill.layer_indices(3, 3) == (0, 1, 2)
    for bad in (1, 4):
        with pytest.raises(ValueError, match="layers"):
            distill.layer_indices(3, bad)
    t_model, t_params = ckpt_lib.load_checkpoint(teacher)
    s_model = distill.student_config(t_model, 2)
    assert (s_model.paligemma.depth, s_model.action_expert.depth) == (2, 2)
    assert distill.student_config(t_model, 3) == t_model
    deep = t_model.replace(paligemma_variant="gemma_2b", action_expert_variant="gemma_300m")
    assert distill.student_config(deep, 4).paligemma.depth == 4     # `<variant>_<n>l` exists for every n <= depth
    with pytest.raises(ValueError, match="gemma_2b_19l"):
        distill.student_config(deep, 19)

    student = distill.slice_layers(t_params, (0, 2))
    ckpt_lib.check_params(s_model, student)
    t_flat, s_flat = (traverse_util.flatten_dict(p, sep="/") for p in (t_params, student))
    assert t_flat.keys() == s_flat.keys()
    sliced = [k for k in t_flat if k.startswith("PaliGemma/llm/layers/")]
    assert any(k.endswith("_1/w") for k in sliced) and len(sliced) == 14     # both experts' blocks
    for k, v in t_flat.items():
        want = v[[0, 2]] if k in sliced else v                # SigLIP's scanned encoderblock is kept whole
        np.testing.assert_array_equal(s_flat[k], want, err_msg=k)
    assert not np.array_equal(t_flat[sliced[0]][1], t_flat[sliced[0]][2])   # layer 1 is not a copy of layer 2


def test_control_loss_is_zero_for_the_teacher_itself(teacher, demos):
    """A student at the teacher's depth and step count (1 here), initialised as the teacher, has loss ~0: the loss
    compares the two samplers on the same observations and noise (the CLI test's student starts far from 0). It stays
    ~0 when the student's output differs in the padding action dim (7 of 8), not in a real one. (With more steps the
    padding dims of x_t feed back into the next velocity, so there they matter to the real dims.)"""
    t_model, t_params = _load(teacher)
    cfg = get_distill_config("dummy_distill", student_steps=1, teacher_steps=1, augment=False)
    dev = _device_data(teacher, demos)
    loss = jax.jit(lambda p: distill.batch_loss(cfg, t_model, t_model, t_params, p, dev, jax.random.key(7)))

    def shifted(dim):
        proj = t_params["action_out_proj"]
        return {**t_params, "action_out_proj": {**proj, "bias": proj["bias"].at[dim].add(1.0)}}

    assert float(loss(t_params)) < 1e-10
    assert float(loss(shifted(7))) < 1e-10
    assert float(loss(shifted(0))) > 1e-2


def test_distill_cli_passes_the_optimiser_flags(tmp_path, monkeypatch):
    """The flags `distill` shares with `train` reach the DistillConfig that distill.distill is given (a spy: no run)."""
    from pi0_jax import cli

    seen = {}

    def spy(cfg, *args, **kw):
        seen["cfg"] = cfg
        return {}

    monkeypatch.setattr(distill, "distill", spy)
    assert cli.main(["distill", "--config", "dummy_distill", "--teacher", str(tmp_path), "--demos", str(tmp_path),
                     "--out", str(tmp_path), "--decay-lr", "0", "--clip-norm", "0.5", "--weight-decay", "0",
                     "--b2", "0.9", "--keep", "1"]) == 0
    assert seen["cfg"] == get_distill_config("dummy_distill", decay_lr=0.0, clip_norm=0.5, weight_decay=0.0, b2=0.9,
                                             keep=1)
    assert seen["cfg"] != get_distill_config("dummy_distill")


def test_distill_help_explains_every_flag(capsys, cli_options):
    from pi0_jax import cli

    with pytest.raises(SystemExit) as e:
        cli.main(["distill", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    flags = ("--teacher", "--demos", "--out", "--config", "--student-steps", "--teacher-steps", "--layers",
             "--steps", "--batch", "--lr", "--warmup", "--ema", "--no-augment", "--seed", "--log-every",
             "--save-every", "--resume", "--stop-at", "--max-episodes", "--decay-lr", "--clip-norm",
             "--weight-decay", "--b2", "--keep")
    for flag in flags:
        assert flag in out
    cli_options("distill", flags)     # each flag defined by the parser, every option with help
    assert "pi0_small_distill" in out and "dummy_distill" in out
