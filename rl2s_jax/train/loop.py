"""The host-side training loop: jitted chunks of ``train_step`` with a progress bar, metrics
logging, checkpoints and a stop on divergence. Python runs only between chunks."""
from __future__ import annotations

import json
import os
import time
from collections.abc import Callable

import jax
import numpy as np
from tqdm.auto import tqdm

from rl2s_jax.train.checkpoint import Checkpointer
from rl2s_jax.train.data import TrainData
from rl2s_jax.train.step import TrainState, train_steps


class TrainingDiverged(RuntimeError):
    """A loss or a parameter became NaN/Inf. ``step`` is the first bad step, ``quantities``
    what was non-finite there, ``last_good`` the last state known to be finite."""

    def __init__(self, step: int, quantities: list[str], last_good: TrainState,
                 saved_at: str | None):
        self.step, self.quantities, self.last_good, self.saved_at = step, quantities, last_good, \
            saved_at
        where = (f"; the last good state (step {int(last_good.step)}) is kept in {saved_at}"
                 if saved_at else f"; the last good state is step {int(last_good.step)}")
        super().__init__(f"training diverged at step {step}: non-finite "
                         f"{', '.join(quantities)}{where}")


_train_chunk = jax.jit(train_steps, static_argnames=("n_steps", "phase"))

WORST_VD_JUMP = 2.0  # a refreshed worst training VD this many times the previous one: a jump


def worst_vd_jumps(mvd: np.ndarray, refreshed: np.ndarray, previous: float | None,
                   factor: float = WORST_VD_JUMP) -> tuple[list[tuple[int, float, float]],
                                                         float | None]:
    """Sharp rises of the worst training-policy VD between completed VD measurements.

    mvd [n], refreshed [n] bool: a chunk's ``mvd_train`` / ``vd_refreshed`` metrics;
    ``previous``: the worst VD of the last measurement before the chunk (None: none yet).
    -> ([(index in the chunk, before, after)] where after > factor * before, the last
    measurement's worst VD)."""
    jumps = []
    for i in np.flatnonzero(np.asarray(refreshed, bool)):
        now = float(mvd[i])
        if previous is not None and np.isfinite(now) and now > factor * previous:
            jumps.append((int(i), previous, now))
        previous = now if np.isfinite(now) else previous
    return jumps, previous


def _first_bad(metrics: dict[str, np.ndarray]) -> tuple[int, list[str]] | None:
    ok = np.asarray(metrics["finite"], bool)
    if ok.all():
        return None
    i = int(np.flatnonzero(~ok)[0])
    names = [k.split("/", 1)[1] for k, v in metrics.items()
             if k.startswith("finite/") and not bool(v[i])]
    return i, names


