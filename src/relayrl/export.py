"""Saved policies: load one for the user's code, or export it for plain PyTorch or ONNX.

`policy/policy.pt` holds a plain dict (network sizes, weights, action bounds) that
`load_policy` rebuilds without the agent or replay; it is read without running any code it
may carry (`policy_file.py`), so a shared policy file is safe to load. `export_policy` (`relayrl export RUN_DIR`;
a few seconds, so not done on every save) writes `policy.pt2`, a
`torch.export` program of the deterministic policy with a dynamic batch dimension, which
runs with nothing but PyTorch:

    program = torch.export.load("run/policy/policy.pt2").module()
    actions = program(obs)  # [B, *obs_shape] in the space's dtype -> [B] or [B, *action_shape]

A policy on Dict or Tuple observations takes one input per entry, in the space's order (a
Dict's keys, a Tuple's "0", "1", ...; nested entries as "outer.inner"). `relayrl export --format
onnx` writes `policy.onnx` instead (input "obs" or one per entry, output "action", the same
shapes). Beside either, `policy.<format>.json` records the inputs' and output's dtype and shape.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import re
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import torch

from relayrl import atomic
from relayrl.agents.registry import for_policy_kind
from relayrl.config_fields import is_user_encoder
from relayrl.errors import UserError, install
from relayrl.loaded_policy import LoadedPolicy, built_quietly, env_box_bounds, env_shaped, rng_kept
from relayrl.paths import is_folder, output_path, user_path, writing
from relayrl.policies import saved_obs_spec
from relayrl.policy_file import REFUSED, env_action_dtype, load_policy_file
from relayrl.seeding import check_seed
from relayrl.specs import PackedSpec, Spec, env_torch_dtype

T = TypeVar("T")


def _policy_file(path: str | Path) -> Path:
    if not isinstance(path, (str, os.PathLike)):  # several runs of a sweep: pathlib's TypeError said only "not list"
        raise UserError(f"{path!r} is not a run directory or a policy file; one policy per call: "
                        "[relayrl.load_policy(d) for d in run_dirs]")
    p = user_path(path)
    if p.name == "config.toml" and p.is_file():  # a run's config names its run, as for `relayrl eval`
        p = p.parent
    for candidate in (p / "policy" / "policy.pt", p / "policy.pt", p):
        if candidate.is_file():
            return candidate
    if (p / "config.toml").is_file():
        raise UserError(f"run {str(p)!r} has not saved a policy yet (a run saves one when it starts, then every "
                        "train.policy_save_interval env steps)")
    raise UserError(f"no saved policy at {str(p)!r} (expected RUN_DIR/policy/policy.pt)")


def _built(f: Path, state: dict[str, Any], build: Callable[[], T]) -> T:
    """`build()` of a saved policy's parts on the CPU, under a float32 default dtype (the networks
    relayrl saved, whatever the caller's default), as `built_quietly`; a file that lacks what they
    read is one line."""
    from relayrl.training.process import float32_default

    try:
        with rng_kept(torch.device("cpu")), float32_default():
            return build()
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        encoder = str(state.get("encoder", ""))
        if isinstance(e, RuntimeError) and is_user_encoder(encoder):  # the user's code, not the file
            raise UserError(f"policy file {str(f)!r}: its encoder {encoder!r} now builds other parameters than the "
                            f"ones saved (did its code change since the run?): {str(e).splitlines()[-1].strip()}"
                            ) from None
        raise UserError(f"policy file {str(f)!r} does not hold a complete {state['kind']} policy "
                        f"({type(e).__name__}: {e}); {REFUSED}") from None


def _read(path: str | Path, trust_code: bool) -> tuple[Path, dict[str, Any]]:
    """A policy file and its state. A file on its own (shared) runs no code: one whose encoder a
    module of the user's builds is refused unless `trust_code`; in its run directory, whose
    config.toml names the same encoder, it is the run's own."""
    from relayrl.training.run_dir import lone_policy_file

    f = _policy_file(path)
    state = load_policy_file(f)
    encoder = str(state.get("encoder", ""))
    if is_user_encoder(encoder) and not trust_code and lone_policy_file(f):
        raise UserError(f"the policy file {str(f)!r} has its network built by {encoder!r}, code it would import and "
                        "run, which a policy file on its own is not trusted to: load it from its run directory, or, "
                        "trusting that code, with --trust-code (in Python, relayrl.load_policy(path, trust_code=True), "
                        "which relayrl.evaluate also takes)")
    return f, state


