"""B-Pref report over a folder of runs: normalised returns, IQM / median / mean / optimality gap with 95% stratified
bootstrap confidence intervals (rliable), a Markdown file with the tables and PNG plots. Docs: docs/experiments.md

    python experiments/report.py runs/mini-bpref          # writes runs/mini-bpref/report/report.md and the PNGs

A run is any folder below the root with a config.json (made by pebble.py, rime.py, qpa.py or prefppo.py, by the
grid runner or by hand). Normalised return of a run = its final evaluation return (Meta-World: success rate, as in
the paper) / the mean of the same over the finished --ground-truth-reward runs of the same algorithm on the same
task. A run is finished when its eval.csv reaches its total steps; config.json and eval.csv are all the tables need
(the reward alignment needs final_model.pt too), so `python experiments/report.py docs/tasks/data/sweep-into` works.
"""

import csv
import functools
import importlib
import inspect
import json
import os
import shlex
import sys
from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import tyro

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from grid import read_eval, run_state  # noqa: E402
from samplers import SAMPLERS, SCHEDULES  # noqa: E402
from sim_teacher import TEACHERS, make_teacher  # noqa: E402

SETTING = ("algorithm", "task", "teacher", "budget", "sampler", "schedule")
METRICS = ("iqm", "median", "mean", "optimality_gap")
GROUND_TRUTH = "ground-truth"
TEACHER_OVERRIDES = ("teacher_beta", "teacher_gamma", "teacher_eps_mistake", "teacher_eps_skip", "teacher_eps_equal",
                     "teacher_bias")
# Config fields that may differ between the seeds of one setting
PER_RUN_FIELDS = {"seed", "output_dir", "resume", "checkpoint_every", "cuda", "track", "wandb_project_name",
                  "capture_video", "exp_name", "labels_from", "reference_command", "started_by_hand"}


@dataclass
class Args:
    root: tyro.conf.Positional[str | None] = None
    """folder of runs (searched recursively for folders with a config.json)"""
    docs: bool = False
    """instead of a report, rewrite every generated block of README.md and docs/ from the runs kept under docs/"""
    out: str | None = None
    """where report.md, runs.csv, aggregates.csv and the PNGs go (default: ROOT/report)"""
    reps: int = 10000
    """bootstrap replications of rliable's stratified bootstrap"""
    seed: int = 0
    """random seed of the bootstrap"""
    alignment_runs: int = 1
    """reward-alignment plots per algorithm and task (0 = none): finished oracle runs first, then the others"""
    parity: str | None = None
    """also write the side-by-side of ours and the reference code (settings run by both) to this Markdown file"""
    compare: tuple[str, str] | None = None
    """NEW BASE: also set two algorithms side by side on every setting both ran (e.g. rime pebble): difference
    NEW - BASE with its CI, curves in one plot, RIME's discriminator; written to OUT/compare_NEW_BASE.md"""
    against_ground_truth: bool = False
    """also set each preference setting beside its algorithm's ground-truth runs on its task (difference with its
    CI, Welch's p, a verdict; Meta-World by success rate, then return): OUT/against_ground_truth.md"""


@dataclass
class Run:
    path: Path
    config: dict
    rows: list[dict]
    state: str
    """finished, resumable, partial or new (grid.run_state)"""
    detail: str
    setting: tuple
    """(algorithm, task, teacher, budget, sampler, schedule)"""
    metric: str
    """episode_return, or success_rate on Meta-World"""
    score: float | None = None
    """final evaluation metric (finished runs only)"""
    normalized: float | None = None

    @property
    def algorithm(self) -> str:
        return self.setting[0]

    @property
    def is_ground_truth(self) -> bool:
        return self.setting[2] == GROUND_TRUTH


@functools.cache
def is_metaworld(env_id: str) -> bool:
    import metaworld

    return f"{env_id.removesuffix('-v3')}-v3" in metaworld.ALL_V3_ENVIRONMENTS


def setting_of(config: dict) -> tuple:
    """(algorithm, task, teacher, budget, sampler, schedule) of a run from its config.json; a teacher's overrides
    (--teacher-beta ... that differ from the named teacher's values) are part of its name, and ground-truth runs
    have no teacher, budget, sampler or schedule."""
    algorithm = ("prefppo" if "num_envs" in config else "rime" if "rime_alpha" in config
                 else "qpa" if "her_ratio" in config else "pebble")
    if config.get("implementation", "ours") != "ours":  # benchmarks/reference/run.py: its own algorithm's row
        algorithm = f"{config['implementation']}-{algorithm}"
    task = config["env_id"].removesuffix("-v3") if is_metaworld(config["env_id"]) else config["env_id"]
    if config.get("ground_truth_reward"):
        return algorithm, task, GROUND_TRUTH, "-", "-", "-"
    preset = make_teacher(config["teacher"])  # a saved value equal to the teacher's own is no override
    overrides = [f"{name.removeprefix('teacher_')}={config[name]}" for name in TEACHER_OVERRIDES
                 if config.get(name) is not None and config[name] != getattr(preset, name.removeprefix("teacher_"))]
    if config.get("label_smoothing"):  # another loss on the same teacher's labels
        overrides.append(f"label_smoothing={config['label_smoothing']}")
    teacher = config["teacher"] + (f"({', '.join(overrides)})" if overrides else "")
    budget = f"{config['max_feedback']}/{config['feedback_per_session']}"
    return algorithm, task, teacher, budget, config["sampler"], config["schedule"]


def kept_run_end(config: dict) -> float:
    """The step a run kept without its final_model.pt (the data committed in docs/) has evaluated to once finished:
    its total steps; the reference PrefPPO's rows are training episodes, whose last wave ends in the last rollout."""
    if config.get("episode_returns") == "training":
        return config["total_timesteps"] - config["num_envs"] * config["num_steps"]
    return config.get("total_timesteps", float("inf"))


def find_runs(root: Path, out: Path) -> list[Run]:
    """Every folder below root with a config.json, except hidden ones (the grid's .aside/) and the report's, where
    the report goes below root (a report beside the kept runs, as docs/parity/ beside docs/parity/data, reads them)."""
    runs = []
    for config_path in sorted(root.rglob("config.json")):
        path = config_path.parent
        relative = path.relative_to(root).parts
        in_report = root in out.parents and (path == out or out in path.parents)
        if any(part.startswith(".") for part in relative) or in_report:
            continue
        try:
            config = json.loads(config_path.read_text())
            setting = setting_of(config)
        except (OSError, ValueError, KeyError) as error:
            print(f"skipped {path}: unreadable config.json ({error})", file=sys.stderr)
            continue
        state, detail = run_state(path)
        metric = "success_rate" if is_metaworld(config["env_id"]) else "episode_return"
        rows = read_eval(path)
        if state != "finished" and rows and rows[-1]["step"] >= kept_run_end(config):
            state = "finished"
        run = Run(path, config, rows, state, detail, setting, metric)
        if state == "finished":
            run.score = rows[-1][metric]
        runs.append(run)
    return runs


def normalize(runs: list[Run]) -> tuple[dict, list[str]]:
    """Divides each finished run's score by the mean score of its algorithm's finished ground-truth runs on the task.
    Returns the baselines {(algorithm, task): scores} and one line per (algorithm, task) that cannot be normalised:
    no finished ground-truth run, or a mean that is not positive. Nothing is divided by a missing baseline."""
    baselines = defaultdict(list)
    for run in runs:
        if run.is_ground_truth and run.score is not None:
            baselines[run.setting[:2]].append(run.score)
    problems = {}
    for run in runs:
        if run.score is None:
            continue
        key = run.setting[:2]
        if not baselines.get(key):
            unfinished = sum(r.is_ground_truth and r.setting[:2] == key for r in runs)
            problems[key] = (f"{key[0]} on {key[1]}: no finished ground-truth run (--ground-truth-reward) to normalise "
                             f"by ({unfinished} unfinished); its runs are reported unnormalised")
        elif np.mean(baselines[key]) <= 0:
            problems[key] = (f"{key[0]} on {key[1]}: the ground-truth runs' mean final {run.metric} is "
                             f"{np.mean(baselines[key]):.4g}, not positive, so it cannot normalise; its runs are "
                             "reported unnormalised")
        else:
            run.normalized = run.score / float(np.mean(baselines[key]))
    return dict(baselines), list(problems.values())


def aggregate(scores: dict[str, np.ndarray], reps: int, seed: int) -> dict[str, dict]:
    """IQM, median, mean and optimality gap of each (runs x tasks) score matrix, with 95% stratified bootstrap
    confidence intervals (runs resampled within each task): rliable, as in the paper."""
    from rliable import library, metrics

    def all_metrics(x):
        return np.array([metrics.aggregate_iqm(x), metrics.aggregate_median(x), metrics.aggregate_mean(x),
                         metrics.aggregate_optimality_gap(x)])

    np.random.seed(seed)  # rliable's StratifiedBootstrap draws from numpy's global generator (random_state unused)
    points, intervals = library.get_interval_estimates(scores, all_metrics, reps=reps)
    return {key: {name: (float(points[key][i]), float(intervals[key][0, i]), float(intervals[key][1, i]))
                  for i, name in enumerate(METRICS)} for key in scores}


def teacher_order(name: str) -> tuple:
    base = name.split("(")[0]
    return (list(TEACHERS).index(base) if base in TEACHERS else len(TEACHERS), name)


def axis_order(column: str):
    """The paper's order along a figure's axis: teachers, samplers and schedules as listed in their modules."""
    if column == "teacher":
        return teacher_order
    names = {"sampler": SAMPLERS, "schedule": SCHEDULES}.get(column, ())
    return lambda value: (names.index(value) if value in names else len(names), str(value))


def sort_key(setting: tuple) -> tuple:
    return setting[:2] + (teacher_order(setting[2]),) + setting[3:]


