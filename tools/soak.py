"""Soak: many random episodes with hostile actions (NaN, infinite, huge, malformed), resets mid-episode and
steps after the end, on every task and scene kind; counts crashes, non-finite observations or rewards and
leaked physics connections, each of which must be 0. Then the arm's path: hostile frames (NaN, infinite
and zero depth, all-zero and all-one detections, poses outside the box, wrong sizes) through `ArmSearch`;
counts non-finite goals, goals beyond a step and tracebacks, each of which must be 0.

    python tools/soak.py [--episodes 2000] [--arm-frames 20000] [--workers 2] [--seed 0]
"""
import gc
import os
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from objfind import (ACTION_MOVES, ACTION_SIZE, EVAL_CHUNK, MAX_SEED, SCENES, TASKS,  # noqa: E402
                     ArgumentParser, ArmSearch, ObjectFindingEnv, Searcher, episodes_arg, learned_policy, make_agent,
                     pb, rotation, run_cli, run_jobs, seed_arg, whole_number_arg, workers_arg, yaw_roll_of)


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


ARM_FRAMES_PER_JOB = 500   # hostile frames per job, from the views of a few scenes
ARM_SCENES_PER_JOB = 5     # scenes whose first views the hostile frames are made from
ARM_SEARCH_FRAMES = 20     # frames of one ArmSearch before a new one, in another base frame
ARM_AGENTS = ("gnbv", "ges", "a3de", "i3de", "random")
ARM_COUNTS = dict(frames=0, goals=0, stops=0, refused=0, non_finite_goals=0, leaps=0, wrongly_refused=0,
                  tracebacks=0, first_failure="")


def hostile_frame(rng: np.random.Generator, view, T_world_tool: np.ndarray, searcher: Searcher) -> tuple:
    """A frame made from a simulated view: (depth, detections, T_workspace_tool) and whether ArmSearch must
    refuse it. Bad depth pixels (NaN, inf, 0, negative, far) and all-zero or all-one detections are to be
    fused; NaN scores, wrong sizes, a sheared or non-finite pose, a tool more than a step out are refused."""
    depth, detections, T_tool = view.depth_m.copy(), view.detections.copy(), T_world_tool.copy()
    bad = rng.random(depth.shape) < rng.choice([0.0, 0.001, 0.1, 1.0])
    depth[bad] = rng.choice([np.nan, np.inf, -np.inf, 0.0, -0.3, 1e6], int(bad.sum()))
    detections[:] = detections if rng.random() < 0.6 else float(rng.random() < 0.5)
    step, half = searcher.max_step_m, searcher.workspace_m / 2
    kind = rng.integers(10)
    if kind == 0:      # just outside the box, within a step: a goal inside it
        T_tool[:2, 3] = np.sign(rng.standard_normal(2)) * (half + rng.uniform(0, step / 2, 2))   # at most 0.71 step
    elif kind == 1:    # far outside: refused
        T_tool[:3, 3] += rng.choice([-1, 1], 3) * rng.uniform(2 * step, 10, 3)
        return depth, detections, T_tool, True
    elif kind == 2:    # not a pose
        T_tool[rng.integers(3), rng.integers(4)] = rng.choice([np.nan, np.inf])
        return depth, detections, T_tool, True
    elif kind == 3:    # sheared
        T_tool[:3, :3] = T_tool[:3, :3] @ np.array([[1, 0.2, 0], [0, 1, 0], [0, 0, 1.0]])
        return depth, detections, T_tool, True
    elif kind == 4:    # a NaN score, or one above 1
        detections[rng.integers(detections.shape[0]), rng.integers(detections.shape[1])] = rng.choice([np.nan, 2.0])
        return depth, detections, T_tool, True
    elif kind == 5:    # another camera's size
        cut = rng.random() < 0.5
        return (depth[1:] if cut else depth), (detections if cut else detections[:, 1:]), T_tool, True
    return depth, detections, T_tool, False


def arm_goal_ok(searcher: Searcher, T_tool: np.ndarray, T_goal: np.ndarray) -> tuple[bool, bool]:
    """(finite, within one step and the box): the soak's own check of a goal, in the workspace frame."""
    if not np.isfinite(T_goal).all():
        return False, False
    (yaw, roll), (goal_yaw, goal_roll) = yaw_roll_of(T_tool[:3, :3]), yaw_roll_of(T_goal[:3, :3])
    move_m = np.linalg.norm(T_goal[:3, 3] - T_tool[:3, 3])   # at most an action's longest: every axis at its limit
    turn = max(abs(goal_roll - roll), abs((goal_yaw - yaw + np.pi) % (2 * np.pi) - np.pi))
    inside = np.abs(T_goal[:2, 3]).max() <= searcher.workspace_m / 2 + 1e-6 and -1e-6 <= T_goal[2, 3] <= \
        searcher.ceiling_m + 1e-6
    return True, inside and move_m <= np.sqrt(3) * searcher.max_step_m + 1e-6 and turn <= searcher.max_turn_rad + 1e-6


