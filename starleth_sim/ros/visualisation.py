"""What sim_node publishes for viewers, each at its rate and off the lockstep critical path:
/tf (world -> base and every movable joint) and /tf_static (the fixed joints) from the
frame tree of :mod:`.tf`, written as CDR bytes, recorded, served by the live view and
published on DDS where tf2_msgs is importable (a full ROS install, or the package that
`make venv` generates: venv_interfaces/), and the contact markers of
:mod:`.contact_markers`. A re-send of the current state (before the first command) carries
/tf too."""
from __future__ import annotations

import numpy as np

from starleth_interface.topics import TOPIC_CONTACT_MARKERS, TOPIC_TF, TOPIC_TF_STATIC

from .contact_markers import ContactMarkers
from .qos import LATCHED_QOS, STATE_QOS, TF_QOS
from .recording import register_msg_text
from .state_io import joint_indices
from .tf import TF_MSG_TEXT, TF_TYPE, FrameTree, TfMessageCdr


def steps_between(rate, control_period) -> int:
    """Steps between two messages at `rate` Hz (0: never)."""
    if rate <= 0:
        return 0
    return max(1, int(round(1.0 / (rate * control_period))))


def tf_message_type(log):
    """tf2_msgs' TFMessage with its type support loaded, or None after one line on `log`
    saying why /tf and /tf_static are recorded but not published."""
    lost = ("/tf and /tf_static are recorded (and served by the live view, live_view:=true) "
            "but not published")
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        log.info("tf2_msgs is not installed (no ROS install provides it; `make venv` "
                 f"generates it from venv_interfaces/): {lost}")
        return None
    try:
        from rclpy.type_support import check_for_type_support
        check_for_type_support(TFMessage)
    except Exception as e:     # a broken install: its type support library does not load
        log.warning(f"tf2_msgs is installed but its type support does not load ({e}): {lost}")
        return None
    return TFMessage