def setting_aggregates(runs: list[Run], reps: int, seed: int) -> list[dict]:
    """One row per setting of preference runs with at least one normalised run: the aggregates on one task."""
    groups = defaultdict(list)
    for run in runs:
        if run.normalized is not None and not run.is_ground_truth:
            groups[run.setting].append(run)
    if not groups:
        return []
    keys = sorted(groups, key=sort_key)
    results = aggregate({"|".join(k): np.array([[r.normalized] for r in groups[k]]) for k in keys}, reps, seed)
    rows = []
    for key in keys:
        scores = np.array([r.score for r in groups[key]])
        rows.append({**dict(zip(SETTING, key)), "runs": len(groups[key]), **results["|".join(key)],
                     "score_mean": float(scores.mean()), "score_std": float(scores.std()),
                     "metric": groups[key][0].metric})
    return rows


def across_task_aggregates(runs: list[Run], reps: int, seed: int) -> tuple[list[dict], list[str]]:
    """Settings run on several tasks: aggregates over all tasks together (stratified: runs resampled within each
    task). rliable needs a (runs x tasks) matrix, so every task must have as many normalised runs."""
    groups = defaultdict(lambda: defaultdict(list))
    for run in runs:
        if run.normalized is not None and not run.is_ground_truth:
            groups[run.setting[:1] + run.setting[2:]][run.setting[1]].append(run.normalized)
    matrices, notes = {}, []
    for key, per_task in groups.items():
        if len(per_task) < 2:
            continue
        counts = {task: len(scores) for task, scores in per_task.items()}
        if len(set(counts.values())) > 1:
            notes.append(f"{' '.join(key)}: not aggregated across tasks, the tasks have different numbers of "
                         f"normalised runs ({', '.join(f'{t}: {n}' for t, n in sorted(counts.items()))})")
            continue
        matrices[key] = np.array([per_task[task] for task in sorted(per_task)]).T
    if not matrices:
        return [], notes
    keys = sorted(matrices, key=lambda k: (k[0], teacher_order(k[1])) + k[2:])
    results = aggregate({"|".join(k): matrices[k] for k in keys}, reps, seed)
    rows = [{"algorithm": k[0], "tasks": len(matrices[k][0]), "teacher": k[1], "budget": k[2], "sampler": k[3],
             "schedule": k[4], "runs": matrices[k].size, **results["|".join(k)]} for k in keys]
    return rows, notes


def mixed_settings(runs: list[Run]) -> list[str]:
    """Settings whose runs differ in a configuration field other than the seed (e.g. two grids with other step
    counts in one folder): their aggregates would mix experiments."""
    groups, notes = defaultdict(list), []
    for run in runs:
        groups[run.setting].append(run.config)
    for setting, configs in sorted(groups.items(), key=lambda item: sort_key(item[0])):
        differing = sorted(k for k in set().union(*configs) if k not in PER_RUN_FIELDS
                           and len({json.dumps(c.get(k)) for c in configs}) > 1)
        absent = [k for k in differing if len({json.dumps(c[k]) for c in configs if k in c}) == 1]
        if differing:
            notes.append(f"{' / '.join(setting)}: runs differ in {', '.join(differing)}"
                         + (f" ({', '.join(absent)}: absent from some configurations, written by an older script)"
                            if absent else ""))
    return notes


# ---------------------------------------------------------------- plots


def plt_figure(rows: int, cols: int, width: float, height: float):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt, *plt.subplots(rows, cols, figsize=(width, height), squeeze=False)


def bar_figures(rows: list[dict], x: str, hue: str, fixed: tuple[str, ...], out: Path, prefix: str,
                title: str) -> list[Path]:
    """One PNG per value of the `fixed` columns: IQM bars with their 95% CIs, `x` along the axis and one bar per
    `hue` value; one panel per combination of the other setting columns. The paper's Figure 2 is x=teacher,
    hue=algorithm, fixed=task."""
    panels_by = [c for c in SETTING if c not in (x, hue, *fixed)]
    figures = defaultdict(lambda: defaultdict(dict))
    for row in rows:
        figures[tuple(row[c] for c in fixed)][tuple(row[c] for c in panels_by)][(row[x], row[hue])] = row["iqm"]
    paths = []
    for fixed_values, panels in sorted(figures.items()):
        order = axis_order(x)
        widest = max(len({k[0] for k in cells}) for cells in panels.values())
        hues = sorted({k[1] for cells in panels.values() for k in cells})
        plt, fig, axes = plt_figure(len(panels), 1, max(6.0, 1.1 * widest * max(1, len(hues)) ** 0.5 + 2),
                                    2.8 * len(panels) + 0.6)
        width = 0.8 / len(hues)
        for ax, (panel, cells) in zip(axes[:, 0], sorted(panels.items())):
            xs = sorted({k[0] for k in cells}, key=order)
            for j, hue_value in enumerate(hues):
                present = [(i, cells[(x_value, hue_value)]) for i, x_value in enumerate(xs)
                           if (x_value, hue_value) in cells]
                if not present:
                    continue
                positions = [i - 0.4 + width * (j + 0.5) for i, _ in present]
                points = np.array([p for _, (p, _, _) in present])
                errors = np.array([[p - low, high - p] for _, (p, low, high) in present]).T
                ax.bar(positions, points, width, yerr=errors, capsize=3, label=str(hue_value), color=f"C{j}")
            ax.axhline(1.0, color="gray", linestyle="--", linewidth=0.8)
            ax.set_xticks(range(len(xs)), xs)
            ax.set_ylabel("IQM normalised return")
            ax.set_title(", ".join(f"{c} {v}" for c, v in zip(panels_by, panel)), fontsize=9)
            ax.legend(fontsize=8, title=hue)
        fig.suptitle(f"{title}: {' '.join(fixed_values)} (bars: IQM, whiskers: 95% CI)", fontsize=10)
        fig.tight_layout()
        path = out / f"{prefix}_{'_'.join(str(v) for v in fixed_values)}.png".replace("/", "-")
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def curve_figures(runs: list[Run], out: Path) -> list[Path]:
    """Per algorithm and task: evaluation return (or success rate) against environment steps, mean over the finished
    runs of each setting and a band of one standard deviation; the ground-truth runs dashed."""
    tasks = defaultdict(lambda: defaultdict(list))
    for run in runs:
        if run.state == "finished":
            tasks[run.setting[:2]][run.setting].append(run)
    paths = []
    for (algorithm, task), settings in sorted(tasks.items()):
        panel_keys = sorted({s[3:] for s in settings if s[2] != GROUND_TRUTH}) or [("-", "-", "-")]
        plt, fig, axes = plt_figure(len(panel_keys), 1, 7.5, 3.4 * len(panel_keys) + 0.4)
        for ax, panel in zip(axes[:, 0], panel_keys):
            for setting in sorted(settings, key=sort_key):
                if setting[3:] != panel and setting[2] != GROUND_TRUTH:
                    continue
                group = settings[setting]
                steps = sorted(set.intersection(*[{row["step"] for row in r.rows} for r in group]))
                values = np.array([[{row["step"]: row[r.metric] for row in r.rows}[s] for s in steps] for r in group])
                mean, std = values.mean(0), values.std(0)
                # a teacher keeps its colour in every panel and figure; the ground-truth runs are black and dashed
                truth = setting[2] == GROUND_TRUTH
                color, style = ("black", "--") if truth else (f"C{teacher_order(setting[2])[0]}", "-")
                ax.plot(steps, mean, label=f"{setting[2]} ({len(group)})", color=color, linestyle=style)
                ax.fill_between(steps, mean - std, mean + std, alpha=0.15, color=color)
            ax.set_xlabel("environment steps")
            ax.set_ylabel(group[0].metric.replace("_", " "))
            ax.set_title(f"budget {panel[0]}, sampler {panel[1]}, schedule {panel[2]}", fontsize=9)
            ax.legend(fontsize=8, title="teacher (runs)")
        fig.suptitle(f"{algorithm} on {task}: mean and one standard deviation over seeds", fontsize=10)
        fig.tight_layout()
        path = out / f"curves_{algorithm}_{task}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def build(cls, obs_dim: int, action_dim: int, config: dict, **named):
    """cls(obs_dim, action_dim, ...) with its other constructor arguments from `named` or, by name, config.json."""
    arguments = list(inspect.signature(cls).parameters)[2:]
    return cls(obs_dim, action_dim, **{a: named[a] if a in named else config[a] for a in arguments
                                       if a in named or a in config})


def load_final_model(run: Run) -> tuple:
    """(the run's script as a module, an evaluation environment made as the script makes it, the final actor, the
    reward ensemble, the observation normaliser or None): final_model.pt in networks of the sizes in config.json."""
    import torch

    module, config = importlib.import_module(run.algorithm), run.config
    env, _ = module.make_env(config["env_id"])
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    saved = torch.load(run.path / "final_model.pt", map_location="cpu", weights_only=True)
    actor = build(module.Actor, obs_dim, action_dim, config)
    actor.load_state_dict(saved["actor"])
    reward_model = build(module.RewardEnsemble, obs_dim, action_dim, config, size=config["reward_ensemble_size"])
    # a run of an older script saved no input normaliser: its inputs were raw (the identity)
    raw_inputs = {key: value for key, value in reward_model.state_dict().items() if key.startswith("input_")}
    reward_model.load_state_dict(raw_inputs | saved["reward_model"])
    obs_stats = None
    if "obs_mean" in saved:  # prefppo: the policy's observation normaliser (the reward model's is in its buffers)
        obs_stats = module.RunningMeanStd(saved["obs_mean"], saved["obs_var"])
    return module, env, actor, reward_model, obs_stats


def final_evaluation_seeds(module, run: Run) -> list[int]:
    """The reset seeds of the run's last evaluation: the scripts number evaluation episodes over the whole run."""
    first = (len(read_eval(run.path)) - 1) * run.config["eval_episodes"]
    return [module.episode_seed(run.config["seed"], module.EVAL_STREAM, first + j)
            for j in range(run.config["eval_episodes"])]


