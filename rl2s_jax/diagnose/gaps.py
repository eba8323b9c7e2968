"""Show what a learned simulator gets wrong: error breakdowns and at-a-glance plots.

Input is held-out residuals that other modules produce; nothing here touches a model.

  resid [n, o]  normalised one-step residuals: delta / delta_std minus the model's predicted
                mean, i.e. in units of the data's delta std per obs dim;
  std [n, o]    the model's predicted std in the same units; z = resid / std.

:func:`error_breakdown` cuts the squared error by obs dim, policy, step within the episode and
region of state/action space (quantile bins of each variable), adds the open-loop k-step error
growth and per-policy value errors when given, and writes a few plain-English findings, each
backed by a number. ``gap_views.plot_gaps`` draws it (two PNGs), ``gap_views.gaps_markdown``
writes a report section. Pure NumPy + matplotlib (Agg); O(n (o + a)) work.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from rl2s_jax.data.episodes import Episodes

__all__ = ["error_breakdown", "jsonable"]

RESID_UNITS = "delta std units"
KSTEP_UNITS = "normalised obs units"
_MIN_REGION_ROWS = 10  # bins with fewer rows are reported but never named "worst"
_MAX_BARS = 25  # bar charts show at most this many dims / policies
_MAX_HEAT_VARS = 30  # the region heat-map shows at most this many variables
_REGION_DIMS = 8  # per-dim region hot spots are searched in the obs dims with the largest share
_NOTABLE = 1.25  # a ratio below this is called unremarkable in the findings


# ----------------------------------------------------------------------------- validation

def _as_float_2d(name: str, x, shape: tuple[int, int]) -> np.ndarray:
    try:
        arr = np.asarray(x, np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name}: expected a float array of shape [n, o] = {list(shape)}, "
                         f"got {type(x).__name__} ({e})") from None
    if arr.shape != shape:
        raise ValueError(f"{name}: expected shape [n, o] = {list(shape)} (n = len(rows), "
                         f"o = eps.obs_size), got {list(arr.shape)}")
    return arr


def _check_finite_rows(name: str, arr: np.ndarray, rows: np.ndarray) -> None:
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        d = int(np.flatnonzero(~np.isfinite(arr[i]))[0])
        raise ValueError(f"{name}: {int(bad.sum())} of {arr.shape[0]} rows hold NaN or inf "
                         f"(first: position {i}, dataset row {int(rows[i])}, dim {d}, value "
                         f"{arr[i, d]}); drop those rows from rows/resid/std first")


def _check_names(name: str, names, size: int) -> list[str] | None:
    if names is None:
        return None
    names = list(names)
    if len(names) != size or not all(isinstance(s, str) for s in names):
        raise ValueError(f"{name}: expected a list of {size} strings, got {len(names)} "
                         f"entries: {names[:5]!r}")
    return names


def _check_kstep(kstep) -> np.ndarray | None:
    if kstep is None:
        return None
    k = np.asarray(kstep, np.float64)
    if k.ndim == 1:
        k = k[None]
    if k.ndim != 2 or k.shape[1] < 1 or k.shape[0] < 1:
        raise ValueError(f"kstep: expected shape [K] or [S, K] (S seeds, K >= 1 rollout "
                         f"lengths), got {list(np.shape(kstep))}")
    if not np.isfinite(k).all() or (k < 0).any():
        raise ValueError("kstep: expected finite RMSE values >= 0, got "
                         f"{k[~np.isfinite(k) | (k < 0)][:3].tolist()}")
    return k


def _check_vd(vd) -> dict | None:
    if vd is None:
        return None
    if not isinstance(vd, dict) or not {"policy", "true", "sim"} <= set(vd):
        raise ValueError("vd: expected a dict with keys 'policy', 'true', 'sim' (one entry "
                         f"per policy), got {type(vd).__name__} with keys "
                         f"{sorted(vd) if isinstance(vd, dict) else '-'}")
    pol = list(vd["policy"])
    out = {"policy": pol}
    for key in ("true", "sim"):
        v = np.asarray(vd[key], np.float64)
        if v.shape != (len(pol),):
            raise ValueError(f"vd['{key}']: expected shape [P] = [{len(pol)}] (len of "
                             f"vd['policy']), got {list(v.shape)}")
        if not np.isfinite(v).all():
            raise ValueError(f"vd['{key}']: expected finite values, got NaN/inf at entries "
                             f"{np.flatnonzero(~np.isfinite(v))[:5].tolist()}")
        out[key] = v
    if not pol:
        raise ValueError("vd: expected at least one policy, got none")
    return out


# ----------------------------------------------------------------------------- helpers

def _f(x) -> float | None:
    """A JSON-able float (None for NaN/inf)."""
    x = float(x)
    return x if math.isfinite(x) else None


def jsonable(obj):
    """Recursively turn NumPy scalars/arrays into Python ones and non-finite floats into None."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, bool | np.bool_):
        return bool(obj)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        return _f(obj)
    return obj


