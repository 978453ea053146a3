"""What a Table keeps its items in: the Storage protocols, and column storage (preallocated
NumPy arrays in RAM, or memory-mapped files).

`Columns` is a fixed set of named arrays with a leading capacity dimension: NumPy arrays,
because indexing them costs several times less per call than torch indexing on CPU (a step
store keeps the columns that live on a torch device itself); memmap columns are `.npy` files
(with headers) so a table can be reopened from disk without copying.
"""

from __future__ import annotations

import contextlib
import json
import mmap
import platform
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import torch

from relayrl.arrays import to_numpy
from relayrl.errors import UserError

if TYPE_CHECKING:
    from numpy.typing import DTypeLike

    from relayrl.replay.step_storage import StepStorage

# name -> (shape per row, dtype: a NumPy dtype or what np.dtype takes, e.g. np.float32)
Signature = dict[str, tuple[tuple[int, ...], "DTypeLike"]]


class Storage(Protocol):
    """Where a table keeps its items' data, by slot. The table calls `write` when it gives
    items slots and `read` with the slots it samples; its checkpoint holds the storage's.
    The optional methods hold their defaults here; a storage inherits them by subclassing."""

    def write(self, slots: np.ndarray, items: Any) -> None: ...
    def read(self, slots: np.ndarray) -> Any: ...
    def state_dict(self) -> dict[str, Any]: ...
    def load_state_dict(self, state: dict[str, Any]) -> None: ...

    def bind(self, slot_key: np.ndarray) -> None:
        """Take the table's key map (read-only, as its selectors get it); the default needs none."""
        return None

    def check(self, items: Any, n: int) -> None:
        """Raise where `items` (`n` of them, batched) cannot be written: a table calls it before
        it gives them slots, so a refused insert leaves the table as it was. The default takes all."""
        return None

    @property
    def appending(self) -> StepStorage | None:
        """The StepStorage that takes appended steps, for a storage of steps (see step_storage);
        None (the default): the table keeps whole items only."""
        return None

    def stale(self, slots: np.ndarray) -> np.ndarray:
        """Bool mask of the items whose data no longer holds what was written (memmap files
        reopened after the run went on), which a table loading a checkpoint deletes. The
        default: none is."""
        return np.zeros(len(slots), dtype=bool)


