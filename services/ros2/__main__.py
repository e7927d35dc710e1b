"""``python -m services.ros2``: bridge FMapping and ROS 2 over zenoh (CDR, as ROS 2 speaks it).

Out: ``fmapping/<ns>/poses/<source>`` -> ``geometry_msgs/msg/PoseStamped`` on ``--pose-topic``
and a growing ``nav_msgs/msg/Path`` on ``--path-topic``; ``fmapping/<ns>/map/points`` ->
``sensor_msgs/msg/PointCloud2`` on ``--points-topic``. In: ``sensor_msgs/msg/Image`` on
``--image-topic`` + ``sensor_msgs/msg/CameraInfo`` on ``--info-topic`` -> ``Frame`` on
``fmapping/<ns>/frames``.

Keys (``--key-style``): ``bridge`` for zenoh-bridge-ros2dds (topic ``/fmapping/pose`` is key
``fmapping/pose``, under ``--ros-prefix`` when the bridge runs with a ROS namespace), ``rmw``
for ROS 2 nodes on rmw_zenoh (``<domain>/<topic>/<type>/<hash>`` plus rmw_zenoh's attachment).
Frames: poses are the camera optical frame (OpenCV axes) in ``--world-frame`` (default ``map``).
Needs the ``[ros]`` extra (rosbags), no ROS installation. It runs until SIGINT / SIGTERM.
"""
from __future__ import annotations

import argparse
import os

from services.process import run_main, service_parser, setup_logging
from services.transport import Service
from services.zenoh_session import add_common_args


def _env_domain() -> int:
    """$ROS_DOMAIN_ID as ROS reads it (unset, empty or not a number: 0)."""
    try:
        return int(os.environ.get("ROS_DOMAIN_ID") or 0)
    except ValueError:
        return 0


def build_parser() -> argparse.ArgumentParser:
    from services.ros2.convert import CAMERA_FRAME, DISTROS, WORLD_FRAME
    from services.ros2.core import Topics

    t = Topics()
    p = service_parser("services.ros2", __doc__)
    g = p.add_argument_group("ROS 2")
    g.add_argument("--key-style", choices=["bridge", "rmw"], default="bridge",
                   help="bridge: zenoh-bridge-ros2dds keys (topic without the leading /); rmw: rmw_zenoh keys "
                        "(default: %(default)s)")
    g.add_argument("--ros-prefix", default="", help="the ROS namespace zenoh-bridge-ros2dds runs with "
                                                    "(its 'namespace' setting), prepended to every key (default: none)")
    g.add_argument("--domain", type=int, default=_env_domain(),
                   help="ROS domain id of rmw_zenoh keys (default: $ROS_DOMAIN_ID or 0)")
    g.add_argument("--distro", choices=DISTROS, default=None,
                   help="ROS 2 distro of the message definitions and type hashes (default: $ROS_DISTRO or jazzy)")
    g.add_argument("--pose-source", default="tracker", help="which poses/<source> to publish (default: %(default)s)")
    g.add_argument("--pose-topic", default=t.pose, help="PoseStamped topic (default: %(default)s)")
    g.add_argument("--path-topic", default=t.path, help="Path topic (default: %(default)s)")
    g.add_argument("--points-topic", default=t.points, help="PointCloud2 topic (default: %(default)s)")
    g.add_argument("--image-topic", default=t.image,
                   help="Image topic read as frames ('' = none; default: %(default)s)")
    g.add_argument("--info-topic", default=t.camera_info, help="CameraInfo topic of the images (default: %(default)s)")
    g.add_argument("--camera", default=None, metavar="FX,FY,CX,CY[,K1,K2,P1,P2[,K3]]",
                   help="intrinsics of the images instead of their CameraInfo (default: none)")
    g.add_argument("--world-frame", default=WORLD_FRAME,
                   help="frame_id of poses, path and points (default: %(default)s)")
    g.add_argument("--camera-frame", default=CAMERA_FRAME,
                   help="the optical frame the poses are of (documentation only: PoseStamped has no child frame; "
                        "default: %(default)s)")
    g.add_argument("--path-interval", type=float, default=0.2,
                   help="seconds between Path messages (default: %(default)s)")
    return add_common_args(p)


def make_core(args, svc: Service):
    from services.ros2.convert import TopicKeys, default_distro
    from services.ros2.core import BridgeCore, Topics

    ros = TopicKeys(args.key_style, args.ros_prefix, args.domain, default_distro(args.distro))
    topics = Topics(args.pose_topic, args.path_topic, args.points_topic, args.image_topic, args.info_topic)
    core = BridgeCore(svc.keys, topics, ros, world_frame=args.world_frame, pose_source=args.pose_source,
                      counters=svc.counters, on_bad_input=svc.report_bad_input, path_interval=args.path_interval)
    if args.camera:
        core.camera_override = camera_for_size(args.camera)
    return core


def camera_for_size(text: str):
    """``--camera`` as a function of the image size (a PinholeCamera needs it); a bad string fails now."""
    from fmapping.camera import PinholeCamera

    PinholeCamera.from_string(text, 1 << 12, 1 << 12)
    return lambda size: PinholeCamera.from_string(text, size[0], size[1])


def publish(svc: Service, outputs) -> None:
    for out in outputs:
        pub = svc.publisher(out.key, block=not out.droppable)
        if out.attachment is None:
            pub.put(out.payload)
        else:
            pub.put(out.payload, attachment=out.attachment)
        svc.counters.inc("published")


def run(svc: Service, args) -> int:
    core = make_core(args, svc)
    svc.subscribe(svc.keys.poses(args.pose_source or "*"), "poses")
    svc.subscribe(svc.keys.points, "points")
    if args.image_topic:
        svc.subscribe(core.in_key("image"), "image")
        svc.subscribe(core.in_key("camera_info"), "camera_info")
    svc.log.info("ROS 2 bridge (%s keys): %s -> %s, %s; %s -> %s; %s, %s -> %s", args.key_style,
                 svc.keys.poses(args.pose_source), core.out_key("pose"), core.out_key("path"), svc.keys.points,
                 core.out_key("points"), core.in_key("image") if args.image_topic else "-",
                 core.in_key("camera_info") if args.image_topic else "-", svc.keys.frames)
    svc.start()
    while not svc.shutdown.requested:
        item = svc.inbox.get(timeout=0.1)
        if item is None:
            publish(svc, core.flush())  # idle: the newest Path goes out
            continue
        channel, (key, data) = item
        publish(svc, core.handle(channel, data, key))
    publish(svc, core.flush())
    return 0


def main(argv=None, session=None, keys=None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(args.log_level, "ros2")
    try:
        import rosbags  # noqa: F401 - the optional extra, checked before any session opens
    except ImportError:
        from services.ros2.convert import MISSING

        raise ValueError(MISSING) from None
    svc = Service("ros2", args, capacities={"poses": 10_000, "points": 2, "camera_info": 4, "image": 4},
                  session=session, keys=keys)
    try:
        return run(svc, args)
    finally:
        svc.close("done")


if __name__ == "__main__":
    run_main(main, "services.ros2")
