"""The paper protocol's improvement phases (``experiments/paper.py``, phase 3): SAC fine-tunes
test policies inside every lane's simulator (``improve.lane_finetune``: all methods x seeds x
policies as one vmapped program), once per variant of the simulated env, the fine-tuned
policies' real returns are measured paired with the start policies', and the same fine-tuning
in the real env is the control. Everything lands in the result dict of ``paper.protocol``."""
from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.app.improvement import guard_floor
from rl2s_jax.app.specs import check_floor_scale
from rl2s_jax.data.collect import measure_values
from rl2s_jax.envs.tasks import Task, get_task
from rl2s_jax.evaluate.oracle import oracle_dynamics
from rl2s_jax.evaluate.scores import evaluate_simulator
from rl2s_jax.improve.finetune import (
    deployment_guard,
    improve_in_real_env,
    improve_policies,
    improvement_metrics,
    paired_returns,
)
from rl2s_jax.improve.lane_finetune import finite_mean, guard_lanes, improve_in_lanes, pick_policies
from rl2s_jax.improve.sim_env import branch_pool, real_rows, scaled_env_options
from rl2s_jax.model.simulator import start_pool
from rl2s_jax.paper.protocol import (
    IMPROVE_METRICS,
    METHODS,
    fmt_ms,
    log,
    method_means,
    none_if_nan,
    take_lanes,
)
from rl2s_jax.policy.policy import Params, index_params
from rl2s_jax.policy.sac import SACConfig, episode_returns
from rl2s_jax.train.config import saved_field
from rl2s_jax.train.step import simulator


@dataclasses.dataclass
class FineTuning:
    """What every fine-tuning of one protocol run shares: the test policies fine-tuned
    (``ids`` [P] into the test data, their true returns ``c0`` [P], their stacked params
    ``policies``), the SAC settings and budget, and the real measurement's protocol."""

    task: Task
    ids: list[int]
    c0: np.ndarray
    policies: Params
    horizon: int
    sac: SACConfig
    iterations: int
    chunk: int
    episodes: int
    episode_length: int
    gamma: float


def setup_fine_tuning(result: dict, task_name: str, test_ds, test_pols, sizes: dict,
                      horizon: int, sac_settings: dict) -> FineTuning:
    """The test policies to fine-tune (``sizes["improve_policies"]`` spread over their true
    returns, none with C0 = 0) and ``SACConfig.fine_tuning`` for episodes of ``horizon``
    steps with ``sac_settings`` (the profile's, then --sac-set) on top; its fields go to
    result["sac_config"]."""
    task = get_task(task_name)
    it = sizes["improve_iterations"]
    c0_all = np.asarray(test_ds.value, np.float64)
    ids = [i for i in pick_policies(c0_all, sizes["improve_policies"]) if c0_all[i] != 0]
    n_envs = sizes["sac_envs"]
    sac = SACConfig.fine_tuning(**{**dict(episode_length=horizon, n_envs=n_envs,
                                          critic_warmup_updates=sizes["sac_critic_warmup"],
                                          updates_per_step=sizes["sac_updates_per_step"],
                                          buffer_size=min(100_000, n_envs * (64 + it))),
                                   **sac_settings})
    result["sac_config"] = {k: (list(v) if isinstance(v, tuple) else v)
                            for k, v in dataclasses.asdict(sac).items()}
    if sac.critic_warmup_updates >= it * sac.updates_per_step:
        log("[paper] note: the critic warm-up covers every SAC update, so the actors stay "
            "as they were")
    return FineTuning(
        task=task, ids=ids, c0=c0_all[ids], policies=index_params(test_pols, np.asarray(ids)),
        horizon=horizon, sac=sac, iterations=it, chunk=min(sizes["sac_chunk"], it),
        episodes=sizes["improve_episodes"],
        episode_length=int(test_ds.meta.get("episode_length") or task.episode_length),
        gamma=float(test_ds.meta.get("gamma") or 0.999))


