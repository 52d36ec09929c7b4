"""Fourier-space drawing of bulge+disk galaxies (comest_bayes.inject.kspace) against GalSim's own transforms."""

import galsim
import numpy as np
import pytest
from scipy import integrate

from comest_bayes.inject.kspace import DEV_K_STEP, buldisk_k, buldisk_radius_per_hlr, devaucouleurs_k_table, exponential_k, kspace_quadratic_forms, shear_matrices
from comest_bayes.inject.profiles import bulge_disk_components, source_profile


def enclosed_fraction(profile, radius):
    """Flux fraction of a circular profile inside ``radius``, by radial integration of xValue."""
    f = lambda r: 2.0 * np.pi * r * profile.xValue(galsim.PositionD(r, 0.0))  # noqa: E731
    inner, _ = integrate.quad(f, 0.0, radius, limit=400, points=[radius * 1e-3, radius * 1e-2])
    return inner / profile.flux


# --------------------------------------------------------------------------- Fourier transforms (batched drawing)


def _kvalues(profile, kx, ky):
    return np.array([profile.kValue(galsim.PositionD(a, b)) for a, b in zip(kx, ky)])


@pytest.mark.parametrize("bulge_fraction", [0.0, 0.35, 1.0])
def test_buldisk_transform_matches_galsim(bulge_fraction):
    bulge, disk = bulge_disk_components(1.0, bulge_fraction, flux=1.0)
    k = np.linspace(0.0, 40.0, 801)
    ref = _kvalues(bulge + disk, k, np.zeros_like(k))
    assert np.abs(ref.imag).max() == 0.0  # real and radial, as the batched drawing assumes
    ours = buldisk_k(k ** 2, bulge_fraction)
    # the disk is analytic (agrees to rounding); the bulge is a linear interpolation of GalSim's own
    # values with step DEV_K_STEP = 0.0025, whose error h^2 |F''| / 8 measured at most 7.6e-6 of F(0) = 1
    tol = 1e-12 if bulge_fraction == 0.0 else 2e-5
    np.testing.assert_allclose(ours, ref.real, rtol=0, atol=tol)
    np.testing.assert_allclose(exponential_k(k ** 2), _kvalues(disk.original, k, 0 * k).real, rtol=1e-12, atol=0)


def test_devaucouleurs_table_is_galsims_values_on_its_grid_and_grows_on_demand():
    small = devaucouleurs_k_table()
    assert small.step == DEV_K_STEP and small.kmax >= 64.0
    bulge = bulge_disk_components(1.0, 1.0)[0]
    idx = np.array([0, 1, 17, 4000, small.values.size - 1])
    np.testing.assert_allclose(small.values[idx], _kvalues(bulge, idx * DEV_K_STEP, 0 * idx).real, rtol=1e-10, atol=0)
    assert small(np.array([0.0]))[0] == pytest.approx(1.0, abs=1e-15)
    big = devaucouleurs_k_table(300.0)
    assert big.kmax >= 300.0 and big.kmax < 2 * 300.0 + 64
    assert devaucouleurs_k_table(10.0) is small  # built once per process


def test_shear_matrices_are_galsims():
    q = np.array([0.3, 0.55, 1.0, 0.9])
    pa = np.array([0.0, 37.0, 120.0, 179.0])
    for m, qi, pi in zip(shear_matrices(q, pa), q, pa):
        np.testing.assert_allclose(m, galsim.Shear(q=qi, beta=pi * galsim.degrees).getMatrix(), rtol=0, atol=1e-15)


def test_quadratic_forms_reproduce_galsims_transformed_profiles():
    # An exponential disk sheared, dilated and mapped to pixels by a rotated, skewed WCS Jacobian:
    # GalSim's transform at pixel wavenumber k must equal flux * F_exp(k^T Q k).
    rng = np.random.default_rng(3)
    hlr, q, pa = np.array([0.4, 0.7]), np.array([0.45, 0.9]), np.array([25.0, 140.0])
    jac = np.array([[[-0.18, 0.05], [0.04, 0.19]], [[0.26, 0.0], [0.0, 0.26]]])
    quad = kspace_quadratic_forms(hlr, q, pa, jac)
    unit = bulge_disk_components(1.0, 0.0)[1].original
    for i in range(2):
        world = unit.dilate(hlr[i]).shear(q=q[i], beta=pa[i] * galsim.degrees).withFlux(3.0)
        prof = galsim.JacobianWCS(*jac[i].ravel()).toImage(world)
        k = rng.uniform(-np.pi, np.pi, (40, 2))
        ref = _kvalues(prof, k[:, 0], k[:, 1])
        ksq = np.einsum("ni,ij,nj->n", k, quad[i], k)
        np.testing.assert_allclose(3.0 * exponential_k(ksq), ref.real, rtol=1e-10, atol=1e-14)
        assert np.abs(ref.imag).max() < 1e-14


def test_buldisk_radius_per_hlr_encloses_the_fraction():
    # vectorised growth-curve search: the first 0.01-step radius enclosing the fraction, per source
    bf = np.array([0.0, 0.2, 0.5, 0.8, 1.0])
    radii = buldisk_radius_per_hlr(bf, 0.995)
    assert np.all(np.diff(radii) > 0)  # more bulge, more light at large radii
    for b, r in zip(bf, radii):
        bulge, disk = bulge_disk_components(1.0, b)
        prof = bulge + disk if 0 < b < 1 else (disk if b == 0 else bulge)
        assert enclosed_fraction(prof, r) >= 0.995 - 1e-4
        assert enclosed_fraction(prof, r - 0.02) < 0.995
    # and it is what source_profile uses for its stamp radius
    sp = source_profile("buldisk", flux=1.0, hlr_arcsec=0.5, q=1.0, pa_deg=0.0, bulge_fraction=0.5)
    assert sp.radius_arcsec == 0.5 * radii[2]
