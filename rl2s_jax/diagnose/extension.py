"""From a diagnosed cause to the model extension: the diagnosis model's spec (``ModelSpec``)
that diagnosis fits, and the ``rl2s train --set`` items that build the same extension into the
simulator users train (``train_set``; docs/DIAGNOSIS.md)."""
from __future__ import annotations

import dataclasses
import json
import shlex

from rl2s_jax.diagnose.causes import rivals
from rl2s_jax.diagnose.model import ModelSpec
from rl2s_jax.train.config import TrainConfig

__all__ = ["CONTEXT_WINDOW", "DEFAULT_TRAIN_STEPS", "EXTENSION_SHARE", "NOISE_NLL_BETA",
           "NOT_TRAINABLE", "extension_for", "train_command", "train_set"]

EXTENSION_SHARE = 0.25  # secondary causes join the extension above this share of the top score
CONTEXT_WINDOW = 4  # transitions the trained simulator's context is inferred from (at least)
NOISE_NLL_BETA = 0.5  # the noise extension's beta-NLL exponent. On the CPU Hopper noise
# recording (85k, held-out episodes, 2 seeds), NLL / MSE: base -9.4 / 0.045; state noise with
# beta 0: -15.3 / 0.099, beta 0.5: -17.0 / 0.036, beta 1: -11.5 / 0.034.


_SPEC_FIELDS = frozenset(f.name for f in dataclasses.fields(ModelSpec))


def extension_for(causes: dict, base: ModelSpec) -> tuple[ModelSpec, list[dict]]:
    """The extended spec for the diagnosed causes: the top cause's extension, plus that of
    every other significant cause scoring at least EXTENSION_SHARE of the top one; an
    extension the base model already has is skipped. -> (spec, [{"cause", "change"}]); the
    base spec and [] when the top cause is none (or nothing would change)."""
    if causes["top_cause"] == "none":
        return base, []
    ranked = [c for c in causes["causes"] if c["significant"] and c["name"] != "none"]
    ranked = [c for c in ranked if c["name"] in rivals(ranked[0]["name"])]
    top_score = ranked[0]["score"]
    spec, changes = base, []
    for c in ranked:
        if c["score"] < EXTENSION_SHARE * top_score:
            continue
        d = c["details"]
        if c["name"] == "actuation_delay":
            change = {"action_history": max(spec.action_history, int(d["lag"]))}
        elif c["name"] == "unobserved_state":
            change = {"obs_history": max(spec.obs_history, max(d["lags"] or [2]))}
        elif c["name"] == "hidden_episode_parameter":
            # inferred from the episode's recent transitions, as the trained simulator does;
            # the std must depend on the inputs: until the past shows the parameter (the
            # first steps) the prediction is uncertain (a global std on the two-mass
            # system: held-out NLL +1.6 nats worse than the base, with a state std -3.7)
            change = {"context_dim": max(spec.context_dim, 2),
                      "obs_history": max(spec.obs_history, CONTEXT_WINDOW),
                      "action_history": max(spec.action_history, CONTEXT_WINDOW),
                      "noise": "state", "nll_beta": max(spec.nll_beta, NOISE_NLL_BETA)}
        elif c["name"] == "stochastic_noise":
            # beta-NLL keeps the state-dependent std from buying likelihood with the mean
            # (plain NLL raised held-out MSE 2.3x on the Hopper noise variant; RESULTS.md)
            change = {"noise": "state", "nll_beta": max(spec.nll_beta, NOISE_NLL_BETA)}
        elif c["name"] == "time_drift":
            over = "order" if d["over"] == "episode_order" else "step"
            change = {"time_inputs": tuple(sorted(set(spec.time_inputs) | {over}))}
        elif c["name"] == "coverage_gap":
            change = {"policy_cvar_eps": 0.25}
        else:  # pragma: no cover - a cause without an extension
            continue
        # a change of how training weighs policies (coverage) is no input of the model:
        # recorded for `rl2s train`, not fitted here
        inputs = {k: v for k, v in change.items() if k in _SPEC_FIELDS}
        if inputs and all(getattr(spec, k) == v for k, v in inputs.items()):
            continue  # the model already has it
        if any(c2["change"] == change for c2 in changes):
            continue
        spec = dataclasses.replace(spec, **inputs)
        changes.append({"cause": c["name"],
                        "change": {k: list(v) if isinstance(v, tuple) else v
                                   for k, v in change.items()}})
    return spec.validate(), changes


