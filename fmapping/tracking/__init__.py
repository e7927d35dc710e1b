"""Camera tracking: direct photometric alignment (fast path), render-and-compare (paper path), pose sources.

* :mod:`fmapping.tracking.direct_align` - image pyramids, pixel selection, analytic-Jacobian
  Gauss-Newton / LM alignment of a frame to a reference keyframe with depth.
* :mod:`fmapping.tracking.direct_tracker` - :class:`DirectTracker`: motion model, loss detection,
  re-localisation against recent keyframes, keyframe decisions.
* :mod:`fmapping.tracking.mono` - :class:`MonoFrontend`: RGB-only two-view bootstrap, sparse
  landmarks from KLT tracks, windowed bundle adjustment (:mod:`fmapping.tracking.ba`,
  :mod:`fmapping.tracking.features`), loop closure; a package (config, keyframe/landmark store,
  bootstrap, front end, loop closing, restart).
* :mod:`fmapping.tracking.render_compare` - Adam on se(3) through the neural field.
* :mod:`fmapping.tracking.mapview` - depth / rays rendered from the mapper's field.
* :mod:`fmapping.tracking.consistency` - how well poses explain the images (KLT tracks moved
  through depth), and the camera-frame rotation that explains them best.
* :mod:`fmapping.tracking.sources` - kiss-icp on depth, TUM files.
"""
from fmapping.tracking.direct_align import AlignConfig, AlignResult, Reference, align, make_reference
from fmapping.tracking.direct_tracker import DirectTracker, TrackerConfig, TrackResult
from fmapping.tracking.ba import BAResult, bundle_adjust
from fmapping.tracking.features import KltConfig, triangulate, two_view_init
from fmapping.tracking.mapview import MapView, MapViewConfig
from fmapping.tracking.mono import MonoConfig, MonoFrontend
from fmapping.tracking.render_compare import RenderCompareConfig, RenderCompareTracker
from fmapping.tracking.sources import KissIcpConfig, KissIcpOdometry, poses_from_file

__all__ = [
    "AlignConfig", "AlignResult", "Reference", "align", "make_reference",
    "DirectTracker", "TrackerConfig", "TrackResult",
    "MapView", "MapViewConfig", "MonoConfig", "MonoFrontend", "bundle_adjust", "BAResult",
    "KltConfig", "triangulate", "two_view_init", "RenderCompareConfig", "RenderCompareTracker",
    "KissIcpConfig", "KissIcpOdometry", "poses_from_file",
]
