"""What an input or autonomy output on ROS 1 needs: the process's one ROS node
(:class:`RosNode`) and CoEx data as standard ROS messages (:mod:`msgs`, pure functions).
Imported on demand (``import coex`` does not load it); rospy is imported only when a node starts."""

from __future__ import annotations

from coex_transports.ros import ROSPY_HINT, RosNode, RosPublisher, import_rospy, msgs

__all__ = ["ROSPY_HINT", "RosNode", "RosPublisher", "import_rospy", "msgs"]
