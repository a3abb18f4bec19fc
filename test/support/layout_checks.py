"""A Foxglove / Lichtblick layout checked against recordings (the shipped layout in test_tf,
a generated one for two robots in test_sim_time): what it names must be in the bags."""
import re

from starleth_sim.ros.tf import base_link


def layout_leaves(tree):
    """The panel keys of a layout's split tree."""
    if isinstance(tree, str):
        return [tree]
    return layout_leaves(tree["first"]) + layout_leaves(tree["second"])


def check_plot_path(value, msgs):
    """A plot's message path (topic.field.field[:]{key=="x"}.field): its topic recorded,
    each field on the last message, ending in a number."""
    topic, _, fields = value.partition(".")
    assert topic in msgs, topic
    obj = msgs[topic][-1].ros_msg
    for part in fields.split("."):
        obj = getattr(obj, re.match(r"\w+", part).group(0))       # the field exists
        if "[:]" in part:                       # {key==...} filters: check one element
            m = re.search(r'\{(\w+)=="([^"]+)"\}', part)
            obj = next(o for o in obj if getattr(o, m.group(1)) == m.group(2))
    float(obj)                                  # a number (or a numeric string)


def check_layout(layout, msgs, tf_frames, optional=("terrain",)):
    """Check `layout` against recorded messages (msgs: {topic: [mcap_ros2 decoded
    messages]}) and the child frames of their /tf and /tf_static: every panel is in the
    layout's tree; the 3D panels' topics are recorded (those ending in one of `optional`:
    only runs that have them), their followed frame is on /tf, each URDF layer reads a
    recorded robot_description whose root link, with the layer's frame prefix, is on /tf;
    every plot path is on the recorded messages. Returns (3D topics, URDF layers, plot
    paths) checked."""
    cfg = layout["configById"]
    assert sorted(layout_leaves(layout["layout"])) == sorted(cfg)
    topics, layers, paths = [], [], 0
    for key, panel in cfg.items():
        if key.startswith("3D!"):
            assert panel["followTf"] in tf_frames, panel["followTf"]
            for topic, opts in panel["topics"].items():
                assert opts["visible"], topic
                assert topic in msgs or topic.endswith(optional), topic
                topics.append(topic)
            for layer in panel["layers"].values():
                if layer["layerId"] != "foxglove.Urdf":
                    continue
                assert layer["sourceType"] == "topic" and layer["topic"] in msgs, layer
                urdf = msgs[layer["topic"]][0].ros_msg.data
                assert layer["framePrefix"] + base_link(urdf) in tf_frames, layer
                layers.append(layer)
        elif key.startswith("Plot!"):
            for path in panel["paths"]:
                check_plot_path(path["value"], msgs)
                paths += 1
    return topics, layers, paths
