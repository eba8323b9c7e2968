"""The model family's ablation (``experiments/ablation_model.py``, issue 10): its variants
(the legacy single generator, the MLE ensemble, RL2S from the pretrained ensemble, each with
its own config overrides: ``bc:multistep_steps=5+multistep_weight=0.5``), other rollout
settings of a trained simulator (``--rollouts``), the leave-policies-out validation split,
and the table over seeds: the TEST metrics at the last evaluation ("final") and at the point
chosen on the training policies (``train.lanes.select_point``: "selected").
``experiments/model_fit.py`` shares the variants; the controls of the ablation's diagnostics
(``experiments/open_loop_control.py``, ``closed_loop_control.py``) its test data and noise
scales."""
from __future__ import annotations

import json
import os

import numpy as np

from rl2s_jax._files import write_json, write_text
from rl2s_jax.app.pipeline import collect_dataset
from rl2s_jax.app.training import parse_overrides
from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.model.dynamics import MEMBER_MODES
from rl2s_jax.model.termination import TERMINATIONS
from rl2s_jax.train.config import LEGACY_MODEL, TrainConfig, saved_field
from rl2s_jax.train.lanes import select_point

# variant -> (config method, config overrides); "rl2s" keeps the EMA and is evaluated twice.
VARIANTS = {
    "legacy": ("rl2s", dict(LEGACY_MODEL)),
    "legacy-bc": ("bc", dict(LEGACY_MODEL)),
    "bc": ("bc", {}),
    "rl2s": ("rl2s", {}),
}
ROWS = ("legacy", "legacy-bc", "bc", "rl2s", "rl2s+ema")
METRICS = ("kendall_tau", "ndcg@1", "avd", "mvd", "spearman")


def parse_variant(spec: str) -> tuple[str, dict]:
    """'bc' or 'bc:multistep_steps=5+multistep_weight=0.5' -> (base variant, its own config
    overrides); the row is named by the whole spec."""
    base, _, extra = spec.partition(":")
    if base not in VARIANTS:
        raise SystemExit(f"variants: expected names from {', '.join(VARIANTS)} (optionally "
                         f"':key=value+key=value'), got {spec!r}")
    try:
        own = parse_overrides([kv for kv in extra.split("+") if kv]) if extra else {}
    except (ValueError, SystemExit) as e:
        raise SystemExit(f"variants: {spec!r}: {e}") from None
    return base, own


def check_variants(task: str, text: str, parse=parse_variant) -> list[str]:
    """The comma-separated variant specs of ``text``, each parsed by ``parse`` and its config
    validated for ``task``: bad input stops here (SystemExit naming the spec), before any
    work."""
    variants = [v for v in text.split(",") if v]
    if not variants:
        raise SystemExit(f"variants: expected names from {', '.join(VARIANTS)}")
    for v in variants:
        base, own = parse(v)
        try:
            TrainConfig.from_dict({"task": task, "method": VARIANTS[base][0],
                                   **VARIANTS[base][1], **own}).validate()
        except (ValueError, TypeError) as e:
            raise SystemExit(f"variants: {v!r}: {e}") from None
    return variants


def parse_rollouts(text: str | None) -> list[tuple]:
    """--rollouts 'random:1,mean:0,random:0:both' -> [("random", 1.0), ("mean", 0.0),
    ("random", 0.0, "both")]: member mode, noise scale and optionally the termination."""
    out = []
    for item in (x.strip() for x in (text or "").split(",") if x.strip()):
        mode, _, rest = item.partition(":")
        noise, _, term = rest.partition(":")
        try:
            scale = float(noise)
        except ValueError:
            scale = -1.0
        if (mode not in MEMBER_MODES or not (np.isfinite(scale) and scale >= 0)
                or (term and term not in TERMINATIONS)):
            raise SystemExit(f"rollouts: expected MODE:NOISE[:TERMINATION] items with MODE in "
                             f"{', '.join(MEMBER_MODES)}, NOISE >= 0 and TERMINATION in "
                             f"{', '.join(TERMINATIONS)}, got {item!r}")
        out.append((mode, scale, term) if term else (mode, scale))
    return out


def rollout_row(variant: str, rollout: tuple) -> str:
    """The table row of a variant evaluated with other rollout settings:
    "<variant>@<mode>:<noise>[:<termination>]"."""
    return f"{variant}@{rollout[0]}:{rollout[1]:g}" + (f":{rollout[2]}" if len(rollout) > 2
                                                         else "")


def split_validation(train_ds, n: int):
    """Leave-policies-out validation inside the training zoo: ``n`` training policies spread
    over its value ranking (the middle of n equal slices) are held out whole, the model is
    fitted on the rest, and the held-out ones are ranked like test policies. A choice made on
    them (e.g. the termination) never sees the test policies, and unlike the training
    policies' held-out episodes it measures generalisation to policies the model has not seen.
    -> (fit Dataset, validation Dataset)"""
    p = train_ds.n_policies
    if not 2 <= n <= p - 2:
        raise SystemExit(f"validation-policies: expected 2 ... {p - 2} (the training split "
                         f"has {p} policies), got {n}")
    order = np.argsort(np.asarray(train_ds.value_discounted, np.float64))
    held = sorted(int(order[int((i + 0.5) * p / n)]) for i in range(n))
    rest = [i for i in range(p) if i not in held]
    zoo_ids = list(train_ds.meta["source"]["zoo_ids"])
    out = []
    for ids in (rest, held):
        part = train_ds.select_policies(ids)
        part.meta["source"] = {**part.meta["source"], "zoo_ids": [int(zoo_ids[i]) for i in ids]}
        out.append(part)
    return tuple(out)


