"""The input boundary: load_image reads any HDU, converts, masks and validates.

Every test writes a small FITS file with known content into ``tmp_path`` and
checks what ``load_image`` returns (or the error it raises, including that the
message names the fix).
"""

import hashlib
import json
import math
import re
import warnings

import numpy as np
import pytest
import sep
from astropy.io import fits

from comest_bayes.errors import InputError, InputFileError
from comest_bayes.io.image import (GAIN_KEYWORDS, SATURATION_KEYWORDS, ZP_KEYWORDS, ImageData, SkyStats, decide_gain, load_image, parse_bunit, sky_statistics)
from conftest import tan_header

SHAPE = (48, 64)  # (ny, nx): non-square, so a transposed array would be caught


def noise_image(seed=0, shape=SHAPE, sky=10.0, sigma=1.0):
    """Flat sky with white noise (float32), from a fixed seed."""
    return (sky + np.random.default_rng(seed).normal(0.0, sigma, shape)).astype(np.float32)


def wcs_header(zp=None, **kwargs):
    header = tan_header(SHAPE, **kwargs)
    if zp is not None:
        header["MAGZERO"] = zp
    return header


def sha256(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


# --------------------------------------------------------------------------- HDUs and data types


def test_tile_compressed_image_in_hdu1_is_found(write_fits):
    data = noise_image(1)
    path = write_fits("comp.fits", data, wcs_header(zp=27.0), compressed=True)
    with fits.open(path) as hdul:  # premise: HDU 0 is empty, HDU 1 is the compressed image
        assert hdul[0].data is None and isinstance(hdul[1], fits.CompImageHDU)
    image = load_image(path)
    assert isinstance(image, ImageData)
    assert image.hdu == 1
    assert image.shape == SHAPE
    np.testing.assert_array_equal(image.data, data)  # GZIP without quantization is lossless
    assert image.zeropoint == 27.0


def test_explicit_hdu_selects_the_extension(write_fits):
    first, second = noise_image(1), noise_image(2, sky=50.0)
    extra = fits.ImageHDU(data=second, header=wcs_header(zp=26.0))
    path = write_fits("two.fits", first, wcs_header(zp=25.0), extra_hdus=[extra])
    default = load_image(path)
    assert default.hdu == 0 and default.zeropoint == 25.0
    np.testing.assert_array_equal(default.data, first)
    chosen = load_image(path, hdu=1)
    assert chosen.hdu == 1 and chosen.zeropoint == 26.0
    np.testing.assert_array_equal(chosen.data, second)


def test_table_hdu_is_rejected_with_a_hint_to_pass_hdu(write_fits, tmp_path):
    table = fits.BinTableHDU.from_columns([fits.Column(name="a", format="E", array=np.arange(5.0))])
    path = write_fits("withtable.fits", noise_image(), wcs_header(zp=25.0), extra_hdus=[table])
    with pytest.raises(InputError, match=r"HDU 1 .* is not a 2-D image.*--hdu"):
        load_image(path, hdu=1)
    with pytest.raises(InputError, match=r"has 2 HDUs \(0-1\); got hdu=5"):
        load_image(path, hdu=5)
    only_table = tmp_path / "onlytable.fits"
    fits.HDUList([fits.PrimaryHDU(), table]).writeto(only_table)
    with pytest.raises(InputError, match=r"no 2-D image in any of its 2 HDUs.*--hdu"):
        load_image(only_table, pixel_scale=0.2, zp=25.0)


def test_cube_is_not_taken_for_an_image(write_fits):
    cube = np.stack([noise_image(1), noise_image(2)])
    path = write_fits("cube.fits", cube)
    with pytest.raises(InputError, match=r"no 2-D image: HDU 0 is a 3-D cube of shape \(2, 48, 64\)\. .*--hdu "
                                         r"chooses an HDU, not a plane of a cube: extract the plane .*fits\.writeto"):
        load_image(path, pixel_scale=0.2, zp=25.0)
    # --hdu cannot help, and the message says so instead of suggesting it
    with pytest.raises(InputError, match=r"HDU 0 of image file .* is a 3-D cube of shape \(2, 48, 64\), not a 2-D "
                                         r"image\. .*not a plane of a cube"):
        load_image(path, hdu=0, pixel_scale=0.2, zp=25.0)


def test_cube_advice_extracts_a_plane_that_loads(write_fits, tmp_path, monkeypatch):
    cube = np.stack([noise_image(1), noise_image(2)])
    path = write_fits("cube.fits", cube, wcs_header(zp=25.0))
    with pytest.raises(InputError) as info:
        load_image(path)
    command = str(info.value).split('python -c "')[1].split('"')[0]
    monkeypatch.chdir(tmp_path)
    exec(command)  # the advice is a working recipe
    image = load_image(tmp_path / "plane.fits")
    np.testing.assert_array_equal(image.data, cube[0])


def test_degenerate_axes_are_dropped(write_fits):
    data = noise_image(1)
    image = load_image(write_fits("deg.fits", data[np.newaxis], wcs_header(zp=25.0)))
    assert image.shape == SHAPE
    np.testing.assert_array_equal(image.data, data)


def test_a_one_plane_cube_with_a_tpv_wcs_reads_as_its_plane(write_fits):
    """wcslib cannot take the celestial sub-WCS of a TPV header with a third axis ('NULL error object in
    wcslib', a traceback before); the plane's own two axes give the same sky positions as the 2-D image."""
    header = wcs_header(zp=25.0, rotation_deg=10.0)
    header["CTYPE1"], header["CTYPE2"] = "RA---TPV", "DEC--TPV"
    for axis, terms in ((1, (0.0, 1.0, 0.0, 0.0, 1e-3)), (2, (0.0, 1.0, 0.0, 0.0, -2e-3))):
        for j, value in enumerate(terms):
            header[f"PV{axis}_{j}"] = value
    data = noise_image(4)
    flat = load_image(write_fits("flat.fits", data, header))
    cube = load_image(write_fits("cube1.fits", data[np.newaxis], header))
    assert cube.shape == SHAPE and cube.wcs is not None
    x, y = np.array([0.0, 30.5, 63.0]), np.array([0.0, 20.0, 47.0])
    np.testing.assert_allclose(cube.wcs.all_pix2world(x, y, 0), flat.wcs.all_pix2world(x, y, 0), rtol=0, atol=1e-12)


def test_big_endian_data_become_native_float32_and_sep_runs(write_fits):
    data = noise_image(3)
    data[20:25, 30:35] += 50.0  # one obvious source
    path = write_fits("be.fits", data, wcs_header(zp=25.0))
    with fits.open(path) as hdul:  # premise: astropy hands FITS data over big-endian
        assert hdul[0].data.dtype.byteorder == ">"
    image = load_image(path)
    assert image.data.dtype == np.float32 and image.data.dtype.isnative
    assert image.data.flags.c_contiguous
    np.testing.assert_array_equal(image.data, data)
    bkg = sep.Background(image.data)  # raises "byte order" errors on non-native input
    objects = sep.extract(image.data - bkg.back(), 5.0, err=bkg.globalrms)
    assert len(objects) == 1
    assert abs(objects["x"][0] - 32.0) < 0.5 and abs(objects["y"][0] - 22.0) < 0.5


def test_scaled_integer_image_is_read_as_float32(tmp_path):
    values = np.random.default_rng(4).integers(0, 1000, SHAPE).astype(np.int16)
    hdu = fits.PrimaryHDU(data=values, header=wcs_header(zp=25.0))
    hdu.header["BSCALE"], hdu.header["BZERO"] = 0.5, 100.0
    path = tmp_path / "int.fits"
    hdu.writeto(path)
    image = load_image(path)
    assert image.data.dtype == np.float32
    np.testing.assert_allclose(image.data, values * 0.5 + 100.0)


def test_nan_and_inf_pixels_are_masked_and_zeroed(write_fits):
    data = noise_image(5)
    bad = [(3, 4), (10, 60), (47, 0)]
    data[3, 4], data[10, 60], data[47, 0] = np.nan, np.inf, -np.inf
    path = write_fits("nan.fits", data, wcs_header(zp=25.0))
    image = load_image(path)
    expected_mask = np.zeros(SHAPE, bool)
    for j, i in bad:
        expected_mask[j, i] = True
    np.testing.assert_array_equal(image.mask, expected_mask)
    assert np.all(np.isfinite(image.data))
    assert all(image.data[j, i] == 0.0 for j, i in bad)
    np.testing.assert_array_equal(image.data[~expected_mask], data[~expected_mask])
    assert image.unmasked_fraction == pytest.approx(1 - 3 / data.size)


# --------------------------------------------------------------------------- WCS and pixel scale


@pytest.mark.parametrize("scale", [0.2, 0.031, 5.0])
def test_pixel_scale_from_tan_cdelt(write_fits, scale):
    path = write_fits("tan.fits", noise_image(), wcs_header(zp=25.0, pixel_scale=scale))
    image = load_image(path)
    assert image.wcs is not None and list(image.wcs.wcs.ctype) == ["RA---TAN", "DEC--TAN"]
    # At the tangent point a TAN projection has exactly the CDELT scale; 1e-6 allows for rounding.
    assert image.pixel_scale == pytest.approx(scale, rel=1e-6)
    assert "WCS" in image.provenance["pixel_scale"]


@pytest.mark.parametrize("rotation", [30.0, 123.4, -71.0])
def test_pixel_scale_from_rotated_cd_matrix(write_fits, rotation):
    header = wcs_header(zp=25.0, pixel_scale=0.27, rotation_deg=rotation)
    assert "CD1_2" in header and header["CD1_2"] != 0  # premise: a genuinely rotated CD matrix
    image = load_image(write_fits("rot.fits", noise_image(), header))
    assert image.pixel_scale == pytest.approx(0.27, rel=1e-6)
    # The world coordinates follow the rotation: one pixel along +x moves by the scale on the sky.
    ra0, dec0 = image.wcs.all_pix2world([[10.0, 10.0], [11.0, 10.0]], 0).T
    step = np.hypot((ra0[1] - ra0[0]) * np.cos(np.deg2rad(dec0[0])), dec0[1] - dec0[0]) * 3600
    assert step == pytest.approx(0.27, rel=1e-5)


def test_pixel_scale_argument_overrides_the_wcs(write_fits):
    image = load_image(write_fits("tan.fits", noise_image(), wcs_header(zp=25.0)), pixel_scale=0.35)
    assert image.pixel_scale == 0.35
    assert image.provenance["pixel_scale"] == "--pixel-scale"
    assert image.wcs is not None  # the WCS is still read for ra/dec


# --------------------------------------------------------------------------- photometric keywords


@pytest.mark.filterwarnings("ignore:Keyword name 'ZEROPOINT':astropy.io.fits.verify.VerifyWarning")
@pytest.mark.parametrize("key", ZP_KEYWORDS)
def test_zero_point_from_each_keyword(write_fits, key):
    header = wcs_header()
    header[key] = 26.125  # ZEROPOINT has 9 letters: astropy writes it as a HIERARCH card
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "image header MAGZPT = 26.1250 is taken per image unit")  # no EXPTIME
        image = load_image(write_fits("zp.fits", noise_image(), header))
    assert image.zeropoint == 26.125
    assert image.provenance["zeropoint"] == f"image header {key}"


