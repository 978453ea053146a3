"""Named presets: TOML files beside this module. The first comment line describes each."""

from __future__ import annotations

from importlib import resources
from typing import Any

from relayrl.config import Config, apply_overrides, from_dict, load_toml
from relayrl.config_fields import did_you_mean
from relayrl.errors import ConfigError


def _files() -> dict[str, Any]:
    root = resources.files(__package__)
    return {p.name[:-5]: p for p in root.iterdir() if p.name.endswith(".toml")}


def list_presets() -> dict[str, str]:
    """name -> one-line description."""
    out = {}
    for name, path in sorted(_files().items()):
        first = path.read_text().splitlines()[0]
        out[name] = first.lstrip("# ").strip()
    return out


def preset_dict(name: str) -> dict[str, Any]:
    files = _files()
    if name not in files:
        raise ConfigError(f"unknown preset {name!r}{did_you_mean(name, list(files))} "
                          f"(valid: {', '.join(sorted(files))}; a config file's name ends in .toml)")
    with files[name].open("rb") as f:
        import tomllib

        return tomllib.load(f)


def load_config(name_or_path: str, overrides: list[str] | None = None, seed: int | None = None) -> Config:
    """A preset name or a path to a config TOML, with `--set` overrides applied and checked."""
    if name_or_path.endswith(".toml"):
        data = load_toml(name_or_path)
    else:
        data = preset_dict(name_or_path)
    data = apply_overrides(data, overrides or [])
    if seed is not None:
        data["seed"] = seed
    return from_dict(data)
