"""Moved to `jaxwear.cli.calibrate`; this name stays the same module object (so that
`import jaxwear._calibrate_cli` and monkeypatching its attributes keep working)."""

import importlib
import sys

sys.modules[__name__] = importlib.import_module("jaxwear.cli.calibrate")
