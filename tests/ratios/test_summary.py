"""The binned part of summary.json and the map-cube headers (comest_bayes.ratios.summary), on a tiny outcome
table whose ratios, counts, intervals and m50 are computed by hand below."""

import math

import numpy as np
import pytest
from astropy.table import Table
from scipy import stats

from comest_bayes.config import load_config
from comest_bayes.ratios.summary import depth_summary, kind_summary, map_cube_header
from comest_bayes.recover.realization import MergedCatalogs

EDGES = np.array([20.0, 21.0, 22.0, 23.0, 24.0])


def _merged() -> MergedCatalogs:
    """Injections and detections of one kind with known counts per 1-mag bin.

    True magnitudes of usable injections: 4 per bin in 20-21, 21-22 and 22-23, none in 23-24; detected
    4, 3 and 1 (completeness 1, 0.75, 0.25, empty); one more injection at 20.5 is unusable (and detected:
    it must not count).  Detections by measured magnitude: 20-21 holds 4 matched and 1 pre-existing source
    (left out), 21-22 holds 3 matched and 2 false (purity 0.6), 22-23 holds 1 matched and 3 false (0.25)
    and one false detection near an unusable injection (left out), 23-24 holds 2 false (0).
    """
    t_mag = [20.2, 20.4, 20.6, 20.8, 21.2, 21.4, 21.6, 21.8, 22.2, 22.4, 22.6, 22.8, 20.5]
    t_det = [1, 1, 1, 1, 1, 1, 1, 0, 1, 0, 0, 0, 1]
    usable = [True] * 12 + [False]
    n = len(t_mag)
    truth = Table({"x": np.linspace(5, 95, n), "y": np.linspace(95, 5, n), "mag": t_mag,
                   "detected": np.array(t_det, bool), "usable": usable})
    rows = ([(20.3, 1, 0, 0)] * 4 + [(20.7, 0, 1, 0)]                      # 20-21
            + [(21.5, 1, 0, 0)] * 3 + [(21.5, 0, 0, 0)] * 2                 # 21-22
            + [(22.5, 1, 0, 0)] + [(22.5, 0, 0, 0)] * 3 + [(22.5, 0, 0, 1)]  # 22-23
            + [(23.5, 0, 0, 0)] * 2)                                        # 23-24
    mag, matched, pre, near = (np.array(c) for c in zip(*rows))
    matched, pre, near = matched.astype(bool), pre.astype(bool), near.astype(bool)
    m = len(mag)
    det = Table({"xwin": np.linspace(3, 97, m), "ywin": np.linspace(3, 97, m), "mag_auto": mag.astype(float),
                 "matched": matched, "preexisting": pre, "near_unusable": near,
                 "false": ~matched & ~pre})
    return MergedCatalogs.from_tables(truth, det)


def _wilson(k, n, confidence=0.6827):
    z = stats.norm.ppf(0.5 + 0.5 * confidence)
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return centre - half, centre + half


def _poisson(k, confidence=0.6827):
    """Frequentist (Garwood) interval on a Poisson count."""
    a = 0.5 * (1 - confidence)
    lo = 0.0 if k == 0 else 0.5 * stats.chi2.ppf(a, 2 * k)
    return lo, 0.5 * stats.chi2.ppf(1 - a, 2 * k + 2)


@pytest.fixture(scope="module")
def entry():
    config = load_config()
    assert config.matching.mag_column == "mag_auto" and config.ratios.interval == "wilson"
    return kind_summary(_merged(), EDGES, config, nreal=2, maps_file=None)


def test_counts_are_the_hand_counts(entry):
    # false: 2 + 3 + 1 (the one near an unusable injection is false, only left out of purity) + 2
    assert entry["counts"] == {"realizations": 2, "injected": 13, "usable": 12, "detected": 8, "false": 8,
                               "preexisting": 1, "near_unusable": 1}
    assert entry["mag_range"] == [20.0, 24.0]
    assert "maps" not in entry


def test_binned_ratios_are_the_hand_ratios_with_null_for_empty_bins(entry):
    b = entry["binned"]
    assert b["mag_edges"] == [20.0, 21.0, 22.0, 23.0, 24.0] and b["mag_centers"] == [20.5, 21.5, 22.5, 23.5]
    assert b["completeness_n"] == [4, 4, 4, 0] and b["completeness_k"] == [4, 3, 1, 0]
    assert b["completeness"][:3] == pytest.approx([1.0, 0.75, 0.25]) and b["completeness"][3] is None
    assert b["purity_n"] == [4, 5, 4, 2] and b["purity_k"] == [4, 3, 1, 0]
    assert b["purity"] == pytest.approx([1.0, 0.6, 0.25, 0.0])
    # detections counted in each measured bin over usable injections in the same true bin: may exceed 1
    assert b["detection_rate"][:3] == pytest.approx([1.0, 1.25, 1.0]) and b["detection_rate"][3] is None
    assert "detection_rate_n" not in b
    assert b["confidence"] == 0.6827 and b["interval"] == "wilson"


def test_intervals_are_wilson_for_the_ratios_and_poisson_for_the_rate(entry):
    b = entry["binned"]
    for name, ks, ns in (("completeness", [4, 3, 1], [4, 4, 4]), ("purity", [4, 3, 1, 0], [4, 5, 4, 2])):
        for i, (k, n) in enumerate(zip(ks, ns)):
            lo, hi = _wilson(k, n)
            assert b[f"{name}_lower"][i] == pytest.approx(lo, abs=1e-6), (name, i)
            assert b[f"{name}_upper"][i] == pytest.approx(hi, abs=1e-6), (name, i)
    assert b["completeness_lower"][3] is None and b["completeness_upper"][3] is None
    for i, (k, n) in enumerate(zip([4, 5, 4], [4, 4, 4])):
        lo, hi = _poisson(k)
        assert b["detection_rate_lower"][i] == pytest.approx(lo / n, rel=1e-4)
        assert b["detection_rate_upper"][i] == pytest.approx(hi / n, rel=1e-4)