def test_zero_point_keyword_order(write_fits):
    # DECam headers carry MAGZERO (per image) and MAGZPT (per second); the first listed wins.
    header = wcs_header()
    header[ZP_KEYWORDS[1]] = 25.3
    header[ZP_KEYWORDS[0]] = 30.2
    # without EXPTIME the per-second MAGZPT cannot be converted, so the two disagree and the user is told
    with pytest.warns(UserWarning, match=r"zero points disagree: image header MAGZERO gives 30\.200 but image header "
                                         r"MAGZPT gives 25\.300; using image header MAGZERO"):
        assert load_image(write_fits("zp.fits", noise_image(), header)).zeropoint == 30.2


def test_zero_point_from_primary_header_when_image_is_an_extension(write_fits):
    primary = fits.Header()
    primary["MAGZERO"] = 30.212
    path = write_fits("ext.fits", noise_image(), wcs_header(), extension=True, primary_header=primary)
    image = load_image(path)
    assert image.hdu == 1
    assert image.zeropoint == 30.212
    assert image.provenance["zeropoint"] == "primary header MAGZERO"
    # The image HDU's own keyword takes precedence over the primary header's.
    path2 = write_fits("ext2.fits", noise_image(), wcs_header(zp=28.0), extension=True, primary_header=primary)
    assert load_image(path2).zeropoint == 28.0


def test_zp_argument_overrides_the_header(write_fits):
    image = load_image(write_fits("zp.fits", noise_image(), wcs_header(zp=25.0)), zp=31.5)
    assert image.zeropoint == 31.5
    assert image.provenance["zeropoint"] == "--zp"


def test_non_numeric_zero_point_keyword_is_skipped(write_fits):
    header = wcs_header()
    header["MAGZERO"] = "unknown"
    header["MAGZP"] = 24.5
    with pytest.warns(UserWarning, match=r"MAGZERO = 'unknown' in the image header is present but not a number; "
                                         r"using image header MAGZP = 24\.5"):
        assert load_image(write_fits("zp.fits", noise_image(), header)).zeropoint == 24.5


def test_non_numeric_zero_point_alone_is_reported_as_not_a_number(write_fits):
    header = wcs_header()
    header["MAGZERO"] = "TBD"
    with pytest.raises(InputError, match=r"no photometric zero point .*MAGZERO = 'TBD' in the image header, which "
                                         r"is present but not a number.*pass --zp MAG") as info:
        load_image(write_fits("zp.fits", noise_image(), header))
    assert "is present;" not in str(info.value) and "none of the header keywords" not in str(info.value)


@pytest.mark.parametrize("gain_key", GAIN_KEYWORDS)
@pytest.mark.parametrize("sat_key", SATURATION_KEYWORDS[:2])
def test_gain_and_saturation_from_header(write_fits, gain_key, sat_key):
    header = wcs_header(zp=25.0)
    header[gain_key] = 4.25
    header[sat_key] = 61000.0
    path = write_fits("gs.fits", noise_image(sky=0.0), header)  # sky subtracted: nothing to check the gain against
    image = load_image(path)
    assert image.gain == 4.25 and image.saturation == 61000.0
    assert gain_key in image.provenance["gain"] and sat_key in image.provenance["saturation"]
    overridden = load_image(path, gain=1.5, saturation=1000.0)
    assert overridden.gain == 1.5 and overridden.saturation == 1000.0


def test_gain_and_saturation_unknown_without_keywords(write_fits):
    header = wcs_header(zp=25.0)
    header["GAIN"] = 0.0  # a zero gain means "unknown", not "infinite photon noise"
    image = load_image(write_fits("g.fits", noise_image(), header))
    assert image.gain is None and image.saturation is None


