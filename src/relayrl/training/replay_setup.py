"""Builds a run's replay (Table + TransitionWriter, or a rollout queue) from its config.

The rate limiter is what decides how many gradient steps follow each collect iteration, in
one process as on Ray: samples_per_insert defaults to gradient_steps * batch_size /
collect_steps, and the error buffer to one iteration's worth of samples, so
`collect_steps` / `gradient_steps` in a preset mean what they say at any env.num_envs.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import torch

from relayrl import atomic
from relayrl.config import Config
from relayrl.errors import ConfigError, UserError
from relayrl.paths import existing_ancestor
from relayrl.replay import Fifo, Prioritized, Table, TransitionWriter, Uniform
from relayrl.replay.group import WriterGroup
from relayrl.replay.rate_limiters import MinSize, RateLimiter, SampleToInsertRatio
from relayrl.replay.rollouts import RolloutWriter
from relayrl.replay.rollouts_torch import TensorRolloutWriter, tensor_rollout_queue
from relayrl.replay.step_storage import ring_rows
from relayrl.seeding import RunSeeds
from relayrl.specs import ArraySpec, Spec, describe, is_image


def collect_only(c: Config) -> bool:
    """train.gradient_steps = 0 with no replay.samples_per_insert: a run that only collects
    (its MinSize limiter would let a learner sample without end)."""
    return c.replay.samples_per_insert == 0 and c.train.gradient_steps == 0


def rate_limiter(c: Config, burst_steps: int | None = None) -> RateLimiter:
    """`burst_steps`: env steps one insert call may bring at once (default: one collect
    iteration of the one-process loop); the error buffer must hold their samples."""
    r = c.replay
    min_size = r.min_size_to_sample or max(1, c.train.initial_collect_steps or c.agent.batch_size)
    if min_size > r.size:
        given = ("replay.min_size_to_sample" if r.min_size_to_sample else "train.initial_collect_steps"
                 if c.train.initial_collect_steps else "agent.batch_size")
        why = "" if r.min_size_to_sample else f" (replay.min_size_to_sample = 0 takes {given})"
        raise ConfigError(f"learning waits for {min_size:,} transitions{why}, more than replay.size={r.size:,} holds; "
                          f"lower {given} or raise replay.size")
    per_iter = c.steps_per_iteration() if burst_steps is None else burst_steps
    # The nominal ratio (gradient_steps per collect_steps env steps), not per actual
    # iteration: with N envs an iteration may take more env steps than collect_steps (all
    # copies step together), and the update-to-data ratio must not change with N.
    spi = r.samples_per_insert or c.train.gradient_steps * c.agent.batch_size / c.train.collect_steps
    if spi == 0:
        return MinSize(min_size)  # gradient_steps = 0: collect only
    burst = spi * per_iter
    buffer = r.error_buffer or burst
    if buffer < burst and burst_steps is None:
        raise ConfigError(f"replay.error_buffer={r.error_buffer:g} is too small for one process: one collect "
                          f"iteration inserts {per_iter} items worth {burst:g} samples; use >= {burst:g} or 0")
    return SampleToInsertRatio(spi, min_size, max(buffer, spi, 1.0))


def build_table(c: Config, burst_steps: int | None = None) -> Table:
    check_table_memory(c, available_host_memory())
    r = c.replay
    sampler = Prioritized(r.priority_exponent) if r.sampler == "prioritized" else Uniform()
    return Table("replay", r.size, sampler=sampler, remover=Fifo(), rate_limiter=rate_limiter(c, burst_steps),
                 seed=RunSeeds(c.seed).sequence("replay"))


REPLAY_OWNER = "run.txt"  # in a memmap replay folder: the run directory whose steps it holds


def memmap_folder(c: Config, run_root: Path) -> Path | None:
    """Where a memmap replay keeps its files (replay.path, else <run_dir>/replay); None for one in memory."""
    if c.replay.storage != "memmap":
        return None
    return Path(c.replay.path) if c.replay.path else run_root / "replay"


def replay_path(c: Config, run_root: Path) -> Path | None:
    """The memmap replay's folder, claimed for this run: a folder another run still holds is
    refused, since two runs writing one folder overwrite each other's steps unnoticed."""
    path = memmap_folder(c, run_root)
    if path is None:
        return None
    owner_file, me = path / REPLAY_OWNER, str(Path(run_root).resolve())
    if c.replay.path and owner_file.is_file():  # <run_dir>/replay is its run's own, a copied run's too
        owner = owner_file.read_text().strip()
        if owner != me and (Path(owner) / "config.toml").is_file():
            raise UserError(f"replay.path={str(path)!r} holds the replay of the run in {owner!r}; give this run a "
                            "folder of its own (or leave replay.path empty: <run_dir>/replay)")
    if path.is_dir() or not path.exists():  # a file in the way is the storage's to report
        path.mkdir(parents=True, exist_ok=True)
        atomic.write_text(owner_file, me)
    return path


