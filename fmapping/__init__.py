"""FMapping: factorized neural field mapping for real-time dense RGB SLAM.

The library is pure torch / numpy and never imports zenoh; the process shells
live in ``services/``. Geometric conventions are documented in
:mod:`fmapping.geometry`.
"""
__version__ = "0.1.0"