def test_m50_is_the_interpolated_crossing_of_one_half(entry):
    # 0.75 at 21.5 and 0.25 at 22.5: linear interpolation crosses 0.5 at 22.0
    assert entry["m50_binned"] == pytest.approx(22.0)
    # its sd: the spread (half the central 68%) of the first crossings of curves drawn from the bins' Jeffreys
    # posteriors, 4 of 4, 3 of 4, 1 of 4 at 20.5, 21.5, 22.5.  Computed here apart, with 400,000 draws (Monte
    # Carlo error 0.2%): the package's 2,000 draws must agree within 6% (their own error is about 2%)
    rng = np.random.default_rng(5)
    p1, p2, p3 = (rng.beta(k + 0.5, 4 - k + 0.5, 400_000) for k in (4, 3, 1))
    first = np.where(p1 >= 0.5, np.where(p2 < 0.5, 1, np.where(p3 < 0.5, 2, 0)),
                     np.where((p2 >= 0.5) & (p3 < 0.5), 2, 0))  # 1: between bins 1 and 2; 2: bins 2 and 3; 0: none
    cross = np.where(first == 1, 20.5 + (p1 - 0.5) / (p1 - p2), 21.5 + (p2 - 0.5) / (p2 - p3))[first > 0]
    lo, hi = np.percentile(cross, [15.865, 84.135])
    assert entry["m50_binned_sd"] == pytest.approx(0.5 * (hi - lo), rel=0.06)
    assert entry["m50_binned_sd"] > np.sqrt(2 * 0.75 * 0.25 / 4)  # the delta method's 0.306 leaves out the jumps
    merged = _merged()
    merged.injected["detected"] = True  # never falls below one half: null, not a number
    flat = kind_summary(merged, EDGES, load_config(), nreal=2, maps_file=None)
    assert flat["m50_binned"] is None and flat["m50_binned_sd"] is None


def test_the_maps_entry_names_the_file_and_its_planes():
    config = load_config()
    entry = kind_summary(_merged(), EDGES, config, nreal=2, maps_file="maps/point_maps.fits",
                         map_edges=np.array([21.0, 22.0, 23.0]))
    assert entry["maps"] == {"file": "maps/point_maps.fits", "mag_edges": [21.0, 22.0, 23.0],
                             "bin_arcmin": config.ratios.map_bin_arcmin}


def test_map_header_without_a_wcs_gives_bin_centres_and_a_magnitude_axis():
    h = map_cube_header(None, 40.0, (3, 4), [22.0, 22.5, 23.0, 23.5])
    assert (h["CTYPE1"], h["CTYPE2"]) == ("X", "Y")
    assert h["CRVAL1"] == h["CRVAL2"] == 19.5 and h["CDELT1"] == 40.0  # first bin covers pixels 0..39
    assert h["WCSAXES"] == 3 and h["CTYPE3"] == "MAG"
    assert h["CRVAL3"] == 22.25 and h["CDELT3"] == 0.5 and h["CRPIX3"] == 1.0
    assert [h[f"MAGLO{i}"] for i in range(3)] == [22.0, 22.5, 23.0]
    assert [h[f"MAGHI{i}"] for i in range(3)] == [22.5, 23.0, 23.5]
    unequal = map_cube_header(None, 40.0, (3, 4), [22.0, 22.5, 23.5])
    assert unequal["CTYPE3"] == "PLANE" and unequal["MAGHI1"] == 23.5


def test_depth_summary_uses_the_unmasked_median_noise():
    noise = np.full((50, 50), 2.0)
    mask = np.zeros((50, 50), bool)
    noise[:10], mask[:10] = 100.0, True  # masked pixels must not set the depth
    d = depth_summary(noise, mask, zeropoint=30.0, fwhm=3.0, det_mags=[22.0] * 10, psf_nea=40.0)
    assert d["noise_median"] == 2.0
    assert d["point_source_5sigma"] == pytest.approx(30.0 - 2.5 * math.log10(5 * 2.0 * math.sqrt(40.0)))
    sigma_psf = 3.0 / (2 * math.sqrt(2 * math.log(2)))
    gauss = 30.0 - 2.5 * math.log10(5 * 2.0 * 2 * math.sqrt(math.pi) * sigma_psf)
    assert d["point_source_5sigma_gaussian"] == pytest.approx(gauss)
    assert d["aperture_diameter_pix"] == 6.0
    assert d["aperture_5sigma"] == pytest.approx(30.0 - 2.5 * math.log10(5 * 2.0 * math.sqrt(math.pi) * 3.0))
    assert d["histogram"] is None  # fewer than 50 detections
    no_nea = depth_summary(noise, mask, zeropoint=30.0, fwhm=3.0, det_mags=[])
    assert no_nea["point_source_5sigma"] == pytest.approx(gauss) and no_nea["psf_nea_pix"] is None


def test_the_merged_catalogs_split_the_tables_as_the_hand_counts():
    merged = _merged()
    # 13 injections, 9 detected (8 usable + the unusable one), 12 usable outcomes, 8 false detections
    assert (len(merged.injected), len(merged.matched), len(merged.unmatched)) == (13, 9, 4)
    assert len(merged.outcomes) == 12 and merged.outcomes.colnames == ["x", "y", "mag", "detected"]
    assert len(merged.false) == 8 and merged.false["false"].all() and merged.seconds == {}
