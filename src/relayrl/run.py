"""`train()`: the trainer's dispatch, at the top of the package so that nothing below imports
upward. The registry says what the config's algorithm needs: its own run (BPTT), or the
Actor + Learner run, in one process or, with distributed.num_actors > 0, on Ray."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from relayrl.agents.registry import algorithm, load_attr, ray_algorithms
from relayrl.config import Config, from_dict, save_toml
from relayrl.errors import UserError
from relayrl.training.assembly import RunResult
from relayrl.training.run_dir import RunDir


def default_run_dir(config: Config) -> Path:
    name = config.env.id.replace("/", "_").replace(":", "_")
    return Path("runs") / f"{config.algo}-{name}-s{config.seed}-{time.strftime('%Y%m%d-%H%M%S')}"


def train(config: Config | dict[str, Any], run_dir: str | Path | None = None, resume: bool = False,
          progress: bool = True) -> RunResult:
    """Train from a Config (or a nested dict of config values) into a run directory.

    A new run refuses a directory that already holds a run; `resume=True` continues the
    run in `run_dir` from its latest checkpoint, with the config saved there.
    """
    if isinstance(config, dict):
        config = from_dict(config)
    config.validate()
    spec = algorithm(config.algo)
    rd = RunDir(run_dir if run_dir is not None else default_run_dir(config))
    if resume:
        rd.require()
    elif rd.metrics.exists() or rd.config.exists():
        raise UserError(f"run directory {str(rd.root)!r} already holds a run; "
                        "pass --resume to continue it or choose another --run-dir")
    if resume and not spec.resumable:
        raise UserError(f"algo={spec.name!r} runs are not checkpointed (they take minutes): start a new run instead")
    if config.distributed.num_actors > 0 and not spec.ray:
        raise UserError(f"algo={spec.name!r} runs in one process only; distributed.num_actors works with "
                        f"{' and '.join(ray_algorithms())}")
    # Each run builds its parts (envs, agent) before anything is written: bad input fails first.
    if spec.run:
        run = load_attr(spec.run)(config, rd, progress)
    elif config.distributed.num_actors > 0:
        from relayrl.distributed.run import DistributedRun

        run = DistributedRun(config, rd, progress)
    else:
        from relayrl.training.loop import LocalRun

        run = LocalRun(config, rd, progress)
    rd.create()
    if not resume:
        save_toml(config, rd.config)
    return run.run(resume=resume)
