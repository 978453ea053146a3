"""Agents: one folder per algorithm with config, pure losses, networks and the agent; the
registry (agents/registry.py) says what each algorithm is."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any


def lazy_exports(package: str, modules: dict[str, str]) -> Callable[[str], Any]:
    """A package's `__getattr__` that imports each name's module (`modules`: name -> module) when
    first asked: the registry (and config.py) import the packages' config.py without torch."""

    def __getattr__(name: str) -> Any:
        if name in modules:
            return getattr(importlib.import_module(f"{package}.{modules[name]}"), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__
