"""``TrainConfig``: the static settings of a training run (re-exported by ``rl2s_jax.train``).

Defaults are the paper-scale run: the official RL2S code's sizes (exp_specs/l2s_hopper.yaml)
and the ensemble model family (docs/SIMULATOR.md, "The model family"). ``TrainConfig.small()``
is a CPU-sized variant; ``TrainConfig(**LEGACY_MODEL)`` is the single generator trained from
scratch that the project used before the family (one member, fixed log-std bounds, no weight
decay, no held-out episodes, no pre-training), which ``train_step`` reproduces exactly.
"""
from __future__ import annotations

import dataclasses
import math

from rl2s_jax.envs.tasks import TASKS, get_task
from rl2s_jax.model.dynamics import (
    ACTIVATIONS,
    BOUND_KINDS,
    MATMUL_DTYPES,
    MEMBER_MODES,
    NOISE_KINDS,
    TIME_INPUTS,
    UNCERTAINTY_KINDS,
    DynamicsSpec,
)
from rl2s_jax.model.reward import REWARDS
from rl2s_jax.model.termination import LEARNED, TERMINATIONS

METHODS = ("rl2s", "gail", "bc", "rl2s-bc")
DEFAULT_EPS = {"rl2s": 0.25, "gail": 1.0, "bc": 1.0, "rl2s-bc": 0.25}
LEGACY_MODEL = dict(ensemble_size=1, n_elites=1, gen_log_std_bounds="fixed",
                    gen_weight_decay=0.0, holdout_frac=0.0, early_stop_patience=0,
                    pretrain_steps=0, disc_warmup_steps=0, ema_decay=0.0, bc_lr=1e-4,
                    nll_beta=0.0, sim_noise=1.0, adv_nll_weight=0.0, gen_activation="relu",
                    batch_size=256)

