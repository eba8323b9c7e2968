"""``TrainConfig``: the static settings of a training run (re-exported by ``rl2s_jax.train``).

Defaults are the paper-scale run: the official RL2S code's sizes (exp_specs/l2s_hopper.yaml)
and the ensemble model family (docs/SIMULATOR.md, "The model family"). ``TrainConfig.small()``
is a CPU-sized variant; ``TrainConfig().override(LEGACY_MODEL)`` is the single generator
trained from scratch that the project used before the family (one member, fixed log-std
bounds, no weight decay, no held-out episodes, no pre-training), which ``train_step``
reproduces exactly.

The fields nest: the generator's ``DynamicsSpec`` and three groups (``AdversarialConfig``,
``VDConfig``, ``OutcomeConfig``); run-level settings stay top-level. Dotted names address a
group's field ("dynamics.obs_history", ``--set dynamics.obs_history=2``); the flat format's
names of before (``FLAT_NAMES``) are read from saved configs and accepted by ``override`` for
one release.
"""
from __future__ import annotations

import dataclasses
import difflib
import math

from rl2s_jax.envs.tasks import TASKS, get_task
from rl2s_jax.model.dynamics import MEMBER_MODES, UNCERTAINTY_KINDS, DynamicsSpec
from rl2s_jax.model.reward import REWARDS
from rl2s_jax.model.termination import LEARNED, TERMINATIONS

METHODS = ("rl2s", "gail", "bc", "rl2s-bc")
DEFAULT_EPS = {"rl2s": 0.25, "gail": 1.0, "bc": 1.0, "rl2s-bc": 0.25}
# The saved format (``TrainConfig.to_dict``): 2 nests the groups; configs saved without a
# "version" are the flat format of before (one level, 59 fields), read through FLAT_NAMES.
CONFIG_VERSION = 2
# The flat format's names of the fields that moved into a group -> their dotted names. Read
# from saved configs, and accepted by ``override`` / ``--set`` for one release.
FLAT_NAMES = {
    **{f"gen_{k}": f"dynamics.{k}" for k in ("hidden", "noise", "activation",
                                             "log_std_bounds")},
    **{k: f"dynamics.{k}" for k in ("action_history", "obs_history", "time_inputs",
                                    "context_dim", "context_hidden", "matmul_dtype")},
    **{k: f"adversarial.{k}" for k in ("disc_hidden", "disc_updates", "disc_lr", "disc_beta1",
                                       "sim_envs", "sim_steps", "sim_horizon", "buffer_size",
                                       "pretrain_steps", "disc_warmup_steps")},
    "adv_nll_weight": "adversarial.nll_weight", "adv_nll_on": "adversarial.nll_on",
    **{f"vd_{k}": f"vd.{k}" for k in ("every", "episodes", "horizon")},
    **{k: f"outcome.{k}" for k in ("reward", "reward_hidden", "reward_steps", "termination",
                                   "hazard_hidden", "hazard_steps", "hazard_window")},
}
LEGACY_MODEL = {"ensemble_size": 1, "n_elites": 1, "dynamics.log_std_bounds": "fixed",
                "gen_weight_decay": 0.0, "holdout_frac": 0.0, "early_stop_patience": 0,
                "adversarial.pretrain_steps": 0, "adversarial.disc_warmup_steps": 0,
                "ema_decay": 0.0, "bc_lr": 1e-4, "nll_beta": 0.0, "sim_noise": 1.0,
                "adversarial.nll_weight": 0.0, "dynamics.activation": "relu", "batch_size": 256}

# Fields added after checkpoints were saved without them, with the value those runs had (a
# saved config that lacks one must not take today's default); flat-format names.
SAVED_BEFORE = {"gen_activation": "relu", "matmul_dtype": "float32"}


def _check_ints(obj, names, low: int, prefix: str = "", off: str = "") -> None:
    for name in names:
        v = getattr(obj, name)
        if not isinstance(v, int) or isinstance(v, bool) or v < low:
            raise ValueError(f"{prefix}{name}: expected an int >= {low}{off}, got {v!r}")


