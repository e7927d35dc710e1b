"""The tracker's public API (re-exported from :mod:`fmapping.tracking`)."""
from fmapping.tracking import *  # noqa: F401,F403
from fmapping.tracking import __all__  # noqa: F401
