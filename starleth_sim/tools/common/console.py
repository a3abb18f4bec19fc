"""How the bag tools (``starleth-analyze``, ``starleth-view``, ``starleth-replay``) run as
console scripts: the exit status, and one line on stderr instead of a traceback for a bag
that cannot be used."""
from __future__ import annotations

import sys

from .bag import BagError


def run_console_script(prog, run, argv, errors=(BagError,)) -> int:
    """Run a bag tool's `run(argv)`: exit status as returned, or 1 with one line
    'prog: error: ...' (no traceback) for `errors` and for OSError (writing the output),
    130 on Ctrl-C; argparse exits with 2 on bad arguments."""
    try:
        return run(argv)
    except (*errors, OSError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130

