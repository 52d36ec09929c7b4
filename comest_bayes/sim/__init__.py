"""Simulated data with known truths: the built-in demo tile, the analytic white-noise
prediction, synthetic outcome tables.
"""
