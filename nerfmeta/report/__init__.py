"""Plots and reports: error against iterations and against wall-clock time."""
