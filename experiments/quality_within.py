"""Is a faster variant of the protocol's quality unchanged (issue 63)? Each variant's numbers
beside a control run of `experiments/paper.py` on the same task, data seed and test policies.

    python experiments/quality_within.py CONTROL.json VARIANT.json [VARIANT.json ...]
        [--json OUT.json]

For example the control docs/results/data_seeds/hopper_data23.json against a run of
`paper.py --task hopper --data-seed 23 --seeds 3 --no-oracle --bootstrap 300
--improve-iterations 0 --set adversarial.disc_updates=2`.

Per method (the control's trained methods; the oracle is the real dynamics, not judged) and
metric (Kendall tau, MVD, AVD, nDCG@1): the variant's mean over its seeds, the control's mean
and its 95% interval, whether the variant's mean lies inside (the issue's test), and where the
two runs share seeds the per-seed paired difference (variant minus control, its mean and 95%
t-interval over the shared seeds: a seed fixes a lane's initial key and its evaluation key,
so the pairing removes part of the noise). The last line per variant says "quality unchanged"
only when every judged method's tau and MVD lie inside; "quality CHANGED" names those
outside; "not judged in full" names the methods the variant lacks and the metrics without a
value (a non-finite lane, a run cut off).

Which interval. A paper.py result holds two: ``intervals`` (what docs/RESULTS.md prints as
"[lo, hi]") is, per lane, a bootstrap over the lane's evaluation episodes and the true values'
standard errors, its ends averaged over seeds: how far evaluation noise moves ONE lane's
number. A variant trains new lanes on the same data, so what its mean may move by without a
change in quality is the spread of the control's mean over training seeds (with their
evaluation episodes), while the true values' noise, which ``intervals`` includes, is shared by
both runs (the same data). The test here is therefore the Student-t 95% interval of the
control's mean over its seeds (``per_seed``, n - 1 degrees of freedom: ``stats.t_interval``),
which is the interval of "the current protocol's number" (a mean over seeds). The published
episode interval is shown beside it, with whether the variant's mean lies in that too. With 3
seeds the t quantile is 4.30: the test catches only a clear change.

Refused before any work, naming the field: a file that is not a paper.py result (one of
REQUIRED missing, or a command that is not paper.py's), a control with fewer than 2 seeds,
and a variant of another task, data seed, policy split or test-policy list. Each variant's
``timings`` are printed against the control's (data, the two training phases, the oracle and
trust, the total, and the total without oracle and trust: the issue's protocol) so that speed
and quality are read together.
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax.stats import paired_seed_difference, t_interval

REQUIRED = ("task", "data_seed", "per_seed", "seeds", "test_policy_names", "command",
            "timings")
SAME = ("task", "data_seed", "policy_split", "test_policy_names")  # control and variant agree
METRICS = ("kendall_tau", "mvd", "avd", "ndcg@1")
JUDGED = ("kendall_tau", "mvd")  # the test
NOT_JUDGED = ("oracle",)  # the real dynamics: no training to change
TIMINGS = ("data", "train_adversarial", "train_mle", "oracle", "trust", "total")
LEVEL = 0.95


def load_result(path: str) -> dict:
    """A paper.py result JSON, refused (SystemExit naming the file and field) when it is not
    one."""
    try:
        with open(path) as f:
            r = json.load(f)
    except (OSError, json.JSONDecodeError) as err:
        raise SystemExit(f"{path}: expected a paper.py result JSON, could not read it: {err}"
                         ) from None
    if not isinstance(r, dict):
        raise SystemExit(f"{path}: expected a paper.py result (a JSON object), got "
                         f"{type(r).__name__}")
    missing = [k for k in REQUIRED if k not in r]
    if missing:
        raise SystemExit(f"{path}: not a paper.py result: no {', '.join(map(repr, missing))}")
    if not str(r["command"]).startswith("python experiments/paper.py"):
        raise SystemExit(f"{path}: command: expected 'python experiments/paper.py ...' (a "
                         f"paper.py result), got {str(r['command'])[:80]!r}")
    if not isinstance(r["per_seed"], dict) or not all(
            isinstance(v, dict) for v in r["per_seed"].values()):
        raise SystemExit(f"{path}: per_seed: expected {{method: {{metric: [per seed]}}}}")
    return r


def seed_ids(r: dict) -> list:
    """The result's seeds in per_seed's order: ``seed_ids``, else 0 .. seeds-1."""
    return list(r.get("seed_ids") or range(int(r["seeds"])))


def check_comparable(control: dict, variant: dict, path: str) -> None:
    """SystemExit naming the field where the variant was run on other data or policies."""
    for k in SAME:
        a, b = control.get(k, "zoo" if k == "policy_split" else None), \
            variant.get(k, "zoo" if k == "policy_split" else None)
        if a != b:
            show = (lambda x: f"{len(x)} policies {x[:3]}...") if k == "test_policy_names" \
                else repr
            raise SystemExit(f"{path}: {k}: expected the control's {show(a)}, got {show(b)}: "
                             "only a run on the same data and test policies can be judged "
                             "against it")


def by_seed(r: dict, method: str, metric: str) -> dict:
    """{seed: value} of a method's metric, the seeds without a value (None) left out."""
    vals = r["per_seed"].get(method, {}).get(metric) or []
    return {s: float(v) for s, v in zip(seed_ids(r), vals, strict=False) if v is not None}


