"""The processes of the multi-process system (the only code that imports zenoh).

``python -m services.io {play,view,record}``, ``python -m services.tracker`` and
``python -m services.mapper``; each service's zenoh-free core in ``services/<name>/core.py``.
Shared plumbing: :mod:`services.core_support` (what the cores share), :mod:`services.process`
(command line, logging, signals, exit), :mod:`services.zenoh_session` (network options, sessions),
:mod:`services.transport` (the zenoh shell :class:`~services.transport.Service`); the wire format
in :mod:`fmapping.protocol`.
"""
