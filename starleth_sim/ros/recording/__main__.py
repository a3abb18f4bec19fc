"""``python -m starleth_sim.ros.recording --writer``: the command line of a ProcessRecorder's
writer process (:mod:`.writer_child`)."""
import sys

from .process_writer import WRITER_FLAG
from .writer_child import main

if __name__ == "__main__" and sys.argv[1:] == [WRITER_FLAG]:
    main()
