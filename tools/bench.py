"""Bench: where the time of one env step and of a reset goes, stage by stage, and env steps/s over worker
processes. Another load on the machine only adds time, so each figure is the best of --repeats runs. With
--training: where a second of `train` goes (env steps, resets, the policy's forward pass, the PPO update,
the bookkeeping), in one process and with --workers worker processes.

    python tools/bench.py [--scene cubes] [--steps 300] [--workers 2] [--repeats 3]
    python tools/bench.py --training [--updates 5] [--workers 2]
"""
import functools
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import objfind  # noqa: E402
from objfind import (ACTION_MOVES, SCENES, ActorCritic, ArgumentParser, ObjectFindingEnv, PPOSettings,  # noqa: E402
                     process_pool, run_cli, steps_arg, whole_number_arg, workers_arg)


def exploring_actions(rng: np.random.Generator, n: int) -> np.ndarray:
    """Random displacements that never terminate: the bench's workload. (n, 6) float32."""
    actions = rng.uniform(-1, 1, (n, 6)).astype(np.float32)
    actions[:, ACTION_MOVES] = -1.0
    return actions


BENCH_STAGES = (("physics", "_drive_gripper"), ("render", "_render"), ("detect", "_detect"),
                ("integrate", "searcher.observe"), ("encode", "searcher.state"))   # a step's stages, in order
BENCH_RESETS = 10   # new scenes per measurement of a reset, seeds seed .. seed + 9


def bench_stages(task: str, scene: str, steps: int, seed: int = 0) -> dict:
    """Mean milliseconds per stage of a step over `steps` exploring steps, and of a reset (building the
    scene, then all of it) over BENCH_RESETS seeds: each stage's method of the env (or its searcher) is
    wrapped in a timer that counts only in its phase, so a reset's view is not counted as a step's."""
    env = ObjectFindingEnv(task, scene)
    env.reset(seed=seed + 1000)     # warm-up: the first reset in a process pays one-time costs
    stages = [stage for stage, _ in BENCH_STAGES] + ["step", "scene", "reset"]
    totals, phase = dict.fromkeys(stages, 0.0), [None]

    def timed(stage, method):
        def run(*args, **kwargs):
            t0 = time.perf_counter()
            result = method(*args, **kwargs)
            if phase[0] == ("reset" if stage == "scene" else "step"):
                totals[stage] += time.perf_counter() - t0
            return result
        return run
    for stage, name in BENCH_STAGES + (("scene", "_build_scene"),):
        owner, name = (env.searcher, name.removeprefix("searcher.")) if "." in name else (env, name)
        setattr(owner, name, timed(stage, getattr(owner, name)))

    def measure(phase_name, stage, call):
        phase[0], t0 = phase_name, time.perf_counter()
        result = call()
        totals[stage], phase[0] = totals[stage] + time.perf_counter() - t0, None
        return result
    for i in range(BENCH_RESETS):
        measure("reset", "reset", lambda: env.reset(seed=seed + i))
    env.reset(seed=seed)
    for action in exploring_actions(np.random.default_rng(seed), steps):
        if measure("step", "step", lambda: env.step(action))[2]:
            env.reset()
    env.close()
    return {stage: 1e3 * total / (BENCH_RESETS if stage in ("scene", "reset") else steps)
            for stage, total in totals.items()}


def bench_throughput(task: str, steps: int, seed: int = 0) -> float:
    """Env steps per second of one process stepping its own env on task/cubes, resets included."""
    env = ObjectFindingEnv(task, "cubes", seed=seed)
    env.reset()
    t0 = time.perf_counter()
    for action in exploring_actions(np.random.default_rng(seed), steps):
        if env.step(action)[2]:
            env.reset()
    rate = steps / (time.perf_counter() - t0)
    env.close()
    return rate


def run_bench(steps: int, workers: int, repeats: int = 3, scenes: tuple = SCENES) -> str:
    """The report of `python objfind.py bench` as Markdown. Each measurement replays the same seeded work
    `repeats` times; another load on the machine can only add time, so each column's fastest is reported."""
    stages = [stage for stage, _ in BENCH_STAGES] + ["step", "scene", "reset"]
    lines = [f"Milliseconds per stage of a step (mean over {steps} exploring steps) and of a reset (building "
             f"the scene, then all of it; mean over {BENCH_RESETS} seeds); one process, best of {repeats} runs:",
             "", "| task / scene | " + " | ".join(stages) + " |", "|---" * (len(stages) + 1) + "|"]
    throughput = ["", f"Env steps per second on cubes (resets included, best of {repeats} runs, {os.cpu_count()} "
                  "cores), each process stepping its own env:", "", f"| task | 1 process | {workers} processes |",
                  "|---|---|---|"]
    with (tqdm(total=2 * (len(scenes) + 2) * repeats, desc="bench", unit="run", file=sys.stderr) as bar,
          process_pool(workers) as pool):
        def best(measure):
            results = []
            for _ in range(repeats):
                results.append(measure())
                bar.update()
            return results

        for task in ("ap", "ip"):
            for scene in scenes:
                runs = best(lambda: bench_stages(task, scene, steps))
                lines.append(f"| {task} / {scene} | " + " | ".join(f"{min(r[s] for r in runs):.2f}" for s in stages)
                             + " |")
            one = max(best(lambda: bench_throughput(task, steps)))
            many = max(best(lambda: sum(pool.map(bench_throughput, [task] * workers, [steps] * workers,
                                                 range(workers)))))
            throughput.append(f"| {task} | {one:.0f} | {many:.0f} |")
    return "\n".join(lines + throughput)


