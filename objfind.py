"""objfind: object finding in cluttered scenes using interactive perception.

A single-file reimplementation of Novkovic, Pautrat et al., "Object Finding in Cluttered Scenes Using
Interactive Perception", ICRA 2020. A gripper with a wrist RGB-D camera looks for a red target among
(active task) or inside piles of (interactive task) objects; its views are fused into a TSDF with a
detection channel, summarised into the 71 numbers of Fig. 2, and an agent picks the next displacement.

Read top to bottom, as data flows: settings; the robot's side (perception, volume, encoder, frames,
searcher, agents, policy, ArmSearch); the simulated world it is fed by (rendering and sensors, scenes,
ObjectFindingEnv); learning (PPO). Below the line where the paper's system ends: input checks, files,
training runs, evaluation and Table II, the demo, and the command line (train, eval, demo).
"""
from __future__ import annotations

import dataclasses
import functools
import itertools
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

# The per-step linear algebra is tiny: BLAS threads would only fight the worker processes for cores.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import cv2
import gymnasium as gym
import numba
import numpy as np
import pybullet_data
import torch
from torch import nn


sys.stderr.flush()
_saved_stderr, _devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
os.dup2(_devnull, 2)   # pybullet prints its build date on import: file descriptor 2 is silenced meanwhile
try:
    import pybullet as pb
    from pybullet_utils.bullet_client import BulletClient
finally:
    os.dup2(_saved_stderr, 2)
    os.close(_saved_stderr), os.close(_devnull)


# ================================================================================================
# Settings: Table I presets and the constants of Sec. IV-A. Lengths in metres, angles in radians.
# Every number of the world and of learning lives here, or in a named constant beside the code using it.
# ================================================================================================

@dataclass(frozen=True)
class Settings:
    """One task preset of Table I with every constant the world needs; the paper's name beside each."""

    # Table I, simulation columns
    min_objects: int = 5                # "Min num. objects"
    max_objects: int = 25               # "Max num. objects"
    num_piles: int = 0                  # "Num. of piles"
    no_target_prob: float = 0.10        # "No target prob."
    exploration_ratio: float = 0.0      # "Exploration ratio": share of pile-task scenes without piles
    workspace_m: float = 0.6            # "Workspace length [m]"
    horizon: int = 130                  # "Time horizon" T
    # Sec. IV-A
    trunc_m: float = 0.04               # TSDF truncation distance
    voxels_per_side: int = 100          # "resolution of 100 voxels per side"
    state_voxel_m: float = 0.006        # the seen target area (the state's and the searchers' share) is counted in
                                        # cells of this size (the policies' training resolution: 0.6 m / 100),
                                        # whatever the volume's voxel size, so a finer volume gives the same share
    max_weight: float = 2.0             # Sec. III-B.1: max TSDF weight, fast forgetting after pushes
    crop_m: float = 1.2                 # state crop: square around the end-effector
    max_step_m: float = 0.06            # max translation per step
    max_turn_rad: float = 0.15          # max roll and yaw per step
    time_penalty: float = 1.0           # r_t
    detection_reward: float = 150.0     # r_d
    # Sec. III-C: simulated detector
    noise_rate: float = 20.0            # lambda of the Exp(lambda) subtracted from true detections
    false_positive_share: float = 0.02  # share of pixels turned into false positives, values ~ Exp(lambda)
    # Sec. IV-B: baselines
    gnbv_samples: int = 10              # n, poses GNBV samples near the current one (simulation)
    gnbv_explored_to_stop: float = 0.97 # GNBV terminates above this explored share ("no target")
    seen_threshold: float = 0.2         # target observed once more than this share of its surface was seen
    # The information rule, where the paper is silent: what every agent is told about its target. True:
    # its size (surface area) is part of the task; the perceived share seen (the searchers' stop, the
    # state's detection factor) is relative to it. False: no agent is told; it is relative to the nominal cube.
    target_size_known: bool = True
    # Table II caption: primitive and shape piles hold more objects
    objects_per_pile_dense: tuple = (15, 30)

    # --- where the paper is silent (README, "Choices") ---
    # objects
    object_size_m: float = 0.04         # side of a cube; other objects are scaled to about this size
    variable_scale: tuple = (0.5, 2.0)  # variable primitives: size factor drawn uniformly from this range
    object_mass_kg: float = 0.1         # a wooden 4 cm cube weighs about 40 g; 0.1 keeps piles stable
    object_friction: float = 0.6        # lateral friction: objects slide when pushed, piles still stand
    model_rolling_friction_m: float = 0.001   # mesh models (balls, blobs) roll to a stop: Bullet's rolling friction
    # wrist camera (TinyRenderer)
    image_width: int = 80
    image_height: int = 60
    fov_y_deg: float = 45.0             # 58 x 45 degrees, close to the real depth camera's 62 x 45
    near_m: float = 0.01
    camera_offset_m: float = 0.08       # camera sits this far behind the fingertips, on the approach axis
    # the rig's sensing (Sec. IV, III-D; README "Choices"): every value 0 gives the ideal RGB-D camera above
    depth_width: int = 0                # a separate depth camera of this many pixels (0: the RGB-D camera) ...
    depth_height: int = 0
    depth_fov_y_deg: float = 0.0        # ... and this vertical field of view
    rgb_offset_m: tuple = (0.0, 0.0, 0.0)   # the RGB camera's origin in the depth camera's frame
    depth_min_range_m: float = 0.0      # no return closer than this
    tof_noise_ratio: float = 0.0        # depth noise: standard deviation / distance
    tof_missing_share: float = 0.0      # pixels without a return, at random
    tof_edge_jump_m: float = 0.0        # a pixel whose neighbour lies this much nearer or farther is on a depth
    tof_edge_drop_share: float = 0.0    # edge: the camera drops this share of them, the rest mix both depths
    hand_eye_error_m: float = 0.0       # the cameras' true pose on the gripper is off by this distance ...
    hand_eye_error_rad: float = 0.0     # ... and angle, in directions drawn per episode
    sensor_error_scale: tuple = (1.0, 1.0)   # domain randomisation (training): each episode multiplies the
                                        # depth noise, missing returns and hand-eye error by a factor drawn
                                        # uniformly from this range; (1, 1) draws nothing
    rig_camera_share: float = 0.0       # domain randomisation (training): this share of episodes is searched
                                        # through RIG_SENSING's cameras and errors, the rest through these
    # gripper
    gripper_mass_kg: float = 0.5
    gripper_force_n: float = 40.0       # bound on the constraint force that drives the gripper ...
    gripper_erp: float = 0.3            # ... closing this share of the gap to its pose per step (Bullet's joint
                                        # ERP; its 0.2 spends half a move's steps on the last centimetre)
    max_roll_rad: float = 1.0           # tilt limit
    ceiling_ratio: float = 0.75         # the end-effector rises to this x workspace_m, above the volume
    fingertip_clearance_m: float = 0.005  # lowest fingertip height above the floor
    gripper_start_margin_m: float = 0.05  # initial pose: this far inside the walls ...
    gripper_start_min_z_m: float = 0.1    # ... at least this high ...
    gripper_start_tries: int = 20         # ... resampled while it overlaps an object, then at the ceiling
    reach_tol_m: float = 0.003          # an action's pose counts as reached within this distance ...
    reach_tol_rad: float = 0.02         # ... and this angle
    stall_m: float = 0.0005             # the gripper stalls (a wall, a heavy pile) if it moves less per check
                                        # (REACH_CHECK_S)
    # physics
    physics_hz: int = 240               # while the gripper moves: at its top speed, about 2 m/s, a step is 9 mm,
                                        # under its fingers' 12 mm (at 120 Hz they pass through a cube)
    settle_hz: int = 120                # while objects come to rest: half the steps, each under 1 cm
    solver_iterations: int = 10         # enough for stable piles, 3x cheaper than pybullet's 50
    move_limit_s: float = 0.5           # simulated time the gripper has to reach one action's pose
    settle_s: float = 0.1               # then for pushed objects to come to rest (the next move steps physics
                                        # if they still roll: each step's observation waits less)
    settle_speed: float = 0.02          # objects slower than this (m/s) count as at rest
    settle_scatter_s: float = 1.0       # a new scene: for scattered objects to come to rest ...
    settle_pile_s: float = 2.0          # ... and for piles
    wall_height_m: float = 0.1
    wall_thickness_m: float = 0.02
    # scenes: scattered objects
    scatter_tries: int = 50             # rejection samples for a free spot before dropping from above
    scatter_gap_m: float = 0.005        # clearance between scattered objects' footprints
    drop_gap_m: float = 0.002           # objects dropped into a pile start this far above their spot
    no_room_drop_m: float = 0.1         # an object without a free spot falls from this height
    # scenes: piles (pile_positions)
    pile_margin_ratio: float = 0.2      # pile centres at least this share of the workspace from the walls ...
    pile_min_apart_ratio: float = 1 / 3 # ... and from each other (but for pile_overlap_chance per draw)
    pile_overlap_chance: float = 0.02   # so a crowded workspace still finds centres
    pile_layers: int = 7                # a pile is a square pyramid of spots, 7 x 7 at the bottom
    pile_spacing_ratio: float = 0.8     # spot spacing / the widest object's diameter: neighbours touch
    pile_layer_cost: float = 0.45       # a layer up costs this many rings out: piles grow tall, not wide
    pile_spot_noise: float = 0.01       # random tie-break between spots of equal cost
    pile_jitter_ratio: float = 0.1      # std of a spot's xy jitter / the spacing
    pile_layer_gap_m: float = 0.005     # vertical clearance between layers when dropped
    # rewards and ground truth
    exploration_normaliser: float = 0.03  # newly explored share of the volume that earns the full r_t
    surface_points: int = 1000          # ground-truth points on the target surface (+-0.013 at 0.2)
    seen_depth_tol_m: float = 0.01      # a point is unoccluded if within this of the rendered depth
    seen_min_cos: float = 0.15          # a surface seen more obliquely than ~80 degrees is not resolved
    # perceived target (the volume's estimate, for the searchers)
    detection_threshold: float = 0.5    # a detection voxel or pixel above this counts as target
    outline_pixel_share: float = 0.5    # a detected pixel on the outline counts as half target area
    claim_margin: float = 1.25          # the searchers claim "found" once the estimate is above this x
    confirm_views: int = 2              # seen_threshold in this many views in a row: the estimate's spread
                                        # at the bar alone gave 0.6-8.5 % early claims (weights/README.md)
    state_share_scale: float = 1.0      # the state carries the perceived share times this: on the simulated camera's
                                        # scale, for a policy trained there (the rig's estimate spreads wider)
    area_median_px: int = 0             # the area a pixel covers is taken on depth median-filtered over this
                                        # many pixels (0: none); 1 % ToF noise alone nearly doubles it (README)
    # baselines
    gnbv_rays: tuple = (16, 12)         # GNBV casts this grid of rays per candidate view
    gnbv_min_detections: int = 3        # GNBV centres the target once this many detection voxels agree
    gnbv_stall_voxels: int = 50         # GNBV has explored all one-step moves can reach when no sampled
    gnbv_stall_steps: int = 3           # view would reveal this many voxels (of its 16 x 12 rays) 3 times;
                                        # both counts are of voxels of state_voxel_m, scaled to the volume's
    ges_clearance_m: float = 0.01       # GES sweeps with its fingertips this far above a nominal cube
    ges_tries_per_node: int = 3         # GES gives up a node it cannot reach (a pile) after this many

    @property
    def voxel_m(self) -> float:
        return self.workspace_m / self.voxels_per_side

    @property
    def volume_height_m(self) -> float:
        """The volume is half as high as it is wide: it holds the tallest pile."""
        return self.workspace_m / 2

    @property
    def ceiling_m(self) -> float:
        """Highest end-effector position: above the volume's top, so the camera can look down on it."""
        return self.ceiling_ratio * self.workspace_m

    @property
    def far_m(self) -> float:
        return 2.0 * self.workspace_m

    @property
    def nominal_target_area_m2(self) -> float:
        """Surface of the nominal target, a cube of side object_size_m."""
        return 6 * self.object_size_m ** 2

    scaled_sensor_errors: ClassVar[tuple] = ("tof_noise_ratio", "tof_missing_share", "hand_eye_error_m",
                                             "hand_eye_error_rad")   # what sensor_error_scale multiplies


# The paper's wrist rig (Sec. IV): a CamBoard pico flexx time-of-flight camera beside a Chameleon 3 RGB
# camera, joined to the gripper by hand-eye calibration. Sources and assumptions: README, "Choices".
RIG_SENSING = dict(
    depth_width=224, depth_height=171, depth_fov_y_deg=45.0,   # pico flexx datasheet: 224 x 171 px, 62 x 45 deg
    depth_min_range_m=0.1,                                     # datasheet: 0.1-4 m
    tof_noise_ratio=0.01,                                      # datasheet: <= 1 % of the distance
    tof_missing_share=0.02, tof_edge_jump_m=0.02, tof_edge_drop_share=0.5,   # assumed, README
    rgb_offset_m=(0.03, 0.0, 0.0),                             # assumed: the two cameras side by side
    camera_offset_m=0.12,                                      # assumed: what the fingertips touch lies beyond
                                                               # the minimum range (8 cm: GES blind, README)
    area_median_px=3,                                          # the robot's filter for such a camera (README)
    state_share_scale=1.25 / 2.0,                              # its searchers claim at 2 x the bar, not 1.25 x
    hand_eye_error_m=0.003, hand_eye_error_rad=0.0175)         # assumed: 3 mm and 1 degree

TASKS = {
    "ap": Settings(),
    "ap-large": Settings(min_objects=10, max_objects=40, workspace_m=1.2, horizon=500, state_voxel_m=0.012),
    "ip": Settings(min_objects=15, max_objects=75, num_piles=3, exploration_ratio=0.25),
    # Table I's real-world columns with the rig's sensing; GNBV samples 30 poses there (Sec. IV-B)
    "ap-real": Settings(min_objects=15, max_objects=30, no_target_prob=0.0, workspace_m=0.33, horizon=50,
                        gnbv_samples=30, claim_margin=2.0, **RIG_SENSING),   # 1.5 x 2, 1.75 x 3 claimed early
    "ip-real": Settings(min_objects=15, max_objects=30, num_piles=4, no_target_prob=0.0, exploration_ratio=0.1,
                        workspace_m=0.33, horizon=50, gnbv_samples=30, confirm_views=3,
                        **RIG_SENSING),   # 1.25 x 2 claimed early
}

TABLE_SCENES = ("cubes", "fixed-primitives", "variable-primitives", "random-shapes", "object-models")   # Table II
SCENES = TABLE_SCENES + ("cubes-and-cuboids",)   # and the real experiments' scenes (Sec. IV-D)


@dataclass(frozen=True)
class PPOSettings:
    """PPO for A3DE and I3DE (Sec. III-B.4, IV-A); the paper's name beside each of its constants. A new
    field is this one line: checkpoints, `--set` and the checks below read the fields of the class."""

    hidden: int = 200                  # "2 hidden layers with 200 units"
    batch_steps: int = 5000            # "batch size of 5000" env steps per update
    minibatch: int = 500               # "minibatch size of 500"
    gamma: float = 0.99                # discount factor
    entropy_coef: float = 0.01         # entropy bonus
    # --- where the paper is silent (README, "Choices") ---
    gae_lambda: float = 0.95           # GAE: the usual bias-variance balance
    clip: float = 0.2                  # clipped surrogate objective
    epochs: int = 10                   # passes over each batch
    learning_rate: float = 3e-4        # Adam
    value_coef: float = 0.5            # weight of the value loss
    max_grad_norm: float = 0.5         # gradient clipping
    reward_scale: float = 1 / 150      # rewards divided by r_d: returns of order one for the critic
    init_log_std: float = -0.5         # initial std 0.6 of the five displacements (the Box is [-1, 1])
    init_terminate_prob: float = 0.02  # a fresh policy that terminated half the time would never look
    adam_eps: float = 1e-5             # Adam's epsilon, as in OpenAI Baselines' PPO2
    obs_clip: float = 5.0              # normalised observations are clipped to +- this many std
    checkpoint_every: int = 5          # updates between checkpoints
    entropy_end_ratio: float = 1.0     # the entropy bonus, the learning rate and the discount go linearly,
    learning_rate_end_ratio: float = 1.0   # from schedule_start_share to schedule_share of the run's --steps, to
    gamma_end_ratio: float = 1.0       # these shares of their values, then stay there (1: constant; `scheduled`;
    schedule_start_share: float = 0.0  # train's TRAIN_RECIPES)
    schedule_share: float = 1.0


# ================================================================================================
# Perception (Sec. III-B.1): the robot's detector, a CIELAB colour detector of the red target.
# ================================================================================================

RED_MIN_CHROMA = 20.0            # CIELAB chroma sqrt(a*^2 + b*^2): saturated enough to be a colour
RED_HUE_DEG = (-10.0, 50.0)      # CIELAB hue atan2(b*, a*): red, not orange, pink or purple


def detect_target(rgb: np.ndarray) -> np.ndarray:
    """CIELAB red detector: (H, W, 3) uint8 RGB -> (H, W) float32, 1 on the target, 0 elsewhere. Hue and
    chroma barely change with shading: lit and shadowed red faces pass, no blue, purple, yellow or grey does."""
    lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2LAB).astype(np.float32)
    a, b = lab[..., 1] - 128, lab[..., 2] - 128   # OpenCV stores a*, b* offset by 128
    hue = np.degrees(np.arctan2(b, a))
    red = (np.hypot(a, b) > RED_MIN_CHROMA) & (hue > RED_HUE_DEG[0]) & (hue < RED_HUE_DEG[1])
    return red.astype(np.float32)


# ================================================================================================
# Volume (Sec. III-B.1): a TSDF with a detection channel, carving and max weight 2; one loop over voxels,
# compiled by Numba (as in Zeng's tsdf-fusion-python), the rest numpy.
# ================================================================================================

MIN_PROJECTION_Z_M = np.float32(1e-3)   # guards the division by z; the renderer's near plane cuts depth anyway
CARVED_TSDF = 0.5    # a voxel this far (x trunc) in front of every surface seen through it is free space
LAYER_SLACK = 1e-3   # fuse_view: slack (pixels x m, or m) on the layers it visits, far above any rounding


def vector_norm(x: np.ndarray) -> np.ndarray:
    """Lengths of (..., 3) vectors: np.linalg.norm's sums in its order, in a quarter of its time."""
    return np.sqrt(x[..., 0] * x[..., 0] + x[..., 1] * x[..., 1] + x[..., 2] * x[..., 2])


def surface_derivative(points: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives of a point image along an image axis: the smaller and the larger of the two one-sided
    differences (at the image's edge, the one there is, twice)."""
    steps = np.diff(points, axis=axis)
    backward = np.concatenate([np.take(steps, [0], axis), steps], axis)
    forward = np.concatenate([steps, np.take(steps, [-1], axis)], axis)
    use_forward = (vector_norm(forward) < vector_norm(backward))[..., None]
    return np.where(use_forward, forward, backward), np.where(use_forward, backward, forward)


def outline_of(mask: np.ndarray) -> np.ndarray:
    """The pixels of a (H, W) mask with a 4-neighbour outside it."""
    return mask & ~(np.roll(mask, 1, 0) & np.roll(mask, -1, 0) & np.roll(mask, 1, 1) & np.roll(mask, -1, 1))


def back_project(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) camera-frame points of a depth image's pixel centres, depth along z."""
    rows, cols = np.mgrid[0:depth_m.shape[0], 0:depth_m.shape[1]] + 0.5
    return np.stack([(cols - K[0, 2]) / K[0, 0] * depth_m, (rows - K[1, 2]) / K[1, 1] * depth_m, depth_m], -1)


@numba.njit(cache=True, nogil=True)
def fuse_view(tsdf, weight, channel, depth_m, detections, terms_x, terms_y, terms_z, columns, far_m, trunc_m,
              per_trunc_m, max_weight, updated_voxels, updated_detections):
    """TSDF fusion's loop over voxels: each voxel of the given columns that projects onto a return and lies in
    front of it or up to trunc_m behind takes the view into its running averages (TSDFVolume.integrate).
    terms_*: (3, n) per-axis terms of (u z, v z, z). Returns (voxels seen for the first time, voxels updated)
    and writes the updated ones' flat indices and new channel values to updated_*. Voxel centres and a
    view's values are float64, the volume float32 (a test: the same volume as whole-volume numpy)."""
    H, W = depth_m.shape
    nz = terms_z.shape[1]
    slope = (terms_z[:, nz - 1] - terms_z[:, 0]) / max(nz - 1, 1)   # (u z, v z, z) per layer
    newly, updated = 0, 0
    for i in range(columns[0], columns[1]):
        for j in range(columns[2], columns[3]):
            # The layers where a voxel can pass the exact tests below: z > MIN_PROJECTION_Z_M, 0 <= u z < W z,
            # 0 <= v z < H z and z <= far_m are each a + b k >= 0 along the column, solved with slack.
            u0 = terms_x[0, i] + terms_y[0, j] + terms_z[0, 0]
            v0 = terms_x[1, i] + terms_y[1, j] + terms_z[1, 0]
            z0 = terms_x[2, i] + terms_y[2, j] + terms_z[2, 0]
            lo, hi = 0.0, nz - 1.0
            for a, b in ((z0 - MIN_PROJECTION_Z_M, slope[2]), (u0, slope[0]), (W * z0 - u0, W * slope[2] - slope[0]),
                         (v0, slope[1]), (H * z0 - v0, H * slope[2] - slope[1]), (far_m - z0, -slope[2])):
                if b > 0.0:
                    lo = max(lo, (-LAYER_SLACK - a) / b)
                elif b < 0.0:
                    hi = min(hi, (a + LAYER_SLACK) / -b)
                elif a < -LAYER_SLACK:
                    hi = -1.0
            if hi < lo:
                continue
            for k in range(max(int(np.floor(lo)) - 1, 0), min(int(np.ceil(hi)) + 2, nz)):
                z = (terms_x[2, i] + terms_y[2, j]) + terms_z[2, k]
                if not z > MIN_PROJECTION_Z_M:
                    continue
                u = ((terms_x[0, i] + terms_y[0, j]) + terms_z[0, k]) / z
                v = ((terms_x[1, i] + terms_y[1, j]) + terms_z[1, k]) / z
                if not (u >= 0 and u < W and v >= 0 and v < H):
                    continue
                row, col = int(v), int(u)
                depth = depth_m[row, col]
                sdf = depth - z
                if not (depth > 0 and sdf >= -trunc_m):   # no return, or behind the surface by more: unseen
                    continue
                w_old = weight[i, j, k]
                if w_old == 0:
                    newly += 1
                if sdf >= trunc_m and w_old == max_weight and tsdf[i, j, k] == 1:
                    continue   # free space known as free at full weight: averaging 1 into 1 changes nothing
                # the weighted average, each view weighing 1; detections as a truncated unsigned distance (the
                # pixel's score fading to 0 at trunc_m), averaged alike and carved out of free space
                w_sum = w_old + np.float32(1.0)
                tsdf[i, j, k] = (tsdf[i, j, k] * w_old + min(1.0, sdf * per_trunc_m)) / w_sum
                fade = max(0.0, 1.0 - abs(sdf) / trunc_m)
                detection_new = (channel[i, j, k] * w_old + detections[row, col] * fade) / w_sum
                if sdf >= trunc_m:
                    detection_new = 0.0
                channel[i, j, k] = detection_new
                weight[i, j, k] = min(w_sum, max_weight)
                updated_voxels[updated] = (i * tsdf.shape[1] + j) * nz + k
                updated_detections[updated] = detection_new
                updated += 1
    return newly, updated


class TSDFVolume:
    """A TSDF over the workspace plus a detection channel (a truncated *unsigned* distance of detections).
    Voxel (i, j, k) is centred at origin + (i + 0.5, j + 0.5, k + 0.5) voxel_m, the origin at (-size/2, -size/2, 0),
    as in Open3D; arrays are [x, y, z]. Unobserved voxels hold 0, so sums say how much was observed."""

    def __init__(self, cfg: Settings):
        self.voxel_m = cfg.voxel_m
        self.shape = (cfg.voxels_per_side, cfg.voxels_per_side, int(round(cfg.volume_height_m / self.voxel_m)))
        self.origin = np.array([-cfg.workspace_m / 2, -cfg.workspace_m / 2, 0.0])
        self.trunc_m, self.max_weight = cfg.trunc_m, cfg.max_weight
        self.tsdf = np.zeros(self.shape, np.float32)        # (nx, ny, nz) signed distance / trunc
        self.weight = np.zeros(self.shape, np.float32)      # (nx, ny, nz) observations, at most max_weight
        self.detections = np.zeros(self.shape, np.float32)  # (nx, ny, nz) detection score near surfaces
        self.detection_threshold, self.seen_min_cos = cfg.detection_threshold, cfg.seen_min_cos
        self.outline_pixel_share, self.area_median_px = cfg.outline_pixel_share, cfg.area_median_px
        # The target surface seen is kept in cells of state_voxel_m whatever the voxel size: two views' samples
        # of one surface then share their cells, and the max over views counts the surface once. A surface
        # along a cell border splits its samples between cells, and would count twice; so it is kept on two
        # grids half a cell apart, sparse (cell index -> m^2), and the smaller total counts.
        self.area_cell_m = cfg.state_voxel_m
        extent = np.array(self.shape) * self.voxel_m
        self.area_shape = tuple(int(np.ceil(e / self.area_cell_m - 1e-9)) + 1 for e in extent)
        self.area_offsets = (0.0, self.area_cell_m / 2)   # the second grid starts half a cell lower
        # Voxel centres are separable, so we keep three 1-D axes instead of an (N, 3) array: a voxel's
        # projection is then a sum of three per-axis terms (integrate), never a matrix product per voxel.
        self.axes = [(np.arange(n, dtype=np.float32) + 0.5) * self.voxel_m + o
                     for n, o in zip(self.shape, self.origin)]
        self.column_xy = [c.reshape(-1) for c in np.meshgrid(self.axes[0], self.axes[1], indexing="ij")]
        self.updated_voxels = np.zeros(self.tsdf.size, np.int64)         # written by fuse_view: the voxels a
        self.updated_detections = np.zeros(self.tsdf.size, np.float64)   # view updated, their new detections
        self.observed_count = 0   # running count of voxels with weight > 0, kept by integrate()
        self.target_area = None   # per grid: (flat cell indices, m^2 of target surface seen in each)
        self.reset()

    def reset(self) -> None:
        self.tsdf.fill(0.0), self.weight.fill(0.0), self.detections.fill(0.0)
        self.target_area = [(np.zeros(0, np.int64), np.zeros(0)) for _ in self.area_offsets]
        self.observed_count = 0

    def explored_fraction(self) -> float:
        return self.observed_count / self.weight.size

    def frustum_columns(self, image_shape, far_m: float, K, T_world_camera) -> tuple[int, int, int, int]:
        """(i0, i1, j0, j1): the columns under the camera's frustum up to far_m, the xy box of its apex and
        far corners grown by a voxel; no voxel outside it can be updated."""
        H, W = image_shape
        u, v = np.array([0, W, W, 0], np.float64), np.array([0, 0, H, H], np.float64)
        base = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(4)], 1) * far_m
        corners = np.concatenate([[[0.0, 0.0, 0.0]], base]) @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]
        lo = np.floor((corners.min(0)[:2] - self.origin[:2]) / self.voxel_m).astype(int) - 1
        hi = np.ceil((corners.max(0)[:2] - self.origin[:2]) / self.voxel_m).astype(int) + 1
        lo, hi = np.clip(lo, 0, self.shape[:2]), np.clip(hi, 0, self.shape[:2])
        return int(lo[0]), int(hi[0]), int(lo[1]), int(hi[1])

    def integrate(self, depth_m: np.ndarray, detections: np.ndarray, K: np.ndarray,
                  T_world_camera: np.ndarray, rgb_outline: np.ndarray | None = None) -> int:
        """Fuse one view, (H, W) depth in metres along z (0: no return) and (H, W) detection scores in [0, 1], by
        the weighted running average of Curless & Levoy (1996), weights capped at max_weight (2: two new views
        overwrite what a push moved). rgb_outline: the depth pixels on the detections' outline in a separate RGB
        camera's image. Returns the number of voxels observed for the first time."""
        if not np.any(depth_m > 0):
            return 0
        far_m = float(depth_m.max()) + self.trunc_m   # no voxel farther can be seen
        columns = self.frustum_columns(depth_m.shape, far_m, K, T_world_camera)
        if columns[0] >= columns[1] or columns[2] >= columns[3]:
            return 0
        # A voxel centre's pixel is (fx x + cx z) / z, (fy y + cy z) / z with x, y, z linear in the centre: each
        # row of world_to_pixel times the centre's offset from the camera is a sum of three per-axis terms.
        world_to_pixel = (K @ T_world_camera[:3, :3].T).astype(np.float32)   # (3, 3) rows give u z, v z, z
        t = T_world_camera[:3, 3].astype(np.float32)
        terms = [world_to_pixel[:, [axis]] * (self.axes[axis] - t[axis]) for axis in range(3)]   # 3 x (3, n)
        newly, updated = fuse_view(
            self.tsdf, self.weight, self.detections, np.ascontiguousarray(depth_m),
            np.ascontiguousarray(detections), *terms, columns, far_m, self.trunc_m,
            1.0 / self.trunc_m, np.float32(self.max_weight), self.updated_voxels, self.updated_detections)
        self.observed_count += newly
        self._mark_target_surface(depth_m, detections, K, T_world_camera, self.updated_voxels[:updated],
                                  self.updated_detections[:updated], rgb_outline)
        return newly

    def _mark_target_surface(self, depth_m, detections, K, T_world_camera, flat, det_new, rgb_outline) -> None:
        """Keep `target_area`: per cell, the most target surface (m^2) one view saw in it, from the detected
        pixels back-projected with the area each covers. The detection band itself cannot say how much of a small
        target was seen (it is as thick as a cube, half of it carved by the next view). A cell's area is
        cleared when this view updates the voxel at its centre and that voxel's detection falls to the
        threshold; with a separate RGB camera, to half of it where the view also carved that voxel."""
        # Detections from a separate RGB camera are registered to about one of its pixels, so a view that misses
        # a cell is expected: the cell forgets at half the threshold after repeated misses, and only once a view
        # saw through its voxel (a push moved the target away, or it was never there).
        forget_at = self.detection_threshold / 2 if rgb_outline is not None else self.detection_threshold
        if any(len(cells) for cells, _ in self.target_area):   # most views: no target seen yet, nothing to forget
            faded = np.zeros(self.detections.size, bool)
            missed = det_new <= forget_at
            if rgb_outline is not None:
                missed &= self.tsdf.reshape(-1)[flat] > CARVED_TSDF
            faded[flat[missed]] = True
        for g, (offset, (cells, area)) in enumerate(zip(self.area_offsets, self.target_area)):
            if len(cells):
                centres = (np.stack(np.unravel_index(cells, self.area_shape), 1) + 0.5) * self.area_cell_m - offset
                voxel = np.minimum(np.floor(np.maximum(centres, 0) / self.voxel_m).astype(np.int64),
                                   np.array(self.shape) - 1)
                keep = ~faded[np.ravel_multi_index(tuple(voxel.T), self.shape)]
                self.target_area[g] = cells[keep], area[keep]
        detected = (detections > self.detection_threshold) & (depth_m > 0)
        if not detected.any():
            return
        # A pixel covers |dP/du x dP/dv| of surface, P the back-projected depth image, each derivative taken
        # towards the neighbour on the same surface (the smaller one-sided difference), so that the target's
        # outline does not borrow the depth jump to the background. A pixel seeing its surface more obliquely
        # than the ground truth's limit by either one-sided difference counts nothing (an edge-on face is a
        # sliver whose smaller differences lean on the face beside it); one on the detections' outline (partly
        # target at best), or on their outline in a separate RGB camera's image (registered only to about one
        # RGB pixel), half. 2 x 2 sub-pixels carry a quarter of a pixel's area each, so that area lands in the
        # right cell even when a pixel is as large as a cell. On a noisy camera the derivatives are taken on
        # median-filtered depth (area_median_px): noise roughens a surface, and a rough surface has more area.
        smooth_m = cv2.medianBlur(depth_m.astype(np.float32), self.area_median_px) if self.area_median_px else depth_m
        points = back_project(smooth_m, K)
        (near_u, far_u), (near_v, far_v) = surface_derivative(points, 1), surface_derivative(points, 0)
        pixel_area = vector_norm(np.cross(near_u, near_v))
        footprint = (depth_m / K[0, 0]) ** 2
        pixel_area[np.maximum(pixel_area, vector_norm(np.cross(far_u, far_v))) * self.seen_min_cos > footprint] = 0.0
        outline = outline_of(detected)
        if rgb_outline is not None:
            outline |= rgb_outline & detected
        if self.area_median_px:   # a noisy camera's outline pixels fly between the surfaces: no slant to tell
            pixel_area[outline] = np.minimum(pixel_area[outline], footprint[outline])
        pixel_area[outline] *= self.outline_pixel_share
        v, u = np.nonzero(detected)
        z = np.repeat(depth_m[v, u], 4)
        su = np.repeat(u, 4) + np.tile([0.25, 0.75, 0.25, 0.75], len(u))
        sv = np.repeat(v, 4) + np.tile([0.25, 0.25, 0.75, 0.75], len(v))
        camera = np.stack([(su - K[0, 2]) / K[0, 0] * z, (sv - K[1, 2]) / K[1, 1] * z, z], 1)
        world = camera @ T_world_camera[:3, :3].T + T_world_camera[:3, 3] - self.origin
        world[:, 2] = np.maximum(world[:, 2], 0.0)   # the floor's own points, rounded a hair below it
        area = np.repeat(pixel_area[v, u], 4) / 4
        for g, offset in enumerate(self.area_offsets):
            index = np.floor((world + offset) / self.area_cell_m).astype(np.int64)
            inside = np.all((index >= 0) & (index < self.area_shape), axis=1)
            hit = np.ravel_multi_index(tuple(index[inside].T), self.area_shape)
            cells, which = np.unique(np.concatenate([self.target_area[g][0], hit]), return_inverse=True)
            merged = np.zeros(len(cells))
            old = len(self.target_area[g][0])
            merged[which[:old]] = self.target_area[g][1]   # the old cells are unique
            view = np.bincount(which[old:], weights=area[inside], minlength=len(cells))
            self.target_area[g] = cells, np.maximum(merged, view)

    def seen_target_area_m2(self) -> float:
        """The target surface the volume holds as seen (m^2), the smaller of its two grids' totals: what the
        searchers' stop rule divides."""
        return float(min(area.sum() for _, area in self.target_area))


