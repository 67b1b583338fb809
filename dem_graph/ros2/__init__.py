"""dem_graph on a ROS 2 graph with no ROS installation: the node that maps from the robot's topics
and publishes what its navigation reads (:mod:`~dem_graph.ros2.node`), and a player of bags
(:mod:`~dem_graph.ros2.player`), over Eclipse Cyclone DDS (:mod:`~dem_graph.ros2.dds`) with rosbags'
message definitions and CDR (:mod:`~dem_graph.ros2.messages`). The ``[ros2]`` extra installs both."""