def reward_alignment(run: Run) -> tuple[np.ndarray, np.ndarray]:
    """True and learned rewards (the ensemble mean) at each step of the first episode of the run's last evaluation,
    replayed with the script's own evaluate() on the final networks (its actions and reward inputs)."""
    import gymnasium as gym
    import torch

    module, env, actor, reward_model, obs_stats = load_final_model(run)
    true_rewards, learned_rewards = [], []

    class RecordTrueReward(gym.Wrapper):
        def step(self, action):
            result = self.env.step(action)
            true_rewards.append(float(result[1]))
            return result

    def recorded_reward_model(obs_action):
        rewards = reward_model(obs_action)  # evaluate() asks for the episode's steps in one batch
        learned_rewards.extend(rewards.mean(0).flatten().tolist())
        return rewards

    policy = module.mean_policy(actor, "cpu") if obs_stats is None else module.mean_policy(actor, obs_stats, "cpu")
    with torch.no_grad():
        module.evaluate(policy, recorded_reward_model, RecordTrueReward(env), final_evaluation_seeds(module, run)[:1],
                        "cpu")
    env.close()
    return np.array(true_rewards), np.array(learned_rewards)


def alignment_figure(run: Run, root: Path, out: Path) -> tuple[Path, float]:
    """The paper's reward analysis: learned and true reward along one episode (two scales: the learned reward is
    tanh-bounded), and learned against true per step with their Pearson correlation."""
    true_rewards, learned_rewards = reward_alignment(run)
    correlation = float("nan")
    if true_rewards.std() > 0 and learned_rewards.std() > 0:
        correlation = float(np.corrcoef(true_rewards, learned_rewards)[0, 1])
    plt, fig, axes = plt_figure(1, 2, 11, 3.6)
    series, scatter = axes[0]
    series.plot(true_rewards, color="tab:red", label="true reward")
    series.set_xlabel("step of the episode")
    series.set_ylabel("true reward", color="tab:red")
    twin = series.twinx()
    twin.plot(learned_rewards, color="tab:green", label="learned reward")
    twin.set_ylabel("learned reward (ensemble mean)", color="tab:green")
    scatter.scatter(true_rewards, learned_rewards, s=4, alpha=0.5)
    scatter.set_xlabel("true reward")
    scatter.set_ylabel("learned reward")
    scatter.set_title(f"Pearson r = {correlation:.3f}", fontsize=9)
    fig.suptitle(f"reward alignment: {run.path.relative_to(root)}", fontsize=9)
    fig.tight_layout()
    path = out / f"alignment_{run.path.name}.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path, correlation


# ---------------------------------------------------------------- parity with the reference code


REFERENCE_PREFIX = "reference-"


def finished_by_setting(runs: list[Run]) -> dict[tuple, list[Run]]:
    groups = defaultdict(list)
    for run in runs:
        if run.state == "finished":
            groups[run.setting].append(run)
    return groups


def parity_pairs(runs: list[Run]) -> list[tuple[tuple, list[Run], list[Run]]]:
    """(our setting, our finished runs, the reference's finished runs) for every setting both implementations ran.
    Where the reference's rows are training episodes (its PrefPPO evaluates no policy), both arms' runs come back
    with training-episode rows (training_rows), so that both are measured alike."""
    groups = finished_by_setting(runs)
    pairs = []
    for setting in sorted(groups, key=sort_key):
        twin = (REFERENCE_PREFIX + setting[0], *setting[1:])
        if not setting[0].startswith(REFERENCE_PREFIX) and twin in groups:
            ours, reference = groups[setting], groups[twin]
            if any(on_training_episodes(run) for run in reference):
                ours = [replace(run, rows=training_rows(run)) for run in ours]
                ours = [replace(run, score=run.rows[-1][run.metric]) for run in ours]
            pairs.append((setting, ours, reference))
    return pairs


def by_return(runs: list[Run]) -> list[Run]:
    """Meta-World runs measured by their return instead of their success rate."""
    return [replace(run, metric="episode_return", score=run.rows[-1]["episode_return"]) for run in runs]


def on_training_episodes(run: Run) -> bool:
    return run.config.get("episode_returns") == "training"


def training_rows(run: Run) -> list[dict]:
    """Our run's training episodes as the reference PrefPPO's rows (benchmarks/reference/run.py): one per step at which
    episodes ended (TensorBoard's charts/episodic_return), their mean true return; the last row keeps the run's wall
    time and final reward correlation."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    # one events file per process: a resumed run's file logs again the steps after its checkpoint, which replace
    # those of the files written before it (in the order of their first events: a checkout's files share one mtime)
    files = []
    for path in run.path.glob("events.out.tfevents.*"):
        events = EventAccumulator(str(path), size_guidance={"scalars": 0})
        events.Reload()
        files.append(events)
    scalars = []
    for events in sorted(files, key=lambda events: events.FirstEventTimestamp()):
        if "charts/episodic_return" in events.Tags()["scalars"]:
            new = [(event.step, event.value) for event in events.Scalars("charts/episodic_return")]
            scalars = [(step, value) for step, value in scalars if step < new[0][0]] + new
    waves = defaultdict(list)
    for step, value in scalars:
        waves[step].append(value)
    rows = [{"step": step, run.metric: float(np.mean(values)), "wall_time": float("nan"),
             "reward_correlation": float("nan")} for step, values in sorted(waves.items())]
    rows[-1] |= {key: run.rows[-1][key] for key in ("wall_time", "reward_correlation")}
    return rows


def difference_ci(ours: np.ndarray, reference: np.ndarray, reps: int, seed: int) -> tuple[float, float, float]:
    """Mean of ours - mean of the reference, with a 95% percentile bootstrap CI (seeds resampled within each arm)."""
    rng = np.random.default_rng(seed)
    draws = (rng.choice(ours, (reps, len(ours))).mean(1) - rng.choice(reference, (reps, len(reference))).mean(1))
    return float(ours.mean() - reference.mean()), *map(float, np.percentile(draws, [2.5, 97.5]))


def welch_p(ours: np.ndarray, reference: np.ndarray) -> float:
    """Two-sided p-value of Welch's t-test on the final returns (nan with fewer than 2 runs a side)."""
    from scipy import stats

    if min(len(ours), len(reference)) < 2:
        return float("nan")
    return float(stats.ttest_ind(ours, reference, equal_var=False).pvalue)


def curve(run: Run) -> dict:
    return {row["step"]: row[run.metric] for row in run.rows}


def parity_rows(pairs: list[tuple[tuple, list[Run], list[Run]]], reps: int, seed: int) -> list[dict]:
    """One row per setting run by both implementations: each arm's final score, mean over its evaluations, IQM with
    its 95% CI, reward correlation and wall time, and the difference ours - reference with its bootstrap CI."""
    rows = []
    for setting, ours, reference in pairs:
        arms = {"ours": ours, "reference": reference}
        finals = {arm: np.array([r.score for r in group]) for arm, group in arms.items()}
        iqm = aggregate({arm: scores[:, None] for arm, scores in finals.items()}, reps, seed)
        row = {**dict(zip(SETTING, setting)), "metric": ours[0].metric,
               "measured_on": "training episodes" if on_training_episodes(reference[0]) else "evaluations"}
        for arm, group in arms.items():
            correlations = [r.rows[-1].get("reward_correlation", float("nan")) for r in group]
            row |= {f"{arm}_runs": len(group), f"{arm}_seeds": " ".join(str(r.config["seed"]) for r in group),
                    f"{arm}_final_mean": float(finals[arm].mean()), f"{arm}_final_std": float(finals[arm].std()),
                    f"{arm}_finals": " ".join(f"{x:.{digits(ours[0].metric) - 1}f}" for x in finals[arm]),
                    f"{arm}_mean_over_evaluations": float(np.mean([np.mean(list(curve(r).values())) for r in group])),
                    f"{arm}_iqm": iqm[arm]["iqm"],
                    f"{arm}_reward_correlation": float(np.nanmean(correlations)) if np.isfinite(correlations).any()
                    else float("nan"),
                    f"{arm}_wall_minutes": float(np.mean([r.rows[-1]["wall_time"] for r in group])) / 60}
        row["difference"] = difference_ci(finals["ours"], finals["reference"], reps, seed)
        row["welch_p"] = welch_p(finals["ours"], finals["reference"])
        rows.append(row)
    return rows


def pooled_differences(pairs: list[tuple[tuple, list[Run], list[Run]]], reps: int, seed: int) -> list[dict]:
    """Per algorithm with two or more settings run by both: is there a gap too small for any one setting's seeds? The
    mean over settings of (ours - reference) / the reference's mean final return, each setting weighing the same, with
    a 95% bootstrap CI (seeds resampled within each arm of each setting), and Stouffer's combination of the settings'
    one-sided Welch tests (p of ours lower, and of ours higher, than the reference)."""
    from scipy import stats

    by_algorithm = defaultdict(list)
    for setting, ours, reference in pairs:
        finals = [np.array([r.score for r in group]) for group in (ours, reference)]
        if min(map(len, finals)) >= 2:
            by_algorithm[setting[0]].append(finals)
    rng = np.random.default_rng(seed)
    pooled = []
    for algorithm, settings in sorted(by_algorithm.items()):
        if len(settings) < 2:
            continue
        relative = np.mean([(ours.mean() - ref.mean()) / abs(ref.mean()) for ours, ref in settings])
        draws = np.mean([(rng.choice(ours, (reps, len(ours))).mean(1) - rng.choice(ref, (reps, len(ref))).mean(1))
                         / abs(ref.mean()) for ours, ref in settings], axis=0)
        z = [stats.norm.isf(stats.ttest_ind(ours, ref, equal_var=False, alternative="less").pvalue)
             for ours, ref in settings]
        combined = float(np.sum(z) / np.sqrt(len(z)))
        pooled.append({"algorithm": algorithm, "settings": len(settings), "relative_difference": float(relative),
                       "low": float(np.percentile(draws, 2.5)), "high": float(np.percentile(draws, 97.5)),
                       "p_lower": float(stats.norm.sf(combined)), "p_higher": float(stats.norm.cdf(combined))})
    return pooled