def _rmse(sq_sum: np.ndarray, count: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, np.sqrt(sq_sum / np.maximum(count, 1)), np.nan)


def _quantile_bins(x: np.ndarray, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Equal-count bins of x: (edges [m + 1], index [n] in [0, m)); tied edges merged, so m may
    be below n_bins (a constant x gives one bin)."""
    edges = np.unique(np.quantile(x, np.linspace(0.0, 1.0, n_bins + 1)))
    if edges.size == 1:
        edges = np.array([edges[0], edges[0]])
    idx = np.searchsorted(edges[1:-1], x, side="right")
    return edges, idx


def _num(x: float | None) -> str:
    """A number for prose: 3 significant digits."""
    if x is None:
        return "n/a"
    return f"{x:.0f}" if 1e3 <= abs(x) < 1e6 else f"{x:.3g}"


def _pct(x: float) -> str:
    return f"{100 * x:.0f}%"


def _policy_key(p) -> str:
    return str(p.item() if isinstance(p, np.generic) else p)


# ----------------------------------------------------------------------------- breakdown

def error_breakdown(eps: Episodes, rows, resid, std, *, kstep=None, vd=None, n_bins: int = 5,
                    obs_names: Sequence[str] | None = None,
                    action_names: Sequence[str] | None = None,
                    policy_names: Sequence[str] | None = None) -> dict:
    """Break held-out one-step error down by obs dim, policy, step and region. -> JSON-able dict.

    eps: the Episodes view; rows [n]: held-out row indices into eps; resid [n, o]: normalised
    residuals (delta std units); std [n, o]: the model's predicted std (same units).
    kstep: open-loop RMSE at k = 1..K ([K], or [S, K] over S seeds -> mean and spread), in
    normalised obs units. vd: {"policy": [P] ids or names, "true": [P], "sim": [P]} values per
    policy (e.g. the test policies'; they need not appear in rows). n_bins: bins for the step
    and region breakdowns (equal-count, see the result's "binning" entries).
    obs_names [o] / action_names [a] / policy_names [eps.n_policies]: labels (policy_names
    also lets vd name policies by name rather than by id).

    Keys of the result: "units", "overall", "by_dim", "by_policy", "by_step", "by_region",
    "kstep" (None without kstep), "vd" (None without vd), "summary" (list of one-line findings).
    Raises ValueError naming the argument for bad shapes, NaN/inf, non-positive std.
    """
    # ---- checks, all before any work
    if not isinstance(eps, Episodes):
        raise ValueError(f"eps: expected an Episodes (diagnose.episodes.from_dataset), got "
                         f"{type(eps).__name__}")
    r = np.asarray(rows)
    if r.ndim != 1 or r.size == 0 or not np.issubdtype(r.dtype, np.integer):
        raise ValueError(f"rows: expected a non-empty 1-D integer array of row indices into "
                         f"eps, got dtype {r.dtype} shape {list(r.shape)}")
    if r.min() < 0 or r.max() >= eps.n:
        raise ValueError(f"rows: expected indices in [0, {eps.n}) (eps.n), got range "
                         f"[{int(r.min())}, {int(r.max())}]")
    rows = r.astype(np.int64)
    n, o, a = rows.size, eps.obs_size, eps.action_size
    resid = _as_float_2d("resid", resid, (n, o))
    std = _as_float_2d("std", std, (n, o))
    if not isinstance(n_bins, int | np.integer) or isinstance(n_bins, bool) or n_bins < 1:
        raise ValueError(f"n_bins: expected a positive int, got {n_bins!r}")
    n_bins = int(n_bins)
    obs_names = _check_names("obs_names", obs_names, o)
    action_names = _check_names("action_names", action_names, a)
    policy_names = _check_names("policy_names", policy_names, eps.n_policies)
    kst = _check_kstep(kstep)
    vdc = _check_vd(vd)
    _check_finite_rows("resid", resid, rows)
    _check_finite_rows("std", std, rows)
    if (std <= 0).any():
        i, d = np.argwhere(std <= 0)[0]
        raise ValueError(f"std: expected predicted stds > 0, got {std[i, d]} at position {i} "
                         f"(dataset row {int(rows[i])}), dim {d}")

    def obs_label(d: int) -> str:
        return f"obs {d} ({obs_names[d]})" if obs_names else f"obs {d}"

    def act_label(d: int) -> str:
        return f"action {d} ({action_names[d]})" if action_names else f"action {d}"

    def pol_label(p: int) -> str:
        return f"policy {p} ({policy_names[p]})" if policy_names else f"policy {p}"

    # ---- overall and per dim
    sq = resid ** 2
    z2 = (resid / std) ** 2
    row_sq = sq.sum(axis=1)  # [n] squared error per row, summed over dims
    total_sq = float(row_sq.sum())
    overall_rmse = math.sqrt(total_sq / (n * o))
    dim_ms = sq.mean(axis=0)
    share = dim_ms / dim_ms.sum() if total_sq > 0 else np.full(o, 1.0 / o)
    by_dim = [{"dim": d, "name": obs_label(d), "rmse": math.sqrt(dim_ms[d]),
               "share": share[d], "mean_z2": z2[:, d].mean(), "bias": resid[:, d].mean(),
               "rms_std": math.sqrt((std[:, d] ** 2).mean())} for d in range(o)]
    overall = {"n_rows": n, "n_episodes": int(np.unique(eps.episode[rows]).size),
               "obs_size": o, "action_size": a, "rmse": overall_rmse,
               "mean_z2": float(z2.mean()), "rms_std": math.sqrt(float((std ** 2).mean()))}

    # ---- per policy (ranked by rmse, worst first)
    pol = eps.policy[rows]
    row_nll = 0.5 * z2.sum(axis=1) + np.log(std).sum(axis=1)
    vd_by_id: dict[int, int] = {}
    if vdc is not None:
        name_to_id = {s: i for i, s in enumerate(policy_names or [])}
        for j, p in enumerate(vdc["policy"]):
            if isinstance(p, int | np.integer) and not isinstance(p, bool):
                vd_by_id[int(p)] = j
            elif isinstance(p, str) and p in name_to_id:
                vd_by_id[name_to_id[p]] = j
            elif isinstance(p, str) and p.strip().isdigit():
                vd_by_id[int(p)] = j
    by_policy = []
    for p in np.unique(pol):
        m = pol == p
        ent = {"policy": int(p), "name": pol_label(int(p)), "n": int(m.sum()),
               "rmse": math.sqrt(row_sq[m].sum() / (m.sum() * o)),
               "share": row_sq[m].sum() / total_sq if total_sq > 0 else None,
               "mean_z2": z2[m].mean(), "nll": row_nll[m].mean()}
        if int(p) in vd_by_id:
            j = vd_by_id[int(p)]
            ent.update(true=vdc["true"][j], sim=vdc["sim"][j],
                       abs_vd=abs(vdc["sim"][j] - vdc["true"][j]))
        by_policy.append(ent)
    by_policy.sort(key=lambda e: -e["rmse"])

    # ---- per step within the episode (equal-count bins of t)
    t = eps.t[rows]
    t_edges, t_idx = _quantile_bins(t.astype(np.float64), n_bins)
    m_bins = t_edges.size - 1
    cnt = np.bincount(t_idx, minlength=m_bins)
    ssum = np.bincount(t_idx, weights=row_sq, minlength=m_bins)
    zsum = np.bincount(t_idx, weights=z2.sum(axis=1), minlength=m_bins)
    step_bins = []
    for b in np.flatnonzero(cnt):
        tb = t[t_idx == b]
        step_bins.append({"t_lo": int(tb.min()), "t_hi": int(tb.max()), "n": int(cnt[b]),
                          "rmse": math.sqrt(ssum[b] / (cnt[b] * o)),
                          "mean_z2": zsum[b] / (cnt[b] * o)})
    by_step = {"binning": "equal-count bins of t (step within episode); t_lo..t_hi inclusive",
               "edges": t_edges, "bins": step_bins}

    # ---- per region: quantile bins of every obs and action dim
    variables = []
    cands = []
    top_dims = [int(d) for d in np.argsort(-dim_ms, kind="stable")[:_REGION_DIMS]
                if dim_ms[d] > 0]
    dim_cands = []  # (ratio of dim d's rmse in the bin to its overall rmse, var, bin, d)
    # one product per variable: [bins, n] one-hot @ [n, 2 + dims] (count, row sq, dim sq)
    weights = np.column_stack([np.ones(n), row_sq, sq[:, top_dims]])
    for kind, x_all, label in (("obs", eps.obs, obs_label), ("action", eps.action, act_label)):
        xs = np.asfortranarray(x_all[rows])
        for d in range(xs.shape[1]):
            edges, idx = _quantile_bins(xs[:, d], n_bins)
            mb = edges.size - 1
            sums = (idx[None, :] == np.arange(mb)[:, None]).astype(np.float64) @ weights
            c = np.rint(sums[:, 0]).astype(np.int64)
            rm = _rmse(sums[:, 1], c * o)
            ratio = rm / overall_rmse if overall_rmse > 0 else np.full(mb, np.nan)
            vi = len(variables)
            variables.append({"kind": kind, "dim": d, "name": label(d), "edges": edges,
                              "n": c, "rmse": rm, "ratio": ratio})
            for b in np.flatnonzero(c >= _MIN_REGION_ROWS):
                if np.isfinite(ratio[b]):
                    cands.append((float(ratio[b]), vi, int(b)))
                dr = np.sqrt(sums[b, 2:] / c[b] / dim_ms[top_dims])
                dim_cands.extend((float(r), vi, int(b), dd)
                                 for r, dd in zip(dr, top_dims, strict=True))
    cands.sort(key=lambda c: -c[0])
    worst = []
    for ratio, vi, b in cands[:5]:
        v = variables[vi]
        x = (eps.obs if v["kind"] == "obs" else eps.action)[rows, v["dim"]]
        in_bin = _quantile_bins(x, n_bins)[1] == b
        dim_sq = sq[in_bin].sum(axis=0)
        top = int(np.argmax(dim_sq))
        worst.append({"variable": v["name"], "kind": v["kind"], "dim": v["dim"], "bin": b,
                      "n_bins": len(v["n"]), "lo": v["edges"][b], "hi": v["edges"][b + 1],
                      "rmse": v["rmse"][b], "ratio": ratio, "n_rows": int(v["n"][b]),
                      "top_dim": obs_label(top),
                      "top_dim_share": dim_sq[top] / dim_sq.sum() if dim_sq.sum() > 0 else None})
    dim_cands.sort(key=lambda c: -c[0])
    worst_dim = []
    for ratio, vi, b, dd in dim_cands[:5]:
        v = variables[vi]
        worst_dim.append({"variable": v["name"], "kind": v["kind"], "dim": v["dim"], "bin": b,
                          "n_bins": len(v["n"]), "lo": v["edges"][b], "hi": v["edges"][b + 1],
                          "n_rows": int(v["n"][b]), "error_dim": dd,
                          "error_dim_name": obs_label(dd), "ratio": ratio})
    by_region = {"binning": f"{n_bins} equal-count (quantile) bins of each obs/action variable "
                            "over the held-out rows; ratio = bin rmse / overall rmse",
                 "variables": variables, "worst": worst,
                 "worst_dim": worst_dim,
                 "worst_dim_note": f"per obs dim (the {len(top_dims)} with the largest share): "
                                   "ratio = that dim's rmse in the bin / its overall rmse"}

    # ---- k-step growth
    kstep_out = None
    if kst is not None:
        mean = kst.mean(axis=0)
        spread = kst.std(axis=0) if kst.shape[0] > 1 else None
        growth = mean[-1] / mean[0] if mean[0] > 0 else None
        double = np.flatnonzero(mean >= 2 * mean[0]) if mean[0] > 0 else np.array([])
        kstep_out = {"k": list(range(1, kst.shape[1] + 1)), "rmse": mean, "std": spread,
                     "n_seeds": kst.shape[0], "growth": growth,
                     "k_double": int(double[0]) + 1 if double.size else None,
                     "units": KSTEP_UNITS}

    # ---- value errors
    vd_out = None
    if vdc is not None:
        absvd = np.abs(vdc["sim"] - vdc["true"])
        vd_out = {"policy": [_policy_key(p) for p in vdc["policy"]], "true": vdc["true"],
                  "sim": vdc["sim"], "abs_vd": absvd, "mean_abs_vd": absvd.mean(),
                  "matched_in_rows": sorted(vd_by_id)}

    out = {"units": {"resid": RESID_UNITS, "kstep": KSTEP_UNITS,
                     "nll": "0.5 * sum_d z^2 + sum_d log std per row, mean over rows "
                            "(no log 2pi term)"},
           "overall": overall, "by_dim": by_dim, "by_policy": by_policy, "by_step": by_step,
           "by_region": by_region, "kstep": kstep_out, "vd": vd_out}
    out = jsonable(out)
    out["summary"] = _findings(out)
    return out


def _findings(b: dict) -> list[str]:
    """Plain-English one-line findings, each backed by a number of the breakdown."""
    lines = []
    ov = b["overall"]
    z2 = ov["mean_z2"]
    if z2 is not None:
        if z2 > 1.5:
            cal = f"over-confident: its std is ~{math.sqrt(z2):.2g}x too small"
        elif z2 < 0.67:
            cal = f"under-confident: its std is ~{1 / math.sqrt(z2):.2g}x too large"
        else:
            cal = "about calibrated (1 = the model's noise covers the error)"
        lines.append(f"held-out one-step rmse {_num(ov['rmse'])} ({RESID_UNITS}) over "
                     f"{ov['n_rows']} rows; mean z^2 {_num(z2)}, so the model is {cal}")

    dims = b["by_dim"]
    if len(dims) > 1:
        top = max(dims, key=lambda d: d["share"] or 0)
        lines.append(f"{top['name']} carries {_pct(top['share'])} of the squared error "
                     f"(rmse {_num(top['rmse'])}; an even split would be "
                     f"{_pct(1 / len(dims))} per dim)")
    bad_cal = [d for d in dims if d["mean_z2"] is not None
               and (d["mean_z2"] > 2 or d["mean_z2"] < 0.5)]
    if bad_cal and (z2 is None or 0.67 <= z2 <= 1.5 or len(bad_cal) < len(dims)):
        d = max(bad_cal, key=lambda d: abs(math.log(d["mean_z2"])))
        word = "over-confident" if d["mean_z2"] > 1 else "under-confident"
        lines.append(f"{d['name']} is the worst calibrated: mean z^2 {_num(d['mean_z2'])} "
                     f"({word}; 1 = calibrated)")
    biased = [d for d in dims if d["rmse"] and d["bias"] is not None
              and d["bias"] ** 2 > 0.25 * d["rmse"] ** 2 and d["share"] > 0.5 / len(dims)]
    if biased:
        d = max(biased, key=lambda d: d["bias"] ** 2 * d["share"] / d["rmse"] ** 2)
        lines.append(f"{d['name']} has a systematic bias {_num(d['bias'])} (bias^2 is "
                     f"{_pct(d['bias'] ** 2 / d['rmse'] ** 2)} of its mean squared error)")

    bins = [s for s in b["by_step"]["bins"] if s["rmse"] is not None]
    if len(bins) >= 2:
        rm = np.array([s["rmse"] for s in bins])
        hi, lo = bins[int(np.argmax(rm))], bins[int(np.argmin(rm))]
        ratio = hi["rmse"] / lo["rmse"] if lo["rmse"] > 0 else float("inf")
        steps = lambda s: f"steps {s['t_lo']}-{s['t_hi']}"
        diffs = np.diff(rm)
        if ratio < _NOTABLE:
            lines.append(f"error is flat over the episode: the worst step bin ({steps(hi)}) "
                         f"is {ratio:.2g}x the best ({steps(lo)})")
        else:
            if (diffs > 0).all() or (len(rm) > 2 and np.corrcoef(np.arange(len(rm)), rm)[0, 1]
                                      > 0.8):
                trend = "error rises with step in episode"
            elif (diffs < 0).all() or (len(rm) > 2 and np.corrcoef(np.arange(len(rm)), rm)[0, 1]
                                        < -0.8):
                trend = "error falls with step in episode"
            else:
                trend = "error varies with step in episode"
            lines.append(f"{trend}: rmse at {steps(hi)} is {ratio:.2g}x that at {steps(lo)} "
                         f"({_num(hi['rmse'])} vs {_num(lo['rmse'])})")

    def where(w: dict) -> str:
        pos = ("top" if w["bin"] == w["n_bins"] - 1 else "bottom" if w["bin"] == 0
               else f"#{w['bin'] + 1} of {w['n_bins']}")
        return (f"{w['variable']} in [{_num(w['lo'])}, {_num(w['hi'])}] ({pos} quantile bin, "
                f"{w['n_rows']} rows)")

    worst = b["by_region"]["worst"]
    if worst and worst[0]["ratio"] >= _NOTABLE:
        w = worst[0]
        lines.append(f"worst region: {where(w)} has rmse {w['ratio']:.2g}x overall, mostly in "
                     f"{w['top_dim']}")
    elif worst:
        w = worst[0]
        lines.append(f"no region of state/action space stands out in the total error: the "
                     f"worst quantile bin, {where(w)}, is {w['ratio']:.2g}x overall")
    wd = b["by_region"].get("worst_dim") or []
    if wd and wd[0]["ratio"] >= 1.5 and not (
            worst and worst[0]["ratio"] >= _NOTABLE and worst[0]["variable"] == wd[0]["variable"]
            and worst[0]["bin"] == wd[0]["bin"] and worst[0]["top_dim"] == wd[0]["error_dim_name"]):
        w = wd[0]
        lines.append(f"hot spot: {w['error_dim_name']} error is {w['ratio']:.2g}x its own "
                     f"average for {where(w)}")

    pols = b["by_policy"]
    if len(pols) >= 2:
        p0 = pols[0]
        med = float(np.median([p["rmse"] for p in pols[1:]]))
        if med > 0 and p0["rmse"] / med < _NOTABLE:
            lines.append(f"one-step error is similar across the {len(pols)} policies: the worst, "
                         f"{p0['name']}, is {p0['rmse'] / med:.2g}x the others' median "
                         f"{_num(med)}")
        else:
            lines.append(f"{p0['name']} has the largest one-step rmse {_num(p0['rmse'])} "
                         + (f"({p0['rmse'] / med:.2g}x the other policies' median {_num(med)})"
                            if med > 0 else "(the others have none)"))

    vd = b["vd"]
    if vd is not None:
        absvd = np.array(vd["abs_vd"])
        j = int(np.argmax(absvd))
        rest = np.delete(absvd, j)
        name = vd["policy"][j]
        name = f"policy {name}" if not name.startswith("policy") else name
        extra = f" (others median {_num(float(np.median(rest)))})" if rest.size else ""
        lines.append(f"{name} has the largest |VD| {_num(absvd[j])}{extra}; mean |VD| "
                     f"{_num(vd['mean_abs_vd'])} over {absvd.size} policies")

    ks = b["kstep"]
    if ks is not None and len(ks["k"]) >= 2 and ks["growth"] is not None:
        dbl = (f"; it doubles by k={ks['k_double']}" if ks["k_double"] else "")
        lines.append(f"k-step error grows {ks['growth']:.2g}x from k=1 to k={ks['k'][-1]} "
                     f"({_num(ks['rmse'][0])} -> {_num(ks['rmse'][-1])} {KSTEP_UNITS}){dbl}")
    return lines


# ----------------------------------------------------------------------------- plots


# ----------------------------------------------------------------------------- markdown

