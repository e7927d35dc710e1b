"""The ROS 2 bridge: :mod:`services.ros2.core` (zenoh-free :class:`~services.ros2.core.BridgeCore`),
:mod:`services.ros2.convert` (message conversions) and its process, ``python -m services.ros2``."""