def tau_swing(points: list[dict], from_step: int = 0) -> float | None:
    """Mean |change of test Kendall tau| between consecutive evaluations of one lane, over the
    evaluations at steps >= from_step (the adversarial phase of a pre-trained run); None with
    fewer than two finite points. How much a lane's ranking moves from one checkpoint to the
    next: what a moving average of the weights should damp."""
    taus = [p["test"]["kendall_tau"] for p in points
            if p["step"] >= from_step and p["test"] is not None]
    taus = np.asarray(taus, np.float64)
    taus = taus[np.isfinite(taus)]
    return float(np.mean(np.abs(np.diff(taus)))) if taus.size > 1 else None


def summarize_rows(results: list[dict]) -> dict:
    """{row: {"final" | "selected": {metric: (mean, std, n)}, "selected_steps": [...],
    "tau_swing": (mean, std, n)}} over the seeds of every variant result; the swing is taken
    from the first evaluation at or after the pre-training steps (the config's
    adversarial.pretrain_steps of an adversarial variant, else from the start)."""
    table = {}
    for res in results:
        cfg = res.get("config") or {}
        adversarial = cfg.get("method") in ("rl2s", "gail")
        from_step = (int(saved_field(cfg, "adversarial.pretrain_steps") or 0) if adversarial
                     else 0)
        for row, lanes in res["curves"].items():
            finals, chosen, steps, swings, valids = [], [], [], [], []
            for points in lanes.values():
                sw = tau_swing(points, from_step)
                if sw is not None:
                    swings.append(sw)
                if points and points[-1]["test"] is not None:
                    finals.append(points[-1]["test"])
                if points and points[-1].get("validation") is not None:
                    valids.append(points[-1]["validation"])
                sel = select_point(points)
                if sel is not None:
                    chosen.append(sel["test"])
                    steps.append(sel["step"])
            entry = {}
            for what, rs in (("final", finals), ("selected", chosen), ("validation", valids)):
                entry[what] = {}
                for k in METRICS:
                    v = np.asarray([r[k] for r in rs], np.float64)
                    entry[what][k] = (float(v.mean()) if v.size else None,
                                      float(v.std(ddof=1)) if v.size > 1 else None, int(v.size))
            entry["selected_steps"] = steps
            v = np.asarray(swings, np.float64)
            entry["tau_swing"] = (float(v.mean()) if v.size else None,
                                  float(v.std(ddof=1)) if v.size > 1 else None, int(v.size))
            entry["seeds"] = len(lanes)
            table[row] = entry
    return table


def markdown(table: dict, task: str) -> str:
    """``summarize_rows``' table as Markdown: per row the final and selected test metrics
    (mean ± std over seeds), the tau swing, the selected steps and, when any row has them,
    the validation policies' tau and AVD."""
    cols = ("kendall_tau", "ndcg@1", "avd", "mvd")
    vcols = ("kendall_tau", "avd") if any(e.get("validation", {}).get("avd", (None,))[0]
                                          is not None for e in table.values()) else ()
    head = (f"| {task} | " + " | ".join(f"{c} final" for c in cols) + " | "
            + " | ".join(f"{c} selected" for c in cols) + " | tau swing | selected steps |"
            + "".join(f" validation {c} |" for c in vcols))
    lines = [head, "|" + "---|" * (2 * len(cols) + 3 + len(vcols))]
    fmt = lambda c: "n/a" if c[0] is None else (f"{c[0]:.3g}" + ("" if c[1] is None
                                                                  else f" ± {c[1]:.2g}"))
    for row in [r for r in ROWS if r in table] + sorted(set(table) - set(ROWS)):
        e = table[row]
        cells = ([fmt(e["final"][c]) for c in cols] + [fmt(e["selected"][c]) for c in cols]
                 + [fmt(e.get("tau_swing", (None, None, 0)))])
        lines.append(f"| {row} | " + " | ".join(cells) + f" | {e['selected_steps']} |"
                     + "".join(f" {fmt(e['validation'][c])} |" for c in vcols))
    return "\n".join(lines)


def write_summary(out: str, task: str, paths: list[str]) -> str:
    """The table of the variant JSONs at ``paths`` (one task) into
    out/ablation_<task>.json (rows, sources, runs) and out/ablation_<task>.md. -> the
    Markdown"""
    results = []
    for p in paths:
        with open(p) as f:
            results.append(json.load(f))
    table = summarize_rows(results)
    md = markdown(table, task)
    write_json(os.path.join(out, f"ablation_{task}.json"),
               {"task": task, "rows": table, "sources": paths,
                "runs": [{k: r[k] for k in ("variant", "hardware", "jax_version", "command",
                                            "timings", "complete")} for r in results]})
    write_text(os.path.join(out, f"ablation_{task}.md"), md + "\n")
    return md


def load_test_split(task_name: str, path: str | None, transitions_per_policy: int):
    """The Dataset at ``path``, else the zoo's test split collected (no value episodes)."""
    if path:
        return load_dataset(path)
    return collect_dataset(task_name, "test", transitions_per_policy, value_episodes=0,
                           progress=False)


def parse_noise(text: str, *, zero_ok: bool) -> list[float]:
    """--noise '0,0.01' -> [0.0, 0.01]; SystemExit naming the field on bad input."""
    bad = f"noise: expected comma-separated floats {'>=' if zero_ok else '>'} 0, got {text!r}"
    try:
        scales = [float(x) for x in text.split(",") if x]
    except ValueError:
        raise SystemExit(bad) from None
    if not scales or any(not np.isfinite(x) or x < 0 or (x == 0 and not zero_ok)
                         for x in scales):
        raise SystemExit(bad)
    return scales
