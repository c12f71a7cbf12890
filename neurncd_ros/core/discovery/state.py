"""Discovery's state to a file and back, so a restarted discovery node keeps its novel ids.

The :class:`~.labeller.Discoverer` (segment memory, clusters, the novel ids and the next
one, its random generator) and its :class:`~.fusion.LabelFusion` (voxel votes, aliases,
their evidence) hold numpy arrays, numbers and dicts keyed by ids or id pairs. They are
written as plain containers of torch tensors and Python numbers (``torch.save``), and
read back with the one weights-only reader (:func:`..torchfile.read_torch_file`): a state
file can hold data only, never code. The state records what it was made for (the
embedding's class ids and the discovery configuration); a file made for another
embedding or configuration is refused, naming the difference, rather than mixing the
meanings of ids.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import torch

STATE_VERSION = 1

_NDARRAY, _RNG, _TUPLE, _DICT = "__ndarray__", "__rng__", "__tuple__", "__dict__"


def to_plain(value: Any) -> Any:
    """Numpy arrays as tensors (with their dtype), numpy scalars as Python numbers, a
    numpy Generator as its bit generator's state; containers recursively. Dicts are
    stored as lists of (key, value) pairs so that keys of any plain type survive."""
    if isinstance(value, np.ndarray):
        data = value.astype(np.int64) if value.dtype.kind == "u" and value.itemsize > 1 \
            else np.ascontiguousarray(value)  # torch has no wide unsigned integers
        return {_NDARRAY: torch.from_numpy(data).clone(), "dtype": value.dtype.str}
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.random.Generator):
        return {_RNG: to_plain(value.bit_generator.state)}
    if isinstance(value, dict):
        return {_DICT: [[to_plain(k), to_plain(v)] for k, v in value.items()]}
    if isinstance(value, tuple):
        return {_TUPLE: [to_plain(v) for v in value]}
    if isinstance(value, list):
        return [to_plain(v) for v in value]
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise TypeError(f"discovery state holds a {type(value).__name__}, which it cannot save")


def from_plain(value: Any) -> Any:
    """The inverse of :func:`to_plain`."""
    if isinstance(value, dict):
        if _NDARRAY in value:
            return value[_NDARRAY].numpy().astype(np.dtype(value["dtype"]), copy=True)
        if _RNG in value:
            state = from_plain(value[_RNG])
            gen = np.random.Generator(getattr(np.random, state["bit_generator"])())
            gen.bit_generator.state = state
            return gen
        if _DICT in value:
            return {from_plain(k): from_plain(v) for k, v in value[_DICT]}
        if _TUPLE in value:
            return tuple(from_plain(v) for v in value[_TUPLE])
        raise ValueError(f"unknown entry in a discovery state: {sorted(value)}")
    if isinstance(value, list):
        return [from_plain(v) for v in value]
    return value


def fields_state(obj: Any, skip: tuple[str, ...]) -> dict[str, Any]:
    """An object's attributes but ``skip`` (its configuration, its children saved on
    their own) as plain data."""
    out = {}
    for name, value in vars(obj).items():
        if name in skip:
            continue
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            value = {"__fields__": {f.name: getattr(value, f.name)
                                    for f in dataclasses.fields(value)}}
        out[name] = to_plain(value)
    return out


def restore_fields(obj: Any, state: dict[str, Any], make: dict[str, type]) -> None:
    """Set the attributes :func:`fields_state` saved; ``make`` names the dataclass of
    each attribute saved as one."""
    for name, value in state.items():
        value = from_plain(value)
        if isinstance(value, dict) and "__fields__" in value:
            value = None if name not in make else make[name](**value["__fields__"])
        setattr(obj, name, value)


def fusion_state(fusion: Any) -> dict[str, Any]:
    """A :class:`~.fusion.LabelFusion`'s votes, aliases and their evidence (and its coarse
    map's) as plain data; not the evidence counted in the last frame (``_counted``),
    which each frame starts anew."""
    coarse = fusion._coarse
    return {"fields": fields_state(fusion, ("cfg", "_coarse", "_counted")),
            "coarse": None if coarse is None else fusion_state(coarse)}


def restore_fusion(fusion: Any, state: dict[str, Any]) -> None:
    """Continue a :class:`~.fusion.LabelFusion` from :func:`fusion_state` (a map of the
    same voxel sizes)."""
    restore_fields(fusion, state["fields"], {})
    coarse = fusion._coarse
    if (coarse is None) != (state["coarse"] is None):
        raise ValueError(f"the saved label fusion has {'no' if state['coarse'] is None else 'a'}"
                         " coarse map; label_fusion.coarse_voxel_size differs")
    if coarse is not None:
        restore_fusion(coarse, state["coarse"])


def save_state(path: str | Path, state: dict[str, Any]) -> None:
    """Write atomically: a node killed mid-save leaves the previous file."""
    from ..torchfile import written_atomically

    with written_atomically(path) as tmp:
        torch.save({"version": STATE_VERSION, **state}, str(tmp))


def load_state(path: str | Path) -> dict[str, Any]:
    """A state :func:`save_state` wrote (weights-only read; a bad file is one clear error)."""
    from ..torchfile import read_torch_file

    state = read_torch_file(path, "cpu", "discovery state")
    if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
        raise ValueError(f"{path} is not a discovery state of version {STATE_VERSION}")
    return state
