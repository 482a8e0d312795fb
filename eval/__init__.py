"""Evaluation tools that ``make`` runs (the quality protocol's baselines and style floor).

Not part of the installed package: run from the repository root (``make quality``).
"""
