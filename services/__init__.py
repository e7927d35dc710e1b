"""The processes of the multi-process system (the only code that imports zenoh).

``python -m services.io {play,view,record}``, ``python -m services.tracker`` and
``python -m services.mapper``; shared plumbing in :mod:`services.common`, the wire
format in :mod:`fmapping.protocol`.
"""
