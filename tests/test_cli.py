"""The README's first quick-start command, `pi0-jax demo`: the embedded trained pi0_small evaluated in the MJX suite
on the CPU, on a reduced episode count (one episode per task, initial state 0)."""

import json
import re

from pi0_jax import cli

# The embedded model scores 87.1 % over 550 episodes on the GPU in bf16 with these settings (10 steps, 5 actions per
# call; docs/RESULTS.md); this CPU run (f32, 11 episodes) scored 10/11 (96 s on 2 cores) when the model was embedded.
# The floor (7/11) catches a broken model or pipeline, which scores 0 (a random policy never succeeds in this suite),
# and a regression to the previous embedded model (38.7 %, 6/11 here); a 90 % policy falls below it with p ~ 0.3 %.
SUCCESS_FLOOR = 7


def test_demo_evaluates_the_embedded_model(tmp_path, capsys):
    out = tmp_path / "demo"
    assert cli.main(["demo", "--output-dir", str(out), "--episodes-per-task", "1", "--batch", "11", "--videos", "1",
                     "--no-progress"]) == 0
    info = json.loads((out / "eval_info.json").read_text())
    agg = info["aggregated"]
    assert agg["n_episodes"] == 11 and info["config"]["policy_info"]["model"] == "pi0_small"
    assert agg["n_success"] >= SUCCESS_FLOOR, f"embedded model: {agg['n_success']}/11 successes"
    assert len(info["video_paths"]) == 1
    assert "| **overall** |" in capsys.readouterr().out


def test_help_lists_every_subcommand(capsys, cli_options):
    try:
        cli.main(["--help"])
    except SystemExit as e:
        assert e.code == 0
    out = capsys.readouterr().out
    assert set(cli_options.commands) == {"convert", "demo", "benchmark", "quantize", "eval", "train", "distill",
                                         "prune", "serve"}
    for cmd in cli_options.commands:   # its own line in --help, with its help text (the description names most)
        assert re.search(rf"^ +{cmd}\s+\S", out, re.M), cmd


def test_every_flag_of_every_subcommand_is_explained(cli_options):
    for cmd in cli_options.commands:
        cli_options(cmd)     # asserts that each of its options has help
