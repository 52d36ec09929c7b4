"""Checks a run makes before it writes its first byte.

:func:`choose_density` (injections per realization), :func:`check_injection_count` (enough
usable injections) and :func:`check_memory` (the placement fits in memory); pure functions of
shapes, configuration and the machine's memory figures, nothing is written.  The rules:
``docs/injection.md`` ("Checks before the first byte").
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from comest_bayes.errors import ConfigError, InputError
from comest_bayes.inject.placement import PUBLISHED_DENSITY as _PUBLISHED_DENSITY
from comest_bayes.inject.population import draw_parameters
from comest_bayes.inject.render import (min_separation_pix, placement_capacity, psf_enclosed_radius_pix,
                                        psf_radius_pix, separation_radius_pix, sizing_rule)
from comest_bayes.inject.psfmodel import make_psf
from comest_bayes.seeding import rng_for

__all__ = ["MIN_USABLE_INJECTIONS", "FEW_USABLE_INJECTIONS", "SMALLEST_SEEING_PIX", "PUBLISHED_DENSITY",
           "TARGET_PER_REALIZATION", "PER_BACKGROUND_MESH", "MAX_PER_BACKGROUND_MESH", "HOLD_FRACTION",
           "BRIGHT_REACH", "BRIGHT_NEIGHBOUR_WARN", "bright_neighbours", "CONFUSION_SPAN", "CONFUSION_RISE",
           "CONFUSION_COVER", "CONFUSION_MAX_SHIFT", "footprint_cover", "confused_bright_end", "DensityChoice",
           "choose_density",
           "choose_densities", "InjectionBudget", "stamp_half_size", "injection_budget", "check_injection_count",
           "budget_warnings", "injection_memory", "available_memory", "check_memory"]

#: Fewest expected usable injections per kind (all realizations together) a run accepts.
MIN_USABLE_INJECTIONS = 10
#: Below this many expected usable injections per kind (all realizations together) a run warns that
#: its m50 will be loose: with 100 outcomes spread over 6.5 mag the 0.2-mag bins at the transition
#: hold about 3 each.
FEW_USABLE_INJECTIONS = 100
#: A seeing wider than this (arcsec) given with --fwhm is questioned in the messages.
IMPLAUSIBLE_SEEING_ARCSEC = 5.0
#: Seeing (pixels) assumed when it cannot be measured, to tell an image too small for any injection.
SMALLEST_SEEING_PIX = 2.0
#: Light fraction a stamp holds (``render_truth``'s default ``flux_fraction``).
STAMP_FLUX_FRACTION = 0.995
#: Random sequential packing of discs stalls near this covered fraction (Feder 1980).
JAMMING_COVERAGE = 0.547

#: ComEst's published injection density, per arcmin^2 (re-exported from :mod:`comest_bayes.inject.placement`).
PUBLISHED_DENSITY = _PUBLISHED_DENSITY
#: Mean injections per realization the automatic density aims for where the published density gives fewer.
TARGET_PER_REALIZATION = 100.0
#: Most injections per background mesh (``detection.back_size`` squared pixels) the automatic density
#: raises to.  Injections lift the background meshes of the detection run on each realization, and m50
#: moves bright with their number: on the shared JWST image (probit m50 minus the noise prediction,
#: mean over 7-11 seeds, +-0.013) +0.038 mag at 0.11 per 64-pixel mesh, +0.032 at 0.25, +0.000 at 0.43
#: and -0.013 at 1 (binned m50: +0.026, -0.024, -0.026, -0.059); on 200x200 DECam cutouts 4.6 per mesh
#: moved it 0.2 mag.  A quarter per mesh stays within the scatter of the sparse case.  (The published
#: density gives 0.7-1.2 per mesh at ground-based pixel scales; the automatic density never goes below
#: it.)
PER_BACKGROUND_MESH = 0.25
#: Most injections per background mesh the automatic density ever asks for.  It is the published
#: density's own load at ground-based pixel scales (1.15 per 64-pixel mesh on the 0.26"/px demo tile,
#: 1.17 on DECam's 0.262"/px), so it changes nothing there; it binds on coarse pixels, where 15 per
#: arcmin^2 would put tens of injections in each mesh.  On the shared 2MASS field (5"/px, 721x720),
#: what the placement holds, 5021 point sources per realization (38 usable per mesh, as many as the
#: sources the image has), lowered the measured completeness by 0.06-0.12 at 8.6-11.1 mag against 160
#: per realization (1.2 per mesh), and moved the binned m50 to 9.57 mag from 9.98-10.16; 53 per
#: realization (0.4 per mesh) agreed with 160 within 1.5 sd in every 0.5-mag bin
#: (benchmarks/bench_crowded_density.py, docs/usage.md).
MAX_PER_BACKGROUND_MESH = 1.25
#: Fraction of the random-packing count at the minimum separation (``JAMMING_COVERAGE``) the automatic
#: density fills at most: dart throwing still places every injection there without stalling.
HOLD_FRACTION = 0.5
#: Sized kinds: the placement must keep at least this fraction of the galaxies asked for, on average
#: (galaxies it cannot place are left out of the realization; the ones left out are not a random
#: draw of the population, so few may be).
SIZED_PLACED_FRACTION = 0.95
#: Largest count per realization whose placement :func:`sized_capacity` runs (above: random packing).
SIMULATED_MAX = 400
#: Trials per count when measuring what a sized kind's placement holds (fewer for large counts).
CAPACITY_TRIALS = 20


def _placed_fraction(kind, n, *, shape, pixel_scale, fwhm_pix, injection, r_psf_pix) -> float:
    trials = max(2, min(CAPACITY_TRIALS, int(1000 // max(n, 1))))
    placed = [placement_capacity(kind, shape=shape, pixel_scale=pixel_scale, fwhm_pix=fwhm_pix, config=injection,
                                 n_try=n, seed=seed, r_psf_pix=r_psf_pix)[0] for seed in range(trials)]
    return float(np.mean(placed)) / n


def sized_capacity(kind: str, *, shape, pixel_scale: float, fwhm_pix: float | None, injection,
                   wanted: float) -> tuple[float, bool]:
    """What the placement of a sized kind (:data:`comest_bayes.inject.render.SIZED_KINDS`) holds per realization.

    Each galaxy keeps its own separation and its whole stamp on the image, so
    what fits depends on the image's shape and the drawn sizes: the placement
    of a realization is run on the image (fixed seeds, :data:`CAPACITY_TRIALS`
    trials per count).  Returns ``(count, full)``: ``full`` False when
    ``ceil(wanted)`` galaxies are placed with at least
    :data:`SIZED_PLACED_FRACTION` of them kept (``count`` is then
    ``wanted``); else the largest count that keeps that fraction (bisection;
    at least 1).  Above :data:`SIMULATED_MAX` galaxies per realization the
    count is instead ``HOLD_FRACTION`` of the random packing of discs of the
    population's mean squared separation radius.
    """
    top = max(1, int(math.ceil(wanted)))
    if top > SIMULATED_MAX:
        # many small stamps on a large field: the edges hardly matter, random packing of the discs does
        params = draw_parameters(kind, 4000, config=injection, mag_range=(20.0, 21.0), rng=rng_for(0),
                                 pixel_scale=pixel_scale)
        r = separation_radius_pix(injection, fwhm_pix, pixel_scale, params["hlr_arcsec"])
        ny, nx = (int(v) for v in shape)
        hold = HOLD_FRACTION * JAMMING_COVERAGE * nx * ny / (math.pi * float(np.mean(r * r)))
        return (float(wanted), False) if hold >= wanted else (float(hold), True)
    opts = dict(shape=shape, pixel_scale=pixel_scale, fwhm_pix=fwhm_pix, injection=injection,
                r_psf_pix=psf_radius_pix(None, injection, fwhm_pix, pixel_scale))
    if _placed_fraction(kind, top, **opts) >= SIZED_PLACED_FRACTION:
        return float(wanted), False
    lo, hi = 1, top  # lo: kept (or the floor of 1), hi: not kept
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if _placed_fraction(kind, mid, **opts) >= SIZED_PLACED_FRACTION:
            lo = mid
        else:
            hi = mid
    return float(lo), True


@dataclass(frozen=True)
class DensityChoice:
    """How many injections of one kind a realization asks for, and why.

    Attributes
    ----------
    kind : str
    density : float
        Injections per arcmin^2 used (``per_realization / area_arcmin2``).
    per_realization : float
        Mean injections per realization (the Poisson mean).
    source : {"user", "automatic"}
    rule : str
        ``user`` (the density given), ``published`` (the published density is enough),
        ``raised`` (the published density gives fewer than the target: raised up to the target, the
        background cap and what the placement holds), ``placement cap`` (the published density is
        more than the placement holds: lowered to it) or ``background cap`` (the published density
        would put more than ``MAX_PER_BACKGROUND_MESH`` in each background mesh: lowered to that).
    warning : str or None
        A user's density above ``MAX_PER_BACKGROUND_MESH`` per background mesh: what it risks.
    min_sep_arcsec : float or None
        A separation the run chose for this kind instead of the automatic one (point sources of a
        range far brighter than the detection limit: ``comest_bayes.pipeline.stages``); None when
        the kind keeps ``injection.min_sep``'s rule.
    reason : str
        One sentence for the log and the report.
    area_arcmin2, published, target, mesh_cap, hold_cap : float
        The image's area, the count the published density gives, the target, the background cap
        (``PER_BACKGROUND_MESH`` per mesh) and what the placement holds (inf without a minimum
        separation), per realization.
    min_sep_pix : float
        The separation of all pairs; for per-source separations (``sizing["per_source"]``) that of
        the pair of the largest galaxies.
    sizing : dict
        The separation and stamp rules (:func:`comest_bayes.inject.render.sizing_rule`).
    """

    kind: str
    density: float
    per_realization: float
    source: str
    rule: str
    reason: str
    area_arcmin2: float
    published: float
    target: float
    mesh_cap: float
    hold_cap: float
    min_sep_pix: float
    sizing: dict | None = None
    warning: str | None = None
    min_sep_arcsec: float | None = None

    def to_dict(self) -> dict:
        d = dict(self.__dict__)
        d["hold_cap"] = d["hold_cap"] if math.isfinite(d["hold_cap"]) else None
        return d


def choose_density(kind: str, *, shape, pixel_scale: float, fwhm_pix: float | None, injection,
                   back_size: int = 64) -> DensityChoice:
    """The injection density of ``kind`` on an image: the user's, or chosen from the image.

    With ``injection.density > 0`` that density is kept.  With 0 (automatic), counted per
    realization on the whole image of area ``A``:

    * ``published = PUBLISHED_DENSITY x A``;
    * ``mesh_cap = PER_BACKGROUND_MESH x npix / back_size^2``: injections lift the background
      meshes of the detection run on each realization, biasing m50 bright;
    * ``hold_cap = HOLD_FRACTION x JAMMING_COVERAGE x npix / (pi r^2 / 4)``, ``r`` the kind's
      minimum separation (:func:`comest_bayes.inject.render.min_separation_pix`): what the placement
      holds without the injections blending with each other; for the kinds placed source by source
      (:data:`comest_bayes.inject.render.SIZED_KINDS`: each galaxy keeps its own separation and its
      whole stamp on the image) the largest count their placement keeps on this image
      (:func:`sized_capacity`);
    * the count is ``hold_cap`` when ``published`` exceeds it (coarse pixels, wide separations);
      else ``published`` when it reaches ``TARGET_PER_REALIZATION`` (large images: the published
      density unchanged); else ``max(published, min(TARGET_PER_REALIZATION, mesh_cap, hold_cap))``
      (small fields of fine pixels, e.g. 1.6 per realization on a 640x640 JWST image at 0.031"/px);
    * and never more than ``MAX_PER_BACKGROUND_MESH x npix / back_size^2`` (coarse pixels: on the
      2MASS field at 5"/px, 160 per realization instead of the 5021 the placement holds).

    ``fwhm_pix`` None (the seeing not yet known) takes a point source's separation as 0.
    """

    ny, nx = (int(v) for v in shape)
    npix = nx * ny
    area = npix * (pixel_scale / 60.0) ** 2
    r = float(min_separation_pix(injection, fwhm_pix, pixel_scale, kind))
    published = PUBLISHED_DENSITY * area
    mesh = PER_BACKGROUND_MESH * npix / float(back_size) ** 2
    sizing = sizing_rule(kind, injection)
    if sizing["per_source"]:
        wanted = injection.density * area if injection.density > 0 else max(published, min(TARGET_PER_REALIZATION, mesh))
        hold, full = sized_capacity(kind, shape=(ny, nx), pixel_scale=pixel_scale, fwhm_pix=fwhm_pix,
                                    injection=injection, wanted=wanted)
        hold = hold if full else math.inf
        held = (f"{hold:.0f} held by the placement (each galaxy kept its own separation and its whole stamp on the "
                f"image; at most {100 * (1 - SIZED_PLACED_FRACTION):.0f}% left out)") if full else ""
    else:
        hold = HOLD_FRACTION * JAMMING_COVERAGE * npix / (math.pi * r * r / 4.0) if r > 0 else math.inf
        held = f"{hold:.1f} held by the placement at the {r:.1f} px minimum separation" if r > 0 else ""
    facts = dict(kind=kind, area_arcmin2=area, published=published, target=TARGET_PER_REALIZATION,
                 mesh_cap=mesh, hold_cap=hold, min_sep_pix=r, sizing=sizing)
    meshes = npix / float(back_size) ** 2
    ceiling = MAX_PER_BACKGROUND_MESH * meshes
    if injection.density > 0:
        n = injection.density * area
        warning = None
        if n > ceiling:
            warning = (f"{injection.density:g} per arcmin^2 puts {n / meshes:.1f} injections in each "
                       f"{back_size}x{back_size} background mesh (more than {MAX_PER_BACKGROUND_MESH:g}): the injections "
                       f"lift the background and crowd the image, which lowers the completeness they measure; "
                       f"{MAX_PER_BACKGROUND_MESH * meshes / area:.3g} per arcmin^2 ({ceiling:.0f} per realization) or "
                       f"less, with more realizations (--nsims), avoids it")
        return DensityChoice(density=float(injection.density), per_realization=n, source="user", rule="user",
                             reason=f"{injection.density:g} per arcmin^2 as given ({n:.1f} per realization)",
                             warning=warning, **facts)
    if published > hold:
        n, rule = hold, "placement cap"
        why = (f"the published {PUBLISHED_DENSITY:g} per arcmin^2 would ask for {published:.0f} per realization, "
               f"more than the placement holds: lowered to the {held}")
    elif published >= TARGET_PER_REALIZATION:
        n, rule = published, "published"
        why = (f"the published {PUBLISHED_DENSITY:g} per arcmin^2, {n:.0f} per realization (at least the "
               f"target of {TARGET_PER_REALIZATION:g})")
    else:
        n = max(published, min(TARGET_PER_REALIZATION, mesh, hold))
        limits = [f"the target {TARGET_PER_REALIZATION:g}", f"{mesh:.1f} ({PER_BACKGROUND_MESH:g} per "
                  f"{back_size}x{back_size} background mesh)"] + ([held] if held else [])
        if n == published:
            rule = "published"
            why = (f"the published {PUBLISHED_DENSITY:g} per arcmin^2, {n:.1f} per realization (no fewer than the "
                   f"smallest of {', '.join(limits)})")
        else:
            rule = "raised"
            why = (f"the published {PUBLISHED_DENSITY:g} per arcmin^2 gives only {published:.1f} per realization on "
                   f"this {nx}x{ny} image; raised to {n:.1f}, the smallest of {', '.join(limits)}")
    if n > ceiling:
        why = (f"{why}; lowered further to {ceiling:.0f}, {MAX_PER_BACKGROUND_MESH:g} per {back_size}x{back_size} "
               f"background mesh (more lift the background and crowd the image, lowering the completeness they "
               f"measure)")
        n, rule = ceiling, "background cap"
    density = PUBLISHED_DENSITY if n == published else n / area  # (15, not 15.000000000000002)
    return DensityChoice(density=density, per_realization=n, source="automatic", rule=rule,
                         reason=f"{density:.4g} per arcmin^2, automatic: {why}", **facts)


def choose_densities(*, shape, pixel_scale: float, fwhm_pix: float | None, injection,
                     back_size: int = 64) -> dict:
    """:func:`choose_density` for every kind of ``injection.kinds``: ``{kind: DensityChoice}``."""
    return {kind: choose_density(kind, shape=shape, pixel_scale=pixel_scale, fwhm_pix=fwhm_pix,
                                 injection=injection, back_size=back_size) for kind in injection.kinds}


# Memory model of one realization, measured on this package's code (tracemalloc and peak RSS):
#: bytes per image pixel held by a worker (image, mask and noise copies, the rendered image,
#: detection buffers): 1.7 GB at 8192^2 in the injection benchmark.
PIXEL_BYTES = 25.0
#: bytes per placement candidate (positions, k-d tree, distances; 1.25 candidates per injection asked for).
CANDIDATE_BYTES = 80.0
#: bytes per candidate pair closer than the minimum separation (scipy's query_pairs output).
PAIR_BYTES = 16.0
#: bytes per placed injection in a worker (truth row, stamp, matching) and in the merge (all tables).
INJECTION_BYTES = 2000.0
#: Environment variable overriding the memory budget, in GB (e.g. on a cluster node whose limit differs).
MEMORY_ENV = "COMEST_BAYES_MEMORY_GB"


@dataclass(frozen=True)
class InjectionBudget:
    """What one kind's injections can give on an image.

    Attributes
    ----------
    kind : str
    density : float
        Injections asked for per arcmin^2.
    requested : float
        Mean injections asked for per realization (density x area).
    placeable : float
        How many fit at the minimum separation (inf without one); for sized kinds the most their
        placement holds (:func:`sized_capacity`; inf when ``requested`` fits).
    min_sep_pix : float
    stamp_half : int
        Half-size (pixels) of a point-source stamp (the smallest stamp).
    inner_fraction : float
        Fraction of the image's pixels that are unmasked and at least
        ``stamp_half`` from every edge (sized kinds, placed where their stamps
        fit: the unmasked fraction).
    usable_per_realization : float
        Expected usable injections per realization (an upper bound).
    sized : bool
        Placed source by source, each where its own stamp fits (see ``placeable``, ``inner_fraction``).
    """

    kind: str
    density: float
    requested: float
    placeable: float
    min_sep_pix: float
    stamp_half: int
    inner_fraction: float
    usable_per_realization: float
    sized: bool = False

    @property
    def placed(self) -> float:
        return min(self.requested, self.placeable)


def stamp_half_size(injection, fwhm_pix: float, pixel_scale: float) -> int:
    """Half-size in pixels of a point source's stamp (the smallest an injection gets)."""
    import galsim


    psf = make_psf(injection, fwhm_pix, pixel_scale)
    radius, _ = psf_enclosed_radius_pix(galsim.PixelScale(pixel_scale).toImage(psf), STAMP_FLUX_FRACTION)
    return max(2, int(math.ceil(radius + 1.0)))


def _inner_unmasked(mask: np.ndarray, half: int) -> int:
    ny, nx = mask.shape
    if nx <= 2 * half or ny <= 2 * half:
        return 0
    return int(np.count_nonzero(~mask[half:ny - half, half:nx - half]))


def injection_budget(kind: str, *, shape, mask, pixel_scale: float, fwhm_pix: float, injection,
                     stamp_half: int | None = None, density: float | None = None) -> InjectionBudget:
    """Expected injections of ``kind`` per realization on an image (see ``docs/injection.md``).

    ``density`` (per arcmin^2) overrides ``injection.density`` (e.g. the automatic choice of
    :func:`choose_density`); an automatic ``injection.density`` of 0 without it counts at the
    published density.
    """

    density = float(density if density is not None else (injection.density or PUBLISHED_DENSITY))
    ny, nx = (int(v) for v in shape)
    npix = nx * ny
    area = npix * (pixel_scale / 60.0) ** 2
    requested = density * area
    r = float(min_separation_pix(injection, fwhm_pix, pixel_scale, kind))
    half = stamp_half if stamp_half is not None else stamp_half_size(injection, fwhm_pix, pixel_scale)
    mask = np.zeros((ny, nx), bool) if mask is None else np.asarray(mask, bool)
    sized = bool(sizing_rule(kind, injection)["per_source"])
    if sized:
        # placed where their stamps fit: what the placement reaches, every one on the image
        hold, full = sized_capacity(kind, shape=(ny, nx), pixel_scale=pixel_scale, fwhm_pix=fwhm_pix,
                                    injection=injection, wanted=requested)
        placeable = hold if full else math.inf
        inner = float(np.count_nonzero(~mask)) / npix
    else:
        placeable = JAMMING_COVERAGE * npix / (math.pi * r * r / 4.0) if r > 0 else math.inf
        inner = _inner_unmasked(mask, half) / npix
    return InjectionBudget(kind=kind, density=density, requested=requested, placeable=placeable, min_sep_pix=r, stamp_half=half,
                           inner_fraction=inner, usable_per_realization=min(requested, placeable) * inner, sized=sized)


def check_injection_count(*, shape, mask, pixel_scale: float, fwhm_pix: float | None, injection,
                          fwhm_given: bool = False, fwhm_assumed: bool = False,
                          densities: dict | None = None) -> list[InjectionBudget]:
    """Refuse a run whose injections cannot give :data:`MIN_USABLE_INJECTIONS` usable outcomes per kind.

    With ``fwhm_pix=None`` (the seeing not yet measured) only the count
    without stamps is checked: density x unmasked area x realizations.
    ``fwhm_given`` (the user's ``--fwhm``) adds a hint when the seeing is
    implausibly wide; ``fwhm_assumed`` words the message for a seeing assumed
    because it could not be measured.  ``densities`` maps each kind to its
    density per arcmin^2 or its :class:`DensityChoice`; by default
    :func:`choose_densities` on the image (the user's density when given).

    Returns
    -------
    list of InjectionBudget
        One per kind (empty when ``fwhm_pix`` is None).

    Raises
    ------
    InputError
        With the numbers and what to change.
    """
    ny, nx = (int(v) for v in shape)
    mask = np.zeros((ny, nx), bool) if mask is None else np.asarray(mask, bool)
    unmasked_area = float(np.count_nonzero(~mask)) * (pixel_scale / 60.0) ** 2
    nsims = int(injection.nsims)
    if densities is None:
        densities = choose_densities(shape=(ny, nx), pixel_scale=pixel_scale, fwhm_pix=fwhm_pix, injection=injection)
    chosen = {k: (v.density if isinstance(v, DensityChoice) else float(v)) for k, v in densities.items()}
    density = max(chosen.values())
    upper = density * unmasked_area * nsims
    # (an automatic density lowered to what the placement holds at a known seeing is judged per kind below,
    # where the message can say why)
    if upper < MIN_USABLE_INJECTIONS and (fwhm_pix is None or injection.density > 0):
        how = "" if injection.density > 0 else " (chosen automatically)"
        raise InputError(
            f"too few injections possible: {density:.4g} per arcmin^2{how} on this image's "
            f"{unmasked_area:.4g} arcmin^2 of unmasked area ({nx}x{ny} pixels of {pixel_scale:.3g}\") over "
            f"{nsims} realization(s) is {upper:.1f} injections per kind, and at least {MIN_USABLE_INJECTIONS} "
            f"usable ones are needed. Raise --nsims or --density, or use a larger image.")
    if fwhm_pix is None:
        return []
    budgets = []
    half = stamp_half_size(injection, fwhm_pix, pixel_scale)
    for kind in injection.kinds:
        b = injection_budget(kind, shape=(ny, nx), mask=mask, pixel_scale=pixel_scale, fwhm_pix=fwhm_pix,
                             injection=injection, stamp_half=half, density=chosen[kind])
        budgets.append(b)
        total = b.usable_per_realization * nsims
        if total >= MIN_USABLE_INJECTIONS:
            continue
        side = 2 * half + 1
        if fwhm_assumed:
            seeing = (f"even at a seeing FWHM as small as {fwhm_pix:.3g} px (the seeing could not be measured on "
                      f"this image)")
        else:
            seeing = f"at the seeing FWHM of {fwhm_pix:.3g} px"
            if fwhm_given and fwhm_pix * pixel_scale > IMPLAUSIBLE_SEEING_ARCSEC:
                seeing += f" = {fwhm_pix * pixel_scale:.3g}\" (--fwhm is in pixels: is that right?)"
        stamp = f"a point source's stamp (99.5% of its light) is {side}x{side} pixels {seeing}"
        if nx <= 2 * half or ny <= 2 * half:
            raise InputError(
                f"no injection can be usable on this {nx}x{ny} image: {stamp}, and an injection counts only when "
                f"its stamp lies wholly on the image. Use an image larger than {side} pixels on each side.")
        if b.inner_fraction == 0:
            raise InputError(
                f"no injection can be usable on this {nx}x{ny} image: {stamp}, and every pixel at least {half} px "
                f"from the edges, where a stamp fits, is masked. Check the mask and --mask-bits.")
        choice = densities.get(kind)
        # the automatic density already lowered to what the placement holds: a higher density cannot help
        held = (isinstance(choice, DensityChoice) and choice.source == "automatic"
                and math.isfinite(choice.hold_cap) and choice.per_realization >= 0.999 * choice.hold_cap)
        need = math.ceil(MIN_USABLE_INJECTIONS / b.usable_per_realization) if b.usable_per_realization > 0 else None
        nsims_hint = f"--nsims to {need} or more" if need else "--nsims"
        if b.placeable < b.requested or held:
            fit = min(b.placeable, b.requested)
            keep = ("each galaxy keeping its own separation and its whole stamp on the image" if b.sized else
                    f"at the minimum separation of {b.min_sep_pix:.1f} px between injections")
            why = (f"only about {fit:.1f} fit on this {nx}x{ny} image per realization, {keep}"
                   + (" (the automatic density is already that)" if held else f", of {b.requested:.1f} asked for"))
            advice = (f"Raise {nsims_hint}" + ("" if b.sized else ", or lower injection.min_sep")
                      + "; a higher --density cannot help.")
        else:
            why = f"{b.requested:.1f} are asked for per realization at {b.density:.4g} per arcmin^2"
            advice = f"Raise {nsims_hint} or --density, or use a larger image."
        edges = ""
        if b.inner_fraction < 0.9:
            edges = (f"; {stamp}, and only {100 * b.inner_fraction:.0f}% of the pixels are unmasked and at least "
                     f"{half} px from the edges")
        raise InputError(
            f"too few usable {kind} injections expected: {total:.1f} over {nsims} realization(s) ({why}{edges}), "
            f"and at least {MIN_USABLE_INJECTIONS} are needed. {advice}")
    return budgets


#: How far a bright point injection takes its fainter neighbours with it, in units of its detection
#: isophote's radius (:func:`comest_bayes.ratios.depth.isophote_radius_pix`).  Measured on 1024^2 white
#: noise (FWHM 3 px, Moffat beta 3, threshold 1.5 sigma, 175 point injections per realization, 60
#: realizations, 11.4-22.9 mag with m5 = 21.4): injections of 20.5-22 mag were detected 0-6% of the
#: time within 12-20 px of one brighter than 14 mag (isophote radius 9-13 px), 25% within 20-30 px and
#: 40-42% beyond (docs/injection.md, "Bright injections and their neighbours").
BRIGHT_REACH = 2.0
#: Share of the injections expected within the reach of a brighter one above which the run warns.
BRIGHT_NEIGHBOUR_WARN = 0.01


def bright_neighbours(mag_range, per_realization: float, area_pix: float, min_sep_pix: float,
                      radius_at, nmag: int = 200) -> dict:
    """Share of point injections expected within the reach of a brighter injection.

    Injections are uniform in magnitude over ``mag_range`` and in position
    over ``area_pix`` pixels, ``per_realization`` of them, at least
    ``min_sep_pix`` apart.  An injection of magnitude ``m`` reaches
    ``BRIGHT_REACH x radius_at(m)`` pixels (``radius_at``: the detection
    isophote's radius, vectorised over magnitudes); a neighbour inside that
    reach but beyond the separation is likely lost in it.  The share is the
    expected number of such neighbours per injection (a Poisson
    approximation: ``density x pi (reach^2 - sep^2)`` averaged over the
    range), which is small when the range is not far brighter than the
    detection limit.

    Returns
    -------
    dict
        ``fraction`` (the share), ``mag_reach`` (the faintest magnitude whose
        reach passes the separation, None when none does), ``radius_bright``
        (the isophote radius of the brightest injection, pixels),
        ``reach_bright`` (its reach, pixels: the separation that keeps every
        pair out of each other's reach) and ``min_sep_pix``.
    """
    lo, hi = (float(v) for v in mag_range)
    m = np.linspace(lo, hi, nmag)
    reach = BRIGHT_REACH * np.asarray(radius_at(m), dtype=float)
    excess = np.pi * np.clip(reach ** 2 - float(min_sep_pix) ** 2, 0.0, None)
    fraction = float(per_realization) / float(area_pix) * float(np.mean(excess)) if area_pix > 0 else 0.0
    over = m[reach > min_sep_pix]
    return {"fraction": fraction, "mag_reach": float(over.max()) if over.size else None,
            "radius_bright": float(reach[0] / BRIGHT_REACH), "reach_bright": float(reach[0]),
            "min_sep_pix": float(min_sep_pix)}


#: The automatic range's confusion check looks at the detected sources in the first CONFUSION_SPAN mag
#: of the range (from its bright end, m5 - 5, fainter).
CONFUSION_SPAN = 2.0
#: Share of the unmasked area their detection footprints may cover before the field counts as confused.
#: Measured on the run's first detection (benchmarks/bench_confusion.py): 0.0965 on the shared 2MASS
#: Galactic-centre frame, where point injections at m5 - 5 are only 71% complete; 0.0113 on the JWST
#: Abell 2744 frame, 0.0068 on KiDS, 0.0064 on the CTIO frame and 0.0033 on the DECam N6 cutout, whose
#: bright ends are complete.  On synthetic star fields: 0.036 at 100 stars per arcmin^2 brighter than m5
#: (bright end 0.94 complete), 0.11 at 300 (0.81; 0.92 from the brighter start) and at 1000 (0.58; 0.99).
CONFUSION_RISE = 0.05
#: On a confused field the range starts where the detected sources brighter than it cover this share of
#: the unmasked area: an injection there rarely lands on a brighter source.  On the 2MASS frame that is
#: 4.4 mag (m5 - 9.2), where point injections were 0.99 complete, against 0.95 at 5.7 mag (where a share
#: of 0.10 would start) and 0.71 at the usual bright end, 8.6 mag.
CONFUSION_COVER = 0.05
#: Farthest (mag) a confused field's bright end moves above the usual m5 - 5.
CONFUSION_MAX_SHIFT = 5.0


def footprint_cover(segmentation: np.ndarray, ids, mags, mask: np.ndarray | None = None):
    """Detection footprints' share of the unmasked area, by source magnitude.

    Returns ``(mag, share)``: the sources' magnitudes in increasing order
    (those with a finite magnitude) and the share of the unmasked pixels
    their segmentation footprints cover, each source's alone (sum a slice for
    the sources in a magnitude interval; the footprints do not overlap).
    """
    seg = np.asarray(segmentation)
    good = np.ones(seg.shape, bool) if mask is None else ~np.asarray(mask, bool)
    area = int(good.sum())
    ids = np.asarray(ids, dtype=np.int64)
    mags = np.asarray(mags, dtype=float)
    if area == 0 or ids.size == 0:
        return np.zeros(0), np.zeros(0)
    counts = np.bincount(seg[good].ravel().astype(np.int64), minlength=int(max(ids.max(), seg.max())) + 1)
    keep = np.isfinite(mags) & (ids > 0)
    order = np.argsort(mags[keep], kind="stable")
    return mags[keep][order], counts[ids[keep]][order] / area


def confused_bright_end(mag, share, lo: float) -> dict:
    """Where the automatic range should start on a confused field (see the ``CONFUSION_*`` settings).

    ``mag, share`` come from :func:`footprint_cover`; ``lo`` is the usual
    bright end (m5 - 5).  The field is confused when the footprints of the
    sources in ``[lo, lo + CONFUSION_SPAN)`` cover more than
    ``CONFUSION_RISE`` of the area: injections there land on sources of their
    own brightness or brighter, and the completeness falls from the first
    injected magnitude.  The bright end then moves to the magnitude where the
    sources brighter than it cover ``CONFUSION_COVER``, by at most
    ``CONFUSION_MAX_SHIFT`` mag.

    Returns
    -------
    dict
        ``rise`` (the share in the first span), ``confused`` (bool),
        ``bright`` (the new bright end, ``lo`` when not confused) and
        ``cover_bright`` (the share covered by sources brighter than it).
    """
    mag = np.asarray(mag, float)
    share = np.asarray(share, float)
    lo = float(lo)
    rise = float(share[(mag >= lo) & (mag < lo + CONFUSION_SPAN)].sum())
    brighter = np.cumsum(share)  # share covered by the sources up to and including each one
    bright = lo
    if rise > CONFUSION_RISE:
        over = np.flatnonzero(brighter > CONFUSION_COVER)
        # the magnitude of the source whose footprint takes the cover past the share, rounded down
        at = float(mag[over[0]]) if over.size else lo
        bright = max(min(math.floor(at * 10.0) / 10.0, lo), lo - CONFUSION_MAX_SHIFT)
    cover = float(share[mag < bright].sum())
    return {"rise": rise, "confused": rise > CONFUSION_RISE, "bright": bright, "cover_bright": cover}


def budget_warnings(budgets, nsims: int) -> list[str]:
    """Warnings for kinds whose expected usable injections, all realizations together, stay under
    :data:`FEW_USABLE_INJECTIONS` (the run goes on; its m50 will be loose)."""
    out = []
    for b in budgets:
        total = b.usable_per_realization * int(nsims)
        if total >= FEW_USABLE_INJECTIONS:
            continue
        if b.sized:
            where = (f"each placed where its whole stamp lies on the image, {100 * b.inner_fraction:.0f}% of the "
                     f"pixels unmasked")
            held = ""
        else:
            where = (f"{100 * b.inner_fraction:.0f}% of the pixels lie far enough from the edges for a point-source "
                     f"stamp, fewer for a galaxy's")
            held = (f"; only about {b.placeable:.1f} fit per realization at the {b.min_sep_pix:.0f} px minimum "
                    f"separation" if b.placeable < b.requested else "")
        need = math.ceil(FEW_USABLE_INJECTIONS / max(b.usable_per_realization, 1e-9))
        out.append(f"only about {total:.0f} usable {b.kind} injections expected over {nsims} realization(s) "
                   f"({b.placed:.1f} per realization{held}; {where}): its completeness will "
                   f"be loose. About {need} realizations would give {FEW_USABLE_INJECTIONS} (--nsims).")
    return out


def injection_memory(budgets, *, npix: int, nsims: int, workers: int) -> float:
    """Peak memory (bytes) the injection stage adds, from the model of the module constants.

    Per worker: ``PIXEL_BYTES npix`` plus placement (``CANDIDATE_BYTES`` per
    candidate and ``PAIR_BYTES`` per candidate pair closer than the minimum
    separation, ``m^2 pi r^2 / (2 npix)`` for ``m = 1.25 n + 32``) plus
    ``INJECTION_BYTES`` per placed injection; times the workers busy at once;
    plus the merge of one kind's realizations in the main process.
    """
    per_worker = max((_realization_bytes(b, npix) for b in budgets), default=0.0)
    merge = max((INJECTION_BYTES * b.placed * nsims for b in budgets), default=0.0)
    return _busy(workers, nsims, budgets) * per_worker + merge


def _realization_bytes(b: InjectionBudget, npix: int) -> float:
    m = 1.25 * b.requested + 32.0
    pairs = 0.0
    if b.min_sep_pix > 0:
        pairs = min(m * m / 2.0, m * m * math.pi * b.min_sep_pix ** 2 / (2.0 * npix))
    return PIXEL_BYTES * npix + CANDIDATE_BYTES * m + PAIR_BYTES * pairs + INJECTION_BYTES * b.placed


def _busy(workers: int, nsims: int, budgets) -> int:
    return max(1, min(int(workers), nsims * max(1, len(budgets))))


def _meminfo_available() -> int | None:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def _cgroup_available() -> int | None:
    try:
        with open("/sys/fs/cgroup/memory.max") as fh:
            limit = fh.read().strip()
        if limit == "max":
            return None
        with open("/sys/fs/cgroup/memory.current") as fh:
            current = int(fh.read().strip())
        return max(0, int(limit) - current)
    except (OSError, ValueError):
        return None


def available_memory() -> tuple[float | None, str]:
    """Memory (bytes) a run may use and where the figure comes from.

    ``$COMEST_BAYES_MEMORY_GB`` when set; else the smaller of the system's
    available memory (``MemAvailable``) and the room left under the
    process's cgroup limit; None when neither is known.
    """
    env = os.environ.get(MEMORY_ENV)
    if env:
        try:
            value = float(env)
            if not value > 0:
                raise ValueError
        except ValueError:
            raise ConfigError(f"{MEMORY_ENV}={env!r} must be a positive number of GB.") from None
        return value * 2 ** 30, f"set by ${MEMORY_ENV}"
    known = [v for v in (_meminfo_available(), _cgroup_available()) if v is not None]
    if not known:
        return None, "unknown"
    return float(min(known)), "available on this machine"


def check_memory(budgets, *, npix: int, nsims: int, workers: int) -> float:
    """Refuse when the injection stage's memory estimate exceeds :func:`available_memory`.

    Returns the estimate (bytes).
    """
    need = injection_memory(budgets, npix=npix, nsims=nsims, workers=workers)
    have, source = available_memory()
    if have is None or need <= have:
        return need
    worst = max(budgets, key=lambda b: _realization_bytes(b, npix))
    hint = ""
    if math.isfinite(worst.placeable) and worst.placeable < worst.requested:
        density_cap = worst.density * worst.placeable / worst.requested
        hint = (f" At the minimum separation of {worst.min_sep_pix:.1f} px only about {worst.placeable:,.0f} "
                f"injections fit per realization anyway (a density of about {density_cap:,.0f} per arcmin^2).")
    busy = _busy(workers, nsims, budgets)
    raise InputError(
        f"the injections would need about {need / 2 ** 30:,.1f} GB of memory ({worst.requested:,.0f} asked for "
        f"per {worst.kind} realization, {busy} realization{'s' if busy > 1 else ''} at once), more than the "
        f"{have / 2 ** 30:,.1f} GB {source}.{hint} Lower --density or --ncpu (or set {MEMORY_ENV} to "
        f"another budget). Nothing was written.")

