"""The direct driver: an algorithm that trains by itself (registry `replay = "none"`: BPTT
through a differentiable env) writes its run directory through this: metrics rows,
TensorBoard, the config, and the policy file at the end (at the iteration a Ctrl-C or SIGTERM
stopped it, too: its runs have no checkpoints). No actor, replay or learner."""

from __future__ import annotations

from typing import Any

from relayrl import interrupts
from relayrl.agents.registry import algorithm
from relayrl.config import Config
from relayrl.policy_file import save_policy_file
from relayrl.training.lifecycle import RunResult, resolve_device
from relayrl.training.report import log_config, say
from relayrl.training.run_dir import MetricsLog, RunDir


class DirectDriver:
    """The trainer's config is checked when the driver is made, before anything is written;
    its runs are not resumable (Algorithm.resumable)."""

    def __init__(self, config: Config, rd: RunDir, progress: bool = True) -> None:
        self.trainer = algorithm(config.algo).direct_trainer()
        self.trainer.check_config(config)
        self.config, self.rd, self.progress = config, rd, progress

    def train(self, resume: bool = False) -> RunResult:
        from torch.utils.tensorboard import SummaryWriter

        rows: list[dict[str, Any]] = []
        log, tb = MetricsLog(self.rd.metrics), SummaryWriter(str(self.rd.tb))
        signals: list[int] = []  # the first Ctrl-C / SIGTERM: stop after this iteration, keep the policy

        def write_row(row: dict[str, Any]) -> None:
            log.write(row)
            rows.append(row)

        def on_signal(signum: int) -> None:
            signals.append(signum)
            say("relayrl: stopping at the end of this iteration to save the policy (no checkpoints for "
                f"algo={self.config.algo!r}; {interrupts.again(signum)})")

        def stop() -> bool:
            return bool(signals)

        try:
            log_config(tb, self.config)
            with interrupts.stop_request(on_signal):
                state = self.trainer.train(self.config, resolve_device(self.config.device), write_row,
                                           tb.add_scalar, say if self.progress else None, stop)
        finally:
            log.close()
            tb.close()
        save_policy_file(state, self.rd.policy / "policy.pt")
        if signals:  # one in the last iteration too: the run is whole, and the caller's loop still stops
            interrupts.redeliver(signals[0], f"the run stopped at env step {state['env_steps']:,}; its policy and "
                                 f"metrics are in {str(self.rd.root)!r} (algo={self.config.algo!r} runs have no "
                                 "checkpoints: a new run starts over)")
        return RunResult(self.rd.root, rows[-1] if rows else {})

    def close(self) -> None:
        """Nothing outlives `train`: the trainer runs in this process, on its own envs."""
