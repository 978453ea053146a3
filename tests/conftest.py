import os
import signal
import sys

import pytest
import torch

HERE = os.path.dirname(__file__)
sys.path.insert(0, HERE)  # so env ids like `toy_envs:Countdown` resolve in-process

# A test run started in the background by a shell without job control (`pytest &` in a script)
# inherits SIGINT ignored, and so would every run a test starts: the Ctrl-C tests would see
# their signal ignored. With Python's handler here, exec'd children start with the default.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(autouse=True)
def _threads():
    torch.set_num_threads(1)


@pytest.fixture
def cli_env():
    """Environment for `relayrl` subprocesses: toy envs importable, no progress bar noise."""
    env = dict(os.environ)
    env["PYTHONPATH"] = HERE + os.pathsep + env.get("PYTHONPATH", "")
    return env
