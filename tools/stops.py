"""The searchers' stops: at every stop of GNBV and GES (and the learned agents), the share of the target the
volume estimates as seen (what the baselines stop on) against the share truly seen (what the world judges),
per Table II cell; a CSV per cell and a table (stops.md) of how often a claim is made with 20 % or less
truly seen. With --rules, each stop rule "MxV" (claim above M x 20 % in V views in a row) is scored on the
same episodes instead: they are traced once with no claim, and each rule is applied to the trace, since the
searchers' moves do not depend on the estimate (rules.md: early claims, success and mean steps per rule).
With --estimates, the traces score how well two estimates tell a target truly seen from one not yet seen,
views with 5-50 % truly seen (estimates.md): the perceived share (the searchers' stop and, since world 10,
the state's detection factor) and the raw detection sum (world 9's state).

    python tools/stops.py [--episodes 200] [--workers 2] [--seed 0] [--agents gnbv,ges] [--out results/stops]
                          [--rules 1x1,1.25x2,1.5x2 | --estimates]
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
        perceived, summed, truth, done = [], [], [], False
        while not done:
            perceived.append(round(env.searcher.perceived_target_share(), 6))
            summed.append(round(detection_sum(env.searcher, env.cfg), 6))
            truth.append(round(info["target_seen_fraction"], 4))
            _, _, done, _, info = env.step(agent.act(env.searcher, env.gripper_pose()))
        traces.append(dict(seed=seed, target_present=info["target_present"], perceived=perceived, truth=truth,
                           detection_sum=summed, steps=info["steps"], success=info["success"]))
    env.close()
    return traces


def detection_sum(searcher, cfg) -> float:
    """The detection channel's sum over the volume in units of the told target's surface, counted in cells of
    state_voxel_m: world 9's state value (it summed the state's crop, all of the `ap` volume)."""
    volume = searcher.volume
    return float(volume.detections.sum()) * volume.voxel_m ** 3 / (searcher.target_area_m2 * cfg.state_voxel_m)


def separation(score: np.ndarray, seen: np.ndarray) -> float:
    """The area under the ROC curve: the chance that a view with the target truly seen scores above one
    without (ties count half); 0.5 is no better than a coin."""
    above = score[seen][:, None] - score[~seen][None, :]   # every (seen, not seen) pair
    return float(np.mean((above > 0) + 0.5 * (above == 0)))


def estimates_markdown(cells: dict) -> str:
    """Per cell, over its views with 5-50 % of the target truly seen: each estimate's separation of views with
    more than 20 % truly seen from the rest, and its correlation with the true share."""
    lines = ["| agent | task / scene | views | perceived share: separation, correlation | raw detection sum: "
             "separation, correlation |", "|---|---|---|---|---|"]
    for (agent, task, scene), traces in cells.items():
        views = np.array([(p, d, t) for tr in traces if tr["target_present"]
                          for p, d, t in zip(tr["perceived"], tr["detection_sum"], tr["truth"])]).reshape(-1, 3)
        views = views[(views[:, 2] > 0.05) & (views[:, 2] < 0.5)]
        seen = target_observed(views[:, 2], TASKS[task].seen_threshold)
        if seen.all() or not seen.any():
            lines.append(f"| {agent} | {task} / {scene} | {len(views)} | - | - |")
            continue
        cols = [f"{separation(views[:, k], seen):.3f}, {np.corrcoef(views[:, k], views[:, 2])[0, 1]:.2f}"
                for k in (0, 1)]
        lines.append(f"| {agent} | {task} / {scene} | {len(views)} | {cols[0]} | {cols[1]} |")
    return "\n".join(lines)


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
    if args.rules and args.estimates:
        raise UsageError("--rules and --estimates: one at a time")
    rules = rules_arg(args.rules) if args.rules else None
    traced = rules or args.estimates
    out, t0 = writable_folder(Path(args.out)), time.perf_counter()
    cells = {}
    for (agent, task), scenes in PAPER_TABLE_II.items():
        if agent not in agents:
            continue
        policy = learned_policy(agent, task) if agent in LEARNED else None
        for scene in scenes:
            seeds = list(range(args.seed, args.seed + args.episodes))
            jobs = [(agent, task, scene, seeds[i:i + EVAL_CHUNK], policy) for i in range(0, len(seeds), EVAL_CHUNK)]
            rows = [row for part in run_jobs(trace_chunk if traced else stop_chunk, jobs, args.workers) for row in part]
            cells[(agent, task, scene)] = rows
            if traced:
                path = out / f"{agent}-{task}-{scene}-traces.json"
                replace_atomically(path, lambda tmp: tmp.write_text(json.dumps(rows)))
                cell = {(agent, task, scene): rows}
                print((rules_markdown(cell, rules) if rules else estimates_markdown(cell)).splitlines()[-1], flush=True)
                continue
            write_csv(rows, out / f"{agent}-{task}-{scene}.csv", STOP_FIELDS)
            print(stops_markdown({(agent, task, scene): rows}, TASKS[task].seen_threshold).splitlines()[-1],
                  flush=True)
    markdown, name = ((rules_markdown(cells, rules), "rules.md") if rules else
                      (estimates_markdown(cells), "estimates.md") if args.estimates else
                      (stops_markdown(cells, TASKS["ap"].seen_threshold), "stops.md"))
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
    parser.add_argument("--estimates", action="store_true", help="score how well the perceived share and the raw "
                                                                 "detection sum tell the target seen instead")
    parser.set_defaults(func=cmd_stops)
    return parser


def main(argv: list | None = None) -> int:
    return run_cli(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
