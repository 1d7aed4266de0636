"""B-Pref's findings at CPU scale (docs/bpref.md), rebuilt from the runs kept under docs/: the findings table, one
figure per task (normalised IQM per teacher, PEBBLE and PrefPPO side by side), the samplers', the schedules', and
each block of runs with its grid preset and the core-hours it took. Docs: docs/bpref.md

    python experiments/report.py --docs     # rewrites docs/bpref.md's generated blocks and docs/bpref/*.png

A block's runs are kept with `python experiments/keep_runs.py runs/<root>/<run>... --to docs/bpref/data/<folder>`;
the oracle and mistake runs it is compared with are the ones kept for the parity, RIME and task reports.
"""

import csv
import functools
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

import grid  # noqa: E402
import report  # noqa: E402

FIGURES = ROOT / "docs" / "bpref"
DATA = FIGURES / "data"
REPS, SEED = report.DOCS_REPS, report.DOCS_SEED  # bootstrap replications and seed of every interval on the page
SMOOTHED = "mistake(label_smoothing=0.1)"  # the label-smoothing runs' teacher (report.setting_of)
# Where each task's runs are kept: the blocks' own folders first, then the runs they are compared with
POOLS = {
    "walker-walk": ("docs/bpref/data/walker-walk", "docs/bpref/data/walker-walk-smoothing",
                    "docs/bpref/data/walker-walk-prefppo", "docs/parity/data/ours"),
    "quadruped-walk": ("docs/bpref/data/quadruped-walk", "docs/tasks/data/quadruped-walk",
                       "docs/tasks/data/quadruped-walk-prefppo"),
    "button-press": ("docs/bpref/data/button-press", "docs/tasks/data/button-press",
                     "docs/tasks/data/button-press-prefppo"),
    "sweep-into": ("docs/tasks/data/sweep-into-250k", "docs/tasks/data/sweep-into-prefppo"),
}
# The skip and equal teachers with the reference's thresholds (--edits reference-thresholds), kept apart from the
# rest: a run's config.json does not say its edits
EDITED = {"walker-walk": "docs/bpref/data/walker-walk-reference-thresholds",
          "quadruped-walk": "docs/bpref/data/quadruped-walk-reference-thresholds"}
MANIPULATION = ("button-press", "sweep-into")
# A finding's verdict waits until its block's runs are all kept (its numbers show as they come); F3's, per pair
FINDING_PRESETS = {"F1": "bpref-walker-prefppo", "F2": "bpref-quadruped-walk", "F4": "bpref-walker-samplers",
                   "F4a": "bpref-walker-samplers-equal", "F5": "bpref-walker-schedules", "F7": "bpref-walker-smoothing"}
PAIR_PRESETS = {("walker-walk", "pebble"): "bpref-walker-teachers", ("walker-walk", "prefppo"): "bpref-walker-prefppo",
                ("button-press", "pebble"): "bpref-button-press", ("quadruped-walk", "pebble"): "bpref-quadruped-walk"}
COVERAGE = ("coverage", "disagreement-coverage", "entropy-coverage")  # the paper's coverage-based samplers


@dataclass(frozen=True)
class Block:
    letter: str
    preset: str
    folder: str
    """under docs/bpref/data"""
    what: str


BLOCKS = (
    Block("a", "bpref-walker-teachers", "walker-walk", "walker-walk, PEBBLE: stoc, skip, equal, myopic"),
    Block("b", "bpref-walker-samplers", "walker-walk", "walker-walk, PEBBLE (oracle): five samplers"),
    Block("b", "bpref-walker-samplers-equal", "walker-walk", "walker-walk, PEBBLE (equal): six samplers"),
    Block("c", "bpref-walker-schedules", "walker-walk", "walker-walk, PEBBLE (oracle): increase, decay"),
    Block("d", "bpref-walker-smoothing", "walker-walk-smoothing", "walker-walk, PEBBLE (mistake): smoothing 0.1"),
    Block("e", "bpref-walker-prefppo", "walker-walk-prefppo", "walker-walk, PrefPPO: five teachers; PPO"),
    Block("f", "bpref-button-press", "button-press", "button-press, PEBBLE: five teachers"),
    Block("g", "bpref-quadruped-walk", "quadruped-walk", "quadruped-walk, PEBBLE: four teachers"),
    Block("h", "bpref-walker-reference-thresholds", "walker-walk-reference-thresholds",
          "walker-walk, PEBBLE: skip, equal with the reference's thresholds"),
    Block("h", "bpref-quadruped-reference-thresholds", "quadruped-walk-reference-thresholds",
          "quadruped-walk, PEBBLE: skip, equal with the reference's thresholds"),
)


