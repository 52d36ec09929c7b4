"""Exception types of comest-bayes.

Every error a user can cause by their input subclasses :class:`ComestError`
*and* the matching built-in exception, so ``except ValueError`` keeps working.
Messages say what was wrong, what was received and how to fix it.  The
command-line interface prints these without a traceback (``--debug`` shows it).
"""

from __future__ import annotations

__all__ = [
    "ComestError",
    "InputError",
    "InputFileError",
    "ConfigError",
    "DetectionOverflowError",
    "BackendUnavailableError",
    "RunDirectoryError",
    "OutputWriteError",
]


class ComestError(Exception):
    """Base class of all errors raised deliberately by comest-bayes."""


class InputError(ComestError, ValueError):
    """An input image, map or parameter is unusable as given."""


class InputFileError(ComestError, FileNotFoundError):
    """An input file does not exist or cannot be read."""


class ConfigError(ComestError, ValueError):
    """A configuration file or override is invalid."""


class DetectionOverflowError(ComestError, RuntimeError):
    """SEP ran out of its pixel stack or deblending sub-object buffer."""


class BackendUnavailableError(ComestError, RuntimeError):
    """An optional detection backend (e.g. the SExtractor binary) is missing."""


class RunDirectoryError(ComestError, RuntimeError):
    """The output directory holds a different run, or cannot be written."""


class OutputWriteError(ComestError, OSError):
    """The operating system refused to write an output file (disk full, read-only, quota)."""
