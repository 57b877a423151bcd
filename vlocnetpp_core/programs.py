"""ROS programs the core starts in a subprocess, found by name, never by module.

The core never imports ROS; where a command needs the real node over DDS (``replay --through-node``,
the demo, the node latency figure of ``bench``) it starts a program that the ROS package
(``vlocnetpp_ros``) registers in the ``vlocnetpp.programs`` entry-point group of its ``setup.py``:

=================  ===================================================================
``replay-node``    replay a bag through a ``localizer`` node over DDS (``replay``'s flags)
``latency-bench``  image-in -> pose-out latency of the node against the bare Localizer
``soak``           the node at camera rate for minutes, good and bad frames (``bench``'s soak figures)
=================  ===================================================================

The same programs are console scripts (``vlocnetpp-replay-node``, ``vlocnetpp-latency-bench``,
``vlocnetpp-soak``) for running by hand.
"""

from __future__ import annotations

import sys
from importlib.metadata import entry_points

from vlocnetpp_core.errors import UserError

GROUP = "vlocnetpp.programs"


def program_command(name: str) -> list[str]:
    """The command line prefix that runs the registered program ``name`` with this Python."""
    found = [ep for ep in entry_points(group=GROUP) if ep.name == name]
    if not found:
        raise UserError(
            f"the ROS program '{name}' is not installed (entry point group {GROUP}); "
            "install the package with its ROS side (bash scripts/dev setup, or colcon build)"
        )
    return [sys.executable, "-m", found[0].module]
