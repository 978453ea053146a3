"""`env.vectorization = "ale"`: the copies of a `relayrl/Atari-<Game>-v0` env stepped by ale-py's
own vector env (`AtariVectorEnv`: C++ threads doing the frame skip, max-pool, grayscale and
resize) with the game settings and preprocessing of the Gymnasium path (envs/atari.py), so a
policy trained here runs there too (`make_env`'s default, `relayrl video`, a policy file's own
evaluation); a run's evaluations take this path where they can (`make_eval_env`).

Two things are done here rather than in ale-py, to match the other envs exactly:
- The frame stack. ale-py pads a new episode's stack with zeros; relayrl's envs repeat the
  first frame, which is what the replay rebuilds from one stored frame per step.
- Auto-reset. In ale-py's "SameStep" mode a copy whose episode ended is reset within the step,
  its last frame in `info["final_obs"]`; the step output carries that true final stack
  (`next_obs`) beside the reset one (`obs`), as `GymBatchEnv` does.

`env.info_keys` read ale-py's per-step info (`lives`, `frame_number`, `episode_frame_number`);
for a copy reset within the step it already describes the new episode.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch

from relayrl.envs.atari import ATARI_ID, GAME_KWARGS, game_settings, import_ale, make_atari_spec_kwargs
from relayrl.envs.gym import BatchEnvBase, episode_info
from relayrl.envs.pixels import SCREEN, SKIP, STACK
from relayrl.errors import UserError
from relayrl.types import StepOutput

# env.kwargs this path takes (`make_atari`'s preprocessing keywords it can honour exactly).
ALE_KWARGS = ("frame_skip", "screen_size", "stack", "noop_max", *GAME_KWARGS)


class AleBatchEnv(BatchEnvBase):
    """`num_envs` copies of one Atari game in ale-py's vector env, as one batched env."""

    def __init__(self, game: str, num_envs: int, max_episode_steps: int = 0, time_limit_terminates: bool = False,
                 num_threads: int = 0, pin_memory: bool = False, frame_skip: int = SKIP,
                 screen_size: int = SCREEN, stack: int = STACK, noop_max: int = 30,
                 repeat_action_probability: float | None = None, full_action_space: bool | None = None) -> None:
        from ale_py.vector_env import AtariVectorEnv

        if num_envs < 1:
            raise UserError("env.num_envs must be >= 1")
        for key, value in (("frame_skip", frame_skip), ("screen_size", screen_size), ("stack", stack)):
            if value < 1:
                raise UserError(f"env.kwargs.{key}={value} is not valid; it must be >= 1")
        v5 = {**make_atari_spec_kwargs(game), **game_settings(
            {"repeat_action_probability": repeat_action_probability, "full_action_space": full_action_space})}
        self.ale = AtariVectorEnv(
            v5["game"], num_envs, num_threads=num_threads, autoreset_mode="SameStep",
            repeat_action_probability=v5.get("repeat_action_probability", 0.25),
            full_action_space=v5.get("full_action_space", False),
            max_num_frames_per_episode=v5.get("max_num_frames_per_episode", 108_000),
            img_height=screen_size, img_width=screen_size, grayscale=True, stack_num=1, frameskip=frame_skip,
            maxpool=True, noop_max=noop_max, episodic_life=False, reward_clipping=False, use_fire_reset=False)
        space = gym.spaces.Box(0, 255, (stack, screen_size, screen_size), np.uint8)
        self._init_specs(num_envs, space, self.ale.single_action_space, time_limit_terminates, frame_stack=stack)
        self.max_episode_steps = max_episode_steps  # 0: only the game's own frame limit
        self.pin_memory = pin_memory
        self._steps = np.zeros(num_envs, np.int64)  # agent steps into each copy's episode
        self._stack = np.zeros((num_envs, *space.shape), np.uint8)  # [B, k, H, W] the stacks acted on
        self._all = np.arange(num_envs)

    def _empty(self) -> torch.Tensor:
        """A fresh [B, k, H, W] uint8 host tensor, pinned on a CUDA run (so the policy's
        `obs.to(device, non_blocking=True)` does not block the host). Fresh each step: the
        replay writers keep the step's tensors until they flush."""
        return torch.empty((self.num_envs, *self._stack.shape[1:]), dtype=torch.uint8, pin_memory=self.pin_memory)

    def _check_order(self, info: dict[str, Any]) -> None:
        """ale-py answers a synchronous batch (batch_size = num_envs) in copy order, and `send`
        gives action i to the i-th copy of the last answer: a batch in any other order would
        pair copies with other copies' actions, so it stops the run instead."""
        if not np.array_equal(np.asarray(info["env_id"]), self._all):
            raise RuntimeError(f"ale-py answered copies {list(info['env_id'])} out of order; relayrl steps them "
                               "in order (report this with the ale-py version)")

    def reset(self, seed: int | None = None) -> torch.Tensor:
        if seed is not None:  # ale-py seeds copy i with seed + i, as a C int
            seed %= 2**31 - self.num_envs
        frames, info = self.ale.reset(seed=seed)  # [B, 1, H, W]
        self._check_order(info)
        out = self._empty()
        out.numpy()[:] = frames  # broadcast over the stack: the first frame repeated
        self._stack = out.numpy()
        self._steps[:] = 0
        return out

    def step(self, action: torch.Tensor) -> StepOutput:
        act = self._actions(action).astype(np.int64, copy=False).reshape(self.num_envs)
        frames, reward, terminated, truncated, info = self.ale.step(act)  # frames [B, 1, H, W]
        self._check_order(info)
        ended_here = terminated | truncated  # ale-py reset these: frames holds their reset frame
        self._steps += 1
        cut = np.zeros_like(ended_here)
        if self.max_episode_steps > 0:
            cut = (self._steps >= self.max_episode_steps) & ~ended_here
            truncated = truncated | cut
        next_obs = self._empty()
        nxt = next_obs.numpy()
        nxt[:, :-1] = self._stack[:, 1:]  # the stack slides by one frame
        nxt[:, -1] = frames[:, 0]
        done = ended_here | cut
        obs = next_obs
        if done.any():
            if ended_here.any():
                nxt[ended_here, -1] = info["final_obs"][ended_here, 0]
            resets = frames
            if cut.any():  # cut by env.max_episode_steps: reset those copies now
                resets, reset_info = self.ale.reset(options={"reset_mask": cut})
                self._check_order(reset_info)
            obs = self._empty()
            o = obs.numpy()
            o[:] = nxt
            o[done] = resets[done]  # broadcast over the stack: each reset frame repeated
            self._steps[done] = 0
        self._stack = obs.numpy()
        if self.time_limit_terminates:
            terminated, truncated = terminated | truncated, np.zeros_like(truncated)
        ended = np.flatnonzero(done).tolist()
        extra = episode_info(self.info_keys, self.num_envs, ended,
                             lambda i: {k: v[i] for k, v in info.items() if k != "final_obs"})
        return StepOutput(next_obs, torch.from_numpy(reward.astype(np.float32)),
                          torch.from_numpy(np.asarray(terminated, np.bool_)),
                          torch.from_numpy(np.asarray(truncated, np.bool_)), obs, extra)

    def close(self) -> None:
        self.ale.close()


