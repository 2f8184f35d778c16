"""The stop rules on the two real cells alone: GNBV ap-real and GES ip-real traced with the claim off on seeds
0-199, with an objfind.py copy (ROOT: a checkout with a candidate patch applied) and setting overrides, and each rule
scored on the traces as tools/stops.py --rules does. Writes OUT/traces.json and OUT/rules.md.

    python results/stops/candidate-judge/realrules.py ROOT OUT ['{"setting": value}']   (NOFORGET=1: never forget;
    SEEDS=1000: seeds 0-999 instead; FIRST_SEED=100000: from that seed; RULES=1.5x2,...: those rules; an OUT
    already traced is scored again)
"""
import json
import os
import sys
ROOT = sys.argv[1]
sys.path.insert(0, ROOT); sys.path.insert(0, ROOT + '/tools')
import objfind as of
import stops
if os.environ.get('NOFORGET'):
    mark = of.TSDFVolume._mark_target_surface
    def nf(self, depth_m, detections, K, T, flat, det_new, rgb_outline):
        return mark(self, depth_m, detections, K, T, flat[:0], det_new[:0], rgb_outline)
    of.TSDFVolume._mark_target_surface = nf
OVR = json.loads(sys.argv[3]) if len(sys.argv) > 3 else {}

def chunk(agent_name, task, scene, seeds):
    env, traces = of.ObjectFindingEnv(task, scene, **stops.NEVER_CLAIM, **OVR), []
    for seed in seeds:
        agent = of.make_agent(agent_name, env.cfg, seed, None)
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

if __name__ == "__main__":
    rules = stops.rules_arg(os.environ.get('RULES', "1x1,1.25x2,1.5x2,1.6x2,1.75x2,2x2,1.25x3,1.5x3"))
    out = sys.argv[2]
    if os.path.exists(out + "/traces.json"):   # traced already: score the rules again
        cells = {(k.split("-", 1)[0], k.split("-", 1)[1], "cubes-and-cuboids"): v
                 for k, v in json.load(open(out + "/traces.json")).items()}
    else:
        cells = {}
        for agent, task in (("gnbv", "ap-real"), ("ges", "ip-real")):
            first = int(os.environ.get('FIRST_SEED', 0))
            seeds = list(range(first, first + int(os.environ.get('SEEDS', 200))))
            jobs = [(agent, task, "cubes-and-cuboids", seeds[i:i + 20]) for i in range(0, len(seeds), 20)]
            cells[(agent, task, "cubes-and-cuboids")] = [r for part in of.run_jobs(chunk, jobs, 2) for r in part]
        os.makedirs(out, exist_ok=True)
        json.dump({f"{a}-{t}": v for (a, t, s), v in cells.items()}, open(out + "/traces.json", "w"))
    md = stops.rules_markdown(cells, rules)
    open(out + "/rules.md", "w").write(md + "\n")
    print(md)
