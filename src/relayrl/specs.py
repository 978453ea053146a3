"""Specs: shape, dtype and bounds of observations and actions, derived from Gymnasium spaces.

Specs describe one element of a batch; batched tensors carry an extra leading dim. Every
space kind maps to one spec: Box -> ArraySpec, Discrete -> DiscreteSpec, MultiDiscrete and
MultiBinary -> their ArraySpec subclasses, Dict and Tuple -> a PackedSpec, so envs, replay and
rollouts handle each observation as one array.

Dict and Tuple observations travel as one byte row: each leaf's bytes at its own aligned
offset, in its own dtype bit for bit (a uint8 image stays one byte per pixel, a float32 vector
four), so storage costs what the leaves cost, and every part that moves observations (shared
memory, the step store's rows, compiled writers, Ray) stays one code path. The encoder
(`nn.encoders.DictEncoder`) views the leaves back without a copy (`unpack`); `PackedSpec.pack`
and `pack_batch` build rows from what the env returns or what a user passes a policy.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from relayrl.arrays import torch_dtype
from relayrl.errors import UserError
from relayrl.frames import frame_layout, frame_layout_before

_TORCH_DTYPES = {
    np.dtype(np.float32): torch.float32,
    np.dtype(np.float64): torch.float32,  # float64 observations are stored and fed as float32
    np.dtype(np.float16): torch.float32,
    np.dtype(np.uint8): torch.uint8,
    np.dtype(np.int8): torch.int8,
    np.dtype(np.int16): torch.int16,
    np.dtype(np.uint16): torch.int32,
    np.dtype(np.int32): torch.int64,
    np.dtype(np.uint32): torch.int64,
    np.dtype(np.int64): torch.int64,
    np.dtype(np.bool_): torch.bool,
}
OBSERVATION_SPACES = "Box, Discrete, MultiDiscrete, MultiBinary, Dict, Tuple"
ACTION_SPACES = "DQN: Discrete; SAC: Box; PPO: Discrete, Box, MultiDiscrete, MultiBinary"


@dataclass(frozen=True)
class ArraySpec:
    """A tensor of fixed shape and dtype, optionally bounded (inclusive)."""

    shape: tuple[int, ...]
    dtype: torch.dtype
    low: np.ndarray | None = None
    high: np.ndarray | None = None
    # k > 1: each observation is a stack of k frames along dim 0 whose older frames are the
    # previous steps' frames (Gymnasium's FrameStackObservation, padding "reset"), so a
    # replay may store only each step's newest frame. Set by the env adapters, not by spaces.
    frame_stack: int = 1
    # A Box action of any other rank than 1 (a scalar, [2, 2]) travels flat, as `shape` = (its
    # size,): the env adapters reshape each action to `env_shape`, and a saved policy's actions
    # come out in it. Set by the env adapters, not by spaces.
    env_shape: tuple[int, ...] | None = None
    # The space's own NumPy dtype where `dtype` is another (float64 and float16 Boxes travel as
    # float32, int32 as int64, ...): the env adapters give actions in it, and a saved policy's
    # actions and an exported program's inputs take it.
    env_dtype: str | None = None

    def zeros(self, batch: int) -> torch.Tensor:
        return torch.zeros((batch, *self.shape), dtype=self.dtype)


def flat_action(spec: ArraySpec) -> ArraySpec:
    """`spec` as a 1-D action, remembering the env's shape (itself where it is 1-D already)."""
    if len(spec.shape) == 1:
        return spec
    size = int(np.prod(spec.shape))
    low, high = (None if b is None else np.asarray(b).reshape(size) for b in (spec.low, spec.high))
    return replace(spec, shape=(size,), low=low, high=high, env_shape=tuple(spec.shape))


@dataclass(frozen=True)
class DiscreteSpec:
    """A scalar integer action or observation in [0, n)."""

    n: int
    shape: tuple[int, ...] = ()
    dtype: torch.dtype = torch.int64

    def zeros(self, batch: int) -> torch.Tensor:
        return torch.zeros((batch,), dtype=self.dtype)