LEVEL = 0.15  # no difference detected and its CI within +-15% of the base's mean: level


def verdict_word(row: dict) -> str:
    """The verdict on a difference row in a few words; verdict() says it with its numbers."""
    point, low, high = row["difference"]
    side = "lower" if point < 0 else "higher"
    base_mean = abs(row["reference_final_mean"])
    if np.isnan(row["welch_p"]):  # welch_p: nan with fewer than 2 runs a side
        return "no difference detected"
    zero_outside = not low <= 0 <= high
    if zero_outside and row["welch_p"] < 0.05:
        return side
    if -LEVEL * base_mean <= low and high <= LEVEL * base_mean:
        return "no difference detected, level"
    if zero_outside:
        return f"{side} by the CI, not by Welch's test"
    return "no difference detected"


def verdict(row: dict, names: tuple[str, str] = ("ours", "reference")) -> str:
    """verdict_word with the numbers: higher or lower when the bootstrap CI of the difference excludes 0 and Welch's
    p < 0.05 (with few seeds the percentile bootstrap is too narrow, so both must agree); lower or higher by the CI
    alone when Welch's test does not agree; else no difference detected, called level as well when the CI lies within
    +-15% of the base's mean. names: how the two arms ("ours" and "reference" in the row's keys) are called."""
    new, base = names
    point, low, high = row["difference"]
    base_mean = abs(row["reference_final_mean"])
    of_base = f"{'the ' * (base == 'reference')}{base}'s mean"
    d = digits(row["metric"])
    difference = f"{new} - {base} = {point:+.{d}f}"
    if np.isnan(row["welch_p"]):
        return f"no difference detected: {difference} (a single run on a side: no test; more seeds needed)"
    interval = f"95% CI [{low:+.{d}f}, {high:+.{d}f}], Welch p = {row['welch_p']:.3f}"
    word = verdict_word(row)
    if word in ("lower", "higher"):
        return f"{word}: {difference} ({abs(point) / base_mean:.0%} of {of_base}), {interval}"
    if word.endswith("level"):
        return f"{word} (the CI within ±{LEVEL:.0%} of {of_base}): {difference}, {interval}"
    if word != "no difference detected":
        return f"{word}: {difference}, {interval} (Welch's p >= 0.05: more seeds needed)"
    return f"no difference detected: {difference}, {interval}"