# ---------------------------------------------------------------- the runs


def load_pool(task: str) -> list[report.Run]:
    """The finished runs of our code on a task (report.kept_runs: each seed of a setting once), normalised by their
    algorithm's ground-truth runs."""
    folders = [folder for folder in POOLS[task] if (ROOT / folder).is_dir()]
    runs = [replace(run) for run in report.kept_runs(*folders)  # copies: normalize() writes into them
            if run.setting[0] in ("pebble", "prefppo") and run.setting[1] == task]
    report.normalize(runs)
    return runs


@functools.cache
def pools() -> dict[str, list[report.Run]]:
    return {task: load_pool(task) for task in POOLS}


def load_edited(task: str) -> list[report.Run]:
    """The kept runs with the reference's thresholds on a task, normalised by the task's SAC runs."""
    if not (ROOT / EDITED[task]).is_dir():
        return []
    edited = [replace(run) for run in report.kept_runs(EDITED[task])]
    report.normalize(edited + [replace(run) for run in load_pool(task) if run.is_ground_truth])
    return [run for run in edited if run.setting[0] == "pebble" and run.setting[1] == task]


def arm(runs, algorithm, teacher, sampler="disagreement", schedule="uniform") -> list[report.Run]:
    return [r for r in runs if r.setting[0] == algorithm and r.setting[2] == teacher and r.setting[4] == sampler
            and r.setting[5] == schedule and r.normalized is not None]


def normalised(runs) -> np.ndarray:
    return np.array([r.normalized for r in runs])


@dataclass
class Comparison:
    new: np.ndarray
    base: np.ndarray
    difference: tuple[float, float, float]
    welch_p: float
    call: str
    """higher, lower or none (no difference detected), by report.verdict_word's rule"""
    word: str
    """report.verdict_word's words"""

    def seeds_needed(self) -> int:
        """Seeds a side that would detect a gap of this size with 80% power at the 5% level (the normal
        approximation of a two-sample test, the arms' pooled standard deviation)."""
        spread = np.sqrt((self.new.var(ddof=1) + self.base.var(ddof=1)) / 2)
        gap = abs(self.difference[0])
        return int(np.ceil(2 * ((1.96 + 0.84) * spread / gap) ** 2)) if gap > 0 else 10 ** 6

    def no_better(self) -> bool:
        """A claim of "no better": the CI's upper end within report.LEVEL (15%) of the base's mean."""
        return self.difference[2] <= report.LEVEL * abs(self.base.mean())

    def text(self) -> str:
        point, low, high = self.difference
        words = self.word
        if self.call == "none" and self.seeds_needed() <= 15:
            words += f" (about {self.seeds_needed()} seeds a side would detect a gap this size)"
        return f"{point:+.2f} [{low:+.2f}, {high:+.2f}], {report.p_text(self.welch_p)}: {words}"


def compare(new: np.ndarray, base: np.ndarray) -> Comparison | None:
    """new - base with report.verdict_word's rule (bootstrap CI of the difference and Welch's test); None without two
    runs a side."""
    if min(len(new), len(base)) < 2:
        return None
    row = {"difference": report.difference_ci(new, base, REPS, SEED), "welch_p": report.welch_p(new, base),
           "reference_final_mean": float(base.mean())}
    word = report.verdict_word(row)
    return Comparison(new, base, row["difference"], row["welch_p"], word if word in ("higher", "lower") else "none",
                      word)


def mean_text(values: np.ndarray) -> str:
    return f"{values.mean():.2f} (n = {len(values)})"


def pending(*presets: str) -> str:
    return f"pending: runs of {', '.join(f'`{p}`' for p in presets)} not yet kept"


