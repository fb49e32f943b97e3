"""Synthetic problems, scenes and calibration cases shared by the tests and the benchmarks.

Not part of the installed package: the tests import it from the repository root (pytest's
`pythonpath`), the bench scripts with `PYTHONPATH=.`.
"""
