"""Tests of comest_bayes.recover.matching: one-to-one matching and detection classes."""

import time

import numpy as np
import pytest

from comest_bayes.errors import InputError
from comest_bayes.recover.matching import classify_detections, match_one_to_one


def _reference_greedy(tx, ty, tm, dx, dy, dm, radius, mag_tol):
    """Plain sequential greedy over all pairs, written independently (O(N M))."""
    pairs = []
    for i in range(len(tx)):
        for j in range(len(dx)):
            sep = np.hypot(dx[j] - tx[i], dy[j] - ty[i])
            dmag = dm[j] - tm[i]
            if sep <= radius and abs(dmag) <= mag_tol:
                pairs.append((sep, abs(dmag), i, j))
    pairs.sort()
    used_t, used_d, out = set(), set(), {}
    for sep, _, i, j in pairs:
        if i not in used_t and j not in used_d:
            used_t.add(i)
            used_d.add(j)
            out[i] = j
    return out


def _crowded_field(rng, ntruth, size, frag_max=3):
    """Injections in a small area, each with 0-frag_max detected fragments, plus spurious detections."""
    tx = rng.uniform(0, size, ntruth)
    ty = rng.uniform(0, size, ntruth)
    tm = rng.uniform(20, 26, ntruth)
    nfrag = rng.integers(0, frag_max + 1, ntruth)
    src = np.repeat(np.arange(ntruth), nfrag)
    dx = tx[src] + rng.normal(0, 1.5, src.size)
    dy = ty[src] + rng.normal(0, 1.5, src.size)
    dm = tm[src] + rng.normal(0, 0.5, src.size)
    nspur = ntruth // 3
    dx = np.r_[dx, rng.uniform(0, size, nspur)]
    dy = np.r_[dy, rng.uniform(0, size, nspur)]
    dm = np.r_[dm, rng.uniform(20, 26, nspur)]
    return tx, ty, tm, dx, dy, dm


def test_two_fragments_of_one_source_only_one_matched():
    # One injected source, two deblended fragments both inside the radius and
    # the magnitude tolerance: the closer fragment is matched, the other is a
    # false detection, and the completeness is 1, not 2.
    res = match_one_to_one([50.0], [50.0], [20.0], [50.5, 51.5], [50.0, 50.5], [20.3, 21.0],
                           radius=3.0, mag_tol=1.5)
    assert res.n_candidates == 2
    assert res.n_matched == 1
    assert res.det_of_truth.tolist() == [0]
    assert res.truth_of_det.tolist() == [0, -1]
    assert res.separation[0] == pytest.approx(0.5)
    assert res.dmag[0] == pytest.approx(0.3)
    classes = classify_detections([50.5, 51.5], [50.0, 50.5], res.det_matched, radius=3.0)
    assert classes.matched.tolist() == [True, False]
    assert classes.false.tolist() == [False, True]
    assert classes.kept.tolist() == [False, False]


def test_detection_between_two_sources_goes_to_the_closer():
    res = match_one_to_one([0.0, 10.0], [0.0, 0.0], [22.0, 22.0], [4.0], [0.0], [22.0], radius=7.0, mag_tol=1.0)
    assert res.det_of_truth.tolist() == [0, -1]
    assert res.truth_of_det.tolist() == [0]
    # mirrored: closer to the second injection
    res = match_one_to_one([0.0, 10.0], [0.0, 0.0], [22.0, 22.0], [6.5], [0.0], [22.0], radius=7.0, mag_tol=1.0)
    assert res.det_of_truth.tolist() == [-1, 0]


