"""Errors that jaxwear reports to users (the CLI turns them into one line and an exit code)."""

import re


class InputError(ValueError):
    """Bad input: a study file, data file, key, value or argument. The CLI exits with code 2.

    The message names the file, the key or line, or the argument, and what was expected.
    An argument of a library call is marked in the message as `<<name>>`: `str()` gives
    the Python name (`train_until`), and the command line words the same message with its
    option (`--train-until`, `worded`), so that one check serves both.
    """

    def __init__(self, message: str = ""):
        self.template = str(message)
        super().__init__(self.worded({}))

    def worded(self, flags: dict) -> str:
        """The message with each `<<name>>` as `flags[name]` (unknown names as they are)."""
        return re.sub(r"<<(\w+)>>", lambda m: flags.get(m.group(1), m.group(1)),
                      self.template)


class ModelFailure(RuntimeError):
    """The model or a method could not give an answer for valid inputs: a contact solve or
    a sampler that did not converge, an integration out of attempts. Exit 1 from the
    command line, with the message alone (it says what failed and what may avoid it)."""


class WornThroughError(RuntimeError):
    """The bushing layer was worn through (h_j ≥ L) during a simulation."""


class TrialFailed(RuntimeError):
    """A model evaluation at a trial point gave no usable value: rows or a work estimate not
    finite, a contact solve or an integration that did not converge, work beyond the budget.

    Model evaluations may raise it; the least-squares core (`_inference.lsq.solve`) catches it
    around its trials only and counts the trial as a rejected step (the trust region shrinks,
    one progress line names the cause). The message says what failed; the core adds where.
    """


class FitError(RuntimeError):
    """A fit could not start: the model gives no usable value at the start, where there is
    nothing to fall back to. The message names the parameter values and the cause."""


class NoSpaceError(OSError):
    """An output could not be written: the device (or the user's quota) is full. Exit 1
    from the command line, with the message alone: the path and what to do (issue 49: it
    read "internal error (OSError: [Errno 28] No space left on device); please report
    it")."""

    def __init__(self, path, errno_: int):
        super().__init__(errno_, f"{path}: no space left on the device (the disk or the "
                                 f"quota is full); free some space or choose another "
                                 f"output folder, and rerun")
        self.path = str(path)

    def __str__(self) -> str:
        return self.strerror