# ================================================================================================
# Encoder (Sec. III-B.1, Fig. 2): the volume around the end-effector -> 71 values.
# ================================================================================================

BINS = 17                      # pooled cells per map (Fig. 2)
MAP_NAMES = ("TSDF above", "TSDF below", "detections above", "detections below")   # of the fingertips
MAPS = len(MAP_NAMES)
STATE_TSDF_SUM, STATE_TARGET_SHARE, STATE_ROLL = MAPS * BINS, MAPS * BINS + 1, MAPS * BINS + 2
STATE_SIZE = MAPS * BINS + 3   # 71: the maps, the two normalisation factors (Fig. 2), the roll

# The 17 bins, seen from above in the end-effector's yaw frame (x forward, y to the left):
# a 3 x 3 grid of crop/3 cells indexed (a, b) with a along x (0 back .. 2 front) and b along y
# (0 right .. 2 left). The 8 outer cells are bins 0-7 in row-major (a, b) order, the middle cell is
# split again into 3 x 3 cells (c, d), bins 8 + 3c + d. Bin 17 collects columns outside the crop.
OUTER_BIN = np.array([0, 1, 2, 3, -1, 4, 5, 6, 7])


def column_bins(u: np.ndarray, v: np.ndarray, crop_m: float) -> np.ndarray:
    """Bin (0..16, or BINS = 17 outside the crop) of columns at (u, v) metres in the end-effector's yaw frame."""
    cell = crop_m / 3
    a = np.floor((u + crop_m / 2) / cell).astype(np.int64)
    b = np.floor((v + crop_m / 2) / cell).astype(np.int64)
    inside = (a >= 0) & (a < 3) & (b >= 0) & (b < 3)
    outer = np.where(inside, a * 3 + b, 0)
    c = np.clip(np.floor((u + cell / 2) / (cell / 3)), 0, 2).astype(np.int64)
    d = np.clip(np.floor((v + cell / 2) / (cell / 3)), 0, 2).astype(np.int64)
    bins = np.where(outer == 4, 8 + 3 * c + d, OUTER_BIN[outer])
    return np.where(inside, bins, BINS)


@numba.njit(cache=True, nogil=True)
def pool_columns(maps: np.ndarray, bins: np.ndarray) -> np.ndarray:
    """(MAPS, BINS) float64 sums of (MAPS, columns) maps over each bin's columns, added in column order as
    np.bincount adds them, without its index array; columns in bin BINS, outside the crop, are dropped."""
    pooled = np.zeros((maps.shape[0], BINS))
    for c in range(maps.shape[1]):
        if bins[c] < BINS:
            for m in range(maps.shape[0]):
                pooled[m, bins[c]] += maps[m, c]
    return pooled


def encode_state(volume: TSDFVolume, ee_xyz, ee_yaw: float, ee_roll: float, finger_z: float,
                 crop_m: float, target_share: float) -> np.ndarray:
    """Fig. 2's state, (71,) float32: TSDF above / below the fingertips, then detections above / below, summed
    along z and pooled into 17 bins around the gripper, each pair normalised by its own sum; then the TSDF sum
    per voxel, the detection part's factor, and the roll. That factor is `target_share`, the share of the
    target's surface the volume holds as seen, not the raw detection sum: the sum counts every false positive
    of the detector, and tracks the truth near the 20 % bar far worse (README, "Choices")."""
    nx, ny, nz = volume.shape
    k = int(np.clip(round(finger_z / volume.voxel_m), 0, nz))
    # Summing each column above and below the fingertips is one matrix product with a (nz, 2) mask.
    layers = np.zeros((nz, 2), np.float32)
    layers[k:, 0], layers[:k, 1] = 1.0, 1.0
    maps = np.concatenate([(volume.tsdf.reshape(-1, nz) @ layers).T,
                           (volume.detections.reshape(-1, nz) @ layers).T])   # (4, nx * ny)
    # rotate column centres (not the volume) into the yaw frame: 10^4 points instead of 5 * 10^5 voxels
    cx, cy = volume.column_xy[0] - ee_xyz[0], volume.column_xy[1] - ee_xyz[1]
    cos, sin = np.cos(ee_yaw), np.sin(ee_yaw)
    bins = column_bins(cos * cx + sin * cy, -sin * cx + cos * cy, crop_m)
    pooled = pool_columns(maps, bins)
    tsdf_sum, det_sum = pooled[:2].sum(), pooled[2:].sum()
    pooled[:2] /= tsdf_sum if abs(tsdf_sum) > 1e-6 else 1.0
    pooled[2:] /= det_sum if abs(det_sum) > 1e-6 else 1.0
    sums = [tsdf_sum / volume.tsdf.size, target_share]
    return np.concatenate([pooled.reshape(-1), sums, [ee_roll]]).astype(np.float32)


# ================================================================================================
# Frames (Sec. III-B.2): the gripper's pose and the cameras on its wrist.
# ================================================================================================

def rotation(angle: float, axis: str) -> np.ndarray:
    """The 3 x 3 rotation by `angle` (radians) about the coordinate axis "x", "y" or "z"."""
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    R = np.eye(3)
    R[i, i] = R[j, j] = np.cos(angle)
    R[i, j], R[j, i] = -np.sin(angle), np.sin(angle)
    return R


def axis_angle_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """The 3 x 3 rotation by `angle` (radians) about a unit axis (Rodrigues' formula)."""
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew


# The gripper in the tool frame (origin between the fingertips, z along the approach axis): a palm
# and two fingers, as (half extents, centre) boxes.
GRIPPER_BOXES = (((0.045, 0.015, 0.01), (0.0, 0.0, -0.09)),
                 ((0.006, 0.012, 0.04), (-0.032, 0.0, -0.04)), ((0.006, 0.012, 0.04), (0.032, 0.0, -0.04)))

FINGER_REACH_M = 0.038   # lateral reach of the fingers: how far a fingertip dips below the ee when rolled

# Tool axes in the yaw frame at roll 0: x to the gripper's right, y backward, z down (the approach axis).
R_YAW_TOOL = np.array([[0, -1, 0], [-1, 0, 0], [0, 0, -1.0]])


def gripper_rotation(yaw: float, roll: float) -> np.ndarray:
    """R_world_tool: yaw about world z, then roll about the yaw frame's forward axis."""
    return rotation(yaw, "z") @ rotation(roll, "x") @ R_YAW_TOOL


def yaw_roll_of(R_world_tool: np.ndarray) -> tuple[float, float]:
    """Inverse of `gripper_rotation` (ignores any small pitch a push may cause)."""
    M = R_world_tool @ R_YAW_TOOL.T
    return float(np.arctan2(M[1, 0], M[0, 0])), float(np.arctan2(M[2, 1], M[2, 2]))


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera in OpenCV's frame (x right, y down, z forward; depth along z), square pixels:
    pixel (u, v) covers [u, u + 1) x [v, v + 1), so its centre is u + 0.5."""

    width: int
    height: int
    K: np.ndarray                # (3, 3) intrinsics
    near_m: float = 0.0          # no depth returns closer than this ...
    far_m: float = np.inf        # ... or farther


@dataclass(frozen=True, eq=False)
class Rig:
    """The wrist cameras as the robot knows them: a depth camera, an RGB camera (the same object when one
    RGB-D camera gives both), and where they sit."""

    depth: Camera
    rgb: Camera
    T_tool_depth: np.ndarray     # (4, 4) the depth camera in the tool frame: the hand-eye calibration
    T_depth_rgb: np.ndarray      # (4, 4) the RGB camera in the depth camera's frame: the extrinsics

    @property
    def one_camera(self) -> bool:
        """One RGB-D camera: the colour and the depth image share their pixels."""
        return self.rgb is self.depth and np.array_equal(self.T_depth_rgb, np.eye(4))

    def detections_in_depth_image(self, detections: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
        """The RGB image's (H', W') detection scores (or (H', W', C) values) at each depth pixel, (H, W[, C]): the
        pixel back-projected by its depth, moved into the RGB camera, and read where it projects (0 off the image)."""
        if self.one_camera:
            return detections
        K_rgb, T_rgb_depth = self.rgb.K, np.linalg.inv(self.T_depth_rgb)
        in_rgb = back_project(depth_m, self.depth.K) @ T_rgb_depth[:3, :3].T + T_rgb_depth[:3, 3]
        z = np.where(in_rgb[..., 2] > MIN_PROJECTION_Z_M, in_rgb[..., 2], np.inf)
        u = np.floor(K_rgb[0, 0] * in_rgb[..., 0] / z + K_rgb[0, 2]).astype(np.int64)
        v = np.floor(K_rgb[1, 1] * in_rgb[..., 1] / z + K_rgb[1, 2]).astype(np.int64)
        hit = (depth_m > 0) & np.isfinite(z) & (u >= 0) & (u < self.rgb.width) & (v >= 0) & (v < self.rgb.height)
        out = np.zeros(depth_m.shape + detections.shape[2:], np.float32)
        out[hit] = detections[v[hit], u[hit]]
        return out


def pinhole(width: int, height: int, fov_y_deg: float, near_m: float, far_m: float) -> Camera:
    """A camera of square pixels with its principal point at the image's centre."""
    f = (height / 2) / np.tan(np.radians(fov_y_deg) / 2)
    return Camera(width, height, np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]]), near_m, far_m)


def wrist_rig(cfg: Settings) -> Rig:
    """The wrist cameras as the robot knows them. By default one RGB-D camera on the approach axis,
    camera_offset_m behind the fingertips; with depth_width, a depth camera there and the RGB camera
    rgb_offset_m from it. The tool frame already has OpenCV's axes (x to the gripper's right, y backward,
    z along the approach axis), so the camera looks between the fingers with the gripper's front at the top."""
    rgb = pinhole(cfg.image_width, cfg.image_height, cfg.fov_y_deg, max(cfg.near_m, cfg.depth_min_range_m), cfg.far_m)
    depth = rgb if cfg.depth_width == 0 else pinhole(cfg.depth_width, cfg.depth_height, cfg.depth_fov_y_deg,
                                                     max(cfg.near_m, cfg.depth_min_range_m), cfg.far_m)
    T_tool_depth, T_depth_rgb = np.eye(4), np.eye(4)
    T_tool_depth[2, 3] = -cfg.camera_offset_m
    T_depth_rgb[:3, 3] = cfg.rgb_offset_m
    return Rig(depth, rgb, T_tool_depth, T_depth_rgb)


# ================================================================================================
# The searcher (Sec. III-B, Fig. 2): what the robot holds and computes, and nothing of the simulator.
# Views in (depth, detections or RGB, the camera's pose) -> the volume -> the 71-value state; a
# policy's action -> the next gripper pose. The same class runs on simulated and on recorded frames.
# ================================================================================================

def target_observed(share: float, seen_threshold: float) -> bool:
    """Sec. III-C's "more than 20 %" seen: the one rule for the world's truth and every agent's estimate."""
    return share > seen_threshold


class Searcher:
    """The robot's side of Fig. 2: its wrist rig, the volume its views fill, the encoder, the told target
    size, the stop threshold and the limits of one step. It opens no physics client."""

    def __init__(self, cfg: Settings, rig: Rig | None = None):
        self.rig = rig or wrist_rig(cfg)
        self.volume = TSDFVolume(cfg)
        self.crop_m = cfg.crop_m
        self.state_share_scale = cfg.state_share_scale
        self.claim_share, self.confirm_views = cfg.claim_margin * cfg.seen_threshold, cfg.confirm_views
        self.detection_threshold = cfg.detection_threshold
        self.workspace_m, self.ceiling_m = cfg.workspace_m, cfg.ceiling_m           # the box it moves in
        self.max_step_m, self.max_turn_rad = cfg.max_step_m, cfg.max_turn_rad       # one step's reach
        self.max_roll_rad, self.fingertip_clearance_m = cfg.max_roll_rad, cfg.fingertip_clearance_m
        self.nominal_target_area_m2 = cfg.nominal_target_area_m2   # told when the target's size is not
        self.reset(cfg.nominal_target_area_m2)

    def reset(self, target_area_m2: float) -> None:
        """A new search, told the target's surface area (m^2), or the nominal cube's if not told its size."""
        self.volume.reset()
        self.target_area_m2 = target_area_m2
        self.views = 0
        self.views_above_claim = 0      # views in a row with the estimate above claim_share
        self._state_of = (None, None)   # (views, pose) -> state: an agent asking again costs nothing

    def camera_pose(self, T_world_tool: np.ndarray) -> np.ndarray:
        """T_world_depth, the depth camera's pose for a gripper pose, through the hand-eye calibration."""
        return T_world_tool @ self.rig.T_tool_depth

    def observe(self, depth_m: np.ndarray, T_world_depth: np.ndarray, detections: np.ndarray | None = None,
                rgb: np.ndarray | None = None) -> int:
        """Fuse one view: (H, W) depth in metres along z and the detector's scores in [0, 1] over the RGB image,
        or that (H', W', 3) image for our colour detector. A depth that is not a number in the camera's range
        (0, NaN, inf: how drivers mark no return) is no return. Returns the voxels seen first."""
        depth_m, detections = checked_view(self.rig, depth_m, T_world_depth, detections, rgb)
        rgb_outline = None
        if not self.rig.one_camera:   # the detections' outline in the RGB image travels with them, in one mapping
            both = self.rig.detections_in_depth_image(
                np.stack([detections, outline_of(detections > self.detection_threshold)], axis=-1), depth_m)
            detections, rgb_outline = np.ascontiguousarray(both[..., 0]), both[..., 1] > 0
        self.views += 1
        newly = self.volume.integrate(depth_m, detections, self.rig.depth.K, T_world_depth, rgb_outline)
        above = target_observed(self.perceived_target_share(), self.claim_share)
        self.views_above_claim = self.views_above_claim + 1 if above else 0
        return newly

    def state(self, T_world_tool: np.ndarray) -> np.ndarray:
        """The 71 values of Fig. 2 around a gripper pose; the detection part's factor is the perceived share of
        the told target's surface, on the simulated camera's scale (`state_share_scale`)."""
        key = (self.views, T_world_tool.tobytes())
        if self._state_of[0] != key:
            yaw, roll = yaw_roll_of(T_world_tool[:3, :3])
            self._state_of = (key, encode_state(self.volume, T_world_tool[:3, 3], yaw, roll, T_world_tool[2, 3],
                                                self.crop_m, self.perceived_target_share() * self.state_share_scale))
        return self._state_of[1].copy()

    def perceived_target_share(self) -> float:
        """Seen target area over the told target's, as the volume has it (the world's truth judges)."""
        return self.volume.seen_target_area_m2() / self.target_area_m2

    def target_found(self) -> bool:
        """The searchers' stop rule: the estimate above claim_margin x the paper's 20 % in confirm_views views
        in a row; the estimate spreads about +-25 % around the truth, so a claim at the bar is early as often."""
        return self.views_above_claim >= self.confirm_views

    def goal_pose(self, T_world_tool: np.ndarray, action: np.ndarray) -> np.ndarray:
        """The pose (T_world_tool) an action asks for: dx, dy, dz in the yaw frame times max_step_m, roll
        and yaw times max_turn_rad; roll bounded, the position inside the volume's box, fingertips above
        the floor."""
        yaw, roll = yaw_roll_of(T_world_tool[:3, :3])
        roll = float(np.clip(roll + action[3] * self.max_turn_rad, -self.max_roll_rad, self.max_roll_rad))
        yaw = float(yaw + action[4] * self.max_turn_rad)
        half = self.workspace_m / 2
        floor_z = self.fingertip_clearance_m + FINGER_REACH_M * abs(np.sin(roll))
        goal = np.eye(4)
        goal[:3, :3] = gripper_rotation(yaw, roll)
        step = rotation(yaw, "z") @ (np.asarray(action[:3]) * self.max_step_m)
        goal[:3, 3] = np.clip(T_world_tool[:3, 3] + step, [-half, -half, floor_z], [half, half, self.ceiling_m])
        return goal


# ================================================================================================
# Agents (Sec. IV-B): each decides from the robot's Searcher and the gripper's pose alone, with
# reset(searcher, T_world_tool) and act(searcher, T_world_tool) -> an action in Box(-1, 1, (6,)):
# dx, dy, dz, roll, yaw, and terminate when the sixth value is above 0. The two baselines here; the
# learned policies follow in the next section.
# ================================================================================================

ACTION_MOVES = 5        # dx, dy, dz, roll, yaw; then terminate
ACTION_SIZE = ACTION_MOVES + 1
ACTION_NAMES = ("dx", "dy", "dz", "roll", "yaw", "terminate")


def stop_action() -> np.ndarray:
    """The action that terminates: stay, and claim the target was found (or that there is none)."""
    action = np.zeros(ACTION_SIZE, np.float32)
    action[ACTION_MOVES] = 1.0
    return action


class GreedyNextBestView:
    """GNBV, the active baseline (Sec. IV-B.1): of n poses one action away, go to the one whose rays would
    newly observe the most voxels (unobserved space taken as empty) or, once the target is detected, the one
    that centres it. Stops above 97 % explored or 20 % of the target perceived."""

    def __init__(self, cfg: Settings, seed: int | None = None):
        self.rng = np.random.default_rng(seed)
        self.samples, self.rays, self.explored_to_stop = cfg.gnbv_samples, cfg.gnbv_rays, cfg.gnbv_explored_to_stop
        # The same volumes at any voxel size: detection voxels fill a band of fixed thickness (a count grows
        # as 1 / voxel^3), the voxels rays reach lie along the rays (1 / voxel).
        finer = cfg.state_voxel_m / cfg.voxel_m
        self.min_detections = int(round(cfg.gnbv_min_detections * finer ** 3))
        self.stall_voxels, self.stall_steps = int(round(cfg.gnbv_stall_voxels * finer)), cfg.gnbv_stall_steps
        # the workspace's floor and walls, which rays hit: the robot knows the box it searches
        self.wall_thickness_m, self.wall_height_m = cfg.wall_thickness_m, cfg.wall_height_m

    def reset(self, searcher: Searcher, T_world_tool: np.ndarray) -> None:
        self.stalled = 0
        camera = searcher.rig.depth
        K = camera.K
        u = (np.arange(self.rays[0]) + 0.5) * camera.width / self.rays[0]    # a subsampled image
        v = (np.arange(self.rays[1]) + 0.5) * camera.height / self.rays[1]
        uu, vv = np.meshgrid(u, v)
        rays = np.stack([(uu.ravel() - K[0, 2]) / K[0, 0], (vv.ravel() - K[1, 2]) / K[1, 1],
                         np.ones(uu.size)], 1)                                # (R, 3) at depth 1
        self.depths = np.arange(camera.near_m, camera.far_m, searcher.volume.voxel_m)   # one sample per voxel
        self.ray_directions = rays
        self.reached = np.zeros(searcher.volume.weight.size, bool)   # scratch: voxels one view would observe
        self.ray_points = (rays[:, None, :] * self.depths[None, :, None]).astype(np.float32)   # (R, D, 3)

    def samples_needed(self, T_world_camera: np.ndarray, box_half: float) -> int:
        """How many samples along the rays of a camera pose can matter: a ray hits nothing once it has left
        the square of the floor and walls, or gone below the floor (a straight ray never comes back)."""
        start = T_world_camera[:3, 3]
        direction = self.ray_directions @ T_world_camera[:3, :3].T   # a sample is start + depth * direction
        with np.errstate(divide="ignore", invalid="ignore"):
            side = np.where(direction[:, :2] == 0, np.inf,
                            (np.sign(direction[:, :2]) * box_half - start[:2]) / direction[:, :2])
            down = np.where(direction[:, 2] < 0, -start[2] / direction[:, 2], np.inf)
        leave = np.minimum(side.min(axis=1), down)
        return int(min(len(self.depths), np.searchsorted(self.depths, leave.max(), "right") + 2))

    def newly_observed(self, searcher: Searcher, T_cameras: np.ndarray, ee_xyz) -> np.ndarray:
        """For each (4, 4) camera pose, the unobserved voxels in the gripper's crop its rays would reach, counted
        once. A ray stops at an observed voxel behind a surface, the floor or a wall; one that hits nothing
        (over a wall) brings no depth and counts 0."""
        volume = searcher.volume
        observed = volume.weight.reshape(-1) > 0
        occupied = observed & (volume.tsdf.reshape(-1) < 0)
        counts = np.zeros(len(T_cameras), np.int64)
        shape = np.array(volume.shape)
        half, floor_half = searcher.workspace_m / 2, searcher.workspace_m / 2 + 2 * self.wall_thickness_m
        for c, T_world_camera in enumerate(T_cameras):
            samples = self.ray_points[:, :self.samples_needed(T_world_camera, floor_half)]   # the rest can hit nothing
            R_camera_world = T_world_camera[:3, :3].T.astype(np.float32)
            world = samples @ R_camera_world + T_world_camera[:3, 3].astype(np.float32)   # (rays, samples, 3)
            index = np.floor((world - volume.origin) / volume.voxel_m).astype(np.int64)
            inside = np.all((index >= 0) & (index < shape), axis=-1)
            inside &= np.all(np.abs(world[..., :2] - ee_xyz[:2]) <= searcher.crop_m / 2, axis=-1)
            flat = (index[..., 0] * shape[1] + index[..., 1]) * shape[2] + index[..., 2]
            flat = np.where(inside, flat, 0)
            out = np.abs(world[..., :2]).max(axis=-1)
            floor = (world[..., 2] < 0) & (out <= floor_half)
            wall = (out > half) & (out <= floor_half) & (world[..., 2] < self.wall_height_m)
            blocked = (inside & occupied[flat]) | floor | wall
            open_ray = ~np.logical_or.accumulate(blocked, axis=1)      # before the first blocker
            returns = blocked.any(axis=1)                              # (R,) the ray brings a depth
            new = flat[open_ray & inside & ~observed[flat] & returns[:, None]]
            self.reached[new] = True                                   # each voxel once, however many rays
            counts[c] = np.count_nonzero(self.reached)
            self.reached[new] = False
        return counts

    def centring_error(self, T_cameras: np.ndarray, target_xyz: np.ndarray, K: np.ndarray) -> np.ndarray:
        """Pixel distance of the target's projection from the image centre, per camera (inf if behind)."""
        errors = np.full(len(T_cameras), np.inf)
        for c, T_world_camera in enumerate(T_cameras):
            p = T_world_camera[:3, :3].T @ (target_xyz - T_world_camera[:3, 3])
            if p[2] > 1e-3:
                errors[c] = np.hypot(K[0, 0] * p[0] / p[2], K[1, 1] * p[1] / p[2])
        return errors

    def act(self, searcher: Searcher, T_world_tool: np.ndarray) -> np.ndarray:
        if (searcher.volume.explored_fraction() > self.explored_to_stop or self.stalled >= self.stall_steps
                or searcher.target_found()):
            return stop_action()
        actions = self.rng.uniform(-1, 1, (self.samples, ACTION_SIZE))   # n random poses one step away
        actions[:, ACTION_MOVES] = -1.0
        cameras = np.stack([searcher.camera_pose(searcher.goal_pose(T_world_tool, a)) for a in actions])
        volume = searcher.volume
        hits = np.argwhere(volume.detections > searcher.detection_threshold)   # the perceived target
        if len(hits) >= self.min_detections:   # a lone voxel is more likely noise than the target
            target = volume.origin + (hits.mean(axis=0) + 0.5) * volume.voxel_m
            best = int(np.argmin(self.centring_error(cameras, target, searcher.rig.depth.K)))
        else:
            gains = self.newly_observed(searcher, cameras, T_world_tool[:3, 3])
            best = int(np.argmax(gains))
            self.stalled = self.stalled + 1 if gains[best] < self.stall_voxels else 0
        return actions[best].astype(np.float32)


