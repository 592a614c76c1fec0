"""Reading files that may come from anywhere: tensors, arrays and plain values only, never code.

`torch.load(weights_only=True)` and `np.load(allow_pickle=False)` refuse pickled objects; every failure becomes one
`InputFileError` line naming the file and what is wrong (the traceback of the loader is not the user's business).
"""
from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import torch

from avatarlab.runtime.errors import InputFileError


def load_tensors(path: str | Path, what: str = "a checkpoint", map_location="cpu"):
    """torch.load with weights_only=True: tensors, dicts, lists, numbers and strings."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: no such file ({what} expected)")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # pickle.UnpicklingError for code, RuntimeError / EOFError for a broken file
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        if "weights_only" in str(err) or "Unsupported global" in str(err):
            reason = "it holds Python objects other than tensors and plain values (refused: loading could run code)"
        hint = "; delete it to start that step over" if what.endswith("checkpoint") else ""
        raise InputFileError(f"{path}: cannot be read as {what}: {reason}{hint}") from None


def load_arrays(path: str | Path, keys: tuple[str, ...] = (), what: str = "arrays",
                finite: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """np.load of a .npz (or .npy, as key 'array') with allow_pickle=False; every key in `keys` must be present, and
    every number of the keys in `finite` finite (no NaN or infinity)."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: no such file ({what} expected)")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files} if isinstance(data, np.lib.npyio.NpzFile) else None
    except TypeError:  # np.load returned a plain array for a .npy (no context manager)
        arrays = None
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as err:
        reason = "it holds pickled Python objects (refused)" if "pickle" in str(err) else str(err).splitlines()[0]
        raise InputFileError(f"{path}: cannot be read as {what}: {reason}") from None
    if arrays is None:
        try:
            arrays = {"array": np.load(path, allow_pickle=False)}
        except (ValueError, OSError) as err:
            reason = "it holds pickled Python objects (refused)" if "pickle" in str(err) else str(err).splitlines()[0]
            raise InputFileError(f"{path}: cannot be read as {what}: {reason}") from None
    missing = [k for k in keys if k not in arrays]
    if missing:
        raise InputFileError(f"{path}: not {what}: missing {', '.join(missing)}")
    for key in finite:
        values = arrays.get(key)
        if values is not None and values.dtype.kind in "fc" and not np.isfinite(values).all():
            bad = int((~np.isfinite(values)).sum())
            raise InputFileError(f"{path}: not {what}: '{key}' holds {bad} value(s) that are NaN or infinite")
    return arrays
