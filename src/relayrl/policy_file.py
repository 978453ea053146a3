"""The policy file (`policy/policy.pt`): the one file of a run that users pass around.

It holds only tensors, numbers, strings, lists and dicts, and is read with
`torch.load(weights_only=True)`, whose unpickler builds nothing else: a crafted file cannot run
code while it is read. Files written before action bounds became lists hold them as float NumPy
arrays; those are read with NumPy's array reconstruction allowed as well (it builds arrays of
the allowed dtypes and nothing else). Checkpoints are different: they hold pickled env and RNG
state and are as trusted as code (`training/checkpoint.py`).
"""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from relayrl import atomic
from relayrl.arrays import torch_dtype
from relayrl.errors import UserError
from relayrl.paths import CHECKPOINT_NAME
from relayrl.specs import ArraySpec, Spec

if TYPE_CHECKING:
    from relayrl.config import Config

REFUSED = "not a relayrl policy file, or one that would run code"

try:
    from numpy._core.multiarray import _reconstruct
except ImportError:  # NumPy 1.x
    from numpy.core.multiarray import _reconstruct  # type: ignore[no-redef]  # the same function, NumPy 1.x's path

# What a policy file written before bounds were lists needs beyond plain types: float arrays.
_OLD_LAYOUT_GLOBALS: list[Any] = [
    (_reconstruct, "numpy._core.multiarray._reconstruct"),
    (_reconstruct, "numpy.core.multiarray._reconstruct"),  # as NumPy 1.x pickles it
    np.ndarray, np.dtype, type(np.dtype(np.float32)), type(np.dtype(np.float64)),
]


def plain(value: Any) -> Any:
    """`value` with NumPy arrays and scalars turned into lists and Python numbers, recursively."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    return value


def env_entries(config: Config) -> dict[str, Any]:
    """The env a policy was trained on, so that a policy file shared on its own evaluates on the
    same env as the run did (`relayrl eval POLICY.pt`): its id, and its evaluation kwargs
    (`Config.eval_env_kwargs`), wrappers and time limit where set."""
    e = config.env
    extra = {"env_kwargs": config.eval_env_kwargs(), "env_wrappers": list(e.wrappers),
             "max_episode_steps": e.max_episode_steps}
    return {"env_id": e.id, **{k: v for k, v in extra.items() if v}}


def env_action_entries(action_spec: Spec) -> dict[str, Any]:
    """What a policy file records of actions that do not come out of the policy as the env
    takes them: a Box's own shape where it travels flat (`specs.flat_action`), and the space's
    own dtype where it is not the one stored (`ArraySpec.env_dtype`)."""
    if not isinstance(action_spec, ArraySpec):
        return {}
    shape = {} if action_spec.env_shape is None else {"action_shape": list(action_spec.env_shape)}
    return {**shape, **({"action_dtype": action_spec.env_dtype} if action_spec.env_dtype else {})}


def env_action_dtype(state: dict[str, Any]) -> torch.dtype | None:
    """The env's action dtype a policy file records (`env_action_entries`); None: the policy's own."""
    return torch_dtype(np.dtype(state["action_dtype"])) if "action_dtype" in state else None


def save_policy_file(state: dict[str, Any], path: Path) -> None:
    """Write `state` (made plain) atomically: a reader sees the old file or the new one."""
    atomic.torch_save(plain(state), path)


def load_policy_file(path: Path) -> dict[str, Any]:
    """The state dict in a policy file, read without running any code it may carry."""
    other = _other_relayrl_file(Path(path))
    if other:  # told by its name, before it is read: "damaged" or "would run code" would mislead
        raise UserError(f"{str(path)!r} is {other}; relayrl.load_policy, relayrl eval and relayrl video take the "
                        "run directory or its policy/policy.pt")
    if not _torch_saved(path):  # a text or JSON file: torch's own errors (KeyError: 105) say nothing
        raise UserError(f"{str(path)!r} is not a relayrl policy file (not a file torch.save wrote): give a run "
                        "directory or its policy/policy.pt")
    bad = atomic.damaged(path)
    if bad:
        raise UserError(f"policy file {str(path)!r} is damaged: {bad}; copy it again from where it came "
                        "from")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        state = _load_old_layout(path)
    except Exception as e:  # truncated, not a torch file at all, ...
        if _is_sb3_model(path):
            raise UserError(f"{str(path)!r} is a Stable-Baselines3 model file, which relayrl does not read: in "
                            "Python, load it with SB3 (e.g. PPO.load(path)) and give the model to "
                            "relayrl.evaluate(model, env)") from None
        raise UserError(f"policy file {str(path)!r} is unreadable ({type(e).__name__}: {_first_line(e)}): "
                        "damaged, or not a relayrl policy file") from None
    if not isinstance(state, dict):
        raise UserError(f"policy file {str(path)!r} holds a {type(state).__name__}, not a policy: {REFUSED}")
    if "kind" not in state:  # another program's dict: not a policy of an older or newer relayrl either
        raise UserError(f"policy file {str(path)!r} holds a dict with no policy 'kind', not a policy: {REFUSED}")
    return state


# what `relayrl export` writes, by the extension it insists on, and how to run each
_EXPORTED = {".pt2": "torch.export.load(path).module()", ".onnx": "onnxruntime.InferenceSession(path)"}


def _other_relayrl_file(path: Path) -> str | None:
    """What `path` is where its name says it is a relayrl file other than a policy file: an
    exported program or a run's checkpoint; None otherwise."""
    run = _EXPORTED.get(path.suffix.lower())
    if run:
        return f"a program written by relayrl export, not a policy file: run it with {run}"
    if CHECKPOINT_NAME.match(path.name):
        return ("a training checkpoint (what --resume reads), not a policy file (a run keeps its latest policy in "
                "policy/policy.pt and its best evaluation's in policy/best.pt)")
    return None


def _load_old_layout(path: Path) -> Any:
    try:
        with torch.serialization.safe_globals(_OLD_LAYOUT_GLOBALS):
            return plain(torch.load(path, map_location="cpu", weights_only=True))
    except Exception:
        raise UserError(f"{str(path)!r} is {REFUSED}; it was not loaded (a policy file holds only tensors, "
                        "numbers, strings, lists and dicts)") from None


def _first_line(e: Exception) -> str:
    text = str(e).strip()
    return text.splitlines()[0].split(". ")[0] if text else "no details"  # torch's run on for sentences


def _torch_saved(path: Path) -> bool:
    """Whether the file begins as torch.save's files do (a zip archive, or a pickle: the legacy
    format), or is empty (a write cut short: damaged)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError:
        return True  # not told apart: the caller's line names the error
    return not head or head.startswith(b"PK\x03\x04") or head[:1] == b"\x80"


def _is_sb3_model(path: Path) -> bool:
    """SB3's `model.save()` zip: a `data` JSON beside `policy.pth`."""
    try:
        with zipfile.ZipFile(path) as z:
            return {"data", "policy.pth"} <= set(z.namelist())
    except Exception:  # not a zip, or one whose directory zipfile cannot read (a changed byte): no SB3 model
        return False