def two_opt(points: np.ndarray, tour: np.ndarray, closed: bool = True) -> np.ndarray:
    """Improve a tour by 2-opt moves (Croes 1958) until none shortens it; returns a new permutation. The
    gain of every move (reversing tour[i:j + 1]) comes at once as an (n, n) array; with closed=False the
    tour is a path whose first point stays first."""
    tour = np.array(tour)
    n = len(tour)
    while True:
        p = points[tour]
        nxt = np.roll(p, -1, axis=0)                    # d after c: wraps for a closed tour
        dist = lambda x, y: np.linalg.norm(x - y, axis=-1)
        a, b = p[:-1][:, None], p[1:][:, None]          # edge (a, b) = (tour[i-1], tour[i]), i = 1..n-1
        c, d = p[None, 1:], nxt[None, 1:]               # edge (c, d) = (tour[j], tour[j+1]), j = 1..n-1
        gain = dist(a, b) + dist(c, d) - dist(a, c) - dist(b, d)
        if not closed:
            gain[:, -1] = (dist(a, b) - dist(a, c))[:, -1]   # the path's end: no edge leaves it
        i, j = np.meshgrid(np.arange(1, n), np.arange(1, n), indexing="ij")
        gain[(j <= i) | ((i == 1) & (j == n - 1) & closed)] = 0.0
        best = np.unravel_index(np.argmax(gain), gain.shape)
        if gain[best] <= 1e-12:
            return tour
        i, j = best[0] + 1, best[1] + 1
        tour[i:j + 1] = tour[i:j + 1][::-1].copy()


class GridExhaustiveSearch:
    """GES, the interactive baseline (Sec. IV-B.2): sweep a grid of nodes one step apart just above the
    lowest layer of objects, pushing what lies on top, along a nearest-neighbour route improved by 2-opt.
    Stops above 20 % of the target perceived, or at the grid's end claiming there is no target."""

    node_tol_m = 0.01   # a node counts as reached within this distance

    def __init__(self, cfg: Settings, seed: int | None = None):
        self.height_m = cfg.object_size_m + cfg.ges_clearance_m     # fingertips just above the lowest cubes
        self.tries_per_node = cfg.ges_tries_per_node

    def reset(self, searcher: Searcher, T_world_tool: np.ndarray) -> None:
        spacing, width = searcher.max_step_m, searcher.workspace_m
        n = int(round(width / spacing))
        axis = (np.arange(n) + 0.5) * spacing - width / 2
        self.nodes = np.stack(np.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
        start = T_world_tool[:2, 3]
        tour = self.nearest_neighbour(self.nodes, int(np.argmin(np.linalg.norm(self.nodes - start, axis=1))))
        self.route = two_opt(self.nodes, tour, closed=False)
        self.next, self.tries = 0, 0

    @staticmethod
    def nearest_neighbour(points: np.ndarray, start: int) -> np.ndarray:
        tour, left = [start], np.ones(len(points), bool)
        left[start] = False
        while left.any():
            d = np.where(left, np.linalg.norm(points - points[tour[-1]], axis=1), np.inf)
            tour.append(int(np.argmin(d)))
            left[tour[-1]] = False
        return np.array(tour)

    def act(self, searcher: Searcher, T_world_tool: np.ndarray) -> np.ndarray:
        yaw, roll = yaw_roll_of(T_world_tool[:3, :3])
        while self.next < len(self.route):            # skip the nodes reached or given up
            offset = np.r_[self.nodes[self.route[self.next]], self.height_m] - T_world_tool[:3, 3]
            if np.linalg.norm(offset[:2]) > self.node_tol_m and self.tries < self.tries_per_node:
                break
            self.next, self.tries = self.next + 1, 0
        if searcher.target_found() or self.next >= len(self.route):
            return stop_action()
        self.tries += abs(offset[2]) < self.node_tol_m           # only count tries at the sweep height
        step = rotation(yaw, "z").T @ offset / searcher.max_step_m
        action = np.zeros(ACTION_SIZE, np.float32)
        action[:3] = np.clip(step, -1, 1)
        action[3] = np.clip(-roll / searcher.max_turn_rad, -1, 1)
        action[ACTION_MOVES] = -1.0
        return action


# ================================================================================================
# The policy (Sec. III-B.4): A3DE and I3DE, an actor-critic MLP on the 71 values, as an agent.
# ================================================================================================

class ActorCritic(nn.Module):
    """Actor and critic MLPs (2 x 200, tanh): the means of a Gaussian over the five displacements (state-
    independent std) and the logit of a Bernoulli "terminate". Inputs are standardised by a running mean
    and variance kept in buffers: the 71 values span 1e-3 (a far bin) to 1 (the roll)."""

    moves = ACTION_MOVES

    def __init__(self, obs_dim: int, ppo: PPOSettings):
        super().__init__()
        self.obs_clip = ppo.obs_clip
        self.register_buffer("obs_mean", torch.zeros(obs_dim))
        self.register_buffer("obs_var", torch.ones(obs_dim))
        self.register_buffer("obs_count", torch.tensor(0.0))
        def mlp(out: int) -> nn.Sequential:
            return nn.Sequential(nn.Linear(obs_dim, ppo.hidden), nn.Tanh(), nn.Linear(ppo.hidden, ppo.hidden),
                                 nn.Tanh(), nn.Linear(ppo.hidden, out))
        self.actor, self.critic = mlp(self.moves + 1), mlp(1)
        self.log_std = nn.Parameter(torch.full((self.moves,), ppo.init_log_std))
        with torch.no_grad():   # small initial means; a rarely terminating start
            self.actor[-1].weight.mul_(0.01)
            self.actor[-1].bias.zero_()
            self.actor[-1].bias[-1] = torch.logit(torch.tensor(ppo.init_terminate_prob))

    @torch.no_grad()
    def reset_terminate(self, prob: float) -> None:
        """Make the terminate head say `prob` in every state, forgetting when to stop; moves are kept."""
        self.actor[-1].weight[-1].zero_()
        self.actor[-1].bias[-1] = torch.logit(torch.tensor(prob))

    def sound(self) -> bool:
        """Every weight and statistic finite, the std positive and finite: a policy that can still be sampled."""
        std = self.log_std.exp()
        finite = all(torch.isfinite(t).all() for t in self.state_dict().values())
        return bool(finite and ((std > 0) & torch.isfinite(std)).all())

    def normalise(self, obs: torch.Tensor) -> torch.Tensor:
        return ((obs - self.obs_mean) / (self.obs_var + 1e-8).sqrt()).clamp(-self.obs_clip, self.obs_clip)

    @torch.no_grad()
    def update_obs_stats(self, obs: torch.Tensor) -> None:
        """Merge a batch's mean and variance into the running ones (the parallel formula of Chan,
        Golub and LeVeque 1979)."""
        n, mean, var = len(obs), obs.mean(0), obs.var(0, unbiased=False)
        total = self.obs_count + n
        delta = mean - self.obs_mean
        self.obs_var.copy_((self.obs_var * self.obs_count + var * n + delta ** 2 * self.obs_count * n / total) / total)
        self.obs_mean.add_(delta * n / total)
        self.obs_count.copy_(total)

    def actor_output(self, obs: torch.Tensor) -> torch.Tensor:
        """(N, 6): the Gaussian's five means, then the terminate logit."""
        return self.actor(self.normalise(obs))

    def distributions(self, obs: torch.Tensor):
        out = self.actor_output(obs)
        return (torch.distributions.Normal(out[:, :self.moves], self.log_std.exp()),
                torch.distributions.Bernoulli(logits=out[:, self.moves]))

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.critic(self.normalise(obs))[:, 0]

    def log_prob(self, move, stop, raw: torch.Tensor) -> torch.Tensor:
        """Log-probability of raw actions (5 displacements, terminate bit) under the policy's distributions."""
        return move.log_prob(raw[:, :self.moves]).sum(1) + stop.log_prob(raw[:, self.moves])

    def evaluate(self, obs: torch.Tensor, raw: torch.Tensor):
        """Log-probability and entropy of raw actions under the policy."""
        move, stop = self.distributions(obs)
        return self.log_prob(move, stop, raw), move.entropy().sum(1) + stop.entropy()


def env_actions(raw: np.ndarray) -> np.ndarray:
    """Raw policy samples -> the env's Box: displacements clipped to [-1, 1], terminate as +-1."""
    moves, stop = np.clip(raw[:, :ACTION_MOVES], -1, 1), np.where(raw[:, ACTION_MOVES:] > 0.5, 1.0, -1.0)
    return np.concatenate([moves, stop], 1).astype(np.float32)


class PPOAgent:
    """A trained policy as an agent for eval and demo: the Gaussian's mean, terminate when p > 0.5."""

    def __init__(self, checkpoint: dict):
        self.model = ActorCritic(checkpoint["obs_dim"], PPOSettings(**checkpoint["settings"]))
        self.model.load_state_dict(checkpoint["model"])
        self.model.eval()

    def reset(self, searcher: Searcher, T_world_tool: np.ndarray) -> None:
        pass

    def act(self, searcher: Searcher, T_world_tool: np.ndarray) -> np.ndarray:
        return self.decide(searcher.state(T_world_tool))

    def decide(self, obs: np.ndarray) -> np.ndarray:
        """The action for a (71,) state: the Gaussian's mean, terminate when its probability is above 0.5."""
        with torch.no_grad():
            out = self.model.actor_output(torch.as_tensor(obs, dtype=torch.float32)[None]).numpy()
        out[:, -1] = out[:, -1] > 0.0   # p > 0.5
        return env_actions(out)[0]


# ================================================================================================
# On an arm (Sec. III-D): the loop a position-controlled arm runs. Each wrist frame (depth, colour or
# detections, poses from the arm's kinematics and the hand-eye calibration) goes to the searcher; the
# agent's displacement comes back as the next gripper pose in the robot's base frame, checked (the
# harness's Input section) so that no bad frame moves the arm. tools/replay.py runs recorded frames through it.
# ================================================================================================

class ArmSearch:
    """One search on an arm. The workspace box (the volume's frame: floor centre, z up) sits at
    T_base_workspace in the robot's base frame; every pose in and out is in the base frame."""

    def __init__(self, searcher: Searcher, agent, T_base_workspace: np.ndarray | None = None,
                 target_area_m2: float | None = None):
        self.searcher, self.agent = searcher, agent
        self.T_base_workspace = None if T_base_workspace is None else checked_pose(T_base_workspace, "T_base_workspace")
        self.T_workspace_base = None if T_base_workspace is None else np.linalg.inv(self.T_base_workspace)
        if target_area_m2 is not None and not (isinstance(target_area_m2, (int, float)) and 0 < target_area_m2 < 1):
            raise ValueError(f"target_area_m2={target_area_m2!r}: a target's surface in m^2 is in (0, 1)")
        searcher.reset(searcher.nominal_target_area_m2 if target_area_m2 is None else float(target_area_m2))
        self.frames = 0

    def in_workspace(self, T_base: np.ndarray) -> np.ndarray:
        return T_base if self.T_workspace_base is None else self.T_workspace_base @ T_base

    def step(self, depth_m: np.ndarray, T_base_tool: np.ndarray, rgb: np.ndarray | None = None,
             detections: np.ndarray | None = None, T_base_depth: np.ndarray | None = None) -> tuple:
        """Fuse one frame (depth in metres; the RGB image or its detection scores) taken with the gripper at
        T_base_tool, and decide: (the action, the next T_base_tool, or None when the agent stops). The depth
        camera's pose defaults to the gripper's through the rig's hand-eye calibration. The goal is finite, in
        the box and at most one step away (`checked_goal`), or a ValueError says what was wrong."""
        T_tool = checked_tool_pose(self.searcher, self.in_workspace(checked_pose(T_base_tool, "T_base_tool")))
        T_depth = (self.searcher.camera_pose(T_tool) if T_base_depth is None
                   else self.in_workspace(checked_pose(T_base_depth, "T_base_depth")))
        self.searcher.observe(depth_m, T_depth, detections=detections, rgb=rgb)
        if self.frames == 0:
            self.agent.reset(self.searcher, T_tool)
        self.frames += 1
        action = checked_action(self.agent.act(self.searcher, T_tool))
        if action[ACTION_MOVES] > 0:
            return action, None
        if outside_box_m(self.searcher, T_tool) > 0:   # outside by at most a step: back to the nearest pose in the box
            action[:3] = 0.0
        T_goal = checked_goal(self.searcher, T_tool, self.searcher.goal_pose(T_tool, action))
        return action, T_goal if self.T_base_workspace is None else self.T_base_workspace @ T_goal


# ================================================================================================
# The world I (Sec. III-B.2, III-C): what the simulator adds to the robot's side. A pybullet world, the
# wrist view rendered by TinyRenderer, the detector's noise, and the gripper painted into an outside view.
# ================================================================================================

class PhysicsClient(BulletClient):
    """One headless pybullet world: pybullet's BulletClient, which passes its client id to every call
    (`sim.stepSimulation()`) and disconnects when garbage collected. Connected without an options
    string, since with one, even empty, pybullet prints "argv[0]=" on every connect."""

    def __init__(self):
        self._shapes, self._pid = {}, os.getpid()
        self._client = pb.connect(pb.DIRECT)

    def clear(self) -> None:
        """An empty world (pybullet's resetSimulation frees every shape, so the shapes made are forgotten)."""
        self.resetSimulation()
        self._shapes.clear()

    def shapes(self, key, make) -> tuple:
        """(collision, visual) shape ids for `key`, made by make() once per world and shared by its bodies."""
        if key not in self._shapes:
            self._shapes[key] = make()
        return self._shapes[key]

    def __getattr__(self, name):
        """BulletClient's bound call, kept: later calls (thousands per step in physics) skip the lookup."""
        bound = super().__getattr__(name)
        if name != "disconnect":   # BulletClient marks the client closed when disconnect is looked up
            setattr(self, name, bound)
        return bound


def quat_of(R: np.ndarray) -> list:
    """pybullet quaternion (x, y, z, w) of a rotation matrix."""
    w = np.sqrt(max(1e-12, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    if w > 1e-3:
        return [(R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w),
                (R[1, 0] - R[0, 1]) / (4 * w), w]
    i = int(np.argmax(np.diag(R)))
    j, k = (i + 1) % 3, (i + 2) % 3
    q = np.zeros(4)
    q[i] = np.sqrt(max(1e-12, 1 + R[i, i] - R[j, j] - R[k, k])) / 2
    q[j] = (R[j, i] + R[i, j]) / (4 * q[i])
    q[k] = (R[k, i] + R[i, k]) / (4 * q[i])
    q[3] = (R[k, j] - R[j, k]) / (4 * q[i])
    return list(q)


_box_lo = np.min([np.subtract(c, h) for h, c in GRIPPER_BOXES], 0)
_box_hi = np.max([np.add(c, h) for h, c in GRIPPER_BOXES], 0)
GRIPPER_CORNERS = np.round([[x, y, z] for x in (_box_lo[0], _box_hi[0]) for y in (_box_lo[1], _box_hi[1])
                            for z in (_box_lo[2], _box_hi[2])], 9)   # (8, 3) corners of the boxes' bounding box


def render_rgbd(sim, T_world_camera: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """TinyRenderer RGB (H, W, 3) uint8 and depth (H, W) metres along z, 0 where nothing was hit."""
    width, height, near_m, far_m = camera.width, camera.height, camera.near_m, camera.far_m
    T_gl = T_world_camera @ np.diag([1.0, -1.0, -1.0, 1.0])   # OpenGL cameras look down -z, y up
    view = np.linalg.inv(T_gl).T.reshape(-1)                  # pybullet wants column-major
    fov_y = np.degrees(2 * np.arctan(height / 2 / camera.K[1, 1]))
    proj = pb.computeProjectionMatrixFOV(fov_y, width / height, near_m, far_m)
    _, _, rgba, zbuf, _ = sim.getCameraImage(width, height, view, proj, renderer=pb.ER_TINY_RENDERER,
                                            flags=pb.ER_NO_SEGMENTATION_MASK, shadow=0)
    rgb = np.asarray(rgba, np.uint8).reshape(height, width, 4)[:, :, :3]
    zbuf = np.asarray(zbuf, np.float32).reshape(height, width)
    depth = far_m * near_m / (far_m - (far_m - near_m) * zbuf)
    depth[zbuf >= 1.0] = 0.0
    return np.ascontiguousarray(rgb), depth.astype(np.float32)


FLOOR_RGBA, WALL_RGBA = (0.78, 0.76, 0.72, 1), (0.55, 0.6, 0.68, 1)
FLOOR_RGB8 = np.array([186, 181, 171], np.uint8)   # FLOOR_RGBA as TinyRenderer shades a plane facing up, from any view


def floor_half_m(cfg: Settings) -> float:
    """Half the floor's side: the workspace and the walls standing on it."""
    return cfg.workspace_m / 2 + 2 * cfg.wall_thickness_m


def draw_floor(rgb: np.ndarray, depth_m: np.ndarray, T_world_camera: np.ndarray, camera: Camera,
               half_m: float) -> None:
    """Draw the floor (z = 0, |x|, |y| <= half_m) into the pixels a render left empty, in place. It has no
    visual shape: TinyRenderer would shade it in one colour at the cost of half a wrist view, where a ray
    meeting a plane is one division per pixel."""
    v, u = np.nonzero(depth_m == 0)
    K, R, origin = camera.K, T_world_camera[:3, :3], T_world_camera[:3, 3]
    ray = R @ np.stack([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], np.ones(len(u))])
    with np.errstate(divide="ignore"):
        z = -origin[2] / ray[2]   # the depth at which each pixel's ray (world direction per metre) meets z = 0
    x, y = origin[0] + z * ray[0], origin[1] + z * ray[1]
    floor = (z > camera.near_m) & (z < camera.far_m) & (np.abs(x) <= half_m) & (np.abs(y) <= half_m)
    hit = v[floor], u[floor]
    depth_m[hit], rgb[hit] = z[floor], FLOOR_RGB8


def add_detector_noise(detections: np.ndarray, rng: np.random.Generator, cfg: Settings) -> np.ndarray:
    """Sec. III-C: true detections lose an Exp(lambda) sample; a random 2 % of pixels become false
    positives valued Exp(lambda)."""
    noisy = detections - detections * rng.exponential(1.0 / cfg.noise_rate, detections.shape)
    n_false = int(round(cfg.false_positive_share * detections.size))
    flat = noisy.reshape(-1)
    picks = rng.choice(detections.size, n_false, replace=False)
    flat[picks] = np.maximum(flat[picks], rng.exponential(1.0 / cfg.noise_rate, n_false))
    return np.clip(noisy, 0.0, 1.0).astype(np.float32)


def time_of_flight(depth_m: np.ndarray, rng: np.random.Generator, cfg: Settings) -> np.ndarray:
    """A time-of-flight camera's errors on a rendered (H, W) depth image, 0 where nothing returned: pixels
    on a depth edge straddle both surfaces and return a mix of the two depths (flying pixels), or are
    dropped by the camera's filter; noise grows with distance; some pixels return nothing; nothing closer
    than the minimum range returns. With every setting 0 it is the image itself, and draws nothing."""
    out = depth_m
    if cfg.tof_edge_jump_m > 0:
        padded = np.pad(depth_m, 1, mode="edge")
        neighbours = np.stack([padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]])
        jump = np.where(neighbours > 0, neighbours - depth_m, 0.0)                # (4, H, W)
        widest = np.take_along_axis(jump, np.abs(jump).argmax(0)[None], 0)[0]    # towards the other surface
        edge = (depth_m > 0) & (np.abs(widest) > cfg.tof_edge_jump_m)
        share = rng.uniform(0.0, 0.5, int(edge.sum()))   # of the pixel's footprint on the other surface
        dropped = rng.random(len(share)) < cfg.tof_edge_drop_share
        out = depth_m.copy()
        out[edge] = np.where(dropped, 0.0, depth_m[edge] + share * widest[edge])
    if cfg.tof_noise_ratio > 0:
        out = out + (rng.standard_normal(out.shape) * cfg.tof_noise_ratio * out).astype(np.float32)
    if cfg.tof_missing_share > 0:
        out = np.where(rng.random(out.shape) < cfg.tof_missing_share, 0.0, out).astype(np.float32)
    if cfg.depth_min_range_m > 0:
        out = np.where(out < cfg.depth_min_range_m, 0.0, out).astype(np.float32)
    return out


def episode_sensing(cfg: Settings, rng: np.random.Generator) -> Settings:
    """The sensor errors of one episode: cfg's, or with sensor_error_scale a range, each error times a factor
    drawn from it (domain randomisation); (1, 1) is cfg itself, and draws nothing."""
    if cfg.sensor_error_scale == (1.0, 1.0):
        return cfg
    factor = rng.uniform(*cfg.sensor_error_scale)
    return dataclasses.replace(cfg, **{name: getattr(cfg, name) * factor for name in cfg.scaled_sensor_errors})


def mounted_rig(believed: Rig, rng: np.random.Generator, cfg: Settings) -> Rig:
    """The rig as it truly sits on the gripper: the robot's calibration off by hand_eye_error_m and
    hand_eye_error_rad in random directions (a fixed error for an episode). No error: the same rig, no draws."""
    if cfg.hand_eye_error_m == 0 and cfg.hand_eye_error_rad == 0:
        return believed
    axis, direction = rng.standard_normal(3), rng.standard_normal(3)
    error = np.eye(4)
    error[:3, :3] = axis_angle_rotation(axis / np.linalg.norm(axis), cfg.hand_eye_error_rad)
    error[:3, 3] = cfg.hand_eye_error_m * direction / np.linalg.norm(direction)
    return dataclasses.replace(believed, T_tool_depth=believed.T_tool_depth @ error)


# A box's 8 corners, indexed x * 4 + y * 2 + z over the signs (-, +), and its 6 faces as corner cycles
# whose normal (second - first) x (fourth - first) points outward; box_mesh and the demo's gripper share them.
BOX_SIGNS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
BOX_FACES = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])



# ================================================================================================
# The world II (Sec. III-C, Table I): scenes. Object meshes (a model renders decimated and collides as
# one hull; its full mesh is the truth), the five scene kinds, piles, and the target's ground-truth
# surface (the points that decide "seen"; never shown to an agent).
# ================================================================================================

def box_mesh(half) -> tuple[np.ndarray, np.ndarray]:
    """A box's corners and outward triangles, from the box tables above (each quad split in two)."""
    return BOX_SIGNS * np.asarray(half, float), BOX_FACES[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3)


def prism_mesh(side: float, length: float) -> tuple[np.ndarray, np.ndarray]:
    """Triangular prism lying on a rectangular face, centred at its bounding box centre."""
    h = side * np.sqrt(3) / 2
    tri = np.array([[-side / 2, 0.0], [side / 2, 0.0], [0.0, h]]) - [0, h / 2]
    v = np.array([[x, -length / 2, z] for x, z in tri] + [[x, length / 2, z] for x, z in tri])
    f = np.array([[0, 1, 2], [3, 5, 4], [0, 3, 4], [0, 4, 1], [1, 4, 5], [1, 5, 2], [2, 5, 3], [2, 3, 0]])
    return v, f


def cylinder_mesh(radius: float, height: float, segments: int = 16) -> tuple[np.ndarray, np.ndarray]:
    a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], 1)
    v = np.concatenate([np.c_[ring, np.full(segments, -height / 2)],
                        np.c_[ring, np.full(segments, height / 2)],
                        [[0, 0, -height / 2], [0, 0, height / 2]]])
    i = np.arange(segments)
    j = (i + 1) % segments
    f = np.concatenate([np.stack([i, j, segments + j], 1), np.stack([i, segments + j, segments + i], 1),
                        np.stack([np.full(segments, 2 * segments), j, i], 1),
                        np.stack([np.full(segments, 2 * segments + 1), segments + i, segments + j], 1)])
    return v, f


def mesh_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Surface area of a triangle mesh (m^2)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return 0.5 * float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator):
    """(n, 3) points uniformly on a triangle mesh (triangles drawn by area) and their (n, 3) unit normals,
    turned away from the centroid since OBJ files do not all wind their faces the same way."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    cross = np.cross(b - a, c - a)
    area = np.linalg.norm(cross, axis=1)
    tri = rng.choice(len(faces), n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random((n, 1))), rng.random((n, 1))
    points = (1 - r1) * a[tri] + r1 * (1 - r2) * b[tri] + r1 * r2 * c[tri]
    normals = cross[tri] / area[tri, None]
    outward = np.sign(np.sum(normals * ((a + b + c)[tri] / 3 - vertices.mean(0)), axis=1))
    return points, normals * np.where(outward == 0, 1.0, outward)[:, None]


@functools.lru_cache(maxsize=None)
def urdf_mesh(urdf_path: str) -> tuple[np.ndarray, np.ndarray]:
    """Visual mesh of a one-link URDF in its link frame (scale and origin applied), parsed from the OBJ."""
    text = Path(urdf_path).read_text()
    visual = text[text.index("<visual"):]
    mesh = re.search(r'<mesh\s+filename="([^"]+)"(?:\s+scale="([^"]+)")?', visual)
    origin = visual[:visual.index("<geometry")]
    xyz, rpy = re.search(r'xyz="([^"]+)"', origin), re.search(r'rpy="([^"]+)"', origin)
    scale = np.array([float(x) for x in mesh.group(2).split()]) if mesh.group(2) else np.ones(3)
    offset = np.array([float(x) for x in xyz.group(1).split()]) if xyz else np.zeros(3)
    roll, pitch, yaw = (float(x) for x in rpy.group(1).split()) if rpy else (0.0, 0.0, 0.0)
    R = rotation(yaw, "z") @ rotation(pitch, "y") @ rotation(roll, "x")       # URDF: fixed-axis roll, pitch, yaw
    vertices, faces = [], []
    for line in (Path(urdf_path).parent / mesh.group(1)).read_text().splitlines():
        if line.startswith("v "):
            vertices.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            idx = [int(tok.split("/")[0]) - 1 for tok in line.split()[1:]]
            faces += [[idx[0], idx[i], idx[i + 1]] for i in range(1, len(idx) - 1)]   # fan triangulation
    return (np.array(vertices) * scale) @ R.T + offset, np.array(faces)


def decimate(vertices: np.ndarray, faces: np.ndarray, cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering (Rossignac and Borrel 1993): one vertex, the mean, per cell of a cells^3 grid over
    the mesh's extent; triangles that collapse, and repeats, dropped. TinyRenderer's cost grows with triangles."""
    cell_m = (vertices.max(0) - vertices.min(0)).max() / cells
    _, cluster, counts = np.unique(np.floor((vertices - vertices.min(0)) / cell_m).astype(np.int64), axis=0,
                                   return_inverse=True, return_counts=True)
    cluster = cluster.reshape(-1)
    merged = np.zeros((len(counts), 3))
    np.add.at(merged, cluster, vertices)
    f = cluster[faces]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    return merged / counts[:, None], f[np.sort(first)]


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    height, turn = 1 - 2 * k / n, np.pi * (1 + 5 ** 0.5) * k
    ring = np.sqrt(1 - height ** 2)
    return np.stack([ring * np.cos(turn), ring * np.sin(turn), height], 1)