def load_policy_state(path: str | Path, trust_code: bool = False) -> dict[str, Any]:
    """A policy file's state, checked: every key `load_policy` and `export_policy` read is there."""
    f, state = _read(path, trust_code)
    module = for_policy_kind(state.get("kind")).policy_module()  # UserError for a kind this version does not know
    _built(f, state, lambda: (module.load(state, torch.device("cpu"), True, None), module.deterministic_module(state)))
    return state


def load_policy(path: str | Path, device: str | torch.device = "cpu", deterministic: bool = True,
                seed: int | None = None, trust_code: bool = False) -> LoadedPolicy:
    """A run directory, its `policy/` folder or the file itself -> the policy, for plain Python.

    It takes NumPy or torch observations, one [*obs_shape] or a batch [B, *obs_shape], and
    returns actions of the same kind, in the env's action shape: for a batch [B] for discrete
    (DQN's greedy action, PPO's most likely one), [B, *action_shape] for Box (SAC's tanh(mean),
    PPO's mean clipped or squashed into the bounds, or sampled with `deterministic=False`) and
    MultiDiscrete / MultiBinary; for one observation, one action. `policy.predict(obs)` returns
    `(action, None)` as Stable-Baselines3's does. Its `env_steps` is the run's env step when the
    policy was saved. During a run the file is replaced atomically, so a policy can be loaded
    at any moment. `device`: cpu, cuda, cuda:N or auto (the GPU where there is one), as a
    config's. `seed`: the seed of the actions sampled with `deterministic=False` (the same
    seed, the same actions). `trust_code`: load a policy file outside its run directory whose
    network a user's encoder builds, importing and running that code (a shared file runs none
    otherwise).
    """
    from relayrl.training.process import resolve_device

    check_seed(seed)  # else a bad seed read as a broken policy file
    on = resolve_device(str(device))  # "auto" as a run's is; a device not here is one line, not torch's assertion
    f, state = _read(path, trust_code)
    module = for_policy_kind(state.get("kind")).policy_module()
    # Built once (a user's encoder may be costly to make); on another device the file is
    # checked on the CPU first, so a device's own error is not taken for a broken file.
    cpu = _built(f, state, lambda: module.load(state, torch.device("cpu"), deterministic, seed))
    batched = cpu if on.type == "cpu" else built_quietly(module, state, on, deterministic, seed)
    return LoadedPolicy(batched, state, str(on), deterministic, seed)


FORMATS = ("pt2", "onnx")


_UNTRACEABLE = ("; torch.export traces the network: a Python branch on a tensor's value (`if x.max() > 3`, in a "
                "user's agent.encoder) cannot be traced: write it with torch.where")


def _cause(e: BaseException) -> str:
    """The innermost cause of an export failure, as its type and first line (the exporters' own
    lines run long and carry terminal colours)."""
    while e.__cause__ is not None:
        e = e.__cause__
    lines = [line.strip() for line in re.sub(r"\x1b\[[0-9;]*m", "", str(e)).splitlines() if line.strip()]
    first = lines[0] if lines else "no details"
    return f"{type(e).__name__}: {first[:200]}"


