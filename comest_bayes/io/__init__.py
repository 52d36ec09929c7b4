"""Input and output: the observed image and its companions, the run directory, JSON.

Modules: ``image`` (reading the image, weight, mask and their facts), ``rundir`` (the run
directory and its files), ``info`` (what a finished run holds), ``jsonio`` (the one JSON writer).
"""