def test_global_greedy_order_and_dmag_tie_break():
    # Truth A at x=0, B at x=3; detection d0 at x=2 is closest to B (1 px),
    # d1 at x=-1 is closest to A (1 px).  A per-truth nearest match would give
    # A -> d0 (2 px); the global greedy gives B -> d0 and A -> d1.
    res = match_one_to_one([0.0, 3.0], [0.0, 0.0], [21.0, 21.0], [2.0, -1.0], [0.0, 0.0], [21.0, 21.0],
                           radius=5.0, mag_tol=1.0)
    assert res.det_of_truth.tolist() == [1, 0]
    # Equal separations: the pair with the smaller |dmag| wins.
    res = match_one_to_one([0.0, 4.0], [0.0, 0.0], [21.0, 22.0], [2.0], [0.0], [21.9], radius=5.0, mag_tol=1.5)
    assert res.det_of_truth.tolist() == [-1, 0]
    # Equal separations and |dmag|: the lower truth index wins.
    res = match_one_to_one([0.0, 4.0], [0.0, 0.0], [21.0, 21.0], [2.0], [0.0], [21.0], radius=5.0, mag_tol=1.5)
    assert res.det_of_truth.tolist() == [0, -1]


def test_matches_sequential_greedy_reference_in_crowded_field():
    rng = np.random.default_rng(11)
    tx, ty, tm, dx, dy, dm = _crowded_field(rng, 250, 120.0)
    radius, mag_tol = 4.0, 1.0
    res = match_one_to_one(tx, ty, tm, dx, dy, dm, radius=radius, mag_tol=mag_tol)
    ref = _reference_greedy(tx, ty, tm, dx, dy, dm, radius, mag_tol)
    assert res.n_candidates > res.n_matched  # crowded: the assignment had choices to make
    assert dict(zip(res.truth_index.tolist(), res.det_index.tolist())) == ref


def test_one_to_one_and_completeness_at_most_one():
    rng = np.random.default_rng(5)
    tx, ty, tm, dx, dy, dm = _crowded_field(rng, 2000, 400.0)
    res = match_one_to_one(tx, ty, tm, dx, dy, dm, radius=5.0, mag_tol=1.5)
    assert np.unique(res.truth_index).size == res.n_matched
    assert np.unique(res.det_index).size == res.n_matched
    # the per-row lookups are each other's inverse
    assert np.all(res.truth_of_det[res.det_of_truth[res.truth_matched]] == np.flatnonzero(res.truth_matched))
    assert np.all(res.det_of_truth[res.truth_of_det[res.det_matched]] == np.flatnonzero(res.det_matched))
    assert res.det_matched.sum() == res.truth_matched.sum() == res.n_matched
    # more detections near sources than sources, yet completeness <= 1 in every bin
    edges = np.arange(20.0, 26.01, 0.5)
    n = np.histogram(tm, edges)[0]
    k = np.histogram(tm[res.truth_matched], edges)[0]
    assert dx.size > tx.size
    assert np.all(k <= n)
    # every pair satisfies both criteria
    assert np.all(res.separation <= 5.0)
    assert np.all(np.abs(res.dmag) <= 1.5)
    np.testing.assert_allclose(res.separation, np.hypot(dx[res.det_index] - tx[res.truth_index],
                                                        dy[res.det_index] - ty[res.truth_index]))


def test_order_invariance():
    rng = np.random.default_rng(3)
    tx, ty, tm, dx, dy, dm = _crowded_field(rng, 800, 250.0)
    res = match_one_to_one(tx, ty, tm, dx, dy, dm, radius=5.0, mag_tol=1.5)
    pt = rng.permutation(tx.size)
    pd = rng.permutation(dx.size)
    res2 = match_one_to_one(tx[pt], ty[pt], tm[pt], dx[pd], dy[pd], dm[pd], radius=5.0, mag_tol=1.5)
    pairs = set(zip(res.truth_index.tolist(), res.det_index.tolist()))
    pairs2 = set(zip(pt[res2.truth_index].tolist(), pd[res2.det_index].tolist()))
    assert len(pairs) > 100
    assert pairs == pairs2