def lane_training_mvd(finals: dict, last_seed: int, horizon: int, gamma: float
                      ) -> list[float]:
    """Each lane's MVD on the training policies at its final state (the last completed VD
    measurement, ``TrainState.vd``), in ``lane_simulators``' lane order: the guard's floor
    (``finetune.deployment_guard``) where comparable with the guard's ``horizon`` and
    ``gamma`` (``app.improvement.guard_floor``: else 0, and 0 where not yet measured)."""
    out = []
    for fam_lanes, states in finals.values():
        vd = np.asarray(states.vd, np.float64)  # [L, P_train]
        at = {"horizon": states.config.vd.horizon, "gamma": states.config.gamma}
        out += [guard_floor({"mvd": float(vd[i].max()), **at}, horizon, gamma)
                for i, (_, s) in enumerate(fam_lanes) if s < last_seed]
    return out


def lane_error_range(result: dict, lane: str, horizon: int, gamma: float) -> float | None:
    """The spread max(e) - min(e) of a lane's signed errors on the training policies, e =
    ``lanes[lane]["train_sim_value"]`` - ``train_true_value`` (its last evaluation), where
    measured at the guard's ``horizon`` and ``gamma``; else None. Where a policy's error lies
    within the training errors' range, the error of a predicted gain (tuned minus start) is at
    most this spread, so a gain predicted above it is real; the training-MVD floor bounds the
    gain's error only where the errors share a sign (issue 39's alternative guard floor).
    Comparable as ``app.improvement.guard_floor`` judges it (a zero spread reads as None too)."""
    entry = result.get("lanes", {}).get(lane) or {}
    sim, truth = entry.get("train_sim_value"), result.get("train_true_value")
    if sim is None or truth is None:
        return None
    e = np.asarray(sim, np.float64) - np.asarray(truth, np.float64)
    cfg = result.get("train_config", {}).get(entry.get("family")) or {}
    spread = guard_floor({"mvd": float(e.max() - e.min()),
                          "horizon": saved_field(cfg, "vd.horizon"),
                          "gamma": cfg.get("gamma", np.nan)}, horizon, gamma)
    return spread or None  # 0.0: measured elsewhere or not finite


def discordant_pair_floor(train_sim_value, train_true_value) -> float:
    """The largest simulated gain between two training policies that is false in truth: the
    max of s_j - s_i over the pairs (i, j) with s_j > s_i but v_j <= v_i (s, v: [P_train]
    simulated and true values); 0 where the simulator orders every pair right. A floor on a
    predicted gain's error from the simulator's ranking mistakes (issue 39's second
    alternative guard floor, judged offline by ``improvement_summary.py``: rejected)."""
    s = np.asarray(train_sim_value, np.float64)
    v = np.asarray(train_true_value, np.float64)
    if s.ndim != 1 or s.shape != v.shape:
        raise ValueError(f"train_sim_value, train_true_value: expected two [P_train] arrays, "
                         f"got {s.shape}, {v.shape}")
    gain_sim, gain_true = s[None, :] - s[:, None], v[None, :] - v[:, None]
    wrong = (gain_sim > 0) & (gain_true <= 0)
    return float(gain_sim[wrong].max()) if wrong.any() else 0.0


def pair_floor_verdict(result: dict, lane: str, member_gain, margin: float, policy_ids,
                       member_start=None) -> np.ndarray:
    """[P] bool: the guard (``finetune.deployment_guard``) with the lane's
    ``discordant_pair_floor``: every elite member's predicted gain (``member_gain`` [M, P],
    value units, of test policies ``policy_ids`` [P]) above the floor and ``margin`` x |its
    value of the start| (``member_start`` [M, P], recorded as ``guard_member_start``; runs
    before it kept none: then the lane's protocol value ``lanes[lane]["sim_value"]`` [P_test]
    stands in, and the floor dominates the margin where it is large)."""
    entry = result["lanes"][lane]
    floor = discordant_pair_floor(entry["train_sim_value"], result["train_true_value"])
    gain = np.asarray(member_gain, np.float64)
    if member_start is None:
        member_start = np.asarray(entry["sim_value"], np.float64)[np.asarray(policy_ids, int)]
        member_start = np.broadcast_to(member_start, gain.shape)
    return deployment_guard(member_start, np.asarray(member_start) + gain, margin, floor)