# What `rl2s train --set` cannot build yet, and why (the report says so beside train_set).
NOT_TRAINABLE = {
    "policy_cvar_eps": "weighting the worst policies is what --method rl2s / rl2s-bc do "
                       "(their eps); no --set needed",
}


def train_set(changes: list[dict], base: TrainConfig | None = None
              ) -> tuple[list[str], list[dict], list[str]]:
    """The extension as ``rl2s train --set`` items (``KEY=VALUE``, TrainConfig fields by
    their dotted names, values in JSON) over ``base``, the config of the simulator being
    extended (default: TrainConfig's defaults, what `rl2s train` builds). An item ``base``
    already satisfies is not repeated: training's default members already have a
    state-dependent noise head and beta-NLL at beta 1, and lowering beta to diagnosis's 0.5
    raised the held-out MSE of Hopper's noise variant by a quarter (docs/DIAGNOSIS.md,
    "Planted effects through `rl2s train` and `rl2s evaluate`").
    -> (train_set, not_trainable [{"change", "why"}], already ["KEY=VALUE" of base])."""
    base = base or TrainConfig()
    dyn = base.dynamics
    want: dict = {}
    skipped: list[dict] = []

    def raise_to(k, v):  # a history input at least v
        want[f"dynamics.{k}"] = max(int(v), getattr(dyn, k), want.get(f"dynamics.{k}", 0))

    for c in changes:
        for k, v in c["change"].items():
            if k in ("action_history", "obs_history"):
                raise_to(k, v)
            elif k == "context_dim":  # inferred online from the recent transitions
                want["dynamics.context_dim"] = max(int(v), dyn.context_dim)
                for h in ("obs_history", "action_history"):
                    raise_to(h, CONTEXT_WINDOW)
            elif k == "noise":
                want["dynamics.noise"] = v
            elif k == "nll_beta":  # at least v
                want["nll_beta"] = max(float(v), base.nll_beta)
            elif k == "time_inputs":  # "order": rollouts run at the end of the recording
                want["dynamics.time_inputs"] = sorted(
                    set(dyn.time_inputs) | set(want.get("dynamics.time_inputs", ())) | set(v))
            else:
                skipped.append({"change": f"{k}={json.dumps(v)}",
                                "why": NOT_TRAINABLE.get(k, "no training field yet")})
    now = lambda k: getattr(dyn, k[len("dynamics."):]) if k.startswith("dynamics.") else getattr(
        base, k)
    has = lambda k, v: (sorted(now(k)) if k.endswith("time_inputs") else now(k)) == v
    items = [f"{k}={json.dumps(v)}" for k, v in want.items() if not has(k, v)]
    already = [f"{k}={json.dumps(v)}" for k, v in want.items() if has(k, v)]
    return items, skipped, already


#: train_steps of the printed `rl2s train` command when no diagnosed checkpoint gives its own.
DEFAULT_TRAIN_STEPS = 2000


def train_command(report: dict, data_path: str, out: str,
                  steps: int = DEFAULT_TRAIN_STEPS) -> str | None:
    """The `rl2s train` command that builds the extended simulator, runnable as printed
    (``steps``: its --steps, the diagnosed checkpoint's step where there is one), or None when
    there is nothing to build."""
    items = report["extension"].get("train_set") or []
    if not items:
        return None
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
    method = report["extension"].get("method", "rl2s")
    sets = " ".join(f"--set {shlex.quote(i)}" for i in items)
    return (f"rl2s train --data {shlex.quote(data_path)} --method {method} --steps {steps} "
            f"--out {shlex.quote(out)} {sets}")
