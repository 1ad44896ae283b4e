"""``python -m freereg_lib register ...``: the ``freereg`` command (:mod:`freereg_lib.cli`)."""
import sys

from .cli import main

sys.exit(main())