def lane_floors(finals: dict, last_seed: int, sims, train_ds, train_pols, ft: FineTuning,
                n_episodes: int = 16) -> list[float]:
    """Each lane's guard floor at the guard's horizon (the real episodes' length,
    ``ft.episode_length``) and gamma: its training MVD where training measured it there
    (``lane_training_mvd``: the GPU profile), else its simulator's MVD on the training
    policies measured now at that horizon (``evaluate_simulator``, keys PRNGKey(50 + lane);
    the CPU profile's training measures 100 steps). sims [L]: ``lane_simulators``'."""
    floors = lane_training_mvd(finals, last_seed, ft.episode_length, ft.gamma)
    for i, floor in enumerate(floors):
        if not floor:
            r = evaluate_simulator(take_lanes(sims, i), train_ds, train_pols,
                                   key=jax.random.PRNGKey(50 + i), n_episodes=n_episodes,
                                   horizon=ft.episode_length, gamma=ft.gamma)
            floors[i] = float(r["metrics"]["mvd"])
    return floors


def lane_simulators(finals: dict, last_seed: int):
    """The simulators of every family's lanes of seeds < ``last_seed``, concatenated.
    finals: {family: (lanes [(method, seed)], TrainState with a lane axis)}.
    -> (lanes, Simulator with a leading lane axis); SystemExit when the families'
    simulators differ in a static setting (they must run in one program)."""
    lanes, sims = [], []
    for fam_lanes, states in finals.values():
        idx = [i for i, (_, s) in enumerate(fam_lanes) if s < last_seed]
        lanes += [fam_lanes[i] for i in idx]
        sims.append(take_lanes(simulator(states), idx))
    statics = {(s.task, s.obs_clip, s.noise_scale, s.n_elites, s.member_mode, s.uncertainty)
               for s in sims}
    if len(statics) != 1:
        raise SystemExit(f"set: the families' simulators differ in {statics}; they must "
                         f"share task, obs_clip, sim_noise and the ensemble's rollout settings "
                         f"to be fine-tuned together")
    return lanes, jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *sims)


def _measure(ft: FineTuning, actors, chosen):
    """The start policies, every lane's fine-tuned ones (actors [L, P, ...]) and the
    snapshots the guard chose (L stacked [P]) measured in the real env from common starts and
    noise draws (``measure_values``' common_groups), C0 alongside.
    -> (returns [G, P, n], per lane ``paired_returns``)"""
    L, P = jax.tree_util.tree_leaves(actors)[0].shape[:2]
    flat = jax.tree_util.tree_map(lambda x: x.reshape((L * P,) + x.shape[2:]), actors)
    groups = [ft.policies, flat, *chosen]
    with_start = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *groups)
    G = 1 + L + len(chosen)
    real = measure_values(ft.task.make_env(), with_start, key=jax.random.PRNGKey(20),
                          n_episodes=ft.episodes, episode_length=ft.episode_length,
                          gamma=ft.gamma, common_groups=G, per_episode=True)
    r = np.asarray(real["returns"], np.float64).reshape(G, P, -1)
    return r, [paired_returns(r[0], r[1 + i]) for i in range(L)]


