"""The side inputs of ``controller_node``: the base state and the four foot wrenches (or, with
``state_source:=estimator``, the IMU and the foot contacts), taken from their subscriptions'
queues when the node wants them, not by an executor (``SideInputs``)."""
from __future__ import annotations

from rclpy.clock import Clock, ClockType
from rclpy.node import Node


class SideInputs:
    """The inputs other than the joint state ("side inputs") of `node`, subscribed (as CDR
    bytes) on a hidden helper node (``_<name>_side_inputs``) that no executor spins: their
    messages wait in the subscriptions' queues and are taken when the joint state of a stamp
    arrives (``take``), so the executor thread wakes once per state instead of six times (a
    simulator that sends /joint_states last, as sim_node does, gets its answer without any
    wait). Until a stamp is complete, the steady-clock timer `poll` (on `node`, started by
    the node) takes them every POLL_PERIOD, and stops itself once `waiting()` (a joint state
    waits for the rest of its stamp) is false: any order of arrival still works. Topic names
    are resolved by `node` (its namespace and remappings). `inputs`: (message type, topic,
    callback) each; a message taken goes to its callback(data)."""

    #: s: while a joint state waits for the other messages of its stamp, the side inputs
    #: are looked at this often (steady clock)
    POLL_PERIOD = 0.0005

    def __init__(self, node, qos, inputs, waiting):
        self.node = Node(f"_{node.get_name()}_side_inputs", context=node.context,
                         namespace=node.get_namespace(), use_global_arguments=False,
                         enable_rosout=False, start_parameter_services=False)

        def sub(typ, topic):
            return self.node.create_subscription(typ, node.resolve_topic_name(topic),
                                                 lambda _: None, qos, raw=True)
        self._inputs = [(sub(typ, topic), on_data) for typ, topic, on_data in inputs]
        self._waiting = waiting
        self.poll = node.create_timer(self.POLL_PERIOD, self._on_poll,
                                      clock=Clock(clock_type=ClockType.STEADY_TIME),
                                      autostart=False)

    def take(self, drain=True):
        """The messages waiting in the queues (drain=False: at most one of each), handed to
        their callbacks (which may complete a stamp and run the controller)."""
        for sub, on_data in self._inputs:
            while True:
                with sub.handle:
                    taken = sub.handle.take_message(sub.msg_type, True)
                if taken is None:
                    break
                on_data(taken[0])
                if not drain:
                    break

    def _on_poll(self):
        """The timer's callback: take the side inputs; stop polling once no joint state
        waits for them."""
        self.take()
        if not self._waiting():
            self.poll.cancel()

    def unsubscribe(self):
        """No more side inputs: the subscriptions destroyed, the polling stopped."""
        for sub, _ in self._inputs:
            self.node.destroy_subscription(sub)
        self._inputs = []
        self.poll.cancel()

    def destroy(self):
        """Destroys the helper node."""
        self.node.destroy_node()
