"""ROS 2 without a ROS installation: the standard messages uwbd's poses and IMU samples
make (:mod:`~uwbd.ros2.messages`), a log written as a rosbag2 folder
(:mod:`~uwbd.tools.ros2_bag`, ``uwbd export --ros2``), and the daemon's live topics on rmw_zenoh's
key expressions (:mod:`~uwbd.ros2.rmw_zenoh` the grammar, :mod:`~uwbd.ros2.publisher` the
publishers), all through the pure-Python ``rosbags`` (the ``ros2`` extra). Which names and
domain: :mod:`~uwbd.config.ros2` (the ``[ros2]`` section), which needs none of it."""
