"""Benchmarks of texspace against this machine's limits (``make bench``; see run.py)."""