def _lane_entries(ft: FineTuning, lanes, methods, r, paired, sim_return, accepted,
                  chosen_index):
    """Per lane its improvement entry (I, MPI / API, paired, guarded and snapshot versions);
    per method the lanes' MPI / API lists. -> (entries by "method/seed", per_method,
    guarded per method, snapshots per method)"""
    c0, L = ft.c0, len(lanes)
    c1 = np.stack([pr["c1"] for pr in paired])
    se = np.stack([pr["c1_se"] for pr in paired])
    improvement = {}
    per_method = {m: {k: [] for k in IMPROVE_METRICS} for m in methods}
    guarded_method = {m: {"mpi": [], "api": []} for m in per_method}
    snapshot_method = {m: {"mpi": [], "api": [], "mpi_paired": [], "api_paired": []}
                       for m in per_method}
    for i, (m, s) in enumerate(lanes):
        try:
            imp = improvement_metrics(c0, c1[i])
        except ValueError as err:  # a non-finite real return
            log(f"  {m:<8} seed {s}  no MPI/API: {err}")
            imp = {"I": np.full(len(ft.ids), np.nan), "mpi": None, "api": None}
        per_method[m]["mpi"].append(imp["mpi"])
        per_method[m]["api"].append(imp["api"])
        pr = paired[i]
        entry = improvement[f"{m}/{s}"] = {
            "method": m, "seed": s, "policy_ids": ft.ids, "c0": c0.tolist(),
            "c1": [none_if_nan(x) for x in c1[i]], "c1_se": se[i].tolist(),
            "I": [none_if_nan(x) for x in imp["I"]],
            "sim_return": [none_if_nan(x) for x in sim_return[i]],
            "mpi": imp["mpi"], "api": imp["api"],
            # C0 re-measured on the episodes of C1 (paired), I from the pair
            "paired_episodes": int(r.shape[-1]),
            "c0_paired": pr["c0"].tolist(), "c0_paired_se": pr["c0_se"].tolist(),
            "diff_se": pr["diff_se"].tolist(), "I_paired": pr["I"].tolist(),
            "mpi_paired": pr["mpi"], "api_paired": pr["api"]}
        per_method[m]["mpi_paired"].append(pr["mpi"])
        per_method[m]["api_paired"].append(pr["api"])
        if accepted is not None and imp["mpi"] is not None:
            # a kept start policy earns its C0: I = 0
            dep = improvement_metrics(c0, np.where(accepted[i], c1[i], c0))
            entry.update(guard_accepted=accepted[i].tolist(), I_deployed=dep["I"].tolist(),
                         mpi_deployed=dep["mpi"], api_deployed=dep["api"])
            guarded_method[m]["mpi"].append(dep["mpi"])
            guarded_method[m]["api"].append(dep["api"])
        if chosen_index is not None and imp["mpi"] is not None:
            idx = chosen_index[i]
            c1_snap = paired_returns(r[0], r[1 + L + i])
            dep = improvement_metrics(c0, np.where(idx > 0, c1_snap["c1"], c0))
            i_paired = np.where(idx > 0, c1_snap["I"], 0.0)  # a kept start: I = 0
            entry.update(guard_snapshot=idx.tolist(), I_snapshot=dep["I"].tolist(),
                         mpi_snapshot=dep["mpi"], api_snapshot=dep["api"],
                         I_snapshot_paired=i_paired.tolist())
            snapshot_method[m]["mpi"].append(dep["mpi"])
            snapshot_method[m]["api"].append(dep["api"])
            snapshot_method[m]["mpi_paired"].append(float(i_paired.min()))
            snapshot_method[m]["api_paired"].append(float(i_paired.mean()))
        if imp["mpi"] is not None:
            log(f"  {m:<8} seed {s}  MPI {imp['mpi']:8.3f}  API {imp['api']:8.3f}  "
                f"(C1 - C0 mean {np.mean(c1[i] - c0):.1f}, simulated training return "
                f"{finite_mean(sim_return[i])})")
    return improvement, per_method, guarded_method, snapshot_method


def variant_pool(test_ds, settings: dict):
    """The real states a variant's simulated episodes start from [S, o]: every state of the
    test data for a branched variant (``settings["rollout_length"]``; at most 100,000), its
    episode starts otherwise."""
    if settings.get("rollout_length"):
        return branch_pool(test_ds, max_states=100_000)
    return start_pool(test_ds)