def export_policy(path: str | Path, out: str | Path | None = None, format: str | None = None,
                  trust_code: bool = False) -> Path:
    """Write the deterministic policy as a `torch.export` program (`policy.pt2`) or, with
    `format="onnx"`, an ONNX model (`policy.onnx`; needs the `onnx` extra). Beside it,
    `<file>.json` says what it takes and returns (`signature`). Without `out`, the file goes
    into the run's `policy/` folder (beside the policy file given); an `out` that is a folder
    takes the default name. Without `format`, an `out` ending in .onnx or .pt2 names it; else
    pt2. `trust_code`: as `load_policy`'s. Returns the file's path."""
    if out is not None and not isinstance(out, (str, os.PathLike)):
        raise UserError(f"out={out!r} is not valid; give a file or folder path (a str or pathlib.Path), or None")
    named = Path(out).suffix.lstrip(".") if out and not is_folder(out) else ""
    if named and named not in FORMATS:  # torch.export's reader and onnxruntime go by the extension
        raise UserError(f"--out {str(out)!r}: give a file name ending in .pt2 or .onnx, or a folder (in Python: "
                        "out=)")
    if format is None:
        format = named or "pt2"  # `named` is one of FORMATS here, or ""
    if format not in FORMATS:
        raise UserError(f"export format {format!r} is not known; valid: {', '.join(FORMATS)}")
    if named and named != format:
        raise UserError(f"--out {str(out)!r} names the {named} format but --format is {format}: "
                        "give one of them, or the same in both (in Python: out= and format=)")
    if format == "onnx":
        try:
            import onnx  # noqa: F401  (torch.onnx writes the model through these)
            import onnxscript  # noqa: F401
        except ImportError:
            raise UserError("--format onnx (in Python: format='onnx') needs the onnx and onnxscript packages: "
                            f"{install('onnx')}") from None
    from relayrl.training.process import float32_default

    with float32_default():  # the networks relayrl saved, whatever the caller's default dtype
        return _export(path, out, format, trust_code)


def _export(path: str | Path, out: str | Path | None, format: str, trust_code: bool) -> Path:
    """`export_policy`'s program and signature, its arguments checked."""
    state = load_policy_state(path, trust_code)
    with rng_kept(torch.device("cpu")):
        module = for_policy_kind(state["kind"]).policy_module().deterministic_module(state)
    module = module.requires_grad_(False).eval()
    inputs = input_specs(state)
    if "action_shape" in state or "action_dtype" in state:  # actions as the env takes them
        dtype = env_action_dtype(state)
        module = EnvShaped(module, state.get("action_shape"), dtype, env_box_bounds(state, dtype))
    # one input per Dict / Tuple entry, each in the env's own dtype (cast to the one the policy takes)
    module = EnvInputs(module, [(name, spec.dtype) for name, spec in inputs], packed=inputs[0][0] != "obs"
                       or len(inputs) > 1).eval()
    examples = tuple(torch.zeros(2, *spec.shape, dtype=env_torch_dtype(spec)) for _, spec in inputs)
    target = output_path(out, _policy_file(path).with_suffix("." + format))
    batch = torch.export.Dim("batch", min=1)
    dynamic: Any = {"entries": tuple({0: batch} for _ in examples)}  # torch.export names *args by its parameter
    # never a half-written program under the real name; torch.export wants the .pt2 suffix
    with writing(target), atomic.replacing(target, ".tmp-" + target.name) as tmp:
        if format == "pt2":
            try:
                with _quiet_export():
                    program_pt2 = torch.export.export(module, examples, dynamic_shapes=dynamic)
            except Exception as e:  # a network torch.export cannot trace (a user's encoder's Python branch)
                raise UserError(f"this policy cannot be exported ({_cause(e)}){_UNTRACEABLE}") from None
            torch.export.save(program_pt2, tmp)
        else:
            try:
                with _quiet_export():
                    program = torch.onnx.export(module, examples, input_names=[n for n, _ in inputs],
                                                output_names=["action"], dynamic_shapes=dynamic, dynamo=True,
                                                verbose=False)
            except Exception as e:  # an op the ONNX exporter cannot write: one line
                # the exporter's first step is torch.export: where that failed, pt2 fails too
                traced = type(e).__name__ != "TorchExportError"
                raise UserError(f"this policy cannot be exported to ONNX ({_cause(e)})"
                                f"{'; use --format pt2' if traced else _UNTRACEABLE}") from None
            assert program is not None  # dynamo=True returns the program (None is the legacy exporter's)
            program.save(str(tmp))
        # the signature in place before the program is: a failure to write it keeps the old pair
        with torch.no_grad():
            action = module(*examples)
        sig_path = target.with_name(target.name + ".json")
        with writing(sig_path):
            atomic.write_text(sig_path, json.dumps(signature(state, format, action), indent=2) + "\n")
    return target


