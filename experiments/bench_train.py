"""train_step throughput, measured side by side in one run (`make bench`).

For a Hopper-shaped problem (obs 12, action 3, the zoo's 64x64 policies) at a given config
(default: paper sizes on a GPU, the small CPU config elsewhere):
  - updates/s (generator updates of the whole ensemble; in an adversarial step each comes with
    ``disc_updates`` critic updates) and simulated transitions/s (training rollouts + the
    spread-out VD rollouts);
  - how the time of one step grows with the number of training policies P and with the
    rollout length (vd_horizon, sim_steps);
  - the step's matmul FLOPs (counted from the layer sizes) and the achieved fraction of this
    device's measured dense matmul rate (a large float32 matmul at JAX's default precision).

The data are random rows of the right shapes: the step's cost does not depend on their values
(every array shape is fixed; terminations only mask).

    python experiments/bench_train.py [--profile auto|cpu|gpu] [--method rl2s|bc]
        [--policies 4 17 64 256] [--horizons 250 1000 4000] [--sim-steps 16 64]
        [--matmul-dtype float32,bfloat16] [--json out.json]

``--method rl2s`` times the adversarial (WGAIL + CVaR) step: pre-training and the critic
warm-up are switched off, else the timed steps would be the MLE pre-training ones.
``--method bc`` times the ensemble's likelihood step (what BC, RL2S-BC and the pre-training
run).
``--matmul-dtype float32,bfloat16`` times every row under each
``TrainConfig.dynamics.matmul_dtype``, one after the other in the same process (issue 40
item 3: bf16 matmuls); the FLOP rate stays the float32 matmul's.

The race with the official loop (issue 40 item 4; its torch port is
../shared/tools/official_port/official_loop.py, run beside this by ``device.sh race``):
``--official-sizes`` times our step at the official loop's sizes (OFFICIAL_SIZES: one 4x512
ReLU generator, batch 256, no NLL anchor, no held-out scoring; 5 critic updates per generator
update as our default); ``--breakdown`` adds rows at P=17 that each take one part away (no VD,
one simulated step, one critic update per generator update, one generator update per step),
so that the differences say where a step's time goes; ``--official-dir DIR`` reads the port's
``official_p<P>.json`` lines from DIR and writes each P's ratios (``race`` in the JSON).
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import re
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from bench import timed  # experiments/bench.py: best of `repeats` after a compile call

from rl2s_jax._files import write_json
from rl2s_jax.app.training import parse_overrides
from rl2s_jax.model.dynamics import Normalizer
from rl2s_jax.policy.policy import init_policy, stack_params
from rl2s_jax.train.config import TrainConfig
from rl2s_jax.train.data import TrainData
from rl2s_jax.train.step import init, train_steps

OBS, ACT, POLICY_HIDDEN = 12, 3, (64, 64)
# The official RL2S loop's model and updates (exp_specs/l2s_hopper.yaml): one generator of
# 4x512 ReLU, batch 256, no NLL anchor, held-out scoring or early stop (the critic 4x512, 5
# updates per generator update, as ours).
OFFICIAL_SIZES = {"ensemble_size": 1, "n_elites": 1, "batch_size": 256,
                  "dynamics.activation": "relu", "adversarial.nll_weight": 0.0,
                  "holdout_frac": 0.0, "early_stop_patience": 0}


def breakdown_configs(cfg: TrainConfig) -> list[tuple[str, TrainConfig]]:
    """(part taken away, config) rows for ``--breakdown``: each row's time subtracted from the
    full step's is that part's share. No VD needs eps 1 (no worst policies to choose)."""
    return [("no VD", cfg.override({"vd.every": 0, "eps": 1.0})),
            ("1 sim step", cfg.override({"adversarial.sim_steps": 1})),
            ("1 critic update", cfg.override({"adversarial.disc_updates": 1})),
            ("1 gen update", cfg.override({"updates_per_step": 1}))]


def race_ratios(rows: list[dict], official: dict[int, dict], horizon: int) -> list[dict]:
    """Our rows against the official port's output per P (``official_loop.py``'s JSON line:
    cycle_s, generator_updates_per_s, sim_transitions_per_s). A cycle is 1000 generator
    updates with their critic updates and their share of VD. -> one dict per (P, vmapped
    runs) of the full-step rows at the VD ``horizon`` (no breakdown or horizon row) whose P
    the port measured."""
    out = []
    for r in rows:
        o = official.get(r["policies"])
        if o is None or r.get("variant", "full") != "full" or r["vd_horizon"] != horizon:
            continue
        ours_cycle = 1000 / r["gen_updates_per_s"]
        out.append({"policies": r["policies"], "vmapped_runs": r["vmapped_runs"],
                    "matmul_dtype": r.get("matmul_dtype", "float32"),
                    "official_cycle_s": o["cycle_s"], "ours_cycle_s": ours_cycle,
                    "cycle_ratio": o["cycle_s"] / ours_cycle,
                    "gen_update_ratio": r["gen_updates_per_s"] / o["generator_updates_per_s"],
                    "sim_ratio": r["sim_transitions_per_s"] / o["sim_transitions_per_s"]})
    return out


def read_official(directory: str) -> dict[int, dict]:
    """official_p<P>.json files of DIR (the port's last JSON line each) -> {P: dict}."""
    found = {}
    for path in sorted(glob.glob(os.path.join(directory, "official_p*.json"))):
        m = re.fullmatch(r"official_p(\d+)\.json", os.path.basename(path))
        lines = [x for x in open(path).read().splitlines() if x.strip().startswith("{")]
        if m and lines:
            found[int(m.group(1))] = json.loads(lines[-1])
    if not found:
        raise SystemExit(f"official-dir: expected official_p<P>.json files with the port's JSON "
                         f"line in {directory}, found none")
    return found


def fake_data(n_policies: int, rows_per_policy: int = 2000, seed: int = 0,
              heldout_rows: int = 0) -> TrainData:
    """Random rows of Hopper's shapes; ``heldout_rows`` of them also serve as the held-out rows
    the members are scored on (what the step computes depends on their number only)."""
    rng = np.random.default_rng(seed)
    n = n_policies * rows_per_policy
    obs = rng.normal(size=(n, OBS)).astype(np.float32)
    obs[:, 1] = 1.25  # hopper's height: healthy, so simulated episodes are not cut at once
    act = np.tanh(rng.normal(size=(n, ACT))).astype(np.float32)
    nxt = (obs + 0.05 * rng.normal(size=(n, OBS))).astype(np.float32)
    keys = jax.random.split(jax.random.PRNGKey(seed), n_policies)
    pols = stack_params([init_policy(k, OBS, ACT, POLICY_HIDDEN) for k in keys])
    return TrainData(obs=jnp.asarray(obs), action=jnp.asarray(act), next_obs=jnp.asarray(nxt),
                     policy_start=jnp.arange(n_policies, dtype=jnp.int32) * rows_per_policy,
                     policy_count=jnp.full((n_policies,), rows_per_policy, jnp.int32),
                     start_pool=jnp.asarray(obs[:512]),
                     true_value=jnp.zeros((n_policies,), jnp.float32), policies=pols,
                     norm=Normalizer.from_data(obs, act, nxt),
                     val_obs=jnp.asarray(obs[:heldout_rows]),
                     val_action=jnp.asarray(act[:heldout_rows]),
                     val_next_obs=jnp.asarray(nxt[:heldout_rows]))


def mlp_flops(sizes) -> int:
    """Forward matmul FLOPs of one row through layers ``sizes`` (2 * in * out per layer)."""
    return sum(2 * a * b for a, b in zip(sizes[:-1], sizes[1:], strict=True))


def step_flops(cfg: TrainConfig, P: int, heldout_rows: int = 0) -> dict:
    """Matmul FLOPs of one train_step (backward = 2x forward) of cfg.method with its ensemble
    of E members: an adversarial step (critic updates, each drawing fake next states from all
    members; every member's WGAIL loss, plus its NLL on the real batch when adv_nll_weight > 0)
    or a likelihood step (every member's loss on its own batch); then the held-out scoring of
    the members and the rollouts (every member is evaluated at each simulated step)."""
    E = cfg.ensemble_size
    gen = mlp_flops([OBS + ACT, *cfg.dynamics.hidden, 2 * OBS])
    disc = mlp_flops([2 * OBS + ACT, *cfg.adversarial.disc_hidden, 1])
    pol = mlp_flops([OBS, *POLICY_HIDDEN, 2 * ACT])
    n = cfg.batch_size
    if cfg.is_adversarial:
        critic = E * gen * n + 3 * disc * 2 * n            # fake s' + D fwd/bwd on real+fake
        member = 3 * gen * 2 * n + 3 * disc * 2 * n        # through G and D, real+sim (s, a)
        if cfg.adversarial.nll_weight:
            member += 3 * gen * n                          # the NLL anchor on the real batch
        updates = cfg.updates_per_step * (cfg.adversarial.disc_updates * critic + E * member)
        sim_rows = cfg.adversarial.sim_envs * cfg.adversarial.sim_steps
    else:
        updates = cfg.updates_per_step * E * 3 * gen * n
        sim_rows = 0
    scoring = E * gen * heldout_rows
    vd_rows = P * cfg.vd.episodes * -(-cfg.vd.horizon // cfg.vd.every) if cfg.vd.every else 0
    rollouts = (sim_rows + vd_rows) * (E * gen + pol)
    return {"updates": updates, "scoring": scoring, "rollouts": rollouts,
            "total": updates + scoring + rollouts, "sim_rows": sim_rows, "vd_rows": vd_rows}


def matmul_rate(n: int) -> float:
    """Measured float32 matmul FLOP/s at JAX's default precision (n x n @ n x n)."""
    a = jax.random.normal(jax.random.PRNGKey(0), (n, n), jnp.float32)
    f = jax.jit(lambda a: a @ a)
    return 2 * n**3 / timed(f, a, repeats=5)


def step_program(cfg: TrainConfig, P: int, steps: int, runs: int = 1):
    """The jitted call of ``steps`` train_steps on fake_data(P) and its start state: one
    run plain, ``runs`` > 1 seeds vmapped (a vmap of one lane is another, slower program).
    -> (run, state)."""
    heldout = cfg.holdout_rows if cfg.holdout_frac else 0
    data = fake_data(P, heldout_rows=heldout)
    if runs == 1:
        state = jax.jit(init, static_argnums=1)(jax.random.PRNGKey(0), cfg, data)
        return jax.jit(lambda s: train_steps(s, data, steps)[0]), state
    keys = jax.random.split(jax.random.PRNGKey(0), runs)
    state = jax.jit(jax.vmap(lambda k: init(k, cfg, data)))(keys)
    return jax.jit(jax.vmap(lambda s: train_steps(s, data, steps)[0])), state


def bench(cfg: TrainConfig, P: int, steps: int, runs: int = 1) -> dict:
    """Time ``steps`` train_steps; ``runs`` > 1 vmaps that many seeds as one program and
    reports their summed throughput."""
    heldout = cfg.holdout_rows if cfg.holdout_frac else 0
    run, state = step_program(cfg, P, steps, runs)
    t0 = time.perf_counter()
    jax.block_until_ready(run(state))
    compile_s = time.perf_counter() - t0
    seconds = timed(run, state) / steps / runs  # per train_step of one run
    fl = step_flops(cfg, P, heldout)
    return {"method": cfg.method, "ensemble_size": cfg.ensemble_size, "policies": P,
            "vd_horizon": cfg.vd.horizon, "sim_steps": cfg.adversarial.sim_steps,
            "vmapped_runs": runs,
            "step_ms": 1e3 * seconds, "steps_per_s": 1 / seconds,
            "gen_updates_per_s": cfg.updates_per_step / seconds,
            "member_updates_per_s": cfg.updates_per_step * cfg.ensemble_size / seconds,
            "disc_updates_per_s": (cfg.updates_per_step * cfg.adversarial.disc_updates / seconds
                                   if cfg.is_adversarial else 0.0),
            "sim_transitions_per_s": (fl["sim_rows"] + fl["vd_rows"]) / seconds,
            "gflop_per_step": fl["total"] / 1e9, "tflop_s": fl["total"] / seconds / 1e12,
            "compile_s": compile_s}


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--profile", choices=("auto", "cpu", "gpu"), default="auto")
    ap.add_argument("--method", choices=("rl2s", "bc"), default="rl2s",
                    help="rl2s: the adversarial step; bc: the ensemble's likelihood step")
    ap.add_argument("--policies", type=int, nargs="*")
    ap.add_argument("--horizons", type=int, nargs="*", help="extra vd_horizon rows at P=17")
    ap.add_argument("--sim-steps", type=int, nargs="*", help="extra sim_steps rows at P=17")
    ap.add_argument("--vmap", type=int, nargs="*", help="extra rows: this many seeds vmapped "
                    "as one program, at P=17")
    ap.add_argument("--steps", type=int, help="train_steps per timed call")
    ap.add_argument("--matmul-dtype", default="float32", help="comma list of "
                    "TrainConfig.dynamics.matmul_dtype values: every row is timed under each "
                    "(float32,bfloat16: the bf16 matmuls beside float32)")
    ap.add_argument("--official-sizes", action="store_true", help="our step at the official "
                    "loop's sizes (OFFICIAL_SIZES): the equal-work race")
    ap.add_argument("--breakdown", action="store_true", help="rows at P=17 that each take one "
                    "part of the step away (where its time goes)")
    ap.add_argument("--official-dir", help="the official port's official_p<P>.json files: "
                    "ratios per P (printed and under 'race' in --json)")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", help="TrainConfig override "
                    "of every row, after --official-sizes (e.g. scan_unroll=6)")
    ap.add_argument("--json")
    return ap


def bench_config(method: str, profile: str, official_sizes: bool, sets,
                 script: str = "bench_train.py") -> TrainConfig:
    """The timed step's config: paper sizes (profile "gpu") or TrainConfig.small(), Hopper,
    ``method`` (rl2s: pre-training and the critic warm-up off, so that the adversarial step
    itself is timed, not the MLE pre-training that precedes it in a run), then
    OFFICIAL_SIZES and the --set overrides, validated (SystemExit naming ``script``)."""
    phase = ({"adversarial.pretrain_steps": 0, "adversarial.disc_warmup_steps": 0}
             if method == "rl2s" else {})
    base = TrainConfig() if profile == "gpu" else TrainConfig.small()
    cfg = base.override({"task": "hopper", "method": method, **phase})
    if official_sizes:
        cfg = cfg.override(OFFICIAL_SIZES)
    try:
        return cfg.override(parse_overrides(sets), "--set").validate()
    except ValueError as err:
        raise SystemExit(f"{script}: {err}") from None


def planned_rows(args: argparse.Namespace, profile: str):
    """The rows to time: the profile's config with --official-sizes and --set, and per row
    (part, config, P, vmapped runs), every config validated before any measurement.
    -> (config, rows, steps per timed call, matmul size of the rate measurement)."""
    cfg = bench_config(args.method, profile, args.official_sizes, args.set)
    if profile == "gpu":
        policies, horizons, sims = [4, 17, 64, 256], [250, 4000], [64]
        steps, mm, vmaps = 10, 8192, [8]
    else:
        policies, horizons, sims = [4, 17], [400], [16]
        steps, mm, vmaps = 5, 1024, [2]
    policies = policies if args.policies is None else args.policies
    horizons = horizons if args.horizons is None else args.horizons
    sims = sims if args.sim_steps is None else args.sim_steps
    vmaps = vmaps if args.vmap is None else args.vmap
    steps = args.steps or steps
    dtypes = [d.strip() for d in args.matmul_dtype.split(",") if d.strip()]
    runs = [(cfg, P, 1) for P in policies]
    runs += [(cfg.override({"vd.horizon": h}), 17, 1) for h in horizons]
    runs += [(cfg.override({"adversarial.sim_steps": s}), 17, 1) for s in sims]
    runs += [(cfg, 17, v) for v in vmaps]
    runs = [("full", c, P, v) for c, P, v in runs]
    if args.breakdown:
        runs += [(part, c, 17, 1) for part, c in breakdown_configs(cfg)]
    runs = [(part, c.override({"dynamics.matmul_dtype": d}), P, v) for part, c, P, v in runs
            for d in dtypes]
    for _, c, _, _ in runs:  # refused by name before any measurement
        c.validate()
    return cfg, runs, steps, mm


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    official = read_official(args.official_dir) if args.official_dir else None
    backend = jax.default_backend()
    profile = args.profile if args.profile != "auto" else ("gpu" if backend == "gpu" else "cpu")
    cfg, runs, steps, mm = planned_rows(args, profile)
    rate = matmul_rate(mm)
    print(f"device {jax.devices()[0].device_kind} ({backend}), jax {jax.__version__}; profile "
          f"{profile}, method {cfg.method}, {cfg.ensemble_size} members: gen "
          f"{cfg.dynamics.hidden}, "
          f"disc {cfg.adversarial.disc_hidden}, batch {cfg.batch_size}, "
          f"{cfg.updates_per_step} gen x {cfg.adversarial.disc_updates} critic updates/step "
          f"(scan unroll {cfg.scan_unroll}), "
          f"{cfg.adversarial.sim_envs} sim envs x {cfg.adversarial.sim_steps} steps, "
          f"VD {cfg.vd.episodes} episodes x "
          f"{cfg.vd.horizon} steps every {cfg.vd.every}", flush=True)
    print(f"measured float32 matmul ({mm}^3, default precision): {rate / 1e12:.1f} TFLOP/s",
          flush=True)
    rows = []
    hdr = (f"{'row':>15} {'matmul':>8} {'P':>4} {'vd_H':>5} {'sim':>4} {'runs':>4} "
           f"{'ms/step':>9} "
           f"{'gen upd/s':>10} "
           f"{'sim trans/s':>12} {'GFLOP/step':>11} {'TFLOP/s':>8} {'of matmul':>9} {'compile':>8}")
    print(hdr, flush=True)
    for part, c, P, v in runs:
        r = bench(c, P, steps, v)
        r["fraction_of_matmul"] = r["tflop_s"] * 1e12 / rate
        r["matmul_dtype"] = c.dynamics.matmul_dtype
        r["variant"] = part
        rows.append(r)
        print(f"{part:>15} {c.dynamics.matmul_dtype:>8} {P:>4} {c.vd.horizon:>5} "
              f"{c.adversarial.sim_steps:>4} {v:>4} "
              f"{r['step_ms']:>9.2f} {r['gen_updates_per_s']:>10.0f} "
              f"{r['sim_transitions_per_s']:>12.0f} "
              f"{r['gflop_per_step']:>11.2f} {r['tflop_s']:>8.2f} "
              f"{r['fraction_of_matmul']:>9.3f} {r['compile_s']:>7.1f}s", flush=True)
    race = race_ratios(rows, official, cfg.vd.horizon) if official is not None else None
    for x in race or []:
        print(f"race P={x['policies']} runs={x['vmapped_runs']} ({x['matmul_dtype']}): official "
              f"{x['official_cycle_s']:.2f} s per cycle, ours {x['ours_cycle_s']:.3f} s: "
              f"{x['cycle_ratio']:.1f}x", flush=True)
    if args.json:
        write_json(args.json, {"device": jax.devices()[0].device_kind, "backend": backend,
                               "jax": jax.__version__, "profile": profile,
                               "official_sizes": args.official_sizes,
                               "matmul_tflop_s": rate / 1e12, "config": cfg.to_dict(),
                               "rows": rows, "race": race})
    return 0


if __name__ == "__main__":
    sys.exit(main())
