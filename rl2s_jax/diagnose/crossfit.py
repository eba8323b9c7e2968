"""The fits behind the cause tests: cross-fitted ridge over episode folds, random features,
nearest-neighbour distances, Gaussian NLL, per-episode sums, variances from predicted log
errors (NumPy). The tests on their results (sign flips, rank sums) are ``rl2s_jax.stats``'."""

from __future__ import annotations

import math

import numpy as np

from rl2s_jax.data.episodes import Episodes


def _standardize_cols(x: np.ndarray) -> np.ndarray:
    sd = x.std(0)
    return (x - x.mean(0)) / np.where(sd > 1e-12, sd, 1.0)


def _random_features(x: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Random Fourier features [len(x), n] of standardised inputs x: lets the linear tests
    absorb smooth nonlinear misfit of the current (s, a), so it is not mistaken for a cause."""
    rng = np.random.default_rng(seed)
    w = rng.normal(0.0, 1.0 / math.sqrt(x.shape[1]), (x.shape[1], n))
    b = rng.uniform(0, 2 * np.pi, n)
    return math.sqrt(2.0 / n) * np.cos(x @ w + b)


def knn_distance(query: np.ndarray, ref: np.ndarray, k: int = 10, chunk: int = 2048
                 ) -> np.ndarray:
    """Mean Euclidean distance [len(query)] from each query row to its k nearest ref rows."""
    ref_sq = (ref ** 2).sum(1)
    out = np.empty(query.shape[0])
    for i in range(0, query.shape[0], chunk):
        q = query[i:i + chunk]
        d2 = np.maximum((q ** 2).sum(1)[:, None] - 2 * q @ ref.T + ref_sq[None], 0.0)
        part = np.partition(d2, min(k, ref.shape[0] - 1), axis=1)[:, :k]
        out[i:i + chunk] = np.sqrt(part).mean(1)
    return out


def episode_folds(eps: Episodes, rows: np.ndarray, n_folds: int, seed: int) -> np.ndarray:
    """[n] fold index of each row; whole episodes per fold."""
    episodes = np.unique(eps.episode[rows])
    n_folds = min(n_folds, len(episodes))
    if n_folds < 2:
        raise ValueError("rows: expected held-out rows from at least 2 episodes")
    assign = np.random.default_rng(seed).permutation(len(episodes)) % n_folds
    lookup = np.zeros(eps.n_episodes, int)
    lookup[episodes] = assign
    return lookup[eps.episode[rows]]


def crossfit_ridge(x: np.ndarray, y: np.ndarray, folds: np.ndarray,
                   models: dict[str, np.ndarray], ridge: float = 1e-3) -> dict[str, np.ndarray]:
    """Cross-fitted ridge predictions of y [n, o] from column subsets of x [n, f].

    models: name -> column indices (an empty subset is the intercept-only model). Columns are
    standardised on each fold's training rows; the penalty is ridge * n_train on the
    standardised coefficients (the intercept is free). -> name -> held-out prediction [n, o].
    """
    out = {m: np.zeros_like(y) for m in models}
    for k in np.unique(folds):
        tr, te = folds != k, folds == k
        mu, sd = x[tr].mean(0), x[tr].std(0)
        sd = np.where(sd > 1e-12, sd, 1.0)
        xs_tr, xs_te = (x[tr] - mu) / sd, (x[te] - mu) / sd
        y_mu = y[tr].mean(0)
        gram, cross = xs_tr.T @ xs_tr, xs_tr.T @ (y[tr] - y_mu)
        n_tr = int(tr.sum())
        for name, cols in models.items():
            cols = np.asarray(cols, int)
            out[name][te] = y_mu
            if cols.size:
                w = np.linalg.solve(gram[np.ix_(cols, cols)] + ridge * n_tr * np.eye(cols.size),
                                    cross[cols])
                out[name][te] += xs_te[:, cols] @ w
    return out


def gaussian_nll(err: np.ndarray, var: np.ndarray) -> np.ndarray:
    """Per-row, per-dim Gaussian NLL [n, o] of errors with variances (both [n, o])."""
    return 0.5 * (np.log(2 * np.pi * var) + err ** 2 / var)


def episode_sums(values: np.ndarray, episode: np.ndarray) -> np.ndarray:
    """Sum of per-row values [n] per episode (in order of first appearance). -> [E']"""
    _, inverse = np.unique(episode, return_inverse=True)
    return np.bincount(inverse, weights=values)


def variance_from_log(pred: np.ndarray, log_u2: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Relative variances [n, o] from predicted log squared errors pred [n, o]: each
    prediction clipped to the range of its dim's log_u2 [n, o], exponentiated and rescaled
    per dim so that its mean is that of u2 [n, o].

    A linear log-variance model extrapolates: on a row with an extreme input (a velocity
    kicked by process noise, squared) it can predict a variance far beyond any error seen,
    and the rescaling would then shrink every other row's variance towards zero."""
    pred = np.clip(pred, log_u2.min(0), log_u2.max(0))
    v = np.exp(pred - pred.max(0))
    return v * (u2.mean(0) / v.mean(0))
