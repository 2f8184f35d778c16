"""A learned agent's greedy moves: how often each displacement sits at the action's bound (|mean| >= 0.99 of
[-1, 1]: the longest step the gripper takes) and the policy's trained std, over a cell's episodes. Long moves
see more new volume, so searches are shorter (the model card's recipe notes).

    python tools/moves.py [--agent a3de] [--weights FILE] [--task ap] [--scene cubes] [--episodes 30] [--seed 0]
"""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from objfind import (ACTION_MOVES, ACTION_NAMES, LEARNED, TASKS, ArgumentParser, ObjectFindingEnv,  # noqa: E402
                     PPOAgent, SCENES, default_task, episodes_arg, learned_policy, run_cli, run_episode, seed_arg)

SATURATED = 0.99   # |mean| at or above this share of the bound counts as a full step


def greedy_moves(policy: dict, task: str, scene: str, seeds: range) -> np.ndarray:
    """(steps, 5): every displacement the greedy policy chose in these episodes, in [-1, 1]."""
    agent, moves = PPOAgent(policy), []
    decide = agent.decide

    def recording(obs: np.ndarray) -> np.ndarray:
        action = decide(obs)
        moves.append(action[:ACTION_MOVES])
        return action

    agent.decide = recording
    env = ObjectFindingEnv(task, scene)
    for seed in seeds:
        run_episode(env, agent, seed)
    env.close()
    return np.array(moves)


def cmd_moves(args) -> int:
    task = args.task or default_task(args.agent)
    policy = learned_policy(args.agent, task, args.weights)
    moves = np.abs(greedy_moves(policy, task, args.scene, range(args.seed, args.seed + args.episodes)))
    std = np.exp(policy["model"]["log_std"].numpy())
    print(f"{len(moves)} moves in {args.episodes} episodes of {task} / {args.scene}")
    print("| move | saturated | mean abs | std |\n|---|---|---|---|")
    for i, name in enumerate(ACTION_NAMES[:ACTION_MOVES]):
        print(f"| {name} | {100 * (moves[:, i] >= SATURATED).mean():.0f} % | {moves[:, i].mean():.2f} | {std[i]:.2f} |")
    return 0


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="tools/moves.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--agent", default="a3de", choices=LEARNED, help="a learned agent (default a3de)")
    parser.add_argument("--weights", help="a checkpoint (default: the agent's shipped weights)")
    parser.add_argument("--task", choices=sorted(TASKS), help="default: the agent's")
    parser.add_argument("--scene", choices=SCENES, default="cubes", help="default cubes")
    parser.add_argument("--episodes", type=episodes_arg, default=30, help="default 30")
    parser.add_argument("--seed", type=seed_arg, default=0, help="episode i uses scene seed + i (default 0)")
    parser.set_defaults(func=cmd_moves)
    return parser


def main(argv: list | None = None) -> int:
    return run_cli(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
