"""The one way this package reads a torch file: weights only, and every failure a
clear error naming the file.

Backbone checkpoints (ours and ESANet's) and saved maps are all read here. ``torch.load``
with ``weights_only=True`` refuses anything that would import and call code; a file that
is truncated, random bytes, or not a torch file at all raises :class:`TorchFileError` (a
ValueError: the nodes exit 2 and the tools 1 with its one line) instead of torch's own
traceback.
"""

from __future__ import annotations

import contextlib
import os
import pickle
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch


class TorchFileError(ValueError):
    """A torch file cannot be read: unsafe, truncated, or not a torch file."""


# Numpy scalars/dtypes (e.g. a best mIoU stored in a checkpoint) rebuild plain data
# without running code; allowed under both the numpy 1 and numpy 2 module names.
_np_scalar = (getattr(np, "_core", None) or np.core).multiarray.scalar
SAFE_GLOBALS: list[Any] = [np.dtype, _np_scalar, (_np_scalar, "numpy.core.multiarray.scalar"),
                           (_np_scalar, "numpy._core.multiarray.scalar")]
SAFE_GLOBALS += [t for t in vars(getattr(np, "dtypes", object)).values()
                 if isinstance(t, type) and issubclass(t, np.dtype)]


def _unpickling_reason(err: Exception) -> str:
    """The informative line of torch's weights_only refusal (which global it blocked)."""
    skip = ("Weights only load failed", "Check the documentation", "Please file an issue")
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    useful = [ln for ln in lines if not ln.startswith(skip)]
    return (useful[0] if useful else type(err).__name__).replace("WeightsUnpickler error: ", "")


def read_torch_file(path: str | Path, device: str = "cpu", what: str = "checkpoint") -> Any:
    """``torch.load(path, weights_only=True)``; ``what`` names the file in the errors
    ("checkpoint", "map")."""
    try:
        with torch.serialization.safe_globals(SAFE_GLOBALS):
            return torch.load(str(path), map_location=device, weights_only=True)
    except pickle.UnpicklingError as e:
        reason = _unpickling_reason(e)
        if "GLOBAL" in reason:
            raise TorchFileError(
                f"refusing {what} {path}: unpickling it would import and call code "
                f"outside plain tensors/containers ({reason}); only weights-only "
                f"{what}s are accepted") from None
        raise TorchFileError(f"cannot read {what} {path}: not a weights-only torch "
                             f"file ({reason})") from None
    except (RuntimeError, EOFError, OSError, ValueError) as e:
        detail = str(e).splitlines()[0] if str(e) else "file is empty or truncated"
        raise TorchFileError(f"cannot read {what} {path}: {type(e).__name__}: "
                             f"{detail}") from None
    except Exception as e:  # noqa: BLE001 - the unpickler's own failures on other bytes
        # Bytes that are not a torch file reach the weights-only unpickler as opcodes,
        # where they fail as KeyError, IndexError, TypeError ... (a text file: KeyError
        # 101, the byte 'e'): none says "not a torch file", and it is what they mean.
        raise TorchFileError(f"cannot read {what} {path}: not a torch file (its bytes "
                             f"fail to unpickle: {type(e).__name__} {e})") from None


def check_save_path(path: str | Path, param: str) -> None:
    """At start, that a file to save to (``param``, e.g. mapper_node.map_path) can be one:
    not a folder, its folder creatable. A run that learnt for minutes must not end in a
    traceback at its first save."""
    p = Path(path)
    if p.is_dir():
        raise TorchFileError(f"{param} {p} is a folder: give a file path")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise TorchFileError(f"{param} {p}: cannot create its folder ({err})") from None


@contextlib.contextmanager
def written_atomically(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; moved onto ``path`` once the block
    ends without error, removed otherwise: a process killed or failing mid-save leaves
    the previous file and nothing beside it (the map and the discovery state)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
