"""The one evaluation setting: how many simulated episodes, how many steps, which seed and which
true value every front end scores a simulator (or the oracle) with.

`rl2s train`'s test evaluations (summary.json, eval.jsonl), `rl2s evaluate`, the pipeline's
report and the paper's protocol all build an ``EvalSetting`` and ``resolve`` it against the
data (and the checkpoint's ``vd_horizon``), so that one checkpoint on one data set gets one
number per quantity unless a flag changes the setting. The defaults live here only.
"""
from __future__ import annotations

import argparse
import dataclasses

EVAL_EPISODES = 16  # simulated episodes per policy
EVAL_SEED = 0  # the evaluation's own key, PRNGKey(seed): not the training seed
CPU_HORIZON = 100  # the cpu profile's steps per simulated episode (at most the data's)
TRUTHS = ("auto", "measured", "logged")


def profile_horizon(profile: str, episode_length: int | None) -> int:
    """The steps per simulated episode a training profile measures VD with (TrainConfig's
    vd_horizon): 'cpu' min(CPU_HORIZON, episode length), 'gpu' the whole episode."""
    ep = int(episode_length or 1000)
    if profile == "cpu":
        return min(CPU_HORIZON, ep)
    if profile == "gpu":
        return ep
    raise ValueError(f"profile: expected 'cpu' or 'gpu', got {profile!r}")


@dataclasses.dataclass(frozen=True)
class EvalSetting:
    """episodes: simulated episodes per policy; horizon: steps per episode (None: the
    checkpoint's vd_horizon, else the backend's profile's, at most the data's episode_length);
    seed: the evaluation key PRNGKey(seed); truth: which true value, "measured" (the data's
    fresh-episode values; they cover whole episodes only), "logged" (the logged episodes'
    discounted return over the horizon) or "auto" (measured where they apply, else logged).
    ``horizon_source`` says where a resolved horizon came from."""

    episodes: int = EVAL_EPISODES
    horizon: int | None = None
    seed: int = EVAL_SEED
    truth: str = "auto"
    horizon_source: str = "--horizon"

    def __post_init__(self):
        for name in ("episodes", "horizon"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise ValueError(f"seed: expected an int, got {self.seed!r}")
        if self.truth not in TRUTHS:
            raise ValueError(f"truth: expected one of {', '.join(TRUTHS)}, got {self.truth!r}")

    @classmethod
    def from_flags(cls, episodes: int | None = None, horizon: int | None = None,
                   seed: int | None = None, truth: str | None = None) -> EvalSetting:
        """A setting from optional flags: None keeps the default."""
        given = dict(episodes=episodes, horizon=horizon, seed=seed, truth=truth)
        return cls(**{k: v for k, v in given.items() if v is not None})

    def resolve(self, episode_length: int | None, vd_horizon: int | None = None,
                profile: str | None = None) -> EvalSetting:
        """The setting with its horizon filled: given > ``vd_horizon`` (a checkpoint's) >
        ``profile_horizon(profile or this backend's)``, each at most ``episode_length``."""
        if self.horizon is not None:
            return self
        import jax  # local: the command line builds its flags here without loading JAX

        if vd_horizon is not None:
            h, source = int(vd_horizon), "the checkpoint's vd_horizon"
        else:
            profile = profile or ("gpu" if jax.default_backend() == "gpu" else "cpu")
            h = profile_horizon(profile, episode_length)
            source = (f"the cpu profile's: at most {CPU_HORIZON} steps of the data's episodes"
                      if profile == "cpu" else "the gpu profile's: the data's episode_length")
        if episode_length is not None and h > int(episode_length):
            h, source = int(episode_length), f"the data's episode_length; {source} {h} is longer"
        return dataclasses.replace(self, horizon=h, horizon_source=source)

    def key(self):
        """The evaluation's key, PRNGKey(seed)."""
        import jax  # local: the command line builds its flags here without loading JAX

        return jax.random.PRNGKey(self.seed)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def describe(self, truth_used: str | None = None) -> str:
        """One line for beside every number: '16 episodes x 100 steps (source), seed 0, true
        values: measured'."""
        h = "? steps" if self.horizon is None else f"{self.horizon} steps"
        used = f" ({truth_used})" if truth_used and self.truth == "auto" else ""
        return (f"{self.episodes} episodes x {h} ({self.horizon_source}), seed {self.seed}, "
                f"true values: {self.truth}{used}")


def _positive(name: str):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = 0
        if value < 1:
            raise argparse.ArgumentTypeError(f"{name}: expected a positive integer, got {text!r}")
        return value
    return parse


def setting_flags(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """The setting's flags on a command's parser: --{prefix}episodes, --{prefix}horizon,
    --{prefix}seed and --truth (each None when not given: ``EvalSetting.from_flags``)."""
    for name, what in (
            ("episodes", f"simulated episodes per policy (default {EVAL_EPISODES})"),
            ("horizon", "steps per simulated episode (default: the checkpoint's vd_horizon; "
             "with no checkpoint the one training on this backend uses; at most the data's "
             "episode_length)"),
            ("seed", f"the evaluation's seed (default {EVAL_SEED})")):
        p.add_argument(f"--{prefix}{name}", help=what,
                       type=int if name == "seed" else _positive(f"{prefix}{name}"))
    p.add_argument("--truth", choices=TRUTHS, help="which true value: measured (the data's "
                   "value episodes, whole episodes only), logged (the logged episodes' return "
                   "over the horizon) or auto (default: measured where they apply)")


def _level(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = None
    if value is None or not 0 <= value < 1:
        raise argparse.ArgumentTypeError(f"level: expected a coverage level in [0, 1) such "
                                         f"as 0.9 (0: no intervals), got {text!r}")
    return value


def trust_flags(p: argparse.ArgumentParser) -> None:
    """`rl2s evaluate`'s value-interval flags: --level (0: none) and --calibration DATA."""
    p.add_argument("--level", type=_level, default=0.9, help="each policy's value interval at "
                   "this coverage level, split conformal over calibration policies (default "
                   "0.9; 0: no intervals; evaluate/trust.py)")
    p.add_argument("--calibration", action="append", metavar="DATA", help="a Dataset of "
                   "policies with known true values to calibrate the intervals on, never the "
                   "evaluated ones; repeatable (default: the checkpoint's training data)")


__all__ = ["EVAL_EPISODES", "EvalSetting", "profile_horizon", "setting_flags", "trust_flags"]