@dataclass(frozen=True)
class MultiDiscreteSpec(ArraySpec):
    """Integers [*shape], entry i in [0, nvec[i]) (Gymnasium's MultiDiscrete)."""

    nvec: tuple[int, ...] = ()  # flattened, one per entry


@dataclass(frozen=True)
class MultiBinarySpec(ArraySpec):
    """0/1 entries [*shape] (Gymnasium's MultiBinary)."""


Spec = ArraySpec | DiscreteSpec


def value_limit(spec: Spec) -> Any:
    """The exclusive upper bound of a Discrete / MultiDiscrete / MultiBinary value (an int, or an
    array shaped like the spec; values start at 0); None for other specs."""
    if isinstance(spec, DiscreteSpec):
        return spec.n
    if isinstance(spec, MultiDiscreteSpec):
        return np.asarray(spec.nvec).reshape(spec.shape)
    return 2 if isinstance(spec, MultiBinarySpec) else None


def spec_from_space(space: gym.Space, role: str = "observation") -> Spec:
    """The spec of one element of `space` (`role`: "observation" or "action", for messages);
    UserError, naming the space and what is valid, for spaces relayrl cannot take."""
    if role == "action" and space.shape is not None and math.prod(space.shape) == 0:  # Box, MultiDiscrete: (0,)
        raise UserError(f"action space {space} has no dimensions: there is no action to learn")
    if isinstance(space, gym.spaces.Discrete):
        if int(space.start) != 0:
            raise UserError(f"{role} space {space} starts at {space.start}; relayrl takes Discrete spaces that start "
                            "at 0 (wrap the env to shift them)")
        return DiscreteSpec(n=int(space.n))
    if isinstance(space, gym.spaces.Box):
        dtype = _TORCH_DTYPES.get(np.dtype(space.dtype))
        if dtype is None:
            raise UserError(f"{role} space {space} has dtype {space.dtype}; valid Box dtypes: float16/32/64, "
                            "uint8, int8/16/32/64, uint16/32, bool")
        return ArraySpec(tuple(space.shape), dtype, np.asarray(space.low), np.asarray(space.high),
                         env_dtype=_other_dtype(space.dtype, dtype))
    if isinstance(space, gym.spaces.MultiDiscrete):
        if np.any(np.asarray(space.start) != 0):
            raise UserError(f"{role} space {space} has a start other than 0; relayrl takes MultiDiscrete spaces "
                            "that start at 0 (wrap the env to shift them)")
        nvec = np.asarray(space.nvec, np.int64)
        return MultiDiscreteSpec(tuple(nvec.shape), torch.int64, np.zeros_like(nvec), nvec - 1,
                                 env_dtype=_other_dtype(space.dtype, torch.int64),
                                 nvec=tuple(int(n) for n in nvec.reshape(-1)))
    if isinstance(space, gym.spaces.MultiBinary):
        shape = tuple(np.atleast_1d(np.asarray(space.n)).tolist())
        return MultiBinarySpec(shape, torch.int8, np.zeros(shape, np.int8), np.ones(shape, np.int8),
                               env_dtype=_other_dtype(space.dtype, torch.int8))
    if isinstance(space, gym.spaces.Dict | gym.spaces.Tuple) and role == "observation":
        return packed_spec(space)
    valid = OBSERVATION_SPACES if role == "observation" else ACTION_SPACES
    # a Text space's repr names its charset, MiniGrid's MissionSpace's a function at an address
    shown = type(space).__name__ if isinstance(space, gym.spaces.Text) or " at 0x" in str(space) else str(space)
    raise UserError(f"{role} space {shown} is not supported; valid {role} spaces: {valid}")


def _other_dtype(space_dtype: Any, stored: torch.dtype) -> str | None:
    """The space's NumPy dtype's name where it is not the one relayrl stores (`env_dtype`)."""
    name = np.dtype(space_dtype).name
    return None if name == _numpy_of(stored).name else name


