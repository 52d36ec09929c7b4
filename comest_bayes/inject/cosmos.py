"""Real COSMOS galaxies: a validated GalSim RealGalaxyCatalog directory (:func:`load_cosmos`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
import galsim
import numpy as np
from astropy.io import fits
from comest_bayes.config import InjectionConfig
from comest_bayes.errors import InputError

__all__ = ['CosmosSample', 'load_cosmos']

# Columns of a GalSim RealGalaxyCatalog naming files that must exist in its directory.
_COSMOS_FILE_COLUMNS = ("GAL_FILENAME", "PSF_FILENAME", "NOISE_FILENAME")


# --------------------------------------------------------------------------- COSMOS


@dataclass
class CosmosSample:
    """A validated GalSim RealGalaxyCatalog (see :func:`load_cosmos`).

    Picklable: the open catalog and the galaxies built from it are dropped
    when pickled and rebuilt on first use in the receiving process.

    Attributes
    ----------
    directory : str
        Directory holding the catalog and its image files.
    file_name : str
        Catalog file name inside ``directory``.
    n : int
        Number of galaxies.
    probabilities : ndarray, shape (n,)
        Selection probability of each galaxy (normalised ``WEIGHT`` column, or uniform).
    mag : ndarray, shape (n,)
        Catalog F814W magnitudes (for reference; injected magnitudes are drawn).
    """

    directory: str
    file_name: str
    n: int
    probabilities: np.ndarray = field(repr=False)
    mag: np.ndarray = field(repr=False)
    _catalog: object = field(default=None, repr=False, compare=False)
    _galaxies: dict = field(default_factory=dict, repr=False, compare=False)

    def catalog(self):
        """The :class:`galsim.RealGalaxyCatalog` (opened on first use)."""
        if self._catalog is None:
            self._catalog = galsim.RealGalaxyCatalog(self.file_name, dir=self.directory)
        return self._catalog

    def galaxy(self, index: int):
        """The :class:`galsim.RealGalaxy` of row ``index`` (built once, then cached)."""
        index = int(index)
        if not 0 <= index < self.n:
            raise InputError(f"COSMOS index {index} is outside the catalog's 0..{self.n - 1}.")
        gal = self._galaxies.get(index)
        if gal is None:
            try:
                # The deviate only feeds noise padding, which is off (noise_pad_size=0); fixing it
                # keeps GalSim from seeding one from the clock.
                gal = galsim.RealGalaxy(self.catalog(), index=index, rng=galsim.BaseDeviate(index + 1))
            except OSError as exc:
                raise InputError(f"cannot read COSMOS galaxy {index} from {self.directory!r}: {exc}.") from None
            self._galaxies[index] = gal
        return gal

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_catalog"] = None
        state["_galaxies"] = {}
        return state


def load_cosmos(config: InjectionConfig | None = None, *, directory=None, file_name=None) -> CosmosSample:
    """Open and validate a GalSim RealGalaxyCatalog directory.

    Every galaxy, PSF and noise file named by the catalog must exist in the
    directory; a missing one is reported by name (the GalSim example catalog
    ships without ``real_galaxy_images.fits``, for instance).  One galaxy is
    built as a final check.

    Parameters
    ----------
    config : InjectionConfig, optional
        Supplies ``cosmos_dir`` and ``cosmos_file``.
    directory, file_name : str, optional
        Override the config's values.

    Returns
    -------
    CosmosSample

    Raises
    ------
    InputError
        Directory not set or missing, catalog unreadable or missing columns, or
        image files missing.
    """
    directory = directory if directory is not None else (config.cosmos_dir if config is not None else "")
    file_name = file_name if file_name is not None else (config.cosmos_file if config is not None
                                                         else InjectionConfig().cosmos_file)
    if not directory:
        raise InputError("kind 'cosmos' needs injection.cosmos_dir: the directory of a GalSim "
                         "RealGalaxyCatalog (catalog FITS file plus its galaxy and PSF image files).")
    dpath = Path(directory)
    if not dpath.is_dir():
        raise InputError(f"injection.cosmos_dir = {str(directory)!r} is not a directory; point it to a GalSim "
                         f"RealGalaxyCatalog directory.")
    cpath = dpath / file_name
    if not cpath.is_file():
        present = sorted(p.name for p in dpath.glob("*.fits"))
        raise InputError(f"the COSMOS catalog file {file_name!r} is not in {str(directory)!r} (FITS files there: "
                         f"{present}); set injection.cosmos_file to the catalog's name.")
    try:
        with fits.open(cpath) as hdul:
            table = hdul[1].data
            names = [c.upper() for c in table.columns.names]
            columns = {c.upper(): np.asarray(table[c]) for c in table.columns.names}
    except (OSError, IndexError, AttributeError) as exc:
        raise InputError(f"cannot read the COSMOS catalog {str(cpath)!r} as a FITS table: {exc}.") from None
    required = ("GAL_FILENAME", "PSF_FILENAME", "GAL_HDU", "PSF_HDU", "PIXEL_SCALE")
    missing_cols = [c for c in required if c not in names]
    if missing_cols:
        raise InputError(f"{str(cpath)!r} is not a GalSim RealGalaxyCatalog: columns {missing_cols} are missing.")
    needed = sorted({str(f).strip() for col in _COSMOS_FILE_COLUMNS if col in columns for f in columns[col]})
    absent = [f for f in needed if not (dpath / f).is_file()]
    if absent:
        raise InputError(f"the COSMOS catalog {file_name!r} in {str(directory)!r} needs image file(s) that are "
                         f"missing: {', '.join(absent)}. Download the complete sample (e.g. "
                         f"galsim_download_cosmos) and point injection.cosmos_dir to it, with injection.cosmos_file "
                         f"set to its catalog's name (e.g. real_galaxy_catalog_25.2.fits), or give a complete one.")
    n = len(columns["GAL_FILENAME"])
    if n == 0:
        raise InputError(f"the COSMOS catalog {str(cpath)!r} has no rows.")
    weight = columns.get("WEIGHT")
    if weight is not None and np.all(np.isfinite(weight)) and np.all(weight >= 0) and weight.sum() > 0:
        prob = np.asarray(weight, dtype=float) / float(np.sum(weight))
    else:
        prob = np.full(n, 1.0 / n)
    mag = np.asarray(columns["MAG"], dtype=float) if "MAG" in columns else np.full(n, np.nan)
    sample = CosmosSample(directory=str(dpath), file_name=str(file_name), n=n, probabilities=prob, mag=mag)
    sample.galaxy(0)
    return sample
