"""An env module that imports in the test's own process only, as a project present on the driver's
node and missing from a Ray worker's: elsewhere it lacks the package it imports."""

import os

if os.environ.get("RELAYRL_DRIVER_PID") != str(os.getpid()):
    raise ModuleNotFoundError("No module named 'simulator'", name="simulator")

from toy_envs import Countdown as Env  # noqa: E402

__all__ = ["Env"]