def env_numpy_dtype(spec: Spec) -> np.dtype:
    """The dtype the env's space has (the dtype stored, unless `env_dtype` says another)."""
    return np.dtype(spec.env_dtype) if isinstance(spec, ArraySpec) and spec.env_dtype else numpy_dtype(spec)


def env_torch_dtype(spec: Spec) -> torch.dtype:
    return torch_dtype(env_numpy_dtype(spec))


def describe(spec: Spec) -> str:
    """The space a spec came from, in Gymnasium's words, for messages."""
    if isinstance(spec, DiscreteSpec):
        return f"Discrete({spec.n})"
    # a flattened action: the env's own shape
    shape = spec.env_shape if isinstance(spec, ArraySpec) and spec.env_shape is not None else spec.shape
    if isinstance(spec, MultiDiscreteSpec):
        return f"MultiDiscrete({np.reshape(spec.nvec, shape).tolist()})"
    if isinstance(spec, MultiBinarySpec):
        return f"MultiBinary({list(shape)})"
    if isinstance(spec, PackedSpec):
        entries = ", ".join(describe(f.spec) if spec.tuple_space else f"{f.key}: {describe(f.spec)}"
                            for f in spec.fields)
        return f"{'Tuple' if spec.tuple_space else 'Dict'}({entries})"
    bounds = "" if spec.low is None or spec.high is None else f"{_bound(spec.low)}, {_bound(spec.high)}, "
    return f"Box({bounds}shape={tuple(shape)}, dtype={env_numpy_dtype(spec).name})"  # the env's dtype


def _bound(values: np.ndarray) -> str:
    """A Box bound for messages: one number where every entry is the same, else the entries."""
    one = _same_everywhere(values)
    if one is not None:
        return f"{one:g}" if np.issubdtype(one.dtype, np.floating) else str(one)
    return np.array2string(np.asarray(values).reshape(-1), threshold=8, separator=", ",
                           max_line_width=10**9)  # a message is one line


def _same_everywhere(values: np.ndarray) -> np.generic | None:
    """The one value every entry of `values` holds, else None."""
    flat = np.asarray(values).reshape(-1)
    return flat[0] if flat.size and (flat == flat[0]).all() else None


def flat_dim(spec: Spec) -> int:
    """Number of scalars in one element (1 for a DiscreteSpec)."""
    return int(np.prod(spec.shape)) if spec.shape else 1


def is_flat_vector(spec: Spec) -> bool:
    """A Box of any rank that an MLP takes flattened as it is (not an image, not a packed
    structure, not integers with a meaning of their own such as Discrete)."""
    return type(spec) is ArraySpec and not is_image(spec)


def is_image(spec: Spec, any_bounds: bool = False) -> bool:
    """A uint8 Box laid out as frames (`frame_layout`) whose bounds are 0 and 255 (Stable-Baselines3's
    rule): frames, which the conv encoders take (scaled by 1/255). A uint8 grid of codes (a
    board, Box(0, 2)) is a vector of numbers, unless a conv encoder is asked for by name
    (`any_bounds`). A spec without bounds (a policy file from before they were kept) counts as
    having them."""
    if type(spec) is not ArraySpec or spec.dtype != torch.uint8 or frame_layout(spec.shape) is None:
        return False
    return any_bounds or _pixel_bounds(spec)


def is_float_frames(spec: Spec) -> bool:
    """A float Box laid out as one frame of 1, 3 or 4 channels ([C, H, W] or [H, W, C], sides
    >= 8): an image already scaled (to [0, 1], say), which the conv encoders take as it is where
    asked for by name; "auto" flattens it, as only uint8 frames 0..255 tell images from other
    grids of floats (a [10, 8] stack of vectors is not one)."""
    if type(spec) is not ArraySpec or not spec.dtype.is_floating_point or len(spec.shape) != 3:
        return False
    layout = frame_layout(spec.shape)
    channels = spec.shape[0] if layout == "CHW" else spec.shape[-1] if layout == "HWC" else 0
    return channels in (1, 3, 4)


