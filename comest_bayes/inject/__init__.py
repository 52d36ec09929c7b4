"""Stage 3: synthetic sources and their injection into the (source-free) image.

Modules: ``placement`` (how many, where), ``sources`` (populations and GalSim profiles),
``render`` (the truth table of one realization and its rendering), ``design`` (adaptive
magnitude design of the next batch).
"""
