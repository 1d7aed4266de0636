"""The reference code's ways (its defects) as text edits of our scripts, for parity runs and ablations.

The scripts do only the fixed way; what reproduces the old reference code lives here, applied to a copy:

    python benchmarks/reference/edits.py raw-reward-inputs -- pebble.py --env-id walker-walk ...   # runs it
    python benchmarks/reference/edits.py raw-reward-inputs --write /tmp/pebble_raw.py -- pebble.py  # writes it

Each edit replaces text that occurs exactly once in the script (else it fails, naming the edit), so an edit
that no longer fits the script is found at once. The edited script runs as __main__ with the repository on
sys.path, so it imports sim_teacher and samplers as the original does; --resume works as for the script.
"""

import argparse
import linecache
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

# name -> {script: [(old text, new text), ...]}; docs/differences.md gives each one's measured effect
EDITS = {
    # The reference PEBBLE's (and RIME's, QPA's code's) reward model sees raw observations (differences.md 17, 22)
    "raw-reward-inputs": {
        "pebble.py": [(
            "    reward_model.set_input_stats(states[..., : segments[\"obs0\"].shape[-1]].flatten(0, 1))\n",
            "")],
        "qpa.py": [(
            "    reward_model.set_input_stats(states[..., : segments[\"obs0\"].shape[-1]].flatten(0, 1))\n",
            "")],
        "prefppo.py": [(
            "    reward_model.set_input_stats(states[..., : segments[\"obs0\"].shape[-1]].flatten(0, 1))\n",
            "")],
        "rime.py": [(
            "    reward_model.set_input_stats(states[..., : segments[\"obs0\"].shape[-1]].flatten(0, 1))\n",
            ""), ("        reward_model.set_input_stats(buffer.obs[: buffer.size])\n", "        pass\n")],
    },
    # The reference's skip and equal thresholds: eps applied twice after the first session (defect 1,
    # differences.md 1), 10x smaller with eps = 0.1
    "reference-thresholds": {script: [(
        "    teacher.set_thresholds(mean_return, args.segment_len, episode_len)\n",
        "    teacher.set_thresholds(mean_return, args.segment_len, episode_len)  # then eps again\n"
        "    if progress.sessions_done > 0:\n"
        "        teacher.delta_skip *= teacher.eps_skip\n"
        "        teacher.delta_equal *= teacher.eps_equal\n")] for script in ("pebble.py", "prefppo.py", "rime.py",
                                                                            "qpa.py")},
    # The reference PrefPPO's SB3 ends an episode at its time limit as at a termination (differences.md 16)
    "no-bootstrap-time-limits": {
        "prefppo.py": [("torch.as_tensor(~terminated, device=device)", "torch.as_tensor(~ends, device=device)")],
    },
    # The reference PrefPPO's query pool and r_hat see VecNormalize's observations of their step (defect 7,
    # differences.md 17); no statistics of D
    "stale-reward-inputs": {
        "prefppo.py": [
            ("envs, raw_obs, env_action", "envs, obs.cpu().numpy(), env_action"),
            ("torch.cat([raw_obs_buf, env_actions_buf], -1)", "torch.cat([obs_buf, env_actions_buf], -1)"),
            ("torch.cat([torch.as_tensor(obs, device=device), action])",
             "torch.cat([obs_stats.normalize(obs).to(device), action])"),
            ("    reward_model.set_input_stats(states[..., : segments[\"obs0\"].shape[-1]].flatten(0, 1))\n", "")],
    },
}


def edited_source(script: str, names: list[str]) -> str:
    """The script's text with the named edits applied; ValueError for an unknown edit or one that does not fit."""
    source = (ROOT / script).read_text()
    for name in names:
        if name not in EDITS or script not in EDITS[name]:
            known = [edit for edit, scripts in EDITS.items() if script in scripts]
            raise ValueError(f"no edit {name!r} for {script} (known: {', '.join(known) or 'none'})")
        for old, new in EDITS[name][script]:
            if source.count(old) != 1:
                raise ValueError(f"edit {name!r} does not fit {script}: its text occurs {source.count(old)} times")
            source = source.replace(old, new)
    return source


def main(argv: list[str]) -> None:
    if "--" not in argv:
        sys.exit("usage: edits.py EDIT [EDIT ...] [--write PATH] -- SCRIPT [FLAGS ...]")
    split = argv.index("--")
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("edits", nargs="+", help=f"one or more of {', '.join(EDITS)}")
    parser.add_argument("--write", help="write the edited script here instead of running it")
    args = parser.parse_args(argv[:split])
    script, *flags = argv[split + 1:]
    try:
        source = edited_source(Path(script).name, args.edits)
    except ValueError as error:
        sys.exit(f"error: {error}")
    if args.write:
        Path(args.write).write_text(source)
        return
    sys.path.insert(0, str(ROOT))
    sys.argv = [str(ROOT / Path(script).name), *flags]
    name = f"{Path(script).name}+{'+'.join(args.edits)}"
    linecache.cache[name] = (len(source), None, source.splitlines(True), name)  # tyro reads the docstrings
    code = compile(source, name, "exec")
    exec(code, {"__name__": "__main__", "__file__": sys.argv[0]})


if __name__ == "__main__":
    main(sys.argv[1:])
