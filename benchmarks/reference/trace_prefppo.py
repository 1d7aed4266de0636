"""The reference PrefPPO (train_PrefPPO.py) run unchanged, with one measurement added from outside: after each of
its rollouts on the learned reward, the Pearson correlation of the rewards PPO got (its reward model's r_hat,
the ensemble mean) with the true rewards of the same steps, written to a CSV, as prefppo.py logs
reward/rollout_correlation. Nothing in the reference's files is edited: its classes are wrapped at import, the
wrappers only record what goes through them, and the run's numbers are the same as without them.

Run it with the reference's interpreter in the reference's tree, with train_PrefPPO.py's flags (run.py's
prefppo_command, e.g. from a parity run's log):

    cd reference/BPref && ../.venv/bin/python ../../benchmarks/reference/trace_prefppo.py \\
        --trace-out /tmp/ref_s4_rollouts.csv --env walker_walk --seed 4 ...
"""

import csv
import runpy
import sys

import numpy as np


def rollout_row(step: int, learned: list, true: list) -> dict:
    """One rollout's row: the correlation of the learned with the true per-step rewards (each list holds one
    array per step, one value per env) and both rewards' mean and standard deviation."""
    learned = np.concatenate([np.ravel(x) for x in learned])
    true = np.concatenate([np.ravel(x) for x in true])
    if len(learned) != len(true):
        raise ValueError(f"{len(learned)} learned rewards against {len(true)} true ones")
    return {"step": step, "correlation": float(np.corrcoef(learned, true)[0, 1]),
            "learned_mean": float(learned.mean()), "learned_std": float(learned.std()),
            "true_mean": float(true.mean()), "true_std": float(true.std())}


def install(trace_path: str):
    """Wrap the reference's env step, r_hat_batch and collect_rollouts so that each rollout on the learned reward
    appends its rollout_row to trace_path."""
    from reward_model import RewardModel
    from stable_baselines3.common.on_policy_with_reward_algorithm import OnPolicyRewardAlgorithm
    from stable_baselines3.common.vec_env import VecNormalize

    recording = {"on": False, "learned": [], "true": []}
    step_wait = VecNormalize.step_wait
    r_hat_batch = RewardModel.r_hat_batch
    collect_rollouts = OnPolicyRewardAlgorithm.collect_rollouts

    def traced_step_wait(self):
        obs, rewards, dones, infos = step_wait(self)
        if recording["on"]:
            recording["true"].append(np.array(rewards))  # norm_reward=False: the true rewards
        return obs, rewards, dones, infos

    def traced_r_hat_batch(self, x):
        r_hat = r_hat_batch(self, x)
        if recording["on"]:
            recording["learned"].append(np.array(r_hat))
        return r_hat

    def traced_collect_rollouts(self, *args, **kwargs):
        recording.update(on=True, learned=[], true=[])
        try:
            result = collect_rollouts(self, *args, **kwargs)
        finally:
            recording["on"] = False
        row = rollout_row(self.num_timesteps, recording["learned"], recording["true"])
        with open(trace_path, "a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(row))
            if f.tell() == 0:
                writer.writeheader()
            writer.writerow(row)
        return result

    VecNormalize.step_wait = traced_step_wait
    RewardModel.r_hat_batch = traced_r_hat_batch
    OnPolicyRewardAlgorithm.collect_rollouts = traced_collect_rollouts


if __name__ == "__main__":
    if len(sys.argv) < 3 or sys.argv[1] != "--trace-out":
        sys.exit("usage: trace_prefppo.py --trace-out FILE.csv [train_PrefPPO.py's flags]")
    trace = sys.argv[2]
    sys.argv = ["train_PrefPPO.py", *sys.argv[3:]]
    sys.path[0] = "."  # the reference's tree (the working directory), in place of this script's folder
    install(trace)
    runpy.run_path("train_PrefPPO.py", run_name="__main__")
