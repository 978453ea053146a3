"""Atari through ale-py (the `[atari]` extra; ale-py ships its ROMs, nothing is downloaded).

`relayrl/Atari-<Game>-v0` is `ALE/<Game>-v5` (sticky actions 0.25, minimal action set, at
most 108,000 frames an episode; env.kwargs `repeat_action_probability` and `full_action_space`
change the first two) made with `frameskip=1` under the standard DQN preprocessing
(`pixels.atari_preprocessing`): uint8 observations [4, 84, 84], one step = 4 frames. Any ALE
game works: `import relayrl.envs` registers an id for each game ale-py ships (`gymnasium.make`
then gives the env a loaded policy acts on), and `resolve_env_fn` any other id of the pattern
the first time it sees it. `render()` gives the game's full RGB frames (what `relayrl video`
records), not the 84x84 stacks.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path
from typing import Any

import gymnasium as gym

from relayrl.envs.pixels import SKIP, atari_preprocessing
from relayrl.errors import UserError, install

ATARI_ID = re.compile(r"relayrl/Atari-(?P<game>[A-Za-z0-9]+)-v0")
# Ids ale-py registers for the raw screen: ALE/<Game>-v5 and the older Gym ids (PongNoFrameskip-v4 ...)
RAW_ALE_ID = re.compile(r"(ALE/(?P<v5>[A-Za-z0-9]+)-v5)"
                        r"|((?P<old>[A-Z][A-Za-z0-9]*?)(NoFrameskip|Deterministic)?-v[04])")
INSTALL = install("atari")
# The game's settings an env.kwargs may change from v5's: sticky actions (0.0 gives the
# deterministic games of the NoFrameskip-v4 ids that CleanRL's and many papers' results use) and
# all 18 actions instead of the game's minimal set.
GAME_KWARGS = ("repeat_action_probability", "full_action_space")
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
    screen_size, stack, noop_max, terminal_on_life_loss; and the game's own GAME_KWARGS)."""
    make_atari_spec_kwargs(game)  # one line if ale-py or the game is missing
    game_kwargs = game_settings({k: preprocessing.pop(k) for k in GAME_KWARGS if k in preprocessing})
    # frameskip=1: AtariPreprocessing skips frames itself, max-pooling the last two.
    env = gym.make(f"ALE/{game}-v5", frameskip=1, render_mode=render_mode, disable_env_checker=True, **game_kwargs)
    env = atari_preprocessing(env, **preprocessing)
    # One step shows every frame_skip-th of the console's 60 frames/s: videos play in real time.
    env.metadata = {**env.metadata, "render_fps": ATARI_FPS // preprocessing.get("frame_skip", SKIP)}
    return env


def game_settings(kwargs: dict[str, Any]) -> dict[str, Any]:
    """GAME_KWARGS given in env.kwargs, checked (one line for a wrong value)."""
    sticky = kwargs.get("repeat_action_probability")
    if sticky is not None and (isinstance(sticky, bool) or not isinstance(sticky, (int, float))
                               or not 0.0 <= sticky <= 1.0):
        raise UserError(f"env.kwargs.repeat_action_probability={sticky!r} is not valid; it must be a number "
                        "in [0, 1] (0.0: no sticky actions)")
    full = kwargs.get("full_action_space")
    if full is not None and not isinstance(full, bool):
        raise UserError(f"env.kwargs.full_action_space={full!r} is not valid; it must be true or false")
    return {k: float(v) if k == "repeat_action_probability" else v for k, v in kwargs.items() if v is not None}


def make_atari_spec_kwargs(game: str) -> dict[str, Any]:
    """The keyword arguments `ALE/<game>-v5` is registered with (its ROM id, sticky actions,
    frame limit); one line if ale-py is missing or has no such game."""
    ale_id = f"ALE/{game}-v5"
    import_ale(f"relayrl/Atari-{game}-v0")
    if ale_id not in gym.registry:
        raise UserError(f"ale-py has no game {game!r} (no {ale_id}); e.g. relayrl/Atari-Pong-v0, "
                        "relayrl/Atari-Breakout-v0")
    return dict(gym.spec(ale_id).kwargs)


# ROMs ale-py ships without a single-player mode, for which it registers no ALE/<Game>-v5 (as its
# registration.py lists them)
MULTIPLAYER_ONLY = frozenset({"combat", "joust", "maze_craze", "warlords"})


def register_shipped_games() -> None:
    """`relayrl/Atari-<Game>-v0` for each single-player ROM in ale-py's folder, found without
    importing ale-py (seconds of start-up that a run without Atari would pay): its file names are
    the ROM ids that ale-py's own `ALE/<Game>-v5` ids spell in PascalCase."""
    spec = importlib.util.find_spec("ale_py")
    for folder in (spec.submodule_search_locations or []) if spec is not None else []:
        roms = Path(folder) / "roms"
        for rom in sorted(roms.glob("*.bin")) if roms.is_dir() else []:
            if rom.stem not in MULTIPLAYER_ONLY:
                register_on_demand(f"relayrl/Atari-{rom.stem.title().replace('_', '')}-v0")


def missing_ale_hint(env_id: str) -> str:
    """For an unregistered id of the form ale-py registers (PongNoFrameskip-v4, Pong-v4) where
    ale-py is missing: the extra that brings it, beside any near miss (Pong-v4's is Ant-v4)."""
    if RAW_ALE_ID.fullmatch(env_id) is None or importlib.util.find_spec("ale_py") is not None:
        return ""
    return f"; if it is an Atari game's, ale-py registers it: {INSTALL}"


def register_on_demand(env_id: str) -> None:
    """Register `env_id` if it is one of the ids registered only when used: `ALE/...` and the
    older `PongNoFrameskip-v4` kind (importing ale-py registers them; the latter only where it is
    installed, as `Name-v0` may be any env's id) and `relayrl/Atari-<Game>-v0`."""
    if env_id.startswith("ALE/") and env_id not in gym.registry:
        import_ale(env_id)
    elif RAW_ALE_ID.fullmatch(env_id) and env_id not in gym.registry and importlib.util.find_spec("ale_py"):
        import_ale(env_id)
    match = ATARI_ID.fullmatch(env_id)
    if match is not None and env_id not in gym.registry:
        gym.register(env_id, entry_point="relayrl.envs.atari:make_atari", kwargs={"game": match["game"]})


def raw_screen_note(env_id: str, kwargs: dict[str, Any], wrappers: list[str] | tuple[str, ...]) -> str | None:
    """A line where env.id is one of ale-py's raw-screen ids and neither env.wrappers nor another
    obs_type change it: the relayrl id and env.kwargs that give its game under the standard
    preprocessing."""
    match = RAW_ALE_ID.fullmatch(env_id)
    if match is None or wrappers or "obs_type" in kwargs or env_id not in gym.registry:
        return None
    spec = gym.spec(env_id)
    if not str(spec.entry_point).startswith("ale_py"):  # CartPole-v0 has the same form
        return None
    name = match["v5"] or match["old"]
    game = {**spec.kwargs, **kwargs}  # the user's env.kwargs over the id's own
    v5 = make_atari_spec_kwargs(name)  # what relayrl/Atari-<Game>-v0 plays
    settings = [f"{k}={game[k]}" for k in GAME_KWARGS if k in game and game[k] != v5.get(k)]
    same = f"relayrl/Atari-{name}-v0" + (
        f" with env.kwargs {', '.join(settings)}" if settings else "")
    # Pong-v0 / Pong-v4 skip 2-4 frames at random; the preprocessed ids skip a fixed 4, max-pooled.
    what = "the same game" if not isinstance(game.get("frameskip", 4), tuple) else "its game with a fixed frame skip"
    return (f"env.id={env_id!r} is ale-py's raw 210x160 RGB screen, without the standard DQN preprocessing: "
            f"{same} is {what} under it (no-op starts, max-pooled frame skip, 84x84 grayscale stacks of 4; "
            "the replay keeps 1/14 of the bytes per step)")
