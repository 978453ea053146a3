"""bench/pong_reference.py and bench/ppo_pong_reference.py, the recipes of dqn-pong-fast and
ppo-pong written without relayrl, which runs beside relayrl's are judged against: their n-step
returns and GAE by hand, and short runs on the CPU."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


def bench_module(name: str):
    sys.path.insert(0, str(BENCH))  # ppo_pong_reference imports pong_reference, as run from bench/
    try:
        spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCH))
    return module


def nstep_class():
    return bench_module("pong_reference").NStep


@pytest.mark.parametrize("terminated", [True, False])
def test_nstep_windows_close_as_hand_computed(terminated):
    ns = nstep_class()(1, 3, 0.5)
    out = []
    for t, r in enumerate([1.0, 2.0, 3.0, 4.0, 5.0]):
        end = np.array([t == 4])
        out += ns.step(np.array([[t]]), np.array([t]), np.array([r]), np.array([[t + 1]]),
                       end & terminated, end & (not terminated))
    got = [(int(o[0]), a, ret, int(nxt[0]), d) for o, a, ret, nxt, d in out]
    last = 0.0 if terminated else None  # truncated: bootstrap from the final observation
    assert got == [(0, 0, 1 + 0.5 * 2 + 0.25 * 3, 3, 0.125), (1, 1, 2 + 0.5 * 3 + 0.25 * 4, 4, 0.125),
                   (2, 2, 3 + 0.5 * 4 + 0.25 * 5, 5, last if last is not None else 0.125),
                   (3, 3, 4 + 0.5 * 5, 5, last if last is not None else 0.25),
                   (4, 4, 5.0, 5, last if last is not None else 0.5)]


@pytest.mark.skipif(importlib.util.find_spec("ale_py") is None, reason="needs ale-py (relayrl[atari])")
def test_a_short_run_on_the_cpu_takes_its_gradient_steps_and_logs(tmp_path):
    # one torch thread, as the tests' own process has (conftest.py): a loaded machine thrashes with more
    r = subprocess.run([sys.executable, str(BENCH / "pong_reference.py"), "--device", "cpu", "--steps", "1200",
                        "--learning-starts", "800", "--batch-size", "4", "--copies", "2", "--replay-size", "2000",
                        "--log-every", "1000", "--threads", "1"], cwd=tmp_path, capture_output=True, text=True,
                       timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    rows = [json.loads(line) for line in r.stdout.splitlines() if line.startswith("{")]
    assert rows[0]["step"] == 1000 and rows[0]["updates"] == 2 * (1000 - 800) // 2 + 2
    assert rows[-1]["done"] == 1200


def test_ppo_reference_gae_as_hand_computed():
    import torch

    gae = bench_module("ppo_pong_reference").gae
    # one copy, 3 steps; the observation at t=2 begins a new episode (the step at t=1 ended one)
    rewards, values = torch.tensor([[1.0], [2.0], [3.0]]), torch.tensor([[0.5], [1.0], [2.0]])
    dones = torch.tensor([[0.0], [0.0], [1.0]])
    g, lam = 0.5, 0.5
    d2 = 3 + g * 4.0 - 2.0  # bootstrapped from the last value 4 (last_done 0)
    d1 = 2 - 1.0  # the episode ended: no bootstrap
    d0 = 1 + g * 1.0 - 0.5
    want = [d0 + g * lam * d1, d1, d2]
    got = gae(rewards, values, dones, torch.tensor([4.0]), torch.tensor([0.0]), g, lam)[:, 0].tolist()
    assert got == pytest.approx(want)


@pytest.mark.skipif(importlib.util.find_spec("ale_py") is None, reason="needs ale-py (relayrl[atari])")
def test_the_ppo_reference_runs_rollouts_on_the_cpu_and_logs(tmp_path):
    r = subprocess.run([sys.executable, str(BENCH / "ppo_pong_reference.py"), "--device", "cpu", "--steps", "4096",
                        "--copies", "2", "--screen", "42", "--log-every", "2048", "--threads", "1"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    rows = [json.loads(line) for line in r.stdout.splitlines() if line.startswith("{")]
    assert [row.get("step", row.get("done")) for row in rows] == [2048, 4096, 4096]
    assert 0 < rows[0]["entropy"] <= np.log(6) + 1e-3