def _check_floats(obj, names, prefix: str = "", positive: bool = False) -> None:
    for name in names:
        v = getattr(obj, name)
        if not (isinstance(v, int | float) and math.isfinite(v) and (v > 0 if positive
                                                                      else v >= 0)):
            raise ValueError(f"{prefix}{name}: expected a "
                             f"{'positive finite float' if positive else 'finite float >= 0'}"
                             f", got {v!r}")


def _check_sizes(obj, names, prefix: str = "") -> None:
    for name in names:
        v = getattr(obj, name)
        if not (isinstance(v, tuple) and v and all(isinstance(h, int) and h > 0 for h in v)):
            raise ValueError(f"{prefix}{name}: expected a non-empty tuple of positive ints, "
                             f"got {v!r}")


@dataclasses.dataclass(frozen=True)
class AdversarialConfig:
    """rl2s / gail only: the critic, the simulated envs its fake batches come from, the MLE
    start (pre-training) and the likelihood anchor kept in the adversarial generator loss."""

    disc_hidden: tuple[int, ...] = (512, 512, 512, 512)
    disc_updates: int = 5          # critic updates before each generator update
    disc_lr: float = 1e-4
    disc_beta1: float = 0.5
    sim_envs: int = 32             # simulated envs stepping in p_phi
    sim_steps: int = 16            # their steps per train_step
    sim_horizon: int = 50          # a simulated env restarts from a real state after this
    buffer_size: int = 8192        # ring buffer of simulated (s, a)
    pretrain_steps: int = 1000     # MLE steps (all policies) before WGAIL
    disc_warmup_steps: int = 10    # critic-only steps after pre-training
    nll_weight: float = 10.0       # weight of the NLL of the real batch kept in the
    # adversarial generator loss; anchors the MLE start (0: pure WGAIL, the paper's, which
    # undid the start on every task: RESULTS)
    nll_on: str = "all"            # whose rows the anchor's batch comes from: "all" (its own
    # batch of every training policy, so regions the CVaR set leaves stay anchored: issue 41,
    # RESULTS) | "selected" (the CVaR set: the adversarial real batch itself; the default
    # before 2026-11-27) | "both" (the mean of the two batches' NLL)

    def validate(self) -> AdversarialConfig:
        p = "adversarial."
        _check_ints(self, ("disc_updates", "sim_envs", "sim_steps", "sim_horizon",
                           "buffer_size"), 1, p)
        _check_ints(self, ("pretrain_steps", "disc_warmup_steps"), 0, p, " (0 = off)")
        _check_sizes(self, ("disc_hidden",), p)
        _check_floats(self, ("disc_lr",), p, positive=True)
        _check_floats(self, ("nll_weight",), p)
        if self.nll_on not in ("selected", "all", "both"):
            raise ValueError(f"adversarial.nll_on: expected 'selected', 'all' or 'both', got "
                             f"{self.nll_on!r}")
        return self


@dataclasses.dataclass(frozen=True)
class VDConfig:
    """The value-difference (VD) measurement of the training policies in the simulator, which
    chooses the CVaR set."""

    every: int = 20                # K: train calls per VD measurement / CVaR refresh (0: off)
    episodes: int = 8              # simulated episodes per training policy per measurement
    horizon: int = 1000            # steps per simulated episode (the task's episode length)

    def validate(self) -> VDConfig:
        _check_ints(self, ("episodes", "horizon"), 1, "vd.")
        _check_ints(self, ("every",), 0, "vd.", " (0 = off)")
        return self