def _pixel_bounds(spec: ArraySpec) -> bool:
    return spec.low is None or spec.high is None or bool((spec.low == 0).all() and (spec.high == 255).all())


def spec_state(spec: Spec) -> dict[str, Any]:
    """A spec as plain data (for policy files, which hold only plain types)."""
    if isinstance(spec, DiscreteSpec):
        return {"kind": "discrete", "n": spec.n}
    if isinstance(spec, PackedSpec):
        return {"kind": "packed", "tuple": spec.tuple_space,
                "fields": [{"key": f.key, "path": list(f.path), "spec": spec_state(f.spec)} for f in spec.fields]}
    kind = ("multi_discrete" if isinstance(spec, MultiDiscreteSpec)
            else "multi_binary" if isinstance(spec, MultiBinarySpec) else "box")
    state: dict[str, Any] = {"kind": kind, "shape": list(spec.shape), "dtype": str(spec.dtype).removeprefix("torch.")}
    if isinstance(spec, MultiDiscreteSpec):
        state["nvec"] = list(spec.nvec)
    if spec.env_dtype:
        state["env_dtype"] = spec.env_dtype
    if kind == "box" and spec.dtype == torch.uint8 and spec.low is not None and spec.high is not None:
        for key, bound in (("low", spec.low), ("high", spec.high)):  # `is_image` reads them
            one = _same_everywhere(bound)  # a frame's 0 or 255
            state[key] = np.asarray(bound).tolist() if one is None else int(one)
        state["layout"] = frame_layout(spec.shape)  # the layout its networks were built for
    return state


def spec_from_state(state: dict[str, Any]) -> Spec:
    """`spec_state`'s inverse (bounds are kept for uint8 Boxes only, which `is_image` reads;
    policies read no others)."""
    kind = state["kind"]
    if kind == "discrete":
        return DiscreteSpec(int(state["n"]))
    if kind == "packed":
        return PackedSpec.build([(f["key"], tuple(f["path"]), spec_from_state(f["spec"])) for f in state["fields"]],
                                bool(state["tuple"]))
    shape, dtype, env = tuple(int(d) for d in state["shape"]), getattr(torch, state["dtype"]), state.get("env_dtype")
    if kind == "multi_discrete":
        return MultiDiscreteSpec(shape, dtype, env_dtype=env, nvec=tuple(int(n) for n in state["nvec"]))
    if kind == "multi_binary":
        return MultiBinarySpec(shape, dtype, env_dtype=env)
    low, high = ((np.broadcast_to(np.asarray(state[k], np.uint8), shape).copy() for k in ("low", "high"))
                 if "low" in state else (None, None))
    return ArraySpec(shape, dtype, low, high, env_dtype=env)


def check_trained_layout(state: dict[str, Any], any_bounds: bool = False, recorded: bool = True) -> None:
    """UserError where frames in a saved observation space (`spec_state`'s form) were read with
    another layout when its networks were trained than `frame_layout` reads them now: a conv
    encoder would be built for other sides or channels. `recorded`: the state's own "layout"
    entries count (a checkpoint's `spaces` lack them: the former rule then applies); `any_bounds`:
    a conv encoder asked for by name reads any uint8 Box as frames."""
    if state["kind"] == "packed":
        for f in state["fields"]:
            check_trained_layout(f["spec"], any_bounds, recorded)
        return
    if state["kind"] != "box" or state["dtype"] != "uint8":
        return
    spec = spec_from_state(state)
    assert isinstance(spec, ArraySpec)
    trained = state["layout"] if recorded and "layout" in state else frame_layout_before(spec.shape)
    if (any_bounds or _pixel_bounds(spec)) and trained != frame_layout(spec.shape):
        raise UserError(f"{describe(spec)} observations were read as {trained or 'a flat vector'} when this run "
                        f"was trained; this version reads them as {frame_layout(spec.shape) or 'a flat vector'} "
                        "(the smaller outer side is the channels, the first where only the last two are equal): "
                        "train it again")


