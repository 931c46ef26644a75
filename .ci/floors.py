"""Print a pip constraints file pinning every dependency of diffgns to its floor.

    python .ci/floors.py [extra ...] > constraints.txt

Reads pyproject.toml: each ``name>=X`` of the core dependencies (and of the extras named on
the command line) becomes ``name==X``; environment markers are kept. Used by ``make test-min``.
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11
    import tomli as tomllib

project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
project = project["project"]
reqs = list(project["dependencies"])
for extra in sys.argv[1:]:
    reqs += project["optional-dependencies"][extra]
pins = {}
for req in reqs:
    spec, _, marker = req.partition(";")
    m = re.fullmatch(r"\s*([A-Za-z0-9_.\-]+)(\[[^\]]*\])?\s*(>=|==)\s*([^,\s]+)\s*", spec)
    if m is None:
        continue  # no floor (e.g. the self-reference diffgns[cfd,symbolic])
    name, version = m.group(1).lower(), m.group(4)
    pins[name] = f"{name}=={version}" + (f"; {marker.strip()}" if marker else "")
print("\n".join(pins[n] for n in sorted(pins)))
