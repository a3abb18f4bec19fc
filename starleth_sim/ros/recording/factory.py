"""Opening a recording: the writer chain a :class:`~.interface.StorageOptions` asks for."""
from __future__ import annotations

import logging

from .interface import StorageOptions
from .mcap_sink import RecordingError, failure_cause
from .mcap_writer import McapRecorder
from .process_writer import ProcessRecorder
from .queued_writer import QueuedRecorder
from .split_writer import SplitRecorder


def open_file_recorder(options: StorageOptions):
    """The writer of the file(s) itself, in this process: a :class:`SplitRecorder` (a bag
    directory) if the options split the recording, else a :class:`McapRecorder`. OSError
    (RecordingError among them) if the file cannot be written."""
    if options.split:
        return SplitRecorder(options.uri, **options.split_limits(), **options.file_settings())
    return McapRecorder(options.uri, **options.file_settings())


def open_recorder(options: StorageOptions, *, on_failure=None, warn=None):
    """sim_node's recorder: a :class:`ProcessRecorder` (the file written by a process of
    its own: nothing of the writing on this interpreter); where no child process can be
    started, `warn` is told so (default: this module's logger) and the file is written by
    a thread of this process (:class:`QueuedRecorder` over :func:`open_file_recorder`'s
    writer), mostly while the controller computes. `on_failure(message)` is called once
    if the recording fails later (the file is then closed as far as it could be).

    Raises RecordingError, one line naming the file and the cause, if the file cannot be
    written."""
    try:
        return ProcessRecorder(options.uri, **options.split_limits(), **options.file_settings(),
                               on_failure=on_failure)
    except RecordingError:
        raise
    except OSError as e:
        (warn or logging.getLogger(__name__).warning)(
            f"recording in this process (no recording process: {e})")
    try:
        file_recorder = open_file_recorder(options)
    except OSError as e:
        raise RecordingError(f"{options.uri}: {failure_cause(e, options.uri)}") from None
    return QueuedRecorder(file_recorder, on_failure=on_failure)
