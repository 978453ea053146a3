"""Observation encoders, chosen from the observation's spec: what every algorithm's networks
put before their MLPs, so any Gymnasium space reaches them as a float vector [B, features].

- a Box of any rank: flattened (no encoder: the MLP flattens; the fast MLP paths stay on)
- an image (uint8 [H, W], [C, H, W] or [H, W, C], sides >= 8, bounds 0 and 255): a conv net on
  pixels / 255 (a uint8 grid of codes, Box(0, 2), is a Box like any other):
  the Nature CNN from 36x36 up (84x84 frames as Mnih et al. 2015), a small one below
- Discrete: one-hot; MultiDiscrete: one one-hot per entry, concatenated; MultiBinary: floats
- Dict and Tuple: each entry encoded as above, concatenated (as SB3's CombinedExtractor)

`agent.encoder` picks: "auto" (the above), "flatten" (every leaf flattened as floats, images
unscaled), "nature_cnn" or "small_cnn" (that conv net for images: uint8 frames scaled by 1/255,
float ones, already scaled, as they are).
"""

from __future__ import annotations

from typing import cast

import torch
from torch import nn

from relayrl.config_fields import ENCODERS, is_user_encoder
from relayrl.errors import UserError, note_where
from relayrl.frames import image_layout, image_size
from relayrl.nn.mlp import MLP
from relayrl.nn.modes import evaluating
from relayrl.specs import (
    ArraySpec,
    DiscreteSpec,
    MultiBinarySpec,
    MultiDiscreteSpec,
    PackedSpec,
    Spec,
    describe,
    flat_dim,
    is_flat_vector,
    is_float_frames,
    is_image,
    spec_from_state,
    spec_state,
    to_space,
    unpack,
)
from relayrl.user_code import bind_error, load_callable

# (out_channels, kernel, stride, padding) per conv, then the dense width: Mnih et al. 2015's Nature
# CNN (the Mario tutorial's net is the same, layer for layer)
NATURE_CONVS, NATURE_HIDDEN = ((32, 8, 4, 0), (64, 4, 2, 0), (64, 3, 1, 0)), 512
# for frames from 8x8 (MiniGrid-like) to 35x35, where the Nature CNN's 8x8 stride-4 first layer
# would leave almost nothing
SMALL_CONVS = ((32, 3, 1, 1), (64, 3, 2, 1), (64, 3, 2, 1))
SMALL_HIDDEN = 256
NATURE_MIN_SIDE = 36
CONV_READY = ("auto", "nature_cnn", "small_cnn")  # the agent.encoder kinds that build a conv net for frames


class Flatten(nn.Module):
    """[B, ...] -> float32 [B, n]."""

    def __init__(self, spec: Spec) -> None:
        super().__init__()
        self.out_dim = flat_dim(spec)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.reshape(x.shape[0], -1).float()


class OneHot(nn.Module):
    """Integers [B, *shape], entry i in [0, nvec[i]) -> concatenated one-hots [B, sum(nvec)]."""

    offsets: torch.Tensor  # a buffer, declared for the type checker

    def __init__(self, nvec: tuple[int, ...]) -> None:
        super().__init__()
        offsets = torch.tensor([0, *nvec[:-1]], dtype=torch.int64).cumsum(0)
        self.register_buffer("offsets", offsets, persistent=False)  # [k] where entry i's one-hot starts
        self.out_dim = int(sum(nvec))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        idx = x.reshape(x.shape[0], -1).long() + self.offsets  # [B, k]
        return torch.zeros(x.shape[0], self.out_dim, device=x.device).scatter_(1, idx, 1.0)  # [B, sum(nvec)]


class ConvEncoder(nn.Module):
    """Frames -> [B, hidden]: convs + ReLU, flatten, one dense layer + ReLU. uint8 frames are
    scaled by 1/255, float ones taken as they are."""

    def __init__(self, spec: ArraySpec, convs: tuple[tuple[int, ...], ...], hidden: int) -> None:
        super().__init__()
        channels, self.channels_last = image_layout(spec)
        self.channels = channels
        self.merge = len(spec.shape) != 3  # [H, W] gains a channel, a stack's frames become channels
        h, w = image_size(spec)
        layers: list[nn.Module] = []
        c = channels
        for out, kernel, stride, *pad in convs:  # (out, kernel, stride[, padding]): padding 0 unless given
            layers += [nn.Conv2d(c, out, kernel, stride, padding=pad[0] if pad else 0), nn.ReLU()]
            c = out
        self.convs = nn.Sequential(*layers, nn.Flatten())
        with torch.no_grad():  # the flattened size for this frame size
            flat = self.convs(torch.zeros(1, channels, h, w)).shape[1]
        self.dense = nn.Sequential(nn.Linear(flat, hidden), nn.ReLU())
        self.out_dim = hidden

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.channels_last:
            x = x.movedim(-1, -3)  # [B, (S,) C, H, W]
        if self.merge:
            x = x.reshape(x.shape[0], self.channels, *x.shape[-2:])  # [B, C, H, W]
        x = x.float().mul_(1.0 / 255.0) if x.dtype == torch.uint8 else x.float()
        return self.dense(self.convs(x))


