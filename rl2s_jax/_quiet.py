"""Import MuJoCo's MJX without its two lines about the absent optional Warp backend.

``mujoco.mjx`` probes for NVIDIA Warp when it is imported and ``print``s
"Failed to import warp: No module named 'warp'" and "Failed to import mujoco_warp: ..." when
Warp is not installed (it is optional; MJX's JAX backend, which we use, does not need it).
Every ``rl2s`` command would start with those two lines. :func:`import_mjx_quietly` imports
``mujoco.mjx`` once with stdout captured and passes on every captured line except exactly
those two messages about the *absent* module: a Warp that is installed but fails to load, an
ImportError of MuJoCo itself, or anything else printed still reaches the terminal.
"""
from __future__ import annotations

import contextlib
import importlib
import io
import re
import sys

# The two lines mujoco/mjx/warp/__init__.py prints when the `warp` package is not installed.
ABSENT_WARP = re.compile(r"^Failed to import (warp|mujoco_warp): No module named 'warp'$")


def import_quietly(module: str) -> None:
    """Import ``module`` (if not yet imported) with stdout captured; pass on every captured
    line but the two about an absent Warp. An ImportError is left for the import that needs
    the module to report."""
    if module in sys.modules:
        return
    captured = io.StringIO()
    try:
        with contextlib.redirect_stdout(captured):
            importlib.import_module(module)
    except ImportError:
        pass
    finally:
        kept = [line for line in captured.getvalue().splitlines()
                if not ABSENT_WARP.match(line)]
        if kept:
            print("\n".join(kept))


def import_mjx_quietly() -> None:
    """Import ``mujoco.mjx`` without the two lines about the absent optional Warp backend."""
    import_quietly("mujoco.mjx")


import_mjx_quietly()  # on import: `rl2s_jax/__init__` imports this module before anything else
