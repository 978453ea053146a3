"""Atari through ale-py (the `[atari]` extra; ale-py ships its ROMs, nothing is downloaded).

`relayrl/Atari-<Game>-v0` is `ALE/<Game>-v5` (sticky actions 0.25, minimal action set, at
most 108,000 frames an episode) made with `frameskip=1` under the standard DQN preprocessing
(`pixels.atari_preprocessing`): uint8 observations [4, 84, 84], one step = 4 frames. Any ALE
game works; an id is registered with Gymnasium the first time `resolve_env_fn` sees it, so
the registry is not filled with a hundred games that may never be played. `render()` gives
the game's full RGB frames (what `relayrl video` records), not the 84x84 stacks.
"""

from __future__ import annotations

import re
from typing import Any

import gymnasium as gym

from relayrl.envs.pixels import SKIP, atari_preprocessing
from relayrl.errors import UserError

ATARI_ID = re.compile(r"relayrl/Atari-(?P<game>[A-Za-z0-9]+)-v0")
INSTALL = "pip install 'relayrl[atari]'"
ATARI_FPS = 60  # NTSC frames per second


def import_ale(env_id: str) -> None:
    """Import ale-py, which registers the `ALE/...` ids with Gymnasium; one line if missing."""
    try:
        import ale_py
    except ImportError:
        raise UserError(f"env.id={env_id!r} needs ale-py: {INSTALL}") from None
    gym.register_envs(ale_py)


def make_atari(game: str, render_mode: str | None = None, **preprocessing: Any) -> gym.Env:
    """`ALE/<game>-v5` with the standard preprocessing (keyword overrides: frame_skip,
    screen_size, stack, noop_max, terminal_on_life_loss)."""
    make_atari_spec_kwargs(game)  # one line if ale-py or the game is missing
    # frameskip=1: AtariPreprocessing skips frames itself, max-pooling the last two.
    env = gym.make(f"ALE/{game}-v5", frameskip=1, render_mode=render_mode, disable_env_checker=True)
    env = atari_preprocessing(env, **preprocessing)
    # One step shows every frame_skip-th of the console's 60 frames/s: videos play in real time.
    env.metadata = {**env.metadata, "render_fps": ATARI_FPS // preprocessing.get("frame_skip", SKIP)}
    return env


def make_atari_spec_kwargs(game: str) -> dict[str, Any]:
    """The keyword arguments `ALE/<game>-v5` is registered with (its ROM id, sticky actions,
    frame limit); one line if ale-py is missing or has no such game."""
    ale_id = f"ALE/{game}-v5"
    import_ale(f"relayrl/Atari-{game}-v0")
    if ale_id not in gym.registry:
        raise UserError(f"ale-py has no game {game!r} (no {ale_id}); e.g. relayrl/Atari-Pong-v0, "
                        "relayrl/Atari-Breakout-v0")
    return dict(gym.spec(ale_id).kwargs)


def register_on_demand(env_id: str) -> None:
    """Register `env_id` if it is one of the ids registered only when used: `ALE/...` (importing
    ale-py registers them) and `relayrl/Atari-<Game>-v0`."""
    if env_id.startswith("ALE/") and env_id not in gym.registry:
        import_ale(env_id)
    match = ATARI_ID.fullmatch(env_id)
    if match is not None and env_id not in gym.registry:
        gym.register(env_id, entry_point="relayrl.envs.atari:make_atari", kwargs={"game": match["game"]})