def arm_soak_chunk(task: str, seed: int, frames: int) -> dict:
    """Hostile frames through ArmSearch in random base frames, each agent in turn (`hostile_frame`)."""
    counts, rng = dict(ARM_COUNTS), np.random.default_rng(seed)
    env = ObjectFindingEnv(task, "cubes")
    views = []
    for s in range(ARM_SCENES_PER_JOB):
        env.reset(seed=seed * ARM_SCENES_PER_JOB + s)
        views.append((env.view, env.gripper_pose()))
    env.close()
    policies = {"a3de": learned_policy("a3de", task), "i3de": learned_policy("i3de", "ip")}   # no large I3DE
    searcher = Searcher(TASKS[task])
    for frame in range(frames):
        if frame % ARM_SEARCH_FRAMES == 0:
            agent = ARM_AGENTS[(frame // ARM_SEARCH_FRAMES) % len(ARM_AGENTS)]
            T_base_workspace = np.eye(4)
            T_base_workspace[:3, :3] = rotation(rng.uniform(-np.pi, np.pi), "z") @ rotation(rng.uniform(-0.3, 0.3), "x")
            T_base_workspace[:3, 3] = rng.uniform(-1, 1, 3)
            search = ArmSearch(searcher, make_agent(agent, TASKS[task], seed, policies.get(agent)), T_base_workspace)
        view, T_world_tool = views[rng.integers(len(views))]
        depth, detections, T_tool, refusable = hostile_frame(rng, view, T_world_tool, searcher)
        counts["frames"] += 1
        try:
            with np.errstate(invalid="ignore", over="ignore"):   # a pose of inf, moved into the base frame
                _, T_base_goal = search.step(depth, T_base_workspace @ T_tool, detections=detections)
        except ValueError as error:
            counts["refused"] += 1
            if not refusable:
                counts["wrongly_refused"] += 1
                counts["first_failure"] = counts["first_failure"] or f"{task} frame {frame}: refused: {error}"[:300]
            continue
        except Exception as error:   # noqa: BLE001  counted, not raised: a soak reports every kind of failure
            counts["tracebacks"] += 1
            counts["first_failure"] = counts["first_failure"] or f"{task} frame {frame}: {error!r}"[:300]
            continue
        if T_base_goal is None:
            counts["stops"] += 1
            continue
        finite, within = arm_goal_ok(searcher, T_tool, np.linalg.inv(T_base_workspace) @ T_base_goal)
        counts["goals"] += 1
        counts["non_finite_goals"] += not finite
        counts["leaps"] += finite and not within
        if refusable:   # a frame the contract refuses came through
            counts["tracebacks"] += 1
            counts["first_failure"] = counts["first_failure"] or f"{task} frame {frame}: a bad frame was accepted"
    return counts


def run_arm_soak(frames: int, workers: int, seed: int = 0, progress: bool = True) -> dict:
    """`frames` hostile frames spread over every task (`arm_soak_chunk`); the summed counts."""
    tasks = list(TASKS)
    jobs = [(tasks[i % len(tasks)], seed + i, min(ARM_FRAMES_PER_JOB, frames - start))
            for i, start in enumerate(range(0, frames, ARM_FRAMES_PER_JOB))]
    total = dict(ARM_COUNTS)
    with tqdm(total=frames, desc="arm soak", unit="frame", disable=not progress, file=sys.stderr) as bar:
        def add(part):
            for k, v in part.items():
                total[k] = (total[k] or v) if k == "first_failure" else total[k] + v
            bar.update(part["frames"])

        run_jobs(arm_soak_chunk, jobs, workers, add)
    return total


def cmd_soak(args) -> int:
    t0 = time.perf_counter()
    counts = run_soak(args.episodes, args.workers, args.seed)
    kinds = min(args.episodes, len(TASKS) * len(SCENES))   # episode i plays kind i mod their number
    print(f"soak: {counts['episodes']} episodes, {counts['steps']} steps over {kinds} of the {len(TASKS)} x "
          f"{len(SCENES)} task and scene kinds in {time.perf_counter() - t0:.0f} s; {counts['refused']} hostile "
          f"actions refused; crashes "
          f"{counts['crashes']}, non-finite observations or rewards {counts['non_finite']}, leaked connections "
          f"{counts['leaked']}")
    if counts["first_crash"]:
        print(f"first crash: {counts['first_crash']}")
    t0, arm = time.perf_counter(), run_arm_soak(args.arm_frames, args.workers, args.seed) if args.arm_frames else None
    if arm:
        print(f"arm soak: {arm['frames']} hostile frames through ArmSearch over {len(TASKS)} tasks in "
              f"{time.perf_counter() - t0:.0f} s: {arm['goals']} goals, {arm['stops']} stops, {arm['refused']} "
              f"refused; "
              f"non-finite goals {arm['non_finite_goals']}, goals beyond a step or the box {arm['leaps']}, tracebacks "
              f"{arm['tracebacks']}, good frames refused {arm['wrongly_refused']}")
        if arm["first_failure"]:
            print(f"first failure: {arm['first_failure']}")
    arm_failed = arm and (arm["non_finite_goals"] or arm["leaps"] or arm["tracebacks"] or arm["wrongly_refused"])
    return 1 if counts["crashes"] or counts["non_finite"] or counts["leaked"] or arm_failed else 0


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="tools/soak.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=episodes_arg, default=2000, help="episodes in all (default 2000)")
    parser.add_argument("--arm-frames", type=whole_number_arg(0, 10 ** 7, "the number of frames"), default=20000,
                        help="hostile frames through ArmSearch after the episodes (default 20000; 0: none)")
    parser.add_argument("--workers", type=workers_arg, default=os.cpu_count() or 1, help="worker processes")
    parser.add_argument("--seed", type=seed_arg, default=0, help="episode i uses seed + i (default 0)")
    parser.set_defaults(func=cmd_soak)
    return parser


def main(argv: list | None = None) -> int:
    return run_cli(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
