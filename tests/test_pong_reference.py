"""bench/pong_reference.py, the recipe of dqn-pong-fast written without relayrl, which a GPU run
beside relayrl's (bench/gpu_pong_ab.sh) is judged against: its n-step returns by hand, and a
short run on the CPU."""

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


def nstep_class():
    spec = importlib.util.spec_from_file_location("pong_reference", BENCH / "pong_reference.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.NStep


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
