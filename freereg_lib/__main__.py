"""``python -m freereg_lib register ...``: the ``freereg`` command (:mod:`freereg_lib.commands.cli`)."""
import sys

from freereg_lib.commands.cli import main

sys.exit(main())