# --------------------------------------------------------------------------- weight maps and masks


def test_weight_types_ivar_rms_var_give_the_same_sigma(write_fits):
    sigma = np.linspace(0.5, 6.0, SHAPE[0] * SHAPE[1]).reshape(SHAPE).astype(np.float32)
    path = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    maps = {"ivar": 1.0 / sigma**2, "rms": sigma, "var": sigma**2}
    noises = {}
    for kind, values in maps.items():
        noises[kind] = load_image(path, weight=write_fits(f"w_{kind}.fits", values), weight_type=kind).noise
        assert noises[kind].dtype == np.float32 and noises[kind].shape == SHAPE
        np.testing.assert_allclose(noises[kind], sigma, rtol=1e-6)
    np.testing.assert_allclose(noises["ivar"], noises["rms"], rtol=1e-6)
    np.testing.assert_allclose(noises["var"], noises["rms"], rtol=1e-6)


def test_non_positive_and_nan_weights_are_masked(write_fits):
    ivar = np.full(SHAPE, 4.0, dtype=np.float32)
    ivar[0, :10] = 0.0
    ivar[5, 5] = -1.0
    ivar[7, 7] = np.nan
    data = noise_image()
    image = load_image(write_fits("img.fits", data, wcs_header(zp=25.0)), weight=write_fits("w.fits", ivar))
    bad = ~(ivar > 0)  # NaN compares False, so it is bad too
    np.testing.assert_array_equal(image.mask, bad)
    assert np.all(np.isinf(image.noise[bad]))
    np.testing.assert_allclose(image.noise[~bad], 0.5)
    assert np.all(image.data[bad] == 0.0)
    np.testing.assert_array_equal(image.data[~bad], data[~bad])


def test_mask_file_non_zero_is_bad(write_fits):
    mvals = np.zeros(SHAPE, dtype=np.int32)
    mvals[10:12, 20:30] = 1
    mvals[30, 40] = 1024
    mvals[31, 41] = -3
    image = load_image(write_fits("img.fits", noise_image(), wcs_header(zp=25.0)),
                       mask=write_fits("m.fits", mvals, extension=True))
    np.testing.assert_array_equal(image.mask, mvals != 0)
    assert "m.fits" in image.provenance["mask"]


def test_mask_bits_select_which_flags_are_bad(write_fits):
    mvals = np.zeros(SHAPE, dtype=np.int32)
    mvals[0, :6] = [1, 2, 4, 6, 8, 3]
    img = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    mpath = write_fits("m.fits", mvals)
    only2 = load_image(img, mask=mpath, mask_bits=2)
    np.testing.assert_array_equal(np.flatnonzero(only2.mask), [1, 3, 5])  # values 2, 6, 3 carry bit 2
    bits_1_4 = load_image(img, mask=mpath, mask_bits=1 | 4)
    np.testing.assert_array_equal(np.flatnonzero(bits_1_4.mask), [0, 2, 3, 5])  # 1, 4, 6, 3
    every = load_image(img, mask=mpath)
    np.testing.assert_array_equal(np.flatnonzero(every.mask), [0, 1, 2, 3, 4, 5])


def test_weight_and_mask_in_chosen_hdus(write_fits):
    sigma = np.full(SHAPE, 2.0, dtype=np.float32)
    decoy = fits.ImageHDU(data=np.full(SHAPE, 100.0, dtype=np.float32))
    wpath = write_fits("w.fits", np.full(SHAPE, 9.0, np.float32), extra_hdus=[fits.ImageHDU(data=sigma)])
    mvals = np.zeros(SHAPE, np.int16)
    mvals[1, 1] = 1
    mpath = write_fits("m.fits", np.zeros(SHAPE, np.int16), extra_hdus=[fits.ImageHDU(data=mvals), decoy])
    image = load_image(write_fits("img.fits", noise_image(), wcs_header(zp=25.0)), weight=wpath, weight_type="rms",
                       weight_hdu=1, mask=mpath, mask_hdu=1)
    np.testing.assert_allclose(image.noise, 2.0)
    assert image.mask.sum() == 1 and image.mask[1, 1]


def test_a_weight_or_mask_hdu_without_an_image_names_its_own_option_and_the_image_hdus(write_fits, tmp_path):
    # as a DECam community-pipeline mask: an empty primary HDU, the mask in HDU 1
    mpath = tmp_path / "ood.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(data=np.zeros(SHAPE, np.int16))]).writeto(mpath)
    img = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    with pytest.raises(InputError, match=r"HDU 0 of mask file .* HDU 1 holds one: pick another with --mask-hdu\."):
        load_image(img, mask=mpath, mask_hdu=0)
    with pytest.raises(InputError, match=r"pick another with --weight-hdu\."):
        load_image(img, weight=mpath, weight_hdu=0)
    assert load_image(img, mask=mpath, mask_hdu=1).mask.sum() == 0


def test_load_image_never_modifies_its_inputs(write_fits):
    data = noise_image()
    data[2, 2] = np.nan  # load_image zeroes this pixel in memory, never on disk
    img = write_fits("img.fits", data, wcs_header(zp=25.0))
    ivar = np.full(SHAPE, 2.0, np.float32)
    ivar[3, 3] = 0.0
    wpath = write_fits("w.fits", ivar)
    mpath = write_fits("m.fits", (np.arange(data.size).reshape(SHAPE) % 7 == 0).astype(np.uint8))
    before = {p: (sha256(p), p.stat().st_mtime_ns) for p in (img, wpath, mpath)}
    image = load_image(img, weight=wpath, mask=mpath)
    image.data[:] = -1.0  # the arrays are in-memory copies, not memory maps of the files
    image.noise[:] = -1.0
    del image
    after = {p: (sha256(p), p.stat().st_mtime_ns) for p in (img, wpath, mpath)}
    assert before == after


def test_facts_are_json_ready(write_fits):
    image = load_image(write_fits("img.fits", noise_image(), wcs_header(zp=25.0)), fwhm=3.0)
    facts = json.loads(json.dumps(image.facts()))
    assert facts["shape"] == list(SHAPE)
    assert facts["zeropoint"] == 25.0 and facts["fwhm_pix"] == 3.0
    assert facts["provenance"]["fwhm"] == "--fwhm"


# --------------------------------------------------------------------------- bad inputs


def test_missing_files_raise_input_file_error(write_fits, tmp_path):
    with pytest.raises(InputFileError, match=r"image file .*nope\.fits' does not exist; check the path"):
        load_image(tmp_path / "nope.fits")
    img = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    with pytest.raises(InputFileError, match=r"weight file .*w\.fits' does not exist"):
        load_image(img, weight=tmp_path / "w.fits")
    with pytest.raises(InputFileError, match=r"mask file .*m\.fits' does not exist"):
        load_image(img, mask=tmp_path / "m.fits")
    with pytest.raises(InputFileError, match="is not a file"):
        load_image(tmp_path)
    assert issubclass(InputFileError, FileNotFoundError)


def test_non_fits_file_is_reported(tmp_path):
    path = tmp_path / "notes.fits"
    path.write_text("this is not FITS\n")
    with pytest.raises(InputError, match="not a readable FITS file"):
        load_image(path)


def test_no_wcs_and_no_pixel_scale_asks_for_pixel_scale(write_fits):
    header = fits.Header()
    header["MAGZERO"] = 25.0
    path = write_fits("nowcs.fits", noise_image(), header)
    with pytest.raises(InputError, match=r"no celestial WCS.*pass --pixel-scale"):
        load_image(path)
    image = load_image(path, pixel_scale=0.2)
    assert image.wcs is None and image.pixel_scale == 0.2


