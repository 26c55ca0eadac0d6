"""``python -m sdp``: the ``sdp`` program, as ``python -m sdp.cli`` and the console script."""

from .cli._main import run

run()