@dataclass(frozen=True)
class MeshModel:
    """A mesh model as the world uses it, in the body frame of pybullet's loadURDF (the inertial frame)."""
    vertices: np.ndarray          # (V, 3) the full visual mesh: its extent places the object
    faces: np.ndarray             # (F, 3)
    render_vertices: np.ndarray   # decimated: what the wrist camera renders and the ground truth judges
    render_faces: np.ndarray
    hull: np.ndarray              # (<= HULL_DIRECTIONS, 3) extreme vertices: the object collides as their hull
    rests: tuple                  # 3 x 3 rotations (body to world) in which it lies still on a floor


RENDER_CELLS = 6        # a rendered model keeps a vertex per cell of a 6^3 grid: 9 mm on a 5.5 cm model
HULL_DIRECTIONS = 64    # an object collides as the convex hull of its furthest vertices along 64 directions
REST_DIRECTIONS = 1000  # "down" directions tried for the orientations a model rests in ...
REST_NEIGHBOURHOOD = np.cos(np.radians(15))   # ... each lower than every other within 15 degrees ...
MAX_RESTS = 4           # ... the lowest few


@functools.cache
def rest_directions() -> tuple[np.ndarray, np.ndarray]:
    """The "down" directions tried for resting orientations, and which of them are neighbours."""
    down = fibonacci_directions(REST_DIRECTIONS)
    return down, down @ down.T > REST_NEIGHBOURHOOD


def rest_rotations(hull: np.ndarray) -> tuple:
    """Rotations (body to world, 3 x 3) in which a convex body rests on a floor: the local minima over "down"
    directions d of the centre of mass's height, max over the hull of p . d (the body origin is its centre of
    mass). A body is stable where a tilt either way would raise it."""
    down, near = rest_directions()
    height = (hull @ down.T).max(0)
    minima = [i for i in np.argsort(height) if height[i] <= height[near[i]].min()][:MAX_RESTS]
    rests = []
    for d in down[minima]:   # the rotation taking d onto -z (Rodrigues), about the axis d x -z
        axis, cos = np.cross(d, [0.0, 0.0, -1.0]), -d[2]
        skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        rests.append(np.eye(3) + skew + skew @ skew / (1 + cos) if cos > -1 + 1e-9 else np.diag([1.0, -1.0, -1.0]))
    return tuple(rests)


@functools.lru_cache(maxsize=None)
def mesh_model(urdf_path: str, scale: float) -> MeshModel:
    """What the world needs of a mesh model, built once per process: a scene then makes its bodies from
    arrays instead of loading the URDF, renders a decimated copy and collides one convex hull (a compound
    of convex pieces costs several times more per physics step), and places it in a pose it rests in."""
    vertices, faces = urdf_mesh(urdf_path)
    inertial = re.search(r"<inertial>.*?<origin[^>]*xyz=\"([^\"]+)\"", Path(urdf_path).read_text(), re.DOTALL)
    vertices = (vertices - (np.array(inertial.group(1).split(), float) if inertial else 0)) * scale   # loadURDF's frame
    directions = np.concatenate([np.eye(3), -np.eye(3), fibonacci_directions(HULL_DIRECTIONS - 6)])   # spans the box
    hull = vertices[np.unique(np.argmax(vertices @ directions.T, axis=0))]
    return MeshModel(vertices, faces, *decimate(vertices, faces, RENDER_CELLS), hull, rest_rotations(hull))


@functools.lru_cache(maxsize=None)
def exterior_surface(urdf_path: str, scale: float, min_cos: float, candidates: int = 8000, views: int = 40,
                     pixels: int = 128):
    """Points on the surface the wrist camera renders of a mesh model (its decimated mesh) that can be seen
    from outside, their normals, and that part's area; cached. Buried faces of overlapping convex pieces (the
    teddy) are dropped, a hollow inside (the mug's) kept: a point stays if one of `views` renders of the
    model alone sees it unoccluded and less obliquely than min_cos, the ground truth's own limit. Its normal
    faces the view that saw it most squarely: a grazing view can pass the depth test from behind."""
    model = mesh_model(urdf_path, scale)
    vertices, faces = model.render_vertices, model.render_faces
    sim = PhysicsClient()
    try:
        sim.createMultiBody(0, -1, sim.createVisualShape(pb.GEOM_MESH, vertices=vertices.tolist(),
                                                         indices=faces.reshape(-1).tolist()))   # world = body frame
        points, normals = sample_surface(vertices, faces, candidates, np.random.default_rng(0))
        radius = float(np.linalg.norm(vertices, axis=1).max())
        distance = 4 * radius
        K = np.array([[pixels * distance / (2.4 * radius), 0, pixels / 2],
                      [0, pixels * distance / (2.4 * radius), pixels / 2], [0, 0, 1]])
        footprint = 2.4 * radius / pixels
        squarest = np.zeros(len(points))              # signed cosine of the squarest view that saw it
        for d in fibonacci_directions(views):
            z_axis = -d
            x_axis = np.cross(z_axis, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
            x_axis /= np.linalg.norm(x_axis)
            T_world_camera = np.eye(4)
            T_world_camera[:3, :3] = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis], 1)
            T_world_camera[:3, 3] = d * distance
            camera = Camera(pixels, pixels, K, distance - 2 * radius, distance + 2 * radius)
            _, depth = render_rgbd(sim, T_world_camera, camera)
            cam = (points - T_world_camera[:3, 3]) @ T_world_camera[:3, :3]
            u = np.clip((K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2]).astype(int), 0, pixels - 1)
            v = np.clip((K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]).astype(int), 0, pixels - 1)
            cos = normals @ d                           # d points from the model to the camera
            slack = footprint / np.maximum(np.abs(cos), min_cos) + 0.01 * radius
            visible = (np.abs(depth[v, u] - cam[:, 2]) < slack) & (np.abs(cos) > np.maximum(min_cos, np.abs(squarest)))
            squarest[visible] = cos[visible]
    finally:
        sim.disconnect()
    keep = squarest != 0
    return points[keep], normals[keep] * np.sign(squarest[keep, None]), mesh_area(vertices, faces) * keep.mean()


# The scene's colours: the target red, everything else clearly not, under any shading (`detect_target`).
TARGET_RGBA = (0.85, 0.05, 0.05, 1.0)
OTHER_RGBA = (
    (0.10, 0.30, 0.90, 1), (0.15, 0.65, 0.20, 1), (0.90, 0.85, 0.20, 1), (0.55, 0.55, 0.55, 1),
    (0.20, 0.70, 0.80, 1), (0.92, 0.92, 0.92, 1), (0.35, 0.35, 0.40, 1), (0.45, 0.25, 0.75, 1),
)

# pybullet_data's household-like meshes with the global scaling that brings each near 5-8 cm
OBJECT_MODELS = (("duck_vhacd.urdf", 0.6), ("teddy_vhacd.urdf", 0.6), ("objects/mug.urdf", 0.5),
                 ("lego/lego.urdf", 1.8), ("jenga/jenga.urdf", 0.5), ("soccerball.urdf", 0.055))


# pybullet_data/random_urdfs/000 .. 999, the paper's footnote set, less 168 (its OBJ holds only NaN vertices)
# and the slivers: thinner than MIN_SHAPE_WIDTH_M every way, such a target is edge-on in most views, a pixel
# or two wide to a camera at 30 cm, and the share seen is a guess to the robot and to the ground truth alike
MIN_SHAPE_WIDTH_M = 0.01
THIN_SHAPES = (110, 167, 178, 232, 292, 295, 297, 304, 350, 357, 479, 507, 578, 602, 824, 933)   # (a test)
RANDOM_SHAPES = tuple(i for i in range(1000) if i != 168 and i not in THIN_SHAPES)

RANDOM_SHAPE_SCALE = 0.5      # about 5-6 cm across


@dataclass
class SceneObject:
    shapes: tuple          # (collision, visual) pybullet shape ids, shared by the objects of one kind and size
    rgba: tuple
    vertices: np.ndarray   # (V, 3) mesh in the body's frame (pybullet's base = centre-of-mass frame)
    faces: np.ndarray      # (F, 3)
    radius_m: float        # of the footprint, for placing objects apart
    half_height_m: float   # lowest vertex below the body origin when resting
    rest: np.ndarray       # 3 x 3 rotation in which it rests (before a yaw about the vertical)
    model: tuple | None = None   # (URDF path, scale) of a mesh model; None for a convex primitive
    body: int = -1               # its pybullet body, once add_bodies has made it


PRIMITIVE_KINDS = ("cube", "cuboid", "cylinder", "prism")   # cubes-and-cuboids draws from the first two


@functools.lru_cache(maxsize=64)
def primitive(kind: str, h: float) -> tuple:
    """(vertices, faces, collision shape, visual shape, footprint radius, half height) of a primitive about 2 h
    across, resting on a face; made once per kind and size (cube scenes reuse one)."""
    if kind in ("cube", "cuboid"):
        half = [h, h, h] if kind == "cube" else [1.5 * h, 0.75 * h, 0.75 * h]
        (v, f), col = box_mesh(half), dict(shapeType=pb.GEOM_BOX, halfExtents=half)
        vis = dict(col)
    elif kind == "cylinder":
        (v, f) = cylinder_mesh(h, 2 * h)
        col = dict(shapeType=pb.GEOM_CYLINDER, radius=h, height=2 * h)
        vis = dict(shapeType=pb.GEOM_CYLINDER, radius=h, length=2 * h)
    else:
        v, f = prism_mesh(2.2 * h, 2 * h)
        col = dict(shapeType=pb.GEOM_MESH, vertices=v.tolist())
        vis = dict(shapeType=pb.GEOM_MESH, vertices=v.tolist(), indices=f.reshape(-1).tolist())
    v.flags.writeable = f.flags.writeable = False   # shared by every object of this kind and size
    return v, f, col, vis, float(np.linalg.norm(v[:, :2], axis=1).max()), float(-v[:, 2].min())


def make_object(sim, scene: str, cfg: Settings, rng: np.random.Generator, rgba) -> SceneObject:
    """One object of a scene kind (primitives about object_size_m across): its shapes and mesh; add_bodies
    then makes its body."""
    kind = "cube" if scene == "cubes" else None
    if scene in ("fixed-primitives", "variable-primitives"):
        kind = PRIMITIVE_KINDS[rng.integers(4)]
    elif scene == "cubes-and-cuboids":
        kind = PRIMITIVE_KINDS[rng.integers(2)]
    if kind is not None:
        scale = rng.uniform(*cfg.variable_scale) if scene == "variable-primitives" else 1.0
        h = cfg.object_size_m * scale / 2
        v, f, col, vis, radius_m, half_height_m = primitive(kind, h)
        shapes = sim.shapes((kind, h), lambda: (sim.createCollisionShape(**col), sim.createVisualShape(**vis)))
        return SceneObject(shapes, rgba, v, f, radius_m, half_height_m, np.eye(3))
    data = pybullet_data.getDataPath()
    if scene == "random-shapes":
        i = RANDOM_SHAPES[rng.integers(len(RANDOM_SHAPES))]
        model = os.path.join(data, "random_urdfs", f"{i:03d}", f"{i:03d}.urdf"), RANDOM_SHAPE_SCALE
    else:
        name, scale = OBJECT_MODELS[rng.integers(len(OBJECT_MODELS))]
        model = os.path.join(data, name), scale
    mesh = mesh_model(*model)
    shapes = sim.shapes(model, lambda: (
        sim.createCollisionShape(pb.GEOM_MESH, vertices=mesh.hull.tolist()),
        sim.createVisualShape(pb.GEOM_MESH, vertices=mesh.render_vertices.tolist(),
                              indices=mesh.render_faces.reshape(-1).tolist())))
    v, f, rest = mesh.vertices, mesh.faces, mesh.rests[rng.integers(len(mesh.rests))]
    resting = v @ rest.T
    return SceneObject(shapes, rgba, v, f, float(np.linalg.norm(resting[:, :2], axis=1).max()),
                       float(-resting[:, 2].min()), rest, model)


def add_bodies(sim, objects: list, cfg: Settings) -> None:
    """Each object's body at the origin, to be placed, made in the objects' order (Bullet's body ids order its
    contacts). Objects in a row that share shapes are made in one batched call: pybullet's client fetches a new
    body's info after each call (about 0.1 ms), after a batch only the last body's (so getNumBodies counts
    short; nothing here reads it)."""
    for shapes, run in itertools.groupby(objects, key=lambda o: o.shapes):
        run = list(run)
        bodies = sim.createMultiBody(cfg.object_mass_kg, *shapes, useMaximalCoordinates=True,
                                     batchPositions=[[0.0, 0.0, 0.0]] * len(run))
        for obj, body in zip(run, bodies):
            obj.body = body
            sim.changeVisualShape(body, -1, rgbaColor=obj.rgba)
            # Objects may sleep: a resting pile then costs nothing per physics step until something touches it.
            sim.changeDynamics(body, -1, lateralFriction=cfg.object_friction,
                               activationState=pb.ACTIVATION_STATE_ENABLE_SLEEPING)
            if obj.model is not None:
                sim.changeDynamics(body, -1, rollingFriction=cfg.model_rolling_friction_m)


GRIPPER_PARKED_M = (0.0, 0.0, 1.0)   # the gripper waits here, above the walls, while a scene settles


def build_workspace(sim, cfg: Settings) -> tuple[int, int]:
    """Floor, four walls and the gripper on its constraint; returns the (gripper, constraint) ids. The floor
    has no visual shape (draw_floor draws it). The gripper's only visual is a transparent speck (TinyRenderer
    would draw its collision shapes into the wrist view), a box: TinyRenderer tessellates a sphere anew in
    every world (0.3 ms). The outside view paints the gripper in."""
    half, thick, wall_z = cfg.workspace_m / 2, cfg.wall_thickness_m, cfg.wall_height_m / 2
    floor_half = floor_half_m(cfg)
    boxes = ([([floor_half] * 2 + [thick], [0, 0, -thick])]   # (half extents, centre): the floor, then walls
             + [([thick, floor_half, wall_z], [sx * (half + thick), 0, wall_z]) for sx in (-1, 1)]
             + [([half, thick, wall_z], [0, sy * (half + thick), wall_z]) for sy in (-1, 1)])
    halves, centres = [b[0] for b in boxes], [b[1] for b in boxes]
    # One static body of five boxes, not five bodies: pybullet's client fetches each new body's info (~0.1 ms).
    room = sim.createMultiBody(0, sim.createCollisionShapeArray([pb.GEOM_BOX] * len(boxes), halfExtents=halves,
                                                                collisionFramePositions=centres),
                               sim.createVisualShapeArray([pb.GEOM_BOX] * (len(boxes) - 1), halfExtents=halves[1:],
                                                          visualFramePositions=centres[1:]))
    for i in range(len(boxes) - 1):
        sim.changeVisualShape(room, -1, shapeIndex=i, rgbaColor=WALL_RGBA)
    halves, centres = [b[0] for b in GRIPPER_BOXES], [b[1] for b in GRIPPER_BOXES]
    col = sim.createCollisionShapeArray([pb.GEOM_BOX] * 3, halfExtents=halves, collisionFramePositions=centres)
    speck = sim.createVisualShape(pb.GEOM_BOX, halfExtents=[1e-4] * 3, visualFramePosition=GRIPPER_BOXES[0][1],
                                 rgbaColor=(0, 0, 0, 0))
    gripper = sim.createMultiBody(cfg.gripper_mass_kg, col, speck, GRIPPER_PARKED_M)
    sim.changeDynamics(gripper, -1, activationState=pb.ACTIVATION_STATE_DISABLE_SLEEPING)
    constraint = sim.createConstraint(gripper, -1, -1, -1, pb.JOINT_FIXED, [0, 0, 0], [0, 0, 0], GRIPPER_PARKED_M)
    sim.changeConstraint(constraint, maxForce=cfg.gripper_force_n)
    return gripper, constraint


def object_count(cfg: Settings, scene: str, rng: np.random.Generator) -> tuple[int, bool]:
    """Number of objects (Table I) and whether they are heaped into piles (all but exploration_ratio of
    the interactive task's scenes); primitive and shape piles are denser (Table II's caption)."""
    heaped = cfg.num_piles > 0 and rng.random() >= cfg.exploration_ratio
    if heaped and scene in ("fixed-primitives", "variable-primitives", "random-shapes"):
        lo, hi = cfg.objects_per_pile_dense
        return int(rng.integers(lo * cfg.num_piles, hi * cfg.num_piles + 1)), True
    return int(rng.integers(cfg.min_objects, cfg.max_objects + 1)), heaped


def scatter_positions(objects: list, cfg: Settings, rng: np.random.Generator) -> list:
    """(xyz, yaw) poses apart from each other, by rejection, resting on the floor; an object with no room
    is dropped from above onto whatever lies below."""
    half, radius_m = cfg.workspace_m / 2, np.array([obj.radius_m for obj in objects])
    # Each object's tries (x, y pairs), then its yaw, drawn at once: rng.uniform's draws, one by one.
    draws = rng.random((len(objects), 2 * cfg.scatter_tries + 1))
    low, high = (-half + radius_m)[:, None, None], (half - radius_m)[:, None, None]
    tries = low + (high - low) * draws[:, :-1].reshape(len(objects), cfg.scatter_tries, 2)
    yaws = -np.pi + 2 * np.pi * draws[:, -1]
    placed_xy, poses = np.zeros((len(objects), 2)), []
    for n, obj in enumerate(objects):
        d = tries[n, :, None] - placed_xy[:n]   # (tries, n, 2) from each try to each object placed
        clearance = radius_m[n] + radius_m[:n] + cfg.scatter_gap_m
        free = np.flatnonzero(np.all(np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]) > clearance, axis=1))
        if len(free):
            xy, z = tries[n, free[0]], obj.half_height_m
        else:
            xy, z = tries[n, -1], obj.half_height_m + cfg.no_room_drop_m
        placed_xy[n] = xy
        poses.append((np.array([xy[0], xy[1], z]), yaws[n]))
    return poses


def pile_positions(objects: list, cfg: Settings, rng: np.random.Generator) -> list:
    """(xyz, yaw) drop poses on square pyramids of spots over num_piles random centres, filled in order of
    ring plus pile_layer_cost per layer, so piles grow up and out from the bottom centre; the first object
    (the target, when there is one) takes the bottom centre of the first pile."""
    half = cfg.workspace_m / 2
    centres = []
    while len(centres) < cfg.num_piles:
        margin_m = cfg.pile_margin_ratio * cfg.workspace_m
        c = rng.uniform(-half + margin_m, half - margin_m, 2)
        apart = all(np.linalg.norm(c - q) > cfg.pile_min_apart_ratio * cfg.workspace_m for q in centres)
        if apart or rng.random() < cfg.pile_overlap_chance:
            centres.append(c)
    share = np.array_split(np.arange(len(objects)), cfg.num_piles)
    poses = [None] * len(objects)
    n = cfg.pile_layers
    for centre, members in zip(centres, share):
        spacing = 2 * max(objects[i].radius_m for i in members) * cfg.pile_spacing_ratio
        step_z = 2 * max(objects[i].half_height_m for i in members) + cfg.pile_layer_gap_m
        spots = [(ring + cfg.pile_layer_cost * layer + cfg.pile_spot_noise * rng.random(), (x, y, layer))
                 for layer in range(n) for x in np.arange(n - layer) - (n - 1 - layer) / 2
                 for y in np.arange(n - layer) - (n - 1 - layer) / 2 for ring in [max(abs(x), abs(y))]]
        spots.sort(key=lambda t: t[0])
        for i, (_, (x, y, layer)) in zip(members, spots):
            jitter = rng.normal(0, cfg.pile_jitter_ratio * spacing, 2)
            z = objects[i].half_height_m + cfg.drop_gap_m + layer * step_z
            xyz = np.append(centre + spacing * np.array([x, y]) + jitter, z)
            poses[i] = (xyz, rng.uniform(-np.pi, np.pi))
    return poses


SETTLE_CHECK_S = 1 / 30   # simulated time between checks that everything is at rest (a check costs a few steps)


def put_to_sleep(sim, objects: list) -> None:
    """Send resting objects to sleep: a resting scene then costs nothing per physics step until touched."""
    for o in objects:
        sim.changeDynamics(o.body, -1, activationState=pb.ACTIVATION_STATE_SLEEP)


def settle(sim, objects: list, cfg: Settings, max_s: float) -> bool:
    """Step physics at settle_hz for at most max_s until every object is slower than settle_speed, then put
    them all to sleep; False if still moving. pybullet only lets bodies sleep after 2 s at rest; sending them
    to sleep at once keeps later physics steps cheap (a resting pile then costs nothing until touched)."""
    every = max(1, round(SETTLE_CHECK_S * cfg.settle_hz))
    sim.setPhysicsEngineParameter(fixedTimeStep=1.0 / cfg.settle_hz)
    try:
        for step in range(round(max_s * cfg.settle_hz)):
            sim.stepSimulation()
            if step % every == every - 1:
                speeds = [sum(c * c for c in sim.getBaseVelocity(o.body)[0]) for o in objects]
                if max(speeds, default=0.0) < cfg.settle_speed ** 2:
                    put_to_sleep(sim, objects)
                    return True
        return False
    finally:
        sim.setPhysicsEngineParameter(fixedTimeStep=1.0 / cfg.physics_hz)


def target_surface(target: SceneObject, cfg: Settings, rng: np.random.Generator):
    """Ground truth of "seen": surface_points points on the target in its own frame (so they follow it
    when pushed), their outward normals, and the target's visible surface area (m^2)."""
    if target.model is None:     # a convex primitive: all of its surface can be seen
        points, normals = sample_surface(target.vertices, target.faces, cfg.surface_points, rng)
        return points, normals, mesh_area(target.vertices, target.faces)
    points, normals, area = exterior_surface(*target.model, cfg.seen_min_cos)
    pick = rng.choice(len(points), cfg.surface_points, replace=False)
    return points[pick], normals[pick], area


@dataclass
class Scene:
    objects: list               # SceneObject, the target first when there is one
    target_present: bool
    heaped: bool                # objects dropped into piles
    target_points: np.ndarray   # (surface_points, 3) ground-truth points in the target's frame; (0, 3) if absent
    target_normals: np.ndarray  # (surface_points, 3) their outward unit normals
    target_area_m2: float       # the target's visible surface (the nominal cube's when absent)


def build_scene(sim, cfg: Settings, scene: str, rng: np.random.Generator) -> Scene:
    """Draw one scene of a kind into a world holding only the workspace: objects, their resting poses
    (scattered, or heaped with the target at the bottom of a pile), and the target's ground truth."""
    count, heaped = object_count(cfg, scene, rng)
    target_present = bool(rng.random() >= cfg.no_target_prob)
    objects = []
    for i in range(count):
        rgba = TARGET_RGBA if i == 0 and target_present else OTHER_RGBA[rng.integers(len(OTHER_RGBA))]
        objects.append(make_object(sim, scene, cfg, rng, rgba))
    add_bodies(sim, objects, cfg)
    poses = (pile_positions if heaped else scatter_positions)(objects, cfg, rng)
    for obj, (xyz, yaw) in zip(objects, poses):
        sim.resetBasePositionAndOrientation(obj.body, xyz, quat_of(rotation(yaw, "z") @ obj.rest))
    # Primitives that all found room rest on the floor as placed (a face down); meshes, drops and piles settle.
    if not heaped and all(o.model is None and xyz[2] == o.half_height_m for o, (xyz, _) in zip(objects, poses)):
        put_to_sleep(sim, objects)
    else:
        settle(sim, objects, cfg, cfg.settle_pile_s if heaped else cfg.settle_scatter_s)
    if target_present:
        points, normals, area = target_surface(objects[0], cfg, rng)
    else:
        points = normals = np.zeros((0, 3))
        area = cfg.nominal_target_area_m2
    return Scene(objects, target_present, heaped, points, normals, area)


# ================================================================================================
# The world III (Sec. III-B.3, III-C): the object finding task as a Gymnasium environment. The world
# simulates the gripper, the scene, the wrist view and the detector's noise, judges "seen" by the
# ground truth and pays the rewards; the robot's side is one Searcher.
# ================================================================================================

SWEEP_MARGIN_M = 0.005  # the box swept by one move, grown by this before asking what it touches
REACH_CHECK_S = 1 / 60   # simulated time between checks of the gripper's progress towards an action's pose


@dataclass(frozen=True, eq=False)
class WristView:
    """One view of the wrist rig as the world made it: what the searcher was fed, and the colour image."""

    rgb: np.ndarray              # (H', W', 3) uint8, the RGB camera's image
    depth_m: np.ndarray          # (H, W) metres along z, 0 where nothing returned, as the depth camera gave it
    detections: np.ndarray       # (H', W') the simulated detector's scores in [0, 1] over the RGB image
    T_world_camera: np.ndarray   # (4, 4) the depth camera's pose as the robot believes it (hand-eye calibration)


