"""What both detection backends share (comest_bayes.detect.base): the filter kernels and the noise map the
threshold is relative to, as known answers without running a detection.
"""

import numpy as np
import pytest

from comest_bayes.detect.base import DEFAULT_CONV, filter_kernel, noise_map, weight_agreement
from comest_bayes.errors import ConfigError
from conftest import FWHM_PER_SIGMA

SEXTRACTOR_SHARE = "/usr/share/source-extractor"


def test_noise_map_fills_masked_pixels_with_the_median():
    rms = np.arange(16, dtype=np.float32).reshape(4, 4) + 1
    mask = np.zeros((4, 4), bool)
    mask[0, 0] = True
    weight = np.full((4, 4), np.inf, np.float32)
    weight[~mask] = 2.0
    out, mode = noise_map("weight", rms, 3.0, weight, mask)
    assert mode == "weight" and np.all(np.isfinite(out))
    scale = np.median(rms[~mask]) / 2.0
    np.testing.assert_allclose(out, 2.0 * scale)


# --------------------------------------------------------------------------- filter kernels


def test_default_kernel_is_sextractors_default_conv():
    kernel = filter_kernel("default")
    assert kernel.shape == (3, 3) and kernel.dtype == np.float32
    assert kernel.sum() == pytest.approx(1.0, abs=1e-7)
    np.testing.assert_allclose(kernel, np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]]) / 16.0, rtol=1e-7)
    np.testing.assert_allclose(kernel, DEFAULT_CONV / 16.0)


def test_default_kernel_equals_the_installed_default_conv():
    path = f"{SEXTRACTOR_SHARE}/default.conv"
    try:
        kernel = filter_kernel(path)
    except ConfigError:
        pytest.skip(f"{path} not installed (Debian package source-extractor)")
    np.testing.assert_allclose(kernel, filter_kernel("default"), rtol=1e-7)


@pytest.mark.parametrize("fwhm, n", [(2.0, 3), (3.0, 5), (3.0, 7), (4.5, 9)])
def test_gauss_kernels(fwhm, n):
    kernel = filter_kernel(f"gauss_{fwhm}_{n}x{n}")
    assert kernel.shape == (n, n)
    assert kernel.sum() == pytest.approx(1.0, abs=1e-6)
    c = n // 2
    np.testing.assert_allclose(kernel, kernel.T)  # circular
    np.testing.assert_allclose(kernel, kernel[::-1, ::-1])
    # Its FWHM: a Gaussian sampled at pixel centres has k(r)/k(0) = exp(-r^2 / 2 sigma^2).
    sigma = np.sqrt(-1.0 / (2.0 * np.log(kernel[c, c + 1] / kernel[c, c])))
    assert sigma * FWHM_PER_SIGMA == pytest.approx(fwhm, rel=1e-5)
    # Separable: the corner holds the product of the two 1-D factors.
    assert kernel[c + 1, c + 1] * kernel[c, c] == pytest.approx(kernel[c, c + 1] ** 2, rel=1e-5)


@pytest.mark.parametrize("name, pattern", [
    ("gauss_2.0_4x4", r"odd square size"),
    ("gauss_2.0_5x7", r"odd square size"),
    ("gaussian", r"neither 'default', 'none', 'gauss_<fwhm>_<n>x<n>' nor an existing"),
    ("/nonexistent/file.conv", r"nor an existing SExtractor \.conv file"),
])
def test_bad_filter_names(name, pattern):
    with pytest.raises(ConfigError, match=pattern):
        filter_kernel(name)


def test_bad_conv_files(tmp_path):
    ragged = tmp_path / "ragged.conv"
    ragged.write_text("CONV NORM\n1 2 1\n2 4\n")
    with pytest.raises(ConfigError, match="rectangular kernel"):
        filter_kernel(str(ragged))
    zero = tmp_path / "zero.conv"
    zero.write_text("CONV NORM\n-1 2 -1\n")
    with pytest.raises(ConfigError, match="cannot be normalised"):
        filter_kernel(str(zero))


def test_noise_map_weight_mode_takes_the_shape_from_the_weights_and_the_level_from_the_rms():
    # a two-level weight map (sigma 1 and 3) and a measured RMS that is 2.5 x the weight sigma nearly
    # everywhere: the result is 2.5 x the weight sigma, whatever the masked pixels hold
    weight = np.ones((10, 10), np.float32)
    weight[:, 5:] = 3.0
    rms = 2.5 * weight
    rms[0, :3] = 50.0  # three outliers do not move the median ratio
    mask = np.zeros((10, 10), bool)
    mask[9, 9] = True
    for copy in (True, False):
        out, mode = noise_map("auto", rms.copy(), 7.0, weight, mask, copy=copy)
        assert mode == "weight" and out.dtype == np.float32
        np.testing.assert_allclose(out[~mask], 2.5 * weight[~mask], rtol=1e-6)
        # the masked pixel gets the median of the others
        assert out[9, 9] == pytest.approx(np.median(2.5 * weight[~mask]))


