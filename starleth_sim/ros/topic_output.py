"""sim_node's outgoing topics: the publishers by key, publishing a message object or its CDR
bytes and recording it, and the subscriber counts that decide whether a topic is built at
all (a topic nobody subscribes to is not published; while recording it is only recorded),
and the same bytes to the live view (:mod:`.live_view`) when it is on."""
from __future__ import annotations

from rclpy.serialization import serialize_message


class TopicOutput:
    """The publishers of the node by key (``pubs[key] = (publisher, topic name resolved,
    type, qos)``), writing to the recording of `recording` (a
    :class:`~.node_recording.NodeRecording`) at the stamp of `service`'s current state."""

    SUBSCRIBER_REFRESH = 10   # steps between two looks at the subscriber counts
    #: the topics whose subscriber counts are taken after every step: a controller that
    #: switches between them (controller_node from /joint_states to the bundle) is
    #: followed at once
    EVERY_STEP_COUNTS = ("joint_states", "state_bundle")

    def __init__(self, node, service, recording):
        self.node = node
        self.service = service
        self.recording = recording
        self.pubs = {}
        self.counts_k = -10 ** 9    # the step of the counts (< 0: none yet, or asked for)
        self.counts = {}
        #: the live view (a :class:`~.live_view.LiveView`, None: off), served every
        #: topic's CDR bytes and asked whether it wants a topic nobody else wants
        self.live = None

    def add(self, key, typ, topic, qos):
        """Create the publisher of `key`."""
        p = self.node.create_publisher(typ, topic, qos)
        self.pubs[key] = (p, p.topic_name, typ, qos)

    def subscription_count(self, key) -> int:
        """The exact number of subscribers of `key` now."""
        return self.pubs[key][0].get_subscription_count()

    def emit(self, key, msg, record):
        """Publish (and record) a message object; while recording, a topic nobody
        subscribes to is only recorded."""
        rec = self.recording.recorder
        if (record and rec is not None and not rec.closed) or self.live_wants(key):
            self.emit_cdr(key, serialize_message(msg), record)   # serialised once for all
        else:
            self.pubs[key][0].publish(msg)

    def emit_cdr(self, key, data, record):
        """The same for CDR bytes."""
        p, topic, _, _ = self.pubs[key]
        rec = self.recording.recorder
        if record and rec is not None and not rec.closed:
            if self.counts.get(key, 1) > 0:
                p.publish(data)
            rec.write(topic, data, self.service.stamp_ns)
        elif self.live is None or self.counts.get(key, 1) > 0:   # (not: built for the live
            p.publish(data)                                       # view alone)
        live = self.live
        if live is not None and (self.service.k % live.every == 0 or topic in live.latched):
            live.log(topic, data, self.service.stamp_ns)

    def live_wants(self, key) -> bool:
        """The live view is on, serves this step (every live.every-th: live_view_rate) and
        a client of it subscribes to `key`'s topic."""
        live = self.live
        return (live is not None and self.service.k % live.every == 0
                and live.wants(self.pubs[key][1]))

    def wanted(self, key, record):
        """Build and publish a topic only if it is recorded or someone subscribes (an
        unmatched publish is invisible; skipping it keeps the lockstep cycle short). The
        counts are taken after the previous state went out (StatePublisher.publish_state):
        /joint_states every step, the other topics every SUBSCRIBER_REFRESH steps, so a new
        subscriber gets its first message at most one step (/joint_states) or that many
        steps late. With the live view on, also a topic one of its clients subscribes to."""
        if record and self.recording.recorder is not None:
            return True
        if self.counts_k < 0:      # no counts yet, or asked for fresh ones
            self.refresh_counts()
        return self.counts.get(key, 0) > 0 or (self.live is not None and self.live_wants(key))

    def forget_counts(self):
        """Take fresh subscriber counts at the next look."""
        self.counts_k = -10 ** 9

    def refresh_counts(self):
        self.counts_k = self.service.k
        self.counts = {key: p[0].get_subscription_count() for key, p in self.pubs.items()}

    def update_counts(self):
        """Subscriber counts for the next state, taken once a state is out (off the lockstep
        critical path): EVERY_STEP_COUNTS every step, the others every SUBSCRIBER_REFRESH
        steps."""
        if not (0 <= self.service.k - self.counts_k < self.SUBSCRIBER_REFRESH):
            self.refresh_counts()
        else:
            pubs = self.pubs
            for key in self.EVERY_STEP_COUNTS:
                if key in pubs:
                    self.counts[key] = pubs[key][0].get_subscription_count()
