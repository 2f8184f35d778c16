"""The searchers' stops: at every stop of GNBV and GES (and the learned agents), the share of the target the
volume estimates as seen (what the baselines stop on) against the share truly seen (what the world judges),
per Table II cell; a CSV per cell and a table (stops.md) of how often a claim is made with 20 % or less
truly seen. With --rules, each stop rule "MxV" (claim above M x 20 % in V views in a row) is scored on the
same episodes instead: they are traced once with no claim, and each rule is applied to the trace, since the
searchers' moves do not depend on the estimate (rules.md: early claims, success and mean steps per rule).

    python tools/stops.py [--episodes 200] [--workers 2] [--seed 0] [--agents gnbv,ges] [--out results/stops]
                          [--rules 1x1,1.25x2,1.5x2]
"""
import json
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from objfind import (ACTION_MOVES, EVAL_CHUNK, LEARNED, PAPER_TABLE_II, TASKS, ArgumentParser,  # noqa: E402
                     ObjectFindingEnv, UsageError, episodes_arg, learned_policy, make_agent, replace_atomically,
                     run_cli, run_jobs, seed_arg, target_observed, workers_arg, write_csv, writable_folder)

STOP_FIELDS = ("seed", "target_present", "stopped", "claimed_found", "steps", "perceived_share", "true_share",
               "success")


def stop_chunk(agent_name: str, task: str, scene: str, seeds: list, policy: dict | None) -> list:
    """Episodes of one cell; each row: the perceived and the true share when the agent stopped (or at the
    horizon), and whether it stopped."""
    env, rows = ObjectFindingEnv(task, scene), []
    for seed in seeds:
        agent = make_agent(agent_name, env.cfg, seed, policy)
        _, info = env.reset(seed=seed)
        agent.reset(env.searcher, env.gripper_pose())
        done = False
        while not done:
            action = agent.act(env.searcher, env.gripper_pose())
            perceived = env.searcher.perceived_target_share()   # before the step: what a stop is decided on
            found = env.searcher.target_found()
            _, _, done, _, info = env.step(action)
        stopped = bool(action[ACTION_MOVES] > 0)
        rows.append(dict(seed=seed, target_present=info["target_present"], stopped=stopped,
                         claimed_found=stopped and found, steps=info["steps"], perceived_share=round(perceived, 6),
                         true_share=round(info["target_seen_fraction"], 4), success=info["success"]))
    env.close()
    return rows


NEVER_CLAIM = dict(claim_margin=5.0, confirm_views=100)   # the settings' limits: a trace the rules are applied to


def trace_chunk(agent_name: str, task: str, scene: str, seeds: list, policy: dict | None) -> list:
    """Episodes of one cell with the claim switched off; each: the estimate and the truth after every view,
    and how it ended (a stop claiming no target, or the horizon)."""
    env, traces = ObjectFindingEnv(task, scene, **NEVER_CLAIM), []
    for seed in seeds:
        agent = make_agent(agent_name, env.cfg, seed, policy)
        _, info = env.reset(seed=seed)
        agent.reset(env.searcher, env.gripper_pose())
        perceived, truth, done = [], [], False
        while not done:
            perceived.append(round(env.searcher.perceived_target_share(), 6))
            truth.append(round(info["target_seen_fraction"], 4))
            _, _, done, _, info = env.step(agent.act(env.searcher, env.gripper_pose()))
        traces.append(dict(seed=seed, target_present=info["target_present"], perceived=perceived, truth=truth,
                           steps=info["steps"], success=info["success"]))
    env.close()
    return traces


def score_rule(trace: dict, margin: float, views: int, threshold: float) -> tuple:
    """(claimed, claimed with <= threshold truly seen, success, steps) of a traced episode under a rule: it
    claims at the first decision after `views` views in a row with the estimate above margin x threshold."""
    above = target_observed(np.array(trace["perceived"]), margin * threshold)
    for k in range(views - 1, len(above)):
        if above[k - views + 1:k + 1].all():
            seen = target_observed(trace["truth"][k], threshold)
            return True, trace["target_present"] and not seen, seen or not trace["target_present"], k + 1
    return False, False, trace["success"], trace["steps"]


def rules_markdown(cells: dict, rules: list) -> str:
    """Per cell and rule: early claims of the episodes with a target, success % and mean steps of all."""
    lines = ["| agent | task / scene | " + " | ".join(f"{m:g} x {v}" for m, v in rules) + " |",
             "|---|---|" + "---|" * len(rules)]
    for (agent, task, scene), traces in cells.items():
        threshold, present = TASKS[task].seen_threshold, sum(t["target_present"] for t in traces)
        entries = []
        for margin, views in rules:
            scored = [score_rule(t, margin, views, threshold) for t in traces]
            entries.append(f"{sum(s[1] for s in scored)} of {present}, {100 * np.mean([s[2] for s in scored]):.1f} %"
                           f", {np.mean([s[3] for s in scored]):.2f}")
        lines.append(f"| {agent} | {task} / {scene} | " + " | ".join(entries) + " |")
    return "\n".join(lines)


