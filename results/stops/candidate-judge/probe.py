"""A world-8 probe (it patches world 8's ObjectFindingEnv._judge_seen): searchers' episodes with the claim off, and at
the horizon the truth as world 8 judges it (the depth camera alone, beyond the renderer's 1 cm near plane), the truth
beyond the depth camera's minimum range, that truth also in the RGB camera's view, and the searcher's estimate.

    python results/stops/candidate-judge/probe.py AGENT TASK SEED,SEED,... ['{"setting": value}']
    NOFORGET=1 ...: the estimate with no cell ever forgotten
"""
import os
import sys
import numpy as np
sys.path.insert(0, str(__import__('pathlib').Path(__file__).resolve().parents[3]))
import objfind as of

agent_name, task = sys.argv[1], sys.argv[2]
seeds = [int(s) for s in sys.argv[3].split(',')]
orig = of.ObjectFindingEnv._judge_seen

def judge(self, T_world_camera, depth_m):
    orig(self, T_world_camera, depth_m)
    if not self.target_present:
        return
    if not hasattr(self, 'alt'):
        self.alt = {k: np.zeros(len(self.target_points), bool) for k in ('minrange', 'both')}
    import pybullet as pb
    pos, orn = self.sim.getBasePositionAndOrientation(self.objects[0].body)
    R = np.array(pb.getMatrixFromQuaternion(orn)).reshape(3, 3)
    world = self.target_points @ R.T + pos
    normals = self.target_normals @ R.T
    def vis(T, K, depth, zmin):
        to_camera = T[:3, 3] - world
        facing = np.sum(normals * to_camera, 1) > self.cfg.seen_min_cos * of.vector_norm(to_camera)
        cam = (world - T[:3, 3]) @ T[:3, :3]
        z = cam[:, 2]; safe = np.where(z > 1e-6, z, 1.0)
        u = np.floor(K[0, 0] * cam[:, 0] / safe + K[0, 2]).astype(int)
        v = np.floor(K[1, 1] * cam[:, 1] / safe + K[1, 2]).astype(int)
        H, W = depth.shape
        inside = (z > zmin) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        r = depth[np.clip(v, 0, H - 1), np.clip(u, 0, W - 1)]
        return facing & inside & ((r == 0) | (r > z - self.cfg.seen_depth_tol_m))
    zmin = max(self.cfg.near_m, self.cfg.depth_min_range_m)
    d = vis(T_world_camera, self.true_rig.depth.K, depth_m, zmin)
    self.alt['minrange'] |= d
    if not self.true_rig.one_camera:
        T_rgb = T_world_camera @ self.true_rig.T_depth_rgb
        _, rgb_depth = self._render_world(T_rgb, of.dataclasses.replace(self.true_rig.rgb, near_m=self.cfg.near_m))
        self.alt['both'] |= d & vis(T_rgb, self.true_rig.rgb.K, rgb_depth, self.cfg.near_m)
    else:
        self.alt['both'] |= d

of.ObjectFindingEnv._judge_seen = judge
if os.environ.get('NOFORGET'):
    mark = of.TSDFVolume._mark_target_surface
    def nf(self, depth_m, detections, K, T, flat, det_new, rgb_outline):
        return mark(self, depth_m, detections, K, T, flat[:0], det_new[:0], rgb_outline)
    of.TSDFVolume._mark_target_surface = nf
extra = __import__('json').loads(sys.argv[4]) if len(sys.argv) > 4 else {}
env = of.ObjectFindingEnv(task, 'cubes-and-cuboids', claim_margin=5.0, confirm_views=100, **extra)
for seed in seeds:
    agent = of.make_agent(agent_name, env.cfg, seed, None)
    if hasattr(env, 'alt'):
        del env.alt   # before the reset: its first view is judged too
    _, info = env.reset(seed=seed)
    agent.reset(env.searcher, env.gripper_pose())
    done = False
    while not done:
        _, _, done, _, info = env.step(agent.act(env.searcher, env.gripper_pose()))
    print(seed, 'truth %.3f minrange %.3f both %.3f est %.3f' % (info['target_seen_fraction'], env.alt['minrange'].mean(),
          env.alt['both'].mean(), env.searcher.perceived_target_share()), flush=True)