def run_improvement(result: dict, ft: FineTuning, lanes, sims, test_ds, variants, *,
                    settings_of: Callable[[str], dict], ablation_methods,
                    guard_margin: float | None, guard_snapshots: bool,
                    phase: Callable[[str, float], None], save: Callable[[], None],
                    guard_floors: list[float] | None = None,
                    guard_floor_scale: float = 1.0) -> None:
    """Every variant's fine-tuning in the lanes ``lanes`` / ``sims`` (``lane_simulators``):
    the first variant in every lane (MPI / API of Table 2: result["per_seed"],
    ["improvement"]), the others in the lanes of ``ablation_methods`` only; each into
    result["ablation"][variant] (with ``guard_margin``: also "<variant>+guard", with
    ``guard_snapshots`` "<variant>+guard-snapshots"). settings_of(variant): its
    ``scaled_env_options`` settings. ``phase(name, t0)`` records a timing, ``save()`` writes
    the result after each variant. The guard values the real episodes' length
    (``ft.episode_length``: the real gain is measured there), whatever SAC's episodes were.
    ``guard_floors``: per lane the training MVD in value units at that horizon (``lane_floors``;
    None: no floor); the guard's floor is ``guard_floor_scale`` x it. Each guarded lane records
    "guard_training_mvd" and "guard_floor" (what the guard used)."""
    check_floor_scale(guard_floor_scale)
    floors = None if guard_floors is None else [guard_floor_scale * f for f in guard_floors]
    keys = jnp.stack([jax.random.split(jax.random.fold_in(jax.random.PRNGKey(10 + s),
                                                          METHODS.index(m)), len(ft.ids))
                      for m, s in lanes])
    u_rows = real_rows(test_ds)
    methods = [m for m in result["per_seed"] if m in METHODS]
    result["ablation"] = {}
    for vi, variant in enumerate(variants):
        t0 = time.perf_counter()
        # the first variant runs in every lane (Table 2), the others in the lanes of
        # --ablation-methods only
        v_idx = [i for i, (m, _) in enumerate(lanes) if vi == 0 or m in ablation_methods]
        if not v_idx:
            continue
        v_lanes, v_sims = [lanes[i] for i in v_idx], take_lanes(sims, v_idx)
        settings = settings_of(variant)
        pool = variant_pool(test_ds, settings)

        def env_options(sim, settings=settings):
            return scaled_env_options(sim, *u_rows, **settings)

        log(f"[paper] improvement ({variant}: {settings}): SAC x {ft.iterations} iterations "
            f"({ft.sac.n_envs} envs, {ft.sac.updates_per_step} update(s) per iteration, critic "
            f"warm-up {ft.sac.critic_warmup_updates} updates, episodes of {ft.horizon} "
            f"steps) for {len(ft.ids)} test policies in {len(v_lanes)} simulators "
            f"({', '.join(f'{m}/{s}' for m, s in v_lanes)}) as one program")
        actors, sim_return = improve_in_lanes(
            v_sims, ft.task, pool, ft.policies, keys[jnp.asarray(v_idx)], ft.sac,
            n_iterations=ft.iterations, chunk=ft.chunk, env_options=env_options,
            snapshots=guard_snapshots, log=lambda m: log(f"[paper]   {m}"))
        snaps = None
        if guard_snapshots:  # [C, L, P, ...]; the final actors are the last
            snaps, actors = actors, jax.tree_util.tree_map(lambda x: x[-1], actors)
        tag = "" if vi == 0 else f"[{variant}]"
        phase(f"improve_sac{tag}", t0)
        accepted, chosen_index, chosen, gains, starts_v = None, None, [], None, None
        if guard_margin is not None:  # each simulator's own verdict per policy
            t0 = time.perf_counter()
            accepted, chosen_index, chosen, gains, starts_v = guard_lanes(
                v_sims, ft.policies, actors, snaps, ft.task, start_pool(test_ds),
                margin=guard_margin, horizon=ft.episode_length, gamma=ft.gamma,
                floors=None if floors is None else [floors[i] for i in v_idx])
            phase(f"improve_guard{tag}", t0)
        t0 = time.perf_counter()
        r, paired = _measure(ft, actors, chosen)
        phase(f"improve_measure{tag}", t0)
        improvement, per_method, guarded, snapshot = _lane_entries(
            ft, v_lanes, methods, r, paired, sim_return, accepted, chosen_index)
        if accepted is not None:
            for j, (i, (m, s)) in enumerate(zip(v_idx, v_lanes, strict=True)):
                entry = improvement[f"{m}/{s}"]
                # [M][P]: what each elite member predicted, and its value of the start (the
                # margin's scale); the guard read these, and so can a rule judged offline
                entry["guard_member_gain"] = np.asarray(gains[j], np.float64).tolist()
                entry["guard_member_start"] = np.asarray(starts_v[j], np.float64).tolist()
                if floors is not None:
                    entry["guard_training_mvd"] = guard_floors[i]
                    entry["guard_floor"] = floors[i]
                # the range floor's verdict on the same members' values (recorded, not used)
                spread = lane_error_range(result, f"{m}/{s}", ft.episode_length, ft.gamma)
                if spread is not None:
                    entry["guard_floor_range"] = spread
                    entry["guard_accepted_range"] = deployment_guard(
                        starts_v[j], starts_v[j] + gains[j], guard_margin, spread).tolist()
        if vi == 0:
            for m in per_method:
                for k in IMPROVE_METRICS:
                    result["per_seed"][m].setdefault(k, [])
                    result["per_seed"][m][k] += per_method[m][k]
            result["improvement"] = improvement
            result["improve_variant"] = variant
        result["ablation"][variant] = {"settings": settings, "lanes": improvement,
                                       "methods": method_means(per_method)}
        if accepted is not None:
            result["ablation"][f"{variant}+guard"] = {
                "settings": {**settings, "guard_margin": guard_margin,
                             "guard_horizon": ft.episode_length,
                             "guard_floor_scale": guard_floor_scale if floors else None,
                             "guard_floor": ("training MVD per lane" if guard_floors
                                             else None)},
                "methods": method_means(guarded)}
        if chosen_index is not None:
            result["ablation"][f"{variant}+guard-snapshots"] = {
                "settings": {**settings, "guard_margin": guard_margin,
                             "snapshot_every": ft.chunk},
                "methods": method_means(snapshot)}
        save()


