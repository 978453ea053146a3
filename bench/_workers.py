"""Fresh-process workers for bench scripts: each measurement runs in its own interpreter
(its own venv for peers) and reports one `RESULT {json}` line on stdout."""

from __future__ import annotations

import json
import subprocess


def report(result: dict) -> None:
    print("RESULT " + json.dumps(result), flush=True)


def run_worker(python: str, script: str, args: list[str]) -> tuple[dict | None, subprocess.CompletedProcess]:
    """Run `python script --worker *args`; the parsed RESULT (None if none) and the process."""
    proc = subprocess.run([python, script, "--worker", *args], capture_output=True, text=True, check=False)
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):]), proc
    return None, proc
