"""Text point clouds (XYZ, TXT, CSV, PTS), read with NumPy: whitespace- or comma-separated
columns x y z then any others, with or without a header line naming them. sdp writes no text."""

from __future__ import annotations

import warnings

import numpy as np

from ._cloud import CloudFileError, EmptyCloudError

__all__ = ["read_text"]


def read_text(path):
    """``(xyz, fields, None)`` of a text file: columns after the third are fields, named by the
    header line if there is one, else ``column3``, ``column4``, …"""
    with open(path, encoding="utf-8", errors="replace") as fh:
        sample = fh.read(4096)
    if not sample.strip():
        raise EmptyCloudError(f"{path}: the file is empty: no point to read")
    delimiter = "," if "," in sample else None
    first = sample.splitlines()[0] if sample else ""
    skip = 0 if _is_numeric_row(first, delimiter) else 1
    with warnings.catch_warnings():  # a header without rows: said below, not as a warning
        warnings.simplefilter("ignore", UserWarning)
        arr = np.loadtxt(path, delimiter=delimiter, skiprows=skip, ndmin=2)
    if arr.size == 0:
        raise EmptyCloudError(f"{path}: holds a header but no point")
    if arr.shape[1] < 3:
        raise CloudFileError(f"{path}: expected at least 3 columns (x y z), found {arr.shape[1]}")
    names = [n.strip().lower() for n in first.replace(",", " ").split()] if skip else []
    fields = {(names[i] if i < len(names) else f"column{i}"): arr[:, i] for i in range(3, arr.shape[1])}
    return arr[:, :3], fields, None


def _is_numeric_row(line: str, delimiter) -> bool:
    try:
        [float(x) for x in line.split(delimiter) if x.strip()]
        return bool(line.strip())
    except ValueError:
        return False
