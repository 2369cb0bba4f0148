"""CoEx and ROS 1 (rospy, from Debian's packages: ``docs/deploy.md``).

* :class:`RosNode` (:mod:`.node`): the process's one ROS node; subscriptions of any type,
  publishers that never block, and registrations made again after a roscore restart.
* :mod:`.msgs`: CoEx data as standard messages (``nav_msgs/Odometry``, ``PointCloud2`` and
  ``OccupancyGrid`` per map level, ``sensor_msgs/Image``, ``nav_msgs/Path``), pure functions.

The vehicle's ``ros`` input and ``ros`` autonomy output (``coex_plugins.inputs.ros``,
``coex_plugins.autonomy.ros``, through :mod:`coex.ros`) and the topside's ROS products
(``coex_apps.console.ros``) are built on them. rospy is imported only when a node starts:
everything else of CoEx runs without ROS.
"""

from __future__ import annotations

from . import msgs
from .node import ROSPY_HINT, RosNode, RosPublisher, import_rospy

__all__ = ["ROSPY_HINT", "RosNode", "RosPublisher", "import_rospy", "msgs"]