@dataclasses.dataclass(frozen=True)
class OutcomeConfig:
    """A simulated step's reward and whether its episode ends, and the heads learned for
    them (rl2s_jax.model.reward, rl2s_jax.model.termination)."""

    reward: str = "task"           # the registered task's reward_fn | "learned", a head
    # r(s, a, s') fitted on the data's rewards in ``init`` (`rl2s train` picks it, and
    # termination "hazard", for data of no registered task)
    reward_hidden: tuple[int, ...] = (256, 256)  # the reward head's hidden sizes
    reward_steps: int = 3000       # its Adam updates (in ``init``, on every training row)
    termination: str = "rule"      # the task's "rule" on the simulated state | a learned
    # "hazard" h(s, a) of the logged done flags | "both" | "predictive": the rule also on one
    # draw at noise scale 1
    hazard_hidden: tuple[int, ...] = (256, 256)  # the hazard classifier's hidden sizes
    hazard_steps: int = 3000       # its Adam updates (in ``init``, on every training row)
    hazard_window: int = 1         # K: it learns P(end within K steps), steps end with
    # 1 - (1 - P)^(1/K) (1: the one-step hazard itself)

    def validate(self) -> OutcomeConfig:
        p = "outcome."
        _check_ints(self, ("hazard_window", "reward_steps"), 1, p)
        _check_ints(self, ("hazard_steps",), 0, p, " (0 = off)")
        _check_sizes(self, ("hazard_hidden", "reward_hidden"), p)
        for name, kinds in (("termination", TERMINATIONS), ("reward", REWARDS)):
            if getattr(self, name) not in kinds:
                raise ValueError(f"{p}{name}: expected one of {', '.join(map(repr, kinds))}, "
                                 f"got {getattr(self, name)!r}")
        if self.termination in LEARNED and self.hazard_steps == 0:
            raise ValueError(f"outcome.hazard_steps: termination {self.termination!r} learns a "
                             f"hazard; expected an int >= 1, got 0")
        return self


# The generator's member of the dynamics-model family, as the paper-scale run has it.
DEFAULT_DYNAMICS = DynamicsSpec(hidden=(512, 512, 512, 512), noise="state",
                                log_std_bounds="learned", activation="silu")