class DictEncoder(nn.Module):
    """Packed Dict / Tuple rows -> each entry's encoding, concatenated in the space's order."""

    def __init__(self, spec: PackedSpec, kind: str) -> None:
        super().__init__()
        self.spec = spec
        keys = [f.key.replace(".", "/") for f in spec.fields]  # ModuleDict keys may not hold dots
        if len(set(keys)) < len(keys):  # "a.b" beside {"a": {"b": ...}} (or "a/b"): one name for two entries
            same = sorted({f.key for f, k in zip(spec.fields, keys, strict=True) if keys.count(k) > 1})
            raise UserError(f"observation entries {', '.join(map(repr, same))} are one name once nested keys are "
                            "joined with '.': rename the env's Dict keys so that none holds '.' or '/'")
        self.parts = nn.ModuleDict({k: leaf_encoder(f.spec, kind) for f, k in zip(spec.fields, keys, strict=True)})
        self.out_dim = sum(encoder_dim(m) for m in self.parts.values())

    def forward(self, x: torch.Tensor | dict[str, torch.Tensor]) -> torch.Tensor:
        """Packed rows [B, nbytes], or the entries themselves by key (an exported policy's inputs)."""
        leaves = x if isinstance(x, dict) else unpack(x, self.spec)
        return torch.cat([m(leaves[f.key]) for f, m in zip(self.spec.fields, self.parts.values(), strict=True)], dim=1)


def encoder_dim(encoder: nn.Module) -> int:
    """The features an encoder gives per observation: each one here sets an int `out_dim`, which
    Module's attribute typing reads as Tensor | Module."""
    return int(cast(int, encoder.out_dim))


def leaf_encoder(spec: Spec, kind: str, float_frames: bool = False) -> nn.Module:
    """The encoder of one non-structured spec (Flatten where nothing more is needed).
    `float_frames`: float images take the conv net `kind` names (a whole observation's; a Dict's
    float entries stay flattened, as they were before float images were taken)."""
    if kind == "flatten" or isinstance(spec, MultiBinarySpec):
        return Flatten(spec)
    if isinstance(spec, (DiscreteSpec, MultiDiscreteSpec)):
        return OneHot((spec.n,) if isinstance(spec, DiscreteSpec) else spec.nvec)
    if not is_image(spec, any_bounds=kind != "auto") and not (float_frames and is_float_frames(spec)):
        return Flatten(spec)
    tiny = min(image_size(spec)) < NATURE_MIN_SIDE
    if kind == "nature_cnn" and tiny:
        raise UserError(f"agent.encoder='nature_cnn' needs frames of at least {NATURE_MIN_SIDE}x{NATURE_MIN_SIDE}, "
                        f"got {describe(spec)}; use agent.encoder='small_cnn' or 'auto'")
    if kind == "small_cnn" or tiny:
        return ConvEncoder(spec, SMALL_CONVS, SMALL_HIDDEN)
    return ConvEncoder(spec, NATURE_CONVS, NATURE_HIDDEN)


