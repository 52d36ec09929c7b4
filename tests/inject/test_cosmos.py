"""Loading the COSMOS galaxy sample (comest_bayes.inject.cosmos): clear errors, and a real sample that loads and pickles."""

import pickle

import numpy as np
import pytest
from astropy.io import fits

from comest_bayes.config import InjectionConfig
from comest_bayes.errors import InputError
from comest_bayes.inject.profiles import source_profile
from comest_bayes.inject.population import draw_parameters
from comest_bayes.inject.cosmos import load_cosmos


# --------------------------------------------------------------------------- COSMOS


def write_fake_cosmos(directory, gal_file="gals.fits", psf_file="psfs.fits"):
    cols = fits.ColDefs([
        fits.Column(name="IDENT", format="J", array=[1, 2]),
        fits.Column(name="GAL_FILENAME", format="20A", array=[gal_file, gal_file]),
        fits.Column(name="PSF_FILENAME", format="20A", array=[psf_file, psf_file]),
        fits.Column(name="GAL_HDU", format="J", array=[0, 1]),
        fits.Column(name="PSF_HDU", format="J", array=[0, 1]),
        fits.Column(name="PIXEL_SCALE", format="D", array=[0.03, 0.03]),
    ])
    fits.BinTableHDU.from_columns(cols).writeto(directory / "cat.fits")


def test_cosmos_missing_image_file_is_named(tmp_path):
    write_fake_cosmos(tmp_path)
    (tmp_path / "psfs.fits").write_bytes(b"")
    with pytest.raises(InputError, match=r"missing: gals\.fits"):
        load_cosmos(directory=str(tmp_path), file_name="cat.fits")


def test_cosmos_configuration_errors(tmp_path):
    with pytest.raises(InputError, match="cosmos_dir"):
        load_cosmos(InjectionConfig())
    with pytest.raises(InputError, match="not a directory"):
        load_cosmos(directory=str(tmp_path / "absent"))
    with pytest.raises(InputError, match="is not in"):
        load_cosmos(directory=str(tmp_path), file_name="cat.fits")


def test_galsim_example_without_images_gives_a_clear_error(shared_data):
    cfg = InjectionConfig(cosmos_dir=str(shared_data / "cosmos" / "galsim_23.5_example"),
                          cosmos_file="real_galaxy_catalog_23.5_example.fits")
    with pytest.raises(InputError, match=r"real_galaxy_images\.fits"):
        load_cosmos(cfg)


def test_cosmos_sample_loads_and_pickles(shared_data):
    cfg = InjectionConfig(cosmos_dir=str(shared_data / "cosmos" / "btk_26_extension"))
    sample = load_cosmos(cfg)
    assert sample.n == 100
    assert sample.probabilities.sum() == pytest.approx(1.0)
    again = pickle.loads(pickle.dumps(sample))
    assert again.galaxy(5).flux == pytest.approx(sample.galaxy(5).flux)
    sp = source_profile("cosmos", flux=42.0, pa_deg=30.0, cosmos_index=5, cosmos=sample)
    assert sp.profile.flux == pytest.approx(42.0)
    with pytest.raises(InputError, match="outside"):
        sample.galaxy(100)
    p = draw_parameters("cosmos", 300, config=cfg, mag_range=(22, 24), rng=np.random.default_rng(0),
                        pixel_scale=0.2, cosmos=sample)
    assert p["cosmos_index"].min() >= 0 and p["cosmos_index"].max() < 100
    assert len(np.unique(p["cosmos_index"])) > 50  # 300 draws from 100 galaxies