GROUPS = {"dynamics": DynamicsSpec, "adversarial": AdversarialConfig, "vd": VDConfig,
          "outcome": OutcomeConfig}


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Static settings of a training run (hashable: it is part of the jit cache key).

    The run-level settings are its own fields; ``dynamics`` is the generator's member of the
    model family (``DynamicsSpec``: sizes, noise, activation, history inputs -- the one place
    the history lengths live), ``adversarial`` the rl2s / gail settings, ``vd`` the VD
    measurement, ``outcome`` the reward and termination of a simulated step. ``override``
    takes dotted names ("dynamics.obs_history") and, for one release, the flat format's
    (``FLAT_NAMES``).

    ``eps=None`` takes the method's default (0.25 for rl2s and rl2s-bc, 1 for gail and bc); it
    is only the initial value of the vmappable ``TrainState.eps``. Steps are ``train_step``
    calls ("train calls"), each ``updates_per_step`` generator updates.
    """

    task: str = "hopper"
    method: str = "rl2s"
    eps: float | None = None
    dynamics: DynamicsSpec = DEFAULT_DYNAMICS
    adversarial: AdversarialConfig = AdversarialConfig()
    vd: VDConfig = VDConfig()
    outcome: OutcomeConfig = OutcomeConfig()
    batch_size: int = 1024         # 256 left the ensemble underfit (RESULTS@bf0c7b2, "Ant and
    # Hopper: the likelihood model was underfit")
    updates_per_step: int = 50     # generator updates per train_step (a "train call")
    gen_lr: float = 1e-4
    bc_lr: float = 1e-3             # with nll_beta 1; 1e-4 left the ensemble underfit (RESULTS)
    grad_clip: float = 0.5         # elementwise gradient clip, as the official code
    gamma: float = 0.999
    obs_clip: float = 10.0         # simulated states kept within +-obs_clip data stds
    sim_noise: float = 0.0         # std scale of p_phi in simulated rollouts (0: its mean;
    # the systems are deterministic and sampling their learned std topples walkers: RESULTS)
    input_ignore_dims: tuple[int, ...] | None = None  # obs dims the networks do not see;
    # None: the task's position_dims (absolute x, y), () for none
    # -- the ensemble (rl2s_jax.model.dynamics; docs/SIMULATOR.md, "The model family")
    ensemble_size: int = 7         # E members, trained as one vmapped program
    n_elites: int = 5              # rollouts use the n_elites lowest held-out NLL members
    member_mode: str = "random"    # rollout step: a random elite | "mean" | "fixed" (best)
    uncertainty: str = "std"       # disagreement: "std" of elite means | "max_pairwise"
    log_std_bound_weight: float = 0.01   # PETS' weight on sum(max) - sum(min) log-std
    gen_weight_decay: float = 0.0  # L2 on the generator's weight matrices (mbrl-lib MBPO's
    # 5e-5 did not lower the held-out error on Ant; off in the measured defaults)
    holdout_frac: float = 0.1      # whole episodes per training policy held out (0: none)
    holdout_rows: int = 8192       # held-out rows scored every step (evenly spread subset)
    early_stop_patience: int = 0   # MLE steps without held-out gain before a member stops
    # (0: off; at 50 every Ant member stopped within 200 steps, far from fitted: RESULTS)
    early_stop_min_delta: float = 0.01  # nats per transition that count as a gain
    ema_decay: float = 0.0         # EMA of the generator for evaluation (0: off)
    multistep_steps: int = 1       # k: MLE loss adds the mean's k-step error (1: one-step only)
    multistep_weight: float = 1.0  # weight of that k-step error (squared, in data stds)
    nll_beta: float = 1.0          # beta-NLL exponent of the likelihood loss (0: plain NLL;
    # 1: the mean learns as under squared error, losses.generator_beta_nll_loss)
    data_episode_length: int | None = None  # the data's time limit (meta.episode_length),
    # what the "step" time input and simulated envs use where no registered task gives one
    # (None: vd.horizon)
    physics: str | None = None     # a hybrid (rl2s_jax.physics.hybrid): the calibrated.json
    # of `rl2s diagnose --physics` whose physics the members' delta is added to; they learn
    # its residual by likelihood ("bc"; VD off in training: its rollouts would step the
    # members alone). None: the plain learned simulator
    scan_unroll: int = 1           # lax.scan unroll of a step's update loops (the likelihood
    # updates, the critic updates, the adversarial updates): fewer loop iterations on the GPU,
    # the same updates (issue 63: the one-lane chain is launch-bound); 1: no unrolling
    batches_up_front: bool = False  # draw every update's batches of a step (and the critic
    # updates' fake states, the members' noise keys) before its chain of updates, as one
    # batched draw, not inside each update: the same numbers, the step's batches held in
    # memory at once; no faster on an H200 (1.00x, docs/BENCHMARKS.md), hence off
    flat_optimizer: bool = False   # the members' and the critic's optimisers over one flat
    # vector of their parameters (optax.flatten): the same elementwise updates in fewer,
    # larger kernels per update (issue 63: the chain of small updates is launch-bound); 1.01x
    # on an H200 (docs/BENCHMARKS.md), hence off; the optimiser state's layout differs, so a
    # checkpoint keeps the setting it was saved with

    @property
    def is_adversarial(self) -> bool:
        """rl2s or gail: a critic and simulated envs (``adversarial``)."""
        return self.method in ("rl2s", "gail")

    @property
    def ignore_dims(self) -> tuple[int, ...]:
        if self.input_ignore_dims is not None:
            return tuple(self.input_ignore_dims)
        return get_task(self.task).position_dims if self.task in TASKS else ()

    @property
    def initial_eps(self) -> float:
        return DEFAULT_EPS[self.method] if self.eps is None else float(self.eps)

    def simulator_settings(self, noise_scale: float | None = None) -> dict:
        """The static ``Simulator`` fields this run's simulator steps with (noise_scale:
        default sim_noise)."""
        d = self.dynamics
        return dict(task=self.task, obs_clip=self.obs_clip,
                    noise_scale=self.sim_noise if noise_scale is None else noise_scale,
                    n_elites=self.n_elites, member_mode=self.member_mode,
                    uncertainty=self.uncertainty, termination=self.outcome.termination,
                    hazard_window=self.outcome.hazard_window, obs_history=d.obs_history,
                    action_history=d.action_history, time_inputs=tuple(d.time_inputs),
                    episode_length=self.episode_length)

    @property
    def markov(self) -> bool:
        """True when the members see the current (s, a) only (no history inputs)."""
        return self.dynamics.markov

    @property
    def episode_length(self) -> int:
        """What scales the "step" time input: the task's time limit (without a registered task
        the data's, data_episode_length, or else vd.horizon)."""
        if self.task in TASKS:
            return get_task(self.task).episode_length
        return self.data_episode_length or self.vd.horizon

    @property
    def registered(self) -> bool:
        """True when ``task`` names a task registered in this process."""
        return self.task in TASKS

    @property
    def early_stopping(self) -> bool:
        return self.early_stop_patience > 0

    @property
    def pretrains(self) -> bool:
        """An adversarial method with an MLE pre-training phase."""
        return self.is_adversarial and self.adversarial.pretrain_steps > 0

    def phase(self, step: int) -> str | None:
        """The phase of the train_step taken at ``step`` (known on the host): "pretrain" or
        "main"; None when the method has one phase (MLE methods, no pre-training)."""
        if not self.pretrains:
            return None
        return "pretrain" if step < self.adversarial.pretrain_steps else "main"

    @classmethod
    def small(cls, **overrides) -> TrainConfig:
        """A CPU-sized config: 2x64 networks, 3 members, short value rollouts, few updates per
        step. No pre-training (the tests exercise the adversarial step from the first call;
        the 'cpu' profile of ``app.training.make_config`` adds it, and fits larger members,
        ``CPU_MODEL``). Its members are the tests' small ones: 2x64 ReLU, batch 64, weight
        decay 5e-5, early stopping at patience 30. ``overrides``: as ``override``'s (a
        field, a group, or a flat-format name)."""
        small = cls(
            dynamics=dataclasses.replace(DEFAULT_DYNAMICS, hidden=(64, 64), activation="relu"),
            adversarial=AdversarialConfig(disc_hidden=(64, 64), disc_updates=2, sim_envs=16,
                                          sim_steps=4, buffer_size=1024, disc_lr=1e-3,
                                          pretrain_steps=0, disc_warmup_steps=0),
            vd=VDConfig(every=5, episodes=4, horizon=100), batch_size=64, updates_per_step=5,
            gen_lr=1e-3, bc_lr=1e-3, ensemble_size=3, n_elites=2, holdout_rows=1024,
            early_stop_patience=30, gen_weight_decay=5e-5)
        return small.override(overrides)

    def override(self, changes: dict | None = None, what: str = "config") -> TrainConfig:
        """This config with ``changes`` {name: value}: a field ("batch_size"), a group
        ("dynamics": a DynamicsSpec or a dict of its fields), a group's field by its dotted
        name ("dynamics.obs_history"), or a flat-format name ("obs_history", ``FLAT_NAMES``).
        Lists become tuples. An unknown name raises ValueError (prefixed ``what``) with the
        closest known name."""
        top, groups = {}, {}
        for key, value in _dotted(changes or {}, what).items():
            value = tuple(value) if isinstance(value, list) else value
            group, _, field = key.partition(".")
            if field:
                groups.setdefault(group, {})[field] = value
            else:
                top[key] = value
        for group, fields in groups.items():
            base = top.get(group, getattr(self, group))
            top[group] = dataclasses.replace(base, **fields)
        return dataclasses.replace(self, **top)

    def validate(self) -> TrainConfig:
        """Raise ValueError naming the first bad field (dotted for a group's); returns self."""
        if self.method not in METHODS:
            raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {self.method!r}")
        if not 0.0 < self.initial_eps <= 1.0:
            raise ValueError(f"eps: expected a float in (0, 1], got {self.eps!r}")
        for name, kind in GROUPS.items():
            if not isinstance(getattr(self, name), kind):
                raise ValueError(f"{name}: expected a {kind.__name__}, got "
                                 f"{getattr(self, name)!r}")
        self.dynamics.validate({f.name: f"dynamics.{f.name}"
                                for f in dataclasses.fields(DynamicsSpec)})
        self.adversarial.validate()
        self.vd.validate()
        self.outcome.validate()
        _check_ints(self, ("batch_size", "updates_per_step", "ensemble_size", "n_elites",
                           "holdout_rows", "multistep_steps", "scan_unroll"), 1)
        _check_ints(self, ("early_stop_patience",), 0, off=" (0 = off)")
        for name in ("batches_up_front", "flat_optimizer"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: expected true or false, got "
                                 f"{getattr(self, name)!r}")
        _check_floats(self, ("gen_lr", "bc_lr", "grad_clip", "obs_clip"), positive=True)
        _check_floats(self, ("sim_noise", "log_std_bound_weight", "gen_weight_decay",
                             "early_stop_min_delta", "multistep_weight", "nll_beta"))
        self._check_ranges()
        self._check_across_groups()
        self._check_task_rules()
        self._check_physics_rules()
        return self

    def _check_ranges(self) -> None:
        """The fractions and kinds of the run-level fields."""
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"gamma: expected a float in (0, 1], got {self.gamma!r}")
        if not (isinstance(self.holdout_frac, int | float) and 0.0 <= self.holdout_frac < 1.0):
            raise ValueError(f"holdout_frac: expected a fraction in [0, 1), got "
                             f"{self.holdout_frac!r}")
        if not (isinstance(self.ema_decay, int | float) and 0.0 <= self.ema_decay < 1.0):
            raise ValueError(f"ema_decay: expected a float in [0, 1) (0 = off), got "
                             f"{self.ema_decay!r}")
        for name, kinds in (("member_mode", MEMBER_MODES), ("uncertainty", UNCERTAINTY_KINDS)):
            if getattr(self, name) not in kinds:
                raise ValueError(f"{name}: expected one of {', '.join(map(repr, kinds))}, got "
                                 f"{getattr(self, name)!r}")
        v = self.data_episode_length
        if v is not None and (not isinstance(v, int) or isinstance(v, bool) or v < 1):
            raise ValueError(f"data_episode_length: expected an int >= 1 or None, got {v!r}")

    def _check_across_groups(self) -> None:
        """The rules that tie fields of different groups together."""
        d = self.dynamics
        if self.vd.every == 0 and self.initial_eps < 1.0:
            raise ValueError(f"vd.every: 0 turns off VD, which method {self.method!r} with eps "
                             f"{self.initial_eps} needs to choose its worst policies")
        if d.context_dim and not (d.obs_history and d.action_history):
            raise ValueError(f"dynamics.context_dim: the context is inferred from the episode's "
                             f"recent transitions; set obs_history and action_history >= 1 (the "
                             f"window is their minimum), got obs_history {d.obs_history}, "
                             f"action_history {d.action_history}")
        if self.outcome.termination == "predictive" and not self.markov:
            raise ValueError("outcome.termination: 'predictive' draws a next state from (s, a) "
                             "alone; with history inputs use 'rule', 'hazard' or 'both'")
        if self.n_elites > self.ensemble_size:
            raise ValueError(f"n_elites: expected at most ensemble_size ({self.ensemble_size}), "
                             f"got {self.n_elites}")
        if self.holdout_frac == 0 and self.n_elites < self.ensemble_size:
            raise ValueError(f"n_elites: choosing {self.n_elites} of {self.ensemble_size} "
                             "members needs held-out episodes to score them; set holdout_frac "
                             "> 0 or n_elites = ensemble_size")
        if self.holdout_frac == 0 and self.early_stop_patience:
            raise ValueError("early_stop_patience: early stopping needs held-out episodes; set "
                             "holdout_frac > 0 or early_stop_patience = 0")
        if self.is_adversarial and self.adversarial.buffer_size < self.batch_size:
            raise ValueError(f"adversarial.buffer_size: expected >= batch_size "
                             f"({self.batch_size}), got {self.adversarial.buffer_size}")

    def _check_physics_rules(self) -> None:
        """A hybrid (``physics`` set) learns the physics' residual by likelihood: every
        rollout inside ``train_step`` (the VD measurement, the adversarial samples) would step
        the members alone, which are not the hybrid, and a learned reward would be fitted to
        the residual rather than to the next state."""
        if self.physics is None:
            return
        if not isinstance(self.physics, str) or not self.physics:
            raise ValueError(f"physics: expected the path of a calibrated.json, got "
                             f"{self.physics!r}")
        if self.method != "bc":
            raise ValueError(f"method: a hybrid (physics {self.physics!r}) learns the "
                             f"physics' residual by likelihood, method 'bc'; {self.method!r} "
                             f"rolls the learned model alone inside train_step (use --method "
                             f"bc)")
        if self.vd.every:
            raise ValueError(f"vd.every: a hybrid trains with the VD measurement off (0): it "
                             f"would roll the residual model alone; got {self.vd.every}")
        if self.outcome.reward != "task":
            raise ValueError(f"outcome.reward: a hybrid takes the task's reward_fn ('task'); a "
                             f"learned reward would be fitted to the residual, got "
                             f"{self.outcome.reward!r}")

    def _check_task_rules(self) -> None:
        """Without a registered task nothing gives simulated steps a reward or a termination
        rule: where rollouts run (vd.every > 0, or the adversarial methods' simulated envs),
        the reward must be learned and the termination the learned hazard."""
        if self.registered or not (self.vd.every or self.is_adversarial):
            return
        what = (f"task {self.task!r} is not registered" if self.task is not None
                else "the data names no task (meta.task null)")
        if self.outcome.reward != "learned":
            raise ValueError(f"outcome.reward: {self.outcome.reward!r} takes rewards from the "
                             f"registered task's reward_fn, and {what}; set "
                             f"outcome.reward='learned' (a head fitted on the data's rewards) "
                             f"or register the task (rl2s_jax.envs.tasks.register)")
        if self.outcome.termination not in LEARNED:
            raise ValueError(f"outcome.termination: {self.outcome.termination!r} ends episodes "
                             f"by the registered task's done_fn, and {what}; set "
                             f"outcome.termination='hazard' (learned from the data's done "
                             f"flags) or register the task")

    def to_dotted(self) -> dict:
        """{name: value}, a group's fields by their dotted names ("dynamics.obs_history")."""
        out = {}
        for key, value in dataclasses.asdict(self).items():
            if key in GROUPS:
                out.update({f"{key}.{k}": v for k, v in value.items()})
            else:
                out[key] = value
        return out

    def to_dict(self) -> dict:
        """The saved format: {"version": CONFIG_VERSION, field: value, group: {field: value}}
        (JSON-ready but for tuples)."""
        return {"version": CONFIG_VERSION, **dataclasses.asdict(self)}

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        """A config from ``to_dict``'s format, or from the flat format of before (no
        "version"): the fields it lacks take today's defaults."""
        if not isinstance(d, dict):
            raise ValueError(f"config: expected a dict, got {type(d).__name__}")
        d = dict(d)
        version = d.pop("version", None)
        if version not in (None, CONFIG_VERSION):
            raise ValueError(f"config: version {version!r} is not one this code reads "
                             f"({CONFIG_VERSION}, or none for the flat format)")
        return cls().override(d)

    @classmethod
    def from_saved(cls, d: dict) -> TrainConfig:
        """A config read back from a checkpoint: the fields a flat-format config predates take
        the values its run had (``SAVED_BEFORE``), not today's defaults."""
        return cls.from_dict(d if "version" in d else {**SAVED_BEFORE, **d})


