"""``python -m diffgns.cli``: the ``diffgns`` command."""
import sys

from diffgns.cli import main

if __name__ == "__main__":  # importing this module (e.g. walking the package) runs nothing
    sys.exit(main())
