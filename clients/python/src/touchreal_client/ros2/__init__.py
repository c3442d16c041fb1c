"""TouchReal in ROS 2 (extra ``ros2``): the ``touchreal_msgs`` message package, the messages of a
stream as field values (:mod:`.messages`) and rosbag2 recordings (:mod:`.rosbag2`). The live DDS
bridge is :mod:`touchreal_client.bridges.ros2`."""
