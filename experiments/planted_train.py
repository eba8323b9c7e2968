"""What diagnosis proposes, built by `rl2s train` and scored by `rl2s evaluate`: MJX Hopper
with a planted effect (clean, actuation delay, per-episode mass, signal-dependent noise).

For every effect: record a training and a held-out recording of the same system (the shipped
zoo's training policies; the held-out one with another key), diagnose the training recording
(`rl2s diagnose`), then train the plain simulator and the extended one (`rl2s train`, the
extension's `--set` items from `extension.train_set`) for every seed, and score both on the
held-out recording (`rl2s evaluate --json`: held-out NLL / MSE, AVD, MVD, tau). Paired by
seed. On the delay, `rl2s improve` and `SimulatorGymEnv` are run on the extended simulator.

    python experiments/planted_train.py --out DIR [--effects clean delay episode_param noise]
        [--seeds 3] [--steps 600] [--transitions-per-policy 3000] [--value-episodes 8]

Writes DIR/<effect>/{train,heldout}.npz, diagnosis/, <variant>/seed<S>/ (checkpoints,
evaluate.json), DIR/planted_train.json and DIR/planted_train.md (rewritten after each effect).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import jax
import numpy as np

from rl2s_jax._files import write_text
from rl2s_jax.app.diagnosis import diagnose
from rl2s_jax.data.dataset import load_dataset, save_dataset
from rl2s_jax.diagnose.extension import train_set
from rl2s_jax.diagnose.planted_mjx import collect_planted
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.policy.policy import index_params
from rl2s_jax.zoo.zoo import load_zoo

EFFECTS = ("clean", "delay", "episode_param", "noise")
METRICS = ("heldout_nll", "heldout_mse", "avd", "mvd", "kendall_tau")


def record(effect: str, tpp: int, value_episodes: int, seed: int):
    zoo = load_zoo("hopper")
    ids = zoo.split_ids("train")
    return collect_planted(
        "hopper", effect, index_params(zoo.params, ids), key=jax.random.PRNGKey(seed),
        transitions_per_policy=tpp, episode_length=get_task("hopper").episode_length,
        policy_names=zoo.policy_names(ids), gamma=0.999, value_episodes=value_episodes,
        progress=False, source={"zoo": "hopper", "split": "train", "zoo_ids": ids,
                                "seed": seed})


def rl2s(*args: str) -> None:
    """One `rl2s` command, as a user runs it (its own process; output streamed)."""
    cmd = [sys.executable, "-m", "rl2s_jax.cli", *args]
    print("$ rl2s " + " ".join(args), flush=True)
    subprocess.run(cmd, check=True)


def train_and_evaluate(args, train_path: str, held_path: str, out: str, seed: int,
                       sets: list[str]) -> None:
    """`rl2s train` (resumes a cut-off run) then `rl2s evaluate --json` on the held-out data."""
    rl2s("train", "--data", train_path, "--method", args.method, "--steps", str(args.steps),
         "--out", out, "--seed", str(seed), "--quiet", "--profile", args.profile,
         *[x for s in sets for x in ("--set", s)])
    rl2s("evaluate", "--ckpt", os.path.join(out, "checkpoints"), "--data", held_path,
         "--episodes", str(args.sim_episodes), "--horizon", str(get_task("hopper").episode_length),
         "--json", os.path.join(out, "evaluate.json"), "--force")  # a rerun re-scores


def paired(a: list[float], b: list[float]) -> dict:
    d = np.asarray(b, float) - np.asarray(a, float)
    sd = float(d.std(ddof=1)) if d.size > 1 else 0.0
    return {"mean": float(d.mean()), "std": sd,
            "ci95": 1.96 * sd / np.sqrt(d.size) if d.size > 1 else None}


def run_effect(effect: str, args, clean_reference) -> dict:
    edir = os.path.join(args.out, effect)
    os.makedirs(edir, exist_ok=True)
    t0 = time.perf_counter()
    train_path, held_path = (os.path.join(edir, f) for f in ("train.npz", "heldout.npz"))
    if not os.path.isfile(held_path):
        save_dataset(train_path, record(effect, args.transitions_per_policy,
                                        args.value_episodes, args.seed))
        save_dataset(held_path, record(effect, args.transitions_per_policy,
                                       args.value_episodes, args.seed + 500))
    t_collect = time.perf_counter() - t0
    ds = load_dataset(train_path)
    done = os.path.join(edir, "diagnosis", "report.json")
    if os.path.isfile(done):  # a resumed run: the diagnosis is made
        with open(done) as f:
            report = json.load(f)
    else:
        report = diagnose(ds, os.path.join(edir, "diagnosis"), seeds=tuple(range(2)),
                          reference=None if effect == "clean" else clean_reference,
                          plots=False, log=lambda s: print(f"[{effect}] {s}", flush=True))
    ext = report["extension"]
    # today's translation (a cached report may predate it)
    ext["train_set"], ext["not_trainable"], ext["already_in_simulator"] = train_set(
        ext["changes"])
    variants = {"plain": []}
    if ext["train_set"]:
        variants["extended"] = list(ext["train_set"])
    scores: dict[str, dict[str, list[float]]] = {}
    for variant, sets in variants.items():
        scores[variant] = {m: [] for m in METRICS}
        for seed in range(args.seeds):
            out = os.path.join(edir, variant, f"seed{seed}")
            ev = os.path.join(out, "evaluate.json")
            if not os.path.isfile(ev):  # else made by an earlier, cut-off run
                train_and_evaluate(args, train_path, held_path, out, seed, sets)
            with open(ev) as f:
                r = json.load(f)
            for m in METRICS:
                scores[variant][m].append(float(r[m] if m in r else r["metrics"][m]))
    row = {"effect": effect, "truth": ds.meta["source"]["planted"],
           "top_cause": report["top_cause"], "confidence": report["confidence"],
           "train_set": ext["train_set"], "not_trainable": ext["not_trainable"],
           "already_in_simulator": ext["already_in_simulator"],
           "scores": scores, "collect_seconds": round(t_collect, 1),
           "diagnose_seconds": report["seconds"]}
    if "extended" in scores:
        row["extended_minus_plain"] = {m: paired(scores["plain"][m], scores["extended"][m])
                                       for m in METRICS}
        if effect == "delay":
            row["doors"] = doors(os.path.join(edir, "extended", "seed0", "checkpoints"),
                                 train_path, os.path.join(edir, "improve"))
    return row


def doors(ckpt: str, data: str, out: str) -> dict:
    """`rl2s improve` and SimulatorGymEnv on the extended simulator: do they run?"""
    from rl2s_jax.improve.gym_env import SimulatorGymEnv  # local: gymnasium only here

    rl2s("improve", "--ckpt", ckpt, "--data", data, "--out", out, "--iterations", "20",
         "--policies", "0", "--episodes", "2", "--quiet", "--force")
    env = SimulatorGymEnv.from_checkpoint(ckpt, data)
    obs, _ = env.reset(seed=0)
    total = 0.0
    for _ in range(20):
        obs, r, term, trunc, _ = env.step(env.action_space.sample())
        total += float(r)
        if term or trunc:
            break
    return {"improve": os.path.isfile(os.path.join(out, "summary.json")),
            "gym_steps_finite": bool(np.isfinite(total))}


def write(args, argv, rows) -> None:
    doc = {"device": jax.devices()[0].device_kind, "jax": jax.__version__,
           "command": "python experiments/planted_train.py " + " ".join(argv),
           "seeds": args.seeds, "steps": args.steps, "method": args.method,
           "profile": args.profile, "rows": rows}
    write_text(os.path.join(args.out, "planted_train.json"),
               json.dumps(doc, indent=1, default=lambda x: np.asarray(x).tolist()))
    lines = ["| planted | found | `--set` | held-out NLL plain -> extended (diff ± 95%) | "
             "MSE | AVD | MVD | tau |", "|---|---|---|---|---|---|---|---|"]
    def cell(r, m, fmt):
        s = r["scores"]
        a = np.mean(s["plain"][m])
        if "extended" not in s:
            return f"{a:{fmt}}"
        d = r["extended_minus_plain"][m]
        ci = "" if d["ci95"] is None else f" ± {d['ci95']:{fmt}}"
        return f"{a:{fmt}} -> {np.mean(s['extended'][m]):{fmt}} ({d['mean']:+{fmt}}{ci})"

    for r in rows:
        sets = " ".join(r["train_set"]) or "-"
        if r.get("already_in_simulator"):
            sets += " (default already: " + " ".join(r["already_in_simulator"]) + ")"
        if r["not_trainable"]:
            sets += " (not trainable: " + ", ".join(n["change"] for n in r["not_trainable"]) + ")"
        lines.append(f"| {r['effect']} | {r['top_cause']} ({r['confidence']:.2f}) | {sets} | "
                     f"{cell(r, 'heldout_nll', '.2f')} | {cell(r, 'heldout_mse', '.4f')} | "
                     f"{cell(r, 'avd', '.1f')} | {cell(r, 'mvd', '.1f')} | "
                     f"{cell(r, 'kendall_tau', '.2f')} |")
    with open(os.path.join(args.out, "planted_train.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines), flush=True)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--effects", nargs="+", default=list(EFFECTS), choices=list(EFFECTS))
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--method", default="rl2s")
    ap.add_argument("--profile", default="cpu", choices=("cpu", "gpu"))
    ap.add_argument("--transitions-per-policy", type=int, default=3000)
    ap.add_argument("--value-episodes", type=int, default=8)
    ap.add_argument("--sim-episodes", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    clean = None
    rows = []
    effects = ["clean"] + [e for e in args.effects if e != "clean"]
    for effect in effects:
        if effect not in args.effects:  # the clean recording is the reference only
            path = os.path.join(args.out, "clean", "train.npz")
            if not os.path.isfile(path):
                os.makedirs(os.path.dirname(path), exist_ok=True)
                save_dataset(path, record("clean", args.transitions_per_policy,
                                          args.value_episodes, args.seed))
            row = None
        else:
            row = run_effect(effect, args, clean)
        if effect == "clean":
            clean = load_dataset(os.path.join(args.out, "clean", "train.npz"))
        if row is not None:
            rows.append(row)
            write(args, argv, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
