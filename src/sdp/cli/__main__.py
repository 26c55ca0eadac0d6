"""``python -m sdp.cli``: the ``sdp`` program."""

from ._main import run

run()
