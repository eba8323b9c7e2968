"""`rl2s zoo`: train (or continue) a task's zoo learners (SAC/PPO over vmapped seeds,
resumable), then measure, choose and split the zoo (rl2s_jax/zoo/build.py)."""

from __future__ import annotations

import os
import time

from rl2s_jax.app.specs import ZooSpec


def run_zoo(spec: ZooSpec) -> int:
    """Train (or continue) a task's zoo learners, then measure, choose and split the zoo into
    ``spec.out`` (default: the shipped zoo's directory); 0 also when the time limit stops."""
    started = time.time()
    # local: after the clock starts, so that --time-limit counts the stack's import (seconds)
    from rl2s_jax.app.training import parse_overrides
    from rl2s_jax.zoo import build as zb
    from rl2s_jax.zoo.store import load_runs, read_export, write_export
    from rl2s_jax.zoo.zoo import zoo_dir

    out = spec.out or zoo_dir(spec.task)
    if spec.plots_only:
        files = zb.write_zoo_plots(out)
        print(f"zoo plots: {', '.join(files)} -> {out}")
        return 0
    overrides: dict = {}
    for k, v in parse_overrides(spec.set).items():
        learner, _, field = k.partition(".")
        if not field:
            raise ValueError(f"set: expected sac.FIELD=VALUE or ppo.FIELD=VALUE, got {k!r}")
        overrides.setdefault(learner, {})[field] = v
    algo = spec.algo or zb.DEFAULT_ALGO.get(spec.task, "sac")
    plans = zb.learner_plans(spec.task, algo, spec.env_steps, spec.snapshots, overrides)
    work = spec.work or os.path.join("runs", "zoo", spec.task)
    imported = read_export(spec.import_file) if spec.import_file else None
    deadline = started + spec.time_limit if spec.time_limit else None
    base, base_log = zb.zoo_with_log(spec.extend) if spec.extend else (None, [])
    zoo, extras = zb.build_zoo(
        spec.task, algo=algo, seeds=spec.seeds, seed=spec.seed, plans=plans, work_dir=work,
        deadline=deadline, imported=imported, value_episodes=spec.value_episodes,
        zoo_size=spec.zoo_size, min_test=spec.min_test if base is not None else None,
        checkpoint_every_s=spec.checkpoint_every, final=spec.final, extend=base,
        progress=not spec.quiet)
    if spec.export:
        files = write_export(spec.export, load_runs(work, plans),
                             max_bytes=int(spec.export_max_mib * 2**20))
        print(f"[zoo] exported the run for resuming: {', '.join(files)}")
    if zoo is None:
        print(f"zoo: training stopped at the time limit ({time.time() - started:.0f}s); the "
              f"same command continues from {work}")
        return 0
    files = zb.write_zoo_outputs(zoo, base_log + extras["log"], out)
    info = zoo.info
    if base is not None:
        print(f"zoo: extended {spec.extend}: {len(extras['added'])} of {len(extras['log'])} new "
              f"snapshots join the test split as ids {base.size}..{zoo.size - 1}")
    bar = info["expert_bar"]
    print(f"zoo: {zoo.size} policies from {info['snapshots_measured']} snapshots, returns "
          f"{zoo.returns.min():.1f} .. {zoo.returns.max():.1f}"
          + (f" (expert bar {bar:g}: {'met' if info['expert_bar_met'] else 'MISSED'})"
             if bar is not None else "")
          + f"; train {len(zoo.train_ids)}, test {len(zoo.test_ids)}")
    for name, lr in info["learners"].items():
        print(f"  {name}: {lr['env_steps_per_seed']:,} of {lr['env_steps_target']:,} env steps "
              f"per seed" + ("" if lr["complete"] else " (stopped at the time limit)"))
    for split in ("train", "test"):
        print("  spread " + zb.format_spread(split, info["spread"][split]))
    print(f"-> {out}: {', '.join(files)} ({time.time() - started:.0f}s)")
    return 0

