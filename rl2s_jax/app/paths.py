"""Output paths checked at the door: before a command loads data, compiles or collects, each
file or directory it will write is checked to be creatable, so a bad ``--out`` fails in a
second with one line that names the user's path (not after the work, naming a temporary file).

Standard library only: ``rl2s_jax.cli`` imports this before any command's work starts. The
check changes nothing: where the path's parents do not exist yet (the commands create them),
their nearest existing ancestor is checked instead, for real, by creating and removing a
temporary file there (``os.access`` says yes for /proc, where nothing can be created). Outputs
that exist are refused too unless ``--force`` (``existing_outputs``).
"""

from __future__ import annotations

import os
import tempfile

KINDS = ("file", "dir")


def output_problem(path: str, kind: str) -> str | None:
    """Why a command cannot write ``path`` as its ``kind`` output ("file": written or replaced
    whole, its parent directories created as needed; "dir": created if missing, files written
    inside it), or None when it can. Leaves nothing behind (a probe file is removed)."""
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    p = os.path.normpath(path) if path else os.curdir
    if os.path.isdir(p):
        if kind == "file":
            return "it is a directory"
        if not os.access(p, os.W_OK | os.X_OK):
            return "permission denied (the directory is not writable)"
        return _probe(p)
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
    return _probe(ancestor)


def _probe(directory: str) -> str | None:
    """Why no file can be created in ``directory`` (tried with a temporary one), or None."""
    try:
        fd, probe = tempfile.mkstemp(dir=directory, prefix=".rl2s-probe-")
    except OSError as err:
        return f"no file can be created in '{directory}' ({err.strerror or err})"
    os.close(fd)
    os.remove(probe)
    return None


def existing_outputs(path: str, kind: str, names: tuple[str, ...] | None) -> list[str]:
    """What a command writing ``path`` would replace: for a "file", ``[path]`` if it exists;
    for a "dir", the ``names`` in it that exist (``names`` None: all its entries, a non-empty
    directory being one output whole, as a Minari export). [] when nothing."""
    if kind == "file" or not os.path.isdir(path):
        return [path] if os.path.lexists(path) else []
    if names is None:
        return sorted(os.listdir(path))
    return [n for n in names if os.path.lexists(os.path.join(path, n))]


def overwrite_error(option: str, path: str, kind: str,
                    names: tuple[str, ...] | None) -> str | None:
    """The one-line refusal to replace earlier outputs without ``--force``, or None."""
    found = existing_outputs(path, kind, names)
    if not found:
        return None
    if kind == "file" or names is None:
        return f"{option}: '{path}' exists; --force replaces it"
    return (f"{option}: '{path}' holds an earlier run's {', '.join(found)}; --force replaces "
            f"them")


def output_error(option: str, path: str, kind: str) -> str | None:
    """The one-line error for an output that cannot be written, ``--out: cannot write to
    'PATH': REASON`` (PATH as the user gave it), or None when it can be."""
    problem = output_problem(path, kind)
    return None if problem is None else f"{option}: cannot write to '{path}': {problem}"


# The files and directories each command writes, as (option, "file" | "dir"); the command line
# checks them right after parsing, before any work.
OUTPUTS = {
    "zoo": (("--out", "dir"), ("--work", "dir"), ("--export", "file")),
    "collect": (("--out", "file"),),
    "import": (("--out", "file"),),
    "export": (("--out", "dir"),),
    "train": (("--out", "dir"),),
    "evaluate": (("--json", "file"),),
    "improve": (("--out", "dir"),),
    "pipeline": (("--out", "dir"),),
    "diagnose": (("--out", "dir"),),
}
# The outputs that an earlier run's results may hold, replaced only with --force: option ->
# the file names inside a "dir" output that count (None: the file, or the directory whole).
# `rl2s train --out` is not here: a run directory resumes (app/training.py keeps its summary).
FORCED = {
    "zoo": {"--out": ("zoo.npz", "zoo.json")},
    "collect": {"--out": None},
    "import": {"--out": None},
    "export": {"--out": None},
    "evaluate": {"--json": None},
    "improve": {"--out": ("zoo.npz", "zoo.json", "summary.json", "summary.md")},
    "pipeline": {"--out": ("report.json", "report.md")},
    "diagnose": {"--out": ("report.json", "report.md")},
}


def output_path(args, option: str) -> str | None:
    """The path ``option`` names for a parsed command, its default where the command has one
    (``zoo --out``: the shipped zoo; ``--work``: runs/zoo/TASK; ``pipeline --out``:
    results/TASK)."""
    path = getattr(args, option.lstrip("-").replace("-", "_"))
    if path is not None:
        return path
    if args.command == "zoo" and option == "--out":
        return os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                            "zoo", "shipped", args.task)
    if args.command == "zoo" and option == "--work":
        return os.path.join("runs", "zoo", args.task)
    if args.command == "pipeline" and option == "--out":
        return os.path.join("results", args.task)
    return None


def outputs_error(args) -> str | None:
    """The first output of a parsed command that cannot be written, or that holds an earlier
    run's results without ``--force`` (``zoo --plots-only`` redraws into its zoo), as one
    line; None when all can be written."""
    forced = {} if getattr(args, "force", False) or getattr(args, "plots_only", False) \
        else FORCED.get(args.command, {})
    for option, kind in OUTPUTS.get(args.command, ()):
        path = output_path(args, option)
        if path is None:
            continue
        error = output_error(option, path, kind)
        if error is None and option in forced:
            error = overwrite_error(option, path, kind, forced[option])
        if error:
            return error
    return None


def stopped_message(args, started: float) -> str:
    """What Ctrl-C left, in one line: train and zoo resume (train: from its newest
    checkpoint), pipeline reuses what it finished; the others name the files they wrote before
    the stop (their writes are atomic: whole files only), or say nothing was written."""
    out = output_path(args, "--out")
    if args.command == "train":
        steps = [int(n) for n in _listdir(os.path.join(out, "checkpoints")) if n.isdigit()]
        at = f"its newest checkpoint is step {max(steps)}" if steps else "no checkpoint yet"
        return f"stopped ({at}); the same command resumes"
    if args.command == "zoo":
        return (f"stopped; the same command continues from {output_path(args, '--work')} "
                f"(its newest checkpoints)")
    if args.command == "pipeline":
        return "stopped; the same command resumes (data and training runs done are reused)"
    written = []
    for option, _ in OUTPUTS.get(args.command, ()):
        path = output_path(args, option)
        if path is not None:
            written += _written_since(path, started)
    return ("stopped; nothing was written" if not written
            else f"stopped; written before the stop: {', '.join(written)}")


def _listdir(path: str) -> list[str]:
    return os.listdir(path) if os.path.isdir(path) else []


def _written_since(path: str, started: float) -> list[str]:
    """``path`` or the files under it modified at or after ``started``."""
    if os.path.isfile(path):
        return [path] if os.path.getmtime(path) >= started else []
    return [os.path.join(root, n) for root, _, files in os.walk(path) for n in files
            if os.path.getmtime(os.path.join(root, n)) >= started]
