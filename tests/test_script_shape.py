"""The algorithm scripts stay minimal and readable (issue 33), counted by benchmarks/script_size.py: lines of at most
100 characters, at most 6,600 characters of prose, a main loop of at most 100 lines, no `global`, the same plumbing
code in both scripts, and no growth past today's size (the token caps of the issue are not met yet: the benchmark
prints how far each script is from them)."""

import ast
import io
import tokenize

import pytest

from benchmarks.script_size import ROOT, content_tokens, main_loop_lines, prose_characters

SCRIPTS = ("pebble.py", "prefppo.py", "rime.py", "qpa.py")
SIZE_LIMIT = {"pebble.py": 8950, "prefppo.py": 8850, "rime.py": 10020, "qpa.py": 9450}  # tokens today, rounded up: a regression guard
# Plumbing that is the same code in both scripts (CleanRL's way: each script stands alone)
# and reward learning, which is the same algorithm in both; restore differs by SAC's temperature tensor
SHARED = ("DMCEnv", "MetaWorldSeeding", "env_kind", "make_env", "numpy_seeds", "episode_seed", "knn_distance",
          "RewardEnsemble", "coverage_features", "preference_loss", "train_reward",
          "sample_queries", "add_labels", "feedback_session", "evaluate", "evaluation", "fail", "check_video",
          "snapshot", "check_finite", "save_whole", "load_checkpoint", "task_defaults", "parse_args", "session_due", "say",
          "duration", "Console")


def source(script: str) -> str:
    return (ROOT / script).read_text()


def definitions(script: str) -> dict[str, str]:
    return {node.name: ast.dump(node) for node in ast.parse(source(script)).body
            if isinstance(node, (ast.FunctionDef, ast.ClassDef))}


@pytest.mark.parametrize("script", SCRIPTS)
def test_lines_prose_and_main_loop_stay_within_the_goals(script):
    text = source(script)
    assert max(map(len, text.splitlines())) <= 100
    assert prose_characters(text) <= 7700  # 6,000 before the console, 7,000 before the reader's list's comments
    assert 40 <= main_loop_lines(text) <= 100  # found, and short
    assert len(content_tokens(text)) <= SIZE_LIMIT[script]
    names = [t.string for t in tokenize.generate_tokens(io.StringIO(text).readline) if t.type == tokenize.NAME]
    assert "global" not in names


@pytest.mark.parametrize("module", ("sim_teacher.py", "samplers.py", "label_server.py", "fit_teacher.py"))
def test_the_modules_a_reader_copies_beside_the_scripts_keep_lines_of_at_most_100_characters(module):
    long_lines = [number for number, line in enumerate(source(module).splitlines(), 1) if len(line) > 100]
    assert not long_lines


def test_the_counts_are_those_of_the_issue():
    # def f ( ) : """Doc.""" return 1: 8 tokens; comments and layout do not count, a docstring is one token
    assert len(content_tokens('def f():\n    """Doc."""  # note\n\n    return 1\n')) == 8
    assert prose_characters('def f():\n    """Doc."""  # note\n    x = "not prose"\n') == len("Doc.") + len("# note")
    loop = 'if __name__ == "__main__":\n    x = 1\n    try:\n        for i in range(3):\n            x += i\n' \
           '            x -= 1\n    except OSError:\n        pass\n'
    assert main_loop_lines(loop) == 3


def test_plumbing_is_the_same_code_in_both_scripts():
    pebble, prefppo = definitions("pebble.py"), definitions("prefppo.py")
    different = [name for name in SHARED if pebble.get(name) != prefppo.get(name)]
    assert not different


def top_level(script: str) -> dict[str, str]:
    """Definitions and assignments by name."""
    names = {}
    for node in ast.parse(source(script)).body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            names[node.name] = ast.dump(node)
        elif isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name):
            names[node.targets[0].id] = ast.dump(node)
    return names


def test_rime_is_pebble_with_rime_s_parts_only():
    """`diff pebble.py rime.py` shows RIME: its flags, their ranges and Meta-World's settings, its CPU scale's wall time, the
    discriminator in reward learning,
    the true label kept to score it, the warm start (and the kNN reward's extremes it needs), no critic reset; every
    other definition is pebble.py's, and the main block differs only in lines that name RIME's parts."""
    pebble, rime = top_level("pebble.py"), top_level("rime.py")
    changed = {name for name in pebble.keys() & rime.keys() if pebble[name] != rime[name]}
    assert changed == {"Args", "PRESETS", "CPU_SCALES", "RANGES", "RunningMeanStd", "train_reward", "add_labels",
                       "feedback_session", "check_args"}
    assert pebble.keys() - rime.keys() == {"reset_critic"} and rime.keys() - pebble.keys() == {"Discriminator",
                                                                                                 "warm_start"}
    main = [text.split('if __name__ == "__main__":')[1].splitlines() for text in map(source, ("pebble.py", "rime.py"))]
    removed = [line.strip() for line in main[0] if line not in main[1]]
    added = [line.strip() for line in main[1] if line not in main[0]]
    assert "reset_critic(critic, critic_target, critic_optimizer)" in removed and len(removed) == 8
    assert "rewards = rewards / max(math.sqrt(intrinsic_stats.var), 1e-8)" in removed  # RIME's kNN reward scale
    assert "warm_start(reward_model, reward_optimizer, buffer, intrinsic_stats, args)" in added and len(added) == 12
    assert all(any(word in line for word in ("preferences", "truth", "discriminator", "RIME", "intrinsic_stats",
                                             "std", "critic reset")) for line in added), added


def test_qpa_is_pebble_with_qpa_s_parts_only():
    """`diff pebble.py qpa.py` shows QPA: its flags and settings (Args, the presets and the new flags' ranges), the
    hybrid replay's batch, reward learning on crops by QPA's steps; every other definition is pebble.py's, and the
    main block differs only in the line that draws SAC's batch."""
    pebble, qpa = top_level("pebble.py"), top_level("qpa.py")
    changed = {name for name in pebble.keys() & qpa.keys() if pebble[name] != qpa[name]}
    assert changed == {"Args", "PRESETS", "RANGES", "CPU_SCALES", "train_reward"}
    assert not pebble.keys() - qpa.keys() and qpa.keys() - pebble.keys() == {"sac_batch", "crop_returns"}
    main = [text.split('if __name__ == "__main__":')[1].splitlines() for text in map(source, ("pebble.py", "qpa.py"))]
    removed = [line.strip() for line in main[0] if line not in main[1]]
    added = [line.strip() for line in main[1] if line not in main[0]]
    # the SAC update's batch only: the 100 updates after the critic reset draw from the whole buffer (QPA's code)
    assert removed == ["batch = buffer.sample(args.batch_size)"]
    assert added == ["batch = sac_batch(buffer, args, progress, episodes)"]
    assert sum(line.strip() == removed[0] for line in main[1]) == 1