def test_magnitude_tolerance_excludes_wrong_magnitude():
    # The closest detection has the wrong magnitude (2 mag off); a farther one
    # with the right magnitude is matched instead.
    res = match_one_to_one([10.0], [10.0], [22.0], [10.2, 12.0], [10.0, 10.0], [24.0, 22.3],
                           radius=3.0, mag_tol=1.5)
    assert res.det_of_truth.tolist() == [1]
    res = match_one_to_one([10.0], [10.0], [22.0], [10.2], [10.0], [24.0], radius=3.0, mag_tol=1.5)
    assert res.n_matched == 0 and res.n_candidates == 0
    # The tolerance is inclusive.
    res = match_one_to_one([10.0], [10.0], [22.0], [10.2], [10.0], [23.5], radius=3.0, mag_tol=1.5)
    assert res.n_matched == 1


def test_nan_magnitudes_never_match_unless_magnitude_test_disabled():
    res = match_one_to_one([10.0, 30.0], [10.0, 30.0], [22.0, np.nan], [10.0, 30.0], [10.0, 30.0],
                           [np.nan, 22.0], radius=2.0, mag_tol=1.5)
    assert res.n_matched == 0
    res = match_one_to_one([10.0, 30.0], [10.0, 30.0], [22.0, np.nan], [10.0, 30.0], [10.0, 30.0],
                           [np.nan, 22.0], radius=2.0, mag_tol=None)
    assert res.det_of_truth.tolist() == [0, 1]


def test_radius_boundary_is_inclusive_and_nonfinite_positions_skipped():
    res = match_one_to_one([0.0], [0.0], [20.0], [3.0], [4.0], [20.0], radius=5.0, mag_tol=1.0)
    assert res.n_matched == 1 and res.separation[0] == 5.0
    res = match_one_to_one([0.0], [0.0], [20.0], [3.0], [4.0], [20.0], radius=4.999, mag_tol=1.0)
    assert res.n_matched == 0
    res = match_one_to_one([np.nan, 0.0], [0.0, 0.0], [20.0, 20.0], [0.0, np.inf], [0.0, 0.0], [20.0, 20.0],
                           radius=1.0, mag_tol=1.0)
    assert res.det_of_truth.tolist() == [-1, 0]


def test_empty_inputs():
    res = match_one_to_one([], [], [], [1.0], [1.0], [20.0], radius=2.0, mag_tol=1.0)
    assert res.n_matched == 0 and res.truth_of_det.tolist() == [-1] and res.det_of_truth.size == 0
    res = match_one_to_one([1.0], [1.0], [20.0], [], [], [], radius=2.0, mag_tol=1.0)
    assert res.det_of_truth.tolist() == [-1]


def test_input_errors():
    with pytest.raises(InputError, match="truth_y has 1 values"):
        match_one_to_one([1.0, 2.0], [1.0], [20.0, 20.0], [1.0], [1.0], [20.0], radius=2.0, mag_tol=1.0)
    with pytest.raises(InputError, match="radius"):
        match_one_to_one([1.0], [1.0], [20.0], [1.0], [1.0], [20.0], radius=0.0, mag_tol=1.0)
    with pytest.raises(InputError, match="mag_tol"):
        match_one_to_one([1.0], [1.0], [20.0], [1.0], [1.0], [20.0], radius=1.0, mag_tol=-1.0)
    with pytest.raises(InputError, match="matched_mask"):
        classify_detections([1.0, 2.0], [1.0, 2.0], np.array([1, 0]), radius=1.0)