def fit(state: TrainState, data: TrainData, n_steps: int, *, chunk: int = 10,
        checkpointer: Checkpointer | None = None, save_every: int | None = None,
        meta: dict | None = None, metrics_path: str | os.PathLike | None = None,
        progress: bool = True, on_chunk: Callable[[TrainState, dict], None] | None = None,
        eval_every: int | None = None,
        on_eval: Callable[[TrainState], dict | None] | None = None,
        on_warning: Callable[[str], None] | None = None
        ) -> tuple[TrainState, dict[str, np.ndarray]]:
    """Train until ``state.step == n_steps`` (a resumed state continues where it stopped).

    Chunks of ``chunk`` steps run as one compiled scan; checkpoints land at every multiple of
    ``save_every`` and at the end; with pre-training a chunk never straddles
    ``pretrain_steps`` (each runs one phase only). Metrics of every step are appended to
    ``metrics_path``, one JSON line each (appended, not rewritten whole: a crash can tear only
    the last line, which the readers skip, ``_files.read_jsonl``, and a resumed run rewrites
    the log before it appends). ``on_eval(state)`` runs at every multiple of ``eval_every``
    (chunks end there too); the scalars of a dict it returns join the progress bar.
    ``on_warning(text)`` hears of every sharp rise of the worst training-policy VD between
    measurements (``worst_vd_jumps``; default: printed above the progress bar). Raises
    TrainingDiverged (after saving the last good state) on NaN/Inf.
    -> (final state, metrics stacked over the steps run here).
    """
    if not isinstance(n_steps, int) or n_steps < 0:
        raise ValueError(f"steps: expected an int >= 0, got {n_steps!r}")
    if chunk < 1:
        raise ValueError(f"chunk: expected an int >= 1, got {chunk!r}")
    save_every = save_every or n_steps or 1
    meta = meta or {}
    start = int(state.step)
    history: list[dict[str, np.ndarray]] = []
    shown: dict[str, str] = {}  # the last evaluation's numbers on the progress bar
    worst = float(np.max(np.asarray(state.vd))) if np.isfinite(state.vd).all() else None
    warn = on_warning or (lambda text: tqdm.write(text))
    bar = None
    if progress:
        bar = tqdm(total=n_steps, initial=min(start, n_steps), unit="step",
                   desc=f"train {state.config.method}", dynamic_ncols=True)
    log = open(metrics_path, "a") if metrics_path else None  # appended: see the docstring
    try:
        while int(state.step) < n_steps:
            step = int(state.step)
            # End chunks on checkpoint boundaries so a resumed run replays the same chunks.
            n = min(chunk, n_steps - step, save_every - step % save_every)
            if eval_every:
                n = min(n, eval_every - step % eval_every)
            phase = state.config.phase(step)
            if phase == "pretrain":
                n = min(n, state.config.adversarial.pretrain_steps - step)
            t0 = time.perf_counter()
            new_state, metrics = _train_chunk(state, data, n_steps=n, phase=phase)
            metrics = jax.device_get(metrics)
            seconds = time.perf_counter() - t0
            bad = _first_bad(metrics)
            if bad is not None:
                saved = None
                if checkpointer is not None:
                    checkpointer.save(state, meta)
                    saved = os.path.join(checkpointer.directory, str(step))
                raise TrainingDiverged(step + bad[0] + 1, bad[1], state, saved)
            state = new_state
            history.append(metrics)
            if log is not None:
                for i in range(n):
                    row = {"step": step + i + 1}
                    row.update({k: _py(v[i]) for k, v in metrics.items()
                                if not k.startswith("finite")})
                    log.write(json.dumps(row) + "\n")
                log.flush()
            if checkpointer is not None and (int(state.step) % save_every == 0
                                             or int(state.step) == n_steps):
                checkpointer.save(state, meta)
            jumps, worst = worst_vd_jumps(metrics["mvd_train"], metrics["vd_refreshed"], worst)
            for i, before, after in jumps:
                warn(f"[train] warning: the worst training-policy VD rose from {before:.4g} to "
                     f"{after:.4g} at step {step + i + 1} ({after / before:.1f}x): the "
                     f"simulator got much worse on some training policy; a checkpoint "
                     f"before it may be the better simulator")
            if on_chunk is not None:
                on_chunk(state, metrics)
            # The evaluation before the bar's update, so that the bar shows this step's
            # numbers (not the previous evaluation's) beside this step's training VD.
            if on_eval is not None and eval_every and int(state.step) % eval_every == 0:
                row = on_eval(state)
                if isinstance(row, dict):
                    shown = {k: f"{v:.3g}" for k, v in row.items()
                             if isinstance(v, int | float) and k != "step"}
            if bar is not None:
                bar.update(n)
                bar.set_postfix({"steps_s": f"{n / seconds:.2f}",
                                 "avd": f"{float(metrics['avd_train'][-1]):.3g}",
                                 "mvd": f"{float(metrics['mvd_train'][-1]):.3g}", **shown},
                                refresh=False)  # on_eval's keys may repeat these: last wins
    finally:
        if bar is not None:
            bar.close()
        if log is not None:
            log.close()
    stacked = ({k: np.concatenate([h[k] for h in history]) for k in history[0]}
               if history else {})
    return state, stacked


def _py(x):
    x = np.asarray(x)
    return x.item() if x.ndim == 0 else x.tolist()


# ------------------------------------------------------------------ from files to a trained run


