"""experiments/bpref.py: B-Pref's findings from kept runs whose right verdicts are known by construction
(tests/test_generated_docs.py checks that the committed docs/bpref.md equals its rebuild)."""

import json

import numpy as np
import pytest

import bpref


def keep(folder, name, seed, final, teacher="oracle", sampler="disagreement", schedule="uniform", truth=False,
         smoothing=0.0, shares=None, prefppo=False):
    """A kept walker-walk PEBBLE run (config.json, eval.csv; labels.csv with the equal answers of `shares`, one
    number a session, 10 queries each)."""
    path = folder / name
    path.mkdir(parents=True)
    config = {"exp_name": "pebble", "env_id": "walker-walk", "seed": seed, "teacher": teacher, "sampler": sampler,
              "schedule": schedule, "max_feedback": 1000, "feedback_per_session": 100, "ground_truth_reward": truth,
              "total_timesteps": 100000, "label_smoothing": smoothing}
    if prefppo:  # report.setting_of tells PrefPPO's config by its num_envs
        config |= {"exp_name": "prefppo", "num_envs": 8}
    (path / "config.json").write_text(json.dumps(config))
    (path / "eval.csv").write_text("step,episode_return,success_rate,reward_correlation,wall_time\n"
                                   f"50000,10.0,0.0,0.5,600\n100000,{final},0.0,0.8,1200\n")
    if shares is not None:
        rows = [f"{i},{10001 + 9000 * i},10,0,{round(10 * share)}" for i, share in enumerate(shares)]
        (path / "labels.csv").write_text("session,step,queries,skipped,equal\n" + "\n".join(rows) + "\n")


@pytest.fixture
def walker(tmp_path, monkeypatch):
    """SAC 1000; oracle with disagreement 900-940, entropy 880-920, uniform 500-520, the coverage samplers about
    uniform's; schedules increase 400-420 (lower), decay 890-950 (level); mistake 400-420, with smoothing 700-720;
    the equal teacher: uniform samples 10-20% equal answers after its first session and ends at 510-530,
    disagreement and entropy 30-50% and 920-960."""
    data = tmp_path / "data"
    finals = {("oracle", "disagreement", "uniform"): (900, 920, 940), ("oracle", "entropy", "uniform"): (880, 900, 920),
              ("oracle", "uniform", "uniform"): (500, 510, 520), ("oracle", "coverage", "uniform"): (500, 520, 540),
              ("oracle", "disagreement-coverage", "uniform"): (505, 515, 525),
              ("oracle", "entropy-coverage", "uniform"): (495, 515, 535),
              ("oracle", "disagreement", "increase"): (400, 410, 420),
              ("oracle", "disagreement", "decay"): (890, 900, 950), ("mistake", "disagreement", "uniform"): (400, 410, 420)}
    for (teacher, sampler, schedule), values in finals.items():
        for seed, final in enumerate(values, 1):
            keep(data, f"{teacher}_{sampler}_{schedule}_{seed}", seed, final, teacher, sampler, schedule)
    for seed, final in enumerate((1000, 990, 1010), 1):
        keep(data, f"sac_{seed}", seed, final, truth=True)
        keep(data, f"smoothing_{seed}", seed, 690 + 10 * seed, "mistake", smoothing=0.1)
        keep(data, f"equal_uniform_{seed}", seed, 500 + 10 * seed, "equal", "uniform",
             shares=[0.9] + [(0.1, 0.2, 0.1)[seed - 1]] * 9)
        for sampler in ("disagreement", "entropy"):
            keep(data, f"equal_{sampler}_{seed}", seed, 900 + 20 * seed, "equal", sampler,
                 shares=[0.1] + [0.2 + 0.1 * seed] * 9)
    monkeypatch.setattr(bpref, "POOLS", {"walker-walk": (str(data),)})
    return {"walker-walk": bpref.load_pool("walker-walk")}