def test_no_zero_point_asks_for_zp(write_fits):
    path = write_fits("nozp.fits", noise_image(), wcs_header())
    with pytest.raises(InputError, match=r"no photometric zero point.*MAGZERO.*pass --zp"):
        load_image(path)
    # zero is a valid zero point (maggies), but not for this image's noise of 1 unit: a warning, not a refusal
    with pytest.warns(UserWarning, match=r"zero point 0 \(--zp\) looks implausible"):
        assert load_image(path, zp=0.0).zeropoint == 0.0


def test_weight_shape_mismatch(write_fits):
    img = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    wpath = write_fits("w.fits", np.ones((SHAPE[1], SHAPE[0]), np.float32))  # transposed
    with pytest.raises(InputError, match=r"weight map .* has shape \(64, 48\) but the image .* has \(48, 64\); "
                                         r"give the weight map that belongs"):
        load_image(img, weight=wpath)


def test_mask_shape_mismatch(write_fits):
    img = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    mpath = write_fits("m.fits", np.zeros((SHAPE[0] + 1, SHAPE[1]), np.int16))
    with pytest.raises(InputError, match=r"mask .* has shape \(49, 64\).*give the mask that belongs"):
        load_image(img, mask=mpath)


def test_all_masked_image(write_fits):
    """Each way of losing every pixel names its own cause and fix, not the files the user never gave."""
    img = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    with pytest.raises(InputError, match=r"every pixel .* is unusable \(100% flagged in the mask\): .*--mask-bits"):
        load_image(img, mask=write_fits("m.fits", np.ones(SHAPE, np.int16)))
    with pytest.raises(InputError, match=r"unusable \(100% NaN or infinite in the image\): is this the right HDU") \
            as info:
        load_image(write_fits("nan.fits", np.full(SHAPE, np.nan, np.float32), wcs_header(zp=25.0)))
    assert "--mask" not in str(info.value) and "weight" not in str(info.value)  # (the tmp path holds "mask")
    with pytest.raises(InputError, match=r"unusable \(100% zero, negative or non-finite in the weight map \(read as "
                                         r"ivar\)\): check --weight-type"):
        load_image(img, weight=write_fits("w.fits", np.zeros(SHAPE, np.float32)))
    # two partial causes that together take every pixel: both shares, both fixes
    half = np.zeros(SHAPE, np.int16)
    half[:, :32] = 1
    weight = np.ones(SHAPE, np.float32)
    weight[:, 32:] = 0.0
    with pytest.raises(InputError, match=r"\(50% zero, .*; 50% flagged in the mask\): check --weight-type.*--mask-bits"):
        load_image(img, weight=write_fits("w2.fits", weight), mask=write_fits("m2.fits", half))


def test_nearly_all_masked_image(write_fits):
    mvals = np.ones(SHAPE, np.int16)
    mvals[:10, :10] = 0  # 100 usable pixels
    img = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    with pytest.raises(InputError, match=r"only 100 usable pixels"):
        load_image(img, mask=write_fits("m.fits", mvals))


def test_constant_image(write_fits):
    data = np.full(SHAPE, 7.0, np.float32)
    data[0, 0] = np.nan  # the constant check looks at the unmasked pixels only
    with pytest.raises(InputError, match=r"is constant \(7\.0 in every unmasked pixel\).*--hdu") as info:
        load_image(write_fits("const.fits", data, wcs_header(zp=25.0)))
    assert "np." not in str(info.value) and str(info.value).endswith("blank frame?")  # a plain number


def test_missing_facts_are_reported_together(write_fits):
    bare = write_fits("bare.fits", noise_image())  # no header keywords at all
    with pytest.raises(InputError, match=r"^2 problems with image .*bare\.fits': \(1\) .*no celestial WCS.*pass "
                                         r"--pixel-scale .*; \(2\) no photometric zero point.*pass --zp MAG"):
        load_image(bare)
    # a companion of the wrong shape is reported with them, not before them
    wrong = write_fits("w.fits", np.ones((SHAPE[1], SHAPE[0]), np.float32))
    with pytest.raises(InputError, match=r"^3 problems .*\(1\) weight map .*has shape \(64, 48\).*\(2\) .*--pixel-scale"
                                         r".*\(3\) .*--zp"):
        load_image(bare, weight=wrong)
    with pytest.raises(InputError, match=r"^no photometric zero point"):  # one problem: no list
        load_image(bare, pixel_scale=0.2)


def test_too_small_image(write_fits):
    with pytest.raises(InputError, match=r"only 8x10 pixels; at least 16x16"):
        load_image(write_fits("small.fits", noise_image(shape=(10, 8)), wcs_header(zp=25.0)))


def test_bad_weight_type(write_fits):
    img = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    with pytest.raises(InputError, match=r"weight_type='weight' is not one of .*use ivar .*rms .*var"):
        load_image(img, weight=img, weight_type="weight")


@pytest.mark.parametrize("name", ["pixel_scale", "fwhm", "gain", "saturation"])
@pytest.mark.parametrize("value", [-0.2, 0.0, float("nan"), float("inf")])
def test_non_positive_parameters(write_fits, name, value):
    img = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    with pytest.raises(InputError, match=rf"{name}=.* must be a positive finite number"):
        load_image(img, **{name: value})


def test_non_finite_zp(write_fits):
    img = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    with pytest.raises(InputError, match=r"zp=nan must be a finite number"):
        load_image(img, zp=float("nan"))


@pytest.mark.parametrize("name", ["zp", "pixel_scale", "fwhm", "gain", "saturation"])
def test_a_parameter_that_is_no_number_is_named_not_blamed_on_the_file(write_fits, name):
    img = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    with pytest.raises(InputError, match=rf"^{name}='abc' must be a number\.$"):
        load_image(img, **{name: "abc"})
    assert load_image(img, **{name: "25.0"}).path  # a number as text is a number


def test_input_errors_are_value_errors():
    # Callers that only know the built-ins can still catch these.
    assert issubclass(InputError, ValueError)


# --------------------------------------------------------------------------- units and sky statistics


@pytest.mark.parametrize("bunit, kind, per_second, jy", [
    ("adu", "counts", False, None), ("ADU/s", "counts", True, None), ("DN/s", "counts", True, None),
    ("counts", "counts", False, None), ("cps", "counts", True, None), ("ELECTRONS", "electrons", False, None),
    ("ELECTRONS/S", "electrons", True, None), ("e-/s", "electrons", True, None),
    ("nanomaggies", "flux", False, 3631e-9), ("nmgy", "flux", False, 3631e-9), ("maggies", "flux", False, 3631.0),
    ("Jy", "flux", False, 1.0), ("mJy", "flux", False, 1e-3), ("uJy/pixel", "flux", False, 1e-6),
    ("nJy", "flux", False, 1e-9), ("MJy/sr", "flux", False, 1e6), ("erg/s/cm2/A", "flux", False, None),
    ("", "unknown", False, None), ("furlongs", "unknown", False, None),
])
def test_parse_bunit(bunit, kind, per_second, jy):
    units = parse_bunit(bunit)
    assert units.kind == kind and units.per_second == per_second
    assert units.jy_per_unit == (None if jy is None else pytest.approx(jy))
    assert units.per_sr == (bunit == "MJy/sr")