def to_space(spec: Spec, stored: bool = False) -> gym.Space:
    """The Gymnasium space a spec describes, as far as the spec keeps it (a Box without bounds is
    unbounded; integers within their dtype's range, bools 0 and 1), in the env's dtypes, or with `stored` in
    the dtypes relayrl keeps (float32, int64): what a user's encoder is given and fed."""
    dtype_of = numpy_dtype if stored else env_numpy_dtype
    if isinstance(spec, DiscreteSpec):
        return gym.spaces.Discrete(spec.n)
    if isinstance(spec, MultiDiscreteSpec):
        return gym.spaces.MultiDiscrete(np.asarray(spec.nvec).reshape(spec.shape), dtype=dtype_of(spec))
    if isinstance(spec, MultiBinarySpec):
        return gym.spaces.MultiBinary(spec.shape[0] if len(spec.shape) == 1 else list(spec.shape))
    if isinstance(spec, PackedSpec):
        return spec.nested([to_space(f.spec, stored) for f in spec.fields], gym.spaces.Tuple, gym.spaces.Dict)
    dtype = dtype_of(spec)
    if spec.low is not None and spec.high is not None:  # bounds in the dtype: Gymnasium warns of a lowered precision
        low, high = np.asarray(spec.low).astype(dtype), np.asarray(spec.high).astype(dtype)
        return gym.spaces.Box(low, high, spec.shape, dtype)
    if dtype == np.bool_:
        return gym.spaces.Box(0, 1, spec.shape, dtype)
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        return gym.spaces.Box(int(info.min), int(info.max), spec.shape, dtype)
    return gym.spaces.Box(-np.inf, np.inf, spec.shape, dtype)


def numpy_dtype(spec: Spec) -> np.dtype:
    return _numpy_of(spec.dtype)


def _numpy_of(dtype: torch.dtype) -> np.dtype:
    return torch.empty((), dtype=dtype).numpy().dtype


def is_bounded_box(spec: Spec) -> bool:
    """A continuous action space with finite low and high everywhere (what SAC's squashed
    Gaussian needs)."""
    return (isinstance(spec, ArraySpec) and spec.dtype.is_floating_point
            and spec.low is not None and spec.high is not None
            and bool(np.isfinite(spec.low).all() and np.isfinite(spec.high).all()))


def which_algorithms(action_spec: Spec) -> str:
    """For a refusal of `action_spec`: which of relayrl's algorithms take actions of its kind."""
    if isinstance(action_spec, DiscreteSpec):
        return "DQN and PPO take Discrete actions"
    if isinstance(action_spec, MultiDiscreteSpec | MultiBinarySpec):
        return f"PPO takes {type(action_spec).__name__.removesuffix('Spec')} actions"
    if isinstance(action_spec, ArraySpec) and not action_spec.dtype.is_floating_point:
        return ("no relayrl algorithm takes a Box of integers: a MultiDiscrete action space (a wrapper that maps "
                "it to the Box) trains with PPO")
    if is_bounded_box(action_spec):
        return "SAC and PPO take Box actions"
    return ("PPO takes a Box with infinite bounds; SAC needs finite ones (Gymnasium's ClipAction makes them "
            "infinite: SAC's actions stay in the env's bounds without it; else a wrapper whose action_space is a "
            "finite Box, mapping it to the env's)")


ALIGN = 8  # every leaf starts at a multiple of its own item size (<= 8), so a view of it is a valid array


@dataclass(frozen=True)
class Field:
    key: str  # "image", "pos.x" for nested dicts, "0" for a Tuple's first entry
    path: tuple[str | int, ...]  # how to reach the leaf in the observation
    spec: Spec
    offset: int  # bytes into the row
    nbytes: int