class UserEncoder(nn.Module):
    """A user's encoder, `agent.encoder = "package.module:make"`: `make(observation_space)` returns
    a torch module taking a batch of observations as relayrl keeps them (float Boxes as float32,
    other integers as int64, uint8 as uint8, MultiBinary as int8, a Dict / Tuple as a dict of
    tensors by entry key: "pos", "a.b", "0") and giving [B, features]. The space it is given has
    those dtypes, and is rebuilt from what a policy file keeps (`to_space` of the saved spec: a
    Box's bounds only where it is uint8), so a loaded policy builds it alike."""

    def __init__(self, spec: Spec, name: str) -> None:
        super().__init__()
        make = load_callable(name, "agent.encoder")
        space = to_space(spec_from_state(spec_state(spec)), stored=True)  # as a policy file rebuilds it
        if (why := bind_error(make, space)) is not None:
            raise UserError(f"agent.encoder={name!r} cannot be called with the observation space alone ({why}); "
                            "give a function make(observation_space) that returns your torch module")
        try:  # its own errors are its own: their traceback, and what relayrl called it with
            module = make(space)
        except Exception as e:
            note_where(e, f"by agent.encoder={name!r}, called as make(observation_space) with {space}")
            raise
        if not isinstance(module, nn.Module):
            raise UserError(f"agent.encoder={name!r} returned {type(module).__name__}, not a torch.nn.Module")
        self.module = module
        self.packed = spec if isinstance(spec, PackedSpec) else None
        features: set[int] = set()
        for b in (1, 2):  # a batch of one too: a squeeze() would pass a batch of two alone
            # in eval mode: a BatchNorm takes a batch of one there, and keeps its statistics
            with torch.no_grad(), evaluating(module):
                zeros = spec.zeros(b)
                try:
                    out = module(unpack(zeros, spec) if isinstance(spec, PackedSpec) else zeros)
                except Exception as e:
                    note_where(e, f"by the module of agent.encoder={name!r} on a batch of {b} zero observation"
                                  f"{'s' * (b > 1)}: {_as_given(spec, b)}")
                    raise
            if not isinstance(out, torch.Tensor) or out.dim() != 2 or out.shape[0] != b or out.shape[1] == 0:
                shape = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
                raise UserError(f"agent.encoder={name!r}: its module gave {shape} for a batch of {b} observation"
                                f"{'s' * (b > 1)} of {describe(spec)}; it must give [B, features], features >= 1")
            features.add(int(out.shape[1]))
        if len(features) > 1:
            raise UserError(f"agent.encoder={name!r}: its module gave {sorted(features)} features for batches of 1 "
                            "and 2; it must give the same number for any batch")
        self.out_dim = features.pop()

    def forward(self, x: torch.Tensor | dict[str, torch.Tensor]) -> torch.Tensor:
        """Observations [B, ...] (packed rows for a Dict / Tuple, or its entries by key)."""
        if self.packed is not None and not isinstance(x, dict):
            x = unpack(x, self.packed)
        return self.module(x).float()


def _as_given(spec: Spec, b: int) -> str:
    """What a user's encoder module is given, for the note on its own error."""
    if isinstance(spec, PackedSpec):
        entries = ", ".join(f"{f.key!r}: {str(f.spec.dtype).removeprefix('torch.')} {[b, *f.spec.shape]}"
                            for f in spec.fields)
        given = f"a dict of tensors by entry key ({entries})"
    else:
        given = f"a {str(spec.dtype).removeprefix('torch.')} tensor {[b, *spec.shape]}"
    raw = " (uint8 frames as 0..255, not scaled to [0, 1])" if "uint8" in given else ""
    return given + raw


def make_encoder(spec: Spec, kind: str = "auto") -> nn.Module | None:
    """The encoder for observations of `spec`, or None where the MLP takes them as they are
    (a Box that is not an image, or `kind="flatten"` on one)."""
    if is_user_encoder(kind):
        return UserEncoder(spec, kind)
    if kind not in ENCODERS:
        raise UserError(f"agent.encoder={kind!r} is not valid; valid: {', '.join(ENCODERS)}, or "
                        "package.module:callable (your own)")
    if isinstance(spec, PackedSpec):
        return DictEncoder(spec, kind)  # `kind` applies to its image entries
    if kind in ("nature_cnn", "small_cnn"):
        if not is_image(spec, any_bounds=True) and not is_float_frames(spec):
            raise UserError(f"agent.encoder={kind!r} needs image observations (uint8 [H, W], [C, H, W] or [H, W, C], "
                            f"or float [C, H, W] or [H, W, C] of 1, 3 or 4 channels; sides >= 8), got "
                            f"{describe(spec)}; use agent.encoder='auto'")
        return leaf_encoder(spec, kind, float_frames=True)
    if is_flat_vector(spec) or (kind == "flatten" and type(spec) is ArraySpec):
        return None
    return leaf_encoder(spec, kind)


class Encoded(nn.Module):
    """An encoder followed by an MLP head: obs -> head(encoder(obs))."""

    def __init__(self, encoder: nn.Module, head: MLP) -> None:
        super().__init__()
        self.encoder = encoder
        self.head = head

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.encoder(x))


def encoded_mlp(spec: Spec, kind: str, hidden: list[int], out_dim: int, activation: str) -> MLP | Encoded:
    """An MLP on `spec`'s observations, behind their encoder when they need one."""
    encoder = make_encoder(spec, kind)
    if encoder is None:
        return MLP(flat_dim(spec), hidden, out_dim, activation)
    return Encoded(encoder, MLP(encoder_dim(encoder), hidden, out_dim, activation))


