"""moma's exception classes (raised by the Rust extension ``moma._moma``).

``MomaError`` is the base of every exception moma raises. Each subclass also derives from
the builtin exception of the same meaning, so ``except ValueError`` / ``except OSError`` work.
"""


class MomaError(Exception):
    """Base class of every error raised by moma."""


class InvalidInputError(MomaError, ValueError):
    """A bad array (wrong shape, dtype, NaN in a prediction, size mismatch) or parameter value,
    or an input the maths cannot use (too few valid samples, degenerate fit)."""


class MomaFileError(MomaError, OSError):
    """A file could not be read or written, or its content is invalid (the message names the file)."""


class BackendError(MomaError, RuntimeError):
    """The depth-model backend is unavailable in this build or failed while running."""
