"""Moved to `jaxwear.cli.predict`; this name stays the same module object."""

import importlib
import sys

sys.modules[__name__] = importlib.import_module("jaxwear.cli.predict")
