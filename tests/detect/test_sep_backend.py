"""SEP detection with SExtractor's semantics, on synthetic images with known truth.

Synthetic skies: point sources of known position and flux (Gaussian: exact
pixel integrals; Moffat: GalSim) on a flat sky with white Gaussian noise of
known sigma, every random draw from a fixed seed (see ``conftest.py``).
"""

import functools
import math

import numpy as np
import pytest
import sep
from scipy.spatial import cKDTree

from comest_bayes.detect.catalog import DETECTION_COLUMNS, FLAG_EDGE, FLAG_MASKED, FLAG_SATURATED
from comest_bayes.config import DetectionConfig
from comest_bayes.detect.sep_backend import detect, detect_array, filter_kernel
from comest_bayes.errors import ConfigError, DetectionOverflowError, InputError
from comest_bayes.io.image import load_image
from conftest import FWHM_PER_SIGMA, render_point_sources, write_fits_file

ZP = 25.0


@pytest.fixture(autouse=True)
def restore_sep_limits():
    """SEP keeps its buffer sizes per process; put them back after each test."""
    pixstack, sublimit = sep.get_extract_pixstack(), sep.get_sub_object_limit()
    yield
    sep.set_extract_pixstack(pixstack)
    sep.set_sub_object_limit(sublimit)


def match(truth_x, truth_y, catalog, xcol="x", ycol="y"):
    """Nearest detection of every true source: (distance, index into catalog)."""
    tree = cKDTree(np.c_[catalog[xcol], catalog[ycol]])
    return tree.query(np.c_[truth_x, truth_y])


def true_mag(flux):
    return ZP - 2.5 * np.log10(flux)


# --------------------------------------------------------------------------- completeness, purity, positions


@pytest.mark.parametrize("psf", ["gaussian", "moffat"])
def test_isolated_sources_are_detected_and_located(make_sky, psf):
    # 49 sources on a 32-px jittered grid (>= 16 px apart), matched-filter SNR 5-300, FWHM 3 px.
    sky = make_sky(psf=psf, seed=1, snr_range=(5.0, 300.0))
    result = detect_array(sky.data, zeropoint=ZP)
    cat = result.catalog
    dist, idx = match(sky.x, sky.y, cat)
    bright = sky.snr >= 10
    # Every source with SNR >= 10 is found: its nearest detection lies within FWHM/2 = 1.5 px.
    # (The isophotal barycentre of an SNR-10 source scatters by >= sqrt(2) sigma_psf / SNR =
    # 0.18 px per axis, the Cramer-Rao bound for a Gaussian, more for the Moffat: observed
    # largest offsets 0.58 px (Gaussian) and 0.83 px (Moffat).  A 0.3 px tolerance is only
    # meaningful at higher SNR, below.)
    assert np.all(dist[bright] < 1.5), dist[bright].max()
    # ... and each by a different detection (no two true sources merged into one).
    assert len(set(idx[bright])) == bright.sum()
    # Positions: windowed centroids of SNR >= 30 sources within 0.3 px (per-axis scatter
    # ~0.06 px for the Gaussian, ~0.08 px for the broader Moffat: > 3.5 sigma radially;
    # observed largest offsets 0.12 and 0.13 px).
    good = sky.snr >= 30
    assert good.sum() >= 20  # premise: enough sources for the statements below
    dwin = np.hypot(cat["xwin"][idx] - sky.x, cat["ywin"][idx] - sky.y)
    assert np.all(dwin[good] < 0.3), dwin[good].max()
    # 0-based pixel coordinates: no systematic offset (a 1-based catalog would be off by 1 px).
    for col, truth in (("x", sky.x), ("y", sky.y), ("xwin", sky.x), ("ywin", sky.y)):
        bias = np.mean(cat[col][idx][good] - truth[good])
        assert abs(bias) < 0.05, (col, bias)  # mean of >= 20 offsets of <= 0.08 px scatter
    # Without a WCS there are no sky coordinates.
    assert np.all(np.isnan(cat["ra"])) and np.all(np.isnan(cat["dec"]))


def test_no_false_detections_at_high_snr(make_sky):
    # A lowered threshold (0.8 sigma) lets noise peaks through, so purity is actually tested:
    # those spurious detections must all have a low measured SNR.
    sky = make_sky(seed=2, snr_range=(5.0, 300.0))
    cat = detect_array(sky.data, zeropoint=ZP, config=DetectionConfig(thresh=0.8)).catalog
    dist, _ = cKDTree(np.c_[sky.x, sky.y]).query(np.c_[cat["x"], cat["y"]])
    spurious = dist > 2.0
    assert spurious.sum() >= 5  # premise: the noise did produce false detections
    # A noise peak's Kron-aperture SNR is a few sigma at most (observed: 17 spurious detections,
    # largest snr_auto 4.1); 6 sigma in pure Gaussian noise has probability ~1e-9 per aperture.
    assert np.all(cat["snr_auto"][spurious] < 6.0), cat["snr_auto"][spurious].max()
    # With the default threshold (1.5 sigma of the unfiltered noise = 4 sigma of the filtered
    # noise for default.conv) white noise gives no false detection here at all.
    cat_default = detect_array(sky.data, zeropoint=ZP).catalog
    dist, _ = cKDTree(np.c_[sky.x, sky.y]).query(np.c_[cat_default["x"], cat_default["y"]])
    assert np.all(dist < 2.0)


