"""Output paths checked at the door: before a command loads data, compiles or collects, each
file or directory it will write is checked to be creatable, so a bad ``--out`` fails in a
second with one line that names the user's path (not after the work, naming a temporary file).

Standard library only: ``rl2s_jax.cli`` imports this before any command's work starts. The
check creates nothing; where the path's parents do not exist yet (the commands create them),
their nearest existing ancestor is checked instead.
"""

from __future__ import annotations

import os

KINDS = ("file", "dir")


def output_problem(path: str, kind: str) -> str | None:
    """Why a command cannot write ``path`` as its ``kind`` output ("file": written or replaced
    whole, its parent directories created as needed; "dir": created if missing, files written
    inside it), or None when it can. Looks only; creates and changes nothing."""
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    p = os.path.normpath(path) if path else os.curdir
    if os.path.isdir(p):
        if kind == "file":
            return "it is a directory"
        if not os.access(p, os.W_OK | os.X_OK):
            return "permission denied (the directory is not writable)"
        return None
    if os.path.lexists(p):
        if kind == "dir":
            return "it exists and is not a directory"
        if os.path.exists(p) and not os.access(p, os.W_OK):
            return "permission denied (the file is read-only)"
    # The file or directory is made in its parent; parents that do not exist yet are created
    # by the command, inside their nearest existing ancestor.
    ancestor = os.path.dirname(p) or os.curdir
    while not os.path.lexists(ancestor):
        ancestor = os.path.dirname(ancestor) or os.curdir
    if not os.path.isdir(ancestor):
        return f"'{ancestor}' is not a directory"
    if not os.access(ancestor, os.W_OK | os.X_OK):
        return f"permission denied ('{ancestor}' is not writable)"
    return None


def output_error(option: str, path: str, kind: str) -> str | None:
    """The one-line error for an output that cannot be written, ``--out: cannot write to
    'PATH': REASON`` (PATH as the user gave it), or None when it can be."""
    problem = output_problem(path, kind)
    return None if problem is None else f"{option}: cannot write to '{path}': {problem}"
