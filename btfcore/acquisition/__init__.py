"""Acquisition: sparse sampling, multiplexed illumination, plans, time and noise models, reconstruction from few measurements (papers 2-4)."""
