"""The full SLAM loop behind ``fmapping slam``: track every frame, map with the tracked poses.

``run_slam(job)`` (:class:`fmapping.job.Job`) opens ``job.data`` and runs, frame by frame,

    pose source -> Mapper.add_frame -> (after each mapping window) refresh of the tracker's reference

and writes into ``job.out``: ``map.ply`` (coloured point cloud), ``mesh.ply``,
``traj.txt`` (TUM format, every frame), ``stats.json`` (per-frame tracking ms,
per-window mapping seconds, tracking-loss events, ATE against the GT when it exists).
``--no-export`` (``slam.export: false``) skips ``map.ply`` / ``mesh.ply`` (and the
reconstruction metrics); ``traj.txt`` and ``stats.json`` are still written.

Pose sources (``job.poses``):

* ``photometric`` (default): RGB only, front end :class:`~fmapping.tracking.mono.MonoFrontend`
  (``slam.frontend: mono``): KLT tracks and a two-view bootstrap give the first poses
  and sparse landmarks; every frame is then aligned photometrically
  (:class:`~fmapping.tracking.direct_tracker.DirectTracker`, the fast path) to the current
  keyframe, whose depth comes from the landmarks (with ``mono.dense_extra``, off by
  default, plus depth rendered from the map where mapped frames looked, at each keyframe
  where it agrees with the landmarks); keyframes are refined by a windowed bundle
  adjustment. The mapper receives the tracked poses (its init pose optimisation is
  off unless ``slam.mapper_refines_init``), and after each keyframe's bundle adjustment
  the poses it moved (``slam.mapper_follows_ba``, :meth:`Mapper.set_poses`).
  ``slam.frontend: map`` is the paper-style alternative: constant-depth bootstrap
  guesses refined by the mapper's init, then tracking against depth rendered from the
  map only (with init checks, retries and a constant-depth fallback). With ``--use-depth`` the sensor depth replaces the
  rendered depth for the references and supervises the mapper (RGB-D mode).
  ``slam.tracking: render_compare`` swaps the direct alignment of the map front end
  for render-and-compare through the field (slow; for comparison).
* ``kiss-icp``: kiss-icp odometry on back-projected depth (needs depth).
* ``gt`` / ``PATH.txt``: given poses (the loop is then the mapping job with tracking stats).

Scale and world frame (monocular RGB has no metric scale), in this order:

1. ground-truth poses in the dataset (``scale_anchor: auto|gt``): the world frame is
   the GT frame of frame 0 and the scale is the GT distance between frame 0 and the
   frame that completes the bootstrap (DIM-SLAM anchors its scale with the first GT
   poses in the same spirit), taken again between frames 0 and 14, the end of the
   init window (``mono.late_anchor_frames``): the front end is rescaled about frame 0
   then, and the mapper gets its first frames only after that, with the rescaled poses.
   With the map front end the same baseline is taken at the end of the init window
   and the remaining factor after the mapper's init is applied to everything written
   out (poses, map, mesh) as a similarity about frame 0. Evaluate with SE(3) (or none).
2. depth in the dataset (map front end, ``auto|depth``): the factor is the median
   ratio of sensor depth to rendered depth at the last init frame.
3. otherwise the median scene depth of the bootstrap is ``mono.unit_depth`` (mono)
   or the assumed ``init_depth`` plane (map); evaluate with Sim(3).

Init failure (map front end): after the init stage the first init frames are aligned
back to the last one with the rendered depth; if the inlier ratio is low or the map
renders too few pixels, init is retried with ``init_retry_frames`` more frames (up to
``init_retries`` times), then tracking falls back to constant-depth references until
the map renders depth (reported in ``notes``). A failed monocular bootstrap starts again
at the next frame, as in the tracker service (frame 0 and the frames 0..14 above are then
the bootstrap's own first frame and the 14 after it, anchored at their GT poses); the
frames before it have no pose and are left out of ``traj.txt`` and the ATE
(``frames_posed``). Only a bootstrap that never succeeds falls back to the map front end.
Tracking loss is reported per frame in ``tracking_loss_events``.
"""
from fmapping.slam.config import SlamConfig, build_slam_config
from fmapping.slam.job import run_slam
from fmapping.slam.map_frontend import MapFrontend, bootstrap_poses, constant_depth
from fmapping.slam.run import SlamRun

__all__ = ["MapFrontend", "SlamConfig", "SlamRun", "bootstrap_poses", "build_slam_config", "constant_depth",
           "run_slam"]