def kept_of(preset: str) -> tuple[list[Path], int]:
    """The kept run folders of a block's preset and the number of runs it plans."""
    block = next(block for block in BLOCKS if block.preset == preset)
    planned = [run.name for run in grid.expand(grid.PRESETS[preset][1])]
    kept = [DATA / block.folder / name for name in planned if (DATA / block.folder / name / "eval.csv").exists()]
    return kept, len(planned)


def unfinished(preset: str) -> str | None:
    """'pending: k of n runs of `preset` kept' while a block has runs to keep, else None."""
    kept, planned = kept_of(preset)
    return None if len(kept) == planned else f"pending: {len(kept)} of {planned} runs of `{preset}` kept"


# ---------------------------------------------------------------- the findings


@dataclass
class Finding:
    key: str
    claim: str
    experiment: str
    figure: str
    numbers: list[str]
    verdict: str


def f1_pebble_above_prefppo(pool) -> Finding:
    lines = []
    calls = {}
    for task, runs in pool.items():
        pebble = normalised(arm(runs, "pebble", "oracle"))
        prefppo = normalised(arm(runs, "prefppo", "oracle"))
        result = compare(pebble, prefppo)
        if result is None:
            lines.append(f"{task}: {pending('bpref-walker-prefppo') if task == 'walker-walk' else 'too few runs'}")
            continue
        calls[task] = result
        lines.append(f"{task}: PEBBLE {mean_text(pebble)}, PrefPPO {mean_text(prefppo)}; PEBBLE - PrefPPO "
                     f"{result.text()}")
    higher = [task for task, c in calls.items() if c.call == "higher"]
    lower = [task for task, c in calls.items() if c.call == "lower"]
    widest = max(calls, key=lambda task: calls[task].difference[0]) if calls else None
    if not calls:
        verdict = "pending"
    elif len(higher) > len(calls) / 2 and widest in MANIPULATION:
        verdict = f"holds: PEBBLE higher on {len(higher)} of {len(calls)} tasks, most on {widest}"
    elif len(lower) >= len(calls) / 2:
        verdict = f"does not hold: PrefPPO higher on {len(lower)} of {len(calls)} tasks"
    elif len(higher) > len(calls) / 2:
        verdict = f"in part: PEBBLE higher on {len(higher)} of {len(calls)} tasks, but most on {widest}"
    else:
        verdict = (f"not detected at this scale: PEBBLE higher on {len(higher)} of {len(calls)} tasks "
                   f"({', '.join(higher) or 'none'}), the widest gap on {widest}")
    return Finding("F1", "PEBBLE above PrefPPO on most tasks, by most on manipulation",
                   "oracle teacher, each task at its CPU scale (PEBBLE 100K-250K steps, PrefPPO 1M), each "
                   "algorithm normalised by SAC / PPO on the true reward at its scale", "[tasks](#the-tasks)",
                   lines, verdict)


def f2_equal_and_skip_above_oracle(pool, edited=None) -> Finding:
    """The verdict is the paper's teachers' (its adaptive thresholds); edited: {task: runs} with the reference's
    thresholds, each teacher beside the task's oracle on a line of its own."""
    runs = pool["quadruped-walk"]
    oracle = normalised(arm(runs, "pebble", "oracle"))
    lines = []
    calls = []
    for teacher in ("equal", "skip"):
        result = compare(normalised(arm(runs, "pebble", teacher)), oracle)
        if result is None:
            lines.append(f"{teacher}: {pending('bpref-quadruped-walk')}")
            continue
        calls.append(result.call)
        lines.append(f"{teacher} {mean_text(result.new)} against the oracle's {mean_text(oracle)}: "
                     f"{teacher} - oracle {result.text()}")
    for task, runs in (edited or {}).items():
        for teacher in ("equal", "skip"):
            result = compare(normalised(arm(runs, "pebble", teacher)), normalised(arm(pool[task], "pebble", "oracle")))
            if result is not None:
                lines.append(f"{task}, the reference's thresholds: {teacher} {mean_text(result.new)}: {teacher} - "
                             f"oracle {result.text()}")
    if len(calls) < 2:
        verdict = "pending"
    elif calls == ["higher", "higher"]:
        verdict = "holds: both above the oracle"
    elif "lower" in calls:
        verdict = "does not hold: below the oracle"
    else:
        verdict = "not detected at this scale (the intervals beside)"
    return Finding("F2", "on quadruped-walk, the equal and skip teachers above the oracle",
                   "PEBBLE, quadruped-walk, 250K steps, 1000 labels", "[quadruped-walk](#the-tasks)", lines, verdict)


