"""How well the likelihood model fits one task's dynamics: its one-step error on the rows it
trained on, on the held-out episodes of the same policies, and on the test policies' rows
(issue 10, item 2: underfitting, overfitting or a shift to other policies).

    python experiments/model_fit.py --task ant --variants bc,bc:gen_hidden=1024x4 \
        [--seeds 2] [--steps 600] [--eval-every 200] [--rows 65536] [--profile gpu] \
        [--transitions-per-policy N] [--value-episodes 1] [--out DIR] [--data-dir DIR]

Every variant is the MLE model (``bc``, or ``legacy-bc``) with its own config overrides as in
``ablation_model.py`` (``bc:key=value+key=value``; hidden sizes as ``gen_hidden=1024x4`` or
``gen_hidden=1024-512``, since commas separate the variants). The
seeds are vmapped lanes of one program; no value rollouts run (``vd_every`` 0), so a
variant costs its likelihood updates only.

The error is the elites' average prediction of the next state against the logged one, in
units of the data's one-step change std per dim (``Normalizer.delta_std``, the units of
``simulate.step_errors`` and the step-error controls), root mean square over dims and rows.
The logged next states are the real dynamics' (the oracle reproduces them to 0.002 of these
units, docs/RESULTS.md), so no oracle is needed. Writes ``model_fit_<task>_<variant>.json``
(curves per seed, the final per-dim error) and prints one table row per variant.
"""
from __future__ import annotations

import argparse
import os
import re
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax.app.training import make_config
from rl2s_jax.envs.tasks import task_names
from rl2s_jax.model import dynamics as dyn
from rl2s_jax.paper.ablation import VARIANTS, check_variants, parse_variant
from rl2s_jax.paper.protocol import load_or_collect, log, profile_sizes
from rl2s_jax.train.data import make_train_data
from rl2s_jax.train.lanes import train_lanes
from rl2s_jax.train.step import init
from rl2s_jax.zoo.zoo import policies_for

MLE_BASES = ("bc", "legacy-bc")
SIZES = {"gpu": dict(seeds=2, steps=600, eval_every=200, rows=65536),
         "cpu": dict(seeds=1, steps=60, eval_every=30, rows=2048)}


def hidden_sizes(text: str) -> tuple[int, ...]:
    """'1024x4' -> (1024,) * 4; '512-256' -> (512, 256)."""
    m = re.fullmatch(r"(\d+)x(\d+)", text)
    sizes = (int(m[1]),) * int(m[2]) if m else tuple(int(h) for h in text.split("-") if h)
    if not sizes or min(sizes) < 1:
        raise ValueError(f"gen_hidden: expected sizes like 1024x4 or 512-256, got {text!r}")
    return sizes


def parse_fit_variant(spec: str) -> tuple[str, dict]:
    """'bc:gen_hidden=1024x4+bc_lr=3e-4' -> ("bc", overrides); only the likelihood models."""
    base, _, extra = spec.partition(":")
    pairs = [kv for kv in extra.split("+") if kv]
    hidden = [kv for kv in pairs if kv.startswith("gen_hidden=")]
    rest = [kv for kv in pairs if not kv.startswith("gen_hidden=")]
    base, own = parse_variant(base + (":" + "+".join(rest) if rest else ""))
    if base not in MLE_BASES:
        raise SystemExit(f"variants: expected a likelihood model ({', '.join(MLE_BASES)}), got "
                         f"{spec!r}")
    for kv in hidden:
        try:
            own["gen_hidden"] = hidden_sizes(kv.partition("=")[2])
        except ValueError as e:
            raise SystemExit(f"variants: {spec!r}: {e}") from None
    return base, own


def logged_rows(obs, action, next_obs, n: int, seed: int) -> tuple:
    """At most n rows, drawn without replacement (all of them when there are fewer)."""
    size = int(np.asarray(obs).shape[0])
    idx = np.sort(np.random.default_rng(seed).choice(size, min(n, size), replace=False))
    return tuple(jnp.asarray(np.asarray(x)[idx], jnp.float32) for x in (obs, action, next_obs))