def frame_stack(obs_spec: Spec) -> int:
    """k for stacked uint8 frames [k, H, W] (FrameStackObservation's; see ArraySpec.frame_stack),
    stored one frame per step; else 1 (whole observations)."""
    k = obs_spec.frame_stack if isinstance(obs_spec, ArraySpec) else 1
    ok = k > 1 and obs_spec.dtype == torch.uint8 and len(obs_spec.shape) >= 2 and obs_spec.shape[0] == k
    return k if ok else 1


# auto keeps a CUDA run's frames on its GPU only where the table takes at most this share of the
# GPU memory still free: the networks, their graphs and the batches need the rest.
GPU_REPLAY_SHARE = 0.5


def replay_bytes(c: Config, obs_spec: Spec, action_spec: Spec, items: int | None = None) -> int:
    """What a device replay allocates there: each env's ring of frames (one per step: the newest
    of a stack) and actions. Rewards, discounts and flags stay in host memory. `items`: the
    rows that holding this many items takes (default: replay.size, the full table)."""
    k = frame_stack(obs_spec)
    row = obs_spec.zeros(1).nbytes // k + action_spec.zeros(1).nbytes
    return c.env.num_envs * ring_rows(items or c.replay.size, c.env.num_envs, c.replay.n_step, k) * row


def available_host_memory() -> int | None:
    """Bytes of host memory available to a new allocation (Linux's MemAvailable); None elsewhere."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024  # in kB
    except (OSError, ValueError, IndexError):
        pass
    return None


# Host bytes a replay keeps per slot of replay.size besides its observations and actions, an upper
# bound: the Table's key, priority, sample count and free-list entry (28), a Uniform sampler's two
# indexes and a Fifo remover's queue entry (24), the step storage's slot map (32), and the rows'
# rewards, discounts and flags. Most of it is written when the table is made, however few items
# the run then inserts.
BOOKKEEPING_BYTES = 96


def check_table_memory(c: Config, available: int | None) -> None:
    """One line, before the table is made, where its bookkeeping alone outgrows the memory
    available (`available` bytes): a replay.size of billions (a typo) took the machine's memory
    in the table's constructor, before any line."""
    need = BOOKKEEPING_BYTES * c.replay.size
    if available is not None and need > available:
        raise UserError(f"replay.size={c.replay.size:,} keeps ~{need / 2**30:.1f} GiB of host memory for its slots "
                        f"from the start ({BOOKKEEPING_BYTES} bytes each, however few items it holds), more than the "
                        f"{available / 2**30:.1f} GiB available here: lower replay.size")


def host_memory_note(c: Config, chosen: torch.device | None, obs_spec: Spec, action_spec: Spec,
                     available: int | None) -> str | None:
    """The log line warning that a host-memory replay outgrows the memory available (`available`
    bytes) before the run ends, as Stable-Baselines3 warns: its arrays are allocated lazily, so
    such a run starts and is killed hours later, once it has written that many rows (SAC's 1M
    default of RGB frames: ~12 GiB at 64x64). None where it fits, or where the table is on a GPU or in files."""
    if available is None or c.replay.storage != "ram" or (chosen is not None and chosen.type != "cpu"):
        return None
    items = min(c.replay.size, c.train.total_steps)  # what this run writes, at most
    need = replay_bytes(c, obs_spec, action_spec, items) + BOOKKEEPING_BYTES * c.replay.size
    if need <= available:
        return None
    return (f"replay: {items:,} transitions of {describe(obs_spec)} take ~{need / 2**30:.1f} GiB of host memory, "
            f"more than the {available / 2**30:.1f} GiB available here: the run will run out of memory as its "
            "replay fills; lower replay.size, or set replay.storage=memmap")


def replay_device(c: Config, run_device: torch.device, stateless_env: bool, obs_spec: Spec | None = None,
                  action_spec: Spec | None = None) -> torch.device | None:
    """Where the writer keeps frames and actions (`replay.device`); None: NumPy arrays. auto: a
    CUDA run's device for image observations where the table fits (batches of frame stacks are
    then gathered on the GPU instead of copied over each gradient step), a stateless torch env's
    device, else NumPy arrays (small vector observations: the per-step writes to a GPU cost more
    than the batches' copies save)."""
    d = c.replay.device
    if d == "auto":
        if _frames_may_go_to_gpu(c, run_device, obs_spec) and action_spec is not None:
            assert obs_spec is not None
            free, _ = torch.cuda.mem_get_info(run_device)
            return run_device if replay_bytes(c, obs_spec, action_spec) <= GPU_REPLAY_SHARE * free else None
        return run_device if stateless_env and run_device.type != "cpu" else None
    if d == "numpy":
        return None
    if d.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"replay.device={d!r} but CUDA is not available here; valid: auto, numpy, cpu")
    return torch.device(d)


def _frames_may_go_to_gpu(c: Config, run_device: torch.device, obs_spec: Spec | None) -> bool:
    """auto's case for a GPU replay: a one-process CUDA run of image observations in a RAM table
    (a distributed run's replay server keeps host arrays)."""
    return (c.replay.device == "auto" and run_device.type == "cuda" and c.replay.storage == "ram"
            and obs_spec is not None and is_image(obs_spec))