def f3_mistake_and_stoc_hurt_most(pool, waiting=None) -> Finding:
    """Per task and algorithm that ran all six teachers: holds where mistake and stoc are the two lowest and both
    below the oracle; does not hold where either is above the oracle or another teacher is below either of them
    (each a comparison by the rule above); else not detected. waiting: {(task, algorithm): text} for the pairs
    whose block is not all kept (no verdict yet)."""
    lines = []
    outcomes = {}
    for task, runs in pool.items():
        for algorithm in ("pebble", "prefppo"):
            means = {t: normalised(arm(runs, algorithm, t)) for t in report.TEACHERS}
            if any(len(values) < 2 for values in means.values()):
                continue
            pair = f"{task} {report.ARM_NAMES[(algorithm, False)]}"
            if (waiting or {}).get((task, algorithm)):
                lines.append(f"{pair}: {waiting[(task, algorithm)]}")
                continue
            calls = {t: compare(values, means["oracle"]) for t, values in means.items() if t != "oracle"}
            ranked = sorted(means, key=lambda t: means[t].mean())
            hurt_more = [f"{t} below {worst}" for t in ("skip", "equal", "myopic") for worst in ("mistake", "stoc")
                         if compare(means[t], means[worst]).call == "lower"]
            if set(ranked[:2]) == {"mistake", "stoc"} and calls["mistake"].call == calls["stoc"].call == "lower":
                outcomes[pair] = "holds"
            elif "higher" in (calls["mistake"].call, calls["stoc"].call) or hurt_more:
                outcomes[pair] = "does not hold"
            else:
                outcomes[pair] = "not detected"
            lines.append(f"{pair}: lowest first {', '.join(f'{t} {means[t].mean():.2f}' for t in ranked)}; "
                         f"mistake - oracle {calls['mistake'].text()}; stoc - oracle {calls['stoc'].text()}"
                         + "".join(f"; {text}" for text in hurt_more))
    if not outcomes:
        verdict = "pending"
        lines.append(pending("bpref-walker-teachers", "bpref-walker-prefppo", "bpref-button-press",
                             "bpref-quadruped-walk"))
    elif all(o == "holds" for o in outcomes.values()) and any("PrefPPO" in pair for pair in outcomes):
        verdict = f"holds on {', '.join(outcomes)}"
    elif all(o == "holds" for o in outcomes.values()):
        verdict = f"in part: holds on {', '.join(outcomes)}; PrefPPO not yet run with the six teachers"
    elif "does not hold" in outcomes.values():
        verdict = f"does not hold on {', '.join(p for p, o in outcomes.items() if o == 'does not hold')}"
    else:
        verdict = f"not detected at this scale on {', '.join(p for p, o in outcomes.items() if o != 'holds')}"
    return Finding("F3", "the mistake and stoc teachers hurt both algorithms most",
                   "the six teachers on each task and algorithm that ran all six", "[tasks](#the-tasks)", lines,
                   verdict)


def f4_uncertainty_samplers(pool, speed: dict[str, float]) -> Finding:
    runs = pool["walker-walk"]
    uniform = normalised(arm(runs, "pebble", "oracle", sampler="uniform"))
    lines = []
    calls = {}
    for sampler in ("disagreement", "entropy", *COVERAGE):
        result = compare(normalised(arm(runs, "pebble", "oracle", sampler=sampler)), uniform)
        if result is None:
            lines.append(f"{sampler}: {pending('bpref-walker-samplers')}")
            continue
        calls[sampler] = result
        lines.append(f"{sampler} {mean_text(result.new)}, uniform {mean_text(uniform)}: {sampler} - uniform "
                     f"{result.text()}")
    if speed:
        lines.append("query selection per session, x disagreement's: " + ", ".join(
            f"{sampler} {ratio:.2f}" for sampler, ratio in speed.items()))
    if len(calls) < 5:
        verdict = "pending"
    else:
        uncertainty_up = calls["disagreement"].call == calls["entropy"].call == "higher"
        coverage_flat = all(calls[s].no_better() for s in COVERAGE)
        slower = all(speed.get(s, 0) > 1 for s in COVERAGE)
        if uncertainty_up and coverage_flat and slower:
            verdict = "holds"
        elif "lower" in (calls["disagreement"].call, calls["entropy"].call) or any(
                calls[s].call == "higher" for s in COVERAGE):
            verdict = "does not hold"
        else:
            verdict = "not detected at this scale: " + "; ".join(samplers_undecided(calls, slower))
    return Finding("F4", "uncertainty samplers (disagreement, entropy) above uniform; coverage samplers no better "
                   "than uniform, and slower", "PEBBLE (oracle), walker-walk, 100K steps, 1000 labels; seconds "
                   "from benchmarks/sampler_speed.py", "[samplers](#samplers-and-schedules)", lines, verdict)


