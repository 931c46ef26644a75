"""``python -m diffgns.cli``: the ``diffgns`` command."""
import sys

from diffgns.cli import main

sys.exit(main())
