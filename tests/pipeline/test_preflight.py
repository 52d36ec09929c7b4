"""Decisions taken before any injection (comest_bayes.pipeline.preflight): the automatic injection density,
against the background mesh, the target, the published density and what the placement holds.
"""

import numpy as np
import pytest


# --------------------------------------------------------------------------- the automatic density
# comest_bayes.pipeline.preflight.choose_density: known image sizes give known counts per realization.

def _choice(kind, shape, pixel_scale, fwhm_pix, back_size=64, **injection):
    from comest_bayes.config import InjectionConfig
    from comest_bayes.pipeline.preflight import choose_density

    return choose_density(kind, shape=shape, pixel_scale=pixel_scale, fwhm_pix=fwhm_pix,
                          injection=InjectionConfig(**injection), back_size=back_size)


def _half_jamming(npix, sep_pix):
    # half of random sequential packing (54.7% covered by discs of diameter sep_pix)
    return 0.5 * 0.547 * npix / (np.pi * sep_pix ** 2 / 4.0)


def test_auto_density_raises_a_small_fine_pixel_field_to_a_quarter_injection_per_background_mesh():
    # The shared JWST cutout: 640x640 at 0.0308"/px is 0.1079 arcmin^2, 1.6 injections per
    # realization at 15 per arcmin^2.  Point sources (FWHM 2.46 px, 9.84 px apart) are raised to
    # a quarter per 64x64 background mesh, 25 (the target is 100, the placement holds 1473).
    c = _choice("point", (640, 640), 0.0308, 2.46)
    area = 640 * 640 * (0.0308 / 60) ** 2
    assert c.source == "automatic" and c.rule == "raised"
    assert c.published == pytest.approx(15 * area)
    assert c.mesh_cap == pytest.approx(0.25 * 100) and c.per_realization == pytest.approx(25.0)
    assert c.density == pytest.approx(25.0 / area)  # 231.6 per arcmin^2
    assert c.hold_cap == pytest.approx(_half_jamming(640 * 640, 4 * 2.46))
    assert "0.25 per 64x64 background mesh" in c.reason
    # Galaxies need 8 x 0.75" = 6" = 194.8 px apart: the placement holds only 3.8 per realization.
    g = _choice("buldisk", (640, 640), 0.0308, 2.46)
    assert g.per_realization == pytest.approx(_half_jamming(640 * 640, 6.0 / 0.0308))
    assert 3.7 < g.per_realization < 3.9 and g.rule == "raised"
    # smaller meshes (detection.back_size 32) allow four times as many
    assert _choice("point", (640, 640), 0.0308, 2.46, back_size=32).per_realization == pytest.approx(100.0)


def test_auto_density_stops_at_the_target():
    # 1400x1400 at 0.05"/px: 20.4 per realization at 15 per arcmin^2, room for 119.6 at a quarter per
    # mesh: the target, 100
    c = _choice("point", (1400, 1400), 0.05, 3.0)
    assert c.published == pytest.approx(15 * (1400 * 0.05 / 60) ** 2) and c.mesh_cap == pytest.approx(0.25 * 1400 ** 2 / 4096)
    assert c.rule == "raised" and c.per_realization == pytest.approx(100.0)


def test_auto_density_keeps_the_published_density_where_it_is_enough():
    # the 3000x3000 demo tile at 0.26"/px: 2535 per realization >= the target
    c = _choice("point", (3000, 3000), 0.26, 3.5)
    assert c.rule == "published" and c.density == 15.0 and c.per_realization == pytest.approx(15 * 13.0 ** 2)
    # a 200x200 DECam cutout at 0.262"/px: 11.4 per realization, already more than one per mesh (9.8)
    d = _choice("point", (200, 200), 0.262, 4.0)
    assert d.rule == "published" and d.density == 15.0
    assert d.per_realization == pytest.approx(15 * (200 * 0.262 / 60) ** 2) and d.mesh_cap < d.per_realization


def test_auto_density_is_lowered_to_what_the_placement_holds_on_coarse_pixels():
    # the 2MASS field: 720x721 at 5"/px is 3605 arcmin^2, 54075 per realization at 15 per arcmin^2;
    # point sources of FWHM 1.5 px, 6 px apart: half of random packing is 5021
    c = _choice("point", (721, 720), 5.0, 1.5)
    assert c.rule == "placement cap"
    assert c.per_realization == pytest.approx(_half_jamming(721 * 720, 6.0))
    assert 5000 < c.per_realization < 5050
    assert c.density == pytest.approx(c.per_realization / (721 * 720 * (5.0 / 60) ** 2))


def test_a_density_the_user_sets_is_kept():
    c = _choice("point", (640, 640), 0.0308, 2.46, density=400.0)
    assert c.source == "user" and c.rule == "user" and c.density == 400.0
    assert c.per_realization == pytest.approx(400.0 * 640 * 640 * (0.0308 / 60) ** 2)
