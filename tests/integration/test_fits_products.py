"""The FITS products of a run read back with their units, BUNIT, EXTNAMEs and a 3-D WCS on the map cubes."""

import warnings

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS, Sip

from comest_bayes.detect.catalog import fits_unit, set_image_units
from comest_bayes.config import load_config
from comest_bayes.sim.demo import MASK_GAP, make_demo_tile, write_demo_tile
from comest_bayes.pipeline.stages import ComputeOptions, ImageOptions, run_pipeline
from comest_bayes.ratios.summary import map_cube_header


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A 300x300 demo tile (BUNIT 'ADU') run with a spatial model, so every kind of product is written."""
    root = tmp_path_factory.mktemp("products")
    paths = write_demo_tile(make_demo_tile(seed=2, size=300), root / "in")
    assert fits.getheader(paths["image"])["BUNIT"] == "ADU"
    config = load_config(overrides=["injection.nsims=2", "fit.model=logistic_depth", "fit.purity_model=none"],
                         seed=3)
    options = ImageOptions(path=str(paths["image"]), weight=str(paths["weight"]), mask=str(paths["mask"]),
                           mask_bits=MASK_GAP)
    run_pipeline(options, config, root / "run", log=lambda s: None, compute=ComputeOptions(executor="serial"),
                 fwhm_fallback=(0.9 / 0.26, "the demo's seeing"))
    return root / "run"


def test_images_in_the_image_unit_carry_its_bunit_and_the_others_do_not(run_dir):
    for name in ("sfi.fits", "bnb.fits", "background.fits", "rms.fits", "noise.fits"):
        assert fits.getheader(run_dir / name).get("BUNIT") == "ADU", name
    for name in ("segmentation.fits", "mask.fits"):  # object ids and flags have no unit
        assert "BUNIT" not in fits.getheader(run_dir / name), name
    with fits.open(run_dir / "maps" / "point_m50.fits") as hdul:
        assert hdul["M50"].header["BUNIT"] == "mag" and hdul["M50_SD"].header["BUNIT"] == "mag"


def test_every_table_hdu_of_every_product_has_an_extname(run_dir):
    tables = 0
    for path in sorted(run_dir.rglob("*.fits")):
        with fits.open(path) as hdul:
            for hdu in hdul[1:]:
                if isinstance(hdu, fits.BinTableHDU):
                    tables += 1
                    assert hdu.header.get("EXTNAME"), f"{path.relative_to(run_dir)} HDU {hdul.index(hdu)}"
    assert tables >= 15  # detection, baseline, 2 kinds x 5 catalogs, the maps' plane tables, realizations
    with fits.open(run_dir / "catalogs" / "point_matched.fits") as hdul:
        assert hdul[1].name == "POINT_MATCHED"
    with fits.open(run_dir / "detection.fits") as hdul:
        assert hdul[1].name == "DETECTIONS"


def test_merged_catalogs_carry_the_column_units_and_read_without_warnings(run_dir):
    expected = {"x": "pix", "y": "pix", "ra": "deg", "dec": "deg", "mag": "mag", "hlr_arcsec": "arcsec",
                "separation": "pix", "det_mag_auto": "mag", "det_flux_radius": "pix", "det_npix": "pix2",
                "flux": "adu", "noise": "adu", "det_flux_auto": "adu"}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a unit astropy cannot read would warn here
        injected = Table.read(run_dir / "catalogs" / "buldisk_injected.fits")
        outcomes = Table.read(run_dir / "catalogs" / "point_outcomes.fits")
        false = Table.read(run_dir / "catalogs" / "point_false.fits")
        detections = Table.read(run_dir / "detection.fits")
    for name, unit in expected.items():
        assert str(injected[name].unit) == unit, name
    for name in ("mag", "x", "noise", "det_mag_auto"):
        assert outcomes[name].unit == injected[name].unit, name
    assert str(false["mag_auto"].unit) == "mag" and str(false["xwin"].unit) == "pix"
    assert str(false["flux_auto"].unit) == "adu" and str(detections["flux_auto"].unit) == "adu"
    assert injected["q"].unit is None and injected["detected"].unit is None  # dimensionless stays so
    assert injected.meta["IMGUNIT"] == "ADU"


def test_map_cubes_have_a_magnitude_axis_and_a_table_of_plane_edges(run_dir):
    with fits.open(run_dir / "maps" / "point_maps.fits") as hdul:
        header = hdul["COMPLETENESS"].header
        edges = Table.read(hdul["MAG_EDGES"])
        nplanes = hdul["COMPLETENESS"].data.shape[0]
        assert hdul["PURITY_N"].header["WCSAXES"] == 3
    assert header["WCSAXES"] == 3 and header["NAXIS"] == 3
    wcs = WCS(header)
    assert wcs.naxis == 3 and wcs.wcs.ctype[2] == "MAG" and str(wcs.wcs.cunit[2]) == "mag"
    assert len(edges) == nplanes and str(edges["mag_lo"].unit) == "mag"
    # the magnitude of plane k is its bin's centre, and the same as the MAGLOk/MAGHIk keywords
    _, _, mags = wcs.pixel_to_world_values(np.zeros(nplanes), np.zeros(nplanes), np.arange(nplanes))
    centres = 0.5 * (np.asarray(edges["mag_lo"]) + np.asarray(edges["mag_hi"]))
    np.testing.assert_allclose(mags, centres, atol=1e-9)
    np.testing.assert_allclose(edges["mag_lo"], [header[f"MAGLO{k}"] for k in range(nplanes)])
    # the celestial axes still place the bins on the sky as the image's WCS does
    image_wcs = WCS(fits.getheader(run_dir / "sfi.fits"))
    b = header["BINPIX"]
    ra, dec, _ = wcs.pixel_to_world_values(1, 0, 0)
    np.testing.assert_allclose(image_wcs.pixel_to_world_values(1.5 * b - 0.5, 0.5 * b - 0.5), (ra, dec),
                               atol=1e-9)


def _tan(sip: bool = False) -> WCS:
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"] if sip else ["RA---TAN", "DEC--TAN"]
    w.wcs.crval, w.wcs.crpix, w.wcs.cdelt = [150.0, 2.0], [50.0, 50.0], [-1e-4, 1e-4]
    if sip:
        w.sip = Sip(np.array([[0, 0, 1e-6], [0, 1e-6, 0], [1e-6, 0, 0]]), np.zeros((3, 3)), None, None,
                    w.wcs.crpix)
    return w


def test_map_cube_header_unequal_planes_no_wcs_and_sip():
    # unequal bins cannot be a linear magnitude axis: the third axis is the plane index
    header = map_cube_header(_tan(), 10.0, (4, 5), [22.0, 23.5, 24.0, 25.0])
    wcs = WCS(header)
    assert wcs.naxis == 3 and wcs.wcs.ctype[2] == "PLANE"
    assert wcs.pixel_to_world_values(0, 0, 2)[2] == pytest.approx(2.0)
    assert (header["MAGLO1"], header["MAGHI1"]) == (23.5, 24.0)
    # without an image WCS the first two axes give the image pixel of each bin's centre
    header = map_cube_header(None, 10.0, (4, 5), [22.0, 23.0, 24.0])
    x, y, mag = WCS(header).pixel_to_world_values([0, 3], [0, 2], [0, 1])
    np.testing.assert_allclose(x, [4.5, 34.5])
    np.testing.assert_allclose(y, [4.5, 24.5])
    np.testing.assert_allclose(mag, [22.5, 23.5])
    # astropy refuses SIP in three dimensions: such a cube keeps a 2-D WCS that reads
    header = map_cube_header(_tan(sip=True), 10.0, (4, 5), [22.0, 23.0, 24.0])
    assert WCS(header).naxis == 2 and "CTYPE3" not in header


@pytest.mark.parametrize("bunit, unit", [("ADU", "adu"), ("MJy/sr", "MJy / sr"), ("COUNTS/S", "ct / s"),
                                         ("electrons/s", None), ("nanomaggies", None), ("", None)])
def test_bunit_becomes_a_column_unit_only_when_fits_knows_it(bunit, unit):
    assert (None if fits_unit(bunit) is None else fits_unit(bunit).to_string()) == unit
    table = set_image_units(Table({"flux": [1.0], "det_flux_auto": [2.0], "mag": [20.0]}), bunit)
    assert (None if table["flux"].unit is None else table["flux"].unit.to_string()) == unit
    assert table["det_flux_auto"].unit == table["flux"].unit and table["mag"].unit is None
    assert table.meta.get("IMGUNIT") == (bunit or None)
