"""Where the data of the starleth_sim distribution lies (``urdf/``, ``robots/``,
``msg_configs/``, ...): the source tree, or the colcon install's share/starleth_sim."""
from __future__ import annotations

import os


def package_share_dir() -> str:
    """Directory holding `urdf/`, `robots/` and `msg_configs/`: the source tree, or the colcon
    install's share/starleth_sim when running from an install."""
    here = os.path.dirname(os.path.abspath(__file__))          # starleth_interface
    src = os.path.dirname(here)
    if os.path.isdir(os.path.join(src, "urdf")) and os.path.isdir(os.path.join(src, "msg_configs")):
        return src
    try:  # installed by colcon
        from ament_index_python.packages import get_package_share_directory
        return get_package_share_directory("starleth_sim")
    except Exception:  # pragma: no cover - only without a source tree and without ament
        pass
    raise FileNotFoundError("cannot find the starleth_sim data directory (urdf/, msg_configs/)")
