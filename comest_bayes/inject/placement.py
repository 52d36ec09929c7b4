"""Where synthetic sources are put: how many, and at which pixel positions.

Pure functions of a shape, an optional mask and a random generator; no I/O.  :func:`draw_count`
draws the Poisson number, :func:`place_sources` the positions (``uniform``, ``grid`` or
``halton``, with a minimum separation).  Conventions and methods: ``docs/injection.md``
("Placement").
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import qmc

from comest_bayes.errors import InputError

__all__ = ["Placement", "PLACEMENT_METHODS", "PUBLISHED_DENSITY", "placement_area_arcmin2", "draw_count", "place_sources",
           "place_sized_sources", "SIZED_MAX_ROUNDS", "pixel_index", "masked_at"]

PLACEMENT_METHODS = ("uniform", "grid", "halton")

#: ComEst's published injection density per arcmin^2 (the method this package follows): the
#: density of a bare :func:`comest_bayes.inject.render.make_truth` call whose ``injection.density`` is 0
#: (automatic), and the base of the run's automatic choice (:func:`comest_bayes.pipeline.preflight.choose_density`).
PUBLISHED_DENSITY = 15.0

#: Random close packing of discs fills at most ~54.7% of the plane (random sequential
#: adsorption jamming limit, Feder 1980); dart throwing stalls well before that.
_RSA_JAMMING_COVERAGE = 0.547


@dataclass
class Placement:
    """Positions of injections.

    Attributes
    ----------
    x, y : ndarray, shape (n,), float64
        0-based continuous pixel coordinates.
    masked : ndarray, shape (n,), bool
        True where the position falls on a masked pixel (all False without a mask).
    n_requested : int
        Number of positions asked for.
    method : str
        ``uniform``, ``grid`` or ``halton``.
    min_sep_pix : float
        Minimum separation that was enforced, pixels.
    border_pix : float
        Border excluded at each image edge, pixels.
    complete : bool
        False when fewer than ``n_requested`` positions could be placed.
    message : str
        Why the placement is incomplete (empty when complete).
    index : ndarray of int or None
        For :func:`place_sized_sources`: which of the sources given each
        position belongs to (ascending; the others could not be placed).
        None for :func:`place_sources`, whose positions are not tied to
        sources.
    """

    x: np.ndarray
    y: np.ndarray
    masked: np.ndarray
    n_requested: int
    method: str
    min_sep_pix: float
    border_pix: float
    complete: bool = True
    message: str = ""
    index: np.ndarray | None = None

    @property
    def n(self) -> int:
        """Number of positions placed."""
        return int(self.x.size)


def _region(shape, border_pix: float) -> tuple[float, float, float, float]:
    ny, nx = (int(v) for v in shape)
    x0, y0 = border_pix - 0.5, border_pix - 0.5
    x1, y1 = nx - 0.5 - border_pix, ny - 0.5 - border_pix
    if x1 <= x0 or y1 <= y0:
        raise InputError(f"the placement region is empty: image shape {tuple(shape)} with a border of "
                         f"{border_pix} pixels; use a smaller border.")
    return x0, x1, y0, y1


def placement_area_arcmin2(shape, pixel_scale: float, border_pix: float = 0.0) -> float:
    """Area of the placement region (image minus border), arcmin^2.

    Parameters
    ----------
    shape : (ny, nx)
        Image shape in pixels.
    pixel_scale : float
        Arcseconds per pixel.
    border_pix : float
        Border excluded at each edge, pixels.
    """
    x0, x1, y0, y1 = _region(shape, border_pix)
    return float((x1 - x0) * (y1 - y0) * (pixel_scale / 60.0) ** 2)


def draw_count(density: float, shape, pixel_scale: float, rng: np.random.Generator, *,
               border_pix: float = 0.0) -> int:
    """Poisson-drawn number of injections for ``density`` per arcmin^2.

    The mean is ``density`` times the area of the whole placement region
    (masked pixels included; see ``docs/injection.md`` for why this gives the
    configured density on the unmasked area).

    Parameters
    ----------
    density : float
        Mean injections per arcmin^2.
    shape : (ny, nx)
        Image shape.
    pixel_scale : float
        Arcseconds per pixel.
    rng : numpy.random.Generator
        Source of randomness (one Poisson draw).
    border_pix : float
        Border excluded at each edge, pixels.

    Returns
    -------
    int
    """
    if not density > 0:
        raise InputError(f"injection density must be positive, got {density!r}.")
    if not pixel_scale > 0:
        raise InputError(f"pixel scale must be positive (arcsec/pixel), got {pixel_scale!r}.")
    return int(rng.poisson(density * placement_area_arcmin2(shape, pixel_scale, border_pix)))


def pixel_index(x, y, shape) -> tuple[np.ndarray, np.ndarray]:
    """Integer pixel ``(ix, iy)`` containing each position (``floor(x + 0.5)``), clipped to the image."""
    ny, nx = (int(v) for v in shape)
    ix = np.clip(np.floor(np.asarray(x, dtype=float) + 0.5).astype(np.int64), 0, nx - 1)
    iy = np.clip(np.floor(np.asarray(y, dtype=float) + 0.5).astype(np.int64), 0, ny - 1)
    return ix, iy


def masked_at(x, y, mask) -> np.ndarray:
    """True where position ``(x, y)`` falls on a masked pixel of ``mask`` (bool, True = bad)."""
    x = np.asarray(x, dtype=float)
    if mask is None:
        return np.zeros(x.shape, dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    ix, iy = pixel_index(x, y, mask.shape)
    return mask[iy, ix]


def _thin_batch(cx, cy, accepted_tree, r):
    """Indices of the candidates kept: none closer than ``r`` to accepted points or to earlier kept ones."""
    keep = np.ones(cx.size, dtype=bool)
    pts = np.column_stack([cx, cy])
    if accepted_tree is not None and accepted_tree.n > 0:
        dist, _ = accepted_tree.query(pts, k=1, distance_upper_bound=r)
        keep &= ~(dist < r)
    idx = np.flatnonzero(keep)
    if idx.size > 1:
        pairs = cKDTree(pts[idx]).query_pairs(r, output_type="ndarray")
        if pairs.size:
            # query_pairs returns i < j; dropping the later one of every close pair leaves no close pair
            # (it may drop a few more than strictly necessary, which does not bias the positions).
            drop = np.unique(pairs.max(axis=1))
            keep[idx[drop]] = False
    return np.flatnonzero(keep)


def _place_sequential(n, draw_batch, r, max_rounds=60):
    """Accept batches of candidates from ``draw_batch(m)`` until ``n`` are kept or placement stalls."""
    xs, ys = np.empty(0), np.empty(0)
    tree = None
    stalled = 0
    for _ in range(max_rounds):
        need = n - xs.size
        if need <= 0:
            break
        m = int(need * 1.25) + 32
        cx, cy = draw_batch(m)
        if r > 0:
            kept = _thin_batch(cx, cy, tree, r)
        else:
            kept = np.arange(cx.size)
        kept = kept[:need]
        if kept.size < 0.01 * m:
            stalled += 1
            if stalled >= 3:
                break
        else:
            stalled = 0
        xs = np.concatenate([xs, cx[kept]])
        ys = np.concatenate([ys, cy[kept]])
        if r > 0 and kept.size:
            tree = cKDTree(np.column_stack([xs, ys]))
    return xs, ys


def place_sources(n: int, shape, rng: np.random.Generator, *, mask=None, method: str = "uniform",
                  min_sep_pix: float = 0.0, border_pix: float = 0.0) -> Placement:
    """Positions of ``n`` injections on an image.

    Parameters
    ----------
    n : int
        Number of positions wanted (e.g. from :func:`draw_count`).
    shape : (ny, nx)
        Image shape in pixels.
    rng : numpy.random.Generator
        The only source of randomness; the same generator state gives the same
        positions.
    mask : ndarray of bool, shape (ny, nx), optional
        True on unusable pixels.  Positions are not avoided there; they are
        flagged in ``Placement.masked``.
    method : {"uniform", "grid", "halton"}
        See ``docs/injection.md`` ("Placement").
    min_sep_pix : float
        Minimum distance between any two positions, pixels (0 = none).
    border_pix : float
        Width of the edge strip kept free of positions, pixels.

    Returns
    -------
    Placement
        Positions in the order they were drawn (a random order for ``grid``).

    Warns
    -----
    UserWarning
        When fewer than ``n`` positions fit at ``min_sep_pix``.
    """
    if method not in PLACEMENT_METHODS:
        raise InputError(f"unknown placement method {method!r}; use one of {PLACEMENT_METHODS}.")
    if len(tuple(shape)) != 2:
        raise InputError(f"image shape must be (ny, nx), got {shape!r}.")
    n = int(n)
    if n < 0:
        raise InputError(f"number of injections must be >= 0, got {n}.")
    if not min_sep_pix >= 0:
        raise InputError(f"minimum separation must be >= 0 pixels, got {min_sep_pix!r}.")
    if mask is not None and np.shape(mask) != tuple(shape):
        raise InputError(f"mask shape {np.shape(mask)} differs from the image shape {tuple(shape)}.")
    x0, x1, y0, y1 = _region(shape, border_pix)
    r = float(min_sep_pix)

    if n == 0:
        xs, ys = np.empty(0), np.empty(0)
    elif method == "uniform":
        def batch(m):
            return rng.uniform(x0, x1, m), rng.uniform(y0, y1, m)

        xs, ys = _place_sequential(n, batch, r)
    elif method == "halton":
        try:
            engine = qmc.Halton(d=2, scramble=True, rng=rng)
        except TypeError:  # SciPy < 1.15 names the argument ``seed``
            engine = qmc.Halton(d=2, scramble=True, seed=rng)

        def batch(m):
            u = engine.random(m)
            return x0 + (x1 - x0) * u[:, 0], y0 + (y1 - y0) * u[:, 1]

        xs, ys = _place_sequential(n, batch, r)
    else:
        xs, ys = _place_grid(n, (x0, x1, y0, y1), r, rng)

    complete = xs.size == n
    message = ""
    if not complete:
        area = (x1 - x0) * (y1 - y0)
        jam = int(_RSA_JAMMING_COVERAGE * area / (np.pi * r * r / 4.0)) if r > 0 else n
        message = (f"only {xs.size} of {n} injections fit with a minimum separation of {r:.2f} pixels "
                   f"({method} placement; random packing saturates near {jam}); lower injection.density or "
                   f"injection.min_sep")
        warnings.warn(message, UserWarning, stacklevel=2)
    return Placement(x=np.asarray(xs, dtype=float), y=np.asarray(ys, dtype=float),
                     masked=masked_at(xs, ys, mask) if xs.size else np.zeros(0, dtype=bool),
                     n_requested=n, method=method, min_sep_pix=r, border_pix=float(border_pix),
                     complete=complete, message=message)


#: Rounds of candidates :func:`place_sized_sources` draws (one per unplaced source each round) before it
#: gives up on the sources still unplaced.
SIZED_MAX_ROUNDS = 200


def place_sized_sources(radius_pix, half_pix, shape, rng: np.random.Generator, *, mask=None,
                        method: str = "uniform", max_rounds: int = SIZED_MAX_ROUNDS) -> Placement:
    """Positions of sources of different sizes, each where its stamp lies wholly on the image.

    Source ``i`` is kept ``radius_pix[i] + radius_pix[j]`` pixels or more from
    every other source ``j`` (per-source separation: two small galaxies may sit
    closer than two large ones) and its centre pixel at least ``half_pix[i]``
    pixels from every edge, so that its stamp of ``2 half_pix[i] + 1`` pixels
    lies on the image.  Dart throwing: each round draws one candidate for every
    source not yet placed, inside that source's own region, largest radius
    first; a candidate is kept when it is far enough from the placed sources
    and from the candidates of larger sources kept in the same round.  After
    ``max_rounds`` rounds (or when the region of a source is empty: a stamp
    wider than the image) the sources left are not placed.

    Parameters
    ----------
    radius_pix : array_like, shape (n,)
        Separation radius of each source, pixels (>= 0).
    half_pix : array_like, shape (n,)
        Stamp half-size of each source, pixels (>= 0).
    shape : (ny, nx)
    rng : numpy.random.Generator
        The only source of randomness.
    mask : ndarray of bool, optional
        Positions on masked pixels are flagged (not avoided), as in :func:`place_sources`.
    method : {"uniform", "halton"}
        Candidates uniform at random, or from a scrambled Halton sequence
        mapped into each source's region.
    max_rounds : int

    Returns
    -------
    Placement
        ``index`` says which source each position belongs to; ``min_sep_pix``
        is the smallest pair separation enforced (twice the smallest radius),
        ``border_pix`` the smallest border.

    Warns
    -----
    UserWarning
        When some sources could not be placed.
    """
    if method not in ("uniform", "halton"):
        raise InputError(f"sized placement supports 'uniform' and 'halton', got {method!r}.")
    radius = np.asarray(radius_pix, dtype=float).ravel()
    half = np.asarray(half_pix, dtype=float).ravel()
    if radius.shape != half.shape:
        raise InputError(f"radius_pix and half_pix differ in length ({radius.size} and {half.size}).")
    if radius.size and not (np.all(radius >= 0) and np.all(half >= 0)):
        raise InputError("separation radii and stamp half-sizes must be >= 0 pixels.")
    if mask is not None and np.shape(mask) != tuple(shape):
        raise InputError(f"mask shape {np.shape(mask)} differs from the image shape {tuple(shape)}.")
    ny, nx = (int(v) for v in shape)
    n = radius.size
    # centre pixel ix in [h, nx - 1 - h]  <=>  x in [h - 0.5, nx - 0.5 - h)
    x0, x1 = half - 0.5, nx - 0.5 - half
    y0, y1 = half - 0.5, ny - 0.5 - half
    fits = (x1 > x0) & (y1 > y0)
    order = np.argsort(-radius, kind="stable")  # largest first: they need the most room
    order = order[fits[order]]
    xs = np.full(n, np.nan)
    ys = np.full(n, np.nan)
    placed = np.zeros(n, dtype=bool)
    engine = None
    if method == "halton":
        try:
            engine = qmc.Halton(d=2, scramble=True, rng=rng)
        except TypeError:  # SciPy < 1.15 names the argument ``seed``
            engine = qmc.Halton(d=2, scramble=True, seed=rng)
    r_max = float(radius.max()) if n else 0.0
    todo = order
    for _ in range(int(max_rounds)):
        if todo.size == 0:
            break
        u = engine.random(todo.size) if engine is not None else rng.uniform(0.0, 1.0, (todo.size, 2))
        cx = x0[todo] + (x1[todo] - x0[todo]) * u[:, 0]
        cy = y0[todo] + (y1[todo] - y0[todo]) * u[:, 1]
        ok = np.ones(todo.size, dtype=bool)
        done = np.flatnonzero(placed)
        if done.size and r_max > 0:
            tree = cKDTree(np.column_stack([xs[done], ys[done]]))
            near = tree.query_ball_point(np.column_stack([cx, cy]), radius[todo] + r_max)
            for k, hits in enumerate(near):
                if hits:
                    j = done[hits]
                    ok[k] = bool(np.all(np.hypot(xs[j] - cx[k], ys[j] - cy[k]) >= radius[todo[k]] + radius[j]))
        idx = np.flatnonzero(ok)
        if idx.size > 1 and r_max > 0:
            pts = np.column_stack([cx[idx], cy[idx]])
            pairs = cKDTree(pts).query_pairs(2.0 * r_max, output_type="ndarray")
            if pairs.size:
                a, b = idx[pairs[:, 0]], idx[pairs[:, 1]]
                close = np.hypot(cx[a] - cx[b], cy[a] - cy[b]) < radius[todo[a]] + radius[todo[b]]
                # todo is ordered largest first, so the later of a close pair is the smaller source
                ok[np.unique(np.maximum(a, b)[close])] = False
        take = todo[ok]
        xs[take], ys[take] = cx[ok], cy[ok]
        placed[take] = True
        todo = todo[~ok]
    index = np.flatnonzero(placed)
    complete = index.size == n
    message = ""
    if not complete:
        wide = int(np.count_nonzero(~fits))
        why = f"; {wide} of them have stamps wider than the image" if wide else ""
        message = (f"only {index.size} of {n} galaxies fit, each keeping its own separation radius "
                   f"({radius.min():.1f}-{radius.max():.1f} px) plus its neighbour's from the others and its whole "
                   f"stamp on the image{why}; the other {n - index.size} are left out of this realization")
        warnings.warn(message, UserWarning, stacklevel=2)
    xs, ys = xs[index], ys[index]
    return Placement(x=xs, y=ys, masked=masked_at(xs, ys, mask) if xs.size else np.zeros(0, dtype=bool),
                     n_requested=n, method=method, min_sep_pix=float(2.0 * radius.min()) if n else 0.0,
                     border_pix=float(half.min()) if n else 0.0, complete=complete, message=message, index=index)


def _place_grid(n, region, r, rng):
    x0, x1, y0, y1 = region
    w, h = x1 - x0, y1 - y0
    cell = np.sqrt(w * h / n)
    ncx = max(1, int(np.floor(w / cell)))
    ncy = max(1, int(np.floor(h / cell)))
    while ncx * ncy < n:  # grow the dimension whose cells are currently larger
        if w / ncx >= h / ncy:
            ncx += 1
        else:
            ncy += 1
    if r > 0 and min(w / ncx, h / ncy) < r:
        ncx = max(1, int(np.floor(w / r)))
        ncy = max(1, int(np.floor(h / r)))
    cw, ch = w / ncx, h / ncy
    ncell = ncx * ncy
    chosen = rng.choice(ncell, size=min(n, ncell), replace=False)
    jx = max(0.0, (cw - r) / 2.0)
    jy = max(0.0, (ch - r) / 2.0)
    ix, iy = chosen % ncx, chosen // ncx
    xs = x0 + (ix + 0.5) * cw + rng.uniform(-jx, jx, chosen.size)
    ys = y0 + (iy + 0.5) * ch + rng.uniform(-jy, jy, chosen.size)
    # keep strictly inside the half-open region
    xs = np.minimum(xs, np.nextafter(x1, x0))
    ys = np.minimum(ys, np.nextafter(y1, y0))
    return xs, ys
