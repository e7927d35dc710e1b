"""Monocular front end: two-view bootstrap, direct tracking against keyframes, windowed bundle adjustment.

RGB-only tracking before (and independently of) the neural map:

1. **Bootstrap.** Corners of frame 0 are followed with KLT; once the tracks to a
   frame ``k`` show enough parallax, the essential matrix gives the relative pose
   (unit baseline), the inlier tracks are triangulated and the scale is fixed by
   an *anchor*: the metric baseline ``|t_k - t_0|`` from a pose source (ground
   truth: the DIM-SLAM convention of anchoring with known first poses), or else
   the convention that the median scene depth is ``unit_depth``. Frames ``1..k``
   are then aligned photometrically to frame 0 with the triangulated depth. With an
   anchor, its baseline is taken again ``late_anchor_frames`` frames in (the end of
   the mapper's init window) and the whole front end is rescaled about frame 0
   (:meth:`MonoFrontend.rescale`): a bootstrap baseline of a few frames is too short
   to hold the scale.
2. **Tracking.** Every frame is aligned by :class:`~fmapping.tracking.direct_tracker.DirectTracker`
   to the current keyframe (sparse depth at tracked corners); KLT tracks are
   carried along from frame to frame. A frame the alignment loses (motion blur, a
   blurred keyframe) gets its pose from the tracked landmarks (PnP + RANSAC) and is
   aligned again from there; if that fails too, the PnP pose stands and the frame
   becomes a keyframe. Only when PnP fails as well does the frame count as lost.
   With ``MonoConfig.frame_pose`` "pnp" the KLT tracks come first: the frame's pose is fitted to its
   tracked landmarks (PnP from the motion model's prediction) and judged against the keyframe's
   reference as an alignment would be (:meth:`~fmapping.tracking.direct_tracker.DirectTracker.verify`);
   the direct alignment runs only for the frames that fail that.
3. **Keyframes.** When the tracker asks for one, tracks with a landmark add an
   observation, tracks without one are triangulated between their first keyframe
   and the new one; then a windowed bundle adjustment (last ``window`` keyframes,
   the two oldest fixed, which also holds the scale) refines keyframe poses and
   landmarks; the new keyframe's reference holds every tracked landmark (at its
   observed pixel, with the refined depth) plus, optionally, dense depth from the
   map (``extra_depth``). New corners fill the gaps. With ``MonoConfig.ba_thread`` the bundle
   adjustment runs in a worker thread (:mod:`~fmapping.tracking.mono.ba_thread`) and is merged
   between frames; the new keyframe's reference then holds the depths from before it.
4. **Loops.** At each keyframe, old keyframes the camera has come back to (by the estimated
   poses) are checked on their own landmarks and image (:mod:`fmapping.tracking.loop`); a
   verified loop that contradicts the chain is closed by a pose graph over the keyframes since
   (:mod:`fmapping.tracking.posegraph`), landmarks moving with their first keyframe, then a
   bundle adjustment of those keyframes with the loop's matches as observations (the pose
   graph bends the chain; the BA makes it agree with the images again), scaled back to the
   pose graph's size; :meth:`MonoFrontend.refined_poses` then hands on every frame's pose.
   With ``MonoConfig.loop_thread`` the search (verification and pose graph) runs in a worker
   thread and its correction is merged at a later frame.

With ``MonoConfig.rolling_shutter`` (the readout time as a fraction of the frame interval) the
tracked pixels are unrolled (:mod:`fmapping.tracking.rolling_shutter`) with each frame's rotation
since the previous one before PnP, triangulation and bundle adjustment; the photometric alignment
and KLT keep the image's own pixels.

Non-keyframe poses are stored relative to their keyframe, so :meth:`MonoFrontend.poses`
returns them moved with the bundle-adjusted keyframes. Poses are camera-to-world
4x4 (see :mod:`fmapping.geometry`).

The package: :mod:`~fmapping.tracking.mono.config` (:class:`MonoConfig`),
:mod:`~fmapping.tracking.mono.store` (tracks, keyframes, landmarks, the windowed BA),
:mod:`~fmapping.tracking.mono.ba_thread` (that BA off the frame path; both workers are
:mod:`~fmapping.tracking.mono.worker`'s),
:mod:`~fmapping.tracking.mono.bootstrap` (1.), :mod:`~fmapping.tracking.mono.frontend`
(:class:`MonoFrontend`: 2., 3., the late anchor), :mod:`~fmapping.tracking.mono.loop_closing` (4.) and
:mod:`~fmapping.tracking.mono.restart` (going on from saved keyframes).
"""
from fmapping.tracking.mono.config import MonoConfig
from fmapping.tracking.mono.frontend import MonoFrontend, moved_poses

__all__ = ["MonoConfig", "MonoFrontend", "moved_poses"]
