"""The input boundary: load_image reads any HDU, converts, masks and validates.

Every test writes a small FITS file with known content into ``tmp_path`` and
checks what ``load_image`` returns (or the error it raises, including that the
message names the fix).
"""

import hashlib
import json

import numpy as np
import pytest
import sep
from astropy.io import fits

from comest_bayes.errors import InputError, InputFileError
from comest_bayes.image import GAIN_KEYWORDS, SATURATION_KEYWORDS, ZP_KEYWORDS, ImageData, load_image
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
    with pytest.raises(InputError, match=r"no 2-D image.*cube"):
        load_image(path, pixel_scale=0.2, zp=25.0)


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
    image = load_image(write_fits("zp.fits", noise_image(), header))
    assert image.zeropoint == 26.125
    assert image.provenance["zeropoint"] == f"image header {key}"


def test_zero_point_keyword_order(write_fits):
    # DECam headers carry MAGZERO (per image) and MAGZPT (per second); the first listed wins.
    header = wcs_header()
    header[ZP_KEYWORDS[1]] = 25.3
    header[ZP_KEYWORDS[0]] = 30.2
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
    assert load_image(write_fits("zp.fits", noise_image(), header)).zeropoint == 24.5


@pytest.mark.parametrize("gain_key", GAIN_KEYWORDS)
@pytest.mark.parametrize("sat_key", SATURATION_KEYWORDS[:2])
def test_gain_and_saturation_from_header(write_fits, gain_key, sat_key):
    header = wcs_header(zp=25.0)
    header[gain_key] = 4.25
    header[sat_key] = 61000.0
    path = write_fits("gs.fits", noise_image(), header)
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
    assert load_image(path, zp=0.0).zeropoint == 0.0  # zero is a valid zero point (e.g. maggies)


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
    img = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    with pytest.raises(InputError, match=r"every pixel .* is masked.*--mask-bits"):
        load_image(img, mask=write_fits("m.fits", np.ones(SHAPE, np.int16)))
    with pytest.raises(InputError, match=r"every pixel .* is masked"):
        load_image(write_fits("nan.fits", np.full(SHAPE, np.nan, np.float32), wcs_header(zp=25.0)))
    with pytest.raises(InputError, match=r"every pixel .* is masked.*weight map"):
        load_image(img, weight=write_fits("w.fits", np.zeros(SHAPE, np.float32)))


def test_nearly_all_masked_image(write_fits):
    mvals = np.ones(SHAPE, np.int16)
    mvals[:10, :10] = 0  # 100 usable pixels
    img = write_fits("img.fits", noise_image(), wcs_header(zp=25.0))
    with pytest.raises(InputError, match=r"only 100 usable pixels"):
        load_image(img, mask=write_fits("m.fits", mvals))


def test_constant_image(write_fits):
    data = np.full(SHAPE, 7.0, np.float32)
    data[0, 0] = np.nan  # the constant check looks at the unmasked pixels only
    with pytest.raises(InputError, match=r"is constant \(.*7\.0.*\).*--hdu"):
        load_image(write_fits("const.fits", data, wcs_header(zp=25.0)))


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


def test_input_errors_are_value_errors():
    # Callers that only know the built-ins can still catch these.
    assert issubclass(InputError, ValueError)
