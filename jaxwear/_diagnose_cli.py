"""Moved to `jaxwear.cli.diagnose`; this name stays the same module object (for
`jaxwear.write_diagnosis` and scripts that import `write_outputs` from here)."""

import importlib
import sys

sys.modules[__name__] = importlib.import_module("jaxwear.cli.diagnose")
