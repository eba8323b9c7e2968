"""Does a policy file hold the policies that collected a Dataset? The logged actions'
log-likelihood under each policy of the file, policy by policy.

A file of the right shape but the wrong policies (another zoo's, or the right ones in another
order) passes every shape check and makes every value error meaningless. The logged actions
tell: the rows policy p collected should be explained best by policy p. This is a warning, not
an error: a stochastic policy's rows are also likely under a similar policy, and clipped or
otherwise altered actions lower every likelihood alike.

An action at the edge of the box (|a| > 1 - EDGE: tanh saturates there in float32, so a policy
pushing hard logs exactly +-1) is scored as censored: the probability that the pre-tanh action
lies beyond atanh(1 - EDGE) on that side, not a density at a point it cannot resolve.
"""
from __future__ import annotations

import warnings
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.data.dataset import spread_rows
from rl2s_jax.policy.policy import Params, policy_dist, tanh_log_det

MAX_ROWS = 20_000  # logged rows scored (evenly spread over the data)
EDGE = 1e-5  # |action| above 1 - EDGE: at the box's edge (censored)
SHARE = 0.1  # warn when the policies not explained best by their own hold more of the rows


class PolicyFileWarning(UserWarning):
    """A policy file whose policies do not explain the actions of the data they claim."""


@jax.jit
def _log_likelihoods(params: Params, obs: jax.Array, action: jax.Array
                     ) -> tuple[jax.Array, jax.Array]:
    """log pi_k(action | obs) of every row under every policy k: [K, n] (the density of the
    squashed action, as ``policy.sample_action`` draws it, in the dims inside the box; the
    censored probability in the dims at its edge), and the same of a uniform action in the
    box: [n]."""
    edge = jnp.abs(action) > 1.0 - EDGE  # [n, a]
    side = jnp.sign(action)
    raw = jnp.arctanh(jnp.clip(action, -1.0 + EDGE, 1.0 - EDGE))

    def one(p):
        loc, scale = policy_dist(p, obs)
        z = (raw - loc) / scale
        inside = -0.5 * z**2 - jnp.log(scale) - 0.5 * jnp.log(2 * jnp.pi) - tanh_log_det(
            raw[..., None])
        beyond = jax.scipy.stats.norm.logcdf(-side * z)  # P(raw past the edge, that side)
        return jnp.sum(jnp.where(edge, beyond, inside), -1)

    uniform = jnp.sum(jnp.where(edge, jnp.log(EDGE / 2), -jnp.log(2.0)), -1)
    return jax.vmap(one)(params), uniform


def policy_log_likelihoods(ds, params: Params, max_rows: int = MAX_ROWS) -> dict:
    """The mean log-likelihood of each policy's logged actions under each policy of ``params``.

    ds: a Dataset of P policies; params: stacked [K, ...] policies (a policy file's, K = P
    when it claims the data). Up to ``max_rows`` rows, evenly spread. -> {"loglik": [P, K]
    (row p: the rows policy_id p logged; NaN where it logged none), "uniform": [P] the same of
    a uniform action in the box [-1, 1]^a (a reference no policy should fall below), "rows":
    [P] rows scored per policy}; edge actions are censored (module docstring)."""
    rows = spread_rows(ds.n_transitions, max_rows)
    obs = jnp.asarray(np.asarray(ds.obs, np.float32)[rows])
    action = jnp.asarray(np.asarray(ds.action, np.float32)[rows])
    ll, uniform = (np.asarray(x, np.float64) for x in _log_likelihoods(params, obs, action))
    pid = np.asarray(ds.policy_id)[rows]
    counts = np.bincount(pid, minlength=ds.n_policies)
    sums = np.stack([np.bincount(pid, weights=w, minlength=ds.n_policies)
                     for w in (*ll, uniform)], axis=1)  # [P, K + 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], np.nan)
    return {"loglik": means[:, :-1], "uniform": means[:, -1], "rows": counts}


def policy_file_mismatch(ds, params: Params, names: Sequence[str] | None = None,
                         share: float = SHARE, max_rows: int = MAX_ROWS) -> str | None:
    """One line naming the policies of a file that do not explain the data they claim, or None.

    Policy p is contradicted where another policy of the file, or a uniform action (the
    reference, which also serves a file of one policy), explains p's logged actions better on
    average (``policy_log_likelihoods``). The line comes when the contradicted policies logged
    more than ``share`` of the scored rows."""
    r = policy_log_likelihoods(ds, params, max_rows)
    ll, rows = r["loglik"], r["rows"]
    P = ll.shape[0]
    names = [str(x) for x in (names if names is not None else range(P))]
    own = ll[np.arange(P), np.arange(P)]
    others = np.where(np.eye(P, dtype=bool), -np.inf, ll)
    best_other = others.argmax(1)
    beaten = np.maximum(others.max(1), r["uniform"]) > own  # NaN rows (none logged): False
    bad = [p for p in range(P) if rows[p] > 0 and beaten[p]]
    if rows.sum() == 0 or rows[bad].sum() <= share * rows.sum():
        return None

    def why(p):
        if P > 1 and others[p, best_other[p]] >= r["uniform"][p]:
            return f"{names[p]} (better explained by {names[best_other[p]]})"
        return f"{names[p]} (worse than a uniform random action)"
    shown = ", ".join(why(p) for p in bad[:5]) + (f" and {len(bad) - 5} more" if len(bad) > 5
                                                    else "")
    return (f"{len(bad)} of {P} policies do not explain the actions they claim to have logged "
            f"({rows[bad].sum() / rows.sum():.0%} of the rows): {shown}; is this the data's "
            f"policy file, in its policy_id order?")


def warn_if_mismatched(ds, params: Params, label: str, path: str,
                       names: Sequence[str] | None = None) -> None:
    """``policy_file_mismatch`` as a PolicyFileWarning starting with ``label`` and ``path``."""
    line = policy_file_mismatch(ds, params, names)
    if line:
        warnings.warn(f"{label}: {path}: {line}", PolicyFileWarning, stacklevel=2)


__all__ = ["PolicyFileWarning", "policy_file_mismatch", "policy_log_likelihoods",
           "warn_if_mismatched"]
