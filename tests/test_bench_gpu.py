"""bench/gpu.py: its smoke mode on the CPU (train, evaluate, export and load every algorithm), and
its one-line refusals. Its figures need a GPU and are not checked here."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path
from types import ModuleType

SCRIPT = Path(__file__).resolve().parents[1] / "bench" / "gpu.py"


def gpu_module() -> ModuleType:
    """bench/gpu.py as a module (bench/ is no package)."""
    spec = importlib.util.spec_from_file_location("bench_gpu", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(SCRIPT), *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


def test_smoke_on_the_cpu_passes_for_every_algorithm(tmp_path):
    r = run(["--smoke", "--device", "cpu", "--steps", "120"], tmp_path)
    lines = [line for line in r.stdout.splitlines() if line.split(" ", 1)[0] in ("PASS", "FAIL", "SKIP")]
    assert r.returncode == 0, r.stdout + r.stderr
    labels = [line.split()[1].rstrip(":") for line in lines]
    assert labels == ["dqn", "sac", "ppo", "bptt", "pixel-ddqn", "pixel-ppo"], lines
    assert not any(line.startswith("FAIL") for line in lines), lines
    assert "exported and loaded" in lines[0]


def test_bad_input_is_one_line_and_exit_code_2(tmp_path):
    for args in (["--device", "tpu0"], ["--smoke", "--device", "cpu", "--steps", "5"]):
        r = run(args, tmp_path)
        assert r.returncode == 2, (args, r.stdout, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1 and r.stderr.startswith("bench/gpu.py: "), r.stderr


def test_on_cuda_each_run_is_also_timed_with_the_replay_where_auto_does_not_put_it():
    # Image runs' frames go to the GPU under replay.device=auto and vector observations stay in
    # NumPy arrays: the A/B variant is the other placement, so the table shows what auto buys.
    import torch

    gpu = gpu_module()
    cuda = torch.device("cuda")
    keys = {name: [v[0] for v in gpu.variants(name, cuda)] for name in ("ddqn-pong", "dqn-pong-fast", "sac-pendulum")}
    assert keys["dqn-pong-fast"] == ["dqn-pong-fast", "dqn-pong-fast@replay.device=numpy"]
    assert "ddqn-pong@replay.device=numpy" in keys["ddqn-pong"] and "ddqn-pong@no-graphs" in keys["ddqn-pong"]
    assert "sac-pendulum@replay.device=cuda" in keys["sac-pendulum"] and "sac-pendulum@compiled" in keys["sac-pendulum"]
    settings = {v[0]: v[2] for v in gpu.variants("sac-pendulum", cuda)}
    assert settings["sac-pendulum@compiled"] == {"RELAYRL_CUDA_GRAPHS": "1", "RELAYRL_COMPILE": "1"}
    assert settings["sac-pendulum@no-graphs"]["RELAYRL_CUDA_GRAPHS"] == "0"
    base = {"RELAYRL_CUDA_GRAPHS": "1", "RELAYRL_COMPILE": "0"}
    assert gpu.variants("sac-pendulum", torch.device("cpu")) == [("sac-pendulum", torch.device("cpu"), base, [])]


def test_ddqn_pongs_ratio_on_four_ale_envs_keeps_one_gradient_step_per_four_env_steps():
    """The 4-env figure stands for ddqn-pong "at its own update-to-data ratio" only if its config
    keeps that ratio: 4 env steps (one batched step of 4 copies) per gradient step of 32."""
    import relayrl

    gpu = gpu_module()
    runs = {name: (preset, overrides) for name, preset, overrides, _ in gpu.RUNS}
    one, four = (relayrl.load_config(*runs[name]) for name in ("ddqn-pong", "ddqn-pong-4ale"))
    assert (four.env.num_envs, four.env.vectorization) == (4, "ale")
    ratio = [c.train.gradient_steps * c.agent.batch_size / c.steps_per_iteration() for c in (one, four)]
    assert ratio == [8.0, 8.0]
    assert four.agent == one.agent and four.replay == one.replay
