"""Wall seconds of named parts of a driver loop (host code that calls JAX programs), a part's
seconds optionally split into JAX's compilation and the rest.

The compile share is read from JAX's own monitoring events (``jax.monitoring``'s time spans of
tracing to a jaxpr, lowering to MLIR, and the XLA compile or persistent-cache load,
``COMPILE_EVENTS``): the union of those spans within the part, so nested spans (a jit traced
inside another's trace) count once. The programs run exactly as without the timer: nothing is
added to them and nothing is synchronised; a part's code must itself end with its results on
the host (or blocked on) for its seconds to hold its device work.
"""
from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator

from jax import monitoring

# jax/_src/dispatch.py's JAXPR_TRACE_EVENT, JAXPR_TO_MLIR_MODULE_EVENT, BACKEND_COMPILE_EVENT
# (the same names from jax 0.4 to 0.11); the last spans compile_or_get_cached.
COMPILE_EVENTS = frozenset({"/jax/core/compile/jaxpr_trace_duration",
                            "/jax/core/compile/jaxpr_to_mlir_module_duration",
                            "/jax/core/compile/backend_compile_duration"})


def union_seconds(spans: list[tuple[float, float]], a: float, b: float) -> float:
    """The length of the union of ``spans`` [(start, end)] clipped to [a, b]."""
    total, reach = 0.0, a
    for s, e in sorted((max(s, a), min(e, b)) for s, e in spans):
        if e > reach and e > s:  # e <= s: a span outside [a, b]
            total += e - max(s, reach)
            reach = e
    return total


class PartTimer:
    """Seconds per named part, in the order the parts end: ``seconds`` {name: s} (a name
    timed twice adds up). ``on_part(name, seconds)`` is called as each entry is recorded."""

    def __init__(self, on_part: Callable[[str, float], None] | None = None):
        self.seconds: dict[str, float] = {}
        self._on_part = on_part

    def _add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds
        if self._on_part is not None:
            self._on_part(name, seconds)

    @contextlib.contextmanager
    def part(self, name: str, split_compile: bool = False) -> Iterator[None]:
        """Time the block as ``name``; ``split_compile``: as "<name>_compile" (JAX's
        compilation within it) and "<name>_run" (the rest), in that order. Nothing is
        recorded when the block raises."""
        spans: list[tuple[float, float]] = []

        def listen(event, start, end, **_):
            if event in COMPILE_EVENTS:
                spans.append((start, end))

        if split_compile:
            monitoring.register_event_time_span_listener(listen)
        a = time.time()  # the clock of jax.monitoring's spans
        try:
            yield
        finally:
            b = time.time()
            if split_compile:
                monitoring.unregister_event_time_span_listener(listen)
        if split_compile:
            compile_s = union_seconds(spans, a, b)
            self._add(f"{name}_compile", compile_s)
            self._add(f"{name}_run", b - a - compile_s)
        else:
            self._add(name, b - a)


def timed(timer: PartTimer | None, name: str, split_compile: bool = False):
    """``timer.part(name, split_compile)``, or a block that times nothing when timer is
    None."""
    return contextlib.nullcontext() if timer is None else timer.part(name, split_compile)
