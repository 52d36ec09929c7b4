"""Stage 3: synthetic sources and their injection into the (source-free) image.

Modules: ``placement`` (how many, where), ``population`` (drawn parameters), ``profiles``
(GalSim profiles), ``kspace`` (batched Fourier drawing), ``psfmodel`` (the injected PSF),
``cosmos`` (real galaxies), ``render`` (the truth table of one realization and its rendering), ``design`` (adaptive
magnitude design of the next batch).
"""
