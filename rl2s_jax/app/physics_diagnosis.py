"""`rl2s diagnose --physics`: what the physics model gets wrong on measured data, the physical
quantities that explain it with their values, written as report.json, report.md, a plot and
calibrated.json (docs/DIAGNOSIS.md, "Physics").

    report = diagnose_physics(PhysicsSpec(data="D.npz", out="out/"))
    report["physics"]["top_cause"]  # {"name", "element", "nominal", "value", "interval"} | None
"""

from __future__ import annotations

import dataclasses
import os
import shlex
import time

import numpy as np

from rl2s_jax._files import save_figure, write_json, write_text
from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.diagnose.gaps import jsonable
from rl2s_jax.physics.hybrid import calibrated_model, read_calibrated
from rl2s_jax.physics.identify import FitConfig, format_quantity, identify
from rl2s_jax.physics.mjx_model import PHYSICS_TASKS, integrator_name, physics_model
from rl2s_jax.physics.residuals import physics_errors

__all__ = ["PhysicsSpec", "diagnose_physics", "load_calibrated", "physics_command"]


@dataclasses.dataclass(frozen=True)
class PhysicsSpec:
    """data: Dataset (.npz); out: report directory; sim_xml: a user's MJCF (obs = qpos ++
    qvel) instead of the data's task; sim_frames: its physics steps per control step; fit:
    the identification's settings (its seed also draws the error breakdowns' windows); k:
    open-loop steps."""

    data: str
    out: str
    sim_xml: str | None = None
    sim_frames: int | None = None
    fit: FitConfig = FitConfig()
    k: int = 10
    quiet: bool = False

    def validate(self) -> PhysicsSpec:
        if self.sim_xml is not None and not os.path.isfile(self.sim_xml):
            raise ValueError(f"sim_xml: expected an MJCF file, got {self.sim_xml!r}")
        if not 0.0 < self.fit.alpha < 1.0:
            raise ValueError(f"alpha: expected a level in (0, 1), got {self.fit.alpha}")
        for name, value in (("rows", self.fit.rows), ("max_params", self.fit.max_params),
                            ("k", self.k)):
            if value < 1:
                raise ValueError(f"{name}: expected a positive int, got {value}")
        return self


def physics_command(spec) -> int:
    """`rl2s diagnose --physics`: its DiagnoseSpec (app/specs.py) -> :class:`PhysicsSpec` ->
    :func:`diagnose_physics`."""
    diagnose_physics(PhysicsSpec(data=spec.data, out=spec.out, sim_xml=spec.sim_xml,
                                 sim_frames=spec.sim_frames, k=spec.k_max, quiet=spec.quiet,
                                 fit=FitConfig(alpha=spec.alpha, seed=spec.seed)))
    return 0


def load_calibrated(path: str):
    """The calibrated simulator a report wrote: (PhysicsModel, theta [K], delays [A])."""
    return calibrated_model(read_calibrated(path))


def diagnose_physics(spec: PhysicsSpec) -> dict:
    """The command's work (module docstring) -> the report dict it wrote."""
    spec.validate()
    ds = load_dataset(spec.data)
    task = ds.meta.get("task")
    if spec.sim_xml is None and task not in PHYSICS_TASKS:
        raise ValueError(f"data: its task {task!r} has no physics model (expected one of "
                         f"{sorted(PHYSICS_TASKS)}); pass --sim-xml FILE with your MJCF model")
    log = (lambda *_: None) if spec.quiet else print  # noqa: E731
    start = time.perf_counter()
    pm = physics_model(task if spec.sim_xml is None else None, xml_path=spec.sim_xml,
                       n_frames=spec.sim_frames)
    cfg = spec.fit
    log(f"[physics] {ds.n_transitions} transitions, {len(pm.candidates)} candidate quantities")
    found = identify(pm, ds, cfg)
    nominal = physics_errors(pm, ds, k=spec.k, seed=cfg.seed)
    content = jsonable({"task": pm.task, "xml": pm.xml_path, "n_frames": pm.n_frames,
                        "theta": found["theta"], "delays": found["delays"],
                        "integrator": found["integrator"], "collisions": found["collisions"],
                        "labels": [c.label for c in pm.candidates]})
    # the calibrated model as calibrated.json loads it; the nominal one (its compiled
    # programs) where the diagnosis kept the model's structure
    pm_cal = (pm if found["integrator"] == integrator_name(pm.mj) and not found["collisions"]
              else calibrated_model(content)[0])
    calibrated = physics_errors(pm_cal, ds, found["theta"], found["delays"], k=spec.k,
                                seed=cfg.seed)
    os.makedirs(spec.out, exist_ok=True)
    cal_path = os.path.join(spec.out, "calibrated.json")
    write_json(cal_path, content)
    # the calibrated simulator as a user runs it (`rl2s improve --physics` and
    # gymnasium.make(..., physics=) take the same file; load_calibrated from Python)
    command = (f"rl2s evaluate --physics {shlex.quote(cal_path)} --data "
               f"{shlex.quote(spec.data)}")
    physics = {k: found[k] for k in ("top_cause", "parameters", "unexplained")}
    physics.update(seconds=time.perf_counter() - start, command=command,
                   error_nominal=found["error_nominal"],
                   error_calibrated=found["error_calibrated"])
    report = jsonable({"physics": physics, "errors": {"nominal": nominal,
                                                     "calibrated": calibrated},
                       "data": spec.data, "task": task, "sim_xml": spec.sim_xml})
    write_json(os.path.join(spec.out, "report.json"), report)
    figs = plot_physics(spec.out, nominal, calibrated)
    write_text(os.path.join(spec.out, "report.md"), physics_markdown(report, figs))
    log(f"[physics] wrote {spec.out}/report.json, report.md, calibrated.json and "
        f"{len(figs)} plot(s) in {physics['seconds']:.1f} s")
    return report


