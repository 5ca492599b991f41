"""A live ROS 2 node without a ROS install: the loop detector over DDS (Cyclone DDS, the ``ros2``
extra), speaking ROS 2's topic and type names and CDR payloads.

* :mod:`.messages`: ROS 2 names on DDS and CDR payloads through ``rosbags`` (no DDS needed).
* :mod:`.dds`: participants, topic types carrying those payloads, ROS 2's QoS profiles.
* :mod:`.node`: :class:`~.node.LoopClosureNode`, camera topics in, decisions out.
* :mod:`.play`: replaying a bag's camera topics, listening to the decisions.
* :mod:`.bagwrite`: a small ROS 2 bag of your own frames.

``stablecues_msgs/msg/LoopClosure.msg`` (a ROS 2 package a workspace can build) and
``cyclonedds_loopback.xml`` (Cyclone DDS on the loopback interface only) ship beside them.
"""
