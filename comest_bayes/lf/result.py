"""The result of a count fit: posterior samples, grids and predictions, saved and loaded as
``lf_posterior.npz`` plus ``lf.json``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
import numpy as np
from comest_bayes.errors import InputFileError
from comest_bayes.io.jsonio import dumps, jsonable
from comest_bayes.recover.transfer import PhotometricTransfer
from comest_bayes.io import layout
from comest_bayes.io.rundir import atomic_path

__all__ = ['LFResult']


# --------------------------------------------------------------------------- results


@dataclass
class LFResult:
    """Posterior of a count-model fit, with the predictions needed for plots and reports.

    Attributes
    ----------
    name, kind, mode : str
    spec : dict
        The count-model specification (:meth:`CountSpec.to_dict`).
    names : list of str
        Count parameter names.
    samples : ndarray, shape (S, P)
        Posterior draws of the count parameters (completeness marginalised).
    comp_samples : ndarray, shape (S, D) or None
        Joint mode: the completeness parameters drawn with them.
    grid : ndarray, shape (M,)
        True-magnitude grid.
    phi_bands : ndarray, shape (5, M)
        2.5, 16, 50, 84, 97.5 percentiles of ``phi`` (deg^-2 mag^-1).
    obs_edges : ndarray, shape (K + 1,)
    observed : ndarray, shape (K,)
        Catalog counts per measured-magnitude bin.
    expected_bands : ndarray, shape (5, K)
        Percentiles of the expected counts per bin (the forward model; Poisson noise not included).
    expected_draws : ndarray, shape (S', K)
        Expected counts of (up to 400) posterior draws.
    fbar_median : ndarray, shape (M,)
        Posterior-median footprint-average completeness on the grid.
    area_deg2 : float
    mag_range : (float, float)
    n_objects : int
    diagnostics : dict
    warnings : list of str
    meta : dict
        Catalog, magnitude column, completeness spec, seed, timings.
    transfer : PhotometricTransfer or None
    """

    name: str
    kind: str
    mode: str
    spec: dict
    names: list
    samples: np.ndarray
    comp_samples: np.ndarray | None
    grid: np.ndarray
    phi_bands: np.ndarray
    obs_edges: np.ndarray
    observed: np.ndarray
    expected_bands: np.ndarray
    expected_draws: np.ndarray
    fbar_median: np.ndarray
    area_deg2: float
    mag_range: tuple
    n_objects: int
    diagnostics: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    meta: dict = field(default_factory=dict)
    transfer: PhotometricTransfer | None = None

    def parameter_summary(self) -> dict:
        """``{name: {median, lo68, hi68, lo95, hi95, mean, sd}}`` of the count parameters."""
        out = {}
        for j, nm in enumerate(self.names):
            q = np.percentile(self.samples[:, j], [2.5, 16, 50, 84, 97.5])
            out[nm] = {"median": float(q[2]), "lo68": float(q[1]), "hi68": float(q[3]), "lo95": float(q[0]),
                       "hi95": float(q[4]), "mean": float(np.mean(self.samples[:, j])),
                       "sd": float(np.std(self.samples[:, j]))}
        return out

    def to_json(self) -> dict:
        """The ``lf.json`` / ``summary.json`` entry."""
        return {"name": self.name, "kind": self.kind, "mode": self.mode, "model": self.spec,
                "parameters": self.parameter_summary(), "mag_range": [float(v) for v in self.mag_range],
                "area_deg2": self.area_deg2, "n_objects": self.n_objects, "n_samples": int(len(self.samples)),
                "observed": {"edges": self.obs_edges.tolist(), "counts": self.observed.tolist(),
                             "expected_median": self.expected_bands[2].tolist(),
                             "expected_lo68": self.expected_bands[1].tolist(),
                             "expected_hi68": self.expected_bands[3].tolist()},
                "diagnostics": jsonable(self.diagnostics), "warnings": list(self.warnings),
                "meta": jsonable(self.meta)}

    def save(self, directory) -> Path:
        """Write ``lf_posterior.npz`` and ``lf.json`` into ``directory`` (atomically); returns the npz path."""

        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        arrays = {"samples": self.samples, "names": np.array(self.names),
                  "comp_samples": np.zeros((0, 0)) if self.comp_samples is None else self.comp_samples,
                  "grid": self.grid, "phi_bands": self.phi_bands, "obs_edges": self.obs_edges,
                  "observed": self.observed, "expected_bands": self.expected_bands,
                  "expected_draws": self.expected_draws, "fbar_median": self.fbar_median,
                  "header": np.array(dumps({
                      "name": self.name, "kind": self.kind, "mode": self.mode, "spec": self.spec,
                      "area_deg2": self.area_deg2, "mag_range": list(self.mag_range), "n_objects": self.n_objects,
                      "diagnostics": self.diagnostics, "warnings": self.warnings, "meta": self.meta}))}
        if self.transfer is not None:
            arrays.update(self.transfer.to_arrays())
        npz = d / layout.LF_POSTERIOR
        with atomic_path(npz) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **arrays)
        with atomic_path(d / layout.LF_JSON) as tmp:
            tmp.write_text(dumps(self.to_json(), indent=2))
        return npz

    @classmethod
    def load(cls, path) -> "LFResult":
        """Read a result from ``lf_posterior.npz`` (or the directory holding it)."""
        p = Path(path)
        if p.is_dir():
            p = p / layout.LF_POSTERIOR
        if not p.is_file():
            raise InputFileError(f"luminosity-function result {str(p)!r} does not exist.")
        with np.load(p, allow_pickle=False) as z:
            h = json.loads(str(z["header"]))
            comp = np.array(z["comp_samples"])
            transfer = PhotometricTransfer.from_arrays(z) if "transfer_nodes" in z.files else None
            return cls(name=h["name"], kind=h["kind"], mode=h["mode"], spec=h["spec"],
                       names=[str(n) for n in z["names"]], samples=np.array(z["samples"]),
                       comp_samples=None if comp.size == 0 else comp, grid=np.array(z["grid"]),
                       phi_bands=np.array(z["phi_bands"]), obs_edges=np.array(z["obs_edges"]),
                       observed=np.array(z["observed"]), expected_bands=np.array(z["expected_bands"]),
                       expected_draws=np.array(z["expected_draws"]), fbar_median=np.array(z["fbar_median"]),
                       area_deg2=float(h["area_deg2"]), mag_range=tuple(h["mag_range"]),
                       n_objects=int(h["n_objects"]), diagnostics=h["diagnostics"], warnings=h["warnings"],
                       meta=h["meta"], transfer=transfer)


# --------------------------------------------------------------------------- fitting (numerics orchestration)


PERCENTILES = (2.5, 16.0, 50.0, 84.0, 97.5)
