"""The contact markers of sim_node (visualization_msgs/MarkerArray on
starleth/contact_markers): a sphere per contact point coloured by its state and an arrow along
the force of each closed contact, built once as a template whose changing fields are patched
per message, as CDR bytes (``msg_cdr.SlotCdr``) or in the message objects."""
from __future__ import annotations

from starleth_interface.msg_cdr import SlotCdr

from ..physics.simulator import CONTACT_STATES

#: colours (r, g, b, a) of the contact states (ContactInfo.state)
MARKER_COLOURS = {"open": (0.6, 0.6, 0.6, 0.5), "stick": (0.1, 0.75, 0.2, 1.0),
                  "slip": (0.9, 0.15, 0.1, 1.0)}
MARKER_SPHERE = 0.02         # sphere diameter [m]
MARKER_SHAFT = 0.008         # arrow shaft diameter [m]


class ContactMarkers:
    """The markers of the contacts of `sim` in `frame`, arrows `scale` [m/N] long per newton;
    `Marker` and `MarkerArray` are visualization_msgs' classes (an optional package).
    ``msg`` is the message object (filled by :meth:`fill`), ``cdr`` its SlotCdr (None where
    none could be made: then the message objects are published)."""

    def __init__(self, sim, frame, scale, Marker, MarkerArray):
        self.sim, self.frame, self.scale = sim, frame, scale
        self.Marker, self.MarkerArray = Marker, MarkerArray
        self.msg = self.template()
        # written as CDR bytes (SlotCdr: stamps, sphere positions and colours, arrow
        # actions and points patched into a template; None: message objects)
        self.cdr = self.make_cdr()
        self.slots = self.slots_of(self.msg)
        self._points = [[0.0] * 6 for _ in range(len(sim.contact_names))]
        self._colours = [MARKER_COLOURS[name] for name in CONTACT_STATES]

    def template(self):
        """One sphere per contact point (namespace 'contacts') and one arrow per contact
        point (namespace 'contact_forces', deleted while the contact is open), ids by
        contact index."""
        Marker = self.Marker
        msg = self.MarkerArray()
        for ns, typ in (("contacts", Marker.SPHERE), ("contact_forces", Marker.ARROW)):
            for i, _name in enumerate(self.sim.contact_names):
                m = Marker()
                m.header.frame_id = self.frame
                m.ns, m.id, m.type, m.action = ns, i, typ, Marker.ADD
                m.pose.orientation.w = 1.0
                if typ == Marker.SPHERE:
                    m.scale.x = m.scale.y = m.scale.z = MARKER_SPHERE
                else:
                    m.scale.x, m.scale.y, m.scale.z = (MARKER_SHAFT, 2 * MARKER_SHAFT,
                                                       3 * MARKER_SHAFT)
                    m.color.r, m.color.g, m.color.b, m.color.a = 0.1, 0.35, 0.95, 1.0
                    m.points = [type(m.pose.position)(), type(m.pose.position)()]
                msg.markers.append(m)
        return msg

    def slots_of(self, msg):
        """The fields of a contact-marker message that change per step, as (object,
        attribute, format): per sphere its stamp, position and colour, per arrow its stamp,
        action and two points (the order of :meth:`values`)."""
        n = len(self.sim.contact_names)
        slots = []
        for m in msg.markers[:n]:
            p, c = m.pose.position, m.color
            slots += [(m.header.stamp, "sec", "i"), (m.header.stamp, "nanosec", "I"),
                      (p, "x", "d"), (p, "y", "d"), (p, "z", "d"),
                      (c, "r", "f"), (c, "g", "f"), (c, "b", "f"), (c, "a", "f")]
        for m in msg.markers[n:]:
            a, b = m.points
            slots += [(m.header.stamp, "sec", "i"), (m.header.stamp, "nanosec", "I"),
                      (m, "action", "i"), (a, "x", "d"), (a, "y", "d"), (a, "z", "d"),
                      (b, "x", "d"), (b, "y", "d"), (b, "z", "d")]
        return slots

    def make_cdr(self):
        """SlotCdr of the contact markers' slots (on a template of its own, which
        SlotCdr.create probes)."""
        msg = self.template()
        return SlotCdr.create(msg, self.slots_of(msg))

    def values(self, sec, nsec):
        """The values of the contact markers' slots: spheres at the contact points coloured
        by state; arrows from each closed contact point along its force, `scale` [m/N] long
        (an open contact's arrow is deleted and keeps its points)."""
        sim, Marker = self.sim, self.Marker
        scale = self.scale
        colours = self._colours
        # the contacts' points, forces and states as arrays (the values of sim.contacts'
        # records, without building them)
        positions, forces = sim.contact_points(), sim.contact_forces()
        spheres, arrows = [], []
        for p, f, state, pts in zip(positions.tolist(), forces.tolist(),
                                    sim.contact_states().tolist(), self._points, strict=True):
            x, y, z = p
            spheres += (sec, nsec, x, y, z, *colours[state])
            if state == 0:     # open
                arrows += (sec, nsec, Marker.DELETE, *pts)
                continue
            pts[:] = (x, y, z, x + scale * f[0], y + scale * f[1], z + scale * f[2])
            arrows += (sec, nsec, Marker.ADD, *pts)
        return spheres + arrows

    def fill(self, sec, nsec):
        """The message object ``msg`` filled with :meth:`values` (where no SlotCdr could be
        made)."""
        for (obj, attr, _), v in zip(self.slots, self.values(sec, nsec), strict=True):
            setattr(obj, attr, v)

    def publish(self, output, sec, nsec):
        """The markers of the current state through `output` (a TopicOutput), recorded."""
        if self.cdr is not None:
            output.emit_cdr("contact_markers", self.cdr.build(self.values(sec, nsec)), True)
        else:
            self.fill(sec, nsec)
            output.emit("contact_markers", self.msg, True)