def test_noise_map_global_and_background_modes():
    rms = np.arange(1.0, 17.0, dtype=np.float32).reshape(4, 4)
    mask = np.zeros((4, 4), bool)
    out, mode = noise_map("global", rms, 3.5, None, mask)
    assert mode == "global" and np.all(out == np.float32(3.5))
    out, mode = noise_map("auto", rms, 3.5, None, mask)  # no weight map: the background RMS itself
    assert mode == "background"
    np.testing.assert_array_equal(out, rms)
    assert out is not rms
    # a NaN in the RMS is filled like a masked pixel; with copy=False the RMS buffer itself is returned
    rms[1, 1] = np.nan
    out, _ = noise_map("background", rms, 3.5, None, mask, copy=False)
    assert out is rms and out[1, 1] == pytest.approx(np.median(np.delete(np.arange(1.0, 17.0), 5)))



# --------------------------------------------------------------------------- a given noise map


def test_given_noise_is_used_as_it_is_with_masked_pixels_filled():
    from comest_bayes.detect.base import given_noise

    noise = np.arange(1, 17, dtype=np.float64).reshape(4, 4)
    mask = np.zeros((4, 4), bool)
    mask[0, :2] = True
    noise[0, 0] = np.nan  # anything may lie under the mask
    out = given_noise(noise, mask)
    assert out.dtype == np.float32 and out.flags.c_contiguous
    np.testing.assert_array_equal(out[~mask], noise[~mask].astype(np.float32))
    np.testing.assert_array_equal(out[mask], np.float32(np.median(noise[~mask])))
    assert np.isnan(noise[0, 0])  # the input is never modified


def test_given_background_zeroes_masked_pixels_and_refuses_non_finite_unmasked_values():
    from comest_bayes.detect.base import given_background
    from comest_bayes.errors import InputError

    back = np.linspace(-2.0, 3.0, 16).reshape(4, 4)
    mask = np.zeros((4, 4), bool)
    mask[3, 3] = True
    back[3, 3] = np.inf  # anything may lie under the mask
    out = given_background(back, mask)
    assert out.dtype == np.float32 and out.flags.c_contiguous
    np.testing.assert_array_equal(out[~mask], back[~mask].astype(np.float32))  # negative levels kept as given
    assert out[3, 3] == 0.0 and np.isinf(back[3, 3])
    bad = back.copy()
    bad[1, 2] = np.nan
    with pytest.raises(InputError, match=r"background map is not finite on 1 unmasked pixels"):
        given_background(bad, mask)
    with pytest.raises(InputError, match=r"shape \(4, 3\) but the image \(4, 4\)"):
        given_background(np.zeros((4, 3)), mask)


def test_given_noise_refuses_a_map_of_another_shape_or_bad_unmasked_values():
    from comest_bayes.detect.base import given_noise
    from comest_bayes.errors import InputError

    mask = np.zeros((4, 4), bool)
    with pytest.raises(InputError, match=r"shape \(3, 4\) but the image \(4, 4\)"):
        given_noise(np.ones((3, 4)), mask)
    bad = np.ones((4, 4))
    bad[2, 1] = 0.0
    with pytest.raises(InputError, match=r"not finite and positive on 1 unmasked pixels"):
        given_noise(bad, mask)


def test_weight_agreement_ranks_the_meshes_as_the_measured_noise_does_only_for_the_right_weight_type():
    # a noise level rising 4x across a 256x256 image, seen by the background RMS (with 5% mesh-to-mesh scatter)
    # and by an error map: read as ivar (1 / sqrt) its sigma falls where the noise rises
    rng = np.random.default_rng(3)
    level = np.tile(np.linspace(1.0, 4.0, 256), (256, 1))
    rms = level * (1.0 + 0.05 * rng.standard_normal((256, 256)))
    err = level.astype(np.float32)
    mask = np.zeros((256, 256), bool)
    right = weight_agreement(err, rms, mask, 32)
    wrong = weight_agreement(1.0 / np.sqrt(err), rms, mask, 32)
    assert right["meshes"] == wrong["meshes"] == 64
    assert right["spearman"] > 0.9 and right["p"] < 1e-10
    assert wrong["spearman"] == pytest.approx(-right["spearman"]) and wrong["p"] == pytest.approx(right["p"])
    # a block more than half masked is left out; a constant weight map says nothing
    mask[:32, :32] = True
    assert weight_agreement(err, rms, mask, 32)["meshes"] == 63
    assert weight_agreement(np.ones_like(err), rms, mask, 32) is None
    assert weight_agreement(err[:64, :64], rms[:64, :64], mask[:64, :64], 32) is None  # 4 meshes: too few
