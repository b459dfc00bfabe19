"""ROS 2 interoperability without a ROS install: CDR messages, rmw_zenoh names, MCAP logs.

Pure (no zenoh): :mod:`~metricslam.ros2.typestore` (message types, REP-2016 type hashes, CDR),
:mod:`~metricslam.ros2.messages` (our poses, paths, clouds and images as ROS 2 messages, and
camera input back), :mod:`~metricslam.ros2.rmw_zenoh` (the key expressions, liveliness tokens and
sample attachments rmw_zenoh uses), :mod:`~metricslam.ros2.mcap_log` (Foxglove-ready MCAP files).
The Zenoh adapter is ``metricslam_slam.service.ros2_bridge``. Needs the ``ros`` extra (``rosbags``,
``mcap``), imported lazily: importing this package needs neither. See ``docs/ros2.md``.
"""