def step_error(gen, rank, norm, n_elites: int, obs, action, next_obs) -> dict:
    """One lane's elites on rows [N, ...]: the root-mean-square error of the elites' average
    mean (``rmse``) and the mean over the elites of each one's own (``member_rmse``), in units
    of the one-step change std, and the former per dim (``rmse_per_dim`` [o])."""
    y = norm.norm_delta(obs, next_obs)                                   # [N, o]
    means, _ = dyn.ensemble_dist(gen, dyn.markov_inputs(norm, obs, action))  # [E, N, o]
    elite = dyn.elite_mask(rank, n_elites, means.shape[0]).astype(jnp.float32)  # [E]
    avg = jnp.einsum("e,eno->no", elite, means) / elite.sum()
    member = jnp.sqrt(((means - y) ** 2).mean((1, 2)))                   # [E]
    per_dim = ((avg - y) ** 2).mean(0)                                   # [o]
    return {"rmse": jnp.sqrt(per_dim.mean()),
            "member_rmse": (member * elite).sum() / elite.sum(),
            "rmse_per_dim": jnp.sqrt(per_dim)}


def run_variant(spec: str, args, sizes: dict, train_ds, test_ds) -> dict:
    base, own = parse_fit_variant(spec)
    method, model = VARIANTS[base]
    cfg = make_config(train_ds, method, args.profile, overrides={**model, "vd_every": 0,
                                                                   **own})
    res = {"task": args.task, "variant": spec, "config": cfg.to_dict(), "sizes": sizes,
           "hardware": jax.devices()[0].device_kind, "jax_version": jax.__version__,
           "command": " ".join(["python", "experiments/model_fit.py", *args.argv])}
    return fit_and_measure(cfg, train_ds, test_ds, sizes, res, label=spec,
                           write=lambda r: _write(args.out, args.task, spec, r))