def unsupported_kwargs(kwargs: dict[str, Any] | None) -> list[str]:
    """The env.kwargs this path cannot honour (sorted); [] where it takes them all."""
    return sorted(set(kwargs or {}) - set(ALE_KWARGS))


def make_ale_env(env_id: str, num_envs: int, max_episode_steps: int = 0, time_limit_terminates: bool = False,
                 device: str | torch.device = "cpu", num_workers: int = 0,
                 kwargs: dict[str, Any] | None = None) -> AleBatchEnv:
    """The `env.vectorization = "ale"` env for an Atari id; one line for anything it cannot do.
    `num_workers` is the number of ale-py's threads (0: one per CPU core)."""
    match = ATARI_ID.fullmatch(env_id)
    if match is None:
        raise UserError(f"env.vectorization='ale' needs an Atari id relayrl/Atari-<Game>-v0 (e.g. "
                        f"relayrl/Atari-Pong-v0), not env.id={env_id!r}; other envs: sync or async")
    import_ale(env_id)  # one line where ale-py is missing
    kwargs = dict(kwargs or {})
    unknown = unsupported_kwargs(kwargs)
    if unknown:
        raise UserError(f"env.kwargs {unknown} are not supported with env.vectorization='ale' "
                        f"(valid: {', '.join(ALE_KWARGS)}); use env.vectorization='sync' for them")
    dev = torch.device(device)
    pin = dev.type == "cuda" and torch.cuda.is_available()
    return AleBatchEnv(match["game"], num_envs, max_episode_steps, time_limit_terminates, num_workers, pin, **kwargs)