def parity_figure(setting: tuple, arms: dict[str, list[Run]], out: Path, prefix: str = "parity") -> Path:
    """Both implementations' learning curves of one setting: mean over seeds (thick) and each seed (thin)."""
    plt, fig, axes = plt_figure(1, 1, 7.5, 3.8)
    ax = axes[0, 0]
    for color, (name, group) in zip(("C0", "C3"), arms.items()):
        steps = sorted(set.intersection(*[set(curve(r)) for r in group]))
        values = np.array([[curve(r)[s] for s in steps] for r in group])
        for seed_values in values:
            ax.plot(steps, seed_values, color=color, linewidth=0.6, alpha=0.35)
        ax.plot(steps, values.mean(0), color=color, linewidth=2.2, label=f"{name} ({len(group)} seeds)")
    ax.set_xlabel("environment steps")
    ax.set_ylabel(group[0].metric.replace("_", " "))
    ax.legend(fontsize=8)
    fig.suptitle(f"{setting[0] if prefix.startswith('parity') else ' vs '.join(arms)} on {setting[1]}, "
                 f"{' / '.join(setting[2:])}\nmean (thick) and each seed (thin)",
                 fontsize=9)
    fig.tight_layout()
    path = out / safe_file(f"{prefix}_{'_'.join(setting)}.png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def compare_pairs(runs: list[Run], new: str, base: str) -> list[tuple[tuple, list[Run], list[Run]]]:
    """(NEW's setting, its finished runs, BASE's finished runs) for every setting both algorithms ran; where BASE ran
    it with one other sampler only (each algorithm asking its own way: QPA uniformly, PEBBLE by disagreement), that
    one."""
    groups = finished_by_setting(runs)
    pairs = []
    for setting in sorted(groups, key=sort_key):
        others = [other for other in groups if other[0] == base and other[1:4] == setting[1:4]
                  and other[5] == setting[5]]
        twin = (base, *setting[1:])
        if setting[0] == new and (twin in groups or len(others) == 1):
            pairs.append((setting, groups[setting], groups[twin if twin in groups else others[0]]))
    return pairs


def ground_truth_pairs(runs: list[Run]) -> list[tuple[tuple, list[Run], list[Run]]]:
    """(a preference setting, its finished runs, its algorithm's finished ground-truth runs on its task), for every
    preference setting with both; on Meta-World by the success rate, then again by the return."""
    groups = finished_by_setting(runs)
    pairs = []
    for setting in sorted(groups, key=sort_key):
        truth = (setting[0], setting[1], GROUND_TRUTH, "-", "-", "-")
        if setting[2] != GROUND_TRUTH and truth in groups:
            pairs.append((setting, groups[setting], groups[truth]))
            if groups[setting][0].metric == "success_rate":
                pairs.append((setting, by_return(groups[setting]), by_return(groups[truth])))
    return pairs


def ground_truth_markdown(rows: list[dict], figures: list[Path], target: Path, command: str, reps: int) -> str:
    """Each preference setting beside the same algorithm on the true reward (the --against-ground-truth page)."""
    names = ("preferences", "true reward")
    lines = ["# Preferences against the true reward", "",
             f"Made by `{command}` from the finished runs: each preference setting beside the same algorithm's runs "
             "with `--ground-truth-reward` on the same task. Final = the last evaluation's score (Meta-World: the "
             f"success rate, then the return); IQM with its 95% bootstrap CI (rliable, {reps} replications); "
             "difference = preferences - true reward, 95% percentile bootstrap CI with seeds resampled within each "
             "arm, and Welch's p beside it (with few seeds the bootstrap interval is too narrow).", ""]
    for row, figure in zip(rows, figures):
        lines += [f"## {row['algorithm']} on {row['task']}, teacher {row['teacher']}, budget {row['budget']}, "
                  f"{row['sampler']}, {row['schedule']}: {row['metric'].replace('_', ' ')}", "",
                  f"**Verdict: {verdict(row, names)}.**", ""]
        lines += arms_table(row, names)
        lines += [f"![{figure.stem}]({os.path.relpath(figure, target.parent)})", ""]
    return "\n".join(lines)


def discriminator(run: Run) -> dict | None:
    """RIME's discriminator at the run's last feedback session (its label file's trusted, flipped, dropped,
    precision and recall; for a run kept without its labels, as in docs/, its discriminator.csv's last row), or
    None for a run without them."""
    keys = ("trusted", "flipped", "dropped", "precision", "recall")
    files = sorted((run.path / "labels").glob("session_*.npz"))
    if files:
        with np.load(files[-1]) as data:
            return {key: float(data[key]) for key in keys} if all(key in data.files for key in keys) else None
    kept = run.path / "discriminator.csv"
    if not kept.is_file():
        return None
    with open(kept) as f:
        last = list(csv.DictReader(f))[-1]
    return {key: float(last[key]) for key in keys}


def digits(metric: str) -> int:
    """Decimals of a mean: two for a success rate (in [0, 1]), one for a return; a single run's, one fewer."""
    return 2 if metric == "success_rate" else 1


def arms_table(row: dict, names: tuple[str, str]) -> list[str]:
    """The two arms of a parity_rows row side by side, then the difference of their means with its CI."""
    d = digits(row["metric"])
    lines = table(["", "seeds", "final (mean ± std)", "per seed", "mean over evaluations", "IQM [95% CI]",
                   "final reward correlation", "wall time per run (min)"],
                  [[name, row[f"{arm}_seeds"], f"{row[f'{arm}_final_mean']:.{d}f} ± {row[f'{arm}_final_std']:.{d}f}",
                    row[f"{arm}_finals"], f"{row[f'{arm}_mean_over_evaluations']:.{d}f}",
                    "{0:.{3}f} [{1:.{3}f}, {2:.{3}f}]".format(*row[f"{arm}_iqm"], d),
                    fmt(row[f"{arm}_reward_correlation"]), f"{row[f'{arm}_wall_minutes']:.1f}"]
                   for arm, name in zip(("ours", "reference"), names)])
    point, low, high = row["difference"]
    return lines + ["", f"Difference {names[0]} - {names[1]}: {point:+.{d}f} [{low:+.{d}f}, {high:+.{d}f}]", ""]


def compare_markdown(rows: list[dict], figures: list[Path], pairs: list, names: tuple[str, str], target: Path,
                     command: str, reps: int) -> str:
    """Two algorithms side by side on every setting both ran (the --compare page)."""
    new, base = names
    lines = [f"# {new} against {base}", "",
             f"Made by `{command}` from the finished runs. Final = the last evaluation's mean return; IQM with its 95% "
             f"bootstrap CI (rliable, {reps} replications); difference = mean final return of {new} - {base}'s, 95% "
             "percentile bootstrap CI with seeds resampled within each arm (with few seeds such intervals are "
             "narrower than they should be: Welch's p is given beside it). Wall time: minutes per run at its last "
             "evaluation.", ""]
    for row, figure, (setting, new_runs, base_runs) in zip(rows, figures, pairs):
        sampler = row["sampler"]
        if base_runs[0].setting[4] != sampler:
            sampler = f"{sampler} ({new}) and {base_runs[0].setting[4]} ({base})"
        lines += [f"## {row['task']}, teacher {row['teacher']}, budget {row['budget']}, {sampler}, "
                  f"{row['schedule']}", "", f"**Verdict: {verdict(row, names)}.**", ""]
        lines += arms_table(row, names)
        records = [(r.config["seed"], d) for r in new_runs if (d := discriminator(r))]
        if records:
            lines += [f"{new}'s discriminator at the last feedback session (labels of D; precision and recall in "
                      "finding the teacher's mistakes):", ""]
            lines += table(["seed", "trusted", "flipped", "dropped", "precision", "recall"],
                           [[seed, *(f"{d[k]:.0f}" for k in ("trusted", "flipped", "dropped")),
                             f"{d['precision']:.2f}", f"{d['recall']:.2f}"] for seed, d in records])
            lines.append("")
        lines += [f"![{figure.stem}]({os.path.relpath(figure, target.parent)})", ""]
    return "\n".join(lines)


def safe_file(name: str) -> str:
    return "".join(c if c.isalnum() or c in "._-" else "-" for c in name)


def parity_markdown(rows: list[dict], figures: list[Path], pooled: list[dict], target: Path, command: str,
                    reps: int) -> str:
    lines = ["# Parity with the reference code", "",
             f"Made by `{command}` from the finished runs: "
             "each setting run by both pebble.py (ours) and the reference code (rll-research/BPref through "
             "benchmarks/reference/run.py, same flags). Final = the last evaluation's mean return (Meta-World: its "
             "success rate, the paper's measure, and then its return in a section of its own); IQM with its 95% "
             f"bootstrap CI (rliable, {reps} replications); difference = mean final return of ours - the reference's, "
             "95% percentile bootstrap CI with seeds resampled within each arm (with 3-5 seeds a side such intervals "
             "are narrower than they should be: Welch's p is given beside it). Wall time: minutes per run as "
             "recorded at its last evaluation, both one thread per run, two runs at a time on the same machine. The rerun "
             "and what was checked where the two part: [benchmarks/reference](../benchmarks/reference/README.md), "
             "[results.md](results.md#does-it-learn-like-the-reference-code).", ""]
    for row, figure in zip(rows, figures):
        measure = f": {row['metric'].replace('_', ' ')}" if is_metaworld(row["task"]) else ""
        lines += [f"## {row['algorithm']} on {row['task']}, teacher {row['teacher']}, budget {row['budget']}, "
                  f"{row['sampler']}, {row['schedule']}{measure}", "", f"**Verdict: {verdict(row)}.**", ""]
        if row["measured_on"] == "training episodes":
            lines += ["Measured on training episodes: the reference's PrefPPO evaluates no policy, so both arms' "
                      "returns are those of their stochastic training episodes (gSDE noise included), a row per step "
                      "at which a wave of episodes ended (every env ends one at the same step); final = the last "
                      "wave, mean over evaluations = mean over the waves.", ""]
        lines += arms_table(row, ("ours", "reference"))
        lines += [f"![{figure.stem}]({os.path.relpath(figure, target.parent)})", ""]
    for row in pooled:
        lines += [f"## {row['algorithm']}: all {row['settings']} settings pooled", "",
                  "A gap too small for any one setting's seeds would show here: the mean over the settings of ours - "
                  "the reference's mean final return, relative to the reference's, each setting weighing the same, "
                  "with its 95% bootstrap CI; and Stouffer's combination of the settings' one-sided Welch tests.", "",
                  f"**Ours - reference: {row['relative_difference']:+.1%} of the reference's mean return, 95% CI "
                  f"[{row['low']:+.1%}, {row['high']:+.1%}]; combined p of ours lower {row['p_lower']:.3f}, of ours "
                  f"higher {row['p_higher']:.3f}.**", ""]
    return "\n".join(lines)


# ---------------------------------------------------------------- the docs' generated blocks
# `python experiments/report.py --docs` writes each block of DOCS_BLOCKS between its two markers in its page, and each
# figure of DOCS_FIGURES, from the runs kept under docs/ (their config.json and eval.csv; PrefPPO's parity reads its
# TensorBoard file too). tests/test_generated_docs.py fails where a committed block differs from its rebuild. A new
# block is a function that returns its Markdown, a row of DOCS_BLOCKS and its two markers in the page
# (docs/experiments.md says how).

DOCS_REPS = 2000  # bootstrap resamples of every generated block, seeded with DOCS_SEED (a folder's report: --reps)
DOCS_SEED = 0
BEGIN = "<!-- generated by experiments/report.py --docs: {name}; do not edit -->"
END = "<!-- end of generated block {name} -->"
ARM_NAMES = {("pebble", False): "PEBBLE", ("pebble", True): "SAC", ("prefppo", False): "PrefPPO",
             ("prefppo", True): "PPO", ("rime", False): "rime.py", ("rime", True): "rime.py's SAC",
             ("reference-pebble", False): "reference PEBBLE", ("reference-pebble", True): "reference SAC",
             ("reference-prefppo", False): "reference PrefPPO", ("reference-rime", False): "RIME's code"}
# the paper's four tasks at CPU scale: the folders of their PEBBLE, SAC, PrefPPO, PPO and reference-code runs
PAPER_TASKS = {"walker-walk": ("docs/parity/data",),
               "quadruped-walk": ("docs/tasks/data/quadruped-walk", "docs/tasks/data/quadruped-walk-prefppo"),
               "button-press": ("docs/tasks/data/button-press", "docs/tasks/data/button-press-prefppo"),
               "sweep-into": ("docs/tasks/data/sweep-into-250k", "docs/tasks/data/sweep-into-prefppo")}
# the CPU-scale runs timed in results.md
RUN_TIME_FOLDERS = ("docs/parity/data", "docs/rime/data/oracle", "docs/tasks/data/quadruped-walk",
                    "docs/tasks/data/quadruped-walk-prefppo", "docs/tasks/data/button-press",
                    "docs/tasks/data/button-press-prefppo", "docs/tasks/data/sweep-into-250k",
                    "docs/tasks/data/sweep-into-prefppo")
# each preference setting against its algorithm's runs on the true reward, folder by folder
TRUE_REWARD_FOLDERS = (("docs/parity/data/ours",), ("docs/tasks/data/quadruped-walk",),
                       ("docs/tasks/data/button-press",), ("docs/tasks/data/sweep-into-250k",),
                       ("docs/tasks/data/sweep-into",), ("docs/tasks/data/quadruped-walk-prefppo",),
                       ("docs/tasks/data/button-press-prefppo",), ("docs/tasks/data/sweep-into-prefppo",))


@functools.cache  # the blocks read the same folders again
def kept_runs(*folders: str) -> tuple[Run, ...]:
    """The finished runs below folders of the repository, each seed of a setting once (the first folder's copy)."""
    seen = set()
    runs = []
    for folder in folders:
        for run in find_runs(ROOT / folder, ROOT / folder / "report"):
            key = (run.setting, run.config["seed"])
            if run.state == "finished" and key not in seen:
                seen.add(key)
                runs.append(run)
    return tuple(runs)


def arm(runs: list[Run], algorithm: str, task: str, teacher: str) -> list[Run]:
    return [run for run in runs if run.setting[:3] == (algorithm, task, teacher)]


def arm_name(run: Run) -> str:
    return ARM_NAMES[run.algorithm, run.is_ground_truth]


def steps(run: Run) -> str:
    total = run.config["total_timesteps"]
    return f"{total // 1_000_000}M" if total % 1_000_000 == 0 else f"{total // 1000}K"


def measure(metric: str) -> str:
    return "success" if metric == "success_rate" else "return"


def spread(group: list[Run]) -> str:
    """Final score, mean ± standard deviation over seeds (numpy's, ddof 0), and the number of seeds."""
    if not group:
        return "-"
    scores = np.array([run.score for run in group])
    d = digits(group[0].metric)
    return f"{scores.mean():.{d}f} ± {scores.std():.{d}f} ({len(scores)})"


def difference_row(new: list[Run], base: list[Run]) -> dict:
    """new - base on the final scores, with the keys that verdict() reads."""
    finals = [np.array([run.score for run in group]) for group in (new, base)]
    return {"metric": new[0].metric, "reference_final_mean": float(finals[1].mean()),
            "difference": difference_ci(*finals, DOCS_REPS, DOCS_SEED), "welch_p": welch_p(*finals)}


def p_text(p: float) -> str:
    return "p < 0.001" if p < 0.001 else f"p = {p:.3f}"


def difference_text(row: dict) -> str:
    d = digits(row["metric"])
    point, low, high = row["difference"]
    return f"{point:+.{d}f} [{low:+.{d}f}, {high:+.{d}f}], {p_text(row['welch_p'])}"


def teacher_text(teacher: str) -> str:
    """A teacher's name as report.py writes it, in words: mistake(eps_mistake=0.3) is mistake, eps_mistake 0.3."""
    if teacher == GROUND_TRUTH:
        return "true reward"
    return teacher.replace("(", ", ").replace("=", " ").removesuffix(")")


def minutes(group: list[Run]) -> str:
    return f"{np.mean([run.rows[-1]['wall_time'] for run in group]) / 60:.1f}"


def same_seeds(new: list[Run], base: list[Run]) -> list[Run]:
    """base's runs of the seeds that new ran (a comparison of two algorithms on the same seeds)."""
    seeds = {run.config["seed"] for run in new}
    return [run for run in base if run.config["seed"] in seeds]


def glance_table() -> str:
    """README: a row per paper task, a column per arm, PEBBLE - SAC's difference and verdict."""
    rows = []
    for task, folders in PAPER_TASKS.items():
        runs = kept_runs(*folders)
        pebble, sac = arm(runs, "pebble", task, "oracle"), arm(runs, "pebble", task, GROUND_TRUTH)
        prefppo = arm(runs, "prefppo", task, "oracle")
        reference = [arm(runs, "reference-pebble", task, teacher) for teacher in ("oracle", GROUND_TRUTH)]
        scale = f"{steps(pebble[0])}" + (f", PrefPPO {steps(prefppo[0])}" if prefppo else "")
        row = difference_row(pebble, sac)
        rows.append([f"{task} ({measure(pebble[0].metric)}; {scale})", spread(pebble), spread(sac), spread(prefppo),
                     spread(arm(runs, "prefppo", task, GROUND_TRUTH)),
                     " / ".join(map(spread, reference)) if reference[0] else "-",
                     f"{difference_text(row)}: {verdict_word(row)}"])
    return "\n".join(table(["task (measure; steps)", "PEBBLE", "SAC", "PrefPPO", "PPO",
                            "reference code: PEBBLE / SAC", "PEBBLE - SAC [95% CI], Welch p: verdict"], rows))


def pebble_sac_figure(path: Path):
    """README: PEBBLE (oracle) and SAC's learning curves on the paper's four tasks, mean and one std over seeds."""
    plt, fig, axes = plt_figure(2, 2, 10, 6.4)
    for ax, (task, folders) in zip(axes.flat, PAPER_TASKS.items()):
        runs = kept_runs(*folders)
        for color, teacher in (("C0", "oracle"), ("black", GROUND_TRUTH)):
            group = arm(runs, "pebble", task, teacher)
            shared = sorted(set.intersection(*[set(curve(run)) for run in group]))
            values = np.array([[curve(run)[step] for step in shared] for run in group])
            label = f"{arm_name(group[0])} ({len(group)} seeds)"
            ax.plot(shared, values.mean(0), color=color, label=label)
            ax.fill_between(shared, values.mean(0) - values.std(0), values.mean(0) + values.std(0), color=color,
                            alpha=0.15)
        ax.set_title(task, fontsize=10)
        ax.set_xlabel("environment steps")
        ax.set_ylabel(group[0].metric.replace("_", " "))
        ax.legend(fontsize=8)
    fig.suptitle("PEBBLE (oracle teacher) against SAC on the true reward: mean and one standard deviation over seeds",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def true_reward_table() -> str:
    """results.md: each preference setting against its algorithm on the true reward (Meta-World: success, then
    return)."""
    rows = []
    for folders in TRUE_REWARD_FOLDERS:
        for setting, new, base in ground_truth_pairs(kept_runs(*folders)):
            row = difference_row(new, base)
            labels = setting[3].split("/")[0]
            preferences = f"{arm_name(new[0])}, {teacher_text(setting[2])}, {labels} labels"
            rows.append([f"{setting[1]}, {steps(new[0])}", preferences,
                         arm_name(base[0]), measure(row["metric"]), spread(new), spread(base), difference_text(row),
                         verdict_word(row)])
    return "\n".join(table(["task, steps", "preferences", "true reward", "measure", "preferences: final",
                            "true reward: final", "difference [95% CI], Welch p", "verdict"], rows))


def parity_table() -> str:
    """results.md: ours against the reference code on every setting both ran (PrefPPO on training episodes)."""
    pairs = parity_pairs(kept_runs("docs/parity/data")) + parity_pairs(kept_runs("docs/tasks/data/button-press"))
    pairs += [(setting, by_return(ours), by_return(reference)) for setting, ours, reference in pairs
              if ours[0].metric == "success_rate"]
    rows = []
    for setting, ours, reference in pairs:
        row = difference_row(ours, reference)
        episodes = " (training episodes)" if on_training_episodes(reference[0]) else ""
        rows.append([f"{arm_name(ours[0])}, {setting[1]}, {steps(ours[0])}", teacher_text(setting[2]),
                     measure(row["metric"]) + episodes, spread(ours), spread(reference), difference_text(row),
                     verdict_word(row)])
    return "\n".join(table(["algorithm, task, steps", "teacher", "measure", "ours", "reference code",
                            "ours - reference [95% CI], Welch p", "verdict"], rows))


def prefppo_defects_table() -> str:
    """results.md: prefppo.py with the reference's two defects as edits, against the reference's PrefPPO."""
    reference = kept_runs("docs/parity/data/reference")
    rows = []
    for name, folder in (("prefppo.py", "docs/parity/data/ours"),
                         ("with no-bootstrap-time-limits", "docs/ablations/prefppo-no-bootstrap-time-limits"),
                         ("with both edits", "docs/ablations/prefppo-reference-ways")):
        ours = [run for run in kept_runs(folder) if run.algorithm == "prefppo"]
        for setting, ours_rows, reference_rows in parity_pairs([*ours, *reference]):
            row = difference_row(ours_rows, reference_rows)
            finals = " ".join(f"{run.score:.0f}" for run in ours_rows)
            rows.append([name, finals, spread(ours_rows), spread(reference_rows), difference_text(row),
                         verdict_word(row)])
    return "\n".join(table(["walker-walk, 1M steps, oracle", "per seed", "final (training episodes)",
                            "reference code", "minus the reference [95% CI], Welch p", "verdict"], rows))


def rime_table() -> str:
    """results.md: rime.py against pebble.py (the same seeds) and RIME's own code, with minutes per run."""
    rows = []
    for folders, bases in ((("docs/rime/data/eps0.3",), ("pebble", "reference-rime")),
                           (("docs/rime/data/eps0.1", "docs/rime/data/oracle", "docs/parity/data/ours"), ("pebble",))):
        runs = kept_runs(*folders)
        for base in bases:
            for setting, new, others in compare_pairs(runs, "rime", base):
                others = same_seeds(new, others)
                row = difference_row(new, others)
                rows.append([f"{teacher_text(setting[2])}, {steps(new[0])}", arm_name(others[0]), spread(new),
                             spread(others), difference_text(row), verdict_word(row),
                             f"{minutes(new)} / {minutes(others)}"])
    return "\n".join(table(["walker-walk: teacher, steps", "against", "rime.py", "the other", "rime.py - the other "
                            "[95% CI], Welch p", "verdict", "minutes per run (rime.py / the other)"], rows))


def teachers_table() -> str:
    """results.md: pebble.py and rime.py with each of the six teachers (mini B-Pref): final return, normalised IQM
    (each by its own runs on the true reward) and rime.py - pebble.py."""
    runs = kept_runs("docs/rime/data/mini-bpref")
    normalize(runs)
    iqm = {row["algorithm"] + row["teacher"]: row["iqm"] for row in setting_aggregates(runs, DOCS_REPS, DOCS_SEED)}
    rows = []
    for setting, rime, pebble in compare_pairs(runs, "rime", "pebble"):
        row = difference_row(rime, pebble)
        normalised = ["{0:.2f} [{1:.2f}, {2:.2f}]".format(*iqm[name + setting[2]]) if name + setting[2] in iqm
                      else "1 (the denominator)" for name in ("pebble", "rime")]
        rows.append([teacher_text(setting[2]), spread(pebble), normalised[0], spread(rime), normalised[1],
                     difference_text(row), verdict_word(row)])
    return "\n".join(table(["teacher", "pebble.py", "normalised IQM [95% CI]", "rime.py", "normalised IQM [95% CI]",
                            "rime.py - pebble.py [95% CI], Welch p", "verdict"], rows))


TEACHER_FIT_FOLDER = "docs/teacher_fit/data"  # runs kept with their label files (keep_runs.py --labels)


def estimate_text(value: float, low: float | None, high: float | None) -> str:
    """An estimate and its interval as fit_teacher.py prints them (4 significant digits, "-" for no end)."""
    ends = ["-" if end is None else f"{end:.4g}" for end in (low, high)]
    return f"{value:.4g} [{ends[0]}, {ends[1]}]"


def teacher_fit_table() -> str:
    """teacher_fit.md: fit_teacher.py on each kept run's labels: each parameter's estimate [95% CI], whether every
    interval holds the run's teacher, and the goodness-of-fit check."""
    fit_teacher = importlib.import_module("fit_teacher")
    names = ("beta", "gamma", "eps_mistake", "eps_skip", "eps_equal", "bias")
    rows = []
    for run in sorted(kept_runs(TEACHER_FIT_FOLDER), key=lambda run: teacher_order(run.setting[2])):
        data = fit_teacher.load_labels(str(run.path))
        result = fit_teacher.fit(data["rewards0"], data["rewards1"], data["y"], data["keep"], data["threshold_scale"])
        truth = fit_teacher.run_teacher(str(run.path))
        intervals = [result["ci"][name] for name in names]  # (None, None) where fitted again with a side bias
        holds = all(low is not None and low <= truth[name] <= high for name, (low, high) in zip(names, intervals))
        cells = [estimate_text(result[name], *interval) for name, interval in zip(names, intervals)]
        rows.append([f"{teacher_text(run.setting[2])}, {run.config['sampler']} sampler, seed {run.config['seed']}",
                     f"{result['n_strict']} / {result['n_equal']} / {result['n_skipped']}", *cells,
                     "yes" if holds else "no", "yes" if "does NOT" not in result["check"]["verdict"] else "no"])
    return "\n".join(table(["run's teacher", "strict / equal / skipped", *names, "every interval holds the teacher",
                            "the check passes"], rows))


def run_times_table() -> str:
    """results.md: minutes per run at CPU scale (one thread a run), and the first command's run on a GPU, projected
    from its first blocks of 10K steps (the last block's rate for the rest, as benchmarks/card_speed.py does)."""
    groups = defaultdict(list)
    for run in kept_runs(*RUN_TIME_FOLDERS):
        if run.setting[2] in ("oracle", GROUND_TRUTH):
            groups[run.setting[1], arm_name(run)].append(run)
    rows = []
    order = {key: (key[0], group[0].config["total_timesteps"], key[1]) for key, group in groups.items()}
    for (task, name), group in sorted(groups.items(), key=lambda item: order[item[0]]):
        wall = np.array([run.rows[-1]["wall_time"] for run in group]) / 60
        size = f"{group[0].config['hidden_dim']} x {group[0].config['num_layers']}"
        rows.append([task, name, steps(group[0]), size, "2-core CPU", len(group),
                     f"{np.median(wall):.0f} ({wall.min():.0f}-{wall.max():.0f})"])
    card = ROOT / "docs/tasks/data/card-h200"
    config = json.loads((card / "config.json").read_text())
    before, last = read_eval(card)[-2:]
    seconds_per_step = (last["wall_time"] - before["wall_time"]) / (last["step"] - before["step"])
    projected = last["wall_time"] + (config["total_timesteps"] - last["step"]) * seconds_per_step
    rows.append([config["env_id"], f"PEBBLE, {config['teacher']} (the first command)", "1M",
                 f"{config['hidden_dim']} x {config['num_layers']}", "one NVIDIA H200", 1,
                 f"{projected / 60:.0f} (projected from its first {last['step'] // 1000:.0f}K steps)"])
    return "\n".join(table(["task", "arm", "steps", "networks", "machine", "runs", "minutes per run: median (range)"],
                           rows))


def raw_inputs_table() -> str:
    """differences.md: pebble.py's reward inputs standardised (the default) or raw (the reference's way), beside the
    reference code, each on the seeds the raw arm ran; final return, then the final reward correlation."""
    raw = kept_runs("docs/ablations/pebble-raw-reward-inputs")
    others = kept_runs("docs/parity/data")
    rows = []
    for setting in sorted({run.setting for run in raw}, key=sort_key):
        raw_runs = [run for run in raw if run.setting == setting]
        standardised = same_seeds(raw_runs, arm(others, "pebble", *setting[1:3]))
        reference = same_seeds(raw_runs, arm(others, "reference-pebble", *setting[1:3]))
        row = difference_row(standardised, raw_runs)
        correlations = [f"{np.mean([run.rows[-1]['reward_correlation'] for run in group]):.2f}"
                        for group in (standardised, raw_runs, reference)]
        rows.append([f"{setting[1]}, {teacher_text(setting[2])}", spread(standardised), spread(raw_runs),
                     spread(reference), f"{difference_text(row)}: {verdict_word(row)}",
                     paired_text(standardised, raw_runs), " / ".join(correlations)])
    return "\n".join(table(["pebble.py, 100K steps", "standardised (the default)", "raw", "reference code",
                            "standardised - raw [95% CI], Welch p: verdict",
                            "seeds where standardised is higher (paired t-test)",
                            "final reward correlation (standardised / raw / reference)"], rows))


def paired_text(new: list[Run], base: list[Run]) -> str:
    """On how many seeds new's final score is above base's, and the paired t-test's p (the seeds both ran)."""
    from scipy import stats

    base_scores = {run.config["seed"]: run.score for run in base}
    pairs = np.array([(run.score, base_scores[run.config["seed"]]) for run in new
                      if run.config["seed"] in base_scores])
    higher = int((pairs[:, 0] > pairs[:, 1]).sum())
    return f"{higher} of {len(pairs)} ({p_text(float(stats.ttest_rel(pairs[:, 0], pairs[:, 1]).pvalue))})"


def script_size_table() -> str:
    """results.md: the algorithm scripts' size as benchmarks/script_size.py counts it, part by part."""
    from benchmarks import script_size

    parts = ("Args, presets", "Environments", "Networks", "Algorithm", "Plumbing", "main block")
    rows = []
    for name in ("pebble.py", "prefppo.py", "rime.py", "qpa.py"):
        source = (ROOT / name).read_text()
        split = script_size.split(source)
        rows.append([name, f"{len(script_size.content_tokens(source)):,}", *(f"{split.get(p, 0):,}" for p in parts),
                     f"{script_size.prose_characters(source):,}", script_size.main_loop_lines(source)])
    return "\n".join(table(["script", "tokens", *parts, "prose (characters)", "main loop (lines)"], rows))


DOCS_BLOCKS = [  # (page, block name, the function that writes the block)
    ("README.md", "results-at-a-glance", glance_table),
    ("docs/results.md", "parity", parity_table),
    ("docs/results.md", "prefppo-defects", prefppo_defects_table),
    ("docs/results.md", "against-the-true-reward", true_reward_table),
    ("docs/results.md", "teachers", teachers_table),
    ("docs/results.md", "rime", rime_table),
    ("docs/results.md", "run-times", run_times_table),
    ("docs/differences.md", "raw-reward-inputs", raw_inputs_table),
    ("docs/results.md", "script-size", script_size_table),
    ("docs/teacher_fit.md", "teacher-fit-runs", teacher_fit_table),
    # docs/bpref.md: experiments/bpref.py (which imports this module) writes its blocks and figures
    ("docs/bpref.md", "bpref-findings", lambda: importlib.import_module("bpref").findings_block()),
    ("docs/bpref.md", "bpref-task-figures", lambda: importlib.import_module("bpref").task_figures_block()),
    ("docs/bpref.md", "bpref-design-figures", lambda: importlib.import_module("bpref").design_figures_block()),
    ("docs/bpref.md", "bpref-blocks", lambda: importlib.import_module("bpref").blocks_block()),
]
DOCS_FIGURES = [("docs/tasks/pebble_against_sac.png", pebble_sac_figure),
                ("docs/bpref", lambda folder: importlib.import_module("bpref").draw_figures(folder))]


def block_span(text: str, name: str, page: str) -> tuple[int, int, str]:
    """Where a block's lines start and end in its page (between its two markers, each there once) and the indent of
    its begin marker, which every line of the block takes (a block inside a list item)."""
    begin, end = BEGIN.format(name=name), END.format(name=name)
    if text.count(begin) != 1 or text.count(end) != 1 or text.index(begin) > text.index(end):
        raise ReportError(f"{page}: block {name!r} needs its two markers once each, in order: {begin} ... {end}")
    start = text.index(begin)
    indent = text[text.rfind("\n", 0, start) + 1:start]
    return start + len(begin), text.index(end) - len(indent), indent


def rebuilt_pages(blocks: list = DOCS_BLOCKS) -> dict[Path, str]:
    """Each page of blocks, with every block rewritten from the kept runs."""
    pages = {}
    for page, name, make in blocks:
        path = ROOT / page
        text = pages[path] if path in pages else path.read_text()
        start, end, indent = block_span(text, name, page)
        lines = "".join(f"{indent}{line}\n" for line in make().splitlines())
        pages[path] = f"{text[:start]}\n{lines}{text[end:]}"
    return pages


def rewrite_docs():
    for path, text in rebuilt_pages().items():
        changed = path.read_text() != text
        path.write_text(text)
        print(f"{path.relative_to(ROOT)}: {'rewritten' if changed else 'unchanged'}")
    for figure, make in DOCS_FIGURES:
        make(ROOT / figure)
        print(f"{figure}: drawn")



# ---------------------------------------------------------------- the report


def fmt(value) -> str:
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return "-"
    return f"{value:.3g}" if isinstance(value, float) else str(value)


def ci_text(value: tuple) -> str:
    point, low, high = value
    return f"{point:.3f} [{low:.3f}, {high:.3f}]"


def table(header: list[str], rows: list[list]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header),
            *["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]]


def expected_runs(root: Path) -> tuple[dict, dict]:
    """From the grid runner's grid.json files below root: {run dir: last exit code} of every run a grid planned."""
    expected = {}
    for spec_path in root.rglob("grid.json"):
        try:
            runs = json.loads(spec_path.read_text())["runs"]
        except (OSError, ValueError, KeyError):
            continue
        for name, entry in runs.items():
            expected[spec_path.parent / name] = entry.get("exit_code")
    return expected, {path: path.parent / "logs" / f"{path.name}.log" for path in expected}


def write_csv(path: Path, rows: list[dict]):
    if not rows:
        path.write_text("")
        return
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def flat(row: dict) -> dict:
    """An aggregate row with each (point, low, high) as three columns."""
    result = {}
    for key, value in row.items():
        if isinstance(value, tuple):
            result.update({key: value[0], f"{key}_low": value[1], f"{key}_high": value[2]})
        else:
            result[key] = value
    return result


def from_repository(path: Path) -> str:
    """A path as written in a report: relative to the repository where it lies inside it."""
    return str(path.relative_to(ROOT)) if ROOT in path.parents else str(path)


class ReportError(Exception):
    """A problem with the command line or the folder, said in one line."""


def report(args: Args) -> Path:
    if args.root is None:
        raise ReportError("give a folder of runs (or --docs alone)")
    root = Path(args.root).resolve()
    out = Path(args.out).resolve() if args.out else root / "report"
    if not root.is_dir():
        raise ReportError(f"{args.root!r} is not a folder")
    if args.reps < 1 or args.alignment_runs < 0:
        raise ReportError("--reps must be >= 1 and --alignment-runs >= 0")
    runs = find_runs(root, out)
    if not runs:
        raise ReportError(f"no runs (folders with a config.json) below {root}")

    def relative(path: Path) -> str:
        return str(path.relative_to(root)) if root in path.parents else str(path)

    out.mkdir(parents=True, exist_ok=True)
    baselines, problems = normalize(runs)
    settings = setting_aggregates(runs, args.reps, args.seed)
    across, across_notes = across_task_aggregates(runs, args.reps, args.seed)
    mixed = mixed_settings(runs)
    finished = [run for run in runs if run.state == "finished"]

    figures = bar_figures(settings, "teacher", "algorithm", ("task",), out, "figure2",
                          "IQM normalised return per teacher")
    for column in ("sampler", "schedule", "budget"):  # compared where an algorithm ran a task with several
        values = defaultdict(set)
        for row in settings:
            values[row["algorithm"], row["task"]].add(row[column])
        varied = [row for row in settings if len(values[row["algorithm"], row["task"]]) > 1]
        figures += bar_figures(varied, "teacher", column, ("algorithm", "task"), out, f"{column}s",
                               f"IQM normalised return per {column}")
    figures += curve_figures(runs, out)
    alignments, alignment_notes = [], []
    if args.alignment_runs:
        candidates = defaultdict(list)
        for run in finished:
            ours = run.config.get("implementation", "ours") == "ours"
            if not run.is_ground_truth and ours and (run.path / "final_model.pt").exists():
                candidates[run.setting[:2]].append(run)
        for key, group in sorted(candidates.items()):
            for run in sorted(group, key=lambda r: (r.setting[2] != "oracle", str(r.path)))[: args.alignment_runs]:
                try:
                    alignments.append((run, *alignment_figure(run, root, out)))
                except Exception as error:  # a model or environment that cannot be rebuilt here: say so and go on
                    alignment_notes.append(f"{run.path.relative_to(root)}: no reward-alignment plot "
                                           f"({type(error).__name__}: {error})")

    lines = [f"# B-Pref report: {root.name}", "",
             f"{len(runs)} runs found in `{from_repository(root)}`, {len(finished)} finished. Normalised return = "
             "final evaluation return (Meta-World: success rate) / mean of the same over the finished ground-truth "
             "runs of the same algorithm on the task. Aggregates over seeds with 95% stratified bootstrap CIs "
             f"(rliable, {args.reps} replications); optimality gap = mean shortfall below 1.", ""]
    if settings:
        lines += ["## Normalised return per setting", ""]
        lines += table(["algorithm", "task", "teacher", "budget", "sampler", "schedule", "runs", "IQM", "median",
                        "mean", "optimality gap", "final score (mean ± std)"],
                       [[*(row[c] for c in SETTING), row["runs"], *(ci_text(row[m]) for m in METRICS),
                         f"{row['score_mean']:.3g} ± {row['score_std']:.3g}"] for row in settings])
        lines.append("")
    if across:
        lines += ["## Across tasks (runs resampled within each task)", ""]
        lines += table(["algorithm", "tasks", "teacher", "budget", "sampler", "schedule", "runs", "IQM", "median",
                        "mean", "optimality gap"],
                       [[row["algorithm"], row["tasks"], row["teacher"], row["budget"], row["sampler"], row["schedule"],
                         row["runs"], *(ci_text(row[m]) for m in METRICS)] for row in across])
        lines.append("")
    if baselines:
        lines += ["## Ground-truth baselines (the denominators)", ""]
        lines += table(["algorithm", "task", "finished runs", "mean final score", "per run"],
                       [[*key, len(scores), f"{np.mean(scores):.4g}", ", ".join(f"{s:.4g}" for s in scores)]
                        for key, scores in sorted(baselines.items())])
        lines.append("")
    for title, notes in (("Not normalisable", problems), ("Settings that mix configurations", mixed),
                         ("Not aggregated across tasks", across_notes),
                         ("Reward alignment not plotted", alignment_notes)):
        if notes:
            lines += [f"## {title}", "", *[f"- {note}" for note in notes], ""]
    if figures or alignments:
        lines += ["## Figures", ""]
        lines += [f"![{path.stem}]({path.name})" for path in figures]
        lines += [f"![{path.stem}]({path.name}) reward alignment of `{relative(run.path)}` along one evaluation "
                  f"episode: Pearson r = {r:.3f}" for run, path, r in alignments]
        lines.append("")

    run_rows = []
    for run in runs:
        last = run.rows[-1] if run.rows else {}
        overhead = last.get("overhead_seconds", float("nan")) / last["wall_time"] if last.get("wall_time") else None
        run_rows.append({"run": relative(run.path), **dict(zip(SETTING, run.setting)), "seed": run.config["seed"],
                         "state": run.state, "step": int(last.get("step", 0)), "metric": run.metric,
                         "score": run.score, "normalized": run.normalized,
                         "mean_over_evaluations": np.mean([r[run.metric] for r in run.rows]) if run.rows else None,
                         "reward_correlation": last.get("reward_correlation"),
                         "wall_minutes": last.get("wall_time", float("nan")) / 60 if last else None,
                         "overhead_share": overhead})
    lines += ["## Runs", ""]
    lines += table(["run", "algorithm", "task", "teacher", "seed", "state", "step", "final score", "normalised",
                    "mean over evaluations", "final reward_correlation", "wall time (min)", "overhead share"],
                   [[f"`{row['run']}`", row["algorithm"], row["task"], row["teacher"], row["seed"], row["state"],
                     row["step"], fmt(row["score"]), fmt(row["normalized"]),
                     fmt(row["mean_over_evaluations"]), fmt(row["reward_correlation"]), fmt(row["wall_minutes"]),
                     fmt(row["overhead_share"])] for row in run_rows])
    lines.append("")

    expected, logs = expected_runs(root)
    found = {run.path: run for run in runs}
    incomplete = []
    for run in runs:
        if run.state != "finished":
            code = expected.get(run.path)
            status = f"last exit code {code}" if code not in (None, 0) else "running or stopped"
            log = f"; log `{relative(logs[run.path])}`" if run.path in logs else ""
            incomplete.append(f"`{relative(run.path)}`: unfinished, {run.detail} ({status}){log}")
    for path, code in sorted(expected.items()):
        if path not in found:
            incomplete.append(f"`{relative(path)}`: missing (planned by the grid, not started"
                              f"{'' if code is None else f', last exit code {code}'}); log `{relative(logs[path])}`")
    if incomplete:
        lines += ["## Unfinished, failed and missing runs (not in the tables above)", "",
                  *[f"- {line}" for line in incomplete], ""]

    if args.parity:
        target = Path(args.parity).resolve()
        pairs = parity_pairs(runs)
        if not pairs:
            raise ReportError(f"--parity: no setting below {root} has finished runs of both ours and the reference")
        # Meta-World: each setting by its success rate, then by its return
        measured = sorted([(pair, "parity") for pair in pairs] +
                          [((setting, by_return(ours), by_return(reference)), "parity_return")
                           for setting, ours, reference in pairs if ours[0].metric == "success_rate"],
                          key=lambda item: sort_key(item[0][0]))
        parity = parity_rows([pair for pair, _ in measured], args.reps, args.seed)
        parity_figures = [parity_figure(setting, {"ours": ours, "reference": reference}, out, prefix)
                          for (setting, ours, reference), prefix in measured]
        command = shlex.join(["python", "experiments/report.py", *sys.argv[1:]])
        pooled = pooled_differences(pairs, args.reps, args.seed)
        target.write_text(parity_markdown(parity, parity_figures, pooled, target, command, args.reps))
        write_csv(out / "parity.csv", [flat(row) for row in parity])
        for row in parity:
            print(f"parity: {' / '.join(row[c] for c in SETTING)}, {row['metric']}: {verdict(row)}")
        for row in pooled:
            print(f"parity: {row['algorithm']}, {row['settings']} settings pooled: {row['relative_difference']:+.1%} "
                  f"[{row['low']:+.1%}, {row['high']:+.1%}], p lower {row['p_lower']:.3f}")
    if args.compare:
        names = tuple(args.compare)
        pairs = compare_pairs(runs, *names)
        if not pairs:
            raise ReportError(f"--compare {' '.join(names)}: no setting below {root} has finished runs of both")
        rows = parity_rows(pairs, args.reps, args.seed)
        figures = [parity_figure(setting, dict(zip(names, (a, b))), out, f"compare_{'_'.join(names)}")
                   for setting, a, b in pairs]
        target = out / safe_file(f"compare_{'_'.join(names)}.md")
        command = shlex.join(["python", "experiments/report.py", *sys.argv[1:]])
        target.write_text(compare_markdown(rows, figures, pairs, names, target, command, args.reps))
        write_csv(out / safe_file(f"compare_{'_'.join(names)}.csv"), [flat(row) for row in rows])
        for row in rows:
            print(f"compare: {' / '.join(row[c] for c in SETTING[1:])}: {verdict(row, names)}")
    if args.against_ground_truth:
        pairs = ground_truth_pairs(runs)
        if not pairs:
            raise ReportError(f"--against-ground-truth: no preference setting below {root} has finished runs beside "
                              "finished ground-truth runs of its algorithm and task")
        rows = parity_rows(pairs, args.reps, args.seed)
        figures = [parity_figure(setting, {"preferences": a, "true reward": b}, out,
                                 f"ground_truth_{a[0].metric}") for setting, a, b in pairs]
        target = out / "against_ground_truth.md"
        command = shlex.join(["python", "experiments/report.py", *sys.argv[1:]])
        target.write_text(ground_truth_markdown(rows, figures, target, command, args.reps))
        write_csv(out / "against_ground_truth.csv", [flat(row) for row in rows])
        for row in rows:
            print(f"against the true reward: {' / '.join(row[c] for c in SETTING)}, {row['metric']}: "
                  f"{verdict(row, ('preferences', 'true reward'))}")
    (out / "report.md").write_text("\n".join(lines))
    write_csv(out / "runs.csv", run_rows)
    write_csv(out / "aggregates.csv", [flat(row) for row in settings])
    write_csv(out / "aggregates_across_tasks.csv", [flat(row) for row in across])
    for note in problems + mixed + alignment_notes:
        print(f"note: {note}")
    if incomplete:
        print(f"{len(incomplete)} runs unfinished, failed or missing: listed in the report")
    print(f"report: {len(runs)} runs ({len(finished)} finished), {len(settings)} settings -> {out / 'report.md'}, "
          f"{len(figures) + len(alignments)} PNGs")
    return out / "report.md"


if __name__ == "__main__":
    args = tyro.cli(Args)
    try:
        if args.docs and args.root is not None:
            raise ReportError("--docs takes no folder: it reads the runs kept under docs/")
        if args.docs:
            rewrite_docs()
        else:
            report(args)
    except ReportError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)
