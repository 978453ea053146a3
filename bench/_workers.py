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


def sb3_eval_callback(env_id: str, every: int, episodes: int, seed: int,
                      at_start: bool = False):  # -> BaseCallback (SB3, peer venv only)
    """An SB3 callback evaluating the deterministic policy for `episodes` episodes every `every`
    env steps (and before the first step with `at_start`, as relayrl does), from seeded start
    states; `.curve` holds (env steps, mean return), `.eval_s` the time spent, and
    `.evaluate()` runs one more evaluation (e.g. at the end)."""
    import time

    import gymnasium as gym
    import numpy as np
    from stable_baselines3.common.callbacks import BaseCallback

    eval_env = gym.make(env_id)

    class Eval(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.eval_s, self.curve = 0.0, []

        def evaluate(self) -> None:
            t0 = time.perf_counter()
            rets = []
            for k in range(episodes):
                obs, _ = eval_env.reset(seed=seed * 1000 + len(self.curve) * 10 + k)
                done, ret = False, 0.0
                while not done:
                    action, _ = self.model.predict(obs, deterministic=True)
                    obs, r, term, trunc, _ = eval_env.step(action)
                    ret += float(r)
                    done = term or trunc
                rets.append(ret)
            self.curve.append((self.num_timesteps, float(np.mean(rets))))
            self.eval_s += time.perf_counter() - t0

        def _on_training_start(self) -> None:
            if at_start:
                self.evaluate()

        def _on_step(self) -> bool:
            if self.num_timesteps % every == 0:
                self.evaluate()
            return True

    return Eval()
