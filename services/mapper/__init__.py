"""The mapper service: :mod:`services.mapper.core` (zenoh-free :class:`~services.mapper.core.MapperCore`)
and its process, ``python -m services.mapper`` (``__main__.py``)."""