def rules_arg(text: str) -> list:
    """--rules: comma-separated MxV, a margin of at least 1 and a whole number of views."""
    rules = []
    for part in text.split(","):
        match = re.fullmatch(r"(\d+(?:\.\d+)?)x(\d+)", part.strip())
        if not match or float(match.group(1)) < 1 or int(match.group(2)) < 1:
            raise UsageError(f"--rules: {part!r} is not MxV (a margin >= 1, views >= 1), e.g. 1.25x2")
        rules.append((float(match.group(1)), int(match.group(2))))
    return rules


def stops_markdown(cells: dict, threshold: float) -> str:
    """Per cell, of the episodes with a target: the claims "found" (the volume's estimate above the threshold),
    those made with at most `threshold` truly seen (a failure the estimate caused), the perceived share's ratio
    to the true one at those claims (median, 10th-90th percentile), and the stops that claimed no target."""
    lines = ["| agent | task / scene | target present | claimed found | ... with <= 20 % truly seen | perceived / "
             "true at claims: median [10 %, 90 %] | claimed absent |", "|---|---|---|---|---|---|---|"]
    for (agent, task, scene), rows in cells.items():
        present = [r for r in rows if r["target_present"]]
        claims = [r for r in present if r["claimed_found"]]
        early = [r for r in claims if r["true_share"] <= threshold]
        ratio = np.array([r["perceived_share"] / max(r["true_share"], 1e-3) for r in claims])
        spread = (f"{np.median(ratio):.2f} [{np.percentile(ratio, 10):.2f}, {np.percentile(ratio, 90):.2f}]"
                  if len(ratio) else "-")
        absent = sum(r["stopped"] and not r["claimed_found"] for r in present)
        lines.append(f"| {agent} | {task} / {scene} | {len(present)} | {len(claims)} | {len(early)} "
                     f"({100 * len(early) / max(len(present), 1):.1f} %) | {spread} | {absent} |")
    return "\n".join(lines)


def cmd_stops(args) -> int:
    agents = args.agents.split(",")
    unknown = [a for a in agents if a not in ("gnbv", "ges", *LEARNED)]
    if unknown:
        raise UsageError(f"--agents: {unknown[0]} is not gnbv, ges, a3de or i3de")
    rules = rules_arg(args.rules) if args.rules else None
    out, t0 = writable_folder(Path(args.out)), time.perf_counter()
    cells = {}
    for (agent, task), scenes in PAPER_TABLE_II.items():
        if agent not in agents:
            continue
        policy = learned_policy(agent, task) if agent in LEARNED else None
        for scene in scenes:
            seeds = list(range(args.seed, args.seed + args.episodes))
            jobs = [(agent, task, scene, seeds[i:i + EVAL_CHUNK], policy) for i in range(0, len(seeds), EVAL_CHUNK)]
            rows = [row for part in run_jobs(trace_chunk if rules else stop_chunk, jobs, args.workers) for row in part]
            cells[(agent, task, scene)] = rows
            if rules:
                path = out / f"{agent}-{task}-{scene}-traces.json"
                replace_atomically(path, lambda tmp: tmp.write_text(json.dumps(rows)))
                print(rules_markdown({(agent, task, scene): rows}, rules).splitlines()[-1], flush=True)
                continue
            write_csv(rows, out / f"{agent}-{task}-{scene}.csv", STOP_FIELDS)
            print(stops_markdown({(agent, task, scene): rows}, TASKS[task].seen_threshold).splitlines()[-1],
                  flush=True)
    markdown = rules_markdown(cells, rules) if rules else stops_markdown(cells, TASKS["ap"].seen_threshold)
    name = "rules.md" if rules else "stops.md"
    replace_atomically(out / name, lambda tmp: tmp.write_text(markdown + "\n"))
    print(markdown)
    print(f"wrote {out / name} and a file per cell; {time.perf_counter() - t0:.0f} s")
    return 0


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="tools/stops.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=episodes_arg, default=200, help="episodes per cell (default 200)")
    parser.add_argument("--workers", type=workers_arg, default=os.cpu_count() or 1, help="worker processes")
    parser.add_argument("--seed", type=seed_arg, default=0, help="episode i uses scene seed + i (default 0)")
    parser.add_argument("--agents", default="gnbv,ges", help="comma-separated (default gnbv,ges)")
    parser.add_argument("--out", default="results/stops", help="folder for the CSVs and stops.md")
    parser.add_argument("--rules", help="score these stop rules instead, comma-separated MxV: claim above M x "
                                        "20 %% in V views in a row (e.g. 1x1,1.25x2)")
    parser.set_defaults(func=cmd_stops)
    return parser


def main(argv: list | None = None) -> int:
    return run_cli(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