def samplers_undecided(calls: dict[str, Comparison], slower: bool) -> list[str]:
    """F4's three parts in words where the finding is not decided: the uncertainty samplers against uniform (with
    the seeds a side that would detect their gaps), the coverage samplers' intervals, their speed."""
    parts = ["disagreement and entropy above uniform"]
    not_up = [s for s in ("disagreement", "entropy") if calls[s].call != "higher"]
    if not_up:
        seeds = " and ".join(str(calls[s].seeds_needed()) for s in not_up)
        gaps = "their gaps" if len(not_up) > 1 else "its gap"
        parts = [f"{' and '.join(not_up)} not detected above uniform (about {seeds} seeds a side would detect {gaps})"]
    wide = [s for s in COVERAGE if not calls[s].no_better()]
    if wide:
        parts.append(f"{', '.join(wide)}: the CI reaches a gain above 15% of uniform's mean, too wide to call no "
                     "better")
    else:
        parts.append("the coverage samplers level with uniform")
    parts.append("the coverage samplers slower" if slower else "the coverage samplers not slower")
    return parts


def equal_share(run: report.Run) -> float | None:
    """Share of the kept answers that were 'equally preferable', over the sessions after the first (the first
    session samples uniformly whatever the sampler); None without labels.csv."""
    path = run.path / "labels.csv"
    if not path.exists():
        return None
    with open(path) as f:
        rows = list(csv.DictReader(f))[1:]
    answered = sum(int(r["queries"]) - int(r["skipped"]) for r in rows)
    return sum(int(r["equal"]) for r in rows) / answered if answered else None


def f4a_equal_answers(pool) -> Finding:
    runs = pool["walker-walk"]
    shares = {}
    returns = {}
    for sampler in ("uniform", "disagreement", "entropy", "coverage", "disagreement-coverage", "entropy-coverage"):
        group = arm(runs, "pebble", "equal", sampler=sampler)
        shares[sampler] = np.array([s for s in map(equal_share, group) if s is not None])
        returns[sampler] = normalised(group)
    lines = []
    calls = {}
    for sampler in shares:
        if len(shares[sampler]) < 2:
            lines.append(f"{sampler}: {pending('bpref-walker-samplers-equal')}")
            continue
        lines.append(f"{sampler}: equal answers {shares[sampler].mean():.1%}, normalised return "
                     f"{mean_text(returns[sampler])}")
    for sampler in ("disagreement", "entropy"):
        share = compare(shares[sampler], shares["uniform"])
        learned = compare(returns[sampler], returns["uniform"])
        if share and learned:
            calls[sampler] = (share.call, learned.call)
            lines.append(f"{sampler} - uniform: equal share {share.text()}; return {learned.text()}")
    if len(calls) < 2:
        verdict = "pending"
    elif all(c == ("higher", "higher") for c in calls.values()):
        verdict = "holds"
    elif any("lower" in c for c in calls.values()):
        verdict = "does not hold"
    else:
        words = {"higher": "above", "none": "not told apart from"}  # a "lower" call does not hold (above)
        verdict = "not detected at this scale: " + "; ".join(
            f"{s}: equal share {words[a]} uniform's, return {words[b]} uniform's" for s, (a, b) in calls.items())
    return Finding("F4a", "under the equal teacher, uncertainty samplers receive more equal answers yet learn more",
                   "PEBBLE (equal), walker-walk, 100K steps, 1000 labels, 3 seeds; share over sessions 2-10",
                   "[samplers](#samplers-and-schedules)", lines, verdict)


