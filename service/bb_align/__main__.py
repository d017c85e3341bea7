"""``python -m bb_align``: the same as the ``bb-align`` command."""

from .cli import app

app(prog_name="bb-align")
