"""comest-bayes: completeness and purity of source detection, with Bayesian uncertainties.

The front door (details in ``docs/usage.md``)::

    import comest_bayes as cb

    run = cb.run("image.fits", out="run1", weight="weight.fits")   # every stage; returns a Run
    run.summary("point").m50_model                                 # posterior m50 with intervals
    fit = cb.fit_completeness("outcomes.fits")                     # any pipeline's injection outcomes

Importing the package is cheap: the names below load their modules (and
JAX, GalSim, matplotlib) on first use.
"""

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("comest-bayes")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0+unknown"

#: Public name -> the module that defines it, imported on first access.
_EXPORTS = {
    "run": "api",
    "fit_completeness": "api",
    "Run": "io.run",
    "KindSummary": "io.run",
    "ModelSummary": "io.run",
    "Interval": "io.run",
    "CompletenessFit": "api",
    "CompletenessPosterior": "bayes.posterior",
    "load_config": "config",
    "write_report": "report.html",
    "ComestError": "errors",
    "InputError": "errors",
    "ConfigError": "errors",
}
#: Public names defined under another name in their module.
_RENAMED = {"fit_lf": ("lf.fit", "run_lf")}

__all__ = ["__version__", *_EXPORTS, *_RENAMED]


def __getattr__(name: str):
    if name in _EXPORTS:
        module, attr = _EXPORTS[name], name
    elif name in _RENAMED:
        module, attr = _RENAMED[name]
    else:
        raise AttributeError(f"module 'comest_bayes' has no attribute {name!r}")
    value = getattr(import_module(f".{module}", __name__), attr)
    globals()[name] = value  # later accesses skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
