"""RUN_DIR/history.json: each process that trained the run, in order, with the software and
machine it ran on and the settings it changed. Bit for bit, a run repeats only on the same torch
build, machine and thread count (README: Seeding and reproducibility), which config.toml does not
say; and config.toml holds the settings a run ended with, where a resume changed some."""

from __future__ import annotations

import json
import platform
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Any

from relayrl import atomic

PACKAGES = ("relayrl", "torch", "numpy", "gymnasium", "ray", "ale-py")


def record_process(path: Path, env_step: int, changed: list[str]) -> None:
    """Add this process's entry to the history at `path`: where it started (`env_step`), what
    it changed on a resume (`changed`, as its log line says them), and what it runs on."""
    entries = read_history(path)
    entries.append({"env_step": env_step, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                    **({"changed": changed} if changed else {}), **machine()})
    atomic.write_text(path, json.dumps(entries, indent=1) + "\n")


def read_history(path: Path) -> list[dict[str, Any]]:
    """The entries so far; none where there is no file or one this cannot read (it is written anew)."""
    try:
        entries = json.loads(path.read_text())
    except (OSError, ValueError):
        return []
    return entries if isinstance(entries, list) else []


def machine() -> dict[str, Any]:
    """The versions, CPU and thread count a run's numbers depend on."""
    import torch

    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    gpu = torch.cuda.get_device_name() if torch.cuda.is_initialized() else None
    return {"versions": {"python": sys.version.split()[0], **versions}, "platform": platform.platform(),
            "cpu": cpu_model(), "torch_threads": torch.get_num_threads(), **({"gpu": gpu} if gpu else {})}


def cpu_model() -> str:
    """The CPU's model name (Linux's /proc/cpuinfo), else what the platform says."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