class ObjectFindingEnv(gym.Env):
    """The object finding task as a Gymnasium environment (Sec. III-B, III-C): the world, and the robot's
    Searcher it feeds. Actions and states are the Searcher's (`goal_pose`, `state`); `info` holds
    target_present, target_seen_fraction, target_observed, explored_fraction, and success at the end."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, task: str = "ap", scene: str = "cubes", seed: int | None = None,
                 render_mode: str | None = None, **overrides):
        for name, value, known in (("task", task, TASKS), ("scene", scene, SCENES),
                                   ("render_mode", render_mode, (None, "rgb_array"))):
            if value not in known:
                raise ValueError(f"unknown {name} {value!r}; choose from {', '.join(map(str, known))}")
        self.task, self.scene, self.render_mode = task, scene, render_mode
        self.cfg = checked_settings(task, overrides)   # e.g. target_size_known=False, for ablations
        self._seed = seed
        self.action_space = gym.spaces.Box(-1.0, 1.0, (ACTION_SIZE,), np.float32)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (STATE_SIZE,), np.float32)
        self.searcher = Searcher(self.cfg)
        self.true_rig = self.searcher.rig   # the cameras as mounted; reset() adds the episode's hand-eye error
        self.sensings = [(self.cfg, self.searcher)]   # the sensing an episode may draw (rig_camera_share)
        if self.cfg.rig_camera_share > 0:
            rig_cfg = dataclasses.replace(self.cfg, **RIG_SENSING)
            self.sensings.append((rig_cfg, Searcher(rig_cfg)))
        self.sim = PhysicsClient()
        self.objects = []
        self.view: WristView | None = None

    # --- one step: the data flow of Fig. 2 ------------------------------------------------------

    def step(self, action):
        """Sec. III-B's step: the searcher turns the action into a pose; the world moves the gripper there,
        pushing, renders, detects and judges; the searcher fuses the view and encodes the state."""
        self.check_open()
        if getattr(self, "episode_over", True):
            raise RuntimeError("step() needs reset() first: " + ("the episode has ended" if hasattr(self, "steps")
                                                                 else "no episode has started"))
        action = checked_action(action)   # nothing of the env changes before the action passed
        self.steps += 1
        reward = -self.cfg.time_penalty
        if action[ACTION_MOVES] > 0:   # terminate: claim the target was found, or that there is none
            info = self._info()
            success = info["target_observed"] if self.target_present else True
            reward += self.cfg.detection_reward if success else -self.cfg.detection_reward
            info.update(success=success, terminated_by_agent=True)
            self.episode_over = True
            return self.searcher.state(self.gripper_pose()), reward, True, False, info
        T_world_tool = self.gripper_pose()
        T_goal = self.searcher.goal_pose(T_world_tool, action)          # robot: the action as a pose
        self._drive_gripper(T_world_tool, T_goal)                       # world: physics, pushing
        newly = self._observe()                                         # world: view -> robot: fuse
        explored_share = newly / self.searcher.volume.tsdf.size         # reward for what was new
        reward += self.cfg.time_penalty * min(1.0, explored_share / self.cfg.exploration_normaliser)
        state, info = self.searcher.state(self.gripper_pose()), self._info()   # robot: encode
        # The horizon is part of the task (a finite-horizon MDP with a failure penalty), so reaching it
        # terminates the episode rather than truncating it.
        if self.steps >= self.cfg.horizon:
            reward -= self.cfg.detection_reward
            info.update(success=False, terminated_by_agent=False)
            self.episode_over = True
            return state, reward, True, False, info
        return state, reward, False, False, info

    def _observe(self) -> int:
        """The wrist view: render from where the cameras truly are, detect with the paper's noise, judge
        "seen" by the ground truth, add the depth camera's errors, and feed the searcher, which places the
        view by its own calibration; returns the voxels it observed for the first time."""
        T_world_tool = self.gripper_pose()
        T_world_depth = T_world_tool @ self.true_rig.T_tool_depth
        rgb, views = self._render(T_world_depth)
        detections = self._detect(rgb)
        self._judge_seen(views)
        depth_m = time_of_flight(views[0][2], self.np_random, self.sensing)
        T_believed = self.searcher.camera_pose(T_world_tool)
        self.view = WristView(rgb, depth_m, detections, T_believed)
        return self.searcher.observe(depth_m, T_believed, detections=detections)

    def _render_world(self, T_world_camera: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """The world as a camera sees it: TinyRenderer's image, with the floor (no visual shape) drawn in."""
        rgb, depth_m = render_rgbd(self.sim, T_world_camera, camera)
        draw_floor(rgb, depth_m, T_world_camera, camera, floor_half_m(self.cfg))
        return rgb, depth_m

    def _render(self, T_world_depth: np.ndarray) -> tuple[np.ndarray, list]:
        """The RGB image and each camera's view, (T_world_camera, camera, ideal depth), the depth camera's first: one
        render per camera, with the renderer's near plane (what lies closer than the sensor's minimum range must
        still hide what is behind it)."""
        cameras = [(T_world_depth, self.true_rig.depth)]
        if not self.true_rig.one_camera:
            cameras.append((T_world_depth @ self.true_rig.T_depth_rgb, self.true_rig.rgb))
        views = []
        for T_world_camera, camera in cameras:   # the last camera rendered is the RGB camera
            rgb, depth_m = self._render_world(T_world_camera, dataclasses.replace(camera, near_m=self.cfg.near_m))
            views.append((T_world_camera, camera, depth_m))
        return rgb, views

    def _detect(self, rgb: np.ndarray) -> np.ndarray:
        """The simulated detector of Sec. III-C: the colour detector's truth with the paper's noise."""
        return add_detector_noise(detect_target(rgb), self.np_random, self.cfg)

    def _judge_seen(self, views: list) -> None:
        """Ground truth: surface points every camera of the robot sees (`_render`'s views): each point faces the
        camera, projects into its image beyond its minimum range, and is unoccluded."""
        if not self.target_present:
            return
        pos, orn = self.sim.getBasePositionAndOrientation(self.objects[0].body)
        R = np.array(pb.getMatrixFromQuaternion(orn)).reshape(3, 3)
        world, normals = self.target_points @ R.T + pos, self.target_normals @ R.T
        self.target_seen |= np.logical_and.reduce([self._visible(world, normals, T_world_camera, camera, depth_m)
                                                   for T_world_camera, camera, depth_m in views])

    def _visible(self, world, normals, T_world_camera: np.ndarray, camera: Camera, depth_m: np.ndarray) -> np.ndarray:
        """Which (n, 3) world points with their normals a camera sees in its ideal depth image."""
        to_camera = T_world_camera[:3, 3] - world
        facing = np.sum(normals * to_camera, axis=1) > self.cfg.seen_min_cos * vector_norm(to_camera)
        cam = (world - T_world_camera[:3, 3]) @ T_world_camera[:3, :3]     # R^T (p - t), row-wise
        z = cam[:, 2]
        safe = np.where(z > 1e-6, z, 1.0)
        u = np.floor(camera.K[0, 0] * cam[:, 0] / safe + camera.K[0, 2]).astype(int)
        v = np.floor(camera.K[1, 1] * cam[:, 1] / safe + camera.K[1, 2]).astype(int)
        H, W = depth_m.shape
        inside = (z > camera.near_m) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        rendered = depth_m[np.clip(v, 0, H - 1), np.clip(u, 0, W - 1)]
        unoccluded = (rendered == 0) | (rendered > z - self.cfg.seen_depth_tol_m)   # nothing in front of it
        return facing & inside & unoccluded

    def _info(self) -> dict:
        seen = float(self.target_seen.mean()) if self.target_present else 0.0
        return dict(target_present=self.target_present, target_seen_fraction=seen,
                    target_observed=target_observed(seen, self.cfg.seen_threshold),
                    explored_fraction=self.searcher.volume.explored_fraction(), steps=self.steps)

    # --- a new scene -----------------------------------------------------------------------------

    def check_open(self) -> None:
        if self.sim is None:
            raise RuntimeError("this ObjectFindingEnv is closed: make a new one")

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self.check_open()
        if seed is None and self._seed is not None:
            seed, self._seed = self._seed, None
        super().reset(seed=seed)
        rng = self.np_random
        self._build_scene(rng)
        self._place_gripper(rng)
        if len(self.sensings) > 1:
            cfg, self.searcher = self.sensings[int(rng.random() < self.cfg.rig_camera_share)]
        else:
            cfg = self.cfg
        self.sensing = episode_sensing(cfg, rng)   # the sensor errors this episode's world applies
        self.true_rig = mounted_rig(self.searcher.rig, rng, self.sensing)
        # the information rule: what the searcher is told of the target's size (the nominal cube's if absent)
        self.searcher.reset(self.target_area_m2 if self.cfg.target_size_known else self.cfg.nominal_target_area_m2)
        self.steps, self.episode_over = 0, False
        self._observe()
        return self.searcher.state(self.gripper_pose()), self._info()

    def _build_scene(self, rng) -> None:
        """A new world: the workspace (floor, walls, the gripper on its constraint), then a drawn scene. Every
        scene gets a world of its own: Bullet's broadphase keeps state across bodies removed and added (its
        pair cache, a cursor of the pairs it checks each step), and a world kept from the last episode would
        order contacts differently, so an episode would depend on the episodes played before it."""
        cfg, sim = self.cfg, self.sim
        sim.clear()
        sim.setGravity(0, 0, -9.81)
        sim.setPhysicsEngineParameter(fixedTimeStep=1.0 / cfg.physics_hz, erp=cfg.gripper_erp,
                                      numSolverIterations=cfg.solver_iterations, deterministicOverlappingPairs=1)
        self.gripper, self.constraint = build_workspace(sim, cfg)
        scene = build_scene(sim, cfg, self.scene, rng)
        self.objects, self.target_present, self.heaped = scene.objects, scene.target_present, scene.heaped
        self.target_points, self.target_normals = scene.target_points, scene.target_normals
        self.target_area_m2 = scene.target_area_m2
        self.target_seen = np.zeros(len(self.target_points), bool)   # (surface_points,) ever seen
        self.disturbed = False   # objects still moving after the last push

    def _place_gripper(self, rng) -> None:
        """Random x, y, height and yaw, roll 0; resampled while it would overlap an object."""
        cfg, sim = self.cfg, self.sim
        half = cfg.workspace_m / 2 - cfg.gripper_start_margin_m
        for attempt in range(cfg.gripper_start_tries):
            xyz = np.r_[rng.uniform(-half, half, 2), rng.uniform(cfg.gripper_start_min_z_m, cfg.ceiling_m)]
            if attempt == cfg.gripper_start_tries - 1:   # the last try: above everything
                xyz[2] = cfg.ceiling_m
            yaw = rng.uniform(-np.pi, np.pi)
            self._teleport(xyz, gripper_rotation(yaw, 0.0))
            sim.performCollisionDetection()
            if not sim.getContactPoints(self.gripper):
                break

    # --- the gripper ----------------------------------------------------------------------------

    def gripper_pose(self) -> np.ndarray:
        """T_world_tool (4 x 4) of the gripper body as simulated: what the arm reports."""
        pos, orn = self.sim.getBasePositionAndOrientation(self.gripper)
        T_world_tool = np.eye(4)
        T_world_tool[:3, :3] = np.array(pb.getMatrixFromQuaternion(orn)).reshape(3, 3)
        T_world_tool[:3, 3] = pos
        return T_world_tool

    def _teleport(self, xyz, R) -> None:
        q = quat_of(R)
        self.sim.resetBasePositionAndOrientation(self.gripper, xyz, q)
        self.sim.resetBaseVelocity(self.gripper, [0, 0, 0], [0, 0, 0])
        self.sim.changeConstraint(self.constraint, xyz, q, maxForce=self.cfg.gripper_force_n)

    def _drive_gripper(self, T_world_tool: np.ndarray, T_goal: np.ndarray) -> None:
        """Drive the gripper to a goal pose. When the box it sweeps touches no other body and nothing still
        moves, the bounded constraint would get there unhindered: the gripper is placed there, no physics step
        spent. Otherwise the constraint pulls it with bounded force until it arrives or stalls, then objects settle."""
        cfg, sim = self.cfg, self.sim
        goal, R_goal = T_goal[:3, 3], T_goal[:3, :3]
        lo, hi = sim.getAABB(self.gripper)
        corners = GRIPPER_CORNERS @ R_goal.T + goal
        lo = np.minimum(lo, corners.min(0)) - SWEEP_MARGIN_M
        hi = np.maximum(hi, corners.max(0)) + SWEEP_MARGIN_M
        near = sim.getOverlappingObjects(lo.tolist(), hi.tolist()) or []
        if not self.disturbed and all(body == self.gripper for body, _ in near):
            self._teleport(goal, R_goal)
            return
        q_goal = quat_of(R_goal)
        sim.changeConstraint(self.constraint, goal.tolist(), q_goal, maxForce=cfg.gripper_force_n)
        last = T_world_tool[:3, 3]
        every = max(1, round(REACH_CHECK_S * cfg.physics_hz))
        for substep in range(1, round(cfg.move_limit_s * cfg.physics_hz) + 1):
            sim.stepSimulation()
            if substep % every == 0:
                pos, orn = sim.getBasePositionAndOrientation(self.gripper)
                pos = np.array(pos)
                angle = 2 * np.arccos(min(1.0, abs(float(np.dot(orn, q_goal)))))
                reached = np.linalg.norm(pos - goal) < cfg.reach_tol_m and angle < cfg.reach_tol_rad
                stalled = np.linalg.norm(pos - last) < cfg.stall_m        # blocked by a wall or a heavy pile
                if reached or stalled:
                    break
                last = pos
        self.disturbed = not settle(sim, self.objects, cfg, cfg.settle_s)

    # --- pictures ---------------------------------------------------------------------------------

    def render(self):
        return outside_view(self) if self.render_mode == "rgb_array" else None   # the demo's picture

    def __reduce__(self):
        raise TypeError("an ObjectFindingEnv holds a live physics world and cannot be copied or pickled; make "
                        "another with the same task, scene, settings and seed")

    def close(self):
        if getattr(self, "sim", None) is not None:
            self.sim.disconnect()
            self.sim = None


# gym.make("objfind/ActivePerception-v0", scene="cubes"): the three Table I presets as Gymnasium ids.
GYM_IDS = {"objfind/ActivePerception-v0": "ap", "objfind/ActivePerceptionLarge-v0": "ap-large",
           "objfind/InteractivePerception-v0": "ip", "objfind/ActivePerceptionReal-v0": "ap-real",
           "objfind/InteractivePerceptionReal-v0": "ip-real"}
for _id, _task in GYM_IDS.items():
    if _id not in gym.registry:
        gym.register(id=_id, entry_point="objfind:ObjectFindingEnv", kwargs=dict(task=_task))


# ================================================================================================
# Learning (Sec. III-B.4, IV-A): a hand-written PPO for the A3DE and I3DE policies.
# ================================================================================================

def gae(rewards, values, dones, last_value, gamma: float, lam: float):
    """Generalised advantage estimation (Schulman et al. 2016, eq. 16) over (T, W) arrays, dones[t] ending
    the episode at t: A_t = delta_t + gamma lam A_{t+1}, delta_t = r_t + gamma V(s_{t+1}) - V(s_t), computed
    backwards; the critic's targets are A_t + V(s_t)."""
    steps = len(rewards)
    advantages = np.zeros_like(rewards)
    running = np.zeros_like(last_value)
    for t in reversed(range(steps)):   # a loop over time steps, not data: T x W arrays at once
        next_value = last_value if t == steps - 1 else values[t + 1]
        not_done = 1.0 - dones[t]
        delta = rewards[t] + gamma * next_value * not_done - values[t]
        running = delta + gamma * lam * not_done * running
        advantages[t] = running
    return advantages, advantages + values


def clipped_surrogate_loss(ratio: torch.Tensor, advantages: torch.Tensor, clip: float) -> torch.Tensor:
    """-L^CLIP (Schulman et al. 2017, eq. 7): a gain cut off outside [1 - clip, 1 + clip], a loss never."""
    return -torch.min(ratio * advantages, ratio.clamp(1 - clip, 1 + clip) * advantages).mean()


def ppo_update(model: ActorCritic, optimizer, batch: dict, ppo: PPOSettings, generator) -> dict:
    """One PPO update (Schulman et al. 2017, eq. 7 and 9): epochs over shuffled minibatches of the clipped
    surrogate, a value loss and an entropy bonus, advantages standardised per batch; the log's statistics."""
    n = len(batch["obs"])
    adv = batch["advantages"]
    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    stats = dict(policy_loss=[], value_loss=[], entropy=[], approx_kl=[], clip_fraction=[])
    for _ in range(ppo.epochs):
        order = torch.randperm(n, generator=generator)
        for start in range(0, n, ppo.minibatch):
            i = order[start:start + ppo.minibatch]
            logp, entropy = model.evaluate(batch["obs"][i], batch["raw"][i])
            log_ratio = logp - batch["logp"][i]
            ratio = log_ratio.exp()
            policy_loss = clipped_surrogate_loss(ratio, adv[i], ppo.clip)
            value_loss = 0.5 * (model.value(batch["obs"][i]) - batch["returns"][i]).pow(2).mean()
            loss = policy_loss + ppo.value_coef * value_loss - ppo.entropy_coef * entropy.mean()
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(model.parameters(), ppo.max_grad_norm)
            optimizer.step()
            if not (torch.isfinite(loss) and model.sound()):
                raise FloatingPointError("a non-finite loss, weight or std")   # train stops, keeping the last update
            with torch.no_grad():
                stats["policy_loss"].append(policy_loss.item())
                stats["value_loss"].append(value_loss.item())
                stats["entropy"].append(entropy.mean().item())
                # KL(old || new) estimated as E[(r - 1) - log r], unbiased and never negative (the "k3"
                # estimator of J. Schulman, "Approximating KL Divergence", 2020)
                stats["approx_kl"].append(((ratio - 1) - log_ratio).mean().item())
                stats["clip_fraction"].append(((ratio - 1).abs() > ppo.clip).float().mean().item())
    return {k: float(np.mean(v)) for k, v in stats.items()}


def collect_rollout(env, model: ActorCritic, steps: int, env_seed: int, sample_seed: int) -> dict:
    """`steps` steps of one env from a reset seeded by `env_seed`, actions sampled with `sample_seed`, so
    an update depends on the weights, the optimizer and its index alone: (T,) arrays and the episodes."""
    generator = torch.Generator().manual_seed(sample_seed)
    obs, _ = env.reset(seed=env_seed)
    out = {k: [] for k in ("obs", "raw", "logp", "values", "rewards", "dones")}
    episodes, ret, length = [], 0.0, 0
    for _ in range(steps):
        obs_t = torch.as_tensor(obs, dtype=torch.float32)[None]
        with torch.no_grad():
            move, stop = model.distributions(obs_t)
            raw = torch.cat([move.mean + move.stddev * torch.randn(move.mean.shape, generator=generator),
                             torch.bernoulli(stop.probs, generator=generator)[:, None]], 1)
            logp = model.log_prob(move, stop, raw)   # the distributions just sampled: one forward pass
            value = model.value(obs_t)
        next_obs, reward, terminated, truncated, info = env.step(env_actions(raw.numpy())[0])
        for k, v in (("obs", obs), ("raw", raw[0].numpy()), ("logp", logp.item()), ("values", value.item()),
                     ("rewards", reward), ("dones", float(terminated or truncated))):
            out[k].append(v)
        ret, length = ret + reward, length + 1
        if terminated or truncated:
            episodes.append(dict(ret=ret, length=length, success=bool(info["success"])))
            (next_obs, _), ret, length = env.reset(), 0.0, 0     # the env's own seeded generator goes on
        obs = next_obs
    with torch.no_grad():
        last_value = model.value(torch.as_tensor(obs, dtype=torch.float32)[None]).item()
    batch = {k: np.array(v, np.float32) for k, v in out.items()}
    return dict(batch, last_value=last_value, episodes=episodes)


def derived_seed(*key: int) -> int:
    """A 32-bit seed for (run seed, update, stream, purpose): distinct streams, reproducible."""
    return int(np.random.SeedSequence(list(key)).generate_state(1)[0])


def scheduled(ppo: PPOSettings, optimizer, done_share: float) -> PPOSettings:
    """The settings of an update `done_share` of the way through a run: the entropy bonus, Adam's learning rate
    and the discount held until schedule_start_share, then moved linearly to their *_end_ratio shares, reached at
    schedule_share."""
    start, end = ppo.schedule_start_share, ppo.schedule_share
    done_share = min(1.0, max(0.0, done_share - start) / (end - start))
    ramp = lambda value, end_ratio: value * (1 + (end_ratio - 1) * done_share)   # noqa: E731
    for group in optimizer.param_groups:
        group["lr"] = ramp(ppo.learning_rate, ppo.learning_rate_end_ratio)
    return dataclasses.replace(ppo, entropy_coef=ramp(ppo.entropy_coef, ppo.entropy_end_ratio),
                               gamma=ramp(ppo.gamma, ppo.gamma_end_ratio))


def ppo_iteration(model: ActorCritic, optimizer, ppo: PPOSettings, collect, seed: int, update: int) -> tuple:
    """One PPO iteration, as CleanRL lays it out: collect, advantages, update, statistics. `collect(weights,
    update)` gives one `collect_rollout` per stream; returns the log's row and the finished episodes."""
    # 1. collect with the current weights, time-major: (T, streams, ...)
    parts = collect(model.state_dict(), update)
    episodes = [e for part in parts for e in part["episodes"]]
    batch = {k: np.stack([part[k] for part in parts], axis=1)
             for k in ("obs", "raw", "logp", "values", "rewards", "dones")}
    last_value = np.array([part["last_value"] for part in parts], np.float32)
    # 2. advantages and the critic's targets
    advantages, returns = gae(batch["rewards"] * ppo.reward_scale, batch["values"], batch["dones"], last_value,
                              ppo.gamma, ppo.gae_lambda)
    n = advantages.size
    flat = dict(obs=torch.as_tensor(batch["obs"].reshape(n, -1)), raw=torch.as_tensor(batch["raw"].reshape(n, -1)),
                logp=torch.as_tensor(batch["logp"].reshape(n)), advantages=torch.as_tensor(advantages.reshape(n)),
                returns=torch.as_tensor(returns.reshape(n)))
    # 3. the update, then the observation statistics (the update's ratios need the rollout's scale)
    stats = ppo_update(model, optimizer, flat, ppo, torch.Generator().manual_seed(derived_seed(seed, update)))
    model.update_obs_stats(flat["obs"])
    if not model.sound():
        raise FloatingPointError("non-finite observation statistics")
    # 4. what the log shows of the sampled policy
    mean = lambda key: float(np.mean([e[key] for e in episodes])) if episodes else float("nan")
    row = {"env_steps": n, "episodes": len(episodes), "return": mean("ret"), "success": mean("success"),
           "episode_length": mean("length"), **stats}
    return row, episodes


# ================================================================================================
# The paper's system ends here. What follows is the harness: input checks, files, training runs,
# evaluation and Table II, the demo and the command line. The scripts in tools/ import the file.
# ================================================================================================

import argparse
import copy
import csv
import hashlib
import importlib.metadata
import json
import multiprocessing
import platform
import shlex
import signal
import socket
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

import filelock
from tqdm import tqdm


# ================================================================================================
# Input: what a user, a file or an arm hands the system (settings, actions, wrist frames and poses,
# checkpoints) is checked here, once; so is each goal before it reaches an arm.
# ================================================================================================

class UsageError(Exception):
    """Bad input (an unknown agent, a missing or foreign checkpoint): one line, exit status 2."""


# Each field's range as an interval (brackets closed, parentheses open); a Settings field not named is at
# least 0, a PPOSettings field only finite. Upper bounds keep memory and time finite.
SETTINGS_RANGES = {
    "min_objects": "[1, inf)", "max_objects": "[1, 500]", "num_piles": "[0, 10]", "no_target_prob": "[0, 1]",
    "exploration_ratio": "[0, 1]", "workspace_m": "(0, 10]", "horizon": "[1, 100000]", "trunc_m": "(0, inf)",
    "voxels_per_side": "[8, 400]", "max_weight": "(0, inf)", "crop_m": "(0, inf)", "max_step_m": "(0, inf)",
    "max_turn_rad": "(0, inf)", "noise_rate": "(0, inf)", "false_positive_share": "[0, 1]",
    "gnbv_samples": "[1, 1000]", "gnbv_explored_to_stop": "(0, 1]", "seen_threshold": "(0, 1]",
    "objects_per_pile_dense": "[1, inf)", "object_mass_kg": "(0, inf)",
    "gripper_mass_kg": "(0, inf)", "variable_scale": "(0, inf)", "image_width": "[8, 1024]",
    "image_height": "[8, 1024]", "fov_y_deg": "(0, 170]", "depth_width": "[0, 1024]", "depth_height": "[0, 1024]",
    "depth_fov_y_deg": "[0, 170]", "rgb_offset_m": "[-0.2, 0.2]", "tof_noise_ratio": "[0, 0.2]",
    "tof_missing_share": "[0, 1]", "tof_edge_drop_share": "[0, 1]", "hand_eye_error_m": "[0, 0.05]",
    "hand_eye_error_rad": "[0, 0.2]", "rig_camera_share": "[0, 1]", "sensor_error_scale": "[0, 4]",
    "near_m": "(0, inf)", "gripper_force_n": "(0, inf)", "gripper_erp": "(0, 1]", "max_roll_rad": "[0, 1.5]",
    "ceiling_ratio": "(0, inf)", "gripper_start_tries": "[1, inf)", "reach_tol_m": "(0, inf)",
    "reach_tol_rad": "(0, inf)", "stall_m": "(0, inf)", "physics_hz": "[1, inf)", "settle_hz": "[1, inf)",
    "solver_iterations": "[1, inf)", "move_limit_s": "(0, 60]", "settle_s": "[0, 60]",
    "settle_scatter_s": "[0, 60]", "settle_pile_s": "[0, 60]", "settle_speed": "(0, inf)",
    "wall_height_m": "(0, inf)", "wall_thickness_m": "(0, inf)", "scatter_tries": "[1, inf)",
    "pile_layers": "[1, 20]", "pile_spacing_ratio": "(0, inf)", "pile_overlap_chance": "[0, 1]",
    "exploration_normaliser": "(0, inf)", "surface_points": "[1, 100000]", "seen_min_cos": "[0, 0.99]",
    "detection_threshold": "(0, 1]", "outline_pixel_share": "[0, 1]", "gnbv_rays": "[1, inf)",
    "gnbv_min_detections": "[1, inf)", "gnbv_stall_steps": "[1, inf)", "ges_tries_per_node": "[1, inf)",
    "claim_margin": "[1, 5]", "confirm_views": "[1, 100]", "state_share_scale": "(0, 10]",
    "state_voxel_m": "[0.001, 1]", "object_size_m": "[0.005, 1]"}   # a cell or an object finer costs memory as 1/v^3
PPO_RANGES = {
    "hidden": "[1, 1024]", "batch_steps": "[1, 1000000]", "epochs": "[1, 1000]", "minibatch": "[1, inf)",
    "gamma": "(0, 1]", "entropy_coef": "[0, inf)", "gae_lambda": "[0, 1]", "clip": "(0, inf)",
    "learning_rate": "(0, inf)", "value_coef": "[0, inf)", "max_grad_norm": "(0, inf)", "reward_scale": "(0, inf)",
    "init_terminate_prob": "[1e-6, 0.999999]", "init_log_std": "[-10, 2]", "adam_eps": "(0, inf)",
    "obs_clip": "(0, inf)", "checkpoint_every": "[1, inf)", "entropy_end_ratio": "[0, 10]",
    "learning_rate_end_ratio": "[0, 10]", "gamma_end_ratio": "(0, 1]", "schedule_start_share": "[0, 1)",
    "schedule_share": "(0, 1]"}


def in_interval(value: float, interval: str) -> bool:
    """Whether a number lies in an interval written "[0, 1)": a bracket includes its end, a parenthesis not."""
    low, high = (float(end) for end in interval[1:-1].split(","))
    return (low <= value if interval[0] == "[" else low < value) and (value <= high if interval[-1] == "]"
                                                                      else value < high)


def field_kind(field: dataclasses.Field) -> str:
    """A settings field's type by name ("int", "float", "bool", "tuple"; a string under `annotations`)."""
    return field.type if isinstance(field.type, str) else field.type.__name__


def check_fields(settings, ranges: dict, default: str) -> None:
    """Every field of a settings dataclass of its type (a whole number, a truth value, a tuple of the default's
    length), every number finite and in its range: a ValueError "NAME=VALUE: it must be ..." otherwise."""
    for field in dataclasses.fields(settings):
        value, kind, interval = getattr(settings, field.name), field_kind(field), ranges.get(field.name, default)
        values = value if kind == "tuple" and isinstance(value, tuple) else (value,)
        number = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
        said = f"{field.name}={repr(value)[:40]}{'...' * (len(repr(value)) > 40)}: it must be"
        if kind == "bool" and not isinstance(value, bool):
            raise ValueError(f"{said} True or False")
        if kind == "int" and not (isinstance(value, int) and not isinstance(value, bool)):
            raise ValueError(f"{said} a whole number")
        if kind == "tuple" and len(values) != len(field.default):
            raise ValueError(f"{said} {len(field.default)} numbers")
        if kind != "bool" and not (number and all(isinstance(v, int) or np.isfinite(v) for v in values)
                                   and all(in_interval(v, interval) for v in values)):   # an int of 400 digits is one
            raise ValueError(f"{said} in {interval}")