def test_uncertainty_samplers_above_uniform_and_coverage_level_and_slower_is_f4_holding(walker):
    slower = {"coverage": 1.3, "disagreement-coverage": 1.29, "entropy-coverage": 1.26}
    finding = bpref.f4_uncertainty_samplers(walker, slower)
    assert finding.verdict == "holds"
    assert any(line.startswith("disagreement 0.92 (n = 3), uniform 0.51 (n = 3): disagreement - uniform +0.41 [")
               and line.endswith(": higher")
               for line in finding.numbers)
    assert any(line.startswith("coverage") and line.endswith("no difference detected, level")
               for line in finding.numbers)
    # coverage - uniform: +0.015, pooled spread 0.016: 2 x (2.8 x 0.016 / 0.015)^2 = 18 seeds, too many to say
    assert not any("seeds a side would" in line for line in finding.numbers)
    not_slower = slower | {"coverage": 0.9}
    assert bpref.f4_uncertainty_samplers(walker, not_slower).verdict == (
        "not detected at this scale: disagreement and entropy above uniform; the coverage samplers level with uniform; "
        "the coverage samplers not slower")


def test_f4_undecided_names_the_seeds_that_would_decide_it_and_the_wide_coverage_intervals(tmp_path, monkeypatch):
    # normalised by SAC's 1000: uniform 0.5-0.7; disagreement 0.03 and entropy 0.05 above it, each sd 0.1:
    # 2 x (2.8 x 0.1 / 0.03)^2 = 174.2 -> 175 and 2 x (2.8 x 0.1 / 0.05)^2 = 62.7 -> 63 seeds a side;
    # the coverage samplers 0.4-0.8, whose CIs reach far above 15% of uniform's 0.6
    finals = {"uniform": (500, 600, 700), "disagreement": (530, 630, 730), "entropy": (550, 650, 750),
              **{sampler: (400, 600, 800) for sampler in bpref.COVERAGE}}
    for sampler, values in finals.items():
        for seed, final in enumerate(values, 1):
            keep(tmp_path, f"{sampler}_{seed}", seed, final, sampler=sampler)
    for seed, final in enumerate((1000, 990, 1010), 1):
        keep(tmp_path, f"sac_{seed}", seed, final, truth=True)
    monkeypatch.setattr(bpref, "POOLS", {"walker-walk": (str(tmp_path),)})
    pool = {"walker-walk": bpref.load_pool("walker-walk")}
    slower = {"coverage": 1.3, "disagreement-coverage": 1.29, "entropy-coverage": 1.26}
    assert bpref.f4_uncertainty_samplers(pool, slower).verdict == (
        "not detected at this scale: disagreement and entropy not detected above uniform (about 175 and 63 seeds a "
        "side would detect their gaps); coverage, disagreement-coverage, entropy-coverage: the CI reaches a gain "
        "above 15% of uniform's mean, too wide to call no better; the coverage samplers slower")


def test_a_schedule_below_and_one_level_with_uniform_is_f5_holding(walker):
    finding = bpref.f5_schedules(walker)
    assert finding.verdict.startswith("holds")
    assert finding.numbers[0].endswith(": lower")
    # decay - uniform: -0.0067, pooled spread 0.027: 2 x (2.8 x 0.027 / 0.0067)^2 = 253 seeds: not said
    assert finding.numbers[1].endswith("no difference detected, level")


def test_smoothing_that_lifts_the_mistake_teacher_s_runs_is_f7_not_holding(walker):
    finding = bpref.f7_label_smoothing(walker)
    assert finding.verdict == "does not hold: smoothing helps"
    assert finding.numbers[0].startswith("smoothing 0.71 (n = 3), without 0.41 (n = 3)")


def test_equal_answers_are_counted_after_the_uniform_first_session(walker):
    finding = bpref.f4a_equal_answers(walker)
    assert "uniform: equal answers 13.3%, normalised return 0.52 (n = 3)" in finding.numbers
    assert "entropy: equal answers 40.0%, normalised return 0.94 (n = 3)" in finding.numbers
    assert finding.verdict == "holds"


