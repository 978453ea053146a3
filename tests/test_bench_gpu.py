"""bench/gpu.py: its smoke mode on the CPU (train, evaluate, export and load every algorithm), and
its one-line refusals. Its figures need a GPU and are not checked here."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "bench" / "gpu.py"


def run(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(SCRIPT), *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


def test_smoke_on_the_cpu_passes_for_every_algorithm(tmp_path):
    r = run(["--smoke", "--device", "cpu", "--steps", "120"], tmp_path)
    lines = [line for line in r.stdout.splitlines() if line.split(" ", 1)[0] in ("PASS", "FAIL", "SKIP")]
    assert r.returncode == 0, r.stdout + r.stderr
    labels = [line.split()[1].rstrip(":") for line in lines]
    assert labels == ["dqn", "sac", "ppo", "bptt", "pixel-ddqn"], lines
    assert not any(line.startswith("FAIL") for line in lines), lines
    assert "exported and loaded" in lines[0]


def test_bad_input_is_one_line_and_exit_code_2(tmp_path):
    for args in (["--device", "tpu0"], ["--smoke", "--device", "cpu", "--steps", "5"]):
        r = run(args, tmp_path)
        assert r.returncode == 2, (args, r.stdout, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1 and r.stderr.startswith("bench/gpu.py: "), r.stderr