def checked_settings(task: str, overrides: dict | None = None) -> Settings:
    """A task's preset with Settings overrides, every field in its range and nothing a scene could not be built
    from; a ValueError naming the first field that is not."""
    unknown = sorted(set(overrides or {}) - {field.name for field in dataclasses.fields(Settings)})
    if unknown:
        raise ValueError(f"{unknown[0]} is not a Settings field")
    cfg = dataclasses.replace(TASKS[task], **(overrides or {}))
    check_fields(cfg, SETTINGS_RANGES, "[0, inf)")
    half, largest_m = cfg.workspace_m / 2, cfg.object_size_m * cfg.variable_scale[1]
    scaled = [getattr(cfg, name) * cfg.sensor_error_scale[1] for name in Settings.scaled_sensor_errors]
    for name, broken, must in (
            ("min_objects", cfg.min_objects > cfg.max_objects, f"at most max_objects ({cfg.max_objects})"),
            ("num_piles", cfg.num_piles > cfg.min_objects, f"at most min_objects ({cfg.min_objects})"),
            ("objects_per_pile_dense", cfg.objects_per_pile_dense[0] > cfg.objects_per_pile_dense[1], "(low, high)"),
            ("variable_scale", cfg.variable_scale[0] > cfg.variable_scale[1], "(low, high)"),
            ("sensor_error_scale", cfg.sensor_error_scale[0] > cfg.sensor_error_scale[1], "(low, high)"),
            ("area_median_px", cfg.area_median_px not in (0, 3, 5), "0, 3 or 5"),
            ("pile_overlap_chance", cfg.num_piles > 1 and cfg.pile_overlap_chance == 0,
             "above 0 with several piles (pile centres are drawn until they fit)"),
            ("pile_margin_ratio", cfg.num_piles and cfg.pile_margin_ratio >= 0.5, "under 0.5 (of workspace_m)"),
            ("object_size_m", largest_m > cfg.workspace_m / 3, "(at the largest variable_scale) at most a "
             f"third of workspace_m ({cfg.workspace_m})"),
            ("gripper_start_margin_m", cfg.gripper_start_margin_m >= half, f"under half of workspace_m ({half})"),
            ("gripper_start_min_z_m", cfg.gripper_start_min_z_m > cfg.ceiling_m,
             f"at most the ceiling (ceiling_ratio x workspace_m = {cfg.ceiling_m:g})"),
            ("near_m", cfg.near_m >= cfg.far_m, f"under the far plane (2 x workspace_m = {cfg.far_m:g})"),
            ("trunc_m", cfg.trunc_m >= cfg.volume_height_m, f"under the volume's height ({cfg.volume_height_m:g})"),
            ("depth_width", cfg.depth_width and not (cfg.depth_height and cfg.depth_fov_y_deg),
             "0, or given with depth_height and depth_fov_y_deg (a separate depth camera)"),
            ("depth_min_range_m", cfg.depth_min_range_m >= cfg.far_m,
             f"under the far plane (2 x workspace_m = {cfg.far_m:g})"),
            ("sensor_error_scale", not all(in_interval(v, SETTINGS_RANGES[name]) for v, name
                                           in zip(scaled, Settings.scaled_sensor_errors)),
             f"small enough that its high end keeps every one of {', '.join(Settings.scaled_sensor_errors)} "
             "in range")):
        if broken:
            raise ValueError(f"{name}={getattr(cfg, name)!r}: it must be {must}")
    return cfg


def checked_action(action) -> np.ndarray:
    """An env action as (6,) float64 clipped to the Box, or a ValueError naming what is wrong with it."""
    try:
        action = np.asarray(action, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"an action must be {ACTION_SIZE} numbers, not {action!r}") from None
    if action.shape != (ACTION_SIZE,):
        raise ValueError(f"an action has shape ({ACTION_SIZE},) ({', '.join(ACTION_NAMES)}), not {action.shape}")
    bad = np.flatnonzero(~np.isfinite(action))
    if len(bad):
        raise ValueError(f"action component {ACTION_NAMES[bad[0]]} (index {bad[0]}) is {action[bad[0]]}: "
                         "every component must be finite")
    return np.clip(action, -1.0, 1.0)


POSE_TOLERANCE = 1e-3   # a rigid transform's rotation is orthonormal to this (float32 poses pass)


def checked_pose(T, name: str) -> np.ndarray:
    """A (4, 4) finite rigid transform as float64 (a rotation and a translation), or a ValueError naming it."""
    try:
        T = np.array(T, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a 4 x 4 array of numbers") from None
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"{name} must be a finite 4 x 4 transform, not of shape {T.shape} with "
                         f"{np.size(T) - np.isfinite(T).sum()} values that are not finite")
    R = T[:3, :3]
    if (np.abs(R @ R.T - np.eye(3)).max() > POSE_TOLERANCE or np.linalg.det(R) < 0
            or np.abs(T[3] - [0, 0, 0, 1]).max() > POSE_TOLERANCE):
        raise ValueError(f"{name} is not a rigid transform (its rotation is not orthonormal, or its last row not "
                         "0, 0, 0, 1)")
    return T


def checked_view(rig: Rig, depth_m, T_world_depth, detections, rgb) -> tuple[np.ndarray, np.ndarray]:
    """A wrist view as the volume fuses it: the depth camera's (H, W) metres, each pixel that is not a number
    in its range (0, NaN, inf, negative, beyond far) as no return (0), and the RGB camera's (H', W') scores
    in [0, 1] or (H', W', 3) uint8 image; a ValueError for a view of another shape, a score that is not in
    [0, 1], or a pose that is not rigid."""
    depth_shape, rgb_shape = (rig.depth.height, rig.depth.width), (rig.rgb.height, rig.rgb.width)
    depth_m = np.asarray(depth_m)
    if depth_m.shape != depth_shape or depth_m.dtype.kind not in "fiu":
        raise ValueError(f"depth_m must be the depth camera's {depth_shape} array of metres, not {depth_m.dtype} "
                         f"{depth_m.shape}")
    with np.errstate(invalid="ignore"):   # NaN is in no range
        in_range = (depth_m >= rig.depth.near_m) & (depth_m <= rig.depth.far_m)
    depth_m = np.where(in_range, depth_m, 0).astype(np.float32)
    checked_pose(T_world_depth, "the depth camera's pose")
    if (detections is None) == (rgb is None):
        raise ValueError("give the RGB image (rgb=) or its detection scores (detections=), one of the two")
    if rgb is not None:
        rgb = np.asarray(rgb)
        if rgb.shape != rgb_shape + (3,) or rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be the RGB camera's {rgb_shape + (3,)} uint8 image, not {rgb.dtype} "
                             f"{rgb.shape}")
        return depth_m, detect_target(rgb)
    detections = np.asarray(detections)
    if detections.shape != rgb_shape or detections.dtype.kind not in "fiub":
        raise ValueError(f"detections must be the RGB camera's {rgb_shape} scores, not {detections.dtype} "
                         f"{detections.shape}")
    if not ((detections >= 0) & (detections <= 1)).all():   # NaN fails both
        raise ValueError("every detection score must be a number in [0, 1]")
    return depth_m, detections.astype(np.float32, copy=False)


def outside_box_m(searcher: Searcher, T_world_tool: np.ndarray) -> float:
    """How far the gripper lies outside the box the searcher moves in (|x|, |y| <= workspace_m / 2, 0 <= z <=
    the ceiling), in metres; 0 inside."""
    half, (x, y, z) = searcher.workspace_m / 2, T_world_tool[:3, 3]
    return float(np.linalg.norm([max(abs(x) - half, 0), max(abs(y) - half, 0), max(-z, z - searcher.ceiling_m, 0)]))


def checked_tool_pose(searcher: Searcher, T_world_tool: np.ndarray) -> np.ndarray:
    """The gripper's pose, if it lies within a step of the box the searcher moves in, pointing down as its yaw
    and roll say: farther out means a wrong T_base_workspace or tool frame, and a goal would leap into the box."""
    step, turn, outside_m = searcher.max_step_m, searcher.max_turn_rad, outside_box_m(searcher, T_world_tool)
    yaw, roll = yaw_roll_of(T_world_tool[:3, :3])
    if outside_m > step or abs(roll) > searcher.max_roll_rad + turn:
        raise ValueError(f"the gripper at {np.round(T_world_tool[:3, 3], 3).tolist()} m, roll {roll:.2f} rad in the "
                         f"workspace frame is {outside_m:.3f} m outside the searched box (|x|, |y| <= "
                         f"{searcher.workspace_m / 2:g}, 0 <= z <= {searcher.ceiling_m:g}, |roll| <= "
                         f"{searcher.max_roll_rad:g}), more than a step ({step:g} m): check T_base_workspace")
    off = gripper_rotation(yaw, roll).T @ T_world_tool[:3, :3]   # pitch: a goal has none, so it must be small
    if np.arccos(np.clip((np.trace(off) - 1) / 2, -1, 1)) > turn:
        raise ValueError("the gripper's approach axis is more than a step's turn from pointing down at the yaw and "
                         "roll it has (README, Frames): check the tool frame's axes")
    return T_world_tool


def checked_goal(searcher: Searcher, T_world_tool: np.ndarray, T_goal: np.ndarray) -> np.ndarray:
    """The goal of one step as an arm may take it: finite, in the box, at most one action's longest move away
    (sqrt(3) max_step_m: every axis at its limit) and max_turn_rad in roll and yaw; else a ValueError."""
    tolerance, xyz = 1e-9, T_goal[:3, 3]
    (yaw, roll), (goal_yaw, goal_roll) = yaw_roll_of(T_world_tool[:3, :3]), yaw_roll_of(T_goal[:3, :3])
    turns = abs(goal_roll - roll), abs((goal_yaw - yaw + np.pi) % (2 * np.pi) - np.pi)
    reach_m = np.sqrt(3) * searcher.max_step_m + tolerance
    if not (np.isfinite(T_goal).all() and outside_box_m(searcher, T_goal) <= tolerance and max(turns) <=
            searcher.max_turn_rad + tolerance and np.linalg.norm(xyz - T_world_tool[:3, 3]) <= reach_m):
        raise ValueError(f"no goal: the step from the gripper at {np.round(T_world_tool[:3, 3], 3).tolist()} would end "
                         f"at {np.round(xyz, 3).tolist()}, outside the box or beyond a step")
    return T_goal


def ppo_settings(values: dict) -> PPOSettings:
    """PPOSettings from NAME: VALUE pairs (a checkpoint's, or --set), each checked, or a one-line UsageError."""
    names = [field.name for field in dataclasses.fields(PPOSettings)]
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise UsageError(f"unknown PPO setting {unknown[0]!r}; the settings are {', '.join(names)}")
    try:
        ppo = PPOSettings(**values)
        check_fields(ppo, PPO_RANGES, "(-inf, inf)")
        if ppo.schedule_start_share >= ppo.schedule_share:
            raise ValueError(f"schedule_start_share={ppo.schedule_start_share}: it must be below schedule_share")
    except ValueError as error:
        raise UsageError(f"PPO setting {error}") from None
    return ppo


# ================================================================================================
# Files: checkpoints read and checked in one place, outputs written atomically, logs and curves.
# ================================================================================================

RUN_FIELDS = dict(   # what a checkpoint of a run adds (the first five always), with the check each must pass
    optimizer=lambda v: isinstance(v, dict) and {"state", "param_groups"} <= set(v),
    update=lambda v: isinstance(v, int) and v >= 0, env_steps=lambda v: isinstance(v, int) and v >= 0,
    wall_s=lambda v: isinstance(v, (int, float)) and np.isfinite(v) and v >= 0,
    seed=lambda v: isinstance(v, int) and 0 <= v <= MAX_SEED,
    rollout_streams=lambda v: isinstance(v, int) and 1 <= v <= MAX_STREAMS,
    task=lambda v: v in TASKS, scene=lambda v: v in SCENES,
    world=lambda v: isinstance(v, dict) and set(v) <= {f.name for f in dataclasses.fields(Settings)},
    schedule_steps=lambda v: isinstance(v, int) and v >= 1)
MAX_CHECKPOINT_BYTES = 64 * 2 ** 20   # the largest network PPOSettings allows, with Adam's state, is about 27 MB
MAX_STREAMS = 4096                    # rollout streams of a run
DEFAULT_STREAMS = 10                  # a new run's: 500 env steps each of the paper's 5000-step batch, enough
                                      # to keep 2 cores or 10 machines busy (the shipped runs used 2: model card)


def read_checkpoint(path: Path, run: bool = False, state_size: int | None = None) -> dict:
    """An objfind checkpoint, loaded with torch.load(weights_only=True) and checked once, here, or one
    line saying why not: its PPO settings, a network they build, finite weights; with `run`, the state
    a resumed run needs; with `state_size`, a network that takes that many values."""
    if path.is_dir():
        raise UsageError(f"{str(path)!r} is a folder, not a checkpoint")
    if not path.is_file():
        raise UsageError(f"checkpoint {str(path)!r} not found")
    if path.stat().st_size > MAX_CHECKPOINT_BYTES:
        raise UsageError(f"{str(path)!r} has {path.stat().st_size / 2 ** 20:.0f} MB; an objfind checkpoint has "
                         f"at most {MAX_CHECKPOINT_BYTES // 2 ** 20} MB")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:   # truncated, not a torch file, or unsafe to unpickle
        raise UsageError(f"{str(path)!r} is not a readable checkpoint ({type(error).__name__})") from None
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != "objfind-ppo":
        raise UsageError(f"{str(path)!r} is not an objfind checkpoint")
    missing = [k for k in ("model", "settings", "obs_dim") if k not in checkpoint]
    if missing:
        raise UsageError(f"{str(path)!r} is an objfind checkpoint without {', '.join(missing)}")
    try:
        if not (isinstance(checkpoint["obs_dim"], int) and 1 <= checkpoint["obs_dim"] <= 10_000):
            raise ValueError(f"a state of {checkpoint['obs_dim']!r} values")
        if not isinstance(checkpoint["settings"], dict) or not isinstance(checkpoint["model"], dict):
            raise ValueError("settings or model is not a dictionary")
        ActorCritic(checkpoint["obs_dim"], ppo_settings(checkpoint["settings"])).load_state_dict(checkpoint["model"])
    except (UsageError, ValueError, RuntimeError) as error:   # load_state_dict's first line is its title
        reason = (str(error).splitlines()[1:] or [str(error)])[0].strip()
        raise UsageError(f"{str(path)!r} does not hold an objfind network: {reason}") from None
    if not all(torch.isfinite(t).all() for t in checkpoint["model"].values() if t.is_floating_point()):
        raise UsageError(f"{str(path)!r} holds non-finite weights")
    if state_size is not None and checkpoint["obs_dim"] != state_size:
        raise UsageError(f"{str(path)!r} is for a {checkpoint['obs_dim']}-value state, not the {state_size} of Fig. 2")
    missing = [k for k in list(RUN_FIELDS)[:5] if k not in checkpoint]
    if run and missing:
        raise UsageError(f"--resume: the checkpoint has no {', '.join(missing)}: it holds weights, not a run")
    wrong = [k for k, ok in RUN_FIELDS.items() if run and k in checkpoint and not ok(checkpoint[k])]
    if wrong:
        raise UsageError(f"--resume: {str(path)!r} has an impossible {wrong[0]} ({str(checkpoint[wrong[0]])[:60]})")
    return checkpoint


LOCK_NAME = ".objfind.lock"   # the lock file of an output folder while a run writes into it
HELD_LOCKS: dict = {}          # folder -> this process's lock on it, released when its command ends


def writable_folder(path: Path, take_lock: bool = True) -> Path:
    """`path` as this run's output folder: made if missing (its parent must exist) and locked, so that a
    second run into it is refused. Taking the lock writes a file, which proves the folder can be written
    (permission bits do not tell: root ignores them, a read-only filesystem does not); the system releases
    it when the process ends, however it ends."""
    if path.exists() and not path.is_dir():
        raise UsageError(f"{str(path)!r} exists and is not a folder")
    if not path.parent.is_dir():
        raise UsageError(f"the parent of the output folder {str(path)!r} does not exist")
    try:
        path.mkdir(exist_ok=True)
        if take_lock and path.resolve() not in HELD_LOCKS:   # a folder of run folders is not locked
            lock = filelock.FileLock(path / LOCK_NAME)
            lock.acquire(timeout=0)
            HELD_LOCKS[path.resolve()] = lock
    except filelock.Timeout:
        raise UsageError(f"{str(path)!r} is being written by another objfind run: wait for it to end, or pick "
                         "another output") from None
    except OSError as error:
        raise UsageError(f"cannot write into {str(path)!r} ({error.strerror or error})") from None
    return path


def locked_by_another(folder: Path) -> bool:
    """Whether another process holds the folder's lock (asking takes it for a moment)."""
    if folder.resolve() in HELD_LOCKS or not (folder / LOCK_NAME).exists():
        return False
    try:
        filelock.FileLock(folder / LOCK_NAME).acquire(timeout=0).lock.release()
        return False
    except filelock.Timeout:
        return True


def release_locks() -> None:
    for lock in HELD_LOCKS.values():
        lock.release()
    HELD_LOCKS.clear()


