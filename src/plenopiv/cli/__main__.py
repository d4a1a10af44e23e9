"""``python -m plenopiv.cli``: the ``plenopiv`` command."""

from plenopiv.cli import console

console()