def judge_metric(control: dict, variant: dict, method: str, metric: str) -> dict:
    """One method's metric: the control's mean and t-interval over seeds, the published
    episode interval, the variant's mean, whether it lies inside each, the paired
    difference over the shared seeds (None with fewer than 2)."""
    c, v = by_seed(control, method, metric), by_seed(variant, method, metric)
    t = t_interval(list(c.values()), LEVEL) if len(c) > 1 else None
    pub = (control.get("intervals") or {}).get(method, {}).get(metric)
    v_mean = float(np.mean(list(v.values()))) if v else None
    shared = [s for s in c if s in v]
    pair = paired_seed_difference([v[s] for s in shared], [c[s] for s in shared])
    inside = (None if t is None or v_mean is None else bool(t[1] <= v_mean <= t[2]))
    return {"control_mean": None if t is None else t[0],
            "control_t95": None if t is None else [t[1], t[2]],
            "control_seeds": len(c), "published": None if not pub else [pub["lo"], pub["hi"]],
            "variant_mean": v_mean, "variant_seeds": len(v), "inside": inside,
            "inside_published": (None if not pub or v_mean is None
                                 else bool(pub["lo"] <= v_mean <= pub["hi"])),
            "paired": None if pair is None else {
                "mean": pair[0], "t95": [pair[1], pair[2]], "variant_lower": pair[3],
                "seeds": pair[4]}}


def timing_rows(control: dict, variant: dict) -> dict:
    """{phase: [control s, variant s]} (None where a run has no such phase), the data
    phase's parts ("data_<part>", where either run logged them) after "data", and
    "protocol": the total without the oracle and trust phases (the issue's `--no-oracle`
    protocol)."""
    parts = [k for r in (control, variant) for k in r["timings"] if k.startswith("data_")]
    keys = [k for t in TIMINGS for k in ([t, *dict.fromkeys(parts)] if t == "data" else [t])]
    rows = {k: [r["timings"].get(k) for r in (control, variant)] for k in keys}

    def protocol(t):
        return None if t.get("total") is None else round(
            t["total"] - t.get("oracle", 0.0) - t.get("trust", 0.0), 1)

    rows["protocol"] = [protocol(control["timings"]), protocol(variant["timings"])]
    return rows


def judge(control: dict, variant: dict) -> dict:
    """The variant against the control: per method and metric ``judge_metric``, the methods
    it lacks, the "method metric" of JUDGED outside their interval and those without a value
    (either run's), the verdict ("unchanged": none of the three), the protocol sizes that
    differ ({key: [control, variant]}), the timings."""
    methods = [m for m in control["per_seed"] if m not in NOT_JUDGED]
    missing = [m for m in methods if m not in variant["per_seed"]]
    rows = {m: {k: judge_metric(control, variant, m, k) for k in METRICS}
            for m in methods if m not in missing}
    outside = [f"{m} {k}" for m, row in rows.items() for k in JUDGED
               if row[k]["inside"] is False]
    no_value = [f"{m} {k}" for m, row in rows.items() for k in JUDGED
                if row[k]["inside"] is None]
    return {"methods": rows, "missing": missing, "outside": outside, "no_value": no_value,
            "unchanged": not (missing or outside or no_value),
            "complete": variant.get("complete"),
            "shared_seeds": sorted(set(seed_ids(control)) & set(seed_ids(variant))),
            "sizes_differ": {k: [control.get("sizes", {}).get(k), v]
                             for k, v in (variant.get("sizes") or {}).items()
                             if control.get("sizes", {}).get(k) != v},
            "timings": timing_rows(control, variant)}


