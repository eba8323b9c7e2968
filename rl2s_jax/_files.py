"""Atomic writes of user-facing files: a temporary file in the same directory, flushed and
fsync'ed, then ``os.replace``d onto the path, so an interrupted or failed write leaves the old
file (or none), never half of one. Standard library only.

``atomic_open(path, "wb")`` for writers that take a file object (``np.savez_compressed(f,
...)`` adds no ``.npz`` suffix to a file object), ``save_figure`` for Matplotlib figures,
``write_json`` / ``write_text`` for the rest.

Logs that grow row by row (a run's metrics.jsonl and eval.jsonl) are appended instead, one
JSON object a line: an interrupted append can only tear the last line, which ``read_jsonl``
skips, and a resumed run rewrites the log whole (atomically) before it appends again.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from typing import IO, Any


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w") -> Iterator[IO]:
    """A file object to write ``path`` whole ("w" text, "wb" bytes); on a clean exit it
    replaces ``path`` at once (permissions as a plain ``open`` would give), on an exception
    (Ctrl-C included) the temporary file is removed and ``path`` left as it was."""
    if mode not in ("w", "wb"):
        raise ValueError(f"mode: expected 'w' or 'wb', got {mode!r}")
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{os.path.basename(path)}.",
                               suffix=".partial")
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it 0600
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_open(path) as f:
        f.write(text)


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 1) -> None:
    """Write ``obj`` as JSON to ``path`` atomically (serialised first: a value JSON cannot
    hold fails before anything is written)."""
    write_text(path, json.dumps(obj, indent=indent))


def save_figure(fig, path: str | os.PathLike, **savefig_kwargs) -> None:
    """``fig.savefig`` to ``path`` atomically, in the format its suffix names (.png, .pdf,
    .svg; png without one)."""
    suffix = os.path.splitext(os.fspath(path))[1].lstrip(".").lower()
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format=suffix or "png", **savefig_kwargs)


def read_jsonl(path: str | os.PathLike) -> list[dict]:
    """The rows of a JSON-lines log, blank lines skipped. A last line that does not parse is
    an append torn by a crash and is skipped; one before it raises ValueError naming the file
    and the line."""
    with open(path) as f:
        lines = [(i, line) for i, line in enumerate(f, 1) if line.strip()]
    rows = []
    for j, (i, line) in enumerate(lines):
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError as err:
            if j == len(lines) - 1:
                break
            raise ValueError(f"{os.fspath(path)}: line {i} is not JSON ({err})") from None
    return rows
