"""The exception types (comest_bayes.errors): each is a ComestError and the matching built-in exception, so
``except ValueError`` (or FileNotFoundError, OSError, RuntimeError) around a call keeps working."""

import pytest

import comest_bayes
from comest_bayes import errors

#: Each error and the built-in exception it must also be.
BUILTIN = {
    "InputError": ValueError,
    "InputFileError": FileNotFoundError,
    "ConfigError": ValueError,
    "DetectionOverflowError": RuntimeError,
    "BackendUnavailableError": RuntimeError,
    "RunDirectoryError": RuntimeError,
    "OutputWriteError": OSError,
}


def test_every_error_is_listed_with_its_builtin():
    assert set(errors.__all__) == {"ComestError", *BUILTIN}
    assert errors.ComestError.__bases__ == (Exception,)


@pytest.mark.parametrize("name", sorted(BUILTIN))
def test_each_error_is_caught_as_comest_error_and_as_its_builtin(name):
    cls = getattr(errors, name)
    for base in (errors.ComestError, BUILTIN[name]):
        with pytest.raises(base, match="what was wrong"):
            raise cls("what was wrong")
    # and by nothing unrelated: a ValueError is no OSError, a RuntimeError no ValueError
    others = {ValueError, OSError, RuntimeError} - {b for b in (ValueError, OSError, RuntimeError)
                                                      if issubclass(BUILTIN[name], b)}
    assert not any(issubclass(cls, o) for o in others), (name, others)


def test_the_package_exports_the_same_classes():
    for name in ("ComestError", "InputError", "ConfigError"):
        assert getattr(comest_bayes, name) is getattr(errors, name)
