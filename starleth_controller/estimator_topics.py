"""The topics of ``controller_node``'s state estimator (``state_source:=estimator``): the IMU
and foot contact messages read from their CDR bytes, and ``estimator/odometry`` written
(``EstimatorTopics``). The filter and the checks of the values: estimator_intake.py."""
from __future__ import annotations

from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState

from starleth_interface.msg_cdr import IMU_FIELDS, ODOM_FIELDS, FixedCdr, StampedReader

from .estimator_intake import EstimatedState
from .state_intake import stamp_ns


class EstimatorTopics:
    """The estimator's messages of `node`: ``imu(data)`` and ``contacts(data)`` -> (stamp ns,
    values) or None for a message that cannot be decoded (`deserialise(data, type, what)`:
    the node's, which reports such a message and gives None);
    ``use_model(model)`` makes the filter (``estimate``, an EstimatedState); ``publish``
    sends its estimate on `odometry_topic` (nav_msgs/Odometry: frame 'odom', child the base
    link, twist in the base frame; an empty topic: none)."""

    def __init__(self, node, params, odometry_topic, qos, deserialise):
        self.params = params
        self._deserialise = deserialise
        self.estimate = None
        self._imu = StampedReader(Imu, IMU_FIELDS)
        self.pub = node.create_publisher(Odometry, odometry_topic, qos) if odometry_topic \
            else None
        self._msg = self._cdr = None

    def use_model(self, model):
        self.estimate = EstimatedState(model, self.params)
        o = self._msg = Odometry()
        o.header.frame_id, o.child_frame_id = "odom", self.estimate.base_frame
        self._cdr = FixedCdr.create(o, ODOM_FIELDS)

    def imu(self, data):
        """(stamp, the 10 values of IMU_FIELDS) of a sensor_msgs/Imu, or None."""
        r = self._imu.decode(data)
        if r is not None:
            sec, nsec, vals = r
            return sec * 1_000_000_000 + nsec, vals
        msg = self._deserialise(data, Imu, "imu")
        if msg is None:
            return None
        o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
        return stamp_ns(msg.header), (o.x, o.y, o.z, o.w, w.x, w.y, w.z, a.x, a.y, a.z)

    def contacts(self, data):
        """(stamp, (names, flags)) of the foot contacts' sensor_msgs/JointState, or None."""
        msg = self._deserialise(data, JointState, "foot contacts")
        return None if msg is None else (stamp_ns(msg.header),
                                         (tuple(msg.name), msg.position))

    def publish(self, sec_nsec):
        """estimator/odometry: the estimate of the state just read, stamped with it."""
        if self.pub is None:
            return
        vals = self.estimate.odometry_values()
        if self._cdr is not None:
            self.pub.publish(self._cdr.build(*sec_nsec, vals))
            return
        o = self._msg
        o.header.stamp.sec, o.header.stamp.nanosec = sec_nsec
        pp, po = o.pose.pose.position, o.pose.pose.orientation
        tl, ta = o.twist.twist.linear, o.twist.twist.angular
        pp.x, pp.y, pp.z, po.x, po.y, po.z, po.w, tl.x, tl.y, tl.z, ta.x, ta.y, ta.z = vals
        self.pub.publish(o)