def fit_and_measure(cfg, train_ds, test_ds, sizes: dict, res: dict, *, label: str = "",
                    write=lambda r: None, policies=None) -> dict:
    """Fit ``cfg``'s likelihood model on train_ds (``sizes``: seeds, steps, eval_every, rows)
    and measure its step error on the three sets at every eval_every steps; ``res`` gets
    "rows", "curves" (per point: step, per set {rmse, member_rmse} [seeds], stopped members
    and held-out NLL), "rmse_per_dim" (the last point's, per set [seeds][o]) and timings.
    ``policies``: train_ds's stacked policies (None: from its zoo, ``policies_for``)."""
    data = make_train_data(train_ds, policies_for(train_ds) if policies is None else policies,
                           cfg)
    sets = {"train": logged_rows(data.obs, data.action, data.next_obs, sizes["rows"], 1),
            "heldout": (data.val_obs, data.val_action, data.val_next_obs),
            "test": logged_rows(test_ds.obs, test_ds.action, test_ds.next_obs, sizes["rows"],
                                2)}
    seeds = list(range(sizes["seeds"]))
    measure = jax.jit(jax.vmap(lambda s, rows: step_error(s.gen, s.rank, s.norm, cfg.n_elites,
                                                          *rows), in_axes=(0, None)))
    res.update(rows={k: int(v[0].shape[0]) for k, v in sets.items()}, curves=[],
               complete=False)
    t0 = time.perf_counter()
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    states = jax.block_until_ready(jax.jit(jax.vmap(lambda k, d: init(k, cfg, d),
                                                    in_axes=(0, None)))(keys, data))
    compiled, t_train = {}, 0.0
    for _ in range(sizes["steps"] // sizes["eval_every"]):
        t1 = time.perf_counter()
        states, m = jax.block_until_ready(train_lanes(states, data, sizes["eval_every"], cfg,
                                                      compiled))
        t_train += time.perf_counter() - t1
        point = {"step": int(states.step[0]), "finite": np.asarray(m["finite"]).tolist(),
                 "stopped": np.asarray(states.stopped).sum(1).tolist(),
                 "heldout_nll": np.round(np.asarray(states.heldout_nll), 3).tolist()}
        per_dim = {}
        for name, rows in sets.items():
            if rows[0].shape[0] == 0:
                continue
            e = measure(states, rows)
            point[name] = {k: np.round(np.asarray(e[k], np.float64), 4).tolist()
                           for k in ("rmse", "member_rmse")}
            per_dim[name] = np.round(np.asarray(e["rmse_per_dim"], np.float64), 4).tolist()
        res["curves"].append(point)
        res["rmse_per_dim"] = per_dim
        res["train_seconds"] = round(t_train, 1)
        log(f"[model_fit] {label} step {point['step']}: rmse "
            + " ".join(f"{k} {point[k]['rmse']}" for k in sets if k in point)
            + f"; stopped members {point['stopped']}; {t_train:.0f}s of training")
        write(res)
    res["seconds_total"] = round(time.perf_counter() - t0, 1)
    res["complete"] = True
    write(res)
    return res


def _write(out: str, task: str, spec: str, res: dict) -> None:
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", spec)
    path = os.path.join(out, f"model_fit_{task}_{safe}.json")
    write_json(path, res)


def table(results: list[dict]) -> str:
    """One markdown row per variant: the final error on each set, mean (min-max) over seeds."""
    lines = ["| variant | train rmse | held-out rmse | test rmse | member rmse (test) | "
             "stopped members | training s |", "|---|---|---|---|---|---|---:|"]

    def cell(last, name, k="rmse"):
        if name not in last:
            return "-"
        v = last[name][k]
        return f"{np.mean(v):.3f} ({min(v):.3f}-{max(v):.3f})" if len(v) > 1 else f"{v[0]:.3f}"

    for r in results:
        last = r["curves"][-1]
        lines.append(f"| {r['variant']} | {cell(last, 'train')} | {cell(last, 'heldout')} | "
                     f"{cell(last, 'test')} | {cell(last, 'test', 'member_rmse')} | "
                     f"{last['stopped']} | {r['train_seconds']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", required=True, choices=task_names())
    ap.add_argument("--variants", default="bc")
    ap.add_argument("--profile", default="auto", choices=("auto", "cpu", "gpu"))
    ap.add_argument("--seeds", type=int)
    ap.add_argument("--steps", type=int)
    ap.add_argument("--eval-every", type=int)
    ap.add_argument("--rows", type=int)
    ap.add_argument("--transitions-per-policy", type=int)
    ap.add_argument("--value-episodes", type=int, default=1,
                    help="truth episodes per policy in the collection (the fit needs none; "
                         "give the ablation's number to share its data directory)")
    ap.add_argument("--out", default="model_fit_out")
    ap.add_argument("--data-dir")
    args = ap.parse_args(argv)
    args.argv = argv
    variants = check_variants(args.task, args.variants, parse_fit_variant)
    if args.profile == "auto":
        args.profile = "gpu" if jax.default_backend() == "gpu" else "cpu"
    sizes = dict(SIZES[args.profile])
    for k in sizes:
        if getattr(args, k, None) is not None:
            sizes[k] = getattr(args, k)
        if not isinstance(sizes[k], int) or sizes[k] < 1:
            raise SystemExit(f"{k.replace('_', '-')}: expected an int >= 1, got {sizes[k]}")
    if sizes["steps"] % sizes["eval_every"]:
        raise SystemExit(f"steps: expected a multiple of --eval-every ({sizes['eval_every']})")
    data_sizes = {"transitions_per_policy": profile_sizes(args.profile, args.task)[
        "transitions_per_policy"], "value_episodes": args.value_episodes}
    if args.transitions_per_policy is not None:
        data_sizes["transitions_per_policy"] = args.transitions_per_policy
    for k, v in data_sizes.items():
        if not isinstance(v, int) or v < 1:
            raise SystemExit(f"{k.replace('_', '-')}: expected an int >= 1, got {v}")
    os.makedirs(args.out, exist_ok=True)
    t0 = time.perf_counter()
    datasets, reused = load_or_collect(args.task, data_sizes, args.data_dir or args.out, 0,
                                       None, False)
    log(f"[model_fit] {args.task} on {jax.devices()[0].device_kind}, sizes {sizes}, data "
        f"{data_sizes} ({'reused' if reused else 'collected'} in "
        f"{time.perf_counter() - t0:.0f}s)")
    results = []
    for v in variants:
        results.append(run_variant(v, args, sizes, datasets["train"], datasets["test"]))
    text = table(results)
    with open(os.path.join(args.out, f"model_fit_{args.task}.md"), "a") as f:
        f.write(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