# --------------------------------------------------------------------------- photometry


def _moffat_kron_loss(beta, kfact=2.5):
    """Magnitude lost outside kfact Kron radii of a Moffat profile (analytic).

    First moment: r_K / alpha = B(3/2, beta - 3/2) (beta - 1), with the enclosed
    fraction 1 - (1 + (R / alpha)^2)^(1 - beta).
    """
    r_kron = math.gamma(1.5) * math.gamma(beta - 1.5) / math.gamma(beta) * (beta - 1)
    enclosed = 1.0 - (1.0 + (kfact * r_kron) ** 2) ** (1.0 - beta)
    return -2.5 * math.log10(enclosed)


@pytest.mark.parametrize("psf", ["gaussian", "moffat"])
def test_auto_magnitudes_of_bright_isolated_sources(make_sky, psf):
    sky = make_sky(psf=psf, seed=1, spacing=40.0, snr_range=(100.0, 400.0))
    cat = detect_array(sky.data, zeropoint=ZP).catalog
    dist, idx = match(sky.x, sky.y, cat)
    assert np.all(dist < 0.5)
    dm = cat["mag_auto"][idx] - true_mag(sky.flux)
    err = cat["magerr_auto"][idx]
    # Kron aperture loss: the AUTO aperture has 2.5 first-moment (Kron) radii, enlarged to the
    # 3.5 minimum when smaller.  For a Gaussian 2.5 r_K = 2.5 sqrt(pi/2) sigma encloses
    # 1 - exp(-2.5^2 pi / 4) = 99.26% (0.008 mag lost); the Moffat (beta=3) wings put
    # 4.2% outside (0.047 mag), see _moffat_kron_loss.  These are upper bounds on the loss.
    if psf == "gaussian":
        loss = -2.5 * math.log10(1.0 - math.exp(-(2.5**2) * math.pi / 4.0))
        assert loss == pytest.approx(0.0080, abs=1e-4)
    else:
        loss = _moffat_kron_loss(3.0)
        assert loss == pytest.approx(0.0470, abs=1e-3)
    # Each source: within 4 of its own 1-sigma errors of [0, loss]; all within 0.1 mag.
    assert np.all(dm > -4 * err) and np.all(dm < loss + 4 * err), (dm, err)
    assert np.all(np.abs(dm) < 0.1)
    # The mean over 36 sources (scatter ~0.015 mag each -> 0.003 on the mean) sits in
    # [0, loss] within 0.01 mag.
    assert -0.01 < dm.mean() < loss + 0.01, dm.mean()
    if psf == "gaussian":
        assert np.all(np.abs(dm) < 0.05)
    else:
        assert dm.mean() > 0.02  # the Moffat wings do lose light
    # Magnitude errors are consistent with flux errors.
    np.testing.assert_allclose(cat["magerr_auto"], 2.5 / np.log(10) * cat["fluxerr_auto"] / cat["flux_auto"])


def test_aperture_flux_of_a_gaussian(make_sky):
    # PHOT_APERTURES are diameters: a 5-px aperture (radius 2.5 px) around a Gaussian of FWHM
    # 3 px (sigma_eff^2 = sigma^2 + 2/12 with pixelisation) holds 1 - exp(-r^2 / 2 sigma_eff^2).
    sky = make_sky(seed=3, spacing=40.0, snr_range=(200.0, 400.0))
    cat = detect_array(sky.data, zeropoint=ZP).catalog
    _, idx = match(sky.x, sky.y, cat)
    sigma_eff2 = (3.0 / FWHM_PER_SIGMA) ** 2 + 2.0 / 12.0
    expected = 1.0 - np.exp(-(2.5**2) / (2.0 * sigma_eff2))
    frac = cat["flux_aper"][idx, 0] / sky.flux
    assert cat["flux_aper"].shape == (len(cat), 1)
    # 2% tolerance: noise (~0.5% per source at SNR >= 200) and the pixelisation approximation.
    assert np.mean(frac) == pytest.approx(expected, rel=0.02)


def test_flux_radius_of_a_gaussian_is_half_the_fwhm(make_sky):
    # For a Gaussian the half-light radius is exactly FWHM/2 (both are sqrt(2 ln 2) sigma).
    # Pixels widen it: the image holds pixel integrals and the circular-aperture sum spreads each
    # pixel uniformly, adding 1/12 px^2 per axis twice (sigma_eff^2 = sigma^2 + 2/12).  And
    # FLUX_RADIUS is relative to flux_auto, which misses a fraction of the light.
    fwhm = 5.0
    sky = make_sky(seed=3, fwhm=fwhm, spacing=40.0, snr_range=(100.0, 400.0))
    cat = detect_array(sky.data, zeropoint=ZP).catalog
    dist, idx = match(sky.x, sky.y, cat)
    assert np.all(dist < 0.5)
    ratio = cat["flux_radius"][idx] / (fwhm / 2.0)
    sigma = fwhm / FWHM_PER_SIGMA
    missed = 1.0 - np.mean(cat["flux_auto"][idx] / sky.flux)
    r_half = sigma * np.sqrt(1.0 + 2.0 / 12.0 / sigma**2) * np.sqrt(-2.0 * np.log(1.0 - 0.5 * (1.0 - missed)))
    expected = r_half / (fwhm / 2.0)
    assert 1.0 < expected < 1.03  # premise: the corrections are small at FWHM = 5 px
    assert np.mean(ratio) == pytest.approx(1.0, rel=0.03)  # FWHM/2 within 3%
    assert np.mean(ratio) == pytest.approx(expected, rel=0.01)  # and the corrected value within 1%
    assert np.std(ratio) < 0.02


