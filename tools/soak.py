"""Soak: many random episodes with hostile actions (NaN, infinite, huge, malformed), resets mid-episode and
steps after the end, on every task and scene kind; counts crashes, non-finite observations or rewards and
leaked physics connections, each of which must be 0.

    python tools/soak.py [--episodes 2000] [--workers 2] [--seed 0]
"""
import gc
import os
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from objfind import (ACTION_MOVES, ACTION_SIZE, EVAL_CHUNK, MAX_SEED, SCENES, TASKS, ArgumentParser,  # noqa: E402
                     ObjectFindingEnv, episodes_arg, pb, run_cli, run_jobs, seed_arg, workers_arg)


SOAK_HOSTILE = (np.nan, np.inf, -np.inf, 1e9, -1e9)   # mixed into random actions; the first three are refused
SOAK_MALFORMED = (np.zeros(ACTION_SIZE - 1), np.zeros((2, ACTION_SIZE)), "forward", None, [0.0] * 7)   # refused
SOAK_TERMINATE_PROB = 0.05                             # about 20 steps per soak episode
SOAK_HOSTILE_PROB = 0.1                                # share of actions with one hostile component ...
SOAK_MALFORMED_PROB = 0.03                             # ... malformed as a whole, or as a list of Python floats
SOAK_RESET_PROB = 0.02                                 # a reset in the middle of an episode, with a large seed
SOAK_COUNTS = dict(episodes=0, steps=0, refused=0, crashes=0, non_finite=0, leaked=0, first_crash="")


def hostile_action(rng: np.random.Generator):
    """A random action, sometimes with a non-finite or huge component, malformed, or a plain list; and
    whether the env must refuse it (ValueError)."""
    action = rng.uniform(-1, 1, ACTION_SIZE)
    action[ACTION_MOVES] = 1.0 if rng.random() < SOAK_TERMINATE_PROB else -1.0
    if rng.random() < SOAK_HOSTILE_PROB:
        action[rng.integers(ACTION_SIZE)] = SOAK_HOSTILE[rng.integers(len(SOAK_HOSTILE))]
    draw = rng.random()
    if draw < SOAK_MALFORMED_PROB:
        return SOAK_MALFORMED[rng.integers(len(SOAK_MALFORMED))], True
    if draw < 2 * SOAK_MALFORMED_PROB:
        action = action.tolist()
    return action, not np.all(np.isfinite(action))


def soak_chunk(task: str, scene: str, seeds: list) -> dict:
    """Episodes of hostile actions (`hostile_action`), resets mid-episode and steps after the end, a fresh
    env each, every other one dropped without close(). Counts crashes (any error but a refusal the env
    owes), non-finite observations or rewards, and pybullet connections still open once the envs are gone."""
    counts, clients = dict(SOAK_COUNTS), []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        env = ObjectFindingEnv(task, scene)
        clients.append(env.sim._client)
        try:
            obs, _ = env.reset(seed=seed)
            counts["non_finite"] += int(not np.all(np.isfinite(obs)))
            done = False
            while not done:
                if rng.random() < SOAK_RESET_PROB:
                    obs, _ = env.reset(seed=int(rng.integers(MAX_SEED)))
                    counts["non_finite"] += int(not np.all(np.isfinite(obs)))
                action, refusable = hostile_action(rng)
                try:
                    obs, reward, done, _, _ = env.step(action)
                except ValueError:
                    if not refusable:
                        raise
                    counts["refused"] += 1
                    continue
                counts["steps"] += 1
                counts["non_finite"] += int(not (np.all(np.isfinite(obs)) and np.isfinite(reward)))
            try:
                env.step(np.zeros(ACTION_SIZE))   # after the end: refused, the episode stays over
                raise AssertionError("a step after the episode ended was accepted")
            except RuntimeError:
                counts["refused"] += 1
            counts["episodes"] += 1
        except Exception as error:   # noqa: BLE001  counted, not raised: a soak reports every kind of failure
            counts["crashes"] += 1
            counts["first_crash"] = counts["first_crash"] or f"{task}/{scene} seed {seed}: {error!r}"[:300]
        if seed % 2:
            env.close()
        del env
    gc.collect()
    counts["leaked"] = sum(pb.isConnected(physicsClientId=c) for c in clients)
    return counts


def run_soak(episodes: int, workers: int, seed: int = 0, progress: bool = True) -> dict:
    """`episodes` soak episodes spread over every task and scene kind; the summed counts."""
    kinds = [(task, scene) for task in TASKS for scene in SCENES]
    seeds = list(range(seed, seed + episodes))
    per_kind = [seeds[j::len(kinds)] for j in range(len(kinds))]          # episode i: kind i mod len(kinds)
    jobs = [(*kind, part[i:i + EVAL_CHUNK]) for kind, part in zip(kinds, per_kind)
            for i in range(0, len(part), EVAL_CHUNK)]
    total = dict(SOAK_COUNTS)
    with tqdm(total=episodes, desc="soak", unit="ep", disable=not progress, file=sys.stderr) as bar:
        def add(part):
            for k, v in part.items():
                total[k] = (total[k] or v) if k == "first_crash" else total[k] + v
            bar.update(part["episodes"] + part["crashes"])

        run_jobs(soak_chunk, jobs, workers, add)
    return total


def cmd_soak(args) -> int:
    t0 = time.perf_counter()
    counts = run_soak(args.episodes, args.workers, args.seed)
    print(f"soak: {counts['episodes']} episodes, {counts['steps']} steps over {len(TASKS)} tasks x {len(SCENES)} scene "
          f"kinds in {time.perf_counter() - t0:.0f} s; {counts['refused']} hostile actions refused; crashes "
          f"{counts['crashes']}, non-finite observations or rewards {counts['non_finite']}, leaked connections "
          f"{counts['leaked']}")
    if counts["first_crash"]:
        print(f"first crash: {counts['first_crash']}")
    return 1 if counts["crashes"] or counts["non_finite"] or counts["leaked"] else 0


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="tools/soak.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=episodes_arg, default=2000, help="episodes in all (default 2000)")
    parser.add_argument("--workers", type=workers_arg, default=os.cpu_count() or 1, help="worker processes")
    parser.add_argument("--seed", type=seed_arg, default=0, help="episode i uses seed + i (default 0)")
    parser.set_defaults(func=cmd_soak)
    return parser


def main(argv: list | None = None) -> int:
    return run_cli(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