def test_sky_statistics_known_answer():
    rng = np.random.default_rng(7)
    values = rng.normal(100.0, 5.0, 200_000)
    values[:2000] += rng.exponential(200.0, 2000)  # 1% sources: clipped away
    sky = sky_statistics(values)
    # sd of a MAD-based sigma on ~2e5 pixels is ~0.2%; the 1% of sources bias the median by ~0.06 sigma
    assert sky.level == pytest.approx(100.0, abs=0.5)
    assert sky.sigma == pytest.approx(5.0, rel=0.02)


# --------------------------------------------------------------------------- gain


def poisson_image(gain, sky, shape=(128, 128), seed=3, scale=1.0):
    """Sky of ``sky`` image units whose noise is Poisson in electrons (``gain`` e-/unit), times ``scale``."""
    electrons = np.random.default_rng(seed).poisson(gain * sky, shape)
    return (electrons / gain * scale).astype(np.float32)


def gain_header(**keys):
    header = wcs_header(zp=25.0)
    for key, value in keys.items():
        header[key] = value
    return header


def test_decide_gain_hst_electrons_per_second():
    # The case: an HST image in e-/s, 69 ks, CCDGAIN 2.5, sky subtracted (sigma 0.003 e-/s).
    sky = SkyStats(level=0.0001, sigma=0.003, npix=10_000)
    decision = decide_gain(units=parse_bunit("ELECTRONS/S"), sky=sky, header_gain=2.5,
                           header_source="primary header CCDGAIN", exptime=69_000.0)
    assert decision.value == 69_000.0 and decision.source == "BUNIT 'ELECTRONS/S' x EXPTIME"
    assert "CCDGAIN = 2.5 is the detector's e-/ADU and does not apply" in decision.reason
    assert math.sqrt(decision.value / 2.5) == pytest.approx(166, abs=1)  # the noise the header gain gave: 166x
    # Without BUNIT the header gain would put the sky noise at 0.0075 electrons: refused, nothing to replace it.
    blind = decide_gain(units=parse_bunit(None), sky=sky, header_gain=2.5, header_source="primary header CCDGAIN")
    assert blind.value is None and blind.contradicted
    assert ("sky noise of one pixel (sigma 0.003 image units) at 0.0075 electrons, less than one electron"
            in blind.reason)


@pytest.mark.parametrize("bunit, header, exptime, expected, source", [
    ("ADU", 4.0, 100.0, 4.0, "image header GAIN"),
    ("ADU/s", 2.0, 100.0, 200.0, "image header GAIN x EXPTIME"),
    ("electrons", 3.0, 100.0, 1.0, "BUNIT 'electrons'"),
    ("e-/s", None, 250.0, 250.0, "BUNIT 'e-/s' x EXPTIME"),
    (None, 4.0, None, 4.0, "image header GAIN"),
])
def test_decide_gain_unit_conventions(bunit, header, exptime, expected, source):
    sky = SkyStats(level=0.0, sigma=5.0, npix=1000)  # subtracted sky: the conventions alone decide
    decision = decide_gain(units=parse_bunit(bunit), sky=sky, header_gain=header,
                           header_source=None if header is None else "image header GAIN", exptime=exptime)
    assert decision.value == pytest.approx(expected) and decision.source == source
    assert not decision.contradicted


@pytest.mark.parametrize("bunit, exptime, why", [
    ("ADU", None, "the image is in ADU but the header has none of the keywords GAIN"),
    ("e-/s", None, "the image is in electrons per second but the header has no EXPTIME"),
    ("MJy/sr", None, "BUNIT 'MJy/sr' is a flux unit and no gain converts it into electrons"),
])
def test_decide_gain_says_why_there_is_none(bunit, exptime, why):
    decision = decide_gain(units=parse_bunit(bunit), sky=SkyStats(0.0, 1.0, 100), exptime=exptime)
    assert decision.value is None and decision.reason.startswith(why)
    assert "the sky was subtracted" in decision.reason
    assert decision.summary().startswith("gain: none, no photon noise added to the injections (")


def test_flux_image_with_detector_gain_gets_no_photon_noise(write_fits):
    # The case: nanomaggies with a detector GAIN; the sky was subtracted, so nothing can replace it.
    data = np.random.default_rng(1).normal(0.0, 0.05, SHAPE).astype(np.float32)
    path = write_fits("nmgy.fits", data, gain_header(BUNIT="nanomaggies", GAIN=4.0, MAGZERO=22.5))
    with pytest.warns(UserWarning, match=r"gain: none, no photon noise added to the injections \(image header GAIN "
                                         r"= 4 was rejected: BUNIT 'nanomaggies' is a flux unit, and the header GAIN = "
                                         r"4 is a detector gain in e-/ADU that does not convert it into electrons"):
        image = load_image(path)
    assert image.gain is None
    assert image.gain_decision["header_value"] == 4.0 and image.gain_decision["contradicted"]
    assert image.provenance["gain"].startswith("unknown (no photon noise on injections): image header GAIN")


def test_maggies_without_bunit_fail_the_one_electron_floor(write_fits):
    data = np.random.default_rng(2).normal(0.0, 4e-12, SHAPE).astype(np.float32)  # KiDS-like: AB maggies
    path = write_fits("maggies.fits", data, gain_header(GAIN=3.5))
    with pytest.warns(UserWarning, match=r"image header GAIN = 3\.5 was rejected: it would put the sky noise of one "
                                         r"pixel \(sigma [34]\.\d+e-12 image units\) at 1\.\de-11 electrons, less than "
                                         r"one electron"):
        image = load_image(path, zp=0.0)
    assert image.gain is None and image.gain_decision["measured"] is None