# Fields added after checkpoints were saved without them, with the value those runs had (a
# saved config that lacks one must not take today's default).
SAVED_BEFORE = {"gen_activation": "relu", "matmul_dtype": "float32"}


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Static settings of a training run (hashable: it is part of the jit cache key).

    ``eps=None`` takes the method's default (0.25 for rl2s and rl2s-bc, 1 for gail and bc); it
    is only the initial value of the vmappable ``TrainState.eps``. Steps are ``train_step``
    calls ("train calls"), each ``updates_per_step`` generator updates.
    """

    task: str = "hopper"
    method: str = "rl2s"
    eps: float | None = None
    gen_hidden: tuple[int, ...] = (512, 512, 512, 512)
    disc_hidden: tuple[int, ...] = (512, 512, 512, 512)
    batch_size: int = 1024         # 256 left the ensemble underfit (RESULTS@bf0c7b2, "Ant and
    # Hopper: the likelihood model was underfit")
    updates_per_step: int = 50     # generator updates per train_step (a "train call")
    disc_updates: int = 5          # critic updates before each generator update
    gen_lr: float = 1e-4
    disc_lr: float = 1e-4
    disc_beta1: float = 0.5
    bc_lr: float = 1e-3             # with nll_beta 1; 1e-4 left the ensemble underfit (RESULTS)
    grad_clip: float = 0.5         # elementwise gradient clip, as the official code
    sim_envs: int = 32             # simulated envs stepping in p_phi (adversarial methods)
    sim_steps: int = 16            # their steps per train_step
    sim_horizon: int = 50          # a simulated env restarts from a real state after this
    buffer_size: int = 8192        # ring buffer of simulated (s, a)
    vd_every: int = 20             # K: calls per VD measurement / CVaR refresh
    vd_episodes: int = 8           # simulated episodes per training policy per measurement
    vd_horizon: int = 1000         # steps per simulated episode (the task's episode length)
    gamma: float = 0.999
    obs_clip: float = 10.0         # simulated states kept within +-obs_clip data stds
    sim_noise: float = 0.0         # std scale of p_phi in simulated rollouts (0: its mean;
    # the systems are deterministic and sampling their learned std topples walkers: RESULTS)
    input_ignore_dims: tuple[int, ...] | None = None  # obs dims the networks do not see;
    # None: the task's position_dims (absolute x, y), () for none
    # -- the dynamics-model family (rl2s_jax.model.dynamics; docs/SIMULATOR.md)
    ensemble_size: int = 7         # E members, trained as one vmapped program
    n_elites: int = 5              # rollouts use the n_elites lowest held-out NLL members
    member_mode: str = "random"    # rollout step: a random elite | "mean" | "fixed" (best)
    uncertainty: str = "std"       # disagreement: "std" of elite means | "max_pairwise"
    gen_noise: str = "state"       # "state": log-std head | "global": one log-std per dim
    gen_activation: str = "silu"   # the members' hidden activation: "silu" | "relu"
    gen_log_std_bounds: str = "learned"  # "fixed" [-5, 1] | "learned" (PETS)
    log_std_bound_weight: float = 0.01   # PETS' weight on sum(max) - sum(min) log-std
    gen_weight_decay: float = 0.0  # L2 on the generator's weight matrices (mbrl-lib MBPO's
    # 5e-5 did not lower the held-out error on Ant; off in the measured defaults)
    holdout_frac: float = 0.1      # whole episodes per training policy held out (0: none)
    holdout_rows: int = 8192       # held-out rows scored every step (evenly spread subset)
    early_stop_patience: int = 0   # MLE steps without held-out gain before a member stops
    # (0: off; at 50 every Ant member stopped within 200 steps, far from fitted: RESULTS)
    early_stop_min_delta: float = 0.01  # nats per transition that count as a gain
    pretrain_steps: int = 1000     # rl2s / gail: MLE steps (all policies) before WGAIL
    disc_warmup_steps: int = 10    # rl2s / gail: critic-only steps after pre-training
    ema_decay: float = 0.0         # EMA of the generator for evaluation (0: off)
    # -- history inputs (docs/SIMULATOR.md, "History inputs"; what `rl2s diagnose` proposes)
    action_history: int = 0        # k previous actions of the episode fed to every member
    obs_history: int = 0           # k previous observations of the episode
    time_inputs: tuple[str, ...] = ()  # of ("order", "step"): "step", t / episode_length, the
    # place in the episode; "order", the episode's place in the recording (0 first, 1 last;
    # rollouts run at 1, the newest dynamics)
    context_dim: int = 0           # C: a per-episode context inferred online from the episode's
    # min(obs_history, action_history) newest transitions (history.history_context; 0: off)
    context_hidden: tuple[int, ...] = (64, 64)  # the context encoder's hidden sizes
    multistep_steps: int = 1       # k: MLE loss adds the mean's k-step error (1: one-step only)
    multistep_weight: float = 1.0  # weight of that k-step error (squared, in data stds)
    nll_beta: float = 1.0          # beta-NLL exponent of the likelihood loss (0: plain NLL;
    # 1: the mean learns as under squared error, losses.generator_beta_nll_loss)
    adv_nll_weight: float = 10.0   # rl2s / gail: weight of the NLL of the real batch kept in
    # the adversarial generator loss; anchors the MLE start (0: pure WGAIL, the paper's,
    # which undid the start on every task: RESULTS)
    adv_nll_on: str = "all"        # whose rows the anchor's batch comes from: "all" (its own
    # batch of every training policy, so regions the CVaR set leaves stay anchored: issue 41,
    # RESULTS) | "selected" (the CVaR set: the adversarial real batch itself; the default
    # before 2026-11-27) | "both" (the mean of the two batches' NLL)
    termination: str = "rule"      # what ends a simulated episode: the task's "rule" on the
    # simulated state | a learned "hazard" h(s, a) of the logged done flags | "both" |
    # "predictive": the rule also on one draw at noise scale 1 (rl2s_jax.model.termination)
    hazard_hidden: tuple[int, ...] = (256, 256)  # the hazard classifier's hidden sizes
    hazard_steps: int = 3000       # its Adam updates (in ``init``, on every training row)
    hazard_window: int = 1         # K: it learns P(end within K steps), steps end with
    # 1 - (1 - P)^(1/K) (1: the one-step hazard itself)
    reward: str = "task"           # a simulated step's reward: the registered task's
    # reward_fn | "learned", a head r(s, a, s') fitted on the data's rewards in ``init``
    # (rl2s_jax.model.reward; `rl2s train` picks it, and termination "hazard", for data of no
    # registered task)
    reward_hidden: tuple[int, ...] = (256, 256)  # the reward head's hidden sizes
    reward_steps: int = 3000       # its Adam updates (in ``init``, on every training row)
    data_episode_length: int | None = None  # the data's time limit (meta.episode_length),
    # what the "step" time input and simulated envs use where no registered task gives one
    # (None: vd_horizon)
    matmul_dtype: str = "float32"  # the hidden layers' matmuls of the members and the critic:
    # "bfloat16" rounds their inputs and weights to bf16 and accumulates in float32 (forward
    # and backward; parameters, optimiser state, losses and outputs stay float32;
    # dynamics.matmul). Unmeasured on the GPU so far: docs/BENCHMARKS.md
    physics: str | None = None     # a hybrid (rl2s_jax.physics.hybrid): the calibrated.json
    # of `rl2s diagnose --physics` whose physics the members' delta is added to; they learn
    # its residual by likelihood ("bc"; VD off in training: its rollouts would step the
    # members alone). None: the plain learned simulator

    @property
    def adversarial(self) -> bool:
        return self.method in ("rl2s", "gail")

    @property
    def ignore_dims(self) -> tuple[int, ...]:
        if self.input_ignore_dims is not None:
            return tuple(self.input_ignore_dims)
        return get_task(self.task).position_dims if self.task in TASKS else ()

    @property
    def initial_eps(self) -> float:
        return DEFAULT_EPS[self.method] if self.eps is None else float(self.eps)

    @property
    def dynamics_spec(self) -> DynamicsSpec:
        """The generator as a member of the dynamics-model family."""
        return DynamicsSpec(hidden=self.gen_hidden, noise=self.gen_noise,
                            activation=self.gen_activation,
                            log_std_bounds=self.gen_log_std_bounds,
                            action_history=self.action_history, obs_history=self.obs_history,
                            time_inputs=tuple(self.time_inputs),
                            context_dim=self.context_dim,
                            context_hidden=tuple(self.context_hidden),
                            matmul_dtype=self.matmul_dtype)

    def simulator_settings(self, noise_scale: float | None = None) -> dict:
        """The static ``Simulator`` fields this run's simulator steps with (noise_scale:
        default sim_noise)."""
        return dict(task=self.task, obs_clip=self.obs_clip,
                    noise_scale=self.sim_noise if noise_scale is None else noise_scale,
                    n_elites=self.n_elites, member_mode=self.member_mode,
                    uncertainty=self.uncertainty, termination=self.termination,
                    hazard_window=self.hazard_window, obs_history=self.obs_history,
                    action_history=self.action_history, time_inputs=tuple(self.time_inputs),
                    episode_length=self.episode_length)

    @property
    def markov(self) -> bool:
        """True when the members see the current (s, a) only (no history inputs)."""
        return self.dynamics_spec.markov

    @property
    def episode_length(self) -> int:
        """What scales the "step" time input: the task's time limit (without a registered task
        the data's, data_episode_length, or else vd_horizon)."""
        if self.task in TASKS:
            return get_task(self.task).episode_length
        return self.data_episode_length or self.vd_horizon

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
        return self.adversarial and self.pretrain_steps > 0

    def phase(self, step: int) -> str | None:
        """The phase of the train_step taken at ``step`` (known on the host): "pretrain" or
        "main"; None when the method has one phase (MLE methods, no pre-training)."""
        if not self.pretrains:
            return None
        return "pretrain" if step < self.pretrain_steps else "main"

    @classmethod
    def small(cls, **overrides) -> TrainConfig:
        """A CPU-sized config: 2x64 networks, 3 members, short value rollouts, few updates per
        step. No pre-training (the tests exercise the adversarial step from the first call;
        the 'cpu' profile of ``fit.make_config`` adds it, and fits larger members,
        ``fit.CPU_MODEL``). Its members are the tests' small ones: 2x64 ReLU, batch 64,
        weight decay 5e-5, early stopping at patience 30."""
        base = dict(gen_hidden=(64, 64), disc_hidden=(64, 64), batch_size=64,
                    updates_per_step=5, disc_updates=2, sim_envs=16, sim_steps=4,
                    buffer_size=1024, vd_every=5, vd_episodes=4, vd_horizon=100,
                    gen_lr=1e-3, disc_lr=1e-3, bc_lr=1e-3, ensemble_size=3, n_elites=2,
                    holdout_rows=1024, early_stop_patience=30, pretrain_steps=0,
                    disc_warmup_steps=0, gen_activation="relu", gen_weight_decay=5e-5)
        base.update(overrides)
        return cls(**base)

    def validate(self) -> TrainConfig:
        """Raise ValueError naming the first bad field; returns self."""
        if self.method not in METHODS:
            raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {self.method!r}")
        if not 0.0 < self.initial_eps <= 1.0:
            raise ValueError(f"eps: expected a float in (0, 1], got {self.eps!r}")
        for name in ("batch_size", "updates_per_step", "disc_updates", "sim_envs", "sim_steps",
                     "sim_horizon", "buffer_size", "vd_episodes", "vd_horizon",
                     "ensemble_size", "n_elites", "holdout_rows", "multistep_steps",
                     "hazard_window", "reward_steps"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
        for name in ("vd_every", "early_stop_patience", "pretrain_steps", "disc_warmup_steps",
                     "hazard_steps"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"{name}: expected an int >= 0 (0 = off), got {v!r}")
        if self.vd_every == 0 and self.initial_eps < 1.0:
            raise ValueError(f"vd_every: 0 turns off VD, which method {self.method!r} with eps "
                             f"{self.initial_eps} needs to choose its worst policies")
        for name in ("gen_hidden", "disc_hidden", "hazard_hidden", "reward_hidden"):
            v = getattr(self, name)
            if not (isinstance(v, tuple) and v and all(isinstance(h, int) and h > 0 for h in v)):
                raise ValueError(f"{name}: expected a non-empty tuple of positive ints, got {v!r}")
        for name in ("gen_lr", "disc_lr", "bc_lr", "grad_clip", "obs_clip"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite float, got {v!r}")
        for name in ("sim_noise", "log_std_bound_weight", "gen_weight_decay",
                     "early_stop_min_delta", "multistep_weight", "adv_nll_weight",
                     "nll_beta"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name}: expected a finite float >= 0, got {v!r}")
        if self.adv_nll_on not in ("selected", "all", "both"):
            raise ValueError(f"adv_nll_on: expected 'selected', 'all' or 'both', got "
                             f"{self.adv_nll_on!r}")
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"gamma: expected a float in (0, 1], got {self.gamma!r}")
        if not (isinstance(self.holdout_frac, int | float) and 0.0 <= self.holdout_frac < 1.0):
            raise ValueError(f"holdout_frac: expected a fraction in [0, 1), got "
                             f"{self.holdout_frac!r}")
        if not (isinstance(self.ema_decay, int | float) and 0.0 <= self.ema_decay < 1.0):
            raise ValueError(f"ema_decay: expected a float in [0, 1) (0 = off), got "
                             f"{self.ema_decay!r}")
        for name, kinds in (("member_mode", MEMBER_MODES), ("uncertainty", UNCERTAINTY_KINDS),
                            ("gen_noise", NOISE_KINDS), ("gen_log_std_bounds", BOUND_KINDS),
                            ("gen_activation", ACTIVATIONS), ("matmul_dtype", MATMUL_DTYPES),
                            ("termination", TERMINATIONS), ("reward", REWARDS)):
            if getattr(self, name) not in kinds:
                raise ValueError(f"{name}: expected one of {', '.join(map(repr, kinds))}, got "
                                 f"{getattr(self, name)!r}")
        for name in ("action_history", "obs_history"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"{name}: expected an int >= 0 (0 = off), got {v!r}")
        v = self.context_dim
        if not isinstance(v, int) or isinstance(v, bool) or v < 0:
            raise ValueError(f"context_dim: expected an int >= 0 (0 = off), got {v!r}")
        if v and not (self.obs_history and self.action_history):
            raise ValueError(f"context_dim: the context is inferred from the episode's recent "
                             f"transitions; set obs_history and action_history >= 1 (the "
                             f"window is their minimum), got obs_history {self.obs_history}, "
                             f"action_history {self.action_history}")
        h = self.context_hidden
        if not (isinstance(h, tuple) and h and all(isinstance(x, int) and x > 0 for x in h)):
            raise ValueError(f"context_hidden: expected a non-empty tuple of positive ints, "
                             f"got {h!r}")
        t = self.time_inputs
        if (not isinstance(t, tuple) or any(x not in TIME_INPUTS for x in t)
                or len(set(t)) != len(t)):
            raise ValueError(f"time_inputs: expected a tuple of distinct names from "
                             f"{TIME_INPUTS}, got {t!r}")
        if self.termination == "predictive" and not self.markov:
            raise ValueError("termination: 'predictive' draws a next state from (s, a) alone; "
                             "with history inputs use 'rule', 'hazard' or 'both'")
        if self.termination in LEARNED and self.hazard_steps == 0:
            raise ValueError(f"hazard_steps: termination {self.termination!r} learns a hazard; "
                             f"expected an int >= 1, got 0")
        v = self.data_episode_length
        if v is not None and (not isinstance(v, int) or isinstance(v, bool) or v < 1):
            raise ValueError(f"data_episode_length: expected an int >= 1 or None, got {v!r}")
        self._check_rules()
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
        if self.adversarial and self.buffer_size < self.batch_size:
            raise ValueError(f"buffer_size: expected >= batch_size ({self.batch_size}), "
                             f"got {self.buffer_size}")
        return self

    def _check_rules(self) -> None:
        self._check_task_rules()
        self._check_physics_rules()

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
        if self.vd_every:
            raise ValueError(f"vd_every: a hybrid trains with the VD measurement off (0): it "
                             f"would roll the residual model alone; got {self.vd_every}")
        if self.reward != "task":
            raise ValueError(f"reward: a hybrid takes the task's reward_fn ('task'); a learned "
                             f"reward would be fitted to the residual, got {self.reward!r}")

    def _check_task_rules(self) -> None:
        """Without a registered task nothing gives simulated steps a reward or a termination
        rule: where rollouts run (vd_every > 0, or the adversarial methods' simulated envs),
        the reward must be learned and the termination the learned hazard."""
        if self.registered or not (self.vd_every or self.adversarial):
            return
        what = (f"task {self.task!r} is not registered" if self.task is not None
                else "the data names no task (meta.task null)")
        if self.reward != "learned":
            raise ValueError(f"reward: {self.reward!r} takes rewards from the registered "
                             f"task's reward_fn, and {what}; set reward='learned' (a head "
                             f"fitted on the data's rewards) or register the task "
                             f"(rl2s_jax.envs.tasks.register)")
        if self.termination not in LEARNED:
            raise ValueError(f"termination: {self.termination!r} ends episodes by the "
                             f"registered task's done_fn, and {what}; set "
                             f"termination='hazard' (learned from the data's done flags) or "
                             f"register the task")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"config: unknown field(s) {unknown}")
        d = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        return cls(**d)

    @classmethod
    def from_saved(cls, d: dict) -> TrainConfig:
        """A config read back from a checkpoint: the fields it predates take the values its
        run had (``SAVED_BEFORE``), not today's defaults."""
        return cls.from_dict({**SAVED_BEFORE, **d})
