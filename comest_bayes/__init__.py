"""comest-bayes: completeness and purity of source detection, with Bayesian uncertainties."""

from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("comest-bayes")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0+unknown"