@contextlib.contextmanager
def _quiet_export() -> Iterator[None]:
    """torch's ONNX exporter notes what it skips ("torchvision is not installed") and warns of its
    own deprecations, and torch.export warns of the symbols it cannot trace and prints the graph it
    failed on to stderr before it raises: noise for a user who asked for a file. Its errors still
    come (relayrl's line names the cause)."""
    logs = [logging.getLogger(name) for name in ("torch.onnx", "torch.fx.experimental.symbolic_shapes")]
    levels = [log.level for log in logs]
    for log in logs:
        log.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stderr(io.StringIO()):
            warnings.simplefilter("ignore", FutureWarning)
            warnings.simplefilter("ignore", DeprecationWarning)
            # one batch Dim over several inputs (a Dict space's entries) is noted as a rename
            warnings.filterwarnings("ignore", message=".*axis name: batch will not be used")
            yield
    finally:
        for log, level in zip(logs, levels, strict=True):
            log.setLevel(level)


class EnvShaped(torch.nn.Module):
    """A policy whose flat [B, A] actions come out in the env's action shape [B, *shape] and dtype,
    inside the env's own `bounds` where given (`loaded_policy.env_box_bounds`)."""

    def __init__(self, module: torch.nn.Module, shape: list[int] | None, dtype: torch.dtype | None,
                 bounds: tuple[torch.Tensor, torch.Tensor] | None = None) -> None:
        super().__init__()
        self.module = module
        self.shape = shape
        self.dtype = dtype
        self.bounds = bounds

    def forward(self, obs: Any) -> torch.Tensor:
        return env_shaped(self.module(obs), self.shape, self.dtype, self.bounds)


class EnvInputs(torch.nn.Module):
    """A policy taking each input in the env's own dtype, cast to the one it was trained on
    (float64 to float32, int32 to int64, ...); for a Dict / Tuple space (`packed`) one input
    per entry, in the space's order, handed on as the dict of entries its encoder takes."""

    def __init__(self, module: torch.nn.Module, inputs: list[tuple[str, torch.dtype]], packed: bool) -> None:
        super().__init__()
        self.module = module
        self.keys = [name for name, _ in inputs]
        self.dtypes = [dtype for _, dtype in inputs]
        self.packed = packed

    def forward(self, *entries: torch.Tensor) -> torch.Tensor:
        cast = [x.to(dtype) for x, dtype in zip(entries, self.dtypes, strict=True)]
        return self.module(dict(zip(self.keys, cast, strict=True)) if self.packed else cast[0])


def input_specs(state: dict[str, Any]) -> list[tuple[str, Spec]]:
    """(name, spec) of each input of an exported policy: "obs", or one per Dict / Tuple entry."""
    spec = saved_obs_spec(state)
    if isinstance(spec, PackedSpec):
        return [(f.key, f.spec) for f in spec.fields]
    return [("obs", spec)]


def signature(state: dict[str, Any], format: str, action: torch.Tensor) -> dict[str, Any]:
    """What an exported policy takes and returns, for `<file>.json` and the CLI's line."""
    inputs = [{"name": name, "dtype": str(env_torch_dtype(spec)).removeprefix("torch."),
               "shape": ["batch", *spec.shape]} for name, spec in input_specs(state)]
    # "input" for the one tensor `obs`; "inputs" alone for a Dict / Tuple policy's entries, whose
    # first one under "input" would read as the whole input
    one = len(inputs) == 1 and inputs[0]["name"] == "obs"
    # the env as the policy was trained on it: what a deployment must reproduce to build the input
    env = {k: state[k] for k in ("env_kwargs", "env_wrappers", "max_episode_steps") if state.get(k)}
    return {"format": format, "kind": state["kind"], "env_id": state.get("env_id"), **env,
            "env_steps": state.get("env_steps"), **({"input": inputs[0]} if one else {"inputs": inputs}),
            "output": {"name": "action", "dtype": str(action.dtype).removeprefix("torch."),
                       "shape": ["batch", *action.shape[1:]]}}


def describe(sig: dict[str, Any]) -> str:
    """'input obs float32 [batch, 4] -> output action int64 [batch]'."""
    def one(part: dict[str, Any]) -> str:
        return f"{part['name']} {part['dtype']} [{', '.join(map(str, part['shape']))}]"

    inputs = sig["inputs"] if "inputs" in sig else [sig["input"]]
    return f"input{'s' if len(inputs) > 1 else ''} {', '.join(map(one, inputs))} -> output {one(sig['output'])}"