def replay_note(c: Config, run_device: torch.device, chosen: torch.device | None, obs_spec: Spec,
                action_spec: Spec) -> str | None:
    """The log line saying where auto put a CUDA run's frames, and why; None where it had no choice."""
    if not _frames_may_go_to_gpu(c, run_device, obs_spec):
        return None
    size = replay_bytes(c, obs_spec, action_spec) / 2**30
    if chosen is not None:
        return f"replay: frames on {chosen} ({size:.2f} GiB when full)"
    return (f"replay: frames in host memory: the full table ({size:.2f} GiB) would take more than half of "
            f"{run_device}'s free memory (replay.device={run_device} puts it there anyway)")


def build_replay(c: Config, obs_spec: Spec, action_spec: Spec, run_root: Path,
                 device: torch.device | None = None) -> tuple[Table, TransitionWriter]:
    """`device`: where frames and actions live (see `replay_device`); None: NumPy arrays."""
    table = build_table(c)
    check_replay_disk(c, obs_spec, action_spec, memmap_folder(c, run_root))
    path = replay_path(c, run_root)
    writer = TransitionWriter(table, c.env.num_envs, obs_spec, action_spec, gamma=c.agent.gamma,
                              n_step=c.replay.n_step, frame_stack=frame_stack(obs_spec), path=path, device=device)
    return table, writer


def _allocated(file: Path) -> int:
    """Bytes the disk holds for `file` (a sparse file's written blocks; its size where the system
    does not say, as on Windows)."""
    st = file.stat()
    blocks = getattr(st, "st_blocks", None)
    return st.st_size if blocks is None else blocks * 512


def check_replay_disk(c: Config, obs_spec: Spec, action_spec: Spec, path: Path | None) -> None:
    """One line, before the files are made, where a memmap replay's files would outgrow the disk's
    free space as the run writes its rows: the files are made sparse, and the write that finds
    the disk full kills the process (SIGBUS) without a line or a checkpoint, hours in. Blocks its
    files already hold (a resume's) count as written."""
    if path is None:
        return
    items = min(c.replay.size, c.train.total_steps)  # what this run writes, at most
    need = replay_bytes(c, obs_spec, action_spec, items)
    held = sum(_allocated(f) for f in path.glob("*.npy")) if path.is_dir() else 0
    free = shutil.disk_usage(existing_ancestor(path)).free  # the folder is made later
    if need - held > free:
        raise UserError(f"replay.storage=memmap: {items:,} transitions of {describe(obs_spec)} take ~"
                        f"{need / 2**30:.1f} GiB in {str(path)!r}, whose disk has {free / 2**30:.1f} GiB free (a "
                        "full disk would kill the run mid-write): free space, lower replay.size, or set replay.path "
                        "to a folder on a larger disk")


def build_rollouts(c: Config, device: torch.device | None = None) -> tuple[Table, RolloutWriter]:
    """An on-policy algorithm's replay (registry replay "rollouts"): a queue of one rollout of
    `train.collect_steps` env steps, each consumed once by the learner. The run collects one
    rollout per iteration with the current policy, so no stale data is ever trained on.
    `device`: rollouts stay torch tensors there (a stateless torch env's); None: NumPy arrays.
    What an on-policy config may not set, `Config` refuses."""
    steps = c.steps_per_iteration() // c.env.num_envs  # per env copy
    if device is not None:
        table = tensor_rollout_queue("rollouts", 1, device)
        return table, TensorRolloutWriter(table, steps, device)
    table = Table.queue("rollouts", 1)
    return table, RolloutWriter(table, steps)


def build_shared_replay(c: Config, obs_spec: Spec, action_spec: Spec, run_root: Path,
                        num_writers: int) -> tuple[Table, WriterGroup]:
    """The replay server's Table, with one writer per rollout actor (see `WriterGroup`).

    Inserts come `distributed.chunk_steps` env steps at a time from each of the actors, so
    the error buffer (when not set) holds all of their chunks: collection may run that far
    ahead of the learner before an actor blocks, and the learner that far behind.
    """
    burst = c.distributed.chunk_steps * num_writers
    table = build_table(c, burst_steps=burst)
    # Each writer's share of the rows, with room for actors that run faster than the rest
    # (a writer whose rows wrap early evicts its oldest items: correct, just not exact FIFO).
    b = c.env.num_envs
    k = frame_stack(obs_spec)  # stacked frames: the actors ship, and the writers store, one frame per step
    rows = -(-c.replay.size // (num_writers * b)) * 3 // 2 + c.replay.n_step + k + 2

    def make_writer(t: Table, index: int, path: Path | None) -> TransitionWriter:
        return TransitionWriter(t, b, obs_spec, action_spec, gamma=c.agent.gamma, n_step=c.replay.n_step,
                                frame_stack=k, path=path, rows=rows)

    check_replay_disk(c, obs_spec, action_spec, memmap_folder(c, run_root))
    return table, WriterGroup(table, num_writers, make_writer, replay_path(c, run_root))
