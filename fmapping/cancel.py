"""Cooperative cancellation of long library calls.

A caller that may have to stop early (a service on SIGTERM) passes ``should_stop``, a
function of no arguments; the call asks it at safe points (between optimisation
iterations, between rendered views) and raises :class:`Cancelled` when it says True.
Nothing is interrupted half-way through an operation, so no lock or file is left behind;
the work of the cancelled call is lost (the mapper: resume from a checkpoint taken
between updates).
"""
from __future__ import annotations

from typing import Callable, Optional

StopFn = Optional[Callable[[], bool]]


class Cancelled(Exception):
    """A long call stopped early because its ``should_stop()`` said so."""


def check_stop(should_stop: StopFn, what: str) -> None:
    """Raise :class:`Cancelled` ("``what`` stopped ...") when ``should_stop`` is given and True."""
    if should_stop is not None and should_stop():
        raise Cancelled(f"{what} stopped on request")
