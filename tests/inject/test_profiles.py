"""Source profiles (comest_bayes.inject.profiles): the de Vaucouleurs bulge, truncation, Sersic radii and
indices, flux and half-light radius of every kind.
"""

import galsim
import numpy as np
import pytest
from scipy import integrate

from comest_bayes.inject.profiles import TRUNC_HLR, bulge_disk_components, sersic_enclosed_radius, sersic_index_grid, sersic_truncation, source_profile


def enclosed_fraction(profile, radius):
    """Flux fraction of a circular profile inside ``radius``, by radial integration of xValue."""
    f = lambda r: 2.0 * np.pi * r * profile.xValue(galsim.PositionD(r, 0.0))  # noqa: E731
    inner, _ = integrate.quad(f, 0.0, radius, limit=400, points=[radius * 1e-3, radius * 1e-2])
    return inner / profile.flux


# --------------------------------------------------------------------------- profiles


def test_bulge_is_a_de_vaucouleurs_sersic_n4_not_a_gaussian():
    hlr = 0.5
    bulge, disk = bulge_disk_components(hlr, 0.4, flux=10.0)
    assert isinstance(bulge.original, galsim.DeVaucouleurs) and bulge.original.n == 4.0
    assert isinstance(disk.original, galsim.Exponential)
    assert bulge.flux == pytest.approx(4.0) and disk.flux == pytest.approx(6.0)
    # ln I is exactly linear in r^(1/4) for a Sersic n=4 profile (inside the truncation) ...
    r = np.linspace(0.1, 3.0, 30) * hlr
    lnI = np.log([bulge.xValue(galsim.PositionD(v, 0.0)) for v in r])
    for power, linear in ((0.25, True), (2.0, False), (1.0, False)):
        coef = np.polyfit(r ** power, lnI, 1)
        resid = np.abs(lnI - np.polyval(coef, r ** power)).max()
        assert (resid < 1e-4) == linear, (power, resid)
    # ... with slope -1 / scale_radius^(1/4) (I ~ exp(-(r / r0)^(1/4)); r0 = hlr / b_4^4 untruncated,
    # a little different here because the truncated profile keeps the requested half-light radius)
    slope = np.polyfit(r ** 0.25, lnI, 1)[0]
    assert -slope * (bulge.original.scale_radius * hlr) ** 0.25 == pytest.approx(1.0, rel=1e-6)
    # the (truncated) bulge, the disk and their sum all have the requested half-light radius
    for prof in (bulge, disk, bulge + disk):
        assert enclosed_fraction(prof, hlr) == pytest.approx(0.5, abs=2e-3)
    assert bulge.original.trunc == pytest.approx(TRUNC_HLR)  # in half-light radii of the unit profile
    assert bulge.original.half_light_radius == pytest.approx(1.0)


def test_truncation_only_where_the_tail_matters():
    assert sersic_truncation(4.0) == TRUNC_HLR
    assert sersic_truncation(2.0) == TRUNC_HLR
    assert sersic_truncation(0.5) == 0.0
    assert sersic_truncation(1.0) == 0.0  # exponential: 2e-5 of the light beyond 8 hlr


def test_sersic_enclosed_radius_matches_the_exponential_formula():
    # exponential: flux inside x scale radii is 1 - (1 + x) exp(-x)
    x = sersic_enclosed_radius(1.0, 1.0, 0.0, 0.995)
    assert 1.0 - (1.0 + x) * np.exp(-x) == pytest.approx(0.995, abs=1e-9)
    # truncated: the radius of the full fraction is the truncation radius
    assert sersic_enclosed_radius(4.0, 0.01, 3.0, 1.0) == pytest.approx(3.0, rel=1e-6)


@pytest.mark.parametrize("kind,kw", [
    ("buldisk", dict(hlr_arcsec=0.6, q=0.5, pa_deg=20.0, bulge_fraction=0.7)),
    ("sersic", dict(hlr_arcsec=0.4, q=0.8, pa_deg=100.0, sersic_n=3.0)),
    ("observed", dict(hlr_arcsec=0.3, q=0.6, pa_deg=45.0, sersic_n=1.5)),
])
def test_source_profile_flux_and_radius(kind, kw):
    sp = source_profile(kind, flux=123.0, fraction=0.995, **kw)
    assert sp.profile.flux == pytest.approx(123.0)
    # the radius encloses >= 99.5% of the light: draw finely and sum inside the ellipse's circumcircle
    scale = 0.02
    n = int(2 * (sp.radius_arcsec * 1.6) / scale) + 1
    img = sp.profile.drawImage(nx=n, ny=n, scale=scale, method="no_pixel").array
    c = (n - 1) / 2.0
    yy, xx = np.mgrid[0:n, 0:n]
    inside = np.hypot(xx - c, yy - c) * scale <= sp.radius_arcsec
    assert img[inside].sum() / 123.0 >= 0.995 - 2e-3  # pixelisation of the cusp costs < 0.2%


def test_point_source_has_no_profile():
    sp = source_profile("point", flux=5.0)
    assert sp.profile is None and sp.radius_arcsec == 0.0


def test_sersic_index_grid():
    g = sersic_index_grid((0.5, 4.0))
    assert g[0] == 0.5 and g[-1] == 4.0 and len(g) == 71
    np.testing.assert_allclose(np.diff(g), 0.05)
    wide = sersic_index_grid((0.3, 6.2))  # 119 values at 0.05: the step widens to keep 80
    assert len(wide) == 80 and wide[0] == 0.3 and wide[-1] == 6.2
    np.testing.assert_allclose(sersic_index_grid((1.0, 2.0)), np.arange(1.0, 2.0001, 0.05))
    np.testing.assert_array_equal(sersic_index_grid((2.0, 2.0)), [2.0])