def control_entry(res: dict, ids: list[int], c0_data: np.ndarray, n_seeds: int,
                  train_return: np.ndarray) -> dict:
    """The JSON 'control' entry from ``measure_improvement``'s dict over R seeds x P policies
    (seed-major [R * P] lists c0, c0_se, c1, c1_se, diff_se): per seed MPI/API and per-policy
    C0/C1 with standard errors ([R][P]); their mean and sample std over seeds. c0_data [P]:
    the data's true returns; train_return [R * P, ...]: SAC's training returns."""
    P = len(ids)
    shape = lambda k: np.asarray(res[k], np.float64).reshape(n_seeds, P)
    c0, c0_se, c1, c1_se = shape("c0"), shape("c0_se"), shape("c1"), shape("c1_se")
    diff_se = shape("diff_se")  # measure_improvement measures C0 and C1 paired
    per = [improvement_metrics(c0[r], c1[r]) for r in range(n_seeds)]
    mpi, api = [p["mpi"] for p in per], [p["api"] for p in per]
    std = lambda x: float(np.std(x, ddof=1)) if len(x) > 1 else None
    return {"policy_ids": ids, "seeds": n_seeds, "c0_data": np.asarray(c0_data).tolist(),
            "c0": c0.tolist(), "c0_se": c0_se.tolist(), "c1": c1.tolist(),
            "c1_se": c1_se.tolist(), "diff_se": diff_se.tolist(), "paired": True,
            "I": [p["I"].tolist() for p in per],
            "train_return": [none_if_nan(x) for x in np.asarray(train_return).reshape(-1)],
            "mpi_per_seed": mpi, "api_per_seed": api, "mpi": float(np.mean(mpi)),
            "api": float(np.mean(api)), "mpi_std": std(mpi), "api_std": std(api)}


def _seeds_tiled(ft: FineTuning, n_seeds: int):
    """ft.policies repeated ``n_seeds`` times, seed-major [n_seeds * P, ...]: one SAC run per
    (seed, policy) in one vmapped program."""
    return jax.tree_util.tree_map(lambda x: jnp.concatenate([x] * n_seeds), ft.policies)


def _last_chunk_returns(ft: FineTuning, metrics) -> np.ndarray:
    """SAC's training-episode returns in the last ``ft.chunk`` iterations of ``metrics``
    [R * P, iterations, ...] (``episode_returns``)."""
    return np.asarray(episode_returns(
        jax.tree_util.tree_map(lambda x: x[:, -ft.chunk:], metrics)))