def test_header_gain_consistent_with_the_sky_is_kept(write_fits):
    path = write_fits("adu.fits", poisson_image(4.0, 1000.0), gain_header(BUNIT="ADU", GAIN=4.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing to warn about
        image = load_image(path)
    assert image.gain == 4.0 and image.provenance["gain"].startswith("image header GAIN: the image is in ADU")
    # level / sigma^2 of Poisson(4000)/4: 1000 / 250 = 4; 16384 pixels give sigma to ~0.7%, g_eff to ~1.5%
    assert image.gain_decision["measured"] == pytest.approx(4.0, rel=0.05)
    assert "consistent with the effective gain 4" in image.gain_summary()


def test_header_gain_contradicted_by_the_sky_is_replaced(write_fits):
    # An averaged stack of 10 exposures keeps the detector GAIN 4 but has an effective gain of 40.
    path = write_fits("stack.fits", poisson_image(40.0, 1000.0), gain_header(GAIN=4.0))
    with pytest.warns(UserWarning, match=r"gain: 4\d\.\d+ e- per image unit from sky noise \(image header GAIN = 4 "
                                         r"contradicts the image: the sky noise implies an effective gain of 4\d"):
        image = load_image(path)
    assert image.gain == pytest.approx(40.0, rel=0.05)  # the same ~1.5% as above, with margin
    assert image.gain_decision["source"] == "sky noise" and image.gain_decision["header_value"] == 4.0


def test_electrons_per_second_with_sky_uses_exptime(write_fits):
    # 400 e- of sky over 69 ks in e-/s: g_eff = level / sigma^2 = (400/t) / (400/t^2) = t.
    t = 69_000.0
    data = poisson_image(1.0, 400.0, scale=1.0 / t)
    path = write_fits("drz.fits", data, gain_header(BUNIT="ELECTRONS/S", EXPTIME=t, CCDGAIN=2.5))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zero point 25 on this image is a separate matter
        image = load_image(path)
    assert image.gain == t and image.gain_decision["source"] == "BUNIT 'ELECTRONS/S' x EXPTIME"
    assert image.gain_decision["measured"] == pytest.approx(t, rel=0.05)


def test_user_gain_is_used_but_checked(write_fits):
    path = write_fits("adu.fits", poisson_image(4.0, 1000.0), gain_header())
    with pytest.warns(UserWarning, match=r"from --gain \(given by the user, although the sky noise implies an "
                                         r"effective gain of 4\.\d+ .*a factor 2\d"):
        image = load_image(path, gain=100.0)
    assert image.gain == 100.0 and image.gain_decision["contradicted"]


def test_no_gain_suggests_the_measured_one(write_fits):
    path = write_fits("adu.fits", poisson_image(4.0, 1000.0), gain_header())
    image = load_image(path)
    assert image.gain is None  # no photon noise rather than a guess
    assert image.gain_decision["measured"] == pytest.approx(4.0, rel=0.05)
    assert re.search(r"no BUNIT and none of the header keywords GAIN.*; the sky noise implies an effective gain of "
                     r"about 4\.\d+: pass --gain 4\.\d+ to add photon noise", image.gain_summary())


def test_gain_decision_is_in_the_facts(write_fits):
    path = write_fits("adu.fits", poisson_image(4.0, 1000.0), gain_header(BUNIT="ADU", GAIN=4.0, EXPTIME=30.0))
    facts = json.loads(json.dumps(load_image(path).facts()))  # as run.json and summary.json hold them
    decision = facts["gain_decision"]
    assert decision["value"] == 4.0 and decision["source"] == "image header GAIN"
    assert decision["header_value"] == 4.0 and decision["header_keyword"] == "GAIN"
    assert decision["measured"] == pytest.approx(4.0, rel=0.05) and "the image is in ADU" in decision["reason"]
    assert facts["bunit"] == "ADU" and facts["exptime"] == 30.0
    assert facts["sky_level"] == pytest.approx(1000.0, rel=0.01) and facts["warnings"] == []


def test_pipeline_options_carry_the_decided_gain(write_fits):
    # The pipeline hands image.gain to the detector and, through SimContext, to the injections' photon noise.
    from comest_bayes.pipeline.stages import ImageOptions

    data = np.random.default_rng(1).normal(0.0, 0.05, SHAPE).astype(np.float32)
    path = write_fits("nmgy.fits", data, gain_header(BUNIT="nanomaggies", GAIN=4.0, MAGZERO=22.5))
    with pytest.warns(UserWarning, match="was rejected"):
        image = ImageOptions(path=str(path)).load()
    assert image.gain is None and image.facts()["gain_decision"]["contradicted"]


def test_pipeline_logs_the_gain_first(write_fits, tmp_path):
    from comest_bayes.config import RunConfig
    from comest_bayes.pipeline.stages import ImageOptions, run_pipeline

    class Stop(Exception):
        pass

    def log(line):
        raise Stop(line)  # the first line the run logs, before anything else happens

    path = write_fits("adu.fits", poisson_image(4.0, 1000.0), gain_header(BUNIT="ADU", GAIN=4.0))
    with pytest.raises(Stop, match=r"^gain: 4 e- per image unit from image header GAIN \(the image is in ADU; "
                                   r"consistent with the effective gain 4\.\d+ measured from the sky noise\)$"):
        run_pipeline(ImageOptions(path=str(path), fwhm=3.0), RunConfig(), tmp_path / "out", log=log)
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- zero-point conventions


def test_magzpt_per_second_becomes_per_image_unit(write_fits):
    header = wcs_header()
    header["MAGZPT"], header["EXPTIME"] = 25.0, 100.0  # UKIDSS: counts, zero point per second
    image = load_image(write_fits("ukidss.fits", noise_image(sky=1000.0, sigma=10.0), header))
    assert image.zeropoint == pytest.approx(30.0)  # 25 + 2.5 log10(100)
    assert image.provenance["zeropoint"] == "image header MAGZPT (per second) + 2.5 log10(EXPTIME)"
    assert "MAGZPT = 25 is per second" in image.zeropoint_convention and "EXPTIME = 100 s" in image.zeropoint_convention
    header["BUNIT"] = "ADU/s"  # an image that is per second keeps it
    per_second = load_image(write_fits("rate.fits", noise_image(sky=10.0, sigma=0.1), header))
    assert per_second.zeropoint == 25.0 and per_second.provenance["zeropoint"] == "image header MAGZPT"


def test_decam_magzero_and_magzpt_agree(write_fits):
    primary = fits.Header()
    # DECam community-pipeline keywords of decam_r_S10 (see ../shared/data): MAGZERO per image, MAGZPT per second
    primary["BUNIT"], primary["EXPTIME"], primary["MAGZERO"], primary["MAGZPT"] = "adu", 90.0, 30.212, 25.326393726402
    path = write_fits("decam.fits", noise_image(sky=300.0, sigma=9.0), wcs_header(), extension=True,
                      primary_header=primary)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # 25.3264 + 2.5 log10(90) = 30.2119: no disagreement
        image = load_image(path)
    assert image.zeropoint == 30.212 and image.provenance["zeropoint"] == "primary header MAGZERO"
    primary["MAGZERO"] = 30.9
    path = write_fits("decam2.fits", noise_image(sky=300.0, sigma=9.0), wcs_header(), extension=True,
                      primary_header=primary)
    with pytest.warns(UserWarning, match=r"zero points disagree: primary header MAGZERO gives 30\.900 but primary "
                                         r"header MAGZPT \(per second\) \+ 2\.5 log10\(EXPTIME\) gives 30\.212"):
        assert load_image(path).zeropoint == 30.9


def jwst_zero_point(sr):
    """AB zero point of MJy/sr on pixels of ``sr`` steradians: 3631 Jy is 0 mag."""
    return -2.5 * math.log10(sr * 1e6 / 3631.0)


@pytest.mark.parametrize("area_keys, source", [
    ({"PIXAR_SR": 2.23e-14}, "BUNIT 'MJy/sr' and image header PIXAR_SR"),
    ({"PIXAR_A2": 0.0009473}, "BUNIT 'MJy/sr' and image header PIXAR_A2 (arcsec^2)"),
    ({}, "BUNIT 'MJy/sr' and the pixel scale 0.0308\" squared"),
])
def test_jwst_zero_point_from_bunit_and_pixel_area(write_fits, area_keys, source):
    header = wcs_header(pixel_scale=0.0308)
    header["BUNIT"] = "MJy/sr"
    for key, value in area_keys.items():
        header[key] = value
    data = np.random.default_rng(4).normal(0.0, 0.005, SHAPE).astype(np.float32)  # MJy/sr, sky subtracted
    image = load_image(write_fits("jwst.fits", data, header))
    sr = area_keys.get("PIXAR_SR") or area_keys.get("PIXAR_A2", 0.0308**2) * (math.pi / 648000) ** 2
    # 1e-6 mag: the pixel scale measured from the WCS differs from 0.0308 by rounding (1e-9 relative)
    assert image.zeropoint == pytest.approx(jwst_zero_point(sr), abs=1e-6)
    assert image.zeropoint == pytest.approx(28.03, abs=0.005)  # ../shared/data/README: 28.03 for this pixel area
    assert image.provenance["zeropoint"] == source
    assert "-2.5 log10(" in image.zeropoint_convention and "3631" in image.zeropoint_convention
    assert image.gain is None and "flux unit" in image.gain_decision["reason"]


@pytest.mark.parametrize("bunit, zp", [("nanomaggies", 22.5), ("maggies", 0.0), ("Jy", 2.5 * math.log10(3631.0)),
                                       ("uJy", 23.9), ("nJy", 31.4)])
def test_flux_units_give_their_ab_zero_point(write_fits, bunit, zp):
    header = wcs_header()
    header["BUNIT"] = bunit
    data = noise_image(sky=0.0, sigma=10 ** (-0.4 * (27.0 - zp)))  # a sky noise of 27 mag per pixel in every unit
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        image = load_image(write_fits("flux.fits", data, header))
    assert image.zeropoint == pytest.approx(zp, abs=0.002)  # 2.5 log10(3631e-6) = 23.8999: nominal 23.9
    assert image.provenance["zeropoint"] == f"BUNIT {bunit!r}"


def test_hst_photflam_zero_point(write_fits):
    header = wcs_header()
    # ACS/WFC F814W: AB zero point 25.94 for one e-/s (STScI zero-point tables for this PHOTFLAM)
    header["BUNIT"], header["EXPTIME"] = "ELECTRONS/S", 2000.0
    header["PHOTFLAM"], header["PHOTPLAM"] = 7.0723e-20, 8057.0
    data = noise_image(sky=0.0, sigma=0.003)
    image = load_image(write_fits("acs.fits", data, header))
    per_second = -2.5 * math.log10(7.0723e-20) - 5 * math.log10(8057.0) - 2.408
    assert image.zeropoint == pytest.approx(per_second, abs=1e-3) and image.zeropoint == pytest.approx(25.94, abs=0.01)
    header["BUNIT"] = "ELECTRONS"  # per image: plus 2.5 log10(EXPTIME)
    image = load_image(write_fits("acs_e.fits", noise_image(sky=0.0, sigma=6.0), header))
    assert image.zeropoint == pytest.approx(per_second + 2.5 * math.log10(2000.0), abs=1e-3)


# --------------------------------------------------------------------------- implausible zero points


@pytest.mark.parametrize("zp, pattern", [
    (100.0, r"zero point 100 \(--zp\) looks implausible: it puts the sky noise of one pixel \(sigma (0\.99|1\.0)\d* "
            r"image units\) at 100\.0 mag, while real images lie between 10 and 40 mag"),
    (-5.0, r"zero point -5 \(--zp\) looks implausible: it puts the sky noise of one pixel .* at -5\.0 mag"),
])
def test_implausible_zero_point_warns(write_fits, zp, pattern):
    path = write_fits("img.fits", noise_image(), wcs_header())
    with pytest.warns(UserWarning, match=pattern) as record:
        image = load_image(path, zp=zp)
    assert image.zeropoint == zp  # a warning, not a refusal
    assert image.warnings == [str(record[0].message)]


@pytest.mark.parametrize("zp, sigma, bunit", [
    (27.0, 1.0, None), (30.2, 9.0, "adu"), (0.0, 4e-12, None), (22.5, 0.02, None), (8.9, 1e-7, "Jy"),
])
def test_plausible_zero_points_are_quiet(write_fits, zp, sigma, bunit):
    header = wcs_header()
    if bunit:
        header["BUNIT"] = bunit
    path = write_fits("img.fits", noise_image(sky=0.0, sigma=sigma), header)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_image(path, zp=zp).zeropoint == zp


def test_zero_point_against_counts_and_flux_units(write_fits):
    header = wcs_header()
    header["BUNIT"] = "ADU/s"  # sigma 0.001: 5 - 2.5 log10(0.001) = 12.5 mag passes the noise rule ...
    path = write_fits("rate.fits", noise_image(sky=0.0, sigma=0.001), header)
    with pytest.warns(UserWarning, match=r"the image is in ADU/s, whose zero points lie between 10 and 40"):
        load_image(path, zp=5.0)  # ... but no detector in counts has a zero point of 5
    header["BUNIT"] = "nanomaggies"
    path = write_fits("nmgy.fits", noise_image(sky=0.0, sigma=0.05), header)
    with pytest.warns(UserWarning, match=r"BUNIT 'nanomaggies' gives an AB zero point of 22\.500, 7\.5 mag away"):
        load_image(path, zp=30.0)


# --------------------------------------------------------------------------- WCS: TNX, ZPX, astropy's warnings


def tnx_header(zp=25.0, projection="TNX"):
    header = wcs_header(zp=zp, pixel_scale=0.26, rotation_deg=10.0)
    header["CTYPE1"], header["CTYPE2"] = f"RA---{projection}", f"DEC--{projection}"
    header["WAT0_001"] = "system=image"
    # wcslib cannot parse these (it stops with "Internal error in wcslib header parser")
    header["WAT1_001"] = 'wtype=tnx axtype=ra lngcor = "3. 2. 2. 0. -1. 1. -1. 1. 0.0 0.001 0.002 "'
    header["WAT2_001"] = 'wtype=tnx axtype=dec latcor = "3. 2. 2. 0. -1. 1. -1. 1. 0.0 0.001 0.002 "'
    if projection == "ZPX":
        header["PV2_1"] = 1.0  # ZPN radial term: r = theta
    return header


@pytest.mark.parametrize("projection, plain", [("TNX", "TAN"), ("ZPX", "ZPN")])
def test_iraf_distortion_wcs_is_read_plain_with_a_warning(write_fits, projection, plain):
    path = write_fits("tnx.fits", noise_image(), tnx_header(projection=projection))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        image = load_image(path)
    assert [w.category for w in caught] == [UserWarning]  # one line, no astropy warnings
    message = str(caught[0].message)
    assert re.search(rf"the WCS is IRAF {projection} \({plain} plus polynomial distortion terms in WAT keywords\), "
                     rf"whose distortion astropy cannot evaluate: it is read as plain {plain}, so the ra/dec of "
                     rf"catalog entries can be off by up to arcseconds", message)
    assert list(image.wcs.wcs.ctype) == [f"RA---{plain}", f"DEC--{plain}"]
    assert image.wcs_note in message and image.facts()["wcs_note"] == image.wcs_note
    assert image.pixel_scale == pytest.approx(0.26, rel=1e-3)
    assert "IRAF distortion terms ignored" in image.provenance["pixel_scale"]


def test_harmless_wcs_fixes_stay_quiet_and_others_make_one_line(write_fits):
    header = wcs_header(zp=25.0)
    header["DATE-OBS"], header["RADECSYS"] = "2012-01-01", "FK5"  # 'datfix' and a deprecated keyword
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_image(write_fits("dated.fits", noise_image(), header))
    header["CTYPE1"], header["CTYPE2"] = "RA---TAN-SIP", "DEC--TAN-SIP"  # SIP and SCAMP's PV terms together
    header["A_ORDER"], header["B_ORDER"], header["A_2_0"], header["B_0_2"] = 2, 2, 1e-6, 1e-6
    header["PV1_1"], header["PV2_1"], header["PV1_5"] = 1.0, 1.0, 1e-4
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        image = load_image(write_fits("sip.fits", noise_image(), header))
    assert [w.category for w in caught] == [UserWarning]
    assert re.search(r"sip\.fits': astropy had to fix the WCS header: Removed redundant SCAMP distortion parameters "
                     r"because SIP parameters are also present$", str(caught[0].message))
    assert image.wcs is not None and image.wcs_note.startswith("astropy had to fix")


def test_unreadable_wcs_with_a_pixel_scale_is_one_line(write_fits):
    header = wcs_header(zp=25.0)
    header["CTYPE1"], header["CTYPE2"] = "RA---ZPN", "DEC--ZPN"  # ZPN without its PV terms: wcslib refuses
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        image = load_image(write_fits("zpn.fits", noise_image(), header), pixel_scale=0.2)
    assert [w.category for w in caught] == [UserWarning]  # not astropy's FITSFixedWarning
    assert re.search(r"the WCS in the header of .*zpn\.fits' cannot be read \(ERROR 5 in wcsset\(\).*\); it is "
                     r"ignored, so the catalogs have no sky positions", str(caught[0].message))
    assert image.wcs is None and image.pixel_scale == 0.2


def test_unreadable_wcs_is_named_in_the_pixel_scale_error(write_fits):
    header = wcs_header(zp=25.0)
    header["CTYPE1"], header["CTYPE2"] = "RA---ZPN", "DEC--ZPN"
    header["PV2_1"], header["PV2_2"] = 0.0, 0.0  # a ZPN polynomial that is zero everywhere
    path = write_fits("zpn.fits", noise_image(), header)
    with pytest.raises(InputError, match=r"the WCS in the header of .*zpn\.fits' cannot be read \(.*\), so its pixel "
                                         r"scale is unknown; fix the WCS keywords or pass --pixel-scale"):
        load_image(path)


def test_broken_header_card_becomes_one_line(write_fits, tmp_path):
    path = write_fits("card.fits", noise_image(), wcs_header(zp=25.0))
    raw = bytearray(path.read_bytes())
    at = raw.find(b"MAGZERO")
    raw[at:at + 80] = b"BADVAL  = 12.3.4 / a broken number".ljust(80)  # in place of MAGZERO
    path.write_bytes(bytes(raw))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_image(path, zp=25.0)
    assert len(caught) == 1 and caught[0].category is UserWarning
    assert re.search(r"astropy reported 1 problem\(s\) reading the header of .*card\.fits' and fixed or ignored them: "
                     r"Card 'BADVAL' is not FITS standard", str(caught[0].message))


# --------------------------------------------------------------------------- real images (../shared/data)


@pytest.mark.realdata
def test_real_jwst_zero_point_and_gain_from_the_header(shared_data):
    image = load_image(shared_data / "jwst" / "jwst_nircam_f200w_a2744_glass_sci.fits")
    # README: ZP 28.03 (MJy/sr with this pixel area); PIXAR_SR = 2.23e-14 gives 28.0293
    assert image.zeropoint == pytest.approx(28.03, abs=0.005)
    assert image.provenance["zeropoint"] == "BUNIT 'MJy/sr' and image header PIXAR_SR"
    # a flux unit, sky subtracted (observed level 0.4 sigma): no gain, said so
    assert image.gain is None and image.gain_decision["measured"] is None
    assert "flux unit" in image.gain_decision["reason"] and "sky was subtracted" in image.gain_decision["reason"]
    assert image.warnings == []


@pytest.mark.realdata
@pytest.mark.parametrize("band, magzero", [("g", 29.787), ("r", 30.212), ("z", 29.837)])
def test_real_decam_magzpt_per_second_gives_magzero(shared_data, tmp_path, band, magzero):
    src = shared_data / "decam" / f"decam_{band}_S10_200px_ooi.fits"
    with fits.open(src) as hdul:
        hdul = fits.HDUList([h.copy() for h in hdul])
    del hdul[0].header["MAGZERO"]  # only the per-second MAGZPT and EXPTIME = 90 s are left
    hdul.writeto(tmp_path / "magzpt.fits")
    image = load_image(tmp_path / "magzpt.fits")
    assert image.zeropoint == pytest.approx(magzero, abs=0.001)
    assert image.provenance["zeropoint"] == "primary header MAGZPT (per second) + 2.5 log10(EXPTIME)"


@pytest.mark.realdata
def test_real_decam_gain_is_measured_and_checked(shared_data, tmp_path):
    src = shared_data / "decam" / "decam_r_S10_200px_ooi.fits"
    image = load_image(src)
    # No GAIN keyword (BUNIT 'adu'): no photon noise, but the sky (not subtracted, 33 sigma) measures one:
    # observed 3.68 e-/ADU, DECam's amplifiers are about 4.
    assert image.gain is None
    assert 2.5 < image.gain_decision["measured"] < 5.5
    assert "pass --gain" in image.gain_decision["reason"]
    for header_gain, kept in ((4.0, True), (40.0, False)):
        with fits.open(src) as hdul:
            hdul = fits.HDUList([h.copy() for h in hdul])
        hdul[0].header["GAIN"] = header_gain
        hdul.writeto(tmp_path / f"gain{header_gain:g}.fits")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            image = load_image(tmp_path / f"gain{header_gain:g}.fits")
        if kept:
            assert image.gain == 4.0 and not caught
        else:
            assert image.gain == pytest.approx(image.gain_decision["measured"]) and image.gain_decision["contradicted"]
            assert len(caught) == 1 and "contradicts the image" in str(caught[0].message)


@pytest.mark.realdata
def test_real_kids_maggies_zero_point_zero_is_plausible(shared_data):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # sky noise 4e-12 maggies: zero point 0 puts it at 28.4 mag
        image = load_image(shared_data / "kids" / "kidsviking_waves_2600px_r.fits", pixel_scale=0.2, zp=0.0)
    assert image.gain is None and "sky was subtracted" in image.gain_decision["reason"]
    with pytest.warns(UserWarning, match=r"zero point 25 \(--zp\) looks implausible: .* at 53\.\d mag"):
        load_image(shared_data / "kids" / "kidsviking_waves_2600px_r.fits", pixel_scale=0.2, zp=25.0)


def test_a_stored_header_is_rebuilt_without_repeating_astropys_fixes():
    """A run stores the image's header as text and rebuilds its WCS in every realization and in the fit.
    Astropy's fixes (here 'obsfix', from OBSGEO-X/Y/Z as on JWST images) were judged when the image was
    read; a rebuild must not print them again, and must give the same WCS."""
    from astropy.wcs import WCS

    from comest_bayes.bayes.posterior import CompletenessPosterior
    from comest_bayes.io.image import wcs_from_stored_header

    h = fits.Header()
    for key, value in (("CTYPE1", "RA---TAN"), ("CTYPE2", "DEC--TAN"), ("CRVAL1", 3.5), ("CRVAL2", -30.4),
                       ("CRPIX1", 5.0), ("CRPIX2", 5.0), ("CDELT1", -1e-5), ("CDELT2", 1e-5),
                       ("OBSGEO-X", -1e8), ("OBSGEO-Y", 1e9), ("OBSGEO-Z", 5e8), ("MJD-OBS", 59000.0)):
        h[key] = value
    text = h.tostring()
    with warnings.catch_warnings(record=True) as direct:
        warnings.simplefilter("always")
        reference = WCS(fits.Header.fromstring(text), relax=True)
    assert any("obsfix" in str(w.message) for w in direct)  # the header does trigger the fix
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rebuilt = wcs_from_stored_header(text)
        via_posterior = CompletenessPosterior.__new__(CompletenessPosterior)
        via_posterior.wcs_header = text
        from_posterior = via_posterior.wcs
    for w in (rebuilt, from_posterior):
        assert np.allclose(w.pixel_to_world_values(1.0, 2.0), reference.pixel_to_world_values(1.0, 2.0), rtol=0,
                           atol=1e-12)