def replace_atomically(path: Path, write) -> None:
    """write(tmp) to this process's own temporary name beside `path` (keeping the suffix, by which OpenCV
    picks the format), flushed to disk, then renamed onto path: a killed run never leaves a half-written
    file, two runs never share one. Nothing is installed into a folder another live run has locked; a
    failed write is one UsageError line, and its temporary file is removed."""
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        write(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        if locked_by_another(path.parent):
            raise OSError("another objfind run took over the folder")
        os.replace(tmp, path)
    except (OSError, RuntimeError) as error:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise UsageError(f"could not write {str(path)!r} ({reason})") from None


def save_checkpoint(path: Path, checkpoint: dict) -> None:
    replace_atomically(path, lambda tmp: torch.save(checkpoint, tmp))


def write_csv(rows: list, path: Path, fields: tuple | None = None) -> None:
    """Rows (episodes, or updates of a training log) with a header, replaced atomically."""
    def write(tmp):
        with open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(fields or rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    replace_atomically(path, write)


def write_image(path: Path, rgb: np.ndarray) -> None:
    """An (H, W, 3) RGB image to a PNG, replaced atomically; cv2.imwrite's False becomes an error."""
    def write(tmp):
        if not cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise OSError("OpenCV could not write the image")
    replace_atomically(path, write)


PROGRESS_EPISODES = 200   # the progress bar's success rate is over this many latest episodes
TRAIN_LOG_FIELDS = ("update", "env_steps", "episodes", "return", "success", "episode_length", "policy_loss",
                    "value_loss", "entropy", "approx_kl", "clip_fraction", "wall_s")


def read_train_log(path: Path, updates: int) -> list:
    """A resumed run's log.csv up to its checkpoint's update, every row checked: one row per update from the
    first, numbers in every column (a spreadsheet may have saved it); anything else is one line."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            if sorted(reader.fieldnames or []) != sorted(TRAIN_LOG_FIELDS):
                raise ValueError(f"its columns are not {', '.join(TRAIN_LOG_FIELDS)}")
            rows = []
            for line, row in enumerate(reader, start=2):
                if None in row or None in row.values() or not all(re.fullmatch(r"[-+.\w]+", v) for v in row.values()):
                    raise ValueError(f"line {line} is not a row of numbers")
                values = {k: float(v) for k, v in row.items()}
                if values["update"] != len(rows) + 1:
                    raise ValueError(f"line {line} is update {row['update']}, not {len(rows) + 1}")
                rows.append({**row, "update": len(rows) + 1})
    except FileNotFoundError:
        rows = []
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise UsageError(f"--resume: {str(path)!r}: {error}") from None
    if len(rows) < updates:
        raise UsageError(f"--resume: {str(path)!r} ends at update {len(rows)}, the checkpoint at {updates}")
    return rows[:updates]   # the tail after the checkpoint is lost work, run again


CURVE_SIZE = (720, 480)     # width, height of a learning-curve PNG
CURVE_MARGINS = (70, 20, 34, 50)   # left, right, top, bottom: room for the tick labels and axis titles


def save_figure(figure, path: Path) -> None:
    """A matplotlib figure to a PNG at 100 dots per inch, replaced atomically."""
    replace_atomically(path, lambda tmp: figure.savefig(tmp, dpi=100))


def plot_learning_curve(rows: list, path: Path) -> None:
    """Success % and mean episode length of the sampled policy per update against env steps: two panels."""
    from matplotlib.figure import Figure   # here, not at the top: worker processes never plot
    from matplotlib.ticker import EngFormatter
    (width, height), (left, right, top, bottom) = CURVE_SIZE, CURVE_MARGINS
    figure = Figure(figsize=(width / 100, height / 100))
    figure.subplots_adjust(left / width, bottom / height, 1 - right / width, 1 - top / height, hspace=0.35)
    steps = [float(r["env_steps"]) for r in rows]
    for ax, key, scale, title in zip(figure.subplots(2, 1, sharex=True), ("success", "episode_length"), (100, 1),
                                     ("success (%) of the sampled policy, one point per PPO update",
                                      "mean episode length (steps)")):
        ax.plot(steps, [float(r[key]) * scale for r in rows], color="C2" if scale == 100 else "C0")
        ax.set_title(title, loc="left", fontsize=9)
        ax.set_ylim(0, 100 if scale == 100 else None)
        ax.grid(alpha=0.3)
    ax.set_xlabel("env steps")
    ax.xaxis.set_major_formatter(EngFormatter(sep=""))
    save_figure(figure, path)


# ================================================================================================
# Training runs: PPO's loop (ppo_iteration) with what a long run needs around it: worker processes,
# resume, checkpoints and logs written as it goes, Ctrl-C and SIGTERM.
# ================================================================================================

def stop_as_ctrl_c(signum, frame):
    """SIGTERM (a scheduler's stop) ends a command as Ctrl-C does: its workers ended, what it finished kept."""
    raise KeyboardInterrupt


def ignore_sigint() -> None:
    """In a worker process: Ctrl-C reaches the whole process group, and the parent alone handles it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def process_pool(workers: int, initializer=ignore_sigint, initargs=()) -> ProcessPoolExecutor:
    """`workers` spawned processes that ignore Ctrl-C; one that dies raises BrokenProcessPool, never hangs."""
    return ProcessPoolExecutor(workers, multiprocessing.get_context("spawn"), initializer, initargs)


def stop_pool(pool: ProcessPoolExecutor) -> None:
    """Cancel what waits and end what runs, at once: Ctrl-C must not wait for a running job. The pool's
    manager thread is then joined, so that nothing of it is left for the interpreter's exit to wake."""
    processes = list((pool._processes or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.terminate()
    for process in processes:
        process.join()
    pool.shutdown(wait=True)


DEAD_WORKER = "a worker process died (killed, or out of memory?)"


class DeadWorker(Exception):
    """A Ray worker or actor died: the command stops, as with a dead worker process."""


RAY_CONNECT_S = 10   # how long --ray ADDRESS may take to answer at all
RAY_EXCLUDES = [".git", "runs", "out", "results", "__pycache__", ".pytest_cache"]   # not needed by workers


def connect_ray(address: str):
    """Ray, connected once per process: `address` "local" joins $RAY_ADDRESS if set (Ray's own rule), else
    starts a Ray instance here; any other joins that cluster. Every worker gets this folder (objfind.py,
    weights/) as its working directory (README)."""
    try:
        import ray
    except ImportError:
        raise UsageError("--ray needs Ray, which objfind does not require: pip install 'ray[default]'") from None
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not ray.is_initialized() and host and port.isdigit():   # Ray retries an address nobody answers for ever
        try:
            socket.create_connection((host, int(port)), timeout=RAY_CONNECT_S).close()
        except OSError as error:
            raise UsageError(f"--ray {address}: nothing answers there ({error.strerror or error}); start the "
                             "cluster (ray start --head) or give its address") from None
    if not ray.is_initialized():
        ray.init(address=None if address == "local" else address, log_to_driver=False,
                 runtime_env={"working_dir": str(Path(__file__).resolve().parent), "excludes": RAY_EXCLUDES})
    return ray


def ray_results(ray, refs: list, done=None) -> list:
    """The results of Ray tasks in submission order; a dead worker or Ctrl-C cancels all that remain."""
    results = []
    try:
        for ref in refs:
            results.append(ray.get(ref))
            done and done(results[-1])
    except BaseException as error:
        for ref in refs[len(results):]:   # best effort: a task's worker is stopped, an actor's task dropped
            try:
                ray.cancel(ref, force=True)
            except ValueError:             # an actor's task cannot be forced; its actor is killed next
                ray.cancel(ref)
        if isinstance(error, (ray.exceptions.WorkerCrashedError, ray.exceptions.RayActorError,
                              ray.exceptions.NodeDiedError)):
            raise DeadWorker(DEAD_WORKER) from None
        if isinstance(error, ray.exceptions.RayTaskError):
            raise error.as_instanceof_cause() from None
        raise
    return results

ROLLOUT_WORKER: dict = {}   # per worker process: its env and its copy of the policy


def start_rollout_worker(make_env, obs_dim: int, ppo: PPOSettings, in_pool: bool = False) -> None:
    torch.set_num_threads(1)   # one env and a small MLP per process: threads would only contend
    if in_pool:
        ignore_sigint()
    ROLLOUT_WORKER.update(env=make_env(), model=ActorCritic(obs_dim, ppo))


def run_rollout_worker(weights: dict, steps: int, env_seed: int, sample_seed: int) -> dict:
    """One rollout stream of a batch, with the current weights. Each worker process steps its own env
    at its own pace: lock-step workers would all wait for whichever is resetting a scene (a pile: 80 ms)."""
    model = ROLLOUT_WORKER["model"]
    model.load_state_dict(weights)
    return collect_rollout(ROLLOUT_WORKER["env"], model, steps, env_seed, sample_seed)


class RolloutActor:
    """A Ray actor: a rollout worker whose env lives across updates, as a worker process's does."""

    def __init__(self, make_env, obs_dim: int, ppo_values: dict):
        start_rollout_worker(make_env, obs_dim, ppo_settings(ppo_values))

    def rollout(self, weights: dict, steps: int, env_seed: int, sample_seed: int) -> dict:
        return run_rollout_worker(weights, steps, env_seed, sample_seed)


def rollout_collector(make_env, env, obs_dim: int, ppo: PPOSettings, streams: int, processes: int, seed: int,
                      ray_address: str | None = None):
    """`collect(weights, update)` for ppo_iteration, serving the run's streams from `processes` worker
    processes or Ray actors (each with its own env) or from this process with `env`; and a function that
    closes them. A stream's rollout depends on its seeds only, never on what serves it."""
    steps = max(1, ppo.batch_steps // streams)

    def jobs(weights: dict, update: int) -> list:
        return [(weights, steps, derived_seed(seed, update, w, 0), derived_seed(seed, update, w, 1))
                for w in range(streams)]
    if ray_address:
        env.close()
        ray = connect_ray(ray_address)
        actor = ray.remote(num_cpus=1, max_restarts=0)(RolloutActor)
        actors = [actor.remote(make_env, obs_dim, vars(ppo)) for _ in range(processes)]
        return (lambda weights, update: ray_results(ray, [actors[i % processes].rollout.remote(*job) for i, job
                                                          in enumerate(jobs(weights, update))]),
                lambda: [ray.kill(a) for a in actors])
    if processes > 1:
        env.close()
        pool = process_pool(processes, start_rollout_worker, (make_env, obs_dim, ppo, True))
        return (lambda weights, update: list(pool.map(run_rollout_worker, *zip(*jobs(weights, update)))),
                lambda: stop_pool(pool))
    start_rollout_worker(lambda: env, obs_dim, ppo)
    return (lambda weights, update: [run_rollout_worker(*job) for job in jobs(weights, update)],
            lambda: ROLLOUT_WORKER.pop("env").close())


class TrainingInterrupted(Exception):
    """Ctrl-C, SIGTERM, a dead worker or a diverged update (`cause`) stopped `train`; the last finished
    update is in the checkpoint."""

    def __init__(self, update: int, env_steps: int, path: Path, cause: str = "interrupted"):
        super().__init__(f"update {update} ({env_steps} env steps)")
        self.update, self.env_steps, self.path, self.cause = update, env_steps, path, cause


def train(make_env, out_dir: Path, total_steps: int, ppo: PPOSettings = PPOSettings(), workers: int = 1,
          seed: int = 0, resume: dict | None = None, progress: bool = True, meta: dict | None = None,
          init: dict | None = None, fresh_terminate: bool = False, streams: int = 1,
          ray_address: str | None = None) -> dict:
    """PPO with `workers` processes, each with its own make_env(): out_dir/log.csv every update, checkpoint.pt
    and curve.png every few updates, at the last and when interrupted. `resume`, the run's checkpoint,
    continues it exactly (its settings, streams and seed) with any worker count; `init` warm-starts a new run
    from a checkpoint's networks, with fresh_terminate the terminate head anew (weights/README.md). Each
    batch is split into `streams` rollouts whatever serves them, so the weights do not depend on `workers`."""
    writable_folder(out_dir)
    ckpt_path, log_path = out_dir / "checkpoint.pt", out_dir / "log.csv"
    schedule_steps = total_steps   # a run's schedule spans the --steps it started with
    if resume is not None:   # a run keeps the settings, seed and streams it started with
        ppo, seed, streams = ppo_settings(resume["settings"]), resume["seed"], resume.get("rollout_streams", workers)
        schedule_steps = resume.get("schedule_steps", total_steps)
        meta = {**({"init": resume["init"]} if "init" in resume else {}), **(meta or {})}
    env = make_env()   # the single worker's env, or only asked for the observation size
    obs_dim = env.observation_space.shape[0]
    torch.manual_seed(seed)
    model = ActorCritic(obs_dim, ppo)
    optimizer = torch.optim.Adam(model.parameters(), lr=ppo.learning_rate, eps=ppo.adam_eps)
    update, env_steps, wall_s, log_rows = 0, 0, 0.0, []
    if resume is not None:
        if resume["obs_dim"] != obs_dim:
            raise UsageError(f"--resume: the checkpoint is for a {resume['obs_dim']}-value state, not {obs_dim}")
        model.load_state_dict(resume["model"])
        try:
            optimizer.load_state_dict(resume["optimizer"])
        except (ValueError, KeyError, TypeError, RuntimeError):
            raise UsageError("--resume: the checkpoint's optimizer state does not fit its network") from None
        update, env_steps, wall_s = resume["update"], resume["env_steps"], resume["wall_s"]
        log_rows = read_train_log(log_path, update)
    elif init is not None:   # a fresh optimizer: Adam's moments belong to the old task
        try:
            model.load_state_dict(init["model"])
        except RuntimeError:
            raise UsageError("--init: the checkpoint's network does not match these settings") from None
        if fresh_terminate:
            model.reset_terminate(ppo.init_terminate_prob)
    collect, close_workers = rollout_collector(make_env, env, obs_dim, ppo, streams, min(workers, streams), seed,
                                               ray_address)

    def snapshot() -> dict:
        """The checkpoint of the update just finished (copies: the next update changes the tensors)."""
        return dict(format="objfind-ppo", model=copy.deepcopy(model.state_dict()),
                    optimizer=copy.deepcopy(optimizer.state_dict()), update=update, env_steps=env_steps,
                    wall_s=wall_s, seed=seed, obs_dim=obs_dim, settings=vars(ppo).copy(), rollout_streams=streams,
                    schedule_steps=schedule_steps,
                    **(meta or {}))

    latest, saved_update, recent = None, update, []
    bar = tqdm(total=total_steps, initial=min(env_steps, total_steps), unit="step", disable=not progress,
               file=sys.stderr, desc="train")
    handles_sigterm = threading.current_thread() is threading.main_thread()
    previous_handler = signal.signal(signal.SIGTERM, stop_as_ctrl_c) if handles_sigterm else None
    try:
        while env_steps < total_steps:
            t0 = time.perf_counter()
            now = scheduled(ppo, optimizer, min(1.0, env_steps / schedule_steps))
            row, episodes = ppo_iteration(model, optimizer, now, collect, seed, update)
            update_s = time.perf_counter() - t0
            steps_per_s = row["env_steps"] / update_s
            update, env_steps, wall_s = update + 1, env_steps + row["env_steps"], wall_s + update_s
            latest = snapshot()
            row.update(update=update, env_steps=env_steps, wall_s=wall_s)
            log_rows.append({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
            write_csv(log_rows, log_path, TRAIN_LOG_FIELDS)
            if update % ppo.checkpoint_every == 0 or env_steps >= total_steps:
                save_checkpoint(ckpt_path, latest)
                saved_update = update
                plot_learning_curve(log_rows, out_dir / "curve.png")
            recent = (recent + episodes)[-PROGRESS_EPISODES:]
            bar.update(min(env_steps, total_steps) - bar.n)
            bar.set_postfix(steps_per_s=f"{steps_per_s:.0f}",
                            success=f"{np.mean([e['success'] for e in recent]) if recent else 0:.2f}")
    except (KeyboardInterrupt, BrokenProcessPool, DeadWorker, FloatingPointError) as stop:
        if latest is not None and latest["update"] > saved_update:
            save_checkpoint(ckpt_path, latest)
            write_csv([r for r in log_rows if int(r["update"]) <= latest["update"]], log_path, TRAIN_LOG_FIELDS)
            plot_learning_curve(log_rows, out_dir / "curve.png")
        kept = latest or resume
        cause = (DEAD_WORKER if isinstance(stop, (BrokenProcessPool, DeadWorker)) else
                 f"training diverged in update {update + 1} ({stop})" if isinstance(stop, FloatingPointError) else
                 "interrupted")
        raise TrainingInterrupted(kept["update"] if kept else 0, kept["env_steps"] if kept else 0, ckpt_path,
                                  cause) from None
    finally:
        bar.close()
        if handles_sigterm:
            signal.signal(signal.SIGTERM, previous_handler)
        close_workers()
    return dict(update=update, env_steps=env_steps, model=model, log=log_rows)


# ================================================================================================
# Evaluation (Sec. IV-C): paired episodes, success with a Wilson interval, the Table II layout.
# ================================================================================================

PAPER_TABLE_II = {   # (agent, task): {scene: (success %, average steps)}; 1000 episodes each, the real robot's 20
    ("gnbv", "ap"): {"cubes": (93.3, 8.59), "fixed-primitives": (94.4, 8.48), "variable-primitives": (94.7, 8.26),
                     "random-shapes": (93.7, 8.62), "object-models": (94.9, 13.25)},
    ("gnbv", "ap-large"): {"cubes": (91.6, 31.89)},
    ("a3de", "ap"): {"cubes": (98.2, 4.14), "fixed-primitives": (97.9, 3.95), "variable-primitives": (96.5, 4.29),
                     "random-shapes": (97.1, 4.35), "object-models": (99.8, 4.38)},
    ("a3de", "ap-large"): {"cubes": (96.3, 14.57)},
    ("ges", "ip"): {"cubes": (99.9, 54.79), "fixed-primitives": (99.6, 51.72), "variable-primitives": (66.8, 70.84),
                    "random-shapes": (89.2, 54.42), "object-models": (35.1, 93.15)},
    ("i3de", "ip"): {"cubes": (88.0, 26.86), "fixed-primitives": (90.5, 21.22), "variable-primitives": (85.0, 30.08),
                     "random-shapes": (89.5, 20.82), "object-models": (82.1, 29.79)},
    ("gnbv", "ap-real"): {"cubes-and-cuboids": (90.0, 11.75)},   # the real robot (ours: a simulated replica)
    ("a3de", "ap-real"): {"cubes-and-cuboids": (90.0, 12.3)},
    ("ges", "ip-real"): {"cubes-and-cuboids": (100.0, 22.9)},
    ("i3de", "ip-real"): {"cubes-and-cuboids": (100.0, 15.35)},
}

PAPER_NO_TARGET = {"a3de": 100.0, "i3de": 96.1}   # % of no-target scenes ended correctly (Sec. V-A)

# Two simple agents beside the paper's baselines: a floor to compare with, and a check of the pipeline.

class RandomAgent:
    """Uniform random displacements; terminates with a small probability per step."""

    terminate_prob = 0.02   # about 50 steps per episode, well inside the horizon

    def __init__(self, cfg: Settings, seed: int | None = None):
        self.rng = np.random.default_rng(seed)

    def reset(self, searcher: Searcher, T_world_tool: np.ndarray) -> None:
        pass

    def act(self, searcher: Searcher, T_world_tool: np.ndarray) -> np.ndarray:
        action = self.rng.uniform(-1, 1, ACTION_SIZE).astype(np.float32)
        action[ACTION_MOVES] = 1.0 if self.rng.random() < self.terminate_prob else -1.0
        return action


class ScriptedAgent:
    """A hand-written searcher: rise to the ceiling, tilt, then turn on the spot while drifting to the
    workspace centre; terminate once the volume holds a perceived target or after one full turn."""

    tilt_rad = 0.6   # looks past the walls' tops from the ceiling

    def __init__(self, cfg: Settings, seed: int | None = None):
        pass

    def reset(self, searcher: Searcher, T_world_tool: np.ndarray) -> None:
        self.turned_rad = 0.0

    def act(self, searcher: Searcher, T_world_tool: np.ndarray) -> np.ndarray:
        yaw, roll = yaw_roll_of(T_world_tool[:3, :3])
        if searcher.target_found() or self.turned_rad >= 2 * np.pi:
            return stop_action()
        action = np.zeros(ACTION_SIZE, np.float32)
        action[ACTION_MOVES] = -1.0
        x, y, z = T_world_tool[:3, 3]
        to_centre = rotation(yaw, "z").T @ np.r_[-x, -y, searcher.ceiling_m - z]
        action[:3] = np.clip(to_centre / searcher.max_step_m, -1, 1)
        action[3] = np.clip((self.tilt_rad - roll) / searcher.max_turn_rad, -1, 1)
        if z > searcher.ceiling_m - searcher.max_step_m:      # high enough: start turning
            action[4] = 1.0
            self.turned_rad += searcher.max_turn_rad
        return action


BASELINES = {"random": RandomAgent, "scripted": ScriptedAgent, "gnbv": GreedyNextBestView,
             "ges": GridExhaustiveSearch}

LEARNED = ("a3de", "i3de")


def default_weights(agent: str, task: str) -> Path:
    """The shipped weights of a learned agent: weights/a3de.pt, weights/a3de-large.pt, weights/i3de.pt."""
    return Path(__file__).resolve().parent / "weights" / (f"{agent}-large.pt" if task == "ap-large" else f"{agent}.pt")


def learned_policy(agent: str, task: str, weights: Path | None = None) -> dict:
    """What a learned agent plays, read and checked once per command: --weights, or the shipped file;
    only the policy (no optimizer state) travels on to worker processes."""
    checkpoint = read_checkpoint(Path(weights or default_weights(agent, task)), state_size=STATE_SIZE)
    return {k: checkpoint[k] for k in ("model", "settings", "obs_dim")}


def policy_fingerprint(policy: dict | None) -> str:
    """What a learned agent plays, as 12 hex digits of its weights' SHA-256 (the same in any file); "none"."""
    if policy is None:
        return "none"
    digest = hashlib.sha256()
    for name in sorted(policy["model"]):
        digest.update(name.encode() + policy["model"][name].numpy().tobytes())
    return digest.hexdigest()[:12]


@functools.cache
def package_versions() -> str:
    """The packages an episode depends on: a cell is exact only under the same versions (README)."""
    return (f"python={platform.python_version()} numpy={np.__version__} "
            f"pybullet={importlib.metadata.version('pybullet')} torch={torch.__version__} "
            f"gymnasium={gym.__version__} opencv={cv2.__version__}")


def world_identity(task: str, overrides: dict | None) -> str:
    """The world a cell's episodes ran in: WORLD_REVISION and 8 hex digits of every setting but the target-size
    rule ("8+1a2b3c4d"): a sensor point run with another camera, or a preset's default edited, is another
    world, whatever its file is called."""
    cfg = dataclasses.replace(TASKS[task], **(overrides or {}))
    values = {k: v for k, v in dataclasses.asdict(cfg).items() if k != "target_size_known"}
    as_json = json.dumps(values, sort_keys=True, default=float)   # tuples as lists, numpy scalars as floats
    return f"{WORLD_REVISION}+{hashlib.sha256(as_json.encode()).hexdigest()[:8]}"


def cell_origin(agent: str, task: str, scene: str, policy: dict | None, overrides: dict | None) -> dict:
    """What made a cell's episodes, stamped on each of its CSV rows: a table refuses a cell made otherwise."""
    size_known = (overrides or {}).get("target_size_known", TASKS[task].target_size_known)
    return dict(agent=agent, task=task, scene=scene, weights=policy_fingerprint(policy),
                target_size_known=size_known, world=world_identity(task, overrides), versions=package_versions())


def make_agent(name: str, cfg: Settings, seed: int, policy: dict | None = None):
    """A fresh agent for one episode of a world with these settings, its randomness seeded by the episode."""
    return PPOAgent(policy) if name in LEARNED else BASELINES[name](cfg, seed)


def run_episode(env: ObjectFindingEnv, agent, seed: int) -> dict:
    """One episode on scene `seed`; returns its row of the evaluation CSV."""
    _, info = env.reset(seed=seed)
    agent.reset(env.searcher, env.gripper_pose())
    decide_s, done = 0.0, False
    while not done:
        T_world_tool = env.gripper_pose()
        t0 = time.perf_counter()
        action = agent.act(env.searcher, T_world_tool)
        decide_s += time.perf_counter() - t0
        _, reward, done, _, info = env.step(action)
    return dict(seed=seed, target_present=info["target_present"], success=info["success"], steps=info["steps"],
                target_seen_fraction=round(info["target_seen_fraction"], 4),
                explored_fraction=round(info["explored_fraction"], 4),
                decision_ms=round(1e3 * decide_s / info["steps"], 3))


def run_jobs(function, jobs: list, workers: int, done=None, ray_address: str | None = None) -> list:
    """function(*job) for every job, in `workers` worker processes, in this one when workers is 1, or as
    Ray tasks; the results in job order, each also handed to done() as it arrives (for progress bars)."""
    if ray_address:
        ray = connect_ray(ray_address)
        task = ray.remote(num_cpus=1, max_retries=0)(function)
        try:
            return ray_results(ray, [task.remote(*job) for job in jobs], done)
        except DeadWorker:
            raise UsageError(f"{DEAD_WORKER}: stopped; what was already written is kept") from None
    results, pool = [], process_pool(workers) if workers > 1 else None
    try:
        for job in [pool.submit(function, *job) for job in jobs] if pool else jobs:
            results.append(job.result() if pool else function(*job))
            done and done(results[-1])
    except BaseException as error:   # Ctrl-C, a dead worker, a failed episode: end the workers at once
        pool and stop_pool(pool)
        if isinstance(error, BrokenProcessPool):
            raise UsageError(f"{DEAD_WORKER}: stopped; what was already written is kept") from None
        raise
    pool and pool.shutdown(wait=True)
    return results


def evaluate_chunk(agent_name: str, task: str, scene: str, seeds: list, policy: dict | None = None,
                   overrides: dict | None = None) -> list:
    """Episodes of one worker process: one env, a fresh baseline per episode (its rng seeded by the
    episode), and a learned agent made once (its policy is deterministic and keeps no state)."""
    env = ObjectFindingEnv(task, scene, **(overrides or {}))
    learned = PPOAgent(policy) if agent_name in LEARNED else None
    try:
        return [run_episode(env, learned or make_agent(agent_name, env.cfg, seed), seed) for seed in seeds]
    finally:
        env.close()


EVAL_CHUNK = 5   # episodes per job of a worker process: small jobs keep all workers busy to the end


def evaluate(agent_name: str, task: str, scene: str, episodes: int, seed: int = 0, workers: int = 1,
             progress: bool = True, policy: dict | None = None, overrides: dict | None = None,
             ray_address: str | None = None) -> list:
    """Paired episodes: episode i is scene seed + i for every agent, in worlds with these Settings
    overrides (an ablation). A learned agent plays `policy`, or its shipped weights. Rows in seed order,
    each with the cell's origin."""
    if agent_name in LEARNED and policy is None:
        policy = learned_policy(agent_name, task)
    origin = cell_origin(agent_name, task, scene, policy, overrides)
    seeds = list(range(seed, seed + episodes))
    jobs = [(agent_name, task, scene, seeds[i:i + EVAL_CHUNK], policy, overrides)
            for i in range(0, episodes, EVAL_CHUNK)]
    with tqdm(total=episodes, desc=f"{agent_name} {task}/{scene}", unit="ep", disable=not progress,
              file=sys.stderr) as bar:
        parts = run_jobs(evaluate_chunk, jobs, workers, lambda part: bar.update(len(part)), ray_address)
    return sorted(({**row, **origin} for part in parts for row in part), key=lambda r: r["seed"])


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a success rate (Wilson 1927): sound near 0 % and 100 %, unlike
    the normal approximation mean +- 1.96 sd."""
    if n == 0:
        return 0.0, 0.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)   # rounding must not print -0.0


def summarise(rows: list) -> dict:
    """Success % (with its 95 % interval), mean steps (with its), no-target success, decision time."""
    success = np.array([r["success"] for r in rows], bool)
    steps = np.array([r["steps"] for r in rows], float)
    absent = np.array([not r["target_present"] for r in rows], bool)
    lo, hi = wilson_interval(int(success.sum()), len(rows))
    steps_half = 1.96 * steps.std(ddof=1) / np.sqrt(len(rows)) if len(rows) > 1 else 0.0
    return dict(episodes=len(rows), success=100 * success.mean(), success_lo=100 * lo, success_hi=100 * hi,
                steps=steps.mean(), steps_half=steps_half,
                steps_with_target=steps[~absent].mean() if (~absent).any() else float("nan"),
                no_target_episodes=int(absent.sum()),
                no_target_success=100 * success[absent].mean() if absent.any() else float("nan"),
                decision_ms=float(np.mean([r["decision_ms"] for r in rows])))


EPISODE_FIELDS = ("seed", "target_present", "success", "steps", "target_seen_fraction", "explored_fraction",
                  "decision_ms")   # the columns of an evaluation CSV, one row per episode ...
ORIGIN_FIELDS = ("agent", "task", "scene", "weights", "target_size_known", "world", "versions")   # what made it
CELL_IDENTITY = ORIGIN_FIELDS[:-1]   # a table's cell must match these; other versions are reported, not refused
WORLD_REVISION = 10  # of the simulated world and the agents: raised by every change that alters the episodes
                     # of a seed (the model card says what each revision changed)


def parse_bool(text: str) -> bool:
    """True/False whatever the case (a spreadsheet writes TRUE), or 1/0; anything else is an error."""
    if text.strip().lower() not in ("true", "1", "false", "0"):
        raise ValueError(f"{text!r} is not true or false")
    return text.strip().lower() in ("true", "1")


def one_of(choices):
    """A CSV column's parser that accepts only these names."""
    def parse(text: str) -> str:
        if text not in choices:
            raise ValueError(f"{text!r} is not one of {', '.join(choices)}")
        return text
    return parse


def world_tag(text: str) -> str:
    """A world_identity: a revision, perhaps with the digits of its settings."""
    if not re.fullmatch(r"\d+(\+[0-9a-f]{8})?", text):
        raise ValueError(f"{text!r} is not a world (a revision, perhaps +8 hex digits of its settings)")
    return text


def fraction(text: str) -> float:
    value = float(text)
    if not 0 <= value <= 1:
        raise ValueError(f"{text} is not a fraction in [0, 1]")
    return value


EPISODE_COLUMNS = dict(seed=int, target_present=parse_bool, success=parse_bool, steps=int,
                       target_seen_fraction=fraction, explored_fraction=fraction, decision_ms=float,
                       agent=one_of(list(BASELINES) + list(LEARNED)), task=one_of(list(TASKS)), scene=one_of(SCENES),
                       weights=str, target_size_known=parse_bool, world=world_tag, versions=str)


def checked_episode(row: dict, first: dict | None) -> dict:
    """One CSV row parsed by its columns' names and checked against what an episode can be."""
    if None in row or None in row.values():
        raise ValueError("it has a different number of fields than the header")
    row = {k: EPISODE_COLUMNS[k](v) for k, v in row.items()}
    if not 1 <= row["steps"] <= TASKS[row["task"]].horizon:
        raise ValueError(f"{row['steps']} steps: an episode of {row['task']} has 1 to {TASKS[row['task']].horizon}")
    if row["decision_ms"] < 0 or not np.isfinite(row["decision_ms"]) or row["seed"] < 0:
        raise ValueError("a negative seed or decision time")
    if not row["target_present"] and row["target_seen_fraction"] > 0:
        raise ValueError("a target seen in a scene without one")
    horizon, threshold = TASKS[row["task"]].horizon, TASKS[row["task"]].seen_threshold
    if row["target_present"] and row["success"] != (row["target_seen_fraction"] > threshold) and (
            row["success"] or row["steps"] < horizon):   # before the horizon only the agent's stop ends an episode
        raise ValueError(f"success {row['success']} with {row['target_seen_fraction']:.1%} of the target seen "
                         f"in {row['steps']} steps: a stop succeeds exactly above {threshold:.0%}")
    if not row["target_present"] and not row["success"] and row["steps"] < horizon:
        raise ValueError("a failure without a target before the horizon (only running out of steps fails there)")
    if first and any(row[k] != first[k] for k in ORIGIN_FIELDS):
        raise ValueError("its origin (agent, task, scene, weights, rule, world, versions) differs from line 2's")
    return row


def read_episodes(path: Path) -> list:
    """The rows of an evaluation CSV, each checked (`checked_episode`), seeds distinct; anything wrong is a
    one-line UsageError naming the file and the line. Never a plausible wrong number."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:   # a spreadsheet may add a byte-order mark
            reader = csv.DictReader(f)
            header = reader.fieldnames or []
            if sorted(header) != sorted(EPISODE_FIELDS + ORIGIN_FIELDS):
                raise UsageError(f"{str(path)} has columns {', '.join(header) or '(none)'}, not those of an "
                                 f"evaluation CSV: {', '.join(EPISODE_FIELDS + ORIGIN_FIELDS)}")
            rows, lines = [], {}
            for line, row in enumerate(reader, start=2):
                try:
                    rows.append(checked_episode(row, rows[0] if rows else None))
                    if rows[-1]["seed"] in lines:
                        raise ValueError(f"seed {rows[-1]['seed']} is also on line {lines[rows[-1]['seed']]}")
                    lines[rows[-1]["seed"]] = line
                except (ValueError, KeyError) as error:
                    raise UsageError(f"{str(path)}, line {line}: {error}") from None
    except (OSError, UnicodeDecodeError) as error:
        raise UsageError(f"cannot read {str(path)!r} ({error.__class__.__name__})") from None
    return rows


def stored_cell(path: Path, seeds: list, origin: dict) -> list | None:
    """The rows of a finished cell: None if no CSV is there yet, its rows if they are exactly these seeds
    made by this origin. A CSV of other seeds, or made by another agent, task, scene, weights, rule or world,
    is another experiment: refused, never overwritten."""
    if not path.exists():
        return None
    if path.is_dir():
        raise UsageError(f"{str(path)!r} is a folder, not a CSV")
    rows = read_episodes(path)
    made = {k: rows[0][k] for k in CELL_IDENTITY} if rows else {}
    want = {k: origin[k] for k in CELL_IDENTITY}
    if rows and made != want:
        def describe(o):
            revision, _, settings = o["world"].partition("+")
            return (f"{o['agent']} on {o['task']}/{o['scene']} (weights {o['weights']}, target size "
                    f"{'known' if o['target_size_known'] else 'unknown'}, world {revision}"
                    + (f" with settings {settings})" if settings else ")"))
        raise UsageError(f"{str(path)} was made by {describe(made)}, not {describe(want)}: "
                         "pass another --out, or delete that file to replace it")
    have = [r["seed"] for r in rows]
    if have != list(seeds):
        described = f"{len(have)} episodes from seed {have[0]}" if have else "no episodes"
        raise UsageError(f"{str(path)} holds {described}, not {len(seeds)} from seed {seeds[0]}: "
                         "pass another --out, or delete that file to replace it")
    return rows


def table_markdown(cells: dict, episodes: int, versions: set) -> str:
    """Table II: ours ("success / steps") beside the paper's, per agent and scene kind, and the share of
    no-target scenes each agent ended correctly (pooled over its cells; the paper gives it in the text)."""
    columns = ([("ap", "cubes"), ("ap-large", "cubes")] + [("ap", scene) for scene in TABLE_SCENES[1:]]
               + [("ap-real", "cubes-and-cuboids")])
    header = ["agent", "cubes", "cubes, large", "fixed prim.", "variable prim.", "random shapes", "object models",
              "real world", "no target"]
    lines = [f"Success % / average steps over {episodes} paired episodes per cell; the paper's below ours. "
             "Real world: ours is a simulated replica of the paper's real setup (ap-real, ip-real: Table I's real "
             "columns, cubes and cuboids, the rig's sensing), the paper's 20 runs of its robot. "
             "No target: % of the no-target scenes in the agent's cells that it ended correctly.", "",
             "| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for agent, interactive in (("gnbv", False), ("a3de", False), ("ges", True), ("i3de", True)):
        ours, paper = [], []
        for task, scene in columns:
            task = {"ap": "ip", "ap-real": "ip-real"}.get(task, task) if interactive else task
            cell = cells.get((agent, task, scene))
            published = PAPER_TABLE_II.get((agent, task), {}).get(scene)
            ours.append("-" if cell is None else f"{cell['success']:.1f} / {cell['steps']:.2f}")
            paper.append("-" if published is None else f"{published[0]:.1f} / {published[1]:.2f}")
        absent = [c for (a, _, _), c in cells.items() if a == agent and c["no_target_episodes"]]
        correct = sum(c["no_target_success"] * c["no_target_episodes"] for c in absent)
        count = sum(c["no_target_episodes"] for c in absent)
        ours.append(f"{correct / count:.1f} of {count}" if count else "-")
        paper.append(f"{PAPER_NO_TARGET[agent]:.1f}" if agent in PAPER_NO_TARGET else "-")
        lines.append(f"| {agent.upper()} (ours) | " + " | ".join(ours) + " |")
        lines.append(f"| {agent.upper()} (paper) | " + " | ".join(paper) + " |")
    made = "; ".join(sorted(versions)) if len(versions) < 2 else "mixed: " + " | ".join(sorted(versions))
    return "\n".join(lines + ["", f"Made with {made}."])


# ================================================================================================
# Demo: pictures of an episode (outside, wrist camera, volume, state) to a PNG and an MP4.
# ================================================================================================

PANEL = (320, 240)   # width, height of render()'s outside view and of each picture in the demo
GRIPPER_RGBA = (0.25, 0.25, 0.28, 1)   # the gripper as the outside view paints it


def paint_gripper(rgb: np.ndarray, depth: np.ndarray, T_world_camera: np.ndarray, K: np.ndarray,
                  T_world_tool: np.ndarray) -> np.ndarray:
    """The gripper's boxes painted into a rendered view: front faces, far to near, shaded by their slant,
    only where the rendered scene is farther than the face (a per-face depth test is enough here)."""
    out = rgb.copy()
    faces = []
    for half, centre in GRIPPER_BOXES:
        world = (BOX_SIGNS * half + centre) @ T_world_tool[:3, :3].T + T_world_tool[:3, 3]
        cam = (world - T_world_camera[:3, 3]) @ T_world_camera[:3, :3]     # R^T (p - t), row-wise
        for face in BOX_FACES:
            quad = cam[face]
            normal = np.cross(quad[1] - quad[0], quad[3] - quad[0])
            if np.dot(normal, quad.mean(0)) >= 0 or (quad[:, 2] <= MIN_PROJECTION_Z_M).any():   # faces away, behind
                continue
            faces.append((quad[:, 2].mean(), quad, abs(normal[2]) / np.linalg.norm(normal)))
    mask = np.zeros(depth.shape, np.uint8)
    for z, quad, facing in sorted(faces, key=lambda f: -f[0]):
        uv = (quad @ K.T)[:, :2] / quad[:, 2:]
        mask[:] = 0
        cv2.fillConvexPoly(mask, np.round(uv).astype(np.int32), 1)
        paint = (mask > 0) & ((depth == 0) | (depth > z))
        out[paint] = (255 * np.array(GRIPPER_RGBA[:3]) * (0.6 + 0.6 * facing)).clip(0, 255).astype(np.uint8)
    return out


def outside_view(env: ObjectFindingEnv, width: int = PANEL[0], height: int = PANEL[1]) -> np.ndarray:
    """The scene from a fixed oblique camera with the gripper painted in, (H, W, 3) uint8. Painted,
    not drawn by a body: moving any body reorders Bullet's broadphase and so changes the episode."""
    eye = np.array([0.0, -1.3, 1.3]) * env.cfg.workspace_m
    forward = np.array([0.0, 0.0, 0.12 * env.cfg.workspace_m]) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    T_world_camera = np.eye(4)
    T_world_camera[:3, :3] = np.stack([right, np.cross(forward, right), forward], 1)   # OpenCV: x right, y down
    T_world_camera[:3, 3] = eye
    K = np.array([[height * 1.1, 0, width / 2], [0, height * 1.1, height / 2], [0, 0, 1]])
    rgb, depth = env._render_world(T_world_camera, Camera(width, height, K, 0.05, 4 * env.cfg.workspace_m))
    return paint_gripper(rgb, depth, T_world_camera, K, env.gripper_pose())


def label(image: np.ndarray, text: str) -> np.ndarray:
    cv2.putText(image, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(image, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return image


DETECTION_OVERLAY_RGB = (255, 0, 255)   # magenta: no scene object has it (TARGET_RGBA, OTHER_RGBA)


def wrist_panel(rgb: np.ndarray, detections: np.ndarray, detection_threshold: float) -> np.ndarray:
    """The wrist camera image, upscaled, with the noisy detections above the threshold painted magenta."""
    image = cv2.resize(rgb, PANEL, interpolation=cv2.INTER_NEAREST)
    confident = (detections > detection_threshold).astype(np.uint8)
    mask = cv2.resize(confident, PANEL, interpolation=cv2.INTER_NEAREST) > 0
    image[mask] = (0.3 * image[mask] + 0.7 * np.array(DETECTION_OVERLAY_RGB)).astype(np.uint8)
    return label(image, "wrist camera + detections (magenta)")


def volume_panel(searcher: Searcher, T_world_tool: np.ndarray) -> np.ndarray:
    """Top view of the volume: unobserved dark, observed light, occupied shaded by height, detected red."""
    volume = searcher.volume
    observed = volume.weight.max(axis=2) > 0                               # (nx, ny)
    inside = (volume.weight > 0) & (volume.tsdf < 0)                       # behind a surface: an object
    height = np.where(inside.any(axis=2), inside.shape[2] - np.argmax(inside[:, :, ::-1], axis=2), 0)
    detected = (volume.detections > searcher.detection_threshold).any(axis=2)
    top = np.full(observed.shape + (3,), 45, np.uint8)
    top[observed] = (215, 215, 210)
    occupied = height > 0
    shade = (170 - 120 * height / inside.shape[2]).astype(np.uint8)
    top[occupied] = np.stack([shade, shade, shade + 20], -1)[occupied]
    top[detected] = (230, 30, 30)
    # arrays are [x, y]; draw x to the right and y up
    image = np.rot90(top).copy()
    side = PANEL[1]
    image = cv2.resize(image, (side, side), interpolation=cv2.INTER_NEAREST)
    n = volume.shape[0]
    to_px = lambda xy: (int((xy[0] - volume.origin[0]) / volume.voxel_m * side / n),
                        int(side - (xy[1] - volume.origin[1]) / volume.voxel_m * side / n))
    ee = T_world_tool[:3, 3]
    yaw, _ = yaw_roll_of(T_world_tool[:3, :3])
    tip = ee[:2] + searcher.max_step_m * np.array([np.cos(yaw), np.sin(yaw)])   # one max step ahead
    cv2.arrowedLine(image, to_px(ee), to_px(tip), (20, 120, 255), 2, tipLength=0.4)
    panel = np.full((PANEL[1], PANEL[0], 3), 255, np.uint8)
    panel[:, (PANEL[0] - side) // 2:(PANEL[0] - side) // 2 + side] = image
    return label(panel, "volume: observed / occupied / detected")


BINS_PANEL_PX = 99   # the side of one map in the demo's bins panel: 9 x 11 pixels, a cell of the middle 3 x 3


def bins_panel(state: np.ndarray) -> np.ndarray:
    """The state's maps as top views of the crop, the gripper's front up and its left on the left, each pixel
    shaded by the value of its bin as `column_bins` assigns it."""
    panel = np.full((PANEL[1], PANEL[0], 3), 255, np.uint8)
    ahead = (BINS_PANEL_PX - 0.5 - np.arange(BINS_PANEL_PX)) / BINS_PANEL_PX - 0.5   # crops ahead (rows), left
    bins = column_bins(*np.meshgrid(ahead, ahead, indexing="ij"), 1.0)              # (side, side)
    edges = (bins != np.roll(bins, 1, 0)) | (bins != np.roll(bins, 1, 1))
    edges[[0, -1]] = edges[:, [0, -1]] = True
    for m, name in enumerate(MAP_NAMES):
        values = np.abs(state[BINS * m:BINS * (m + 1)])
        grey = (255 - 230 * np.minimum(1.0, values / max(float(values.max()), 1e-6))).astype(np.uint8)[bins]
        tile = np.stack([grey, grey, np.full_like(grey, 255) if "detections" in name else grey], -1)
        tile[edges] = 120
        x0, y0 = 12 + (m % 2) * 156, 30 + (m // 2) * 106
        panel[y0:y0 + BINS_PANEL_PX, x0:x0 + BINS_PANEL_PX] = tile
        cv2.putText(panel, name, (x0 + 2, y0 - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    sums = (f"tsdf sum {state[STATE_TSDF_SUM]:.2f}, share seen {state[STATE_TARGET_SHARE]:.2f}, "
            f"roll {state[STATE_ROLL]:.2f}")
    return label(panel, f"state bins ({sums})")


def demo_frame(env: ObjectFindingEnv, state: np.ndarray, text: str) -> np.ndarray:
    """The four pictures of one moment side by side, (240, 1280, 3) RGB."""
    searcher = env.searcher
    return np.concatenate([label(outside_view(env, *PANEL), text),
                           wrist_panel(env.view.rgb, env.view.detections, searcher.detection_threshold),
                           volume_panel(searcher, env.gripper_pose()), bins_panel(state)], axis=1)


def write_contact_sheet(path: Path, frames: list) -> None:
    """Four moments of an episode (first, last and two between), stacked into one PNG."""
    picks = sorted(set(np.linspace(0, len(frames) - 1, 4).round().astype(int)))
    write_image(path, np.concatenate([frames[i] for i in picks], axis=0))


def run_demo(agent_name: str, task: str, scene: str, seed: int, out_dir: Path,
             policy: dict | None = None) -> tuple[Path, Path, dict]:
    """One episode to an MP4 (every step) and a PNG contact sheet (four moments of it); a learned agent
    plays `policy`, or its shipped weights."""
    if agent_name in LEARNED and policy is None:
        policy = learned_policy(agent_name, task)
    env = ObjectFindingEnv(task, scene, seed=seed)
    agent = make_agent(agent_name, env.cfg, seed, policy)
    state, info = env.reset()
    agent.reset(env.searcher, env.gripper_pose())
    frames = [demo_frame(env, state, f"{task}/{scene} seed {seed}: start")]
    done = False
    while not done:
        state, reward, done, _, info = env.step(agent.act(env.searcher, env.gripper_pose()))
        status = (f"step {info['steps']}: seen {info['target_seen_fraction']:.2f}, "
                  f"explored {info['explored_fraction']:.2f}")
        if done:
            status += "  SUCCESS" if info["success"] else "  FAILURE"
        frames.append(demo_frame(env, state, status))
    env.close()
    stem = writable_folder(out_dir) / f"demo-{task}-{scene}-{agent_name}"
    png, mp4 = stem.with_suffix(".png"), stem.with_suffix(".mp4")
    write_contact_sheet(png, frames)

    def write_video(tmp):
        h, w = frames[0].shape[:2]
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"),
                                 ObjectFindingEnv.metadata["render_fps"], (w, h))
        if not writer.isOpened():
            raise OSError("OpenCV could not open a video writer")
        for frame in frames:
            writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
        writer.release()
        video, read = cv2.VideoCapture(str(tmp)), 0     # read back: OpenCV reports no write error itself
        while video.read()[0]:
            read += 1
        if read != len(frames):
            raise OSError(f"the video holds {read} of its {len(frames)} frames (a full disk?)")
    replace_atomically(mp4, write_video)
    return png, mp4, info


# ================================================================================================
# Command line: train, eval and demo. Bad input ends with one line and exit status 2.
# ================================================================================================

class ArgumentParser(argparse.ArgumentParser):
    def error(self, message):
        sys.stderr.write(f"objfind: error: {message}\n")
        sys.exit(2)


MAX_SEED = 2 ** 32 - 1          # seeds torch and numpy alike; a scene's seed is seed + episode index
MAX_EPISODES = 1_000_000        # seed lists and jobs are made up front
MAX_WORKERS = 4 * (os.cpu_count() or 1)   # more processes only add memory (about 250 MB each)
MAX_STEPS = 10 ** 10            # train's --steps (tools/bench.py's steps per measurement too)


def whole_number_arg(minimum: int, maximum: int, meaning: str):
    """An argparse type: an integer in [minimum, maximum], or one line saying what the flag is."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if not minimum <= value <= maximum:
            raise argparse.ArgumentTypeError(f"{text!r}: {meaning} must be in [{minimum}, {maximum}]")
        return value
    return parse


seed_arg = whole_number_arg(0, MAX_SEED, "a seed")
episodes_arg = whole_number_arg(1, MAX_EPISODES, "the number of episodes")
workers_arg = whole_number_arg(1, MAX_WORKERS, "the number of worker processes (at most 4 per core)")
steps_arg = whole_number_arg(1, MAX_STEPS, "the number of steps")


def setting_arg(settings: type):
    """An argparse type: NAME=VALUE for one field of a settings class, of the field's type (a tuple as comma-
    separated numbers: sensor_error_scale=0,2); ranges are checked where the settings are made."""
    kinds = {field.name: field_kind(field) for field in dataclasses.fields(settings)}

    def parse(text: str) -> tuple:
        name, _, value = text.partition("=")
        if name not in kinds:
            raise argparse.ArgumentTypeError(f"{text!r} is not NAME=VALUE with NAME a {settings.__name__} field")
        try:
            typed = (tuple(float(v) for v in value.split(",")) if kinds[name] == "tuple" else parse_bool(value)
                     if kinds[name] == "bool" else int(value) if kinds[name] == "int" else float(value))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{value!r} is not a {kinds[name]}") from None
        return name, typed
    return parse


# What `train` runs without --steps and --set: env steps and PPOSettings per learned agent, two phases as one
# schedule (the entropy bonus held, then to a tenth); ap-large trains as ap, ip-real as ip (weights/README.md)
TRAIN_RECIPES = {"a3de": (1_200_000, dict(entropy_end_ratio=0.1, schedule_start_share=0.8, schedule_share=0.85)),
                 "i3de": (1_350_000, dict(entropy_end_ratio=0.1, schedule_share=0.25))}


def default_task(agent: str) -> str:
    """The task an agent runs on without --task: the interactive agents on ip, the rest on ap."""
    return "ip" if agent in ("ges", "i3de") else "ap"


def information_rule(args) -> dict:
    """Settings overrides of --target-size: {} for the rule of Table II, or the ablation's."""
    return {} if args.target_size == "known" else dict(target_size_known=False)


def agent_policy(args) -> dict | None:
    """The policy a learned agent plays (--weights, or its shipped file), read before any work; None for
    a baseline, which takes no --weights."""
    if args.weights is not None and args.agent not in LEARNED:
        raise UsageError(f"--weights is for the learned agents ({', '.join(LEARNED)}), not {args.agent}")
    return learned_policy(args.agent, args.task, args.weights) if args.agent in LEARNED else None


def cmd_demo(args) -> int:
    args.task = args.task or default_task(args.agent)
    args.scene = args.scene or "cubes"
    policy, out = agent_policy(args), writable_folder(Path(args.out))
    png, mp4, info = run_demo(args.agent, args.task, args.scene, args.seed, out, policy)
    outcome = "success" if info["success"] else "failure"
    print(f"{args.agent} on {args.task}/{args.scene} seed {args.seed}: {outcome} after {info['steps']} steps "
          f"(target seen {info['target_seen_fraction']:.2f}, explored {info['explored_fraction']:.2f})")
    print(f"wrote {png} and {mp4}")
    return 0


def print_summary(agent: str, task: str, scene: str, cell: dict, wall_s: float) -> None:
    fmt = lambda value, spec: "-" if np.isnan(value) else format(value, spec)   # a kind of scene not drawn
    print(f"{agent} on {task}/{scene}, {cell['episodes']} episodes: success {cell['success']:.1f} % "
          f"[{cell['success_lo']:.1f}, {cell['success_hi']:.1f}], steps {cell['steps']:.2f} +- "
          f"{cell['steps_half']:.2f} ({fmt(cell['steps_with_target'], '.2f')} with a target), "
          f"no-target success {fmt(cell['no_target_success'], '.1f')} % of {cell['no_target_episodes']}, "
          f"decision {cell['decision_ms']:.2f} ms/step; {wall_s:.0f} s")


def eval_table(args) -> int:
    """Every cell of Table II. A cell whose CSV in --out holds exactly these episodes, made by this agent,
    weights and rule, is read back, so an interrupted table loses nothing; any other CSV there is refused
    before an episode runs, never overwritten. table2.md is written only for a whole table."""
    given = [flag for flag in ("agent", "weights", "task", "scene") if getattr(args, flag)]
    if given:
        raise UsageError(f"--table runs every cell of Table II with the shipped weights: drop --{given[0]}")
    out = writable_folder(Path(args.out or "results"))
    seeds = list(range(args.seed, args.seed + args.episodes))
    suffix = "-size-unknown" if information_rule(args) else ""   # the ablation's files sit beside
    policies = {key: learned_policy(*key) for key in PAPER_TABLE_II if key[0] in LEARNED}   # each read once
    origins = {(agent, task, scene): cell_origin(agent, task, scene, policies.get((agent, task)),
                                                 information_rule(args))
               for (agent, task), scenes in PAPER_TABLE_II.items() for scene in scenes}
    stored = {cell: stored_cell(out / f"{'-'.join(cell)}{suffix}.csv", seeds, origins[cell]) for cell in origins}
    if args.ray and None in stored.values() and not args.from_csv:
        connect_ray(args.ray)
    cells, versions, t_table = {}, set(), time.perf_counter()
    for (agent, task, scene), rows in stored.items():
        csv_path, t_cell = out / f"{agent}-{task}-{scene}{suffix}.csv", time.perf_counter()
        if rows is None and args.from_csv:   # the cell is missing; the others go on
            print(f"{agent} on {task}/{scene}: - (not run yet: no {csv_path})")
            continue
        if rows is None:
            rows = evaluate(agent, task, scene, args.episodes, args.seed, args.workers,
                            policy=policies.get((agent, task)), overrides=information_rule(args),
                            ray_address=args.ray)
            write_csv(rows, csv_path)
        cells[(agent, task, scene)] = summarise(rows)
        versions.add(rows[0]["versions"])
        print_summary(agent, task, scene, cells[(agent, task, scene)], time.perf_counter() - t_cell)
    markdown, table = table_markdown(cells, args.episodes, versions), out / f"table2{suffix}.md"
    if len(cells) == len(stored):      # written before it is printed: a closed output loses nothing
        replace_atomically(table, lambda tmp: tmp.write_text(markdown + "\n"))
    print(markdown)
    print(f"wrote {table} and one CSV per cell in {out}" if len(cells) == len(stored) else
          f"{len(stored) - len(cells)} of {len(stored)} cells missing: {table} not written; the {len(cells)} "
          f"finished cells are in {out}")
    print(f"table: {time.perf_counter() - t_table:.0f} s")
    return 0


def cmd_eval(args) -> int:
    """One cell: its episodes, their summary and, with --out, their CSV, which never replaces the CSV of
    another experiment (a table's cell, another agent's, other seeds): the same checks as --table's."""
    if args.table:
        return eval_table(args)
    if args.agent is None:
        raise UsageError("eval needs --agent or --table")
    if args.from_csv:
        raise UsageError("--from-csv reads the cells of --table; a plain eval runs its episodes")
    args.task = args.task or default_task(args.agent)
    args.scene = args.scene or "cubes"
    policy = agent_policy(args)
    csv_path = Path(args.out) if args.out else None
    if csv_path is not None:           # a file (stored_cell refuses a folder), in a folder this run has locked
        writable_folder(csv_path.parent)
        origin = cell_origin(args.agent, args.task, args.scene, policy, information_rule(args))
        stored_cell(csv_path, list(range(args.seed, args.seed + args.episodes)), origin)
    if args.ray:
        connect_ray(args.ray)
    t0 = time.perf_counter()
    rows = evaluate(args.agent, args.task, args.scene, args.episodes, args.seed, args.workers, policy=policy,
                    overrides=information_rule(args), ray_address=args.ray)
    if csv_path:
        write_csv(rows, csv_path)      # before anything is printed: a closed output loses nothing
    print_summary(args.agent, args.task, args.scene, summarise(rows), time.perf_counter() - t0)
    if csv_path:
        print(f"wrote {csv_path}")
    return 0


def cmd_train(args) -> int:
    run = None
    if args.resume:
        if args.set or args.world or args.init or args.fresh_terminate or args.seed is not None or args.streams:
            raise UsageError("--set, --world, --seed, --streams, --init and --fresh-terminate start a new run; a "
                             "resumed run keeps its own")
        out = Path(args.out or Path("runs") / f"{args.task or 'ap'}-{args.scene or 'cubes'}")
        if not (out / "checkpoint.pt").exists():
            raise UsageError(f"--resume: no checkpoint in {str(out)!r}")
        run = read_checkpoint(out / "checkpoint.pt", run=True)
        for flag, default in (("task", "ap"), ("scene", "cubes")):   # a run goes on with what it trained on
            given, stored = getattr(args, flag), run.get(flag)
            if given is not None and stored is not None and given != stored:
                raise UsageError(f"--{flag} {given}: the run in {str(out)!r} trains on {flag} {stored}; "
                                 f"leave --{flag} out to continue it")
            setattr(args, flag, given or stored or default)
    else:
        args.task, args.scene = args.task or "ap", args.scene or "cubes"
        out = Path(args.out) if args.out else writable_folder(Path("runs"), False) / f"{args.task}-{args.scene}"
        if (out / "checkpoint.pt").exists():
            raise UsageError(f"{str(out)!r} already holds a run: add --resume to continue it, or pick another --out")
        if args.fresh_terminate and not args.init:
            raise UsageError("--fresh-terminate needs --init")
    world = run.get("world", {}) if run else dict(args.world or [])
    try:
        checked_settings(args.task, world)
    except ValueError as error:
        raise UsageError(f"--world: {error}") from None
    recipe_steps, recipe = TRAIN_RECIPES["i3de" if TASKS[args.task].num_piles else "a3de"]
    args.steps = args.steps or (run.get("schedule_steps", recipe_steps) if run else recipe_steps)
    ppo = ppo_settings({**recipe, **dict(args.set or [])})
    init = read_checkpoint(Path(args.init)) if args.init else None
    if args.ray:   # asked before any work: an address nobody answers is one line
        connect_ray(args.ray)
    writable_folder(out)
    meta = dict(task=args.task, scene=args.scene, **({"world": world} if world else {}))
    if init is not None:
        meta["init"] = (f"{Path(args.init).name} ({init.get('task', '?')}/{init.get('scene', '?')}, update "
                        f"{init.get('update', '?')}){', terminate reset' if args.fresh_terminate else ''}")
    resume = (f"python objfind.py train --resume --out {shlex.quote(str(out))} --steps {args.steps} "
              f"--workers {args.workers}")
    try:
        result = train(functools.partial(ObjectFindingEnv, args.task, args.scene, **world), out, args.steps,
                       ppo, workers=args.workers, seed=args.seed or 0,
                       resume=run, meta=meta, init=init, fresh_terminate=args.fresh_terminate,
                       streams=args.streams or DEFAULT_STREAMS, ray_address=args.ray)
    except TrainingInterrupted as stop:
        diverged = stop.cause.startswith("training diverged")
        kept = f"kept {stop} in {stop.path}" if stop.update else "nothing was kept"
        then = ("; a smaller learning_rate or reward_scale (--set) in a new run may help" if diverged else
                f"; resume with: {resume}" if stop.update else "")
        sys.stderr.write(f"objfind: {stop.cause}; {kept}{then}\n")
        return 130 if stop.cause == "interrupted" else 2
    print(f"trained {result['env_steps']} env steps in {result['update']} updates; "
          f"wrote {out / 'checkpoint.pt'}, {out / 'log.csv'} and {out / 'curve.png'}")
    return 0


def add_agent_args(command, default_agent: str | None) -> None:
    """The flags that pick what runs: agent, task, scene, weights (demo and eval)."""
    command.add_argument("--agent", choices=list(BASELINES) + list(LEARNED), default=default_agent,
                         help="random, scripted, the baselines gnbv and ges, or the learned a3de and i3de")
    command.add_argument("--task", choices=list(TASKS), help="Table I preset: ap (active), ap-large, ip (interactive, "
                         "piles), the real-world ap-real and ip-real; default ip for ges and i3de, ap otherwise")
    command.add_argument("--scene", choices=SCENES, help="scene kind (default cubes)")
    command.add_argument("--weights", help="a learned agent's checkpoint (default: weights/AGENT.pt, "
                         "AGENT-large.pt on ap-large)")


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="objfind.py", description=__doc__.split("\n\n")[0],
                            epilog="python objfind.py COMMAND --help lists a command's flags.")
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser("demo", help="one episode to a PNG contact sheet and an MP4")
    add_agent_args(demo, "a3de")
    demo.add_argument("--seed", type=seed_arg, default=0, help="the scene's seed (default 0)")
    demo.add_argument("--out", default="out", help="output folder for demo-TASK-SCENE-AGENT.png and .mp4 "
                      "(default out; its parent must exist)")
    demo.set_defaults(func=cmd_demo)
    training = commands.add_parser("train", help="train A3DE (ap) or I3DE (ip) with PPO; resumable")
    training.add_argument("--task", choices=list(TASKS),
                          help="ap trains A3DE, ip trains I3DE (default ap; with --resume, the run's own)")
    training.add_argument("--scene", choices=SCENES,
                          help="scene kind to train on (default cubes; with --resume, the run's own)")
    training.add_argument("--workers", type=workers_arg, default=os.cpu_count() or 1,
                          help="env worker processes serving the run's rollout streams (default all cores); "
                               "the weights do not depend on it")
    training.add_argument("--streams", type=whole_number_arg(1, MAX_STREAMS, "the number of rollout streams"),
                          help=f"rollout streams a new run splits each PPO batch into (default {DEFAULT_STREAMS}); "
                               "kept in the checkpoint, so the run repeats exactly on any number of processes")
    training.add_argument("--steps", type=steps_arg,
                          help="env steps in all, counting those of a resumed run (default: the task's recipe, "
                               "TRAIN_RECIPES; with --resume, the run's own)")
    training.add_argument("--seed", type=seed_arg,
                          help="seeds the network, and each update's env resets and samples (default 0)")
    training.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                          help="serve the rollout streams with --workers Ray actors: on the cluster at ADDRESS, "
                               "else at $RAY_ADDRESS, else on a Ray instance started here (README: Speed)")
    training.add_argument("--out", help="run folder: checkpoint.pt, log.csv, curve.png (default runs/TASK-SCENE)")
    training.add_argument("--resume", action="store_true",
                          help="continue the run in --out from its checkpoint, with the settings it started with")
    training.add_argument("--set", type=setting_arg(PPOSettings), action="append", metavar="NAME=VALUE",
                          help="change a PPOSettings field of the task's recipe (TRAIN_RECIPES) for a new run "
                               "(repeatable), e.g. entropy_coef=0.003")
    training.add_argument("--world", type=setting_arg(Settings), action="append", metavar="NAME=VALUE",
                          help="change a Settings field of the training world for a new run (repeatable), e.g. "
                               "tof_noise_ratio=0.01 or sensor_error_scale=0,2 (weights/README.md)")
    training.add_argument("--init", help="warm-start a new run from this checkpoint's policy (I3DE from A3DE)")
    training.add_argument("--fresh-terminate", action="store_true",
                          help="with --init: keep the moves and the critic, learn when to terminate afresh")
    training.set_defaults(func=cmd_train)
    evaluation = commands.add_parser("eval", help="paired evaluation episodes, or the whole Table II")
    add_agent_args(evaluation, None)
    evaluation.add_argument("--table", action="store_true",
                            help="every cell of Table II beside the paper: one CSV per cell in --out and "
                                 "table2.md; a cell whose CSV holds these seeds is read back, not run again")
    evaluation.add_argument("--episodes", type=episodes_arg, default=100, help="episodes per cell (default 100)")
    evaluation.add_argument("--workers", type=workers_arg, default=os.cpu_count() or 1,
                            help="worker processes (default all cores); results do not depend on it")
    evaluation.add_argument("--seed", type=seed_arg, default=0,
                            help="episode i uses scene seed + i for every agent, so agents meet the same scenes")
    evaluation.add_argument("--from-csv", action="store_true",
                            help="with --table: only read cells already run, print '-' for the others")
    evaluation.add_argument("--target-size", choices=("known", "unknown"), default="known",
                            help="the information rule: every agent is told its target's size (known, Table II), "
                                 "or no agent is (unknown: the ablation; use another --out for its table)")
    evaluation.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                            help="run the episodes as Ray tasks on every CPU of the cluster at ADDRESS, else at "
                                 "$RAY_ADDRESS, else of a Ray instance started here (--workers is then unused)")
    evaluation.add_argument("--out", help="CSV of every episode (with --table: a folder, default results)")
    evaluation.set_defaults(func=cmd_eval)
    return parser


def run_cli(parser: ArgumentParser, argv: list[str] | None = None) -> int:
    """Parse and run a command (objfind's or a tool's): bad input is one line and exit 2, Ctrl-C or SIGTERM
    exit 130 keeping what finished, and the output folders' locks are released."""
    args = parser.parse_args(argv)
    if getattr(args, "episodes", None) and args.seed + args.episodes - 1 > MAX_SEED:
        parser.error(f"--seed {args.seed} with --episodes {args.episodes} goes past the largest seed, {MAX_SEED}")
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, stop_as_ctrl_c)
    try:
        return args.func(args)
    except UsageError as error:
        sys.stderr.write(f"objfind: error: {error}\n")
        return 2
    except KeyboardInterrupt:
        table = getattr(args, "table", False)
        sys.stderr.write(f"objfind: interrupted{' (each finished cell is kept: the same command goes on)' * table}\n")
        return 130
    except BrokenPipeError:   # the reader went away (| head): results are already written; say nothing more
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    finally:
        release_locks()


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv)


if __name__ == "__main__":
    if any(arg == "--ray" or arg.startswith("--ray=") for arg in sys.argv[1:]):
        # Ray's workers find functions by module name: run the command in `objfind`, not in __main__
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        sys.exit(importlib.import_module("objfind").main())
    sys.exit(main())
