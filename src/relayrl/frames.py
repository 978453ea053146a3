"""How an observation's shape reads as frames ([H, W], [C, H, W], [H, W, C], stacks of them):
the rule that decides which observations the conv encoders take and how they are laid out."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from relayrl.specs import ArraySpec


def frame_layout(shape: Sequence[int]) -> str | None:
    """How a shape reads as frames: "HW", "CHW", "HWC", or a stack of them along the first side,
    "SCHW" / "SHWC" (Gymnasium's FrameStackObservation over RGB frames), the channels being the
    smaller of the outer sides ([84, 84, 12] is four RGB frames side by side, as Stable-Baselines3
    reads it; [4, 84, 84] four gray ones), unless only the last two sides are equal: [12, 8, 8] is
    twelve square 8x8 frames stacked, not a 12x8 image of 8 channels; None where a side is under 8
    pixels or the rank is another."""
    if len(shape) not in (2, 3, 4):
        return None
    frame = tuple(shape[-3:]) if len(shape) > 2 else tuple(shape)
    square_last = len(frame) == 3 and frame[1] == frame[2] != frame[0]
    layout = "HW" if len(frame) == 2 else "HWC" if frame[2] < frame[0] and not square_last else "CHW"
    sides = frame if len(frame) == 2 else frame[:2] if layout == "HWC" else frame[1:]
    if min(sides) < 8:
        return None
    return "S" + layout if len(shape) == 4 else layout


def image_layout(spec: ArraySpec) -> tuple[int, bool]:
    """(channels, channels last) of an image spec, a stack's frames counting as channels."""
    layout, shape = frame_layout(spec.shape), spec.shape
    assert layout is not None, f"{shape} is not laid out as frames"
    if layout == "HW":
        return 1, False
    channels = shape[-1] if layout.endswith("C") else shape[-3]
    return channels * (shape[0] if layout.startswith("S") else 1), layout.endswith("C")


def image_size(spec: ArraySpec) -> tuple[int, int]:
    """(H, W) of an image-shaped spec."""
    shape = spec.shape
    return (shape[-3], shape[-2]) if image_layout(spec)[1] else (shape[-2], shape[-1])


def frame_layout_before(shape: Sequence[int]) -> str | None:
    """The layout of policy files and checkpoints without a "layout" entry: ranks 2 and 3 only,
    [H, W, C] where the last side was 1, 3 or 4 and the first was not."""
    if len(shape) == 2:
        return "HW" if min(shape) >= 8 else None
    if len(shape) != 3:
        return None
    last = shape[-1] in (1, 3, 4) and shape[0] not in (1, 3, 4)
    return ("HWC" if last else "CHW") if min(shape[:2] if last else shape[1:]) >= 8 else None
