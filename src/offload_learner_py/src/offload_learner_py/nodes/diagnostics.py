"""A node's /diagnostics (diagnostic_updater, the ROS convention rqt_robot_monitor and diagnostic_aggregator read):
one status named after the node's job, built by a callable returning an online.health.Status, published every
~diagnostic_period (s, default 1, diagnostic_updater's own parameter) and at once when its level changes."""
import threading

import diagnostic_updater
import rospy

UPDATER_PERIOD_S = 1.0   # diagnostic_updater's own default for ~diagnostic_period


class NodeDiagnostics:
    def __init__(self, task: str, status, hardware_id: str = "none"):
        """`status()`: the node's online.health.Status now."""
        self.status = status
        self.updater = diagnostic_updater.Updater()
        self.updater.setHardwareID(hardware_id)
        self.updater.add(task, self._fill)
        self._level = None
        self._lock = threading.Lock()
        period = float(rospy.get_param("~diagnostic_period", UPDATER_PERIOD_S))
        # The updater rereads ~diagnostic_period each update through rospy's parameter cache, which holds only a
        # parameter that is set: an unset one cost an XML-RPC call to the master every second (about 0.7 ms of
        # the robot's CPU a second per node). Set, it is read from the cache.
        if not rospy.has_param("~diagnostic_period"):
            rospy.set_param("~diagnostic_period", period)
        self.timer = rospy.Timer(rospy.Duration(period if period > 0 else UPDATER_PERIOD_S),
                                 lambda _: self.updater.update())

    def _fill(self, stat):
        status = self.status()
        with self._lock:
            self._level = status.level
        stat.summary(status.level, status.message)
        for key, value in status.values.items():
            stat.add(key, value)
        return stat

    def changed(self) -> None:
        """Publish now if the level moved since the last publish (a link that went down: the operator sees it at once,
        not a period later)."""
        with self._lock:
            level = self._level
        if level is not None and self.status().level != level:
            try:
                self.updater.force_update()
            except rospy.ROSException:   # publishing during shutdown
                pass

    def close(self) -> None:
        self.timer.shutdown()
