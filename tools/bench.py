"""Bench: where the time of one env step and of a reset goes, stage by stage, and env steps/s over worker
processes. Another load on the machine only adds time, so each figure is the best of --repeats runs.

    python tools/bench.py [--scene cubes] [--steps 300] [--workers 2] [--repeats 3]
"""
import os
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from objfind import (ACTION_MOVES, SCENES, ArgumentParser, ObjectFindingEnv, process_pool, run_cli,  # noqa: E402
                     steps_arg, whole_number_arg, workers_arg)


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


def cmd_bench(args) -> int:
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
    parser.set_defaults(func=cmd_bench)
    return parser


def main(argv: list | None = None) -> int:
    return run_cli(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