TRAINING_PARTS = (   # what a part of a training second is timed by, and whether only while collecting rollouts
    ("env steps", ObjectFindingEnv, "step", False), ("resets", ObjectFindingEnv, "reset", False),
    ("policy forward", ActorCritic, "distributions", True), ("policy forward", ActorCritic, "value", True),
    ("PPO update", objfind, "ppo_update", False), ("bookkeeping", objfind, "write_csv", False),
    ("bookkeeping", objfind, "save_checkpoint", False), ("bookkeeping", objfind, "plot_learning_curve", False))
TRAINING_PARTS_ORDER = ("env steps", "resets", "policy forward", "PPO update", "bookkeeping", "other")


def bench_training(task: str, updates: int, workers: int, ppo: PPOSettings = PPOSettings()) -> dict:
    """Seconds of `updates` PPO updates of `train` on task/cubes, in all and by part (in this process: with
    workers > 1 the env steps, resets and forward passes run in the workers, and the rest of a second waits
    for them). The parts are timed by wrapping the functions `train` calls; "other" is what is left."""
    totals, collecting = dict.fromkeys(TRAINING_PARTS_ORDER[:-1] + ("total",), 0.0), [False]
    collect_rollout = objfind.collect_rollout
    originals = [(owner, name, getattr(owner, name)) for _, owner, name, _ in TRAINING_PARTS]
    originals.append((objfind, "collect_rollout", collect_rollout))

    def timed(part, method, only_collecting):
        def run(*args, **kwargs):
            if only_collecting and not collecting[0]:
                return method(*args, **kwargs)
            t0 = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                totals[part] += time.perf_counter() - t0
        return run

    def collecting_rollout(*args, **kwargs):
        collecting[0] = True
        try:
            return collect_rollout(*args, **kwargs)
        finally:
            collecting[0] = False
    try:
        for part, owner, name, only_collecting in TRAINING_PARTS:
            setattr(owner, name, timed(part, getattr(owner, name), only_collecting))
        objfind.collect_rollout = collecting_rollout
        with tempfile.TemporaryDirectory() as out:
            t0 = time.perf_counter()
            objfind.train(functools.partial(ObjectFindingEnv, task, "cubes"), Path(out) / "run",
                          updates * ppo.batch_steps, ppo, workers=workers, progress=False,
                          streams=objfind.DEFAULT_STREAMS)
            totals["total"] = time.perf_counter() - t0
    finally:
        for owner, name, method in originals:
            setattr(owner, name, method)
    totals["other"] = totals["total"] - sum(v for k, v in totals.items() if k != "total")
    return totals


def training_markdown(task: str, updates: int, workers: int) -> str:
    """Where a second of training goes, in one process and with `workers` worker processes."""
    lines = [f"Where a second of `train --task {task}` goes: {updates} updates of {PPOSettings().batch_steps} env "
             f"steps on {os.cpu_count()} cores, seconds (share of the total):", "",
             "| worker processes | env steps/s | " + " | ".join(TRAINING_PARTS_ORDER) + " | total |",
             "|---" * (len(TRAINING_PARTS_ORDER) + 3) + "|"]
    for n in sorted({1, workers}):
        parts = bench_training(task, updates, n)
        lines.append(f"| {n} | {updates * PPOSettings().batch_steps / parts['total']:.0f} | "
                     + " | ".join(f"{parts[k]:.1f} ({100 * parts[k] / parts['total']:.0f} %)"
                                  for k in TRAINING_PARTS_ORDER) + f" | {parts['total']:.1f} |")
    lines.append("")
    lines.append("With worker processes, env steps, resets and forward passes run in the workers and are not "
                 "seen here: their wait is in \"other\".")
    return "\n".join(lines)


def cmd_bench(args) -> int:
    if args.training:
        print(training_markdown("ap", args.updates, args.workers))
        return 0
    print(run_bench(args.steps, args.workers, args.repeats, SCENES if args.scene == "all" else (args.scene,)))
    return 0


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="tools/bench.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=steps_arg, default=300, help="steps per measurement")
    parser.add_argument("--scene", choices=SCENES + ("all",), default="all", help="scene kind (default all)")
    parser.add_argument("--workers", type=workers_arg, default=os.cpu_count() or 1,
                        help="processes for the throughput rows (default all cores)")
    parser.add_argument("--repeats", type=whole_number_arg(1, 100, "repeats"), default=3,
                        help="report the best of this many runs")
    parser.add_argument("--training", action="store_true", help="where a second of train --task ap goes instead")
    parser.add_argument("--updates", type=whole_number_arg(1, 1000, "updates"), default=5,
                        help="with --training: PPO updates per measurement (default 5)")
    parser.set_defaults(func=cmd_bench)
    return parser


def main(argv: list | None = None) -> int:
    return run_cli(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