def f5_schedules(pool) -> Finding:
    runs = pool["walker-walk"]
    uniform = normalised(arm(runs, "pebble", "oracle"))
    lines = []
    calls = []
    for schedule in ("increase", "decay"):
        result = compare(normalised(arm(runs, "pebble", "oracle", schedule=schedule)), uniform)
        if result is None:
            lines.append(f"{schedule}: {pending('bpref-walker-schedules')}")
            continue
        calls.append(result)
        lines.append(f"{schedule} {mean_text(result.new)}, uniform {mean_text(uniform)}: {schedule} - uniform "
                     f"{result.text()}")
    if len(calls) < 2:
        verdict = "pending"
    elif any(c.call == "higher" for c in calls):
        verdict = "does not hold: a schedule above uniform"
    elif all(c.no_better() for c in calls):
        verdict = "holds: neither above uniform by more than 15% (the intervals beside)"
    else:
        verdict = "not detected at this scale: an interval reaches a gain above 15% of uniform's"
    return Finding("F5", "increase and decay schedules no better than uniform at the same budget",
                   "PEBBLE (oracle), walker-walk, 100K steps, 1000 labels", "[samplers](#samplers-and-schedules)",
                   lines, verdict)


def f6_alignment(pool) -> Finding:
    lines = []
    lows = {}
    for task, runs in pool.items():
        r = np.array([run.rows[-1]["reward_correlation"] for run in arm(runs, "pebble", "oracle")])
        r = r[np.isfinite(r)]
        if len(r) < 2:
            continue
        draws = np.random.default_rng(SEED).choice(r, (REPS, len(r))).mean(1)
        low, high = np.percentile(draws, [2.5, 97.5])
        lows[task] = low
        lines.append(f"{task}: r = {r.mean():.2f} [{low:.2f}, {high:.2f}] (n = {len(r)})")
    strong = [task for task, low in lows.items() if low > 0.5]
    if not lows:
        verdict = "pending"
    elif len(strong) == len(lows):
        verdict = "holds on every task (r's CI above 0.5)"
    elif all(low > 0 for low in lows.values()):
        verdict = (f"in part: strong on {', '.join(strong) or 'no task'} (r's CI above 0.5), weaker on "
                   f"{', '.join(t for t in lows if t not in strong)} (r > 0, its CI reaching below 0.5)")
    else:
        verdict = "does not hold: r's CI reaches 0 on " + ", ".join(t for t, low in lows.items() if low <= 0)
    return Finding("F6", "the learned reward is aligned with the true one (tanh-bounded, at another scale)",
                   "PEBBLE (oracle), each task at its CPU scale: Pearson r of r_hat and the true reward per step "
                   "over the last evaluation's 10 episodes", "[tasks](#the-tasks)", lines, verdict)


def f7_label_smoothing(pool) -> Finding:
    runs = pool["walker-walk"]
    mistake = normalised(arm(runs, "pebble", "mistake"))
    result = compare(normalised(arm(runs, "pebble", SMOOTHED)), mistake)
    if result is None:
        lines = [pending("bpref-walker-smoothing")]
        verdict = "pending"
    else:
        lines = [f"smoothing {mean_text(result.new)}, without {mean_text(mistake)}: smoothing - without "
                 f"{result.text()}"]
        if result.call == "higher":
            verdict = "does not hold: smoothing helps"
        elif result.no_better():
            verdict = "holds: smoothing no better by more than 15% (the interval beside)"
        else:
            verdict = "not detected at this scale: the interval reaches a gain above 15%"
    return Finding("F7", "label smoothing does not help against wrong labels",
                   "PEBBLE, mistake teacher (eps 0.1), walker-walk, 100K steps, 1000 labels", "-", lines, verdict)


def sampler_speed() -> dict[str, float]:
    """Query selection's seconds per session as a multiple of disagreement's, at 900 labelled pairs, from the kept
    output of benchmarks/sampler_speed.py (docs/bpref/sampler_speed.md); {} without it."""
    path = FIGURES / "sampler_speed.md"
    if not path.exists():
        return {}
    ratios = {}
    for line in path.read_text().splitlines():
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        if len(cells) == 5 and cells[0] in grid.SAMPLERS:
            ratios[cells[0]] = float(cells[4])
    return ratios