def test_f4a_undecided_says_which_part_is_not_told_apart(tmp_path, monkeypatch):
    # the uncertainty samplers learn more (0.92 against 0.51) but receive uniform's share of equal answers
    for seed, share in enumerate((0.1, 0.2, 0.1), 1):
        keep(tmp_path, f"sac_{seed}", seed, (1000, 990, 1010)[seed - 1], truth=True)
        keep(tmp_path, f"uniform_{seed}", seed, 500 + 10 * seed, "equal", "uniform", shares=[0.9] + [share] * 9)
        for sampler in ("disagreement", "entropy"):
            keep(tmp_path, f"{sampler}_{seed}", seed, 900 + 10 * seed, "equal", sampler, shares=[0.9] + [share] * 9)
    monkeypatch.setattr(bpref, "POOLS", {"walker-walk": (str(tmp_path),)})
    finding = bpref.f4a_equal_answers({"walker-walk": bpref.load_pool("walker-walk")})
    assert finding.verdict == (
        "not detected at this scale: disagreement: equal share not told apart from uniform's, return above uniform's; "
        "entropy: equal share not told apart from uniform's, return above uniform's")


def test_an_undecided_gap_says_how_many_seeds_would_detect_it():
    result = bpref.compare(np.array([1.0, 1.2, 1.4]), np.array([0.8, 1.0, 1.2]))  # gap 0.2, spread 0.2
    assert result.call == "none" and result.seeds_needed() == 16  # 2 x (2.8 x 0.2 / 0.2)^2 = 15.7
    result = bpref.compare(np.array([1.0, 1.2, 1.4]), np.array([0.7, 0.9, 1.1]))  # gap 0.3: 7.0 -> 7
    assert result.call == "none"  # the bootstrap CI excludes 0, Welch's p = 0.14 does not
    assert result.text().endswith("higher by the CI, not by Welch's test (about 7 seeds a side would detect a gap "
                                  "this size)")


def test_findings_without_their_runs_are_pending(walker):
    assert bpref.f2_equal_and_skip_above_oracle(walker | {"quadruped-walk": []}).verdict == "pending"
    assert bpref.f3_mistake_and_stoc_hurt_most(walker).verdict == "pending"  # stoc, skip, myopic never ran



def test_a_verdict_waits_until_its_block_is_all_kept(walker, tmp_path, monkeypatch):
    """The walker fixture's F4 holds; with one of the samplers block's two runs kept it is pending, and F3's
    walker-walk PEBBLE pair waits on the teachers block (its numbers beside, no outcome)."""
    presets = dict(bpref.grid.PRESETS)
    presets["bpref-walker-samplers"] = ("", bpref.grid.Grid(teachers=("oracle",), budgets=("1000/100",), seeds=(1, 2),
                                                           samplers=("uniform",), ground_truth=False))
    monkeypatch.setattr(bpref.grid, "PRESETS", presets)
    monkeypatch.setattr(bpref, "DATA", tmp_path / "blocks")
    monkeypatch.setattr(bpref, "sampler_speed", lambda: {"coverage": 1.3, "disagreement-coverage": 1.29,
                                                         "entropy-coverage": 1.26})
    names = [run.name for run in bpref.grid.expand(presets["bpref-walker-samplers"][1])]
    keep(tmp_path / "blocks" / "walker-walk", names[0], 1, 500)
    walker = walker | {"quadruped-walk": []}
    found = {finding.key: finding for finding in bpref.findings(walker)}
    assert found["F4"].verdict == "pending: 1 of 2 runs of `bpref-walker-samplers` kept"
    assert any(line.startswith("entropy 0.90 (n = 3)") for line in found["F4"].numbers)
    assert found["F5"].verdict.startswith("pending: 0 of 10 runs of `bpref-walker-schedules` kept")
    keep(tmp_path / "blocks" / "walker-walk", names[1], 2, 510)
    assert bpref.f4_uncertainty_samplers(walker, bpref.sampler_speed()).verdict == "holds"
    assert {f.key: f for f in bpref.findings(walker)}["F4"].verdict == "holds"
    six = six_teachers(tmp_path / "data", stoc=450, skip=870)
    waiting = {("walker-walk", "pebble"): "pending: 3 of 20 runs of `bpref-walker-teachers` kept"}
    finding = bpref.f3_mistake_and_stoc_hurt_most(six, waiting)
    assert finding.verdict == "pending"
    assert finding.numbers[0] == "walker-walk PEBBLE: pending: 3 of 20 runs of `bpref-walker-teachers` kept"


