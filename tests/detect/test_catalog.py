"""The one detection-catalog schema (comest_bayes.detect.catalog): columns, order, dtypes, units, the empty
catalog, magnitudes from fluxes, sky coordinates and the image's units."""

import math

import astropy.units as u
import numpy as np
import pytest
from astropy.wcs import WCS

from comest_bayes.detect.catalog import (DETECTION_COLUMNS, FLAG_APER_TRUNC, FLAG_BLENDED, FLAG_DEBLEND_OVERFLOW,
                                         FLAG_EDGE, FLAG_MASKED, FLAG_SATURATED, derived_columns, fits_unit,
                                         flux_to_mag, make_catalog, set_image_units)

#: The columns every consumer relies on (matching, ratios, the completeness model, the report).
REQUIRED = ("id", "x", "y", "xwin", "ywin", "ra", "dec", "a", "b", "theta", "npix", "flux_auto", "fluxerr_auto",
            "mag_auto", "magerr_auto", "snr_auto", "flux_aper", "mag_aper", "flux_radius", "noise", "flags")


def _columns(n: int, naper: int = 2) -> dict:
    cols = {}
    for name, (dtype, _, _) in DETECTION_COLUMNS.items():
        shape = (n, naper) if name.endswith("_aper") else (n,)
        cols[name] = np.arange(int(np.prod(shape)), dtype=float).reshape(shape) + 1.0
    return cols


def test_required_columns_and_their_types():
    assert set(REQUIRED) <= set(DETECTION_COLUMNS)
    for name in ("id", "npix", "flags"):
        assert DETECTION_COLUMNS[name][0] == "i8", name
    for name in set(DETECTION_COLUMNS) - {"id", "npix", "flags"}:
        assert DETECTION_COLUMNS[name][0] == "f8", name
    assert DETECTION_COLUMNS["x"][1] == "pix" and DETECTION_COLUMNS["ra"][1] == "deg"
    assert DETECTION_COLUMNS["mag_auto"][1] == "mag" and DETECTION_COLUMNS["theta"][1] == "rad"
    assert all(desc for _, _, desc in DETECTION_COLUMNS.values())


def test_flags_are_distinct_sextractor_bits():
    bits = [FLAG_MASKED, FLAG_BLENDED, FLAG_SATURATED, FLAG_EDGE, FLAG_APER_TRUNC, FLAG_DEBLEND_OVERFLOW]
    assert bits == [1, 2, 4, 8, 16, 64]  # SExtractor's FLAGS meaning of each bit


def test_make_catalog_keeps_the_schema_order_dtypes_units_and_meta():
    cols = _columns(3, naper=2)
    cols["id"] = [1.0, 2.0, 3.0]  # floats in, i8 out
    cat = make_catalog(dict(reversed(list(cols.items()))), naper=2, meta={"ZP": 25.0})
    assert cat.colnames == list(DETECTION_COLUMNS)
    assert len(cat) == 3 and cat.meta == {"ZP": 25.0}
    for name, (dtype, unit, desc) in DETECTION_COLUMNS.items():
        assert cat[name].dtype == np.dtype(dtype), name
        assert (cat[name].unit is None) == (unit is None) and cat[name].description == desc, name
    assert cat["flux_aper"].shape == (3, 2) and cat["mag_aper"].shape == (3, 2)
    assert list(cat["id"]) == [1, 2, 3]
    assert cat["x"].unit == u.pix


def test_the_empty_catalog_has_every_column():
    cat = make_catalog(_columns(0, naper=3), naper=3)
    assert len(cat) == 0 and cat.colnames == list(DETECTION_COLUMNS)
    assert cat["flux_aper"].shape == (0, 3) and cat["flags"].dtype == np.int64


def test_a_missing_column_is_named():
    cols = _columns(2)
    del cols["snr_auto"], cols["flags"]
    with pytest.raises(KeyError, match=r"\['flags', 'snr_auto'\]"):
        make_catalog(cols, naper=2)


def test_magnitudes_from_fluxes_and_nan_for_non_positive_flux():
    mag, err = flux_to_mag([100.0, 1.0, 0.0, -5.0], [10.0, 0.5, 1.0, 1.0], 25.0)
    assert mag[0] == pytest.approx(20.0) and mag[1] == pytest.approx(25.0)
    assert err[0] == pytest.approx(2.5 / math.log(10) * 0.1) and err[1] == pytest.approx(1.0857362 * 0.5)
    assert np.isnan(mag[2:]).all() and np.isnan(err[2:]).all()


def test_derived_columns_snr_and_sky_positions():
    d = derived_columns([100.0, 50.0], [10.0, 0.0], np.array([[10.0], [20.0]]), np.array([[1.0], [2.0]]),
                        [10.0, 20.0], [30.0, 40.0], zeropoint=25.0)
    assert d["snr_auto"][0] == pytest.approx(10.0) and np.isnan(d["snr_auto"][1])  # zero error: no SNR
    assert d["mag_aper"][:, 0] == pytest.approx([25.0 - 2.5, 25.0 - 2.5 * math.log10(20.0)])
    assert np.isnan(d["ra"]).all() and np.isnan(d["dec"]).all()  # no WCS
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval, w.wcs.crpix, w.wcs.cdelt = [150.0, 2.0], [11.0, 31.0], [-0.2 / 3600, 0.2 / 3600]
    d = derived_columns([1.0, 1.0], [1.0, 1.0], np.ones((2, 1)), np.ones((2, 1)), [10.0, 20.0], [30.0, 40.0],
                        zeropoint=25.0, wcs=w)
    # pixel (10, 30), 0-based, is CRPIX (11, 31), 1-based: the reference point itself
    assert d["ra"][0] == pytest.approx(150.0) and d["dec"][0] == pytest.approx(2.0)
    assert d["ra"][1] < 150.0 and d["dec"][1] > 2.0  # +x is west (RA decreases), +y north


@pytest.mark.parametrize("bunit, expected", [("MJy/sr", u.MJy / u.sr), ("ADU", u.adu), ("COUNTS/S", u.count / u.s),
                                             ("electrons", None), ("nanomaggy", None), ("", None), (None, None)])
def test_fits_unit(bunit, expected):
    assert fits_unit(bunit) == expected


def test_image_unit_columns_get_the_bunit_and_others_do_not():
    cat = make_catalog(_columns(2), naper=2)
    cat["det_flux_auto"] = [1.0, 2.0]
    set_image_units(cat, "MJy/sr")
    assert cat["flux_auto"].unit == u.MJy / u.sr and cat["det_flux_auto"].unit == u.MJy / u.sr
    assert cat["x"].unit == u.pix and cat["mag_auto"].unit == u.mag
    assert cat.meta["IMGUNIT"] == "MJy/sr"
    other = set_image_units(make_catalog(_columns(1), naper=2), " electrons ")
    assert other["flux_auto"].unit is None and other.meta["IMGUNIT"] == "electrons"