# ---------------------------------------------------------------- figures and blocks


def teacher_rows(runs) -> list[dict]:
    """The paper's Figure 2 on a task: IQM per teacher and algorithm (their budgets differ: set aside)."""
    default = [r for r in runs if r.setting[4:] == ("disagreement", "uniform") and r.setting[2] != SMOOTHED
               and r.normalized is not None]  # PrefPPO waits for its PPO runs on walker-walk
    budgets = sorted({(r.setting[0], r.setting[3]) for r in default if r.setting[3] != "-"})
    label = ", ".join(f"{algorithm} {budget}" for algorithm, budget in budgets)
    return [row | {"budget": label} for row in report.setting_aggregates(default, REPS, SEED)]


def design_rows(column: str) -> list[dict]:
    """walker-walk, PEBBLE: IQM per sampler (oracle and equal teachers) or per schedule (oracle)."""
    walker = [r for r in pools()["walker-walk"] if r.setting[0] == "pebble"]
    if column == "sampler":
        runs = [r for r in walker if r.setting[5] == "uniform" and r.setting[2] in ("oracle", "equal")]
    else:
        runs = [r for r in walker if r.setting[4] == "disagreement" and r.setting[2] == "oracle"]
    return report.setting_aggregates(runs, REPS, SEED)


def draw_figures(folder: Path) -> None:
    """docs/bpref/teachers_<task>.png per task, samplers_walker-walk.png and schedules_walker-walk.png."""
    folder.mkdir(parents=True, exist_ok=True)
    for runs in pools().values():
        report.bar_figures(teacher_rows(runs), "teacher", "algorithm", ("task",), folder, "teachers",
                           "IQM normalised return per teacher")
    for column in ("sampler", "schedule"):
        report.bar_figures(design_rows(column), column, "teacher", ("task",), folder, f"{column}s",
                           f"IQM normalised return per {column}")


def task_figures_block() -> str:
    return "\n\n".join(f"![teachers on {task}](bpref/teachers_{task}.png)" for task, runs in pools().items()
                        if teacher_rows(runs))


def design_figures_block() -> str:
    return "\n\n".join(f"![{column}s on walker-walk](bpref/{column}s_walker-walk.png)"
                        for column in ("sampler", "schedule") if design_rows(column))


def blocks_block() -> str:
    """Per block: its preset, the runs kept of those it plans and the core-hours they took (one thread a run)."""
    rows = []
    for block in BLOCKS:
        kept, planned = kept_of(block.preset)
        seconds = sum(grid.read_eval(path)[-1]["wall_time"] for path in kept)
        rows.append([block.letter, block.what, f"`{block.preset}`", f"{len(kept)} of {planned}",
                     f"{seconds / 3600:.1f}"])
    return "\n".join(report.table(["block", "runs", "preset", "kept", "core-hours"], rows))


def findings(pool) -> list[Finding]:
    """Every finding; a verdict resting on a block with runs still to keep reads 'pending: k of n runs kept'."""
    waiting = {pair: unfinished(preset) for pair, preset in PAIR_PRESETS.items()}
    edited = {task: load_edited(task) for task in EDITED}
    found = [f1_pebble_above_prefppo(pool), f2_equal_and_skip_above_oracle(pool, edited),
             f3_mistake_and_stoc_hurt_most(pool, waiting), f4_uncertainty_samplers(pool, sampler_speed()),
             f4a_equal_answers(pool), f5_schedules(pool), f6_alignment(pool), f7_label_smoothing(pool)]
    for finding in found:
        waits = unfinished(FINDING_PRESETS[finding.key]) if finding.key in FINDING_PRESETS else None
        finding.verdict = waits or finding.verdict
    return found


def findings_block() -> str:
    found = findings(pools())
    holding = sum(f.verdict.startswith("holds") for f in found)
    in_part = sum(f.verdict.startswith("in part") for f in found)
    lines = [f"{holding} of {len(found)} findings hold at this scale, {in_part} in part.", ""]
    lines += report.table(["", "finding", "experiment", "figure", "our numbers (95% CIs)", "verdict"],
                          [[f.key, f.claim, f.experiment, f.figure, "<br>".join(f.numbers), f.verdict]
                           for f in found])
    return "\n".join(lines)
