"""The README's first quick-start command, `pi0-jax demo`, end to end (reduced iterations)."""

import json

from pi0_jax import cli


def test_demo_runs_and_writes_result(tmp_path, capsys):
    assert cli.main(["demo", "--out-dir", str(tmp_path), "--iters", "2", "--steps", "2"]) == 0
    result = json.loads((tmp_path / "demo_result.json").read_text())
    assert result["actions_shape"] == [10, 7]  # horizon 10, LeRobot's 7-D action feature
    assert result["noise_injection_reproducible"]
    assert (tmp_path / "demo_pi05" / "params").is_dir()
    out = capsys.readouterr().out
    assert "| infer, median of 2 |" in out


def test_help_lists_every_subcommand(capsys):
    try:
        cli.main(["--help"])
    except SystemExit as e:
        assert e.code == 0
    out = capsys.readouterr().out
    assert "convert" in out and "demo" in out
