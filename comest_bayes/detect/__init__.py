"""Stage 1: source detection, with SEP or the SExtractor binary, and the image's seeing.

Modules: ``base`` (what both backends share), ``sep_backend``, ``sextractor``, ``catalog``
(the detection catalog schema), ``psf`` (the seeing FWHM and PSF measured from the image's stars).
"""