class Visualisation:
    """/tf, /tf_static and the contact markers of `sim` for `settings` (tf_rate,
    tf_frame_prefix, contact_markers_rate, contact_marker_scale, world_frame), published on
    `node` through `output` (a :class:`~.topic_output.TopicOutput`, which also holds the
    recording) at the stamps of `service`."""

    def __init__(self, node, sim, settings, service, output, log):
        s = settings
        self.sim, self.service, self.output = sim, service, output
        desc = sim.description
        self.frames = FrameTree(desc.model, desc.urdf_xml, s.world_frame, s.tf_frame_prefix)
        self._joint_q = None      # the joints' indices in the model's q (tf_configuration)
        self.tf_every = steps_between(s.tf_rate, sim.control_period)
        self.markers_every = steps_between(s.contact_markers_rate, sim.control_period)
        self._tf_cdr = TfMessageCdr(self.frames.names(self.frames.dynamic))
        self._tf_static_cdr = TfMessageCdr(self.frames.names(self.frames.static))
        register_msg_text(TF_TYPE, TF_MSG_TEXT)
        #: {key: (topic, qos)} of TF_TYPE; recorded when tf_rate > 0 (tf_topics_recorded)
        self.tf_topics = {"tf": (TOPIC_TF, TF_QOS), "tf_static": (TOPIC_TF_STATIC, LATCHED_QOS)}
        self.tf_pubs = {}
        #: /tf's DDS subscribers: the count (at most SUBSCRIBER_REFRESH steps old), its step,
        #: and the count when /tf last went out on DDS (a re-send goes to newcomers only)
        self._tf_subs, self._tf_subs_k, self._tf_sent_to = 0, -10 ** 9, 0
        TFMessage = tf_message_type(log) if self.tf_every else None
        if TFMessage is not None:
            for key, (topic, qos) in self.tf_topics.items():
                self.tf_pubs[key] = node.create_publisher(TFMessage, topic, qos)
        self.markers = None
        if self.markers_every:
            try:
                from visualization_msgs.msg import Marker, MarkerArray
            except ImportError:
                self.markers_every = 0
                log.warning("visualization_msgs is not installed: no contact markers")
            else:
                output.add("contact_markers", MarkerArray, TOPIC_CONTACT_MARKERS, STATE_QOS)
                self.markers = ContactMarkers(sim, s.world_frame, s.contact_marker_scale,
                                              Marker, MarkerArray)

    def tf_topics_recorded(self) -> dict:
        """{key: (topic, qos)} of the TF topics a recording holds (none with tf_rate 0)."""
        return self.tf_topics if self.tf_every else {}

    def _emit_tf(self, key, data, stamp_ns, dds=True, record=True):
        """`key`'s CDR bytes to DDS (where tf2_msgs is importable; dds=False: not), to the
        recording (record=False: not) and to the live view."""
        pub = self.tf_pubs.get(key)
        if pub is not None and dds:
            pub.publish(data)
        rec = self.output.recording.recorder
        if record and rec is not None and not rec.closed:
            rec.write(self.tf_topics[key][0], data, stamp_ns)
        live = self.output.live      # the live view serves TF without tf2_msgs too
        if live is not None:
            live.log(self.tf_topics[key][0], data, stamp_ns)

    def _tf_subscribers(self, fresh=False) -> int:
        """/tf's DDS subscribers: a count taken at most TopicOutput.SUBSCRIBER_REFRESH steps
        ago (fresh: now), as for the other topics of a step (TopicOutput.wanted)."""
        pub = self.tf_pubs.get("tf")
        if pub is None:
            return 0
        k = self.service.k
        if fresh or not 0 <= k - self._tf_subs_k < self.output.SUBSCRIBER_REFRESH:
            self._tf_subs, self._tf_subs_k = pub.get_subscription_count(), k
        return self._tf_subs

    def publish(self):
        """/tf (every tf_rate-th step) and the contact markers, after the state (off the
        lockstep critical path: the controller is computing its answer meanwhile)."""
        svc = self.service
        k = svc.k
        sec, nsec = divmod(svc.stamp_ns, 1_000_000_000)
        if self.tf_every and k % self.tf_every == 0:
            n = self._tf_sent_to = self._tf_subscribers()
            self._publish_tf(sec, nsec, n > 0, True)
        if self.markers_every and k % self.markers_every == 0 and \
                self.output.wanted("contact_markers", True):
            self.markers.publish(self.output, sec, nsec)

    def republish(self):
        """/tf of the current state again with a re-send of the state (StatePublisher.
        republish_state: before the first command, to late subscribers), not recorded: to
        the live view, and on DDS only where /tf has subscribers it has not reached yet (a
        tf2 buffer warns of a transform repeated at the same stamp)."""
        if not self.tf_every:
            return
        n = self._tf_subscribers(fresh=True)
        newcomers, self._tf_sent_to = n > self._tf_sent_to, n
        sec, nsec = divmod(self.service.stamp_ns, 1_000_000_000)
        self._publish_tf(sec, nsec, newcomers, False)

    def _publish_tf(self, sec, nsec, dds, record):
        """/tf of the current state: on DDS if `dds`, recorded if `record`, to the live view
        if a client of it subscribes; built only if it goes anywhere."""
        out = self.output
        rec = out.recording.recorder
        recorded = record and rec is not None and not rec.closed
        live = out.live is not None and out.live.wants(TOPIC_TF)
        if not (dds or recorded or live):
            return
        poses = self.frames.transforms(self.tf_configuration(), self.frames.dynamic)
        self._emit_tf("tf", self._tf_cdr.build(sec, nsec, poses), self.service.stamp_ns,
                      dds=dds, record=record)

    def tf_configuration(self):
        """q of the current state in the minimal coordinates of the URDF's model (free flyer:
        position, quaternion x y z w, joint angles), the configuration FrameTree.transforms
        takes: state_io.minimal_state's q, gathered with the joints' indices
        (state_io.joint_indices) found once."""
        sim = self.sim
        idx = self._joint_q
        if idx is None:
            idx = self._joint_q = joint_indices(sim.description.model, sim.joint_names)[0]
        b = sim.base_state()
        q = np.zeros(sim.description.model.nq)
        q[0:3] = b["position"]
        q[3:7] = b["orientation_xyzw"]
        q[idx] = sim.joint_positions()
        return q

    def publish_static_transforms(self):
        """/tf_static once (transient local): the fixed joints."""
        if not self.tf_every or not self.frames.static:
            return
        poses = self.frames.transforms(self.tf_configuration(),
                                       self.frames.static)   # do not depend on q
        self._emit_tf("tf_static", self._tf_static_cdr.build(0, 0, poses),
                      self.service.stamp_ns)