def saved_field(saved: dict, name: str, default=None):
    """The value of ``name`` (dotted for a group's field: "vd.horizon") in a saved config dict
    of either format (``TrainConfig.to_dict``'s, or the flat one of before), without building
    the config (a saved dict may hold only some fields); ``default`` where it is absent."""
    if "version" not in saved:
        flat = {v: k for k, v in FLAT_NAMES.items()}
        return saved.get(flat.get(name, name), default)
    group, _, field = name.partition(".")
    if not field:
        return saved.get(name, default)
    return (saved.get(group) or {}).get(field, default)


def known_names() -> list[str]:
    """Every name ``override`` takes: the fields, the groups and their dotted fields."""
    names = []
    for f in dataclasses.fields(TrainConfig):
        names.append(f.name)
        if f.name in GROUPS:
            names += [f"{f.name}.{g.name}" for g in dataclasses.fields(GROUPS[f.name])]
    return names


def _dotted(changes: dict, what: str) -> dict:
    """``changes`` with flat-format names mapped to dotted ones and a group given as a dict
    spread into dotted names; an unknown name raises ValueError with the closest known."""
    known = set(known_names())
    out = {}
    for key, value in changes.items():
        key = FLAT_NAMES.get(key, key)
        if key in GROUPS and isinstance(value, dict):
            out.update({f"{key}.{k}": v for k, v in value.items()})
        else:
            out[key] = value
    for key in out:
        if key not in known:
            close = difflib.get_close_matches(key, [*known, *FLAT_NAMES], n=1, cutoff=0.6)
            hint = f"; did you mean {FLAT_NAMES.get(close[0], close[0])!r}?" if close else (
                "; known: the fields of TrainConfig and its groups (train.config.known_names)")
            raise ValueError(f"{what}: unknown config field {key!r}{hint}")
    return out