def run_control(result: dict, ft: FineTuning, n_seeds: int,
                phase: Callable[[str, float], None]) -> None:
    """The same fine-tuning (policies, budget, SAC settings) in the real env, ``n_seeds``
    times, with real returns before and after (``improve_in_real_env``): result["control"],
    the ceiling of improvement for that budget; ``phase("control", t0)`` its timing."""
    t0 = time.perf_counter()
    log(f"[paper] control: the same SAC x {ft.iterations} iterations in the real env for "
        f"{len(ft.ids)} test policies x {n_seeds} seed(s)")
    _, ctrl_metrics, ctrl = improve_in_real_env(
        ft.task, _seeds_tiled(ft, n_seeds), jax.random.PRNGKey(30), ft.sac,
        n_iterations=ft.iterations, n_episodes=ft.episodes, episode_length=ft.episode_length,
        gamma=ft.gamma, chunk_iterations=ft.chunk)
    result["control"] = control_entry(ctrl, ft.ids, ft.c0, n_seeds,
                                      _last_chunk_returns(ft, ctrl_metrics))
    phase("control", t0)
    cc = result["control"]
    log(f"[paper] control (real env): MPI {fmt_ms(cc['mpi'], cc['mpi_std'])}  API "
        f"{fmt_ms(cc['api'], cc['api_std'])} over {n_seeds} seed(s)")


def run_oracle_improvement(result: dict, ft: FineTuning, test_ds, variant: str, settings: dict,
                           n_seeds: int, phase: Callable[[str, float], None]) -> None:
    """The same fine-tuning inside the oracle simulator (``evaluate.oracle``: the real physics
    stepped from each observation) through the simulated env of ``variant`` (its rollouts and
    start states; the oracle has no ensemble, so a penalty or stop on u is a no-op), ``n_seeds``
    times, measured like the lanes: result["oracle_improvement"]. Between the real-env control
    and the learned simulators it splits a gap in two: what the simulated env's set-up costs
    (branches from the data's states, the task's reward and termination functions) and what
    the learned model's errors cost. ``phase("improve_oracle", t0)`` its timing."""
    t0 = time.perf_counter()
    opts = ({"rollout_length": int(settings["rollout_length"])}
            if settings.get("rollout_length") else {})
    pool = variant_pool(test_ds, settings)
    log(f"[paper] oracle improvement ({variant}, {opts or 'whole episodes'}): the same SAC x "
        f"{ft.iterations} iterations inside the real dynamics stepped from observations, for "
        f"{len(ft.ids)} test policies x {n_seeds} seed(s)")
    P = len(ft.ids)
    actors, metrics = improve_policies(
        oracle_dynamics(ft.task), ft.task, pool, _seeds_tiled(ft, n_seeds),
        jax.random.PRNGKey(50), ft.sac, n_iterations=ft.iterations,
        chunk_iterations=ft.chunk, env_options=opts)
    actors = jax.tree_util.tree_map(lambda x: x.reshape((n_seeds, P) + x.shape[1:]), actors)
    r, paired = _measure(ft, actors, [])
    sim_return = _last_chunk_returns(ft, metrics).reshape(n_seeds, P)
    per = []
    for s, pr in enumerate(paired):
        per.append({"seed": s, "c0_paired": pr["c0"].tolist(), "c1": pr["c1"].tolist(),
                    "c1_se": pr["c1_se"].tolist(), "diff_se": pr["diff_se"].tolist(),
                    "I_paired": pr["I"].tolist(), "mpi_paired": pr["mpi"],
                    "api_paired": pr["api"],
                    "sim_return": [none_if_nan(x) for x in sim_return[s]]})
    result["oracle_improvement"] = {
        "variant": variant, "env_options": opts, "policy_ids": ft.ids, "c0": ft.c0.tolist(),
        "seeds": n_seeds, "paired_episodes": int(r.shape[-1]), "per_seed": per,
        "mpi": float(np.mean([p["mpi_paired"] for p in per])),
        "api": float(np.mean([p["api_paired"] for p in per]))}
    phase("improve_oracle", t0)
    oi = result["oracle_improvement"]
    log(f"[paper] oracle improvement: MPI {oi['mpi']:+.3f}  API {oi['api']:+.3f} over "
        f"{n_seeds} seed(s)")