def _f(x, metric: str = "") -> str:
    if x is None:
        return "n/a"
    return f"{x:.1f}" if metric in ("mvd", "avd") else f"{x:.3f}"


def report(path: str, variant: dict, j: dict) -> str:
    """The printed comparison of one variant."""
    lines = [f"\nvariant {path} ({variant['command']}); seeds {seed_ids(variant)}"
             + ("" if j["complete"] is not False else "; INCOMPLETE run (complete: false)")
             + "".join(f"\n  sizes differ: {k} {a} (control) -> {b}"
                       for k, (a, b) in j["sizes_differ"].items()),
             f"  {'method':<8} {'metric':<12} {'variant':>9} {'control':>9} "
             f"{'control t95':>21} {'in':>3} {'episode interval':>21} {'in':>3} "
             f"{'paired diff [t95]':>30}"]
    for m, row in j["methods"].items():
        for k, r in row.items():
            t95 = ("n/a" if r["control_t95"] is None else
                   f"[{_f(r['control_t95'][0], k)}, {_f(r['control_t95'][1], k)}]")
            pub = ("n/a" if r["published"] is None else
                   f"[{_f(r['published'][0], k)}, {_f(r['published'][1], k)}]")
            p = r["paired"]
            pair = ("n/a" if p is None else f"{_f(p['mean'], k)} [{_f(p['t95'][0], k)}, "
                    f"{_f(p['t95'][1], k)}] ({p['seeds']} seeds)")
            yes = {True: "yes", False: "NO", None: "n/a"}
            lines.append(f"  {m:<8} {k:<12} {_f(r['variant_mean'], k):>9} "
                         f"{_f(r['control_mean'], k):>9} {t95:>21} {yes[r['inside']]:>3} "
                         f"{pub:>21} {yes[r['inside_published']]:>3} {pair:>30}")
    lines.append(f"  {'timings (s)':<18} {'control':>9} {'variant':>9} {'ratio':>6}")
    for k, (a, b) in j["timings"].items():
        ratio = f"{b / a:.2f}" if a and b is not None else "n/a"
        lines.append(f"  {k:<18} {_f(a, 'mvd'):>9} {_f(b, 'mvd'):>9} {ratio:>6}")
    if j["unchanged"]:
        lines.append(f"  => quality unchanged: every method's {' and '.join(JUDGED)} inside "
                     "the control's 95% t-interval over seeds")
    if j["outside"]:
        lines.append(f"  => quality CHANGED: outside the control's 95% t-interval: "
                     f"{', '.join(j['outside'])}")
    if j["missing"] or j["no_value"]:
        why = ([f"methods missing: {', '.join(j['missing'])}"] if j["missing"] else []) + (
            [f"no value: {', '.join(j['no_value'])}"] if j["no_value"] else [])
        lines.append(f"  => not judged in full ({'; '.join(why)})")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("control", help="the control run: a paper.py result JSON (>= 2 seeds)")
    ap.add_argument("variants", nargs="+", help="paper.py result JSONs of variants")
    ap.add_argument("--json", help="also write the comparisons here")
    args = ap.parse_args(argv)
    control = load_result(args.control)
    if len(seed_ids(control)) < 2:
        raise SystemExit(f"{args.control}: seeds: expected a control of >= 2 seeds (a "
                         f"t-interval over seeds), got {seed_ids(control)}")
    variants = [(p, load_result(p)) for p in args.variants]
    for p, v in variants:
        check_comparable(control, v, p)
    print(f"control {args.control} ({control['command']}); task {control['task']}, data seed "
          f"{control['data_seed']}, seeds {seed_ids(control)}")
    out = {"control": args.control, "level": LEVEL, "judged": list(JUDGED), "variants": {}}
    for p, v in variants:
        out["variants"][p] = j = judge(control, v)
        print(report(p, v, j))
    if args.json:
        write_json(args.json, out)
        print(f"-> {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
