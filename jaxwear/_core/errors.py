"""Errors that jaxwear reports to users (the CLI turns them into one line and an exit code)."""


class InputError(ValueError):
    """Bad input: a study file, data file, key or value. The CLI exits with code 2.

    The message names the file, the key or line, and what was expected.
    """


class WornThroughError(RuntimeError):
    """The bushing layer was worn through (h_j ≥ L) during a simulation."""