# --------------------------------------------------------------------------- segmentation


def test_segmentation_ids_are_catalog_ids(make_sky):
    sky = make_sky(seed=2, snr_range=(5.0, 300.0))
    result = detect_array(sky.data, zeropoint=ZP, config=DetectionConfig(thresh=0.8))
    cat, seg = result.catalog, result.segmentation
    assert seg.dtype == np.int32 and seg.shape == sky.data.shape
    assert len(cat) > 40
    np.testing.assert_array_equal(cat["id"], np.arange(1, len(cat) + 1))
    assert set(np.unique(seg)) - {0} == set(cat["id"])
    # Each object's segment holds its pixels above the threshold in the filtered image; npix
    # (ISOAREA_IMAGE) counts those of them that are above threshold in the unfiltered image too.
    counts = np.bincount(seg.ravel(), minlength=len(cat) + 1)[1:]
    assert np.all(cat["npix"] <= counts) and np.all(cat["npix"] >= 0)
    assert np.median(cat["npix"] / counts) > 0.3
    # ... and covers the true position of the bright sources it was matched to.
    dist, idx = match(sky.x, sky.y, cat)
    ok = (sky.snr >= 10) & (dist < 1.0)
    ys, xs = np.round(sky.y[ok]).astype(int), np.round(sky.x[ok]).astype(int)
    np.testing.assert_array_equal(seg[ys, xs], cat["id"][idx[ok]])


def test_blended_pair_is_deblended_and_flagged():
    rng = np.random.default_rng(7)
    model = render_point_sources((96, 96), [44.0, 50.0], [48.0, 48.5], [20000.0, 12000.0], fwhm=3.0)
    data = (100.0 + model + rng.normal(0.0, 5.0, model.shape)).astype(np.float32)
    result = detect_array(data, zeropoint=ZP)
    cat = result.catalog
    assert len(cat) == 2
    assert np.all(cat["flags"] & 2)  # FLAGS bit 2: deblended from a blend
    np.testing.assert_allclose(np.sort(cat["x"]), [44.0, 50.0], atol=0.3)
    # Deblending off: one merged object covering both.
    merged = detect_array(data, zeropoint=ZP, config=DetectionConfig(deblend_mincont=1.0)).catalog
    assert len(merged) == 1 and merged["npix"][0] == cat["npix"].sum()


# --------------------------------------------------------------------------- threshold semantics


def _flat_patch_image(amplitude, kind, seed=3, n=128, sky=100.0, sigma=5.0, half=10):
    """Noise everywhere except a noise-free (2*half+1)^2 patch at the centre holding one feature.

    ``plateau``: a 5x5 block of ``amplitude`` above the sky; after the normalised 3x3
    default.conv its central 3x3 pixels still hold exactly ``amplitude`` and its edge pixels
    0.75 of it (the 1-D kernel is [1, 2, 1]/4).  ``spike``: a single pixel; its filtered
    value is 4/16 of ``amplitude``.
    """
    rng = np.random.default_rng(seed)
    data = sky + rng.normal(0.0, sigma, (n, n))
    c = n // 2
    data[c - half:c + half + 1, c - half:c + half + 1] = sky
    if kind == "plateau":
        data[c - 2:c + 3, c - 2:c + 3] += amplitude
    else:
        data[c, c] += amplitude
    return data.astype(np.float32), c


@pytest.mark.parametrize("thresh", [1.5, 3.0])
@pytest.mark.parametrize("kind, filtered_peak_per_amplitude, minarea", [("plateau", 1.0, 5), ("spike", 0.25, 1)])
@pytest.mark.parametrize("factor", [0.95, 1.05])
def test_threshold_has_sextractors_meaning(thresh, kind, filtered_peak_per_amplitude, minarea, factor):
    """DETECT_THRESH: filtered (normalised kernel) value > thresh * sigma of the unfiltered noise.

    The feature sits in a noise-free patch of known sky, so its filtered peak is known exactly.
    A "matched" threshold (relative to the filtered noise, 0.375 sigma for default.conv) would
    detect the 0.95 cases; an unfiltered threshold would detect the 0.95 spike (3.8 T).
    """
    sigma = 5.0
    amplitude = factor * thresh * sigma / filtered_peak_per_amplitude
    data, c = _flat_patch_image(amplitude, kind, sigma=sigma)
    config = DetectionConfig(thresh=thresh, minarea=minarea, noise="global")
    result = detect_array(data, zeropoint=ZP, config=config)
    noise = float(result.noise[c, c])
    # The global RMS is the noise sigma (the patch is 2.7% of the image; 5% tolerance).
    assert noise == pytest.approx(sigma, rel=0.05)
    assert noise == result.meta["globrms"]
    # The realised margin: filtered peak above the estimated background, over thresh * noise.
    peak = filtered_peak_per_amplitude * amplitude + (100.0 - float(result.background[c, c]))
    margin = peak / (thresh * noise)
    assert abs(margin - 1.0) > 0.01  # premise: not a knife-edge case
    detected = result.segmentation[c, c] != 0
    assert detected == (margin > 1.0), (margin, detected)
    assert detected == (factor > 1.0)