def _kept(p: dict) -> str:
    """The report's "kept" cell: a quantity not kept whose drop lies mostly in under half of
    the test episodes says so (more data with what moves them, e.g. a rare contact, decides)."""
    few, total = p.get("drop_episodes") or (0, 0)
    if p["significant"] or not 0 < few < total / 2:
        return "yes" if p["significant"] else "no"
    return (f"no: 90% of its drop is in {few} of {total} test episodes (more episodes where "
            f"it acts decide)")


def plot_physics(out_dir: str, nominal: dict, calibrated: dict) -> list[str]:
    """physics_one_step.png: per-dim normalised one-step RMSE, nominal vs calibrated, and the
    k-step growth. -> the paths written."""
    # Imported here to keep start-up fast: matplotlib loads in about a second, and only
    # the plot needs it.
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 3.6))
    dims = np.arange(len(nominal["one_step"]["by_dim"]))
    for shift, (name, e) in zip((-0.2, 0.2), (("nominal", nominal), ("calibrated", calibrated)),
                                strict=True):
        ax.bar(dims + shift, [d["rmse_normalised"] for d in e["one_step"]["by_dim"]], 0.4,
               label=name)
        if e["kstep"]:
            bx.plot(np.arange(1, len(e["kstep"]) + 1), e["kstep"], marker="o", label=name)
    ax.set(xlabel="obs dim", ylabel="one-step RMSE / std(next_obs - obs)", xticks=dims)
    bx.set(xlabel="open-loop steps k", ylabel="normalised RMSE")
    ax.legend()
    bx.legend()
    fig.tight_layout()
    path = os.path.join(out_dir, "physics_one_step.png")
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return [path]


def physics_markdown(report: dict, figs: list[str]) -> str:
    """report.md: the cause with its value, every quantity tried, the errors, the plot."""
    ph, err = report["physics"], report["errors"]
    top = ph["top_cause"]
    lines = ["# Physics diagnosis", "",
             f"Data: `{report['data']}` (task {report['task']}"
             + (f", model `{report['sim_xml']}`" if report["sim_xml"] else "") + ").", "",
             ("**Top cause:** " + format_quantity(top)) if top else
             "**Nothing significant:** no quantity of the candidate set explains the error.",
             "", f"Calibrated model leaves {100 * ph['unexplained']:.1f}% of the held-out "
             f"one-step error ({ph['seconds']:.1f} s).", "",
             "| quantity | nominal -> value [95% interval] | held-out error drop | p | kept |",
             "|---|---|---|---|---|"]
    for p in ph["parameters"]:
        lines.append(f"| {p['name']}[{p['element']}] | {format_quantity(p).split('] ', 1)[1]} | "
                     f"{100 * p['gain']:.1f}% | {p['p_value']:.2g} | {_kept(p)} |")
    lines += ["", "| error (normalised RMSE) | nominal | calibrated |", "|---|---|---|",
              f"| one-step | {err['nominal']['one_step']['rmse']:.4g} | "
              f"{err['calibrated']['one_step']['rmse']:.4g} |"]
    for where, label in (("in", "in contact"), ("out", "out of contact")):
        a, b = err["nominal"]["one_step"]["contact"][where], \
            err["calibrated"]["one_step"]["contact"][where]
        if a is not None:
            lines.append(f"| one-step, {label} | {a:.4g} | {b:.4g} |")
    if err["nominal"]["kstep"]:
        k = len(err["nominal"]["kstep"])
        lines.append(f"| {k}-step open loop | {err['nominal']['kstep'][-1]:.4g} | "
                     f"{err['calibrated']['kstep'][-1]:.4g} |")
    for j, jc in zip(err["nominal"]["one_step"]["by_joint"],
                     err["calibrated"]["one_step"]["by_joint"], strict=True):
        lines.append(f"| joint {j['joint']} ({j['body']}) | {j['rmse_normalised']:.4g} | "
                     f"{jc['rmse_normalised']:.4g} |")
    lines += ["", f"Calibrated simulator: `{ph['command']}`", ""]
    lines += [f"![{os.path.basename(f)}]({os.path.basename(f)})" for f in figs]
    return "\n".join(lines) + "\n"
