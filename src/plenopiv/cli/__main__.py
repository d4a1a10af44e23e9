"""``python -m plenopiv.cli``: the ``plenopiv`` command."""

import sys

from plenopiv.cli import main

sys.exit(main())