def test_classify_detections_kept_positions_and_segmentation():
    seg = np.zeros((40, 40), dtype=np.int32)
    seg[20:25, 5:10] = 7  # a kept source's pixels: x in [5, 9], y in [20, 24]
    det_x = np.array([30.0, 30.5, 9.6, 9.4, 15.0, 7.0])
    det_y = np.array([30.0, 10.0, 22.0, 19.4, 15.0, 22.0])
    matched = np.array([False, False, False, False, False, True])
    classes = classify_detections(det_x, det_y, matched, kept_x=[31.0], kept_y=[30.0], kept_segmentation=seg,
                                  radius=2.0)
    # 0: within 1 px of the kept position; 1: far from everything;
    # 2: centre pixel (10, 22) is outside the segment (x = 10 > 9) -> false;
    # 3: centre pixel (9, 19) is outside (y = 19 < 20) -> false;
    # 4: far -> false; 5: matched injection on the kept source -> matched.
    assert classes.coincident.tolist() == [True, False, False, False, False, True]
    assert classes.kept.tolist() == [True, False, False, False, False, False]
    assert classes.false.tolist() == [False, True, True, True, True, False]
    assert classes.counted.tolist() == [False, True, True, True, True, True]
    # A centre inside the segment (pixel (9, 22)) is coincident.
    classes = classify_detections([9.4], [22.4], np.array([False]), kept_segmentation=seg, radius=2.0)
    assert classes.kept.tolist() == [True]
    # every detection is in exactly one class
    total = classes.matched.astype(int) + classes.kept + classes.false
    assert np.all(total == 1)


def test_matching_speed_20000_by_25000():
    rng = np.random.default_rng(0)
    ntruth, ndet, size = 20_000, 25_000, 10_000.0
    tx, ty = rng.uniform(0, size, ntruth), rng.uniform(0, size, ntruth)
    tm = rng.uniform(18, 26, ntruth)
    rec = rng.choice(ntruth, 18_000, replace=False)
    dx = np.r_[tx[rec] + rng.normal(0, 1, rec.size), rng.uniform(0, size, ndet - rec.size)]
    dy = np.r_[ty[rec] + rng.normal(0, 1, rec.size), rng.uniform(0, size, ndet - rec.size)]
    dm = np.r_[tm[rec] + rng.normal(0, 0.3, rec.size), rng.uniform(18, 26, ndet - rec.size)]
    start = time.perf_counter()
    res = match_one_to_one(tx, ty, tm, dx, dy, dm, radius=4.0, mag_tol=1.5)
    elapsed = time.perf_counter() - start
    # ~0.03 s measured on 2 cores; 1 s leaves room for slow CI machines.
    assert elapsed < 1.0
    # nearly all the displaced copies (sd 1 px, 4 px radius, sd 0.3 mag) are recovered
    assert res.n_matched >= 17_900


# --------------------------------------------------------------------------- the clean zone


def test_clean_zone_flags_fainter_injections_within_reach_of_detected_brighter_ones():
    from comest_bayes.recover.matching import CLEAN_ZONE, in_clean_zone

    # a bright detected injection (a = 3 px) at the origin; the zone for a neighbour of a = 1 px is
    # CLEAN_ZONE x (3 + 1) = 40 px.  Fainter injections at 39.9 px (inside) and 40.0 px (on the edge:
    # cleaning needs strictly less) and a brighter one inside; an undetected bright one cleans nothing.
    x = np.array([0.0, 39.9, 0.0, 10.0, 500.0, 520.0])
    y = np.array([0.0, 0.0, 40.0, 0.0, 0.0, 0.0])
    flux = np.array([100.0, 1.0, 1.0, 200.0, 100.0, 1.0])
    a = np.array([3.0, np.nan, np.nan, np.nan, np.nan, np.nan])
    out = in_clean_zone(x, y, flux, a, a_other=1.0)
    assert CLEAN_ZONE == 10.0
    np.testing.assert_array_equal(out, [False, True, False, False, False, False])
    # the zone grows with the cleaner's size and the assumed size of the other
    np.testing.assert_array_equal(in_clean_zone(x, y, flux, a, a_other=1.1), [False, True, True, False, False, False])
    # the brighter one at 10 px, once detected, puts the first one and both faint ones in its zone
    a[3] = 1.0
    np.testing.assert_array_equal(in_clean_zone(x, y, flux, a, a_other=1.0), [True, True, False, False, False, False])
    assert not in_clean_zone(x[:0], y[:0], flux[:0], a[:0], a_other=1.0).size
    with pytest.raises(InputError, match="a_other must be >= 0"):
        in_clean_zone(x, y, flux, a, a_other=-1.0)