def test_minarea_counts_pixels_above_threshold():
    # At 1.05 T the 5x5 plateau has exactly 9 filtered pixels above threshold (its edges are at
    # 0.75 * 1.05 T < T): DETECT_MINAREA 9 keeps it, 10 drops it.
    data, c = _flat_patch_image(1.05 * 1.5 * 5.0, "plateau")
    keep = detect_array(data, zeropoint=ZP, config=DetectionConfig(minarea=9, noise="global"))
    drop = detect_array(data, zeropoint=ZP, config=DetectionConfig(minarea=10, noise="global"))
    assert keep.segmentation[c, c] != 0
    assert keep.catalog["npix"][keep.segmentation[c, c] - 1] == 9
    assert drop.segmentation[c, c] == 0


# --------------------------------------------------------------------------- noise modes


@pytest.fixture(scope="module")
def two_noise_image():
    """Left half sigma 4, right half sigma 8, eight equal bright sources (four per half)."""
    ny, nx = 192, 384
    rng = np.random.default_rng(11)
    sigma = np.where(np.arange(nx)[None, :] >= nx // 2, 8.0, 4.0) * np.ones((ny, 1))
    xs = np.array([48, 144, 240, 336, 48, 144, 240, 336], float) + 0.3
    ys = np.array([48, 48, 48, 48, 144, 144, 144, 144], float) + 0.2
    model = render_point_sources((ny, nx), xs, ys, np.full(8, 3000.0), fwhm=3.0)
    data = (50.0 + model + rng.normal(0.0, 1.0, (ny, nx)) * sigma).astype(np.float32)
    return data, sigma.astype(np.float32), xs, ys


@pytest.mark.parametrize("mode", ["global", "background", "weight"])
def test_noise_modes(two_noise_image, mode):
    data, sigma, xs, ys = two_noise_image
    nx = data.shape[1]
    left, right = slice(0, nx // 2 - 40), slice(nx // 2 + 40, nx)  # 40 px away from the step
    config = DetectionConfig(noise=mode, thresh=1.0, back_size=32)
    result = detect_array(data, weight_noise=sigma if mode == "weight" else None, zeropoint=ZP, config=config)
    cat = result.catalog
    assert result.meta["noisemod"] == mode
    dist, idx = match(xs, ys, cat)
    assert np.all(dist < 0.5)  # the bright sources are found in every mode
    src_noise = np.asarray(cat["noise"][idx])
    n_left = int(np.sum(cat["x"] < nx // 2))
    n_right = len(cat) - n_left
    if mode == "global":
        # One number everywhere: the global RMS (between 4 and 8).
        assert np.ptp(result.noise) == 0.0 and 4.0 < result.noise[0, 0] < 8.0
        np.testing.assert_array_equal(src_noise, result.meta["globrms"])
        # So the noisy half, thresholded too low, is full of noise peaks (observed 51 vs 4).
        assert n_right > 5 * n_left, (n_left, n_right)
    else:
        # A per-pixel sigma: the noisy half gets a twice higher absolute threshold.
        rel = 1e-6 if mode == "weight" else 0.05  # weight: exact shape; background: measured in meshes
        assert np.median(result.noise[:, left]) == pytest.approx(4.0, rel=0.05)
        assert np.median(result.noise[:, right]) == pytest.approx(8.0, rel=0.05)
        ratio = src_noise[xs > nx // 2].mean() / src_noise[xs < nx // 2].mean()
        assert ratio == pytest.approx(2.0, rel=rel)
        # ... so spurious detections are as rare on both sides (observed 7/7 and 6/6, four
        # real sources per side; the tolerance allows Poisson scatter of a few).
        assert abs(n_right - n_left) <= 5, (n_left, n_right)
    if mode == "weight":
        # The weight map fixes the shape of the noise, the image its level (MAP_WEIGHT):
        # the median of the per-pixel ratio of the rescaled map to the measured background RMS is 1.
        np.testing.assert_allclose(result.noise / sigma, (result.noise / sigma)[0, 0], rtol=1e-6)
        assert np.median(result.noise / result.rms) == pytest.approx(1.0, rel=1e-5)


def test_auto_noise_mode_picks_weight_when_given(two_noise_image):
    data, sigma, _, _ = two_noise_image
    assert detect_array(data, weight_noise=sigma, zeropoint=ZP).meta["noisemod"] == "weight"
    assert detect_array(data, zeropoint=ZP).meta["noisemod"] == "background"


def test_weight_mode_without_a_weight_map():
    data, _ = _flat_patch_image(0.0, "spike")
    with pytest.raises(ConfigError, match=r"needs a weight map; pass --weight FILE"):
        detect_array(data, zeropoint=ZP, config=DetectionConfig(noise="weight"))


# --------------------------------------------------------------------------- masks and flags


def test_mask_excludes_detections_in_the_masked_region(make_sky):
    sky = make_sky(seed=4, snr_range=(50.0, 300.0))
    mask = np.zeros(sky.data.shape, bool)
    mask[:, :100] = True
    # One more bright source straddling the mask edge.
    edge_src = render_point_sources(sky.data.shape, [102.0], [230.0], [20000.0], fwhm=3.0)
    data = sky.data + edge_src.astype(np.float32)
    result = detect_array(data, mask=mask, zeropoint=ZP)
    cat, seg = result.catalog, result.segmentation
    assert np.all(seg[mask] == 0)
    assert np.all(cat["x"] >= 100.0 - 0.5)
    outside = sky.x >= 105.0
    dist, _ = match(sky.x[outside], sky.y[outside], cat)
    assert np.all(dist < 1.0)  # everything outside is still found
    assert len(cat) == outside.sum() + 1  # ... and nothing inside
    d_edge, i_edge = match([102.0], [230.0], cat)
    assert d_edge[0] < 1.5 and cat["flags"][i_edge[0]] & FLAG_MASKED
    # Without the mask the sources inside are found too.
    assert len(detect_array(data, zeropoint=ZP).catalog) > len(cat)


def test_unmasked_nan_is_refused():
    data, _ = _flat_patch_image(0.0, "spike")
    data[5, 5] = np.nan
    with pytest.raises(InputError, match="mask them first"):
        detect_array(data, zeropoint=ZP)
    mask = np.zeros(data.shape, bool)
    mask[5, 5] = True
    assert detect_array(data, mask=mask, zeropoint=ZP).segmentation[5, 5] == 0


def test_saturation_and_edge_flags():
    rng = np.random.default_rng(8)
    model = render_point_sources((96, 96), [30.0, 70.0, 1.0], [40.0, 40.0, 60.0], [50000.0, 5000.0, 8000.0],
                                 fwhm=3.0)
    data = (100.0 + model + rng.normal(0.0, 5.0, model.shape)).astype(np.float32)
    saturation = 100.0 + 0.5 * model[40, 30]  # the first source's peak pixel exceeds it
    cat = detect_array(data, zeropoint=ZP, saturation=saturation).catalog
    _, (i_sat, i_ok, i_edge) = match([30.0, 70.0, 1.0], [40.0, 40.0, 60.0], cat)
    assert cat["flags"][i_sat] & FLAG_SATURATED and not cat["flags"][i_ok] & FLAG_SATURATED
    assert cat["flags"][i_edge] & FLAG_EDGE and not cat["flags"][i_ok] & FLAG_EDGE


def test_conv_file_is_parsed_and_normalised(tmp_path):
    path = tmp_path / "my.conv"
    path.write_text("CONV NORM\n# a 3x5 kernel, SExtractor format\n"
                    "0 1 2 1 0\n1 2 4 2 1   # trailing comment\n0 1 2 1 0\n\n")
    kernel = filter_kernel(str(path))
    expected = np.array([[0, 1, 2, 1, 0], [1, 2, 4, 2, 1], [0, 1, 2, 1, 0]], float)
    np.testing.assert_allclose(kernel, expected / expected.sum(), rtol=1e-6)
    # The kernel is used: a detection with it runs (SEP needs a C-contiguous float32 kernel).
    data, c = _flat_patch_image(10.0, "plateau")
    result = detect_array(data, zeropoint=ZP, config=DetectionConfig(filter=str(path), noise="global"))
    assert result.segmentation[c, c] != 0


def test_filter_none_disables_filtering():
    assert filter_kernel("none") is None
    # Unfiltered, a single-pixel spike of 1.05 T is detected (filtered it would be 0.26 T).
    data, c = _flat_patch_image(1.05 * 1.5 * 5.0, "spike")
    result = detect_array(data, zeropoint=ZP, config=DetectionConfig(filter="none", minarea=1, noise="global"))
    margin = (1.05 * 1.5 * 5.0 + 100.0 - result.background[c, c]) / (1.5 * result.noise[c, c])
    assert (result.segmentation[c, c] != 0) == (margin > 1.0)


def test_object_aligned_with_the_y_axis_is_measured():
    # Regression: a vertical two-pixel object has theta = float32(pi/2), which is larger than
    # pi/2 in float64; sep.sum_ellipse used to reject it ("invalid aperture parameters").
    data, c = _flat_patch_image(0.0, "spike")
    data[c:c + 2, c] += 3.0 * 1.5 * 5.0
    result = detect_array(data, zeropoint=ZP, config=DetectionConfig(filter="none", minarea=2, noise="global"))
    obj = result.catalog[result.segmentation[c, c] - 1]
    assert obj["npix"] == 2
    assert abs(obj["theta"]) == pytest.approx(np.pi / 2, abs=1e-6) and abs(obj["theta"]) <= np.pi / 2
    assert obj["y"] == pytest.approx(c + 0.5, abs=1e-3) and obj["x"] == pytest.approx(c, abs=1e-3)
    assert np.isfinite(obj["flux_auto"]) and obj["flux_auto"] > 0


def test_an_object_without_a_shape_is_measured_in_the_circle_of_its_area(monkeypatch):
    # Found by a new user on a demo tile without its weight map: a faint object's second moments were negative
    # (x2 = -3.5), SEP gave b = NaN, and sep.sum_ellipse aborted the run ("invalid aperture parameters").
    import comest_bayes.detect.sep_backend as S

    data, c = _flat_patch_image(0.0, "spike")
    data[c - 1:c + 2, c - 1:c + 2] += 3.0 * 1.5 * 5.0
    real = S.sep.extract
    seen = {}

    def extract(*args, **kwargs):
        out = real(*args, **kwargs)
        objs = out[0] if isinstance(out, tuple) else out
        objs["b"][:] = np.nan  # as SEP gives for negative second moments
        seen["npix"] = np.array(objs["npix"], float)
        return out

    monkeypatch.setattr(S.sep, "extract", extract)
    result = detect_array(data, zeropoint=ZP, config=DetectionConfig(filter="none", minarea=2, noise="global"))
    obj = result.catalog[result.segmentation[c, c] - 1]
    radius = np.sqrt(seen["npix"][result.segmentation[c, c] - 1] / np.pi)
    assert obj["a"] == pytest.approx(radius) and obj["b"] == pytest.approx(radius) and obj["theta"] == 0.0
    assert np.isfinite(obj["flux_auto"]) and obj["flux_auto"] > 0 and np.isfinite(obj["mag_auto"])


# --------------------------------------------------------------------------- buffer overflows


def test_pixel_stack_overflow_is_retried():
    # One 60-px FWHM blob: ~18000 pixels above threshold, more than a 10000-pixel stack.
    rng = np.random.default_rng(5)
    blob = render_point_sources((256, 256), [128.2], [127.6], [3e6], fwhm=60.0)
    data = (100.0 + blob + rng.normal(0.0, 5.0, blob.shape)).astype(np.float32)
    result = detect_array(data, zeropoint=ZP, config=DetectionConfig(pixstack=10_000))
    assert len(result.catalog) == 1
    assert result.catalog["npix"][0] > 10_000  # premise: the first attempt had to overflow
    assert result.meta["pixstack"] == data.size  # the retry used a stack as large as the image


def _crowded(nstars, n, seed=5):
    """Stars (FWHM 2.5 px) on a broad bright halo, so that all are one connected blend."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, n, nstars), rng.uniform(0, n, nstars)
    stars = render_point_sources((n, n), x, y, rng.uniform(2000.0, 20000.0, nstars), fwhm=2.5)
    halo = render_point_sources((n, n), [n / 2], [n / 2], [3e6], fwhm=60.0)
    return (100.0 + halo + stars + rng.normal(0.0, 5.0, (n, n))).astype(np.float32)


def test_sub_object_overflow_is_retried_with_a_larger_limit():
    data = _crowded(600, 256)
    small = detect_array(data, zeropoint=ZP, config=DetectionConfig(sub_object_limit=64))
    assert small.meta["subobj"] == 256  # 64 overflowed; the retry used 4 x 64
    default = detect_array(data, zeropoint=ZP)
    assert default.meta["subobj"] == 4096
    # The retry gives the same catalog as a run that never overflowed.
    assert len(small.catalog) == len(default.catalog) > 100
    np.testing.assert_allclose(small.catalog["x"], default.catalog["x"])


def test_persistent_overflow_raises_a_clear_error():
    data = _crowded(1500, 200)
    with pytest.raises(DetectionOverflowError,
                       match=r"sub-object limit of 256 .*deblending.*too crowded.*raise detection\.thresh"
                             r".*detection\.sub_object_limit"):
        detect_array(data, zeropoint=ZP, config=DetectionConfig(sub_object_limit=64))
    # The same image with SEP's normal limits is fine.
    assert len(detect_array(data, zeropoint=ZP).catalog) > 50


def test_other_sep_errors_are_not_disguised(monkeypatch):
    def broken(*args, **kwargs):
        raise Exception("some other SEP failure")

    monkeypatch.setattr(sep, "extract", broken)
    data, _ = _flat_patch_image(0.0, "spike")
    with pytest.raises(Exception, match="some other SEP failure") as info:
        detect_array(data, zeropoint=ZP)
    assert not isinstance(info.value, DetectionOverflowError)


# --------------------------------------------------------------------------- empty results, dispatch


def test_empty_image_gives_an_empty_catalog_with_all_columns():
    data = (100.0 + np.random.default_rng(9).normal(0.0, 5.0, (128, 128))).astype(np.float32)
    config = DetectionConfig(thresh=50.0, phot_apertures=(4.0, 8.0))
    result = detect_array(data, zeropoint=ZP, config=config)
    cat = result.catalog
    assert len(cat) == 0 and result.meta["nobj"] == 0
    assert list(cat.colnames) == list(DETECTION_COLUMNS)
    for name, (dtype, unit, _) in DETECTION_COLUMNS.items():
        assert cat[name].dtype == np.dtype(dtype), name
    assert cat["flux_aper"].shape == (0, 2) and cat["mag_aper"].shape == (0, 2)
    assert not result.segmentation.any()
    assert cat.meta["ZEROPT"] == ZP and cat.meta["THRESH"] == 50.0


def test_detect_dispatches_on_image_data(tmp_path, synthetic_fits):
    made = synthetic_fits(seed=6, snr_range=(30.0, 200.0), spacing=30.0)
    sigma = np.full(made.sky.data.shape, made.sky.sigma, np.float32)
    weight = write_fits_file(tmp_path / "w.fits", 1.0 / sigma**2)
    image = load_image(made.path, weight=weight)
    result = detect(image)
    assert result.meta["noisemod"] == "weight" and result.meta["zeropt"] == made.zeropoint
    cat = result.catalog
    dist, idx = match(made.sky.x, made.sky.y, cat)
    assert np.all(dist < 0.5)
    # ra/dec come from the WCS at the windowed centroid, 0-based.
    ra, dec = image.wcs.all_pix2world(cat["xwin"], cat["ywin"], 0)
    np.testing.assert_allclose(cat["ra"], ra, rtol=0, atol=1e-10)
    np.testing.assert_allclose(cat["dec"], dec, rtol=0, atol=1e-10)
    truth_ra, truth_dec = image.wcs.all_pix2world(made.sky.x, made.sky.y, 0)
    sep_arcsec = np.hypot((cat["ra"][idx] - truth_ra) * np.cos(np.deg2rad(truth_dec)),
                          cat["dec"][idx] - truth_dec) * 3600
    assert np.all(sep_arcsec < 0.3 * made.pixel_scale)
    with pytest.raises(ConfigError, match="detect_array runs SEP"):
        detect_array(image.data, zeropoint=ZP, config=DetectionConfig(backend="sextractor"))


# --------------------------------------------------------------------------- fast path of the realizations


def _crowded_masked_image(seed=12, shape=(320, 288)):
    """Many point sources (some blended, some on the edge) with a masked block holding NaN.

    Returns fresh copies of (data float32, mask, sigma map float32) on every call.
    """
    return tuple(a.copy() for a in _crowded_masked_image_cached(seed, shape))


@functools.lru_cache(maxsize=1)
def _crowded_masked_image_cached(seed, shape):
    rng = np.random.default_rng(seed)
    n = 160
    xs, ys = rng.uniform(-2.0, shape[1] + 1.0, n), rng.uniform(-2.0, shape[0] + 1.0, n)
    model = render_point_sources(shape, xs, ys, 10 ** rng.uniform(2.0, 4.5, n), fwhm=3.0, psf="moffat")
    sigma = np.where(np.arange(shape[1])[None, :] >= shape[1] // 2, 7.0, 4.0) * np.ones((shape[0], 1))
    data = (100.0 + model + rng.normal(0.0, 1.0, shape) * sigma).astype(np.float32)
    mask = np.zeros(shape, bool)
    mask[40:90, 200:260] = True
    data[mask] = np.nan
    return data, mask, sigma.astype(np.float32)


@pytest.mark.parametrize("mode,masked", [("background", True), ("weight", True), ("weight", False),
                                         ("global", True)])
def test_fast_path_gives_the_same_catalog(mode, masked):
    # What recovery.py runs on every realization: no segmentation map, background subtracted in the
    # caller's array, the RMS map used as the noise map without a copy, no finiteness check. The
    # catalog must equal the default path's (the brief asks for 1e-6 relative; the arithmetic is the
    # same, so equality is expected and any difference means the fast path changed what SEP sees).
    data, mask, sigma = _crowded_masked_image()
    if not masked:  # weight mode has a separate branch when every pixel is good
        data, mask = np.where(mask, np.float32(100.0), data), np.zeros_like(mask)
    kw = dict(mask=mask, weight_noise=sigma if mode == "weight" else None, zeropoint=ZP, gain=2.0,
              saturation=2.0e4, config=DetectionConfig(noise=mode, back_size=32))
    original = data.copy()
    ref = detect_array(data, **kw)
    np.testing.assert_array_equal(data, original)  # the default path leaves its input alone
    work = data.copy()
    fast = detect_array(work, segmentation=False, inplace=True, check_finite=False, **kw)
    assert len(ref.catalog) > 100 and np.any(ref.catalog["flags"] & FLAG_EDGE)  # premise: a varied catalog
    assert fast.segmentation is None and ref.segmentation is not None
    assert fast.catalog.colnames == ref.catalog.colnames and len(fast.catalog) == len(ref.catalog)
    for name in ref.catalog.colnames:
        a, b = np.asarray(fast.catalog[name]), np.asarray(ref.catalog[name])
        if a.dtype.kind == "f":
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=0, equal_nan=True, err_msg=name)
        else:
            np.testing.assert_array_equal(a, b, err_msg=name)
    assert fast.meta == ref.meta
    # the work array now holds the background-subtracted image, zero on masked pixels
    expected = np.where(mask, np.float32(0.0), original - ref.background)
    np.testing.assert_allclose(work, expected, rtol=0, atol=1e-3)
    np.testing.assert_array_equal(fast.noise, ref.noise)
    if mode == "background":
        assert fast.noise is fast.rms  # no copy
    # the weight map handed in is never modified
    if mode == "weight":
        np.testing.assert_array_equal(sigma, _crowded_masked_image()[2])


def test_fast_path_keeps_the_input_when_it_cannot_use_it():
    # a float64 or read-only input is copied, so inplace=True never fails and never writes to it
    data, mask, _ = _crowded_masked_image()
    data = np.where(mask, 100.0, data)
    ref = detect_array(data, mask=mask, zeropoint=ZP).catalog
    as64 = data.astype(np.float64)
    readonly = data.copy()
    readonly.setflags(write=False)
    for arr in (as64, readonly):
        before = arr.copy()
        cat = detect_array(arr, mask=mask, zeropoint=ZP, inplace=True, segmentation=False).catalog
        np.testing.assert_array_equal(arr, before)
        np.testing.assert_array_equal(np.asarray(cat["flux_auto"]), np.asarray(ref["flux_auto"]))


def test_fast_path_without_the_check_trusts_the_caller_and_with_it_refuses_nan():
    data, mask, _ = _crowded_masked_image()
    data[5, 7] = np.nan  # unmasked
    with pytest.raises(InputError, match="NaN or infinite values in unmasked pixels"):
        detect_array(data.copy(), mask=mask, zeropoint=ZP, inplace=True)
    with pytest.raises(InputError, match="mask has shape"):
        detect_array(data, mask=mask[:-1], zeropoint=ZP)


def test_sextractor_backend_accepts_the_fast_path_options(tmp_path):
    # detect_with_backend passes the SEP-only options to SEP and drops them for SExtractor, which
    # reads the image from its own file: the input is unchanged and the result the normal one.
    from comest_bayes.detect.sep_backend import detect_with_backend
    from comest_bayes.errors import BackendUnavailableError
    from comest_bayes.detect.sextractor import find_sextractor

    try:
        find_sextractor()
    except BackendUnavailableError:
        pytest.skip("the SExtractor binary is not installed (Debian package source-extractor)")
    data, mask, _ = _crowded_masked_image()
    data = np.where(mask, 100.0, data).astype(np.float32)
    before = data.copy()
    config = DetectionConfig(backend="sextractor", back_size=32)
    fast = detect_with_backend(data, mask=mask, zeropoint=ZP, config=config, workdir=tmp_path,
                               segmentation=False, inplace=True, check_finite=False)
    np.testing.assert_array_equal(data, before)
    ref = detect_with_backend(data, mask=mask, zeropoint=ZP, config=config, workdir=tmp_path)
    assert fast.meta["backend"] == "sextractor" and len(fast.catalog) == len(ref.catalog) > 100
    np.testing.assert_array_equal(np.asarray(fast.catalog["flux_auto"]), np.asarray(ref.catalog["flux_auto"]))


def test_a_given_noise_map_is_the_threshold_sigma_whatever_the_image_holds(two_noise_image):
    # detection.noise_level = "observed": an injected image is thresholded at the observed noise map.
    # Adding bright sources raises the image's measured RMS, but the noise the threshold (and the
    # catalog's noise column) uses stays the given map exactly.
    data, sigma, xs, ys = two_noise_image
    crowded = data + render_point_sources(data.shape, xs + 20.0, ys + 25.0, np.full(8, 3.0e5), fwhm=6.0)
    config = DetectionConfig(thresh=1.0, back_size=32)
    per_image = detect_array(crowded, weight_noise=sigma, zeropoint=ZP, config=config)
    base = detect_array(data, weight_noise=sigma, zeropoint=ZP, config=config)
    # premise: the level moved (observed +0.8%; the weight map is rescaled to the higher measured RMS)
    assert np.median(per_image.noise) > 1.005 * np.median(base.noise)
    given = detect_array(crowded, weight_noise=sigma, threshold_noise=base.noise, zeropoint=ZP, config=config)
    assert given.meta["noisemod"] == "given"
    np.testing.assert_array_equal(given.noise, base.noise)
    assert np.all(np.isin(np.asarray(given.catalog["noise"], np.float32), np.unique(base.noise)))
    # the same map given to the fast path (in place, no segmentation) gives the same catalog
    fast = detect_array(crowded.copy(), threshold_noise=base.noise, zeropoint=ZP, config=config, inplace=True,
                        segmentation=False)
    np.testing.assert_array_equal(np.asarray(fast.catalog["flux_auto"]), np.asarray(given.catalog["flux_auto"]))


def test_a_given_background_map_is_subtracted_as_it_is(two_noise_image):
    # detection.background_level = "observed": the level subtracted is the given map (here the true
    # sky, 50), not one measured in meshes on this image, where bright sources lift it.
    data, sigma, xs, ys = two_noise_image
    crowded = data + render_point_sources(data.shape, xs + 20.0, ys + 25.0, np.full(8, 3.0e5), fwhm=6.0)
    config = DetectionConfig(thresh=1.0, back_size=32)
    sky = np.full(data.shape, 50.0, np.float32)
    measured = detect_array(crowded, weight_noise=sigma, zeropoint=ZP, config=config)
    assert measured.background.max() > 50.5  # premise: the meshes under the bright sources are lifted
    given = detect_array(crowded, threshold_background=sky, threshold_noise=sigma, zeropoint=ZP, config=config)
    np.testing.assert_array_equal(given.background, sky)
    np.testing.assert_array_equal(given.rms, sigma)  # nothing measured: the rms is the given noise
    np.testing.assert_array_equal(np.asarray(given.catalog["background"], np.float32), 50.0)
    assert given.meta["globback"] == 50.0 and given.meta["noisemod"] == "given"
    # the background alone may be given too: the noise is then measured as usual
    alone = detect_array(crowded, threshold_background=sky, weight_noise=sigma, zeropoint=ZP, config=config)
    np.testing.assert_array_equal(alone.background, sky)
    np.testing.assert_array_equal(alone.noise, measured.noise)


def test_sextractor_refuses_a_given_background():
    from comest_bayes.detect.sextractor import detect_sextractor

    with pytest.raises(ConfigError, match=r"background_level='observed' needs detection\.backend='sep'"):
        detect_sextractor(np.zeros((8, 8), np.float32), zeropoint=ZP, threshold_background=np.zeros((8, 8)))
    with pytest.raises(ConfigError, match=r"invalid detection\.background_level = 'observed'.*use the SEP backend"):
        DetectionConfig(backend="sextractor", background_level="observed")
