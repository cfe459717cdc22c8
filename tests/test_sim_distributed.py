"""Multi-host evaluation through jax.distributed, on two local CPU processes (one device each, gloo collectives):
the episodes are sharded over both processes' devices, results are gathered, process 0 writes eval_info.json, and
the per-episode outcomes equal a single-process run of the same configuration (episodes are keyed by index, not by
where they ran). The expert with a 30-step limit gives a non-trivial pattern: it lifts in ~26 steps, and runs out of
time on the pick-and-place tasks. Segments of 2 plans (10 steps), so each carry goes back into the ahead-compiled
segment program with the shardings it was compiled for (MJX's zero-size fields came back replicated before)."""

import json
import os
import socket
import subprocess
import sys

from pi0_jax.sim.evaluate import EvalConfig, evaluate

ARGS = ["--policy", "expert", "--suite", "goal", "--episodes-per-task", "1", "--batch", "auto", "--steps", "30",
        "--resolution", "32", "--videos", "0", "--no-progress", "--segment-replans", "2"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_process_eval_matches_single_process(tmp_path):
    out = tmp_path / "dist"
    port = _free_port()
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    env.pop("XLA_FLAGS", None)    # each process sets its own CPU flags (and gets one CPU device)
    procs = [subprocess.Popen([sys.executable, "-m", "pi0_jax.cli", "eval", *ARGS, "--output-dir", str(out),
                               "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i)],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for i in range(2)]
    try:
        # meanwhile, the reference: the same evaluation in this process, one device
        ref = evaluate("expert", EvalConfig(suite="goal", episodes_per_task=1, batch=4, max_steps=30, resolution=32,
                                            videos=0), None, progress=False)
        logs = [p.communicate(timeout=600)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for p, log in zip(procs, logs):
        assert p.returncode == 0, log[-3000:]
    assert "| **overall** | | 4 |" in logs[0] and "| **overall** |" not in logs[1]   # only process 0 reports

    info = json.loads((out / "eval_info.json").read_text())
    assert info["config"]["processes"] == 2 and info["config"]["devices"] == 2
    assert [t["batch"] for t in info["config"]["batch_auto"]["tried"]] == [4]    # both hosts agreed on auto
    assert info["timing"]["segment_collectives"] >= 1     # counted: MJX's solver loop all-reduces its stop flag
    key = ("task", "init_state", "success", "length")
    assert [[e[k] for k in key] for e in info["per_episode"]] == [[e[k] for k in key] for e in ref["per_episode"]]
    outcome = {e["task"]: e["success"] for e in info["per_episode"]}
    assert outcome["goal/lift_red_block"] and not outcome["goal/stack_green_on_blue"]