@dataclass(frozen=True)
class PackedSpec(ArraySpec):
    """A Dict or Tuple observation packed into uint8 [nbytes] (see the module docstring)."""

    fields: tuple[Field, ...] = ()
    tuple_space: bool = False  # the space is a Tuple: a policy also takes a tuple or list

    @staticmethod
    def build(leaves: Sequence[tuple[str, tuple[str | int, ...], Spec]], tuple_space: bool) -> PackedSpec:
        fields, offset = [], 0
        for key, path, spec in leaves:
            nbytes = int(np.prod(spec.shape, dtype=np.int64)) * numpy_dtype(spec).itemsize
            fields.append(Field(key, path, spec, offset, nbytes))
            offset += -(-nbytes // ALIGN) * ALIGN
        return PackedSpec((max(offset, ALIGN),), torch.uint8, fields=tuple(fields), tuple_space=tuple_space)

    def pack(self, obs: Any) -> np.ndarray:
        """One observation as the env returns it -> uint8 [nbytes]."""
        return self.pack_batch(obs, batch=None)[0]

    def pack_batch(self, obs: Any, batch: int | None) -> np.ndarray:
        """Leaves [batch, *leaf_shape] (or one observation, batch None) -> uint8 [batch or 1, nbytes]."""
        n = 1 if batch is None else batch
        row = np.zeros((n, self.shape[0]), np.uint8)
        for f in self.fields:
            leaf = leaf_array(obs, f)
            want = f.spec.shape if batch is None else (batch, *f.spec.shape)
            if leaf.shape != want:
                first = self.fields[0].key
                batched = ("" if batch is None else
                           f" or a batch [B, ...] for all keys, as observation[{first!r}]'s B = {batch}")
                raise UserError(f"observation[{f.key!r}] has shape {leaf.shape}; this policy takes "
                                f"{list(f.spec.shape)}{batched}")
            dtype = numpy_dtype(f.spec)
            stored = leaf.astype(dtype, copy=False)
            # an integer entry whose cast may change values (float frames, numbers outside the dtype):
            # the caller says what was wrong (the env's step, `_unfit`; a policy checks values first)
            if (stored is not leaf and dtype.kind in "iu" and not np.can_cast(leaf.dtype, dtype, "safe")
                    and not np.array_equal(stored, leaf)):
                raise ValueError(f"observation[{f.key!r}] holds {leaf.dtype} values that {dtype} would change")
            row[:, f.offset:f.offset + f.nbytes] = stored.reshape(n, -1).view(np.uint8)
        return row

    def observation(self, row: np.ndarray) -> Any:
        """`pack`'s inverse: one packed row [nbytes] -> the observation as the env returns it (nested
        dicts and tuples of arrays, a Discrete entry as an integer)."""
        leaves = [row[f.offset:f.offset + f.nbytes].view(numpy_dtype(f.spec)).reshape(f.spec.shape)
                  for f in self.fields]
        return self.nested([leaf[()] if leaf.ndim == 0 else leaf.copy() for leaf in leaves])

    def nested(self, leaves: list[Any], as_tuple: Callable[[list[Any]], Any] = tuple,
               as_dict: Callable[[dict[Any, Any]], Any] = dict) -> Any:
        """One value per field (in `fields`' order) put in the space's structure: a Tuple's
        entries through `as_tuple`, a Dict's through `as_dict` (tuples and dicts of the values by
        default; `gym.spaces.Tuple` and `gym.spaces.Dict` for spaces)."""
        tree: dict[Any, Any] = {}
        for f, leaf in zip(self.fields, leaves, strict=True):
            node = tree
            for step in f.path[:-1]:
                node = node.setdefault(step, {})
            node[f.path[-1]] = leaf
        return _as_space(tree, self.tuple_space and not isinstance(next(iter(tree)), str), as_tuple, as_dict)

    def batch_size(self, obs: Any) -> int | None:
        """None when `obs` is one observation, else the batch its leaves share."""
        first = self.fields[0]
        leaf = leaf_array(obs, first)
        extra = leaf.ndim - len(first.spec.shape)
        if extra not in (0, 1):
            raise UserError(f"observation[{first.key!r}] has shape {leaf.shape}; this policy takes "
                            f"{list(first.spec.shape)} or a batch [B, {', '.join(map(str, first.spec.shape))}]")
        return leaf.shape[0] if extra == 1 else None


def _as_space(node: Any, tuple_here: bool, as_tuple: Callable[[list[Any]], Any],
              as_dict: Callable[[dict[Any, Any]], Any]) -> Any:
    """Nested dicts from `nested` as the space's structure: int keys are a Tuple's entries."""
    if not isinstance(node, dict):
        return node
    if tuple_here or all(isinstance(k, int) for k in node):
        return as_tuple([_as_space(node[k], False, as_tuple, as_dict) for k in sorted(node)])
    return as_dict({k: _as_space(v, False, as_tuple, as_dict) for k, v in node.items()})


def leaf_array(obs: Any, f: Field) -> np.ndarray:
    """The entry field `f` names, as a NumPy array (a tensor's detached host copy)."""
    x = entry(obs, f)
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def entry(obs: Any, f: Field) -> Any:
    """The entry of a Dict / Tuple observation that field `f` names, as it is given."""
    x = obs
    for step in f.path:
        try:
            x = x[step]
        except (KeyError, IndexError, TypeError):
            what = "a dict with key" if isinstance(step, str) else "a tuple with entry"
            raise UserError(f"observation is not {what} {step!r} (this policy takes {f.key!r}: "
                            f"{list(f.spec.shape)})") from None
    return x


# the space kinds an observation entry may be (spec_from_space takes them, Dict and Tuple aside)
_TAKEN = (gym.spaces.Discrete, gym.spaces.Box, gym.spaces.MultiDiscrete, gym.spaces.MultiBinary)


def packed_spec(space: gym.spaces.Dict | gym.spaces.Tuple) -> PackedSpec:
    """The packed spec of a Dict or Tuple space (nested ones flattened into dotted keys)."""
    leaves: list[tuple[str, tuple[str | int, ...], Spec]] = []

    def walk(s: gym.Space, path: tuple[str | int, ...]) -> None:
        if isinstance(s, gym.spaces.Dict):
            for k, sub in s.spaces.items():
                walk(sub, (*path, k))
        elif isinstance(s, gym.spaces.Tuple):
            for i, sub in enumerate(s.spaces):
                walk(sub, (*path, i))
        else:
            key = ".".join(map(str, path))
            try:
                leaves.append((key, path, spec_from_space(s, "observation")))
            except UserError as e:  # which entry of a large Dict the user's wrapper must change
                # a kind relayrl takes (a Discrete that starts at 1) is mended by a wrapper; another is left out
                drop = "" if isinstance(s, _TAKEN) else (
                    f"; an env.wrappers entry that leaves {key!r} out (a function of the env returning "
                    "gymnasium.wrappers.FilterObservation(env, the other keys), or the env's own wrapper for it) "
                    "trains on the rest")
                raise UserError(f"the observation's entry {key!r}: {e}{drop}") from None

    walk(space, ())
    if not leaves:
        raise UserError(f"observation space {space} has no entries")
    return PackedSpec.build(leaves, isinstance(space, gym.spaces.Tuple))


def unpack(x: torch.Tensor, spec: PackedSpec) -> dict[str, torch.Tensor]:
    """uint8 rows [B, nbytes] -> each leaf [B, *leaf_shape] in its dtype (views, no copy)."""
    b = x.shape[0]
    out = {}
    for f in spec.fields:
        part = x[:, f.offset:f.offset + f.nbytes]
        if f.spec.dtype != torch.uint8:
            part = part.view(f.spec.dtype)  # valid on the slice: offsets and row length are multiples of ALIGN
        out[f.key] = part.reshape(b, *f.spec.shape)
    return out
