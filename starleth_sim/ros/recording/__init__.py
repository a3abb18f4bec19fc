"""Recording ROS 2 bags (MCAP, the rosbag2 layout) without a running ROS graph: the public
API of the recorders.

* :class:`StorageOptions` says where and how (rosbag2's ``StorageOptions``) and
  :func:`open_recorder` opens sim_node's recorder for it; every recorder implements the one
  :class:`Recorder` protocol (rosbag2's ``BaseWriterInterface``);
* :class:`McapRecorder` writes one file (:mod:`.mcap_writer`), :class:`SplitRecorder` a bag
  directory of numbered files and ``metadata.yaml`` (:mod:`.split_writer`),
  :class:`QueuedRecorder` either from a thread (:mod:`.queued_writer`) and
  :class:`ProcessRecorder` either from a child process (:mod:`.process_writer`, whose child
  is :mod:`.writer_child`, run as ``python -m starleth_sim.ros.recording --writer``);
* the schemas (:mod:`.schemas`), the QoS metadata (:mod:`.qos`), and the file under a
  recording with the repair of a damaged one (:mod:`.mcap_sink`: :class:`RecordingError`).

Importing this package does not import rclpy.
"""
from .factory import open_file_recorder, open_recorder
from .interface import Recorder, StorageOptions
from .mcap_sink import RecordingError, repair
from .mcap_writer import McapRecorder
from .process_writer import ProcessRecorder
from .qos import qos_profiles_yaml, qos_to_dict
from .queued_writer import QueuedRecorder
from .schemas import (
                      SEPARATOR,
                      generated_msg_text,
                      message_class,
                      message_definition,
                      msg_text,
                      register_msg_text,
                      type_name,
)
from .split_writer import SplitRecorder

__all__ = ["Recorder", "StorageOptions", "open_recorder", "open_file_recorder",
           "RecordingError", "repair", "McapRecorder", "SplitRecorder", "QueuedRecorder",
           "ProcessRecorder", "SEPARATOR", "type_name", "message_class", "msg_text",
           "generated_msg_text", "message_definition", "register_msg_text", "qos_to_dict",
           "qos_profiles_yaml"]
