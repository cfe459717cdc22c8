"""Shared fixtures. `sp_model_path`: a tiny SentencePiece model trained in well under a second, shaped like the real
PaliGemma tokenizer where it matters (pad 0, eos 1, bos 2; identity normalisation; no dummy prefix; "\\n" a
user-defined piece; digits split; byte fallback so any text encodes). `cli_options`: a subcommand's options as its
parser defines them (a --help test that only searched the printed text would pass on the description's mentions)."""

import argparse
import io

import jax
import pytest
import sentencepiece

import pi0_jax.sim  # noqa: F401  (sets XLA:CPU flags for MJX before any test initialises a JAX backend)

_SENTENCES = [
    "pick up the black bowl between the plate and the ramekin and place it on the plate",
    "put both the alphabet soup and the tomato sauce in the basket",
    "open the top drawer and put the bowl inside",
    "turn on the stove and put the moka pot on it",
    "Task: put the cream cheese in the bowl, State: 12 255 0 128 7;\nAction: ",
    "0123456789 ,;:. _",
]


# The modules with the longest tests (the roadmap's rollout fixture, the demo, the two-process evaluation: 1.5-3 min
# each on CI's 2 cores) run first, so that `-n 2` does not end with one worker on a long test while the other idles.
SLOW_FIRST = ("test_roadmap.py", "test_cli.py", "test_sim_distributed.py")


def pytest_collection_modifyitems(items):
    items.sort(key=lambda item: item.path.name not in SLOW_FIRST)   # stable: the order within each group stays


# Most of the suite's time is XLA:CPU compiling programs that then run once or twice. With jax's
# `jax_disable_most_optimizations` (LLVM at -O0, its expensive passes off) they compile in a third to half the time and
# run 2-3x slower. It is on except in the modules whose time is running programs (MJX's physics and rendering, the
# demo, the trainer) and in tests marked `optimized`: those whose time is running too, and an FP8 comparison that sits
# on e4m3 rounding boundaries (at -O0 the GELU kernel and its XLA form round 0.12 % of values apart, not 0.05 %:
# docs/BENCHMARKS.md, session 73). A switch clears jax's caches, so no program compiled one way runs the other way.
OPTIMIZED_MODULES = {"test_cli.py", "test_sim_distributed.py", "test_sim_env.py", "test_sim_policy.py",
                     "test_sim_render.py", "test_sim_tasks.py", "test_train.py"}


def pytest_configure(config):
    config.addinivalue_line("markers", "optimized: compile with XLA's optimisations (conftest.py)")


def _optimise(on: bool) -> None:
    if jax.config.values["jax_disable_most_optimizations"] == on:
        jax.clear_caches()
        jax.config.update("jax_disable_most_optimizations", not on)


@pytest.fixture(autouse=True, scope="module")
def _module_optimisation(request):
    """The module's setting, made before its module fixtures compile anything and restored after each test."""
    optimised = request.path.name in OPTIMIZED_MODULES
    _optimise(optimised)
    return optimised


@pytest.fixture(autouse=True)
def _test_optimisation(request, _module_optimisation):
    _optimise(_module_optimisation or request.node.get_closest_marker("optimized") is not None)
    yield
    _optimise(_module_optimisation)


@pytest.fixture(scope="session")
def sp_model_path(tmp_path_factory):
    buf = io.BytesIO()
    sentencepiece.SentencePieceTrainer.train(
        sentence_iterator=iter(_SENTENCES * 4), model_writer=buf, vocab_size=400, hard_vocab_limit=False,
        model_type="bpe", byte_fallback=True, split_digits=True, user_defined_symbols=["\n"],
        normalization_rule_name="identity", add_dummy_prefix=False, remove_extra_whitespaces=False,
        pad_id=0, eos_id=1, bos_id=2, unk_id=3, minloglevel=2)
    path = tmp_path_factory.mktemp("sp") / "tokenizer.model"
    path.write_bytes(buf.getvalue())
    return path


@pytest.fixture
def cli_options():
    """options(COMMAND, flags=()) -> {option string: its argparse action} of `pi0-jax COMMAND`, -h excluded, after
    checking that `flags` are among them and that every option has help; `options.commands`: the subcommands."""
    from pi0_jax import cli

    sub = next(a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction))

    def options(command: str, flags=()) -> dict:
        found = {o: a for a in sub.choices[command]._actions for o in a.option_strings if o not in ("-h", "--help")}
        assert set(flags) <= set(found), set(flags) - set(found)
        assert all(a.help and a.help != argparse.SUPPRESS for a in found.values()), [
            o for o, a in found.items() if not a.help or a.help == argparse.SUPPRESS]
        return found

    options.commands = tuple(sub.choices)
    return options