def six_teachers(data, stoc, skip, myopic=950):
    """The walker fixture's oracle (0.92), mistake (0.41) and equal (0.94) runs, and three seeds each of stoc, skip
    and myopic ending at the given return + 10, 20, 30."""
    for seed in (1, 2, 3):
        keep(data, f"stoc_{seed}", seed, stoc + 10 * seed, "stoc")
        keep(data, f"skip_{seed}", seed, skip + 10 * seed, "skip")
        keep(data, f"myopic_{seed}", seed, myopic + 10 * seed, "myopic")
    bpref.report.kept_runs.cache_clear()
    return {"walker-walk": bpref.load_pool("walker-walk")}


def test_mistake_and_stoc_lowest_and_below_the_oracle_is_f3_holding_for_pebble_alone(walker, tmp_path):
    finding = bpref.f3_mistake_and_stoc_hurt_most(six_teachers(tmp_path / "data", stoc=450, skip=870))
    assert finding.verdict == "in part: holds on walker-walk PEBBLE; PrefPPO not yet run with the six teachers"
    assert finding.numbers[0].startswith("walker-walk PEBBLE: lowest first mistake 0.41, stoc 0.47, skip 0.89")


def test_another_teacher_below_mistake_and_stoc_is_f3_not_holding(walker, tmp_path):
    finding = bpref.f3_mistake_and_stoc_hurt_most(six_teachers(tmp_path / "data", stoc=450, skip=290))
    assert finding.verdict == "does not hold on walker-walk PEBBLE"
    assert finding.numbers[0].startswith("walker-walk PEBBLE: lowest first skip 0.31, mistake 0.41, stoc 0.47")
    assert finding.numbers[0].endswith("; skip below mistake; skip below stoc")


def test_stoc_level_with_the_oracle_and_nothing_below_it_is_f3_not_detected(walker, tmp_path):
    finding = bpref.f3_mistake_and_stoc_hurt_most(six_teachers(tmp_path / "data", stoc=900, skip=910))
    assert "stoc - oracle +0.00 [" in finding.numbers[0]
    assert finding.verdict == "not detected at this scale on walker-walk PEBBLE"


def test_skip_above_the_oracle_and_equal_level_is_f2_not_detected_and_skip_below_it_not_holding(tmp_path,
                                                                                                 monkeypatch):
    def pool(skip):
        data = tmp_path / f"skip_{skip}"
        for seed in (1, 2, 3):
            keep(data, f"sac_{seed}", seed, 1000, truth=True)
            keep(data, f"oracle_{seed}", seed, 900 + 20 * seed)
            keep(data, f"equal_{seed}", seed, 910 + 20 * seed, "equal")
            keep(data, f"skip_{seed}", seed, skip + 10 * seed, "skip")
        monkeypatch.setattr(bpref, "POOLS", {"walker-walk": (str(data),)})
        return {"quadruped-walk": bpref.load_pool("walker-walk")}

    finding = bpref.f2_equal_and_skip_above_oracle(pool(skip=1000))
    assert finding.numbers[0].startswith("equal 0.95 (n = 3) against the oracle's 0.94 (n = 3): equal - oracle +0.01")
    assert finding.numbers[1].startswith("skip 1.02 (n = 3) against the oracle's 0.94 (n = 3): skip - oracle +0.08")
    assert finding.numbers[1].endswith(": higher")
    assert finding.verdict == "not detected at this scale (the intervals beside)"
    edited = tmp_path / "edited"
    for seed in (1, 2, 3):
        keep(edited, f"equal_{seed}", seed, 1100 + 10 * seed, "equal")
    monkeypatch.setattr(bpref, "EDITED", {"walker-walk": str(edited)})
    quadruped = {"quadruped-walk": bpref.load_pool("walker-walk")}  # still skip=1000's runs
    with_edit = bpref.f2_equal_and_skip_above_oracle(quadruped, {"quadruped-walk": bpref.load_edited("walker-walk")})
    assert with_edit.numbers[2].startswith("quadruped-walk, the reference's thresholds: equal 1.12 (n = 3): equal - "
                                           "oracle +0.18 [")
    assert with_edit.numbers[2].endswith(": higher") and len(with_edit.numbers) == 3  # no skip runs with the edit
    assert with_edit.verdict == finding.verdict  # the verdict is the paper's teachers'
    assert bpref.load_edited("walker-walk")[0].normalized == pytest.approx(1.11)
    assert bpref.f2_equal_and_skip_above_oracle(pool(skip=300)).verdict == "does not hold: below the oracle"


