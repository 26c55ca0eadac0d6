"""Progress bars (tqdm, on stderr) for steps that may take more than a second.

Off by default, so the library stays silent; the command line turns them on unless ``--quiet``
or ``--json`` is given. A bar appears only once its step has run for a second. Bars step per
chunk of points read (LAS/LAZ) or binned (4 M points per kernel call, :mod:`sdp.fields._density`).
"""

from __future__ import annotations

import sys

_enabled = False


def enable(on: bool) -> None:
    """Show (``True``) or hide progress bars from now on."""
    global _enabled
    _enabled = bool(on)


def bar(total: int, desc: str, unit: str = "pt"):
    """A tqdm bar over ``total`` units; a silent one when bars are off."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, unit_scale=True, delay=1.0, leave=False,
                disable=not _enabled, file=sys.stderr, dynamic_ncols=True)
