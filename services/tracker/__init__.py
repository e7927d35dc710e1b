"""The tracker service: :mod:`services.tracker.core` (zenoh-free :class:`~services.tracker.core.TrackerCore`)
with its ``map`` front end :mod:`services.tracker.map_frontend` and the saved keyframes of
:mod:`services.tracker.resume_state`, and its process, ``python -m services.tracker`` (``__main__.py``)."""