class Columns:
    def __init__(self, signature: Signature, leading: tuple[int, ...], path: str | Path | None = None) -> None:
        self.signature = {k: (tuple(s), np.dtype(d)) for k, (s, d) in signature.items()}
        self.leading = tuple(leading)
        self.path = Path(path) if path is not None else None
        self.arrays: dict[str, Any] = {}
        self.reopened = False  # memmap: files of this layout were there already, and are used as they are
        if self.path is not None:
            try:
                self.path.mkdir(parents=True, exist_ok=True)
            except (FileExistsError, NotADirectoryError):
                raise UserError(f"memmap replay storage needs a folder at {self.path}, but a file is in the way; "
                                "move it, or use another run directory") from None
            meta = {"leading": list(self.leading),
                    "signature": {k: [list(s), d.str] for k, (s, d) in self.signature.items()}}
            meta_file = self.path / "columns.json"
            reopen = meta_file.exists() and json.loads(meta_file.read_text()) == meta
            self.reopened = reopen and all((self.path / f"{name}.npy").exists() for name in self.signature)
            for name, (shape, dtype) in self.signature.items():
                file = self.path / f"{name}.npy"
                if reopen and file.exists():  # reopen without copying
                    self.arrays[name] = np.load(file, mmap_mode="r+")
                else:
                    self.arrays[name] = np.lib.format.open_memmap(file, mode="w+", dtype=dtype,
                                                                  shape=self.leading + shape)
            meta_file.write_text(json.dumps(meta))
        else:
            for name, (shape, dtype) in self.signature.items():
                self.arrays[name] = lazy_zeros(self.leading + shape, dtype)

    def nbytes(self) -> int:
        return sum(int(np.prod(self.leading + s)) * d.itemsize for s, d in self.signature.values())

    def used_rows(self, used: int | None) -> tuple[slice, ...]:
        """The index of the first `used` rows along the last leading dimension (None: all)."""
        return (slice(None),) * (len(self.leading) - 1) + (slice(0, used),)

    def state_dict(self, used: int | None = None) -> dict[str, Any]:
        """The arrays' first `used` rows along the last leading dimension (None: all): a
        checkpoint grows with what the storage holds, not with what it can hold."""
        if self.path is not None:
            for a in self.arrays.values():
                a.flush()  # the checkpoint refers to the files, wherever the resume starts from
            return {"memmap": str(self.path.resolve())}
        rows = self.used_rows(used)
        return {"arrays": {k: v[rows].copy() for k, v in self.arrays.items()}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if "memmap" in state:
            # The files are where this run keeps them: the checkpoint's folder, or a copy of it
            # (a copied run directory's own replay/), whose layout matched when it was reopened.
            if self.path is None or (Path(state["memmap"]).resolve() != self.path.resolve() and not self.reopened):
                raise UserError(f"the checkpoint's replay files are in {state['memmap']!r}, but this run keeps its "
                                f"replay in {str(self.path)!r}, which holds none; resume with the replay.path the "
                                "run was started with")
            return  # the files were reopened in __init__
        for k, v in state["arrays"].items():
            self.arrays[k][self.used_rows(v.shape[len(self.leading) - 1])] = to_numpy(v)


# Linux's MAP_NORESERVE where it is 0x4000 (x86, Arm and RISC-V; Python's mmap does not name it)
_NORESERVE = 0x4000 if sys.platform.startswith("linux") and platform.machine() in ("x86_64", "aarch64",
                                                                                   "riscv64") else 0
_LAZY_FROM = 64 * 2**20  # smaller arrays: np.zeros


def lazy_zeros(shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    """np.zeros whose memory is taken as its rows are written, however large: Linux's default
    overcommit refuses one allocation larger than memory and swap (np.zeros' "Unable to allocate
    29.7 GiB") even where a run writes a few of its rows (SAC's 1M-row default replay of
    images, for 1,000 steps). Anonymous pages mapped without a reservation are only counted
    once written; a run that writes more than the machine holds is said at its start
    (`replay_setup.host_memory_note`)."""
    nbytes = int(np.prod(shape)) * dtype.itemsize
    if not _NORESERVE or nbytes < _LAZY_FROM:
        return np.zeros(shape, dtype=dtype)
    try:
        pages = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | _NORESERVE)
    except OSError as e:  # past the address space, or a strict overcommit policy: as NumPy says it
        raise MemoryError(f"Unable to allocate {nbytes / 2**30:.1f} GiB for an array with shape {shape} and data "
                          f"type {dtype} ({e.strerror or e})") from None
    if hasattr(mmap, "MADV_HUGEPAGE"):  # as NumPy asks for its large arrays: fewer TLB misses in random gathers
        with contextlib.suppress(OSError):  # a kernel without transparent huge pages refuses it, as NumPy ignores
            pages.madvise(mmap.MADV_HUGEPAGE)
    return np.frombuffer(pages, dtype=dtype).reshape(shape)


class ItemStorage(Storage):
    """A table's storage for items inserted directly: one row per slot and field."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.columns: Columns | None = None  # built from the first item's structure
        self.single = False  # items are one array rather than a dict of arrays
        self.slot_key: np.ndarray | None = None  # the table's: which slots hold items (-1: none)

    def bind(self, slot_key: np.ndarray) -> None:
        self.slot_key = slot_key

    def _build(self, item: Any) -> None:
        self.single = not isinstance(item, dict)
        fields = {"item": item} if self.single else item
        sig: Signature = {k: (to_numpy(v).shape[1:], to_numpy(v).dtype) for k, v in fields.items()}
        self.columns = Columns(sig, (self.capacity,))

    def check(self, items: Any, n: int) -> None:
        """Items of other fields, of another shape than the table's first (NumPy would broadcast
        a [n, 1] field into its [n, 4] rows) or of a dtype its columns would cast across kinds
        (floats truncated into integers) are refused."""
        if self.columns is None:
            return  # the first insert sets the layout
        if self.single == isinstance(items, dict):
            raise ValueError(f"the table holds {'single arrays' if self.single else 'dicts of arrays'}, this item is "
                             f"{'a dict' if self.single else 'not a dict'}")
        fields = {"item": items} if self.single else items
        if set(fields) != set(self.columns.signature):
            raise ValueError(f"item fields {sorted(fields)} differ from the table's {sorted(self.columns.signature)}")
        for name, value in fields.items():
            shape, dtype = self.columns.signature[name]
            array = to_numpy(value)
            if array.shape != (n, *shape):
                raise ValueError(f"item field {name!r} has shape {array.shape[1:]} per item, the table's is {shape} "
                                 f"(the table's first insert set it)")
            if not np.can_cast(array.dtype, dtype, "same_kind"):
                raise ValueError(f"item field {name!r} is {array.dtype}, which the table's {dtype} column cannot hold")

    def write(self, slots: np.ndarray, items: Any) -> None:
        if self.columns is None:
            self._build(items)
        assert self.columns is not None
        fields = {"item": items} if self.single else items
        for name, value in fields.items():
            self.columns.arrays[name][slots] = to_numpy(value)

    def read(self, slots: np.ndarray) -> Any:
        assert self.columns is not None
        out = {name: torch.from_numpy(np.ascontiguousarray(col[slots])) for name, col in self.columns.arrays.items()}
        return out["item"] if self.single else out

    def state_dict(self) -> dict[str, Any]:
        if self.columns is None:
            return {}
        live = None if self.slot_key is None else np.flatnonzero(self.slot_key >= 0)
        used = None if live is None else int(live[-1]) + 1 if live.size else 0  # slots above hold no item
        return {"single": self.single,
                "signature": {k: (s, d.str) for k, (s, d) in self.columns.signature.items()},
                "columns": self.columns.state_dict(used)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if not state:
            return
        self.single = bool(state["single"])
        sig = {k: (tuple(s), np.dtype(d)) for k, (s, d) in state["signature"].items()}
        self.columns = Columns(sig, (self.capacity,))
        self.columns.load_state_dict(state["columns"])
