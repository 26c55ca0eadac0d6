"""Text point clouds (XYZ, TXT, CSV, PTS), read with NumPy: comma-, semicolon- or
whitespace-separated columns, with or without a header line naming them (CloudCompare's
``//X,Y,Z,…`` too), a Leica PTS file's leading point count, ``#`` comment lines, and a UTF-8
byte-order mark. Columns named x, y and z by the header are the coordinates wherever they stand;
without such names, the first three. sdp writes no text."""

from __future__ import annotations

import warnings

import numpy as np

from ._cloud import CloudFileError, EmptyCloudError

__all__ = ["read_text"]


def read_text(path):
    """``(xyz, fields, None)`` of a text file: the columns the header names x, y, z (else the first
    three) are the coordinates, the others fields named by the header if there is one, else
    ``column3``, ``column4``, …"""
    # utf-8-sig: a byte-order mark (Excel's "CSV UTF-8") is skipped, not read as part of the
    # first line, where it made the first point a header, or the first column's name "\ufeffid"
    with open(path, encoding="utf-8-sig", errors="replace") as fh:
        sample = fh.read(65536)
    rows = [(i, ln.strip()) for i, ln in enumerate(sample.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows:
        raise EmptyCloudError(f"{path}: the file is empty: no point to read")
    data = [ln for _, ln in rows if _values(ln) is not None]
    delimiter = next((d for d in (",", ";") if data and d in data[0]), None)
    head, names = 0, []
    first = rows[0][1]
    values = _values(first)
    if values is None:  # a header naming the columns
        head, names = rows[0][0] + 1, [n.strip().lstrip("/").strip().lower() for n in first.replace(";", ",")
                                       .replace(",", " ").split()]
    elif len(values) == 1 and len(rows) > 1 and len(_values(rows[1][1]) or ()) >= 3:
        head = rows[0][0] + 1  # a PTS file's point count
    with warnings.catch_warnings():  # a header without rows: said below, not as a warning
        warnings.simplefilter("ignore", UserWarning)
        try:
            arr = np.loadtxt(path, delimiter=delimiter, skiprows=head, ndmin=2, comments="#", encoding="utf-8-sig")
        except ValueError as exc:
            # NumPy's own advice (its `usecols`) is not an sdp option: the cause alone
            raise CloudFileError(f"{path}: not a table of numbers ({str(exc).split('; use `usecols`')[0]})") from None
    if arr.size == 0:
        raise EmptyCloudError(f"{path}: holds a header but no point")
    if arr.shape[1] < 3:
        raise CloudFileError(f"{path}: expected at least 3 columns (x y z), found {arr.shape[1]}")
    if not names and str(path).lower().endswith(".pts") and arr.shape[1] in (4, 7):
        names = ["x", "y", "z", "intensity", "red", "green", "blue"]  # Leica's PTS: x y z i [r g b]
    names = names[:arr.shape[1]] + [f"column{i}" for i in range(len(names), arr.shape[1])]
    axes = [names.index(a) for a in "xyz"] if {"x", "y", "z"} <= set(names) else [0, 1, 2]
    fields = {names[i]: arr[:, i] for i in range(arr.shape[1]) if i not in axes}
    return arr[:, axes], fields, None


def _values(line: str) -> list[float] | None:
    """The numbers of a row (any of the separators), None if it holds something else."""
    try:
        return [float(x) for x in line.replace(";", ",").replace(",", " ").split()]
    except ValueError:
        return None