def test_pebble_above_prefppo_with_the_widest_gap_on_manipulation_is_f1_holding(tmp_path, monkeypatch):
    def task(name, pebble, prefppo):
        data = tmp_path / name
        for seed in (1, 2, 3):
            keep(data, f"sac_{seed}", seed, 1000, truth=True)
            keep(data, f"ppo_{seed}", seed, 500, truth=True, prefppo=True)
            keep(data, f"pebble_{seed}", seed, pebble + 10 * seed)
            keep(data, f"prefppo_{seed}", seed, prefppo + 5 * seed, prefppo=True)
        monkeypatch.setattr(bpref, "POOLS", {"walker-walk": (str(data),)})
        return bpref.load_pool("walker-walk")

    # normalised: walker-walk PEBBLE 0.92, PrefPPO 0.84; "button-press" (the same runs' task, named so) 0.92 and 0.44
    pool = {"walker-walk": task("walker", 900, 410), "button-press": task("press", 900, 210)}
    finding = bpref.f1_pebble_above_prefppo(pool)
    assert finding.numbers[0].startswith("walker-walk: PEBBLE 0.92 (n = 3), PrefPPO 0.84 (n = 3); "
                                         "PEBBLE - PrefPPO +0.08")
    assert finding.verdict == "holds: PEBBLE higher on 2 of 2 tasks, most on button-press"
    pool = {"walker-walk": task("walker-wide", 900, 110), "button-press": pool["button-press"]}
    verdict = bpref.f1_pebble_above_prefppo(pool).verdict
    assert verdict == "in part: PEBBLE higher on 2 of 2 tasks, but most on walker-walk"
    pool = {"walker-walk": task("walker-level", 900, 455), "button-press": pool["button-press"]}  # 0.92, 0.92
    assert bpref.f1_pebble_above_prefppo(pool).verdict == ("not detected at this scale: PEBBLE higher on 1 of 2 tasks "
                                                          "(button-press), the widest gap on button-press")
    pool = {"walker-walk": task("walker-low", 300, 410), "button-press": task("press-low", 300, 410)}
    assert bpref.f1_pebble_above_prefppo(pool).verdict == "does not hold: PrefPPO higher on 2 of 2 tasks"


def test_smoothing_within_15_percent_holds_f7_and_a_wide_interval_leaves_it_not_detected(tmp_path, monkeypatch):
    def finding(smoothed):
        data = tmp_path / "_".join(map(str, smoothed))
        for seed, final in enumerate(smoothed, 1):
            keep(data, f"sac_{seed}", seed, 1000, truth=True)
            keep(data, f"mistake_{seed}", seed, 400 + 10 * seed, "mistake")
            keep(data, f"smoothing_{seed}", seed, final, "mistake", smoothing=0.1)
        monkeypatch.setattr(bpref, "POOLS", {"walker-walk": (str(data),)})
        return bpref.f7_label_smoothing({"walker-walk": bpref.load_pool("walker-walk")})

    # without smoothing 0.42: 15% of it is 0.063
    assert finding((400, 410, 420)).verdict == "holds: smoothing no better by more than 15% (the interval beside)"
    wide = finding((300, 420, 600))  # mean 0.44, its CI reaching about +0.15
    assert wide.verdict == "not detected at this scale: the interval reaches a gain above 15%"
    assert wide.numbers[0].startswith("smoothing 0.44 (n = 3), without 0.42 (n = 3): smoothing - without +0.02 [")
