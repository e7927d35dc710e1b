"""The tracker service: :mod:`services.tracker.core` (zenoh-free :class:`~services.tracker.core.TrackerCore`)
and its process, ``python -m services.tracker`` (``__main__.py``)."""
