"""Tests for objfind: each asserts a behaviour that a wrong implementation would break."""
import dataclasses
import functools
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import gymnasium as gym
import numpy as np
import pytest

import objfind as of
from tools import bench, moves, sensors, soak, stops
from tools import replay as replay_tool

torch = of.torch   # imported by objfind after it limits BLAS threads

HERE = Path(__file__).resolve().parent

# ------------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------------


def small_volume(max_weight=2.0):
    """The `ap` volume: 0.6 m wide, 0.3 m high, 6 mm voxels."""
    return of.TSDFVolume(dataclasses.replace(of.TASKS["ap"], max_weight=max_weight))


def looking_down(height_m, xy=(0.0, 0.0)):
    """T_world_camera of a camera at `height_m` looking straight down (OpenCV axes)."""
    T = np.eye(4)
    T[:3, :3] = of.gripper_rotation(0.0, 0.0)
    T[:3, 3] = [xy[0], xy[1], height_m]
    return T


K = of.wrist_rig(of.TASKS["ap"]).depth.K


def plane_view(volume, plane_z, detection=0.0, camera_z=0.3, times=1):
    """Integrate a view of a horizontal plane at plane_z (depth is constant for a downward camera)."""
    depth = np.full((60, 80), camera_z - plane_z, np.float32)
    detections = np.full((60, 80), detection, np.float32)
    for _ in range(times):
        volume.integrate(depth, detections, K, looking_down(camera_z))


def column(volume, values, xy=(0.0, 0.0)):
    """The volume's values along z at the column containing world point xy."""
    i, j = (int((c - o) / volume.voxel_m) for c, o in zip(xy, volume.origin[:2]))
    return values[i, j]


def z_of(volume, k):
    return (k + 0.5) * volume.voxel_m


def zero_crossing(volume):
    """Height of the sign change from negative (below) to positive (above) in the centre column."""
    t, w = column(volume, volume.tsdf), column(volume, volume.weight)
    ks = [k for k in range(len(t) - 1) if w[k] > 0 and w[k + 1] > 0 and t[k] < 0 <= t[k + 1]]
    assert len(ks) == 1, t
    k = ks[0]
    return z_of(volume, k) + (z_of(volume, k + 1) - z_of(volume, k)) * (-t[k]) / (t[k + 1] - t[k])


# ------------------------------------------------------------------------------------------------
# settings
# ------------------------------------------------------------------------------------------------


def test_presets_follow_table_one():
    ap, large, ip = of.TASKS["ap"], of.TASKS["ap-large"], of.TASKS["ip"]
    assert (ap.min_objects, ap.max_objects, ap.num_piles, ap.workspace_m, ap.horizon) == (5, 25, 0, 0.6, 130)
    assert (large.min_objects, large.max_objects, large.workspace_m, large.horizon) == (10, 40, 1.2, 500)
    assert (ip.min_objects, ip.max_objects, ip.num_piles, ip.exploration_ratio) == (15, 75, 3, 0.25)
    real_ap, real_ip = of.TASKS["ap-real"], of.TASKS["ip-real"]
    assert (real_ip.num_piles, real_ip.exploration_ratio, real_ap.num_piles) == (4, 0.1, 0)
    for name, s in of.TASKS.items():
        paper = (s.no_target_prob, s.trunc_m, s.max_weight, s.max_step_m, s.max_turn_rad, s.detection_reward)
        assert paper == (0.0 if name.endswith("-real") else 0.1, 0.04, 2, 0.06, 0.15, 150)
    with pytest.raises(dataclasses.FrozenInstanceError):
        ap.horizon = 10


# ------------------------------------------------------------------------------------------------
# perception
# ------------------------------------------------------------------------------------------------


def test_detector_finds_red_under_any_shading_and_nothing_else():
    image = np.zeros((40, 10 * (1 + len(of.OTHER_RGBA)), 3), np.uint8)
    for i, rgba in enumerate((of.TARGET_RGBA,) + of.OTHER_RGBA):
        for row, shade in enumerate(np.linspace(0.35, 1.0, 4)):   # lit to shadowed faces
            colour = (np.array(rgba[:3]) * shade * 255).astype(np.uint8)
            image[10 * row:10 * row + 10, 10 * i:10 * i + 10] = colour
    detections = of.detect_target(image)
    assert detections.dtype == np.float32 and detections.shape == image.shape[:2]
    assert detections[:, :10].min() == 1.0
    assert detections[:, 10:].max() == 0.0


def test_detector_noise_follows_the_paper():
    s = of.TASKS["ap"]
    truth = np.zeros((200, 200), np.float32)
    truth[:100] = 1.0
    noisy = of.add_detector_noise(truth, np.random.default_rng(0), s)
    true_part, false_part = noisy[:100], noisy[100:]
    assert abs(float(1.0 - true_part.mean()) - 1 / s.noise_rate) < 0.005      # Exp(20) has mean 0.05
    assert abs(np.count_nonzero(false_part) / false_part.size - s.false_positive_share) < 0.005
    assert abs(float(false_part[false_part > 0].mean()) - 1 / s.noise_rate) < 0.01
    again = of.add_detector_noise(truth, np.random.default_rng(0), s)
    assert np.array_equal(noisy, again)


# ------------------------------------------------------------------------------------------------
# volume
# ------------------------------------------------------------------------------------------------


def test_tsdf_of_a_plane_at_a_known_depth():
    volume = small_volume()
    plane_view(volume, plane_z=0.1)
    assert abs(zero_crossing(volume) - 0.1) < volume.voxel_m
    t, w = column(volume, volume.tsdf), column(volume, volume.weight)
    ks = np.arange(len(t))
    in_front = (z_of(volume, ks) > 0.1 + 0.04) & (z_of(volume, ks) < 0.25)   # the top is outside the frustum
    assert np.all(w[in_front] > 0) and np.allclose(t[in_front], 1.0)       # free space, truncated
    behind = z_of(volume, ks) < 0.1 - 0.04 - volume.voxel_m
    assert np.all(w[behind] == 0) and np.all(t[behind] == 0)                # never seen
    band = np.abs(z_of(volume, ks) - 0.1) < 0.04 - volume.voxel_m
    assert np.all(np.abs(t[band]) < 1.0)
    assert 0 < volume.explored_fraction() < 1
    assert volume.observed_count == np.count_nonzero((volume.weight > 0))


def reference_fusion(volume, depth_m, detections, K, T_world_camera):
    """TSDF fusion as whole-volume numpy, no culling, with fuse_view's arithmetic: what it must equal."""
    P, t = (K @ T_world_camera[:3, :3].T).astype(np.float32), T_world_camera[:3, 3].astype(np.float32)
    terms = [P[:, [axis]] * (volume.axes[axis] - t[axis]) for axis in range(3)]   # float64, (3, n) each
    u_z, v_z, z = ((terms[0][r][:, None, None] + terms[1][r][None, :, None]) + terms[2][r][None, None, :]
                   for r in range(3))
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = u_z / z, v_z / z
    H, W = depth_m.shape
    valid = (z > of.MIN_PROJECTION_Z_M) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    pixel = np.where(valid, v, 0).astype(np.int64) * W + np.where(valid, u, 0).astype(np.int64)
    depth = depth_m.reshape(-1)[pixel]
    sdf = depth - z
    seen = valid & (depth > 0) & (sdf >= -volume.trunc_m)
    w_old = volume.weight[seen]
    volume.observed_count += int(np.count_nonzero(w_old == 0))
    seen[seen] = ~((sdf[seen] >= volume.trunc_m) & (w_old == volume.max_weight) & (volume.tsdf[seen] == 1))
    sdf, pixel, w_old = sdf[seen], pixel[seen], volume.weight[seen]
    w_sum = w_old + np.float32(1)
    volume.tsdf[seen] = (volume.tsdf[seen] * w_old + np.minimum(1.0, sdf * (1.0 / volume.trunc_m))) / w_sum
    detection = (volume.detections[seen] * w_old
                 + detections.reshape(-1)[pixel] * np.maximum(0.0, 1.0 - np.abs(sdf) / volume.trunc_m)) / w_sum
    volume.detections[seen] = np.where(sdf >= volume.trunc_m, 0.0, detection)
    volume.weight[seen] = np.minimum(w_sum, volume.max_weight)


@pytest.mark.parametrize("task", ["ap", "ip-real"])
def test_compiled_fusion_equals_whole_volume_numpy_fusion(task):
    """fuse_view skips columns and layers outside the frustum; over an episode's tilted, near and far views
    its volume must equal, bit for bit, one fused by projecting every voxel."""
    env = of.ObjectFindingEnv(task, "cubes" if task == "ap" else "cubes-and-cuboids")
    env.reset(seed=3)
    fused, reference = of.TSDFVolume(env.cfg), of.TSDFVolume(env.cfg)
    K, rng = env.searcher.rig.depth.K, np.random.default_rng(5)
    for action in bench.exploring_actions(np.random.default_rng(4), 12):
        view = env.view
        scores = rng.random(view.depth_m.shape).astype(np.float32)   # scores everywhere: every band is averaged
        fused.integrate(view.depth_m, scores, K, view.T_world_camera)
        reference_fusion(reference, view.depth_m, scores, K, view.T_world_camera)
        for name in ("tsdf", "weight", "detections"):
            assert np.array_equal(getattr(fused, name), getattr(reference, name)), name
        assert fused.observed_count == reference.observed_count > 0
        env.step(action)
    env.close()


def test_integration_only_touches_the_frustum():
    volume = small_volume()
    plane_view(volume, plane_z=0.0, camera_z=0.1)   # a low camera sees a small patch of floor
    observed = (volume.weight > 0)
    assert observed[50, 50].any()
    assert not observed[:10].any() and not observed[-10:].any()


def test_detection_is_integrated_then_carved_away_in_free_space():
    volume = small_volume()
    plane_view(volume, plane_z=0.1, detection=1.0)
    d = column(volume, volume.detections)
    k_surface = int(0.1 / volume.voxel_m)
    assert d[k_surface] > 0.8 and d[k_surface + 10] == 0.0     # unsigned distance: peak at the surface
    plane_view(volume, plane_z=0.0, detection=0.0)             # the object is gone: its voxels are free
    assert np.all(column(volume, volume.detections)[k_surface - 2:k_surface + 3] == 0.0)
    assert volume.seen_target_area_m2() == 0.0


def test_max_weight_two_forgets_a_removed_object_after_two_views():
    for max_weight, forgotten in ((2.0, True), (50.0, False)):
        volume = small_volume(max_weight)
        plane_view(volume, plane_z=0.1, times=10)               # the object, seen for a long time
        plane_view(volume, plane_z=0.0, times=2)                # removed: two new views of the floor
        t = column(volume, volume.tsdf)
        k_old = int(0.1 / volume.voxel_m) - 3                   # inside the removed object
        assert (t[k_old] > 0) == forgotten
        assert column(volume, volume.weight).max() <= max_weight


def test_a_surface_that_moved_within_the_truncation_band_settles_at_its_new_depth():
    volume = small_volume()
    plane_view(volume, plane_z=0.1, times=5)
    plane_view(volume, plane_z=0.07, times=6)       # weight 2: old values fade by 2/3 per view
    assert abs(zero_crossing(volume) - 0.07) < volume.voxel_m


# ------------------------------------------------------------------------------------------------
# encoder
# ------------------------------------------------------------------------------------------------


def put(volume, values, xy, z, value):
    i, j = (int((c - o) / volume.voxel_m) for c, o in zip(xy, volume.origin[:2]))
    values[i, j, int(z / volume.voxel_m)] = value
    volume.weight[i, j, int(z / volume.voxel_m)] = 1.0


def bin_at(ahead_m: float, left_m: float, crop_m: float = 1.2) -> int:
    """The bin of a column ahead of and left of the gripper, as the encoder defines it."""
    return int(of.column_bins(np.array([ahead_m]), np.array([left_m]), crop_m)[0])


def in_state(map_name: str, ahead_m: float, left_m: float) -> int:
    """The index in the state of a map's bin of a column."""
    return of.BINS * of.MAP_NAMES.index(map_name) + bin_at(ahead_m, left_m)


def test_the_71_values_of_a_hand_built_volume():
    volume = small_volume()
    ee, finger_z = np.array([0.0, 0.0, 0.15]), 0.15
    put(volume, volume.tsdf, (0.25, 0.0), 0.05, 1.0)     # 0.25 m ahead, below the fingers: outer front cell
    put(volume, volume.tsdf, (-0.25, 0.0), 0.20, 1.0)    # behind, above the fingers: outer back cell
    put(volume, volume.tsdf, (-0.25, 0.0), 0.25, 1.0)
    put(volume, volume.tsdf, (0.0, 0.0), 0.05, -1.0)     # under the gripper: the inner centre cell
    put(volume, volume.detections, (0.0, 0.1), 0.05, 0.8)   # to the left, below: inner left cell
    state = of.encode_state(volume, ee, 0.0, 0.3, finger_z, 1.2, 0.37)
    assert of.STATE_SIZE == 71 and state.shape == (of.STATE_SIZE,)   # Fig. 2
    expected = np.zeros(of.STATE_SIZE, np.float32)
    tsdf_sum = 1.0 + 2.0 - 1.0
    expected[in_state("TSDF above", -0.25, 0.0)] = 2.0 / tsdf_sum
    expected[in_state("TSDF below", 0.25, 0.0)] = 1.0 / tsdf_sum
    expected[in_state("TSDF below", 0.0, 0.0)] = -1.0 / tsdf_sum
    expected[in_state("detections below", 0.0, 0.1)] = 1.0
    expected[of.STATE_TSDF_SUM] = tsdf_sum / volume.tsdf.size
    expected[of.STATE_TARGET_SHARE] = 0.37   # the perceived share, as the searcher hands it over
    expected[of.STATE_ROLL] = 0.3
    np.testing.assert_allclose(state, expected, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("yaw", [0.0, 0.7, 2.5, -1.9])
def test_a_detection_to_the_gripper_left_lands_in_a_left_bin_whatever_the_yaw(yaw):
    volume = small_volume()
    ee = np.array([0.02, -0.01, 0.2])
    below = of.BINS * of.MAP_NAMES.index("detections below")
    for forward, left in ((0.0, 0.1), (0.0, -0.1), (0.1, 0.0), (0.0, 0.25)):
        volume.detections[:] = 0
        xy = ee[:2] + of.rotation(yaw, "z")[:2, :2] @ [forward, left]
        put(volume, volume.detections, xy, 0.05, 1.0)
        state = of.encode_state(volume, ee, yaw, 0.0, 0.2, 1.2, 0.0)
        bin_index = bin_at(forward, left)
        assert np.argmax(state[below:below + of.BINS]) == bin_index and state[below + bin_index] == 1.0


def test_bins_partition_the_crop_into_a_three_by_three_grid_whose_middle_is_split_again():
    u, v = np.meshgrid(np.linspace(-0.8, 0.8, 161), np.linspace(-0.8, 0.8, 161))
    bins = of.column_bins(u.ravel(), v.ravel(), 1.2)
    inside = (np.abs(u.ravel()) < 0.6) & (np.abs(v.ravel()) < 0.6)
    assert set(bins[inside]) == set(range(of.BINS)) and set(bins[~inside]) == {of.BINS}
    cells = (np.arange(90) + 0.5) / 90 * 1.2 - 0.6                     # a fine grid over the crop
    area = np.bincount(of.column_bins(*np.meshgrid(cells, cells), 1.2).ravel(), minlength=of.BINS) / 90 ** 2
    assert sorted(np.round(area * 81).astype(int)) == [1] * 9 + [9] * 8   # 9 inner ninths, 8 outer cells
    assert bin_at(0.0, 0.1) != bin_at(0.0, -0.1) and bin_at(0.3, 0.0) != bin_at(-0.3, 0.0)


def test_the_demos_bins_panel_draws_the_encoders_bins(monkeypatch):
    state = np.zeros(of.STATE_SIZE, np.float32)
    state[in_state("TSDF below", 0.0, 0.1)] = 1.0                    # the inner cell to the left
    drawn = lambda: np.argwhere((of.bins_panel(state) == 25).all(axis=2)).mean(axis=0)   # the darkest cell's centre
    left = drawn()
    column_bins = of.column_bins
    monkeypatch.setattr(of, "column_bins", lambda u, v, crop_m: column_bins(u, -v, crop_m))   # left and right swapped
    right = drawn()
    assert right[1] > left[1] + 15 and abs(right[0] - left[0]) < 2     # the panel follows: now to the right


def test_pooling_the_columns_gives_numpys_bincount_sums_bit_for_bit():
    """The state of world 6 was pooled by np.bincount, which adds in column order: so must pool_columns."""
    rng = np.random.default_rng(0)
    maps = (rng.normal(size=(of.MAPS, 5000)) * rng.random((of.MAPS, 5000)) ** 8).astype(np.float32)
    bins = rng.integers(0, of.BINS + 1, 5000)
    index = (bins[None, :] + (of.BINS + 1) * np.arange(of.MAPS)[:, None]).reshape(-1)
    expected = np.bincount(index, weights=maps.reshape(-1), minlength=of.MAPS * (of.BINS + 1))
    assert np.array_equal(of.pool_columns(maps, bins), expected.reshape(of.MAPS, of.BINS + 1)[:, :of.BINS])


# ------------------------------------------------------------------------------------------------
# simulation
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ap_env():
    env = of.ObjectFindingEnv("ap", "cubes")
    yield env
    env.close()


def seed_with(env, **wanted):
    """The first seed whose scene has the wanted info values (e.g. target_present=False)."""
    for seed in range(200):
        obs, info = env.reset(seed=seed)
        if all(info[k] == v for k, v in wanted.items()):
            return seed, obs, info
    raise AssertionError(f"no seed with {wanted}")


@pytest.mark.filterwarnings("ignore:.*Box observation space.*infinity")
def test_env_follows_the_gymnasium_api(ap_env):
    from gymnasium.utils.env_checker import check_env
    check_env(ap_env, skip_render_check=True)
    assert ap_env.action_space == gym.spaces.Box(-1, 1, (6,), np.float32)
    assert ap_env.observation_space.shape == (of.STATE_SIZE,)


@pytest.mark.parametrize("gym_id, task", sorted(of.GYM_IDS.items()))
def test_registered_ids_make_the_same_env_as_the_constructor(gym_id, task):
    from gymnasium.utils.env_checker import check_env
    made = gym.make(gym_id, scene="fixed-primitives")
    direct = of.ObjectFindingEnv(task, "fixed-primitives")
    try:
        assert made.unwrapped.task == task and made.unwrapped.scene == "fixed-primitives"
        obs_made, _ = made.reset(seed=11)
        obs_direct, _ = direct.reset(seed=11)
        assert np.array_equal(obs_made, obs_direct)
        action = np.array([0.5, -0.5, 1.0, 0.2, 0.3, -1.0], np.float32)
        assert np.array_equal(made.step(action)[0], direct.step(action)[0])
        check_env(made.unwrapped, skip_render_check=True)
    finally:
        made.close(), direct.close()


def scene_positions(s, seed=4):
    """(n, 3) resting positions of a cubes scene drawn with settings `s` in a fresh world."""
    sim = of.PhysicsClient()
    try:
        sim.setGravity(0, 0, -9.81)
        sim.setPhysicsEngineParameter(fixedTimeStep=1.0 / s.physics_hz, numSolverIterations=s.solver_iterations)
        of.build_workspace(sim, s)
        scene = of.build_scene(sim, s, "cubes", np.random.default_rng(seed))
        assert scene.heaped == (s.num_piles > 0) and len(scene.objects) >= 10
        return np.array([sim.getBasePositionAndOrientation(o.body)[0] for o in scene.objects])
    finally:
        sim.disconnect()


def test_every_scene_setting_changes_the_scene():
    """A student who edits a Settings field sees the scene change: no hidden copy of it in the builder."""
    piles = dict(num_piles=2, pile_margin_ratio=0.3, pile_min_apart_ratio=0.1, pile_layers=5, pile_spacing_ratio=1.2, pile_layer_cost=2.0,
                 pile_spot_noise=0.5, pile_jitter_ratio=0.3, pile_layer_gap_m=0.03, drop_gap_m=0.02,
                 settle_pile_s=0.15, settle_speed=0.5, object_size_m=0.05, object_mass_kg=0.3,
                 object_friction=0.2, wall_height_m=0.3)
    scattered = dict(scatter_gap_m=0.05, settle_scatter_s=0.02, object_size_m=0.05)   # on a floor so small that
    unchanged = []                                                                    # some cubes find no room
    for s, changes in ((of.TASKS["ip"], piles), (of.TASKS["ap-real"], scattered)):
        base = scene_positions(s)
        assert np.array_equal(base, scene_positions(s))          # the same settings: the same scene
        unchanged += [name for name, value in changes.items()
                      if np.array_equal(base, scene_positions(dataclasses.replace(s, **{name: value})))]
    assert not unchanged


def episode_digest(env, seed: int, steps: int = 15) -> str:
    """Hex digest of an episode's states and every object's pose after its reset and after exploring steps."""
    digest = of.hashlib.sha256()
    state, _ = env.reset(seed=seed)
    poses = [env.sim.getBasePositionAndOrientation(o.body) for o in env.objects]
    digest.update(state.tobytes() + np.array([p + q for p, q in poses]).tobytes())
    for action in bench.exploring_actions(np.random.default_rng(seed), steps):
        state, _, done, _, _ = env.step(action)
        digest.update(state.tobytes())
        if done:
            break
    poses = [env.sim.getBasePositionAndOrientation(o.body) for o in env.objects]
    return digest.hexdigest() + of.hashlib.sha256(np.array([p + q for p, q in poses]).tobytes()).hexdigest()


@pytest.mark.parametrize("task, scene, before, seed", [("ap", "variable-primitives", 2, 0), ("ap", "variable-primitives", 3, 1),
                                                       ("ip", "cubes", 3, 0), ("ip", "object-models", 1, 2)])
def test_an_episode_does_not_depend_on_the_episode_played_before_it(task, scene, before, seed):
    """An env that played another episode first gives the episode a fresh env gives with that seed, pushes
    included. A Bullet world kept across resets fails the first three: its broadphase state orders contacts."""
    env = of.ObjectFindingEnv(task, scene)
    try:
        episode_digest(env, before)
        played = episode_digest(env, seed)
    finally:
        env.close()
    fresh = of.ObjectFindingEnv(task, scene)
    try:
        assert episode_digest(fresh, seed) == played
    finally:
        fresh.close()


def test_same_seed_same_scene_and_state_different_seed_different(ap_env):
    def snapshot(seed):
        obs, info = ap_env.reset(seed=seed)
        poses = [ap_env.sim.getBasePositionAndOrientation(o.body)[0] for o in ap_env.objects]
        return obs, np.array(poses), ap_env.gripper_pose()

    a, b, c = snapshot(7), snapshot(7), snapshot(8)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2])
    assert not np.array_equal(a[0], c[0])
    assert a[1].shape != c[1].shape or not np.allclose(a[1], c[1])


def test_rewards_of_each_termination_kind(ap_env):
    s = ap_env.cfg
    terminate, stay = np.array([0, 0, 0, 0, 0, 1.0]), np.array([0, 0, 0, 0, 0, -1.0])
    seed, *_ = seed_with(ap_env, target_present=True, target_observed=False)
    _, reward, done, truncated, info = ap_env.step(terminate)        # claims too early
    assert (reward, done, truncated, info["success"]) == (-1 - 150, True, False, False)
    ap_env.reset(seed=seed)
    ap_env.target_seen[:] = True                                       # as if the target had been seen
    _, reward, done, _, info = ap_env.step(terminate)
    assert (reward, done, info["success"]) == (-s.time_penalty + s.detection_reward, True, True)
    seed_with(ap_env, target_present=False)
    _, reward, done, _, info = ap_env.step(terminate)                 # "there is no target": right
    assert (reward, done, info["success"]) == (-s.time_penalty + s.detection_reward, True, True)
    ap_env.reset(seed=seed)
    ap_env.cfg = dataclasses.replace(s, horizon=3)
    try:
        rewards = [ap_env.step(stay)[1] for _ in range(2)]
        _, reward, done, truncated, info = ap_env.step(stay)
    finally:
        ap_env.cfg = s
    assert rewards == [-s.time_penalty] * 2                           # no motion, nothing new seen
    assert (reward, done, truncated, info["success"]) == (-1 - 150, True, False, False)


def test_exploration_reward_is_positive_and_never_exceeds_the_time_penalty(ap_env):
    ap_env.reset(seed=3)
    rewards = [ap_env.step(np.array([0.0, 0.0, 1.0, 0.5, 1.0, -1.0]))[1] for _ in range(4)]
    assert all(-1.0 <= r <= 0.0 for r in rewards)
    assert max(rewards) > -1.0


def test_the_gripper_stays_in_the_workspace_and_never_passes_a_wall(ap_env):
    s = ap_env.cfg
    half = s.workspace_m / 2
    ap_env.reset(seed=0)
    ap_env._teleport(np.array([0.2, 0.0, 0.05]), of.gripper_rotation(0.0, 0.0))
    for _ in range(6):                                    # low, straight into the +x wall (body 2)
        ap_env.step(np.array([1.0, 0, -0.3, 0, 0, -1]))
        lo, hi = ap_env.sim.getAABB(ap_env.gripper)
        assert hi[0] < half + s.wall_thickness_m / 2      # the wall's inner face is at x = half
        into_wall = [c[8] for c in ap_env.sim.getContactPoints(ap_env.gripper) if c[2] == 2]
        assert min(into_wall, default=0.0) > -0.002       # pushed against it, at most 2 mm in
    for _ in range(8):                                    # up and out over the -y wall
        ap_env.step(np.array([0.0, -1.0, 1.0, 0, 1.0, -1]))
    for _ in range(8):                                    # down into the floor
        ap_env.step(np.array([0.0, 0.0, -1.0, 0, 0, -1]))
    T = ap_env.gripper_pose()
    assert np.all(np.abs(T[:2, 3]) <= half + 0.001) and -0.002 < T[2, 3] <= s.ceiling_m + 0.001


def test_yaw_and_roll_round_trip():
    for yaw, roll in ((0.3, -0.4), (-2.9, 0.9), (1.2, 0.0)):
        assert np.allclose(of.yaw_roll_of(of.gripper_rotation(yaw, roll)), (yaw, roll))
        R = of.gripper_rotation(yaw, roll)
        q = of.quat_of(R)
        assert np.allclose(np.array(of.pb.getMatrixFromQuaternion(q)).reshape(3, 3), R, atol=1e-6)


def test_rendered_depth_matches_the_camera_model(ap_env):
    """A cube straight below the camera: its top face at the expected depth and pixel."""
    ap_env.reset(seed=3)
    target = ap_env.objects[0]
    pos, _ = ap_env.sim.getBasePositionAndOrientation(target.body)
    T_camera = looking_down(pos[2] + 0.25, pos[:2])
    rgb, depth = of.render_rgbd(ap_env.sim, T_camera, of.Camera(80, 60, K, 0.01, 1.2))
    top = 0.25 - of.Settings.object_size_m / 2
    assert abs(depth[30, 40] - top) < 0.003
    red = of.detect_target(rgb) if ap_env.target_present else None
    if red is not None:
        ys, xs = np.nonzero(red)
        assert abs(xs.mean() - 40) < 1.5 and abs(ys.mean() - 30) < 1.5


def test_target_seen_counts_only_points_that_face_the_camera(ap_env):
    seed, *_ = seed_with(ap_env, target_present=True)
    pos, _ = ap_env.sim.getBasePositionAndOrientation(ap_env.objects[0].body)
    ap_env._teleport(np.array(pos) + [0, 0, 0.2], of.gripper_rotation(0.0, 0.0))
    ap_env.target_seen[:] = False
    ap_env._observe()
    top_only = ap_env.target_seen.mean()
    assert 0.1 < top_only < ap_env.cfg.seen_threshold       # the top face of a cube is a sixth of it
    ap_env._teleport(np.array(pos) + [0.12, 0.0, 0.15], of.gripper_rotation(0.0, 0.0))
    ap_env._observe()                                      # off to the side: a second face appears
    assert ap_env.target_seen.mean() > top_only + 0.03


def test_target_seen_follows_the_target_when_it_moves(ap_env):
    # The seen points live on the target: turn it upside down and the same view shows a new face.
    seed, *_ = seed_with(ap_env, target_present=True)
    body = ap_env.objects[0].body
    pos, orn = ap_env.sim.getBasePositionAndOrientation(body)
    ap_env._teleport(np.array(pos) + [0, 0, 0.2], of.gripper_rotation(0.0, 0.0))
    ap_env.target_seen[:] = False
    ap_env._observe()
    top_only = ap_env.target_seen.mean()
    ap_env._observe()
    assert ap_env.target_seen.mean() == top_only                # the same face again adds nothing
    flipped = ap_env.sim.multiplyTransforms([0, 0, 0], [1, 0, 0, 0], [0, 0, 0], orn)[1]   # 180 deg about x
    ap_env.sim.resetBasePositionAndOrientation(body, pos, flipped)
    ap_env._observe()
    assert ap_env.target_seen.mean() > 1.8 * top_only           # the old bottom face is new


def test_the_outside_view_paints_the_gripper_where_it_is_and_only_where_nothing_is_in_front():
    K = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])
    T_tool = np.eye(4)
    T_tool[:3, 3] = [0.1, 0.0, 0.5]                       # 0.5 m ahead of the camera, 0.1 m to its right
    rgb, empty = np.full((120, 160, 3), 255, np.uint8), np.zeros((120, 160), np.float32)
    painted = np.any(of.paint_gripper(rgb, empty, np.eye(4), K, T_tool) != 255, axis=2)
    v, u = np.nonzero(painted)
    assert painted.sum() > 100 and abs(u.mean() - (80 + 100 * 0.1 / 0.45)) < 6 and abs(v.mean() - 60) < 6
    wall = np.full_like(empty, 0.3)                       # a surface in front of the whole gripper
    assert (of.paint_gripper(rgb, wall, np.eye(4), K, T_tool) == 255).all()
    behind = T_tool.copy()
    behind[2, 3] = -0.5                                   # behind the camera: nothing to paint
    assert (of.paint_gripper(rgb, empty, np.eye(4), K, behind) == 255).all()


@pytest.mark.parametrize("scene", of.SCENES)
def test_every_scene_kind_builds_and_only_the_target_is_red(scene):
    env = of.ObjectFindingEnv("ap", scene)
    try:
        seed_with(env, target_present=False)
        assert 5 <= len(env.objects) <= 25
        assert of.detect_target(of.outside_view(env)).sum() == 0
        seed, obs, info = seed_with(env, target_present=True)
        assert of.detect_target(of.outside_view(env)).sum() > 0
        assert obs.shape == (71,) and np.all(np.isfinite(obs))
        obs, *_ = env.step(env.action_space.sample())
        assert np.all(np.isfinite(obs))
    finally:
        env.close()


def test_object_counts_and_pile_free_share_follow_table_one():
    env = of.ObjectFindingEnv("ip", "cubes")
    rng = np.random.default_rng(0)
    draws = [of.object_count(env.cfg, "cubes", rng) for _ in range(2000)]
    env.close()
    counts, piles = np.array([d[0] for d in draws]), np.array([d[1] for d in draws])
    assert counts.min() == 15 and counts.max() == 75
    assert abs((~piles).mean() - 0.25) < 0.03                       # exploration ratio
    dense = of.ObjectFindingEnv("ip", "fixed-primitives")
    counts = [of.object_count(dense.cfg, "fixed-primitives", rng) for _ in range(500)]
    dense.close()
    assert min(n for n, heaped in counts if heaped) >= 45            # 15-30 per pile, 3 piles


def test_piles_bury_the_target():
    env = of.ObjectFindingEnv("ip", "cubes")
    try:
        buried = 0
        for seed in range(12):
            env.reset(seed=seed)
            if not (env.heaped and env.target_present):
                continue
            assert 15 <= len(env.objects) <= 75
            sim = env.sim
            target = np.array(sim.getBasePositionAndOrientation(env.objects[0].body)[0])
            others = np.array([sim.getBasePositionAndOrientation(o.body)[0] for o in env.objects[1:]])
            near = np.linalg.norm(others[:, :2] - target[:2], axis=1) < 0.06
            buried += bool(np.any(others[near, 2] > target[2] + 0.02))
            assert target[2] < 0.03                                 # on the floor, at the bottom
        assert buried >= 3
    finally:
        env.close()


def test_a_push_moves_objects():
    env = of.ObjectFindingEnv("ip", "cubes")
    try:
        seed_with(env, target_present=True)
        sim = env.sim
        before = np.array([sim.getBasePositionAndOrientation(o.body)[0] for o in env.objects])
        target = before[0]
        env._teleport(target + [-0.15, 0, 0.01], of.gripper_rotation(0.0, 0.0))
        for _ in range(5):                               # yaw 0: +x is forward
            env.step(np.array([1.0, 0, 0, 0, 0, -1]))
        after = np.array([sim.getBasePositionAndOrientation(o.body)[0] for o in env.objects])
        assert np.linalg.norm(after[0] - target) > 0.03  # the target was pushed along
        assert np.count_nonzero(np.linalg.norm(after - before, axis=1) > 0.01) >= 2
    finally:
        env.close()


def test_a_push_through_a_hand_built_pile_reveals_the_buried_target():
    env = of.ObjectFindingEnv("ip", "cubes")
    try:
        seed_with(env, target_present=True)
        sim, a = env.sim, env.cfg.object_size_m
        for o in env.objects[9:]:
            sim.removeBody(o.body)
        env.objects = env.objects[:9]
        # the target at the bottom centre, a cube on each side of it, four cubes on top
        spots = [(0, 0, 0), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0),
                 (0.5, 0.5, 1), (-0.5, 0.5, 1), (0.5, -0.5, 1), (-0.5, -0.5, 1)]
        for o, (x, y, layer) in zip(env.objects, spots):
            sim.resetBasePositionAndOrientation(o.body, [1.02 * a * x, 1.02 * a * y, a / 2 + 0.001 + layer * (a + 0.002)],
                                                [0, 0, 0, 1])
        assert of.settle(sim, env.objects, env.cfg, env.cfg.settle_pile_s)
        env.searcher.volume.reset()
        env.target_seen[:] = False

        def look() -> float:     # the same two views before and after the push
            for xyz in ([0.0, -0.05, 0.35], [0.1, 0.0, 0.2]):
                env._teleport(xyz, of.gripper_rotation(0.0, 0.0))
                env._observe()
            return float(env.target_seen.mean())

        before = np.array([sim.getBasePositionAndOrientation(o.body)[0] for o in env.objects])
        seen_before = look()
        assert seen_before < env.cfg.seen_threshold                    # buried: not observed from above
        env._teleport([-0.2, 0.0, 0.012], of.gripper_rotation(0.0, 0.0))
        for _ in range(7):                                           # through the pile's centre along +x
            env.step(np.array([1.0, 0, 0, 0, 0, -1]))
        after = np.array([sim.getBasePositionAndOrientation(o.body)[0] for o in env.objects])
        assert np.count_nonzero(np.linalg.norm(after - before, axis=1) > 0.02) >= 4   # the pile came apart
        seen_after = look()
        assert seen_after > seen_before + 0.1 and seen_after >= env.cfg.seen_threshold
    finally:
        env.close()


def test_vector_env_over_worker_processes():
    import functools
    fns = [functools.partial(of.ObjectFindingEnv, "ap", "cubes", i) for i in range(2)]
    envs = gym.vector.AsyncVectorEnv(fns, context="spawn")
    try:
        obs, info = envs.reset(seed=0)
        assert obs.shape == (2, 71)
        obs, reward, done, truncated, info = envs.step(bench.exploring_actions(np.random.default_rng(0), 2))
        assert obs.shape == (2, 71) and reward.shape == (2,)
    finally:
        envs.close()


# ------------------------------------------------------------------------------------------------
# command line
# ------------------------------------------------------------------------------------------------


def run_cli(*args):
    return subprocess.run([sys.executable, str(HERE / "objfind.py"), *args], capture_output=True, text=True,
                          timeout=300)


@pytest.mark.parametrize("args", [["demo", "--task", "nope"], ["demo", "--scene", "boxes"],
                                  ["demo", "--seed", "-1"], ["demo", "--out", "/no/such/parent/demo"],
                                  ["fly"], [],
                                  ["train", "--set", "entropy=0.1"], ["train", "--set", "epochs=ten"]])
def test_cli_bad_input_is_one_line_and_exit_two(args):
    result = run_cli(*args)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and result.stderr.startswith("objfind: error:")


def test_demo_writes_a_contact_sheet_and_a_video(tmp_path):
    out = tmp_path / "demo"
    assert of.main(["demo", "--agent", "random", "--seed", "2", "--out", str(out)]) == 0
    png = out / "demo-ap-cubes-random.png"
    sheet = cv2.imread(str(png))
    assert sheet is not None and sheet.shape[1] == 4 * of.PANEL[0] and sheet.shape[0] % of.PANEL[1] == 0
    video = cv2.VideoCapture(str(out / "demo-ap-cubes-random.mp4"))
    ok, frame = video.read()
    assert ok and frame.shape[:2] == (of.PANEL[1], 4 * of.PANEL[0])


def test_scripted_agent_finds_a_visible_target(ap_env):
    agent = of.ScriptedAgent(ap_env.cfg)
    successes = 0
    for seed in range(5):
        obs, info = ap_env.reset(seed=seed)
        agent.reset(ap_env.searcher, ap_env.gripper_pose())
        done = False
        while not done:
            obs, reward, done, _, info = ap_env.step(agent.act(ap_env.searcher, ap_env.gripper_pose()))
        successes += info["success"]
    assert successes >= 3


def test_large_workspace_and_rgb_render():
    env = of.ObjectFindingEnv("ap-large", "cubes", seed=1, render_mode="rgb_array")
    try:
        obs, info = env.reset()
        assert env.searcher.volume.shape == (100, 100, 50) and abs(env.searcher.volume.voxel_m - 0.012) < 1e-9
        assert 10 <= len(env.objects) <= 40
        frame = env.render()
        assert frame.shape == (240, 320, 3) and frame.dtype == np.uint8
        obs, reward, done, _, info = env.step(np.array([0, 0, 1.0, 0, 0, -1]))
        assert obs.shape == (71,) and not done and info["explored_fraction"] > 0
    finally:
        env.close()


def test_constructor_seed_makes_the_first_reset_reproducible():
    a, b = of.ObjectFindingEnv("ap", "cubes", seed=11), of.ObjectFindingEnv("ap", "cubes", seed=11)
    try:
        assert np.array_equal(a.reset()[0], b.reset()[0])
    finally:
        a.close(), b.close()


def test_the_training_bench_splits_a_runs_time_into_parts_and_leaves_train_as_it_was():
    before = (of.collect_rollout, of.ppo_update, of.write_csv, of.ObjectFindingEnv.step, of.ActorCritic.evaluate)
    parts = bench.bench_training("ap", 2, 1, of.PPOSettings(batch_steps=200, minibatch=100, epochs=1))
    assert all(parts[k] > 0 for k in bench.TRAINING_PARTS_ORDER[:-1]) and parts["other"] >= 0
    assert sum(parts[k] for k in bench.TRAINING_PARTS_ORDER) == pytest.approx(parts["total"])
    assert parts["env steps"] > parts["policy forward"]      # 400 steps of physics, rendering and fusion
    assert (of.collect_rollout, of.ppo_update, of.write_csv, of.ObjectFindingEnv.step, of.ActorCritic.evaluate) == before


@pytest.mark.parametrize("scene", ["cubes", "object-models"])
def test_bench_stages_account_for_the_step_and_the_reset(scene):
    means = bench.bench_stages("ap", scene, 20)
    stages = ("physics", "render", "detect", "integrate", "encode")
    assert all(means[s] >= 0 for s in stages) and means["render"] > 0 and means["integrate"] > 0
    assert sum(means[s] for s in stages) <= means["step"] * 1.02      # the stages are parts of the step
    assert 0 < means["scene"] < means["reset"]                        # building the scene is part of a reset


# ------------------------------------------------------------------------------------------------
# baselines and evaluation
# ------------------------------------------------------------------------------------------------


def tour_length(points: np.ndarray, tour: np.ndarray, closed: bool = True) -> float:
    legs = np.linalg.norm(np.diff(points[tour], axis=0), axis=1).sum()
    return float(legs + (np.linalg.norm(points[tour[-1]] - points[tour[0]]) if closed else 0.0))


def test_two_opt_uncrosses_a_tour_and_returns_a_permutation():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    crossed = np.array([0, 2, 1, 3])                     # edges 0-2 and 1-3 cross
    better = of.two_opt(square, crossed)
    assert sorted(better) == [0, 1, 2, 3] and better[0] == 0
    assert tour_length(square, better) == pytest.approx(4.0)
    assert tour_length(square, crossed) > 4.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_opt_on_a_grid_is_within_five_percent_of_optimal(seed):
    xs, ys = np.meshgrid(np.arange(6.0), np.arange(6.0))
    points = np.stack([xs.ravel(), ys.ravel()], 1) * 0.06
    start = of.GridExhaustiveSearch.nearest_neighbour(points, seed)
    tour = of.two_opt(points, start)
    assert sorted(tour) == list(range(36))
    assert tour_length(points, tour) <= 1.05 * 36 * 0.06
    path = of.two_opt(points, start, closed=False)       # a search route: the start stays first
    assert path[0] == seed and tour_length(points, path, closed=False) <= tour_length(points, start, closed=False)


def test_gnbv_prefers_a_view_of_unobserved_space(ap_env):
    ap_env.reset(seed=3)
    volume = ap_env.searcher.volume
    volume.reset()
    volume.weight[:50] = 1.0                             # the -x half of the workspace is known
    volume.tsdf[:50] = 1.0
    gnbv = of.GreedyNextBestView(ap_env.cfg)
    gnbv.reset(ap_env.searcher, ap_env.gripper_pose())
    T = np.eye(4)
    T[:3, :3] = of.gripper_rotation(0.0, 0.0)
    toward_known, toward_unknown = T.copy(), T.copy()
    toward_known[:3, 3] = [-0.15, 0.0, 0.3]
    toward_unknown[:3, 3] = [0.15, 0.0, 0.3]
    cameras = np.stack([ap_env.searcher.camera_pose(P) for P in (toward_known, toward_unknown)])
    counts = gnbv.newly_observed(ap_env.searcher, cameras, np.zeros(3))
    assert counts[1] > 10 * max(counts[0], 1)


def test_ges_grid_spacing_is_one_step_and_covers_the_workspace():
    env = of.ObjectFindingEnv("ip", "cubes")
    try:
        env.reset(seed=0)
        ges = of.GridExhaustiveSearch(env.cfg)
        ges.reset(env.searcher, env.gripper_pose())
        s = env.cfg
        xs = np.unique(ges.nodes[:, 0])
        assert np.allclose(np.diff(xs), s.max_step_m)
        assert xs.min() - s.max_step_m / 2 == pytest.approx(-s.workspace_m / 2)
        assert xs.max() + s.max_step_m / 2 == pytest.approx(s.workspace_m / 2)
        assert sorted(ges.route) == list(range(len(ges.nodes)))
        legs = np.linalg.norm(np.diff(ges.nodes[ges.route], axis=0), axis=1)
        assert np.median(legs) == pytest.approx(s.max_step_m)
    finally:
        env.close()


def test_wilson_interval():
    lo, hi = of.wilson_interval(50, 100)
    assert lo == pytest.approx(0.4038, abs=1e-3) and hi == pytest.approx(0.5962, abs=1e-3)
    lo, hi = of.wilson_interval(10, 10)
    assert hi == pytest.approx(1.0) and 0.6 < lo < 0.75


def test_eval_writes_one_csv_row_per_episode(tmp_path):
    out = tmp_path / "gnbv.csv"
    assert of.main(["eval", "--agent", "gnbv", "--episodes", "3", "--workers", "1", "--seed", "5",
                    "--out", str(out)]) == 0
    lines = out.read_text().splitlines()
    assert lines[0].startswith("seed,target_present,success,steps")
    assert [line.split(",")[0] for line in lines[1:]] == ["5", "6", "7"]


def test_the_interactive_agents_run_on_piles_unless_told_otherwise(capsys):
    assert of.main(["eval", "--agent", "ges", "--episodes", "1", "--workers", "1", "--seed", "2"]) == 0
    assert "ges on ip/cubes" in capsys.readouterr().out
    assert of.main(["eval", "--agent", "ges", "--task", "ap", "--episodes", "1", "--workers", "1"]) == 0
    assert "ges on ap/cubes" in capsys.readouterr().out


def test_eval_bad_agent_or_checkpoint_is_one_line_and_exit_two(tmp_path):
    foreign = tmp_path / "foreign.pt"
    foreign.write_text("not a checkpoint")
    import torch
    other = tmp_path / "other.pt"
    torch.save({"state_dict": {}}, other)
    for args in (["eval", "--agent", "nope"], ["eval", "--agent", "a3de", "--weights", str(tmp_path / "none.pt")],
                 ["eval", "--agent", "a3de", "--weights", str(foreign)],
                 ["eval", "--agent", "i3de", "--weights", str(other)], ["eval"]):
        result = run_cli(*args)
        assert result.returncode == 2, args
        assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr


def test_eval_csv_round_trips_for_resumed_tables(tmp_path):
    origin = of.cell_origin("gnbv", "ap", "cubes", None, None)
    rows = [dict(seed=3, target_present=True, success=False, steps=7, target_seen_fraction=0.1,
                 explored_fraction=0.5, decision_ms=1.5, **origin)]
    path = tmp_path / "cell.csv"
    of.write_csv(rows, path)
    assert of.stored_cell(path, [3], origin) == rows and of.stored_cell(tmp_path / "none.csv", [3], origin) is None
    with pytest.raises(of.UsageError, match="holds 1 episodes from seed 3, not 1 from seed 4"):
        of.stored_cell(path, [4], origin)               # another experiment's cell: refused, never replaced
    ablation = of.cell_origin("gnbv", "ap", "cubes", None, dict(target_size_known=False))
    with pytest.raises(of.UsageError, match="made by gnbv on ap/cubes .weights none, target size known, world .* "
                                            "settings [0-9a-f]{8}., not gnbv on ap/cubes .weights none, target "
                                            "size unknown"):
        of.stored_cell(path, [3], ablation)
    older_world = dict(origin, world=str(of.WORLD_REVISION - 1))    # made before a change that alters episodes
    of.write_csv([dict(rows[0], **older_world)], path)
    with pytest.raises(of.UsageError, match=f"world {of.WORLD_REVISION - 1}., not .* world {of.WORLD_REVISION} with"):
        of.stored_cell(path, [3], origin)


def test_a_sensor_point_made_with_other_settings_is_refused_whatever_its_file_is_called(tmp_path):
    rig = of.cell_origin("i3de", "ip", "cubes", None, of.RIG_SENSING)
    assert re.fullmatch(rf"{of.WORLD_REVISION}\+[0-9a-f]{{8}}", rig["world"])
    assert of.cell_origin("i3de", "ip", "cubes", None, dict(of.RIG_SENSING)) == rig
    table_two = of.cell_origin("i3de", "ip", "cubes", None, None)["world"]
    assert re.fullmatch(rf"{of.WORLD_REVISION}\+[0-9a-f]{{8}}", table_two) and table_two != rig["world"]
    for plain in ({}, dict(target_size_known=False), dict(tof_noise_ratio=of.TASKS["ip"].tof_noise_ratio)):
        assert of.cell_origin("i3de", "ip", "cubes", None, plain)["world"] == table_two
    path = tmp_path / "i3de-ip-rig-camera-1.csv"
    of.write_csv(fake_rows(0, 2, "i3de", "ip", overrides=of.RIG_SENSING), path)
    assert len(of.stored_cell(path, [0, 1], rig)) == 2
    your_camera = of.cell_origin("i3de", "ip", "cubes", None, dict(of.RIG_SENSING, depth_width=320))
    with pytest.raises(of.UsageError, match=rf"world {of.WORLD_REVISION} with settings [0-9a-f]{{8}}\), not .* "
                                            rf"world {of.WORLD_REVISION} with settings [0-9a-f]{{8}}\)"):
        of.stored_cell(path, [0, 1], your_camera)
    of.write_csv([dict(row, world="7+zz") for row in fake_rows(0, 1)], path)
    with pytest.raises(of.UsageError, match="line 2: '7.zz' is not a world"):
        of.read_episodes(path)


def test_a_settings_default_edited_in_the_file_changes_the_world_stamp(monkeypatch):
    before = of.cell_origin("gnbv", "ap", "cubes", None, None)["world"]
    monkeypatch.setitem(of.TASKS, "ap", dataclasses.replace(of.TASKS["ap"], trunc_m=0.05))   # as an edited default
    edited = of.cell_origin("gnbv", "ap", "cubes", None, None)["world"]
    assert edited.split("+")[0] == before.split("+")[0] == str(of.WORLD_REVISION) and edited != before


def test_table_two_pools_the_no_target_scenes_of_each_agent():
    def rows(successes, absent_successes):
        found = [dict(target_present=True, success=ok, steps=5, decision_ms=1.0) for ok in successes]
        return found + [dict(target_present=False, success=ok, steps=9, decision_ms=1.0) for ok in absent_successes]
    cells = {("i3de", "ip", "cubes"): of.summarise(rows([True, False], [True] * 4)),
             ("i3de", "ip", "object-models"): of.summarise(rows([True] * 2, [True, False, False, False])),
             ("i3de", "ip-real", "cubes-and-cuboids"): of.summarise(rows([True] * 3, []))}   # the real column
    table = of.table_markdown(cells, 6, {"numpy=1"}).splitlines()
    assert table[-1] == "Made with numpy=1."
    i3de = next(line for line in table if line.startswith("| I3DE (ours)"))
    assert i3de.split(" | ")[1:] == ["83.3 / 7.67", "-", "-", "-", "-", "50.0 / 7.67", "100.0 / 5.00", "62.5 of 8 |"]
    paper = next(line for line in table if line.startswith("| I3DE (paper)"))
    assert "88.0 / 26.86" in paper and paper.endswith("100.0 / 15.35 | 96.1 |")
    assert next(line for line in table if line.startswith("| GES (ours)")).endswith("- |")


def test_every_random_shape_and_object_model_has_finite_geometry():
    import os
    data = of.pybullet_data.getDataPath()
    paths = [os.path.join(data, "random_urdfs", f"{i:03d}", f"{i:03d}.urdf") for i in of.RANDOM_SHAPES]
    paths += [os.path.join(data, name) for name, _ in of.OBJECT_MODELS]
    for path in paths:
        vertices, faces = of.urdf_mesh(path)
        assert len(faces) and np.all(np.isfinite(vertices)), path


def test_urdf_visual_origin_rotation_is_applied():
    path = Path(of.pybullet_data.getDataPath()) / "lego" / "lego.urdf"     # visual rpy = (pi/2, 0, 0)
    vertices, _ = of.urdf_mesh(str(path))
    extent = vertices.max(0) - vertices.min(0)
    assert extent[2] < extent[1]      # the brick lies flat: rotated, its height is the smallest side


def test_perceived_share_grows_with_the_faces_seen_and_tracks_the_truth(ap_env):
    seed, *_ = seed_with(ap_env, target_present=True)
    s = ap_env.cfg
    pos = np.array(ap_env.sim.getBasePositionAndOrientation(ap_env.objects[0].body)[0])
    ap_env.searcher.volume.reset()
    ap_env.target_seen[:] = False
    shares = []
    for dist, yaw, roll in [(0.25, 0, 0), (0.2, 0, 0.6), (0.2, np.pi, 0.6), (0.2, np.pi / 2, 0.6)]:
        R = of.gripper_rotation(yaw, roll)
        axis = R[:, 2]
        ap_env._teleport(pos - axis * dist + s.camera_offset_m * axis, R)   # camera looking at the target
        ap_env._observe()
        shares.append((ap_env.searcher.perceived_target_share(), ap_env.target_seen.mean()))
    (top, top_truth), (last, last_truth) = shares[0], shares[-1]
    assert last > top + 0.1 and last_truth > top_truth + 0.1          # more faces, more seen, in both
    assert all(0.6 * t < p < t + 0.03 for p, t in shares), shares     # in step, on the safe side


@pytest.mark.parametrize("height_m, low", [(0.08, 1 / 6 - 0.025), (0.3, 0.1)])
def test_a_view_from_straight_above_perceives_one_face_of_six(ap_env, height_m, low):
    # The top face is exactly a sixth of a cube's surface. The seen area measures it, less the outline
    # pixels, whose one-sided difference to the floor is a jump (more of them far away); a count of
    # marked voxels read 0.19-0.21 here and stopped the searchers early.
    seed_with(ap_env, target_present=True)
    pos = np.array(ap_env.sim.getBasePositionAndOrientation(ap_env.objects[0].body)[0])
    ap_env.searcher.volume.reset()
    camera_z = pos[2] + ap_env.cfg.object_size_m / 2 + height_m
    ap_env._teleport(np.r_[pos[:2], camera_z - ap_env.cfg.camera_offset_m], of.gripper_rotation(0.0, 0.0))
    ap_env._observe()
    assert low < ap_env.searcher.perceived_target_share() <= 1 / 6 + 0.005


@pytest.mark.parametrize("agent, task, scene, seed", [("ges", "ip", "cubes", 87), ("ges", "ip", "cubes", 185),
                                                       ("gnbv", "ap-real", "cubes-and-cuboids", 149),
                                                       ("gnbv", "ap-real", "cubes-and-cuboids", 20)])
def test_the_searchers_do_not_claim_where_world_7_claimed_with_20_percent_or_less_seen(agent, task, scene, seed):
    # World 7 claimed "found" in these scenes at steps 1-3 with 14-19 % of the target truly seen
    # (results/stops/ of that world): the estimate passed 20 % on its first views.
    env = of.ObjectFindingEnv(task, scene)
    env.reset(seed=seed)
    searcher = of.make_agent(agent, env.cfg, seed)
    searcher.reset(env.searcher, env.gripper_pose())
    for _ in range(12):
        action = searcher.act(env.searcher, env.gripper_pose())
        _, _, done, _, info = env.step(action)
        if action[of.ACTION_MOVES] > 0:
            assert info["target_seen_fraction"] > 0.2, info
        if done:
            break
    env.close()


def test_a_flat_target_on_the_floor_is_perceived_as_seen():
    # A sticker on the floor, seen from straight above: its points back-project onto the floor plane, and
    # float32 depth puts them a hair below it, outside the volume, unless they are kept on the floor.
    searcher = of.Searcher(of.TASKS["ap"])
    searcher.reset(0.04 * 0.04)                            # told its area: one 4 cm square face
    camera = searcher.rig.depth
    T_world_depth = np.eye(4)
    T_world_depth[:3, :3], T_world_depth[2, 3] = of.rotation(np.pi, "x"), 0.3   # looking straight down
    depth_m = np.full((camera.height, camera.width), 0.3, np.float32)
    floor = of.back_project(depth_m.astype(np.float64), camera.K)
    sticker = (np.abs(floor[..., 0]) < 0.02) & (np.abs(floor[..., 1]) < 0.02)
    searcher.observe(depth_m, T_world_depth, detections=sticker.astype(np.float32))
    assert 0.7 < searcher.perceived_target_share() <= 1.0


def test_perceived_share_is_conservative_over_random_views(ap_env):
    perceived, truth = [], []
    rng = np.random.default_rng(0)
    for seed in range(60):
        _, info = ap_env.reset(seed=seed)
        for _ in range(4):
            ap_env.searcher.volume.reset()
            ap_env.target_seen[:] = False
            ap_env._observe()
            if info["target_present"] and ap_env.target_seen.mean() > 0.05:
                perceived.append(ap_env.searcher.perceived_target_share())
                truth.append(ap_env.target_seen.mean())
            ap_env.step(np.r_[rng.uniform(-1, 1, 5), -1.0])
    perceived, truth = np.array(perceived), np.array(truth)
    errors = perceived - truth
    assert len(errors) >= 30 and -0.12 < errors.mean() < 0.0, errors
    claims = perceived >= 0.2                  # where a searcher would stop: rarely short of the truth
    assert claims.sum() >= 10 and np.mean(truth[claims] < 0.2) < 0.15, (perceived, truth)


def test_ground_truth_of_a_model_uses_only_its_surface_seen_from_outside():
    import os
    data = of.pybullet_data.getDataPath()
    shares = {}
    for name, scale in of.OBJECT_MODELS:
        path = os.path.join(data, name)
        points, normals, area = of.exterior_surface(path, scale, of.TASKS["ap"].seen_min_cos, candidates=2000)
        shares[name] = len(points) / 2000
        assert np.allclose(np.linalg.norm(normals, axis=1), 1.0) and area > 0
    assert shares["teddy_vhacd.urdf"] < 0.9          # its convex pieces overlap: buried faces dropped
    assert shares["jenga/jenga.urdf"] > 0.99 and shares["objects/mug.urdf"] > 0.95   # what is left of its inside


def test_the_ground_truth_is_the_surface_the_camera_renders():
    # The camera renders a decimated mesh (a mug's inner wall mostly gone): the truth's points are drawn on
    # that mesh, its area is that mesh's, and each normal points to the side the squarest view saw.
    import os
    path = os.path.join(of.pybullet_data.getDataPath(), "objects/mug.urdf")
    model = of.mesh_model(path, 0.5)
    points, normals, area = of.exterior_surface(path, 0.5, of.TASKS["ap"].seen_min_cos, candidates=2000)
    rendered, _ = of.sample_surface(model.render_vertices, model.render_faces, 2000, np.random.default_rng(0))
    rows = {tuple(p) for p in np.round(rendered, 12)}
    assert all(tuple(p) in rows for p in np.round(points, 12))
    assert area <= of.mesh_area(model.render_vertices, model.render_faces) + 1e-12
    assert area < 0.75 * of.mesh_area(model.vertices, model.faces)


def test_a_box_models_ground_truth_normals_point_out():
    # Grazing views pass the depth test from behind a face: a normal turned to the first view that saw its
    # point faced into a jenga block for 13 % of them; turned to the squarest, every one points out.
    import os
    path = os.path.join(of.pybullet_data.getDataPath(), "jenga/jenga.urdf")
    points, normals, _ = of.exterior_surface(path, 0.5, of.TASKS["ap"].seen_min_cos, candidates=2000)
    centre = of.mesh_model(path, 0.5).render_vertices.mean(0)
    assert np.mean(np.sum(normals * (points - centre), axis=1) > 0) > 0.99


def test_random_shapes_leave_out_exactly_the_slivers_thinner_than_the_minimum_width():
    import os
    data, directions = of.pybullet_data.getDataPath(), of.fibonacci_directions(500)
    thin = set()
    for i in range(1000):
        if i == 168:    # its OBJ holds only NaN vertices
            continue
        hull = of.mesh_model(os.path.join(data, "random_urdfs", f"{i:03d}", f"{i:03d}.urdf"),
                             of.RANDOM_SHAPE_SCALE).hull @ directions.T
        if (hull.max(0) - hull.min(0)).min() < of.MIN_SHAPE_WIDTH_M:
            thin.add(i)
    assert thin == set(of.THIN_SHAPES) and set(of.RANDOM_SHAPES) == set(range(1000)) - thin - {168}


# --- PPO ---------------------------------------------------------------------------------------------

class Reach(gym.Env):
    """A 1-D reach: move a point to a goal with the first of six action values, then terminate."""

    observation_space = gym.spaces.Box(-2.0, 2.0, (3,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (6,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.goal, self.t = 0.0, float(self.np_random.choice([-0.8, 0.8])), 0
        return self._obs(), {}

    def _obs(self):
        return np.array([self.x, self.goal, self.goal - self.x], np.float32)

    def step(self, action):
        self.t += 1
        if action[5] > 0:
            success = abs(self.goal - self.x) < 0.2
            return self._obs(), (1.0 if success else -1.0), True, False, dict(success=success)
        before = abs(self.goal - self.x)
        self.x = float(np.clip(self.x + 0.2 * np.clip(action[0], -1, 1), -1, 1))
        done = self.t >= 20
        reward = before - abs(self.goal - self.x) - (1.0 if done else 0.0)
        return self._obs(), reward, done, False, dict(success=False)


TINY_PPO = of.PPOSettings(hidden=32, batch_steps=256, minibatch=64, epochs=4, learning_rate=3e-3,
                          reward_scale=1.0, init_terminate_prob=0.05, checkpoint_every=1)


def test_ppo_improves_the_return_of_a_tiny_reach_task(tmp_path):
    result = of.train(Reach, tmp_path, total_steps=256 * 25, ppo=TINY_PPO, progress=False)
    returns = [float(r["return"]) for r in result["log"]]
    assert np.mean(returns[-5:]) > np.mean(returns[:3]) + 0.5, returns
    assert (tmp_path / "checkpoint.pt").exists() and (tmp_path / "curve.png").exists()
    assert len(of.read_train_log(tmp_path / "log.csv", 25)) == 25


def test_a_warm_start_begins_from_the_trained_policy(tmp_path):
    trained = of.train(Reach, tmp_path / "a", total_steps=256 * 20, ppo=TINY_PPO, progress=False)
    init = of.read_checkpoint(tmp_path / "a" / "checkpoint.pt")
    warm = of.train(Reach, tmp_path / "b", total_steps=256, ppo=TINY_PPO, progress=False, seed=1, init=init,
                    meta=dict(init="reach"))
    fresh = of.train(Reach, tmp_path / "c", total_steps=256, ppo=TINY_PPO, progress=False, seed=1)
    first = lambda result: float(result["log"][0]["return"])
    assert first(warm) > first(fresh) + 0.5, (first(warm), first(fresh), trained["log"][-1])
    checkpoint = of.read_checkpoint(tmp_path / "b" / "checkpoint.pt")
    assert checkpoint["update"] == 1 and checkpoint["init"] == "reach"       # a new run, its origin recorded
    assert checkpoint["model"]["obs_count"] > init["model"]["obs_count"]     # the statistics carried over


def test_a_fresh_terminate_keeps_the_moves_and_forgets_when_to_stop():
    trained = of.ActorCritic(3, TINY_PPO)
    with torch.no_grad():
        for parameter in trained.actor.parameters():
            parameter.add_(torch.randn(parameter.shape, generator=torch.Generator().manual_seed(0)))
    model = of.ActorCritic(3, TINY_PPO)
    model.load_state_dict(trained.state_dict())
    model.reset_terminate(0.05)
    obs = torch.randn(64, 3, generator=torch.Generator().manual_seed(1))
    before, after = trained.actor_output(obs), model.actor_output(obs)
    assert torch.equal(before[:, :5], after[:, :5])                       # the moves are kept
    assert before[:, 5].std() > 0.1                                         # the trained head varied
    assert torch.allclose(torch.sigmoid(after[:, 5]), torch.tensor(0.05))  # now the same everywhere


def test_a_resumed_run_repeats_the_next_update_exactly(tmp_path):
    straight = of.train(Reach, tmp_path / "a", total_steps=256 * 3, ppo=TINY_PPO, progress=False)
    of.train(Reach, tmp_path / "b", total_steps=256 * 2, ppo=TINY_PPO, progress=False)
    # a resumed run takes its settings from its checkpoint, whatever it is given
    resumed = of.train(Reach, tmp_path / "b", total_steps=256 * 3, ppo=of.PPOSettings(), progress=False,
                       resume=of.read_checkpoint(tmp_path / "b" / "checkpoint.pt", run=True))
    for (name, a), b in zip(straight["model"].state_dict().items(), resumed["model"].state_dict().values()):
        assert torch.equal(a, b), name
    same = lambda row: {k: v for k, v in row.items() if k != "wall_s"}
    assert same(straight["log"][-1]) == same(resumed["log"][-1])


def test_the_progress_bar_shows_each_updates_own_rate(tmp_path, monkeypatch, capsys):
    """On a clock that moves one second per reading, every update of 256 steps runs at 256 steps/s (the
    cumulative steps over one update's time would read 512, then 768)."""
    clock = iter(range(10 ** 6))
    monkeypatch.setattr(of.time, "perf_counter", lambda: float(next(clock)))
    of.train(Reach, tmp_path, total_steps=256 * 3, ppo=TINY_PPO, progress=True)
    of.release_locks()
    rates = re.findall(r"steps_per_s=(\d+)", capsys.readouterr().err)
    assert len(rates) >= 3 and set(rates) == {"256"}, rates


def test_the_learning_curve_has_labelled_ticks_on_both_axes(tmp_path):
    rows = [dict(env_steps=5000 * u, success=min(1.0, 0.3 + 0.01 * u), episode_length=40 - 0.2 * u)
            for u in range(1, 121)]
    path = tmp_path / "curve.png"
    of.plot_learning_curve(rows, path)
    image = cv2.imread(str(path))
    assert image.shape[:2] == of.CURVE_SIZE[::-1] and [p.name for p in tmp_path.iterdir()] == ["curve.png"]
    ink = image.min(axis=2) < 128                                       # dark pixels: text and lines
    width, height = of.CURVE_SIZE
    left, right, top, bottom = of.CURVE_MARGINS
    assert ink[top:height - bottom, :left - 8].sum(axis=1).astype(bool).sum() > 40   # y tick labels, both panels
    under_axis = ink[height - bottom + 8:height - bottom + 22, left - 20:width - right + 20]
    columns = np.flatnonzero(under_axis.any(axis=0))
    groups = 1 + np.count_nonzero(np.diff(columns) > 8)                # separate x tick labels
    assert groups >= 4


def test_a_killed_checkpoint_write_leaves_the_last_checkpoint_readable(tmp_path, monkeypatch):
    of.train(Reach, tmp_path, total_steps=256, ppo=TINY_PPO, progress=False)
    of.release_locks()
    checkpoint = of.read_checkpoint(tmp_path / "checkpoint.pt", run=True)

    def killed_halfway(obj, path):                                      # half the bytes, then the process dies
        Path(path).write_bytes(b"half a file")
        raise KeyboardInterrupt
    monkeypatch.setattr(of.torch, "save", killed_halfway)
    with pytest.raises(KeyboardInterrupt):
        of.save_checkpoint(tmp_path / "checkpoint.pt", dict(checkpoint, update=2))
    assert of.read_checkpoint(tmp_path / "checkpoint.pt")["update"] == 1
    assert [p.read_bytes() for p in tmp_path.glob(".checkpoint.*")] == [b"half a file"]   # beside it, not on it
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes((tmp_path / "checkpoint.pt").read_bytes()[:200])
    with pytest.raises(of.UsageError):
        of.read_checkpoint(truncated)


def test_gae_matches_a_case_worked_by_hand():
    """gamma 0.9, lambda 0.8; the episode ends at t = 1. Backwards: A2 = 3 + 0.9 * 2 - 0.5 = 4.3; A1 = 2 - 0.5
    (no bootstrap past the end) = 1.5; A0 = (1 + 0.9 * 0.5 - 0.5) + 0.9 * 0.8 * 1.5 = 2.03."""
    rewards, values = np.array([[1.0], [2.0], [3.0]]), np.full((3, 1), 0.5)
    advantages, returns = of.gae(rewards, values, np.array([[0.0], [1.0], [0.0]]), np.array([2.0]), 0.9, 0.8)
    assert np.allclose(advantages[:, 0], [2.03, 1.5, 4.3]) and np.allclose(returns[:, 0], [2.53, 2.0, 4.8])


def test_the_clipped_surrogate_matches_a_case_worked_by_hand():
    """clip 0.2: min(r A, clip(r) A) per sample is 0.5, 1.1, 1.2 (gain cut) and -1.5 (loss kept): mean 0.325."""
    ratio = torch.tensor([0.5, 1.1, 1.5, 1.5], requires_grad=True)
    loss = of.clipped_surrogate_loss(ratio, torch.tensor([1.0, 1.0, 1.0, -1.0]), 0.2)
    loss.backward()
    assert abs(loss.item() + 0.325) < 1e-6
    assert torch.allclose(ratio.grad, torch.tensor([-0.25, -0.25, 0.0, 0.25]))   # the cut sample pulls nothing


def test_the_observation_normaliser_matches_the_statistics_of_all_batches_seen():
    model = of.ActorCritic(3, TINY_PPO)
    batches = [torch.randn(n, 3) * torch.tensor([0.01, 1.0, 30.0]) + 5.0 for n in (7, 100, 33)]
    for batch in batches:
        model.update_obs_stats(batch)
    everything = torch.cat(batches)
    assert torch.allclose(model.obs_mean, everything.mean(0), rtol=1e-4)
    assert torch.allclose(model.obs_var, everything.var(0, unbiased=False), rtol=1e-3)
    assert model.normalise(everything).std(0).sub(1).abs().max() < 0.05   # each input now at unit scale


def test_the_policy_maps_a_state_to_a_valid_action():
    model = of.ActorCritic(71, of.PPOSettings())
    agent = of.PPOAgent(dict(obs_dim=71, settings=vars(of.PPOSettings()), model=model.state_dict()))
    action = agent.decide(np.random.default_rng(0).normal(size=71).astype(np.float32))
    assert action.shape == (6,) and np.all(np.abs(action) <= 1) and action[5] == -1.0   # rarely terminates


def test_train_and_demo_bad_input_is_one_line_and_exit_two(tmp_path, capsys):
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(b"PK\x03\x04 cut short")
    (tmp_path / "run").mkdir()
    of.save_checkpoint(tmp_path / "run" / "checkpoint.pt", {"format": "objfind-ppo", "update": 0})
    cases = (["train", "--resume", "--out", str(tmp_path / "empty")],          # nothing to resume
             ["train", "--out", str(tmp_path / "run")],                          # would overwrite a run
             ["train", "--out", str(tmp_path / "no" / "such" / "dir")],
             ["train", "--init", str(truncated), "--out", str(tmp_path / "fresh")],    # a broken warm start
             ["train", "--resume", "--set", "epochs=3", "--out", str(tmp_path / "run")],
             ["train", "--fresh-terminate", "--out", str(tmp_path / "fresh")],         # without --init
             ["train", "--resume", "--init", str(truncated), "--out", str(tmp_path / "run")],
             ["demo", "--agent", "a3de", "--weights", str(truncated)],
             ["eval", "--agent", "a3de", "--weights", str(truncated)])
    for args in cases:
        assert of.main(args) == 2, args
        assert len(capsys.readouterr().err.strip().splitlines()) == 1, args


@pytest.mark.parametrize("agent, task, name", [("a3de", "ap", "a3de.pt"), ("a3de", "ap-large", "a3de-large.pt"),
                                               ("i3de", "ip", "i3de.pt")])
def test_the_shipped_weights_load_and_act(agent, task, name):
    path = Path(of.__file__).resolve().parent / "weights" / name
    assert of.default_weights(agent, task) == path     # eval's default
    checkpoint = of.read_checkpoint(path)
    assert checkpoint["obs_dim"] == 71 and checkpoint["env_steps"] > 0 and checkpoint["task"] == task
    policy = of.PPOAgent(of.learned_policy(agent, task, path))
    env = of.ObjectFindingEnv(task, checkpoint["scene"], seed=3)     # where it was trained
    env.reset()
    action = policy.act(env.searcher, env.gripper_pose())
    assert action.shape == (6,) and np.all(np.abs(action) <= 1) and abs(action[5]) == 1.0
    assert checkpoint["model"]["obs_count"].item() > 0          # trained: the normaliser has seen batches
    env.close()


def test_demo_runs_the_shipped_a3de_by_default(tmp_path):
    assert of.main(["demo", "--seed", "1", "--out", str(tmp_path / "demo")]) == 0
    assert (tmp_path / "demo" / "demo-ap-cubes-a3de.png").exists()


I3DE_SEED = 10   # a pile the shipped I3DE pushes apart to reveal the target (the README's picture)


def test_an_i3de_demo_ends_by_its_own_choice_and_is_the_episode_eval_runs(tmp_path):
    png, _, info = of.run_demo("i3de", "ip", "cubes", I3DE_SEED, tmp_path)   # the shipped weights
    assert png.exists()
    assert info["terminated_by_agent"] and info["success"] and info["steps"] < of.TASKS["ip"].horizon
    # drawing the outside view must not touch the physics: the picture shows eval's episode
    row, = of.evaluate("i3de", "ip", "cubes", 1, seed=I3DE_SEED, progress=False)
    assert (row["steps"], row["target_seen_fraction"]) == (info["steps"], round(info["target_seen_fraction"], 4))


PUSH_MOVE_M = 0.01       # an object displaced this far in one step was moved by the gripper
I3DE_BURIED_SEED = 6     # a pile whose target the shipped I3DE cannot see enough of until it pushes
I3DE_EMPTY_SEED = 0      # a pile scene without a target


def shipped_i3de_episode(seed: int) -> tuple[list, dict]:
    """The shipped I3DE's greedy episode on ip/cubes scene `seed`: per step, the target's seen share
    before the step and whether the step moved an object; and the last info."""
    agent = of.PPOAgent(of.learned_policy("i3de", "ip"))
    env = of.ObjectFindingEnv("ip", "cubes")
    obs, info = env.reset(seed=seed)
    positions = lambda: np.array([env.sim.getBasePositionAndOrientation(o.body)[0] for o in env.objects])
    trace, done, before = [], False, positions()
    while not done:
        seen = info["target_seen_fraction"]
        obs, _, done, _, info = env.step(agent.act(env.searcher, env.gripper_pose()))
        after = positions()
        trace.append((seen, np.linalg.norm(after - before, axis=1).max() > PUSH_MOVE_M))
        before = after
    env.close()
    return trace, info


def test_the_shipped_i3de_reveals_a_buried_target_by_pushing():
    trace, info = shipped_i3de_episode(I3DE_BURIED_SEED)
    bar = of.TASKS["ip"].seen_threshold                   # 20 % of the target's surface seen
    first_push = next(i for i, (_, moved) in enumerate(trace) if moved)
    assert trace[first_push][0] < bar                     # before any object moved: under the bar
    assert info["target_present"] and info["terminated_by_agent"] and info["success"]
    assert info["target_seen_fraction"] > bar             # the push uncovered it, and the agent said so


def test_the_shipped_i3de_ends_a_scene_without_a_target_before_the_horizon():
    trace, info = shipped_i3de_episode(I3DE_EMPTY_SEED)
    assert not info["target_present"] and info["terminated_by_agent"] and info["success"]
    assert len(trace) < of.TASKS["ip"].horizon


def test_a_policy_checkpoint_runs_as_an_eval_agent(tmp_path):
    model = of.ActorCritic(71, of.PPOSettings())
    path = tmp_path / "a3de.pt"
    of.save_checkpoint(path, dict(format="objfind-ppo", model=model.state_dict(), obs_dim=71,
                                  settings=vars(of.PPOSettings()), task="ap", scene="cubes"))
    rows = of.evaluate("a3de", "ap", "cubes", episodes=2, workers=1, progress=False,
                       policy=of.learned_policy("a3de", "ap", path))
    assert len(rows) == 2 and all(1 <= r["steps"] <= 130 for r in rows)


# ------------------------------------------------------------------------------------------------
# nothing a user types loses results or reports something false
# ------------------------------------------------------------------------------------------------

UNWRITABLE = "/proc/self/objfind-out"   # no file can be made under /proc, not even by root


def one_line_exit_two(capsys, args) -> str:
    assert of.main(args) == 2, args
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("objfind: error:"), err
    return err


def no_episodes(monkeypatch):
    """Make any evaluation or demo episode fail the test: the checks must come before the work."""
    def refuse(*args, **kwargs):
        raise AssertionError("an episode ran before the input was checked")
    monkeypatch.setattr(of, "evaluate", refuse)
    monkeypatch.setattr(of, "run_demo", refuse)


def test_a_table_of_other_episodes_leaves_the_stored_cells_byte_identical(tmp_path, capsys, monkeypatch):
    out = tmp_path / "results"
    out.mkdir()
    of.write_csv(fake_rows(0, 30), out / "gnbv-ap-cubes.csv")
    (out / "table2.md").write_text("the stored table\n")
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.name != of.LOCK_NAME}
    no_episodes(monkeypatch)
    err = one_line_exit_two(capsys, ["eval", "--table", "--episodes", "20", "--out", str(out)])
    assert "gnbv-ap-cubes.csv holds 30 episodes from seed 0, not 20" in err
    one_line_exit_two(capsys, ["eval", "--table", "--episodes", "30", "--seed", "1", "--out", str(out)])
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.name != of.LOCK_NAME} == before
    # the same experiment, read back: an incomplete table prints but does not write table2.md
    assert of.main(["eval", "--table", "--episodes", "30", "--from-csv", "--out", str(out)]) == 0
    assert "table2.md not written" in capsys.readouterr().out
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.name != of.LOCK_NAME} == before


def test_a_table_refuses_a_cell_of_other_weights_and_names_other_package_versions(tmp_path, capsys, monkeypatch):
    out = tmp_path / "results"
    out.mkdir()
    no_episodes(monkeypatch)
    for (agent, task), scenes in of.PAPER_TABLE_II.items():
        policy = of.learned_policy(agent, task) if agent in of.LEARNED else None
        for scene in scenes:
            of.write_csv(fake_rows(0, 2, agent, task, scene, policy), out / f"{agent}-{task}-{scene}.csv")
    cell = out / "a3de-ap-cubes.csv"
    rows = of.read_episodes(cell)
    of.write_csv([dict(row, weights="0123456789ab") for row in rows], cell)
    table = ["eval", "--table", "--episodes", "2", "--from-csv", "--out", str(out)]
    assert "weights 0123456789ab" in one_line_exit_two(capsys, table)
    of.write_csv([dict(row, versions="python=3.0 numpy=1.0") for row in rows], cell)
    assert of.main(table) == 0
    made = (out / "table2.md").read_text().splitlines()[-1]
    assert made.startswith("Made with mixed: ") and "numpy=1.0" in made and of.package_versions() in made


def cell_csv(path: Path, header: str, lines: list) -> Path:
    path.write_text(header + "\n" + "\n".join(lines) + "\n")
    return path


def test_episode_csvs_are_read_strictly(tmp_path, capsys, monkeypatch):
    fields = "seed,target_present,success,steps,target_seen_fraction,explored_fraction,decision_ms"
    fields += ",agent,task,scene,weights,target_size_known,world,versions"
    made = f",gnbv,ap,cubes,none,True,{of.WORLD_REVISION}," + of.package_versions()
    # a spreadsheet's TRUE/FALSE, and columns in another order: read by name, the right rate
    spreadsheet = cell_csv(tmp_path / "a.csv", fields, [f"{i},TRUE,{'TRUE,5,0.3' if i < 9 else 'FALSE,5,0.1'},0.5,1.0"
                                                        + made for i in range(10)])
    assert np.mean([r["success"] for r in of.read_episodes(spreadsheet)]) == 0.9
    reordered = cell_csv(tmp_path / "b.csv", "success,target_present," + fields.replace("target_present,success,", ""),
                         [f"{'True' if i < 9 else 'False'},true,{i},5,{0.3 if i < 9 else 0.1},0.5,1.0" + made
                          for i in range(10)])
    rows = of.read_episodes(reordered)
    assert np.mean([r["success"] for r in rows]) == 0.9 and all(r["target_present"] for r in rows)
    good = "0,True,True,5,0.3,0.5,1.0" + made
    lines = {"truncated line": [good, "1,True,Tr"], "not true or false": ["0,yes,True,5,0.3,0.5,1.0" + made],
             "seed 0 is also on line 2": [good, good], "0 steps": ["0,True,True,0,0.3,0.5,1.0" + made],
             "131 steps": ["0,True,True,131,0.3,0.5,1.0" + made], "not a fraction": ["0,True,True,5,1.3,0.5,1.0" + made],
             "a target seen in a scene without one": ["0,False,True,5,0.3,0.5,1.0" + made],
             "a stop succeeds exactly above 20%": ["0,True,True,5,0.0,0.5,1.0" + made],         # success, 0 % seen
             "success False with 30.0% of the target seen": ["0,True,False,5,0.3,0.5,1.0" + made],   # flipped
             "a failure without a target before the horizon": ["0,False,False,5,0.0,0.5,1.0" + made],
             "not one of": ["0,True,True,5,0.3,0.5,1.0" + made.replace("gnbv", "nbv")],
             "differs from line 2": [good, "1,True,True,5,0.3,0.5,1.0" + made.replace("cubes", "random-shapes")]}
    bad = {name: cell_csv(tmp_path / f"bad{i}.csv", fields, rows) for i, (name, rows) in enumerate(lines.items())}
    bad["no header"] = cell_csv(tmp_path / "d.csv", good, [good.replace("0,", "1,", 1)])
    bad["no origin columns"] = cell_csv(tmp_path / "f.csv", fields.split(",agent")[0], ["0,True,True,5,0.3,0.5,1.0"])
    for name, path in bad.items():
        with pytest.raises(of.UsageError, match=str(path.name)) as error:
            of.read_episodes(path)
        assert name in str(error.value) or name in ("no header", "no origin columns", "truncated line"), error.value
    # inside a table: one line naming the file, before any episode runs
    out = tmp_path / "results"
    out.mkdir()
    (out / "gnbv-ap-cubes.csv").write_bytes(bad["truncated line"].read_bytes())
    no_episodes(monkeypatch)
    assert "gnbv-ap-cubes.csv, line 3" in one_line_exit_two(capsys, ["eval", "--table", "--out", str(out)])


def test_a_random_agents_csv_under_a_gnbv_cell_is_refused_and_plain_eval_replaces_no_cell(tmp_path, capsys,
                                                                                        monkeypatch):
    out = tmp_path / "results"
    out.mkdir()
    cell = out / "gnbv-ap-cubes.csv"
    assert of.main(["eval", "--agent", "random", "--episodes", "2", "--workers", "1", "--out", str(cell)]) == 0
    capsys.readouterr()
    random_cell = cell.read_bytes()
    no_episodes(monkeypatch)
    err = one_line_exit_two(capsys, ["eval", "--table", "--episodes", "2", "--from-csv", "--out", str(out)])
    assert "gnbv-ap-cubes.csv was made by random on ap/cubes" in err and "not gnbv on ap/cubes" in err
    # a plain eval never replaces another experiment's CSV: another agent's, or other episodes of its own
    for args in (["--agent", "gnbv"], ["--agent", "random", "--episodes", "3"], ["--agent", "random", "--seed", "5"]):
        one_line_exit_two(capsys, ["eval", *args, "--workers", "1", "--out", str(cell)])
    assert cell.read_bytes() == random_cell


def test_outputs_are_checked_before_any_episode(tmp_path, capsys, monkeypatch):
    no_episodes(monkeypatch)
    (tmp_path / "folder.csv").mkdir()
    (tmp_path / "a-file").write_text("")
    for args in (["demo", "--agent", "random", "--out", UNWRITABLE],
                 ["demo", "--agent", "random", "--out", str(tmp_path / "a-file")],
                 ["eval", "--agent", "random", "--out", UNWRITABLE + ".csv"],
                 ["eval", "--agent", "random", "--out", str(tmp_path / "folder.csv")],
                 ["eval", "--table", "--out", UNWRITABLE],
                 ["eval", "--agent", "gnbv", "--weights", "weights/a3de.pt"],     # weights for a baseline
                 ["train", "--out", UNWRITABLE]):
        one_line_exit_two(capsys, args)
    assert not list(tmp_path.glob("**/*.tmp*"))


def test_a_failed_image_or_video_write_is_one_line_and_exit_two(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(of.cv2, "imwrite", lambda *args, **kwargs: False)
    err = one_line_exit_two(capsys, ["demo", "--agent", "random", "--seed", "2", "--out", str(tmp_path)])
    assert "could not write" in err and [p.name for p in tmp_path.iterdir()] == [of.LOCK_NAME]


def test_a_non_finite_or_misshapen_action_is_refused_and_the_env_goes_on(ap_env):
    fresh = of.ObjectFindingEnv("ap", "cubes")
    with pytest.raises(RuntimeError, match="reset"):
        fresh.step(np.zeros(6))                                          # before any reset
    fresh.close()
    obs, _ = ap_env.reset(seed=3)
    for bad, name in (([np.nan, 0, 0, 0, 0, -1], "dx"), ([0, 0, 0, 0, np.nan, -1], "yaw"),
                      ([0, 0, np.inf, 0, 0, -1], "dz"), (np.zeros((2, 3)), "shape"), ([0, 0, 1], "shape")):
        with pytest.raises(ValueError, match=name):
            ap_env.step(np.array(bad, np.float64))
    obs, reward, done, _, info = ap_env.step(np.array([0, 0, 1, 0, 0, -1.0]))
    assert np.all(np.isfinite(obs)) and np.isfinite(reward) and info["steps"] == 1 and not done
    ap_env.step(of.stop_action())
    with pytest.raises(RuntimeError, match="ended"):
        ap_env.step(np.zeros(6))                                         # after the episode's end


def test_dropped_envs_release_their_physics_connection():
    import gc
    clients = []
    for _ in range(20):
        env = of.ObjectFindingEnv("ap", "cubes")
        env.reset(seed=0)
        clients.append(env.sim._client)
        del env                                                           # no close()
    gc.collect()
    assert not any(of.pb.isConnected(physicsClientId=c) for c in clients)


def broken_checkpoints(tmp_path) -> dict:
    good = of.read_checkpoint(Path(of.__file__).parent / "weights" / "a3de.pt")
    cases = {"wrong shapes": dict(good, model={k: v[..., :3] if v.ndim else v for k, v in good["model"].items()}),
             "another obs_dim": dict(good, obs_dim=40),
             "another hidden": dict(good, settings=dict(good["settings"], hidden=64)),
             "no settings": {k: v for k, v in good.items() if k != "settings"},
             "NaN weights": dict(good, model={k: v * float("nan") if v.is_floating_point() else v
                                              for k, v in good["model"].items()})}
    paths = {}
    for name, checkpoint in cases.items():
        paths[name] = tmp_path / (name.replace(" ", "-") + ".pt")
        of.torch.save(checkpoint, paths[name])
    return paths


def test_a_checkpoint_of_the_wrong_shape_or_with_nan_weights_is_one_line_everywhere(tmp_path, capsys, monkeypatch):
    no_episodes(monkeypatch)
    for name, path in broken_checkpoints(tmp_path).items():
        for args in (["eval", "--agent", "a3de", "--weights", str(path)],
                     ["demo", "--agent", "a3de", "--weights", str(path)],
                     ["train", "--init", str(path), "--out", str(tmp_path / "run")]):
            one_line_exit_two(capsys, args)
        run = tmp_path / ("resume-" + path.stem)
        run.mkdir()
        (run / "checkpoint.pt").write_bytes(path.read_bytes())
        one_line_exit_two(capsys, ["train", "--resume", "--out", str(run)])


def test_resume_keeps_the_runs_task_and_scene(tmp_path, capsys, monkeypatch):
    of.train(Reach, tmp_path / "run", total_steps=256, ppo=TINY_PPO, progress=False, meta=dict(task="ip", scene="cubes"))
    run = str(tmp_path / "run")
    assert "trains on task ip" in one_line_exit_two(capsys, ["train", "--resume", "--task", "ap", "--out", run])
    assert "scene cubes" in one_line_exit_two(capsys, ["train", "--resume", "--scene", "random-shapes", "--out", run])
    made = []
    monkeypatch.setattr(of, "train", lambda make_env, *args, **kwargs: made.append(make_env.args) or
                        dict(env_steps=0, update=0))
    assert of.main(["train", "--resume", "--out", run]) == 0 and made == [("ip", "cubes")]


def test_a_run_gives_the_same_weights_with_any_worker_count_resumed_or_not(tmp_path):
    """Streams belong to the run: 3 streams served by 2 processes, by 1, and resumed on 1 after a stop."""
    env = functools.partial(of.ObjectFindingEnv, "ap", "cubes")
    p = of.PPOSettings(hidden=16, batch_steps=63, minibatch=21, epochs=2, checkpoint_every=1)
    straight = of.train(env, tmp_path / "a", total_steps=126, ppo=p, workers=2, streams=3, progress=False)
    alone = of.train(env, tmp_path / "c", total_steps=126, ppo=p, workers=1, streams=3, progress=False)
    of.train(env, tmp_path / "b", total_steps=63, ppo=p, workers=2, streams=3, progress=False)
    resumed = of.train(env, tmp_path / "b", total_steps=126, ppo=p, workers=1, progress=False,
                       resume=of.read_checkpoint(tmp_path / "b" / "checkpoint.pt", run=True))
    assert of.read_checkpoint(tmp_path / "b" / "checkpoint.pt", run=True)["rollout_streams"] == 3
    for other in (alone, resumed):
        for (name, a), b in zip(straight["model"].state_dict().items(), other["model"].state_dict().values()):
            assert torch.equal(a, b), name


def test_training_keeps_its_last_update_and_an_interrupted_one(tmp_path, monkeypatch, capsys):
    p = dataclasses.replace(TINY_PPO, checkpoint_every=5)
    of.train(Reach, tmp_path / "short", total_steps=256 * 2, ppo=p, progress=False)
    assert of.read_checkpoint(tmp_path / "short" / "checkpoint.pt")["update"] == 2   # the last update
    real_update, calls = of.ppo_update, []

    def interrupted_third_update(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real_update(*args, **kwargs)
    monkeypatch.setattr(of, "ppo_update", interrupted_third_update)
    with pytest.raises(of.TrainingInterrupted) as stop:
        of.train(Reach, tmp_path / "cut", total_steps=256 * 10, ppo=p, progress=False)
    assert stop.value.update == 2 and of.read_checkpoint(tmp_path / "cut" / "checkpoint.pt")["update"] == 2
    assert len(of.read_train_log(tmp_path / "cut" / "log.csv", 2)) == 2
    monkeypatch.setattr(of, "ppo_update", real_update)
    resumed = of.train(Reach, tmp_path / "cut", total_steps=256 * 3, ppo=p, progress=False,
                       resume=of.read_checkpoint(tmp_path / "cut" / "checkpoint.pt", run=True))
    assert resumed["update"] == 3
    # on the command line: one line saying what was kept and how to resume
    monkeypatch.setattr(of, "train", lambda *a, **k: (_ for _ in ()).throw(
        of.TrainingInterrupted(7, 35000, tmp_path / "x" / "checkpoint.pt")))
    assert of.main(["train", "--out", str(tmp_path / "x")]) == 130
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "kept update 7 (35000 env steps)" in err and "--resume --out" in err


def test_the_success_interval_never_prints_minus_zero(capsys):
    assert of.wilson_interval(0, 20)[0] == 0.0 and of.wilson_interval(20, 20)[1] == 1.0
    rows = [dict(seed=i, target_present=True, success=False, steps=130, target_seen_fraction=0.0,
                 explored_fraction=0.5, decision_ms=1.0) for i in range(20)]
    of.print_summary("gnbv", "ap", "cubes", of.summarise(rows), 1.0)
    assert "-0.0" not in capsys.readouterr().out


def test_a_short_soak_finds_no_crash_no_nan_and_no_leak():
    counts = soak.run_soak(episodes=10, workers=1, progress=False)
    assert counts["episodes"] == 10 and counts["refused"] > 0
    assert counts["crashes"] == 0 and counts["non_finite"] == 0 and counts["leaked"] == 0, counts["first_crash"]


def test_the_stops_study_records_each_stop_with_the_estimated_and_the_true_share():
    rows = stops.stop_chunk("gnbv", "ap", "cubes", [0, 1, 2, 3], None)
    assert [row["seed"] for row in rows] == [0, 1, 2, 3] and all(0 <= row["true_share"] <= 1 for row in rows)
    assert any(row["claimed_found"] for row in rows)
    bar = of.TASKS["ap"].claim_margin * of.TASKS["ap"].seen_threshold
    for row in rows:   # a claim "found" has the estimate above the bar, and succeeds exactly when the truth is
        assert not row["claimed_found"] or (row["stopped"] and row["perceived_share"] > bar)
        assert not row["claimed_found"] or row["success"] == (row["true_share"] > 0.2)
    table = stops.stops_markdown({("gnbv", "ap", "cubes"): rows}, 0.2).splitlines()
    assert len(table) == 3 and table[-1].startswith("| gnbv | ap / cubes | ")


def test_a_stop_rule_scored_on_a_trace_gives_the_episodes_that_rule_plays():
    cfg, seeds = of.TASKS["ap"], [0, 1, 2, 3, 4, 5]
    played = stops.stop_chunk("gnbv", "ap", "cubes", seeds, None)
    traces = stops.trace_chunk("gnbv", "ap", "cubes", seeds, None)
    scored = [stops.score_rule(t, cfg.claim_margin, cfg.confirm_views, cfg.seen_threshold) for t in traces]
    assert [(s[2], s[3]) for s in scored] == [(r["success"], r["steps"]) for r in played]
    assert [s[0] for s in scored] == [r["claimed_found"] for r in played] and any(s[0] for s in scored)
    assert [s[3] for s in (stops.score_rule(t, 1.0, 1, 0.2) for t in traces)] != [s[3] for s in scored]
    assert stops.rules_arg("1x1, 1.25x2") == [(1.0, 1), (1.25, 2)]
    with pytest.raises(of.UsageError, match="is not MxV"):
        stops.rules_arg("0.9x2")


def test_the_estimates_study_scores_each_estimate_by_the_area_under_its_roc_curve():
    seen = np.array([False, False, True, True])
    assert stops.separation(np.array([0.1, 0.2, 0.3, 0.4]), seen) == 1.0
    assert stops.separation(np.array([0.4, 0.3, 0.2, 0.1]), seen) == 0.0
    assert stops.separation(np.array([0.1, 0.3, 0.2, 0.4]), seen) == 0.75   # 3 of 4 pairs in order
    assert stops.separation(np.ones(4), seen) == 0.5                         # ties: a coin
    trace = stops.trace_chunk("a3de", "ap", "cubes", [4], of.learned_policy("a3de", "ap"))[0]
    assert len(trace["detection_sum"]) == len(trace["perceived"]) == trace["steps"]
    assert max(trace["detection_sum"]) > max(trace["perceived"]) > 0   # the raw sum counts false positives too
    table = stops.estimates_markdown({("a3de", "ap", "cubes"): [trace]}).splitlines()
    assert len(table) == 3 and table[-1].startswith("| a3de | ap / cubes | ")


def test_a_short_arm_soak_gets_only_finite_goals_within_a_step_and_no_traceback():
    arm = soak.run_arm_soak(frames=600, workers=1, progress=False)
    assert arm["frames"] == 600 and arm["goals"] > 100 and arm["refused"] > 100 and arm["stops"] > 0
    failures = (arm["non_finite_goals"], arm["leaps"], arm["tracebacks"], arm["wrongly_refused"])
    assert failures == (0, 0, 0, 0), arm["first_failure"]


# ------------------------------------------------------------------------------------------------
# one information rule for every agent
# ------------------------------------------------------------------------------------------------


def state_share_seen_the_same_way(side_m: float, target_size_known: bool) -> float:
    """The state's detection factor after three views of a lone red cube of side `side_m`, placed at
    distances in proportion to its size: from above and from two sides."""
    env = of.ObjectFindingEnv("ap", "variable-primitives", target_size_known=target_size_known)
    env.reset(seed=1)
    for o in env.objects:
        env.sim.removeBody(o.body)
    s = dataclasses.replace(env.cfg, object_size_m=side_m)
    target = of.make_object(env.sim, "cubes", s, np.random.default_rng(0), of.TARGET_RGBA)
    of.add_bodies(env.sim, [target], s)
    env.sim.resetBasePositionAndOrientation(target.body, [0, 0, side_m / 2], [0, 0, 0, 1])
    env.objects, env.target_present = [target], True
    env.target_area_m2 = of.mesh_area(target.vertices, target.faces)
    # what reset tells the searcher under each rule
    env.searcher.reset(env.target_area_m2 if target_size_known else env.cfg.nominal_target_area_m2)
    env.np_random = np.random.default_rng(0)                  # the same detector noise for every size
    for offset in ([0, 0, 4], [3, 0, 3], [0, 3, 3]):
        direction = -np.array(offset, float) / np.linalg.norm(offset)
        roll = np.arctan2(np.hypot(direction[0], direction[1]), -direction[2])
        yaw = np.arctan2(direction[1], direction[0]) if offset[:2] != [0, 0] else 0.0
        env._teleport(np.array(offset, float) * side_m + [0, 0, side_m], of.gripper_rotation(yaw, roll))
        env._observe()
    value = float(env.searcher.state(env.gripper_pose())[of.STATE_TARGET_SHARE])
    env.close()
    return value


def test_the_state_detection_factor_is_a_share_of_the_told_target_size():
    cube, twice = (state_share_seen_the_same_way(side, True) for side in (0.04, 0.08))
    assert 0.75 < twice / cube < 1.33                      # the same share of a target twice the size
    cube_b, twice_b = (state_share_seen_the_same_way(side, False) for side in (0.04, 0.08))
    assert cube_b == pytest.approx(cube) and twice_b / cube_b > 2.5   # no size told: 4x the surface, 4x the sum


def test_the_state_share_is_on_the_simulated_cameras_scale():
    """The rig's estimate spreads wider (its searchers claim at 2 x the bar, not 1.25 x): the state shrinks the
    share by that ratio on both real presets, so that a policy trained in simulation meets it on its own scale."""
    env = of.ObjectFindingEnv("ap-real", "cubes-and-cuboids")
    env.reset(seed=0)   # the first view perceives about 20 % of the target
    share = env.searcher.perceived_target_share()
    assert share > 0.1
    assert env.searcher.state(env.gripper_pose())[of.STATE_TARGET_SHARE] == np.float32(share * 1.25 / 2.0)
    env.close()
    assert [of.Searcher(cfg).state_share_scale for cfg in of.TASKS.values()] == [1.0, 1.0, 1.0, 0.625, 0.625]


def test_the_state_carries_the_perceived_share_and_no_false_positive():
    """The detection part's factor is the searcher's estimate of the share seen: the detector's false positives,
    which fill the detection channel in every scene, do not raise it where no target is."""
    for seed, present in ((4, True), (1, False)):   # seed 4: these moves see 41 % of the target
        env = of.ObjectFindingEnv("ap", "cubes", no_target_prob=0.0 if present else 1.0)
        env.reset(seed=seed)
        for _ in range(4):
            env.step(np.array([0.5, 0.3, -0.3, 0.0, 0.4, -1.0], np.float32))
        state = env.searcher.state(env.gripper_pose())
        assert state[of.STATE_TARGET_SHARE] == np.float32(env.searcher.perceived_target_share())
        assert env.searcher.volume.detections.sum() > 0                # false positives (and the target) fused
        assert (state[of.STATE_TARGET_SHARE] > 0) == present
        env.close()


def test_every_agent_runs_on_the_searcher_alone_and_the_searcher_is_told_only_the_rule():
    for known in (True, False):
        env = of.ObjectFindingEnv("ip", "variable-primitives", target_size_known=known)
        for name in list(of.BASELINES) + list(of.LEARNED):
            env.reset(seed=5)
            searcher = env.searcher
            assert not any(isinstance(v, (of.ObjectFindingEnv, of.PhysicsClient, of.Settings))
                           for v in vars(searcher).values())
            assert searcher.target_area_m2 == (env.target_area_m2 if known else env.cfg.nominal_target_area_m2)
            policy = of.learned_policy(name, "ip") if name in of.LEARNED else None
            agent = of.make_agent(name, env.cfg, 5, policy)
            agent.reset(searcher, env.gripper_pose())
            assert not any(isinstance(v, (of.ObjectFindingEnv, of.PhysicsClient, of.Settings))
                           for v in vars(agent).values())
            for _ in range(8):                               # each agent acts on the searcher alone
                _, _, done, _, _ = env.step(agent.act(searcher, env.gripper_pose()))
                if done:
                    break
        assert env.target_present and abs(env.target_area_m2 / env.cfg.nominal_target_area_m2 - 1) > 0.05
        env.close()


def test_gnbv_ends_a_scene_without_target_by_the_explored_criterion():
    env = of.ObjectFindingEnv("ap", "cubes")
    agent = of.make_agent("gnbv", env.cfg, 25)
    obs, info = env.reset(seed=25)
    agent.reset(env.searcher, env.gripper_pose())
    done = False
    while not done:
        obs, _, done, _, info = env.step(agent.act(env.searcher, env.gripper_pose()))
    env.close()
    assert not info["target_present"] and info["terminated_by_agent"] and info["success"]
    assert info["steps"] < env.cfg.horizon and info["explored_fraction"] > env.cfg.gnbv_explored_to_stop
    assert agent.stalled < env.cfg.gnbv_stall_steps         # ended by 97 % explored, not by the stall rule


# ------------------------------------------------------------------------------------------------
# the robot's side: a Searcher needs no simulator
# ------------------------------------------------------------------------------------------------

def recorded_episode(agent_name: str, task: str, seed: int) -> tuple:
    """An env episode as a robot would log it: per view the depth, the detections, the camera's and
    the gripper's poses; per step the state and the action. The env is closed before returning."""
    env = of.ObjectFindingEnv(task, "cubes")
    policy = of.learned_policy(agent_name, task) if agent_name in of.LEARNED else None
    agent = of.make_agent(agent_name, env.cfg, seed, policy)
    obs, _ = env.reset(seed=seed)
    told = env.searcher.target_area_m2
    agent.reset(env.searcher, env.gripper_pose())
    views, states, actions, done = [], [obs], [], False
    while not done:
        views.append((env.view.depth_m, env.view.detections, env.view.T_world_camera, env.gripper_pose()))
        actions.append(agent.act(env.searcher, env.gripper_pose()))
        obs, _, done, _, _ = env.step(actions[-1])
        states.append(obs)
    client = env.sim._client
    env.close()
    assert not of.pb.isConnected(physicsClientId=client)
    return env.cfg, told, views, states, actions


class NoPhysics:
    """Stands in for pybullet: any use of it, or a new physics client, fails the test."""

    def __getattr__(self, name):
        raise AssertionError(f"pybullet's {name} was used")

    def __call__(self, *args, **kwargs):
        raise AssertionError("a physics client was opened")


@pytest.fixture
def no_physics(monkeypatch):
    monkeypatch.setattr(of, "pb", NoPhysics())
    monkeypatch.setattr(of, "PhysicsClient", NoPhysics())


@pytest.mark.parametrize("agent_name, task, seed", [("gnbv", "ap", 7), ("a3de", "ap", 7003), ("ges", "ip", 2)])
def test_a_searcher_fed_a_recorded_episode_gives_its_states_and_its_agent_acts_the_same(agent_name, task, seed,
                                                                                       request):
    cfg, told, views, states, actions = recorded_episode(agent_name, task, seed)
    request.getfixturevalue("no_physics")
    searcher = of.Searcher(cfg)
    searcher.reset(told)
    policy = of.learned_policy(agent_name, task) if agent_name in of.LEARNED else None
    agent = of.make_agent(agent_name, cfg, seed, policy)
    for i, (depth_m, detections, T_world_camera, T_world_tool) in enumerate(views):
        searcher.observe(depth_m, T_world_camera, detections=detections)
        if i == 0:
            agent.reset(searcher, T_world_tool)
        assert np.array_equal(searcher.state(T_world_tool), states[i]), i      # bit for bit
        assert np.array_equal(agent.act(searcher, T_world_tool), actions[i]), i
    assert len(actions) >= 2


def test_detections_of_an_offset_rgb_camera_land_where_its_pixels_see_in_the_depth_image():
    depth_camera = of.wrist_rig(of.TASKS["ap"]).depth
    K_rgb = np.array([[100.0, 0, 64], [0, 100.0, 48], [0, 0, 1]])
    rgb_camera = of.Camera(128, 96, K_rgb)
    T_depth_rgb = np.eye(4)
    T_depth_rgb[0, 3] = 0.05                          # the RGB camera 5 cm to the depth camera's right
    rig = of.Rig(depth_camera, rgb_camera, np.eye(4), T_depth_rgb)
    depth_m = np.full((depth_camera.height, depth_camera.width), 0.5, np.float32)   # a wall 0.5 m ahead
    depth_m[:, :5] = 0.0                                                             # no return there
    detections = np.zeros((96, 128), np.float32)
    detections[40:56, 70:90] = 1.0                    # a red patch in the RGB image
    mapped = rig.detections_in_depth_image(detections, depth_m)
    K = depth_camera.K
    rows, cols = np.mgrid[0:depth_camera.height, 0:depth_camera.width] + 0.5
    x, y = (cols - K[0, 2]) / K[0, 0] * 0.5, (rows - K[1, 2]) / K[1, 1] * 0.5
    u = np.floor(K_rgb[0, 0] * (x - 0.05) / 0.5 + K_rgb[0, 2])   # where each depth pixel lands in the RGB image
    v = np.floor(K_rgb[1, 1] * y / 0.5 + K_rgb[1, 2])
    expected = (u >= 70) & (u < 90) & (v >= 40) & (v < 56) & (depth_m > 0)
    assert expected.sum() > 10 and np.array_equal(mapped > 0, expected)
    same = of.wrist_rig(of.TASKS["ap"])               # one RGB-D camera: the scores pass unchanged
    assert same.detections_in_depth_image(depth_m, depth_m) is depth_m


def test_a_new_ppo_setting_is_one_field_and_round_trips_through_a_checkpoint_and_set(tmp_path, monkeypatch, capsys):
    extended = dataclasses.make_dataclass("PPOSettings", [("momentum", float, 0.5)], bases=(of.PPOSettings,),
                                          frozen=True)
    monkeypatch.setattr(of, "PPOSettings", extended)
    run = tmp_path / "run"
    small = ["--set", "batch_steps=32", "--set", "hidden=8", "--set", "minibatch=16", "--set", "epochs=1"]
    assert of.main(["train", "--task", "ap", "--out", str(run), "--steps", "32", "--streams", "1",
                    "--set", "momentum=0.7", *small]) == 0
    assert of.read_checkpoint(run / "checkpoint.pt")["settings"]["momentum"] == 0.7
    assert of.main(["train", "--resume", "--out", str(run), "--steps", "64", "--workers", "1"]) == 0
    checkpoint = of.read_checkpoint(run / "checkpoint.pt", run=True)
    assert checkpoint["update"] == 2 and of.ppo_settings(checkpoint["settings"]).momentum == 0.7
    assert of.main(["eval", "--agent", "a3de", "--weights", str(run / "checkpoint.pt"), "--episodes", "1",
                    "--workers", "1"]) == 0
    capsys.readouterr()
    assert of.main(["train", "--out", str(tmp_path / "bad"), "--set", "momentum=nan"]) == 2
    assert "momentum" in capsys.readouterr().err and not (tmp_path / "bad").exists()


def test_a_run_keeps_its_schedule_and_the_schedule_moves_linearly_from_start_to_end(tmp_path):
    run = tmp_path / "run"
    small = ["--set", "batch_steps=32", "--set", "hidden=8", "--set", "minibatch=16", "--set", "epochs=1"]
    assert of.main(["train", "--task", "ap", "--out", str(run), "--steps", "32", "--streams", "1", "--workers", "1",
                    "--set", "entropy_end_ratio=0.1", "--set", "learning_rate_end_ratio=0.5",
                    "--set", "gamma_end_ratio=0.98", *small]) == 0
    checkpoint = of.read_checkpoint(run / "checkpoint.pt", run=True)
    assert checkpoint["schedule_steps"] == 32 and checkpoint["update"] == 1
    ppo = of.ppo_settings(checkpoint["settings"])
    assert (ppo.entropy_end_ratio, ppo.learning_rate_end_ratio, ppo.gamma_end_ratio) == (0.1, 0.5, 0.98)
    assert (ppo.schedule_start_share, ppo.schedule_share) == (0.8, 0.85)      # the recipe's, kept
    optimizer = torch.optim.Adam(of.ActorCritic(of.STATE_SIZE, ppo).parameters(), lr=ppo.learning_rate)
    for done_share, entropy_share, lr_share, gamma_share in ((0.0, 1.0, 1.0, 1.0), (0.8, 1.0, 1.0, 1.0),
                                                             (0.825, 0.55, 0.75, 0.99), (0.85, 0.1, 0.5, 0.98),
                                                             (1.0, 0.1, 0.5, 0.98)):
        now = of.scheduled(ppo, optimizer, done_share)
        assert now.entropy_coef == pytest.approx(ppo.entropy_coef * entropy_share)
        assert optimizer.param_groups[0]["lr"] == pytest.approx(ppo.learning_rate * lr_share)
        assert now.gamma == pytest.approx(ppo.gamma * gamma_share)
    assert of.scheduled(of.PPOSettings(), optimizer, 0.7).entropy_coef == of.PPOSettings().entropy_coef * (
        1 + (of.PPOSettings().entropy_end_ratio - 1) * 0.7)   # the defaults are a schedule too
    ppo = dataclasses.replace(ppo, schedule_start_share=0.0, schedule_share=1.0)   # linear over the whole run
    half = dataclasses.replace(ppo, schedule_share=0.5)      # the schedule ends half-way and holds
    for done_share, entropy_share in ((0.0, 1.0), (0.25, 0.55), (0.5, 0.1), (0.75, 0.1), (1.0, 0.1)):
        assert of.scheduled(half, optimizer, done_share).entropy_coef == pytest.approx(ppo.entropy_coef * entropy_share)
    late = dataclasses.replace(ppo, schedule_start_share=0.5)   # holds half-way, then moves to the end
    for done_share, entropy_share in ((0.0, 1.0), (0.5, 1.0), (0.75, 0.55), (1.0, 0.1)):
        assert of.scheduled(late, optimizer, done_share).entropy_coef == pytest.approx(ppo.entropy_coef * entropy_share)
    with pytest.raises(of.UsageError, match="schedule_start_share"):
        of.ppo_settings({"schedule_start_share": 0.5, "schedule_share": 0.5})


def test_train_with_no_flags_runs_its_agents_recipe_and_set_and_resume_change_it(tmp_path, monkeypatch):
    asked = []
    monkeypatch.setattr(of, "train", lambda make_env, out, steps, ppo, **kwargs: asked.append((steps, ppo)) or
                        {"env_steps": steps, "update": 1})
    for task, agent in (("ap", "a3de"), ("ap-large", "a3de"), ("ip", "i3de"), ("ip-real", "i3de")):
        assert of.main(["train", "--task", task, "--out", str(tmp_path / task)]) == 0
        steps, recipe = of.TRAIN_RECIPES[agent]
        assert asked[-1] == (steps, of.ppo_settings(recipe))
    assert asked[0][1].entropy_end_ratio < 1 and asked[2][1].schedule_share < 1     # the recipes are schedules
    assert of.main(["train", "--task", "ip", "--out", str(tmp_path / "set"), "--steps", "500",
                    "--set", "schedule_share=0.5"]) == 0
    assert asked[-1] == (500, of.ppo_settings({**of.TRAIN_RECIPES["i3de"][1], "schedule_share": 0.5}))
    run = tmp_path / "resumed"
    run.mkdir()
    torch.save({"task": "ip", "scene": "cubes", "schedule_steps": 777, "update": 3, "env_steps": 15,
                "settings": dataclasses.asdict(of.PPOSettings())}, run / "checkpoint.pt")
    monkeypatch.setattr(of, "read_checkpoint", lambda path, run=False: torch.load(path, weights_only=True))
    assert of.main(["train", "--resume", "--out", str(run)]) == 0
    assert asked[-1][0] == 777                                                      # its own schedule's length


def test_train_runs_in_a_fresh_clone(tmp_path):
    listed = subprocess.run(["git", "ls-files"], cwd=HERE, capture_output=True, text=True)
    if listed.returncode != 0:
        pytest.skip("not a git checkout")
    clone = tmp_path / "clone"
    for name in listed.stdout.splitlines():
        assert not name.startswith("runs/"), name          # no old runs to trip over
        source = HERE / name
        if source.is_file():
            (clone / name).parent.mkdir(parents=True, exist_ok=True)
            (clone / name).write_bytes(source.read_bytes())
    done = subprocess.run([sys.executable, "objfind.py", "train", "--task", "ip", "--steps", "24", "--streams", "2",
                           "--set", "batch_steps=24", "--set", "minibatch=12"], cwd=clone, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert of.read_checkpoint(clone / "runs" / "ip-cubes" / "checkpoint.pt", run=True)["update"] == 1


# ------------------------------------------------------------------------------------------------
# two runs at once, a closed output, a full disk, a dead worker: nothing lost, nothing false
# ------------------------------------------------------------------------------------------------

def fake_rows(seed: int, episodes: int, agent="gnbv", task="ap", scene="cubes", policy=None, overrides=None) -> list:
    """Rows as `evaluate` writes them, with the origin a cell of this agent would have."""
    origin = of.cell_origin(agent, task, scene, policy, overrides)
    return [dict(seed=s, target_present=True, success=True, steps=3, target_seen_fraction=0.3,
                 explored_fraction=0.2, decision_ms=1.0, **origin) for s in range(seed, seed + episodes)]


def test_a_second_run_into_a_folder_being_written_is_refused_and_the_first_keeps_its_cells(tmp_path, capsys,
                                                                                        monkeypatch):
    out, second = tmp_path / "results", []

    def evaluate_while_a_second_run_starts(agent, task, scene, episodes, seed, workers, **kwargs):
        if not second:   # the same job submitted twice: a real second process into the same folder
            second.append(subprocess.run([sys.executable, "objfind.py", "eval", "--table", "--episodes", "2",
                                          "--out", str(out)], cwd=HERE, capture_output=True, text=True))
        return fake_rows(seed, episodes, agent, task, scene, kwargs.get("policy"), kwargs.get("overrides"))
    monkeypatch.setattr(of, "evaluate", evaluate_while_a_second_run_starts)
    assert of.main(["eval", "--table", "--episodes", "1", "--out", str(out)]) == 0
    refused = second[0]
    assert refused.returncode == 2 and len(refused.stderr.strip().splitlines()) == 1, refused.stderr
    assert "being written by another objfind run" in refused.stderr
    cells = sorted(out.glob("*.csv"))
    assert len(cells) == sum(map(len, of.PAPER_TABLE_II.values()))            # all the first run's cells
    assert all(len(of.read_episodes(cell)) == 1 for cell in cells)
    assert (out / "table2.md").exists() and not list(out.glob(".*.tmp*"))   # no temporary file left
    # the lock of a run that was killed is free again; one held by a live process is not
    hold = (f"import filelock, time; lock = filelock.FileLock({str(out / of.LOCK_NAME)!r}); lock.acquire(timeout=0); "
            "print('held', flush=True); time.sleep(60)")
    holder = subprocess.Popen([sys.executable, "-c", hold], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        capsys.readouterr()
        assert "being written" in one_line_exit_two(capsys, ["train", "--out", str(out)])
        assert of.locked_by_another(out)
    finally:
        holder.kill()
        holder.wait()
    assert of.main(["eval", "--table", "--from-csv", "--episodes", "1", "--out", str(out)]) == 0


def test_eval_into_a_closed_pipe_still_writes_its_csv(tmp_path):
    csv_path = tmp_path / "episodes.csv"
    done = subprocess.run(f"{sys.executable} objfind.py eval --agent random --episodes 2 --workers 1 "
                          f"--out {csv_path} | head -0", shell=True, cwd=HERE, capture_output=True, text=True)
    assert "Traceback" not in done.stderr, done.stderr
    assert len(of.read_episodes(csv_path)) == 2


def test_a_video_that_could_not_be_written_whole_leaves_the_old_one_and_exits_two(tmp_path, capsys, monkeypatch):
    video = tmp_path / "demo-ap-cubes-random.mp4"
    video.write_bytes(b"the good video of an earlier run")
    real_writer = of.cv2.VideoWriter

    class FullDisk:   # as on a full disk: frames after the first few are lost, and OpenCV says nothing
        def __init__(self, *args):
            self.writer, self.frames = real_writer(*args), 0

        def isOpened(self):
            return self.writer.isOpened()

        def write(self, frame):
            self.frames += 1
            if self.frames <= 2:
                self.writer.write(frame)

        def release(self):
            self.writer.release()
    monkeypatch.setattr(of.cv2, "VideoWriter", FullDisk)
    err = one_line_exit_two(capsys, ["demo", "--agent", "random", "--seed", "2", "--out", str(tmp_path)])
    assert "frames" in err and video.read_bytes() == b"the good video of an earlier run"
    assert not list(tmp_path.glob("*tmp*"))


def worker_processes(parent: int) -> list:
    """The pids of `parent`'s spawned worker processes (Linux /proc)."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields, cmdline = stat.read_text().rsplit(")", 1)[1].split(), (stat.parent / "cmdline").read_bytes()
        except OSError:
            continue
        if int(fields[1]) == parent and b"spawn_main" in cmdline:
            pids.append(int(stat.parent.name))
    return pids


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds worker processes through /proc")
@pytest.mark.parametrize("command", [["eval", "--agent", "gnbv", "--episodes", "200", "--out", "episodes.csv"],
                                     ["train", "--steps", "200000", "--set", "batch_steps=4000", "--out", "run"]])
def test_a_killed_worker_ends_the_command_with_one_line_and_exit_two(command, tmp_path):
    import os
    import signal
    import time
    run = subprocess.Popen([sys.executable, str(HERE / "objfind.py"), *command, "--workers", "2"], cwd=tmp_path,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not (workers := worker_processes(run.pid)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert workers, "no worker process started"
    time.sleep(2)
    os.kill(workers[0], signal.SIGKILL)               # as the OOM killer would
    _, err = run.communicate(timeout=60)              # ends within a bounded time, never hangs
    said = [line for line in err.replace("\r", "\n").splitlines() if line.startswith("objfind:")]   # no bar
    assert run.returncode == 2 and len(said) == 1 and "worker process died" in said[0], err


def test_an_env_refuses_to_be_copied_and_goes_on(ap_env):
    import copy
    import pickle
    ap_env.reset(seed=1)
    for copy_it in (copy.deepcopy, copy.copy, pickle.dumps):
        with pytest.raises(TypeError, match="cannot be copied"):
            copy_it(ap_env)
    obs, *_ = ap_env.step(np.zeros(6))
    assert np.all(np.isfinite(obs))


def test_a_csv_saved_by_a_spreadsheet_with_a_byte_order_mark_reads_back(tmp_path):
    path = tmp_path / "cell.csv"
    of.write_csv(fake_rows(0, 3), path)
    path.write_bytes("\ufeff".encode() + path.read_bytes())
    assert [row["seed"] for row in of.read_episodes(path)] == [0, 1, 2]


def test_runs_into_different_run_folders_go_on_side_by_side(tmp_path):
    of.writable_folder(tmp_path / "runs")                        # as a run holds it: its own folder only
    of.writable_folder(tmp_path / "runs" / "ap-cubes")
    try:
        small = ["--steps", "24", "--set", "batch_steps=24", "--set", "minibatch=12", "--workers", "1"]
        train = lambda task: subprocess.run([sys.executable, str(HERE / "objfind.py"), "train", "--task", task, *small],
                                            cwd=tmp_path, capture_output=True, text=True, timeout=300)
        beside, same = train("ip"), train("ap")
        assert beside.returncode == 0, beside.stderr[-500:]
        assert same.returncode == 2 and "being written" in same.stderr
    finally:
        of.release_locks()


@pytest.mark.parametrize("overrides, field", [
    (dict(min_objects=30, max_objects=5), "min_objects"), (dict(pile_margin_ratio=0.5), "pile_margin_ratio"),
    (dict(num_piles=3, min_objects=2), "num_piles"), (dict(horizon=0), "horizon"),
    (dict(voxels_per_side=2.5), "voxels_per_side"), (dict(trunc_m=float("nan")), "trunc_m"),
    (dict(num_piles=3, pile_overlap_chance=0.0), "pile_overlap_chance"), (dict(variable_scale=(2.0, 1.0)), "variable_scale"),
    (dict(target_size_known="no"), "target_size_known"), (dict(object_size_m=0.2), "object_size_m"),
    (dict(state_voxel_m=0.0), "state_voxel_m"), (dict(horizon=10 ** 400), "horizon")])
def test_settings_that_cannot_build_a_scene_are_refused_at_construction_naming_the_field(overrides, field):
    with pytest.raises(ValueError, match=f"^{field}="):
        of.ObjectFindingEnv("ip", **overrides)
    with pytest.raises(ValueError, match=f"^{field}="):
        of.checked_settings("ip", overrides)


def test_step_or_reset_after_close_says_the_env_is_closed():
    env = of.ObjectFindingEnv("ap", seed=2)
    env.reset()
    env.close()
    for call in (lambda: env.step(np.zeros(6)), env.reset):
        with pytest.raises(RuntimeError, match="is closed: make a new one"):
            call()


@pytest.mark.parametrize("args, said", [
    (["eval", "--agent", "gnbv", "--workers", "100000"], "worker processes"),
    (["eval", "--agent", "gnbv", "--episodes", "10000000"], "number of episodes"),
    (["eval", "--agent", "gnbv", "--seed", str(2 ** 40)], "a seed must be"),
    (["eval", "--agent", "gnbv", "--seed", str(2 ** 32 - 5), "--episodes", "10"], "past the largest seed"),
    (["train", "--set", "hidden=100000"], "hidden=100000"),
    (["train", "--set", "init_log_std=-1000"], "init_log_std=-1000"),
    (["train", "--set", "init_terminate_prob=1e-300"], "init_terminate_prob"),
    (["train", "--world", "state_voxel_m=0"], "state_voxel_m=0"),
    (["eval", "--table", "--scene", "random-shapes"], "drop --scene"),
    (["eval", "--agent", "gnbv", "--from-csv"], "--from-csv reads the cells of --table"),
    (["train", "--resume", "--seed", "3"], "start a new run")])
def test_out_of_bounds_values_and_flags_that_would_be_ignored_are_one_line(args, said, capsys, monkeypatch, tmp_path):
    no_episodes(monkeypatch)
    monkeypatch.chdir(tmp_path)
    try:
        code = of.main(args)
    except SystemExit as error:    # argparse's own checks exit
        code = error.code
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and said in err, err


def test_a_diverging_run_stops_with_one_line_and_keeps_its_last_finite_update(tmp_path, capsys, monkeypatch):
    real_update = of.ppo_update

    def third_update_diverges(model, *args, **kwargs):
        stats = real_update(model, *args, **kwargs)
        if len(calls) == 2:
            with of.torch.no_grad():
                next(model.parameters()).fill_(float("inf"))
                raise FloatingPointError("a non-finite loss or weight")
        calls.append(1)
        return stats
    calls = []
    monkeypatch.setattr(of, "ppo_update", third_update_diverges)
    with pytest.raises(of.TrainingInterrupted) as stop:
        of.train(Reach, tmp_path / "run", total_steps=256 * 10, ppo=TINY_PPO, progress=False)
    assert stop.value.update == 2 and stop.value.cause.startswith("training diverged in update 3")
    assert of.read_checkpoint(tmp_path / "run" / "checkpoint.pt")["update"] == 2   # finite: read_checkpoint checks
    # from the command line: a learning rate that sends the weights to infinity in the first update
    args = ["train", "--steps", "48", "--set", "batch_steps=48", "--set", "learning_rate=1e12", "--workers", "1",
            "--out", str(tmp_path / "cli")]
    monkeypatch.setattr(of, "ppo_update", real_update)
    assert of.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "training diverged in update 1" in err and "nothing was kept" in err, err


def test_resume_checks_the_checkpoints_run_fields_and_a_log_a_spreadsheet_saved(tmp_path, capsys):
    run = tmp_path / "run"
    of.train(Reach, run, total_steps=256 * 2, ppo=TINY_PPO, progress=False)
    of.release_locks()
    good = of.torch.load(run / "checkpoint.pt", weights_only=True)
    for field, value in (("update", -1), ("seed", 2 ** 40), ("wall_s", float("nan")), ("rollout_streams", 0),
                         ("task", "xp"), ("optimizer", [])):
        of.torch.save({**good, field: value}, run / "checkpoint.pt")
        with pytest.raises(of.UsageError, match=f"impossible {field}"):
            of.read_checkpoint(run / "checkpoint.pt", run=True)
    of.torch.save(good, run / "checkpoint.pt")
    log = (run / "log.csv").read_text().splitlines()
    for broken, said in ((log[:2], "ends at update 1, the checkpoint at 2"), ([log[0], log[2], log[1]], "is update 2"),
                         ([log[0], log[1], "2,=SUM(A1)" + log[2][1:]], "not a row of numbers")):
        (run / "log.csv").write_text("\n".join(broken) + "\n")
        with pytest.raises(of.UsageError, match=said):
            of.read_train_log(run / "log.csv", 2)
    # a spreadsheet's byte-order mark and exponent notation read back
    (run / "log.csv").write_text("\ufeff" + "\n".join([log[0], log[1], "2.0" + log[2][1:]]) + "\n", encoding="utf-8")
    assert [row["update"] for row in of.read_train_log(run / "log.csv", 2)] == [1, 2]


def test_a_huge_file_is_refused_as_a_checkpoint_before_it_is_loaded(tmp_path, monkeypatch):
    huge = tmp_path / "huge.pt"
    with open(huge, "wb") as f:
        f.truncate(of.MAX_CHECKPOINT_BYTES + 1)        # sparse: costs no disk
    monkeypatch.setattr(of.torch, "load", lambda *a, **k: pytest.fail("torch.load ran on a huge file"))
    with pytest.raises(of.UsageError, match="an objfind checkpoint has at most 64 MB"):
        of.read_checkpoint(huge)


def test_a_checkpoint_whose_tensors_do_not_fit_names_the_tensor(tmp_path):
    checkpoint = of.torch.load(of.default_weights("a3de", "ap"), weights_only=True)
    name = sorted(checkpoint["model"])[0]
    checkpoint["model"][name] = checkpoint["model"][name][:1]
    of.torch.save(checkpoint, tmp_path / "cut.pt")
    with pytest.raises(of.UsageError, match=f"does not hold an objfind network: size mismatch for {name}"):
        of.read_checkpoint(tmp_path / "cut.pt")


def test_the_twenty_percent_rule_is_one_function_and_a_claim_needs_the_margin_in_views_in_a_row(monkeypatch):
    env = of.ObjectFindingEnv("ip", seed=3)
    env.reset()
    calls, share = [], [0.0]
    real = of.target_observed
    monkeypatch.setattr(of, "target_observed", lambda s, threshold: calls.append((s, threshold)) or real(s, threshold))
    monkeypatch.setattr(of.Searcher, "perceived_target_share", lambda self: share[0])
    bar = env.cfg.claim_margin * env.cfg.seen_threshold
    assert env.cfg.confirm_views == 2 and bar > env.cfg.seen_threshold
    for s in (bar, bar, bar, bar + 1e-3, bar, bar + 1e-3):   # exactly at the bar, or above it once at a time
        share[0] = s
        env._observe()
        assert calls[-1] == (s, bar) and not env.searcher.target_found()
    for name in ("scripted", "gnbv", "ges"):
        agent = of.make_agent(name, env.cfg, seed=0)
        agent.reset(env.searcher, env.gripper_pose())
        assert agent.act(env.searcher, env.gripper_pose())[of.ACTION_MOVES] < 0, name    # does not stop
    env._observe()                                           # above the bar in a second view in a row
    assert env.searcher.target_found()
    for name in ("scripted", "gnbv", "ges"):
        agent = of.make_agent(name, env.cfg, seed=0)
        agent.reset(env.searcher, env.gripper_pose())
        assert agent.act(env.searcher, env.gripper_pose())[of.ACTION_MOVES] > 0, name
    env.target_seen[:] = np.arange(len(env.target_seen)) < 0.2 * len(env.target_seen)   # the truth: exactly 20 %
    calls.clear()
    assert env._info()["target_observed"] is False and calls == [(0.2, 0.2)]
    env.close()


def body_frame_mesh(sim, body: int, urdf_path: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The visual mesh of a loaded URDF body in pybullet's base frame, which is the inertial frame."""
    v, f = of.urdf_mesh(urdf_path)
    _, _, _, inertial_pos, inertial_orn, *_ = sim.getDynamicsInfo(body, -1)
    R = np.array(of.pb.getMatrixFromQuaternion(inertial_orn)).reshape(3, 3)
    return (v * scale - np.array(inertial_pos)) @ R, f


MODEL_PATHS = [(str(Path(of.pybullet_data.getDataPath()) / name), scale) for name, scale in of.OBJECT_MODELS] + \
              [(str(Path(of.pybullet_data.getDataPath()) / "random_urdfs" / f"{i:03d}" / f"{i:03d}.urdf"),
                of.RANDOM_SHAPE_SCALE) for i in (0, 7, 500)]


@pytest.mark.parametrize("path, scale", MODEL_PATHS)
def test_a_cheaper_mesh_model_keeps_the_ground_truths_mesh_in_loadurdfs_frame(path, scale):
    model = of.mesh_model(path, scale)
    sim = of.PhysicsClient()
    try:
        vertices, faces = body_frame_mesh(sim, sim.loadURDF(path, globalScaling=scale), path, scale)
    finally:
        sim.disconnect()
    assert np.allclose(model.vertices, vertices, atol=1e-12) and np.array_equal(model.faces, faces)
    assert len(model.render_faces) <= max(len(faces), 12) and len(model.render_faces) <= 600   # what is rendered
    lo, hi = vertices.min(0), vertices.max(0)
    assert np.all(model.hull >= lo - 1e-12) and np.all(model.hull <= hi + 1e-12) and len(model.hull) <= 64
    assert np.allclose(model.hull.max(0), hi) and np.allclose(model.hull.min(0), lo)   # the hull spans the mesh
    for rest in model.rests:
        assert np.allclose(rest @ rest.T, np.eye(3)) and np.isclose(np.linalg.det(rest), 1.0)


def test_the_targets_ground_truth_comes_from_its_exterior_surface(monkeypatch):
    env = of.ObjectFindingEnv("ap", "object-models")
    for seed in range(20):
        env.reset(seed=seed)
        if env.target_present:
            break
    points, normals, area = of.exterior_surface(*env.objects[0].model, env.cfg.seen_min_cos)
    assert env.target_area_m2 == area
    rows = {tuple(p) for p in np.round(points, 12)}
    assert all(tuple(p) in rows for p in np.round(env.target_points, 12))
    env.close()


@pytest.mark.parametrize("scene", ["object-models", "random-shapes", "fixed-primitives"])
def test_a_second_reset_reuses_models_and_gives_a_fresh_envs_scene(scene):
    used, fresh = of.ObjectFindingEnv("ip", scene), of.ObjectFindingEnv("ip", scene)
    try:
        used.reset(seed=4)
        used.reset(seed=5)
        fresh.reset(seed=5)
        built = of.mesh_model.cache_info().misses
        poses = lambda env: np.array([np.r_[env.sim.getBasePositionAndOrientation(o.body)[0],
                                            env.sim.getBasePositionAndOrientation(o.body)[1]] for o in env.objects])
        assert np.array_equal(poses(used), poses(fresh))
        assert np.array_equal(used.target_points, fresh.target_points) and used.target_area_m2 == fresh.target_area_m2
        assert np.array_equal(used.searcher.state(used.gripper_pose()), fresh.searcher.state(fresh.gripper_pose()))
        used.reset(seed=4)
        assert of.mesh_model.cache_info().misses == built       # the models of a scene seen before: reused
    finally:
        used.close(), fresh.close()


@pytest.mark.parametrize("path, scale", MODEL_PATHS[:6])
def test_a_model_placed_in_a_rest_orientation_stays_there(path, scale):
    cfg, model = of.TASKS["ap"], of.mesh_model(path, scale)
    sim = of.PhysicsClient()
    try:
        sim.setGravity(0, 0, -9.81)
        sim.setPhysicsEngineParameter(fixedTimeStep=1.0 / cfg.physics_hz, numSolverIterations=cfg.solver_iterations)
        sim.createMultiBody(0, sim.createCollisionShape(of.pb.GEOM_PLANE))
        body = sim.createMultiBody(cfg.object_mass_kg, sim.createCollisionShape(of.pb.GEOM_MESH,
                                                                                vertices=model.hull.tolist()))
        sim.changeDynamics(body, -1, lateralFriction=cfg.object_friction)
        rest = model.rests[0]
        sim.resetBasePositionAndOrientation(body, [0, 0, -(model.vertices @ rest.T)[:, 2].min() + 0.001],
                                            of.quat_of(rest))
        for _ in range(240):
            sim.stepSimulation()
        R = np.array(of.pb.getMatrixFromQuaternion(sim.getBasePositionAndOrientation(body)[1])).reshape(3, 3)
        assert np.degrees(np.arccos(np.clip((np.trace(R.T @ rest) - 1) / 2, -1, 1))) < 10   # it did not tip over
    finally:
        sim.disconnect()


def test_gnbv_counts_the_same_voxels_with_its_rays_cut_where_they_can_hit_nothing(ap_env):
    agent = of.GreedyNextBestView(ap_env.cfg, 0)
    ap_env.reset(seed=2)
    agent.reset(ap_env.searcher, ap_env.gripper_pose())
    for _ in range(4):
        T = ap_env.gripper_pose()
        actions = agent.rng.uniform(-1, 1, (10, of.ACTION_SIZE))
        actions[:, of.ACTION_MOVES] = -1.0
        cameras = np.stack([ap_env.searcher.camera_pose(ap_env.searcher.goal_pose(T, a)) for a in actions])
        cut = agent.newly_observed(ap_env.searcher, cameras, T[:3, 3])
        assert min(agent.samples_needed(c, 0.34) for c in cameras) < len(agent.depths)   # some rays were cut
        agent.samples_needed = lambda T_camera, box_half: len(agent.depths)               # every sample
        assert np.array_equal(agent.newly_observed(ap_env.searcher, cameras, T[:3, 3]), cut)
        del agent.samples_needed
        ap_env.step(actions[int(np.argmax(cut))].astype(np.float32))


# --- recordings, replay and the arm's loop ---------------------------------------------------------

RECORDED_SEED = 1   # the shipped I3DE searches this ip/cubes scene for 13 steps, moving an object once, then stops


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """An I3DE episode recorded by `tools/replay.py record`, and the env's own states and actions of it."""
    folder = tmp_path_factory.mktemp("recording") / "episode"
    policy = of.learned_policy("i3de", "ip")
    replay_tool.record("i3de", "ip", "cubes", RECORDED_SEED, policy, folder)
    env = of.ObjectFindingEnv("ip", "cubes")
    agent = of.make_agent("i3de", env.cfg, RECORDED_SEED, policy)
    state, _ = env.reset(seed=RECORDED_SEED)
    states, actions, done = [state], [], False
    while not done:
        actions.append(agent.act(env.searcher, env.gripper_pose()))
        state, _, done, _, info = env.step(actions[-1])
        states.append(state)
    env.close()
    return folder, states, actions, info


def test_a_recorded_episode_replays_to_the_env_states_and_actions_exactly(recording):
    folder, states, actions, info = recording
    assert info["terminated_by_agent"] and len(actions) > 5
    cfg, rig, meta, frames = replay_tool.read_recording(folder)
    assert len(frames) == len(actions) and rig.rgb is rig.depth
    rows, replayed, _ = replay_tool.replay(cfg, rig, meta, frames, "i3de", of.learned_policy("i3de", "ip"))
    assert len(rows) == len(actions) and rows[-1]["stop"] and not any(row["stop"] for row in rows[:-1])
    for row, action in zip(rows, actions):
        assert np.array_equal([row[name] for name in of.ACTION_NAMES], action)
    for a, b in zip(replayed, states):   # the env's state after each frame, bit for bit
        assert np.array_equal(a, b)
    # each move's goal is where the recording's next frame has the gripper (it moved there, pushing)
    next_xyz = np.array([f["T_base_tool"][:3, 3] for f in frames[1:]])
    goals = np.array([[row[k] for k in ("goal_x_m", "goal_y_m", "goal_z_m")] for row in rows[:-1]])
    assert np.median(np.linalg.norm(goals - next_xyz, axis=1)) < 0.01


def test_millimetre_png_depth_replays_to_the_same_stop_with_nearby_moves(recording, tmp_path, capsys):
    """--depth png: millimetre depth and the colour detector (without the simulated detector's noise) in place
    of what the searcher fused. The README's "slightly different": the same stop, moves within half a step."""
    folder, actions = recording[0], np.array(recording[2])
    assert replay_tool.main(["play", str(folder), "--agent", "i3de", "--depth", "png", "--out", str(tmp_path)]) == 0
    assert "actions equal to the recording's own" in capsys.readouterr().out
    rows = list(of.csv.DictReader(open(tmp_path / f"replay-{folder.name}-i3de-png.csv")))
    replayed = np.array([[float(row[name]) for name in of.ACTION_NAMES] for row in rows])
    assert len(rows) == len(actions) and rows[-1]["stop"] == "True"        # stops at the recording's frame
    assert np.abs(replayed - actions)[:, :of.ACTION_MOVES].mean() < 0.5
    assert {row["depth"] for row in rows} == {"png"} and {row["weights"] for row in rows} == {
        of.policy_fingerprint(of.learned_policy("i3de", "ip"))}                # the CSV says what made it
    sheet = cv2.imread(str(tmp_path / f"replay-{folder.name}-i3de-png.png"))
    assert sheet is not None and sheet.shape[1] == 4 * of.PANEL[0]


def test_replays_into_one_folder_never_replace_another_experiments(recording, tmp_path, capsys):
    folder, out = recording[0], tmp_path / "out"
    play = lambda source, *extra: replay_tool.main(["play", str(source), "--out", str(out), *extra])
    assert play(folder, "--agent", "a3de") == 0 and play(folder, "--agent", "a3de", "--depth", "png") == 0
    written = {p.name: p.read_bytes() for p in out.glob("replay-*.csv")}
    assert len(written) == 2                                                  # exact and png side by side
    assert play(folder, "--agent", "a3de") == 0                               # the same replay again: its own file
    namesake = tmp_path / "elsewhere" / folder.name                           # another recording, the same name
    shutil.copytree(folder, namesake)
    capsys.readouterr()
    assert play(namesake, "--agent", "a3de") == 2
    assert "made by another replay" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.glob("replay-*.csv")} == written
    rows = list(of.csv.DictReader(open(out / f"replay-{folder.name}-a3de-exact.csv")))
    assert all(np.isfinite(float(row["dx"])) for row in rows) and rows[0]["agent"] == "a3de"


def broken_copy(folder: Path, tmp_path: Path, name: str) -> Path:
    copy = tmp_path / name
    shutil.copytree(folder, copy)
    return copy


def test_a_broken_recording_is_one_line_exit_two_and_writes_nothing(recording, tmp_path, capsys):
    folder = recording[0]
    missing = broken_copy(folder, tmp_path, "missing")
    for path in (missing / "frames").glob("000003-*"):
        path.unlink()
    small = broken_copy(folder, tmp_path, "small")
    cv2.imwrite(str(small / "frames" / "000002-depth.png"), np.zeros((10, 10), np.uint16))
    pose = broken_copy(folder, tmp_path, "pose")
    (pose / "frames" / "000001-pose.json").write_text('{"T_base_tool": [[1, 0')
    intrinsics = broken_copy(folder, tmp_path, "intrinsics")
    meta = of.json.loads((intrinsics / "recording.json").read_text())
    meta["depth_camera"]["width"] = meta["depth_camera"]["width"] * 2
    (intrinsics / "recording.json").write_text(of.json.dumps(meta))
    meta = of.json.loads((folder / "recording.json").read_text())
    hostile = dict(task_list=dict(task=["ip"]), odd_seed=dict(seed="seven"), png_scale=dict(depth_png_m=-0.001),
                   nan_scale=dict(depth_png_m=float("nan")), area_bool=dict(target_area_m2=True),
                   tiny_focal=dict(rgb_camera=dict(meta["rgb_camera"], K=[[1e-300, 0, 40], [0, 1e-300, 30], [0, 0, 1]])))
    for name, change in hostile.items():
        broken = broken_copy(folder, tmp_path, name)
        (broken / "recording.json").write_text(of.json.dumps(dict(meta, **change)))
    zero = broken_copy(folder, tmp_path, "zero")
    (zero / "recording.json").unlink()
    (zero / "recording.json").symlink_to("/dev/zero")
    empty, npz = broken_copy(folder, tmp_path, "empty"), broken_copy(folder, tmp_path, "npz")
    (empty / "frames" / "000001-depth.npy").write_bytes(b"")
    np.savez(npz / "frames" / "000001-depth.npy", np.zeros(3))
    (npz / "frames" / "000001-depth.npy.npz").rename(npz / "frames" / "000001-depth.npy")
    huge = broken_copy(folder, tmp_path, "huge")   # a small PNG that would decode to 15000 x 15000
    cv2.imwrite(str(huge / "frames" / "000002-color.png"), np.zeros((15000, 15000, 3), np.uint8))
    expected = {"missing": "frame 3", "small": "depth image", "pose": "unreadable", "intrinsics": "depth image",
                "task_list": "task must be", "odd_seed": "seed must be", "png_scale": "depth_png_m",
                "nan_scale": "depth_png_m", "area_bool": "target_area_m2", "tiny_focal": "rgb_camera.K",
                "zero": "not a file", "empty": "depth 000001", "npz": "not one .npy", "huge": "15000 x 15000"}
    for name, words in expected.items():
        out = tmp_path / f"out-{name}"
        depth = "exact" if name in ("empty", "npz") else "png"
        assert replay_tool.main(["play", str(tmp_path / name), "--depth", depth, "--out", str(out)]) == 2, name
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], (name, err)
        assert not out.exists(), name   # refused before any output


def test_detection_masks_replace_the_colour_detector(recording, tmp_path):
    folder = recording[0]
    cfg, rig, meta, frames = replay_tool.read_recording(folder, "png")
    _, states, _ = replay_tool.replay(cfg, rig, meta, frames, "i3de", of.learned_policy("i3de", "ip"))
    assert max(s[of.STATE_TARGET_SHARE] for s in states) > 0   # the colour detector sees the target
    masks = tmp_path / "masks"
    masks.mkdir()
    for i, frame in enumerate(frames):
        cv2.imwrite(str(masks / f"{i:06d}.png"), np.zeros(frame["rgb"].shape[:2], np.uint8))
    cfg, rig, meta, frames = replay_tool.read_recording(folder, "png", masks)
    _, states, _ = replay_tool.replay(cfg, rig, meta, frames, "i3de", of.learned_policy("i3de", "ip"))
    assert all(s[of.STATE_TARGET_SHARE] == 0 for s in states)   # a detector that sees nothing


def test_the_arm_loop_works_in_any_base_frame(recording):
    """The same frames, with the workspace moved and turned in the robot's base frame: the same actions,
    and goal poses moved the same way."""
    cfg, rig, meta, frames = replay_tool.read_recording(recording[0])
    rows, _, _ = replay_tool.replay(cfg, rig, meta, frames[:6], "i3de", of.learned_policy("i3de", "ip"))
    T_base_workspace = np.eye(4)
    T_base_workspace[:3, :3] = of.rotation(0.7, "z")
    T_base_workspace[:3, 3] = [0.4, -0.2, 0.05]
    moved = [dict(f, T_base_tool=T_base_workspace @ f["T_base_tool"], T_base_depth=T_base_workspace @ f["T_base_depth"])
             for f in frames[:6]]
    rows_moved, _, _ = replay_tool.replay(cfg, rig, dict(meta, T_base_workspace=T_base_workspace), moved, "i3de",
                                 of.learned_policy("i3de", "ip"))
    for a, b in zip(rows, rows_moved):
        assert np.allclose([a[n] for n in of.ACTION_NAMES], [b[n] for n in of.ACTION_NAMES], atol=1e-4)
        goal = T_base_workspace[:3, :3] @ [a["goal_x_m"], a["goal_y_m"], a["goal_z_m"]] + T_base_workspace[:3, 3]
        assert np.allclose(goal, [b["goal_x_m"], b["goal_y_m"], b["goal_z_m"]], atol=1e-3)


# --- on an arm: every input checked, every goal finite, in the box and one step away at most ---------

@pytest.fixture(scope="module")
def wrist_view():
    """A simulated first view of an ap scene with the target in sight, and the gripper's pose."""
    env = of.ObjectFindingEnv("ap", "cubes")
    env.reset(seed=2)
    view, T_world_tool = env.view, env.gripper_pose()
    env.close()
    return view, T_world_tool


def arm_search(task="ap", agent="random", **kwargs) -> of.ArmSearch:
    return of.ArmSearch(of.Searcher(of.TASKS[task]), of.make_agent(agent, of.TASKS[task], 0), **kwargs)


def test_a_bad_depth_pixel_is_no_return_and_the_rest_of_the_view_is_fused(wrist_view):
    view = wrist_view[0]
    fuse = lambda depth: of.Searcher(of.TASKS["ap"]).observe(depth, view.T_world_camera, detections=view.detections)
    clean = fuse(view.depth_m)
    assert clean > 10000
    for bad in (np.nan, np.inf, -np.inf, -0.5, 1e6, 0.0):
        depth = view.depth_m.copy()
        depth[30, 40] = bad
        with warnings.catch_warnings():
            warnings.simplefilter("error")          # and no numpy warning either
            assert abs(fuse(depth) - clean) <= 0.01 * clean, bad
    half_bad = view.depth_m.copy()
    half_bad[:, ::2] = np.nan
    assert 0.5 * clean < fuse(half_bad) <= clean


def test_bad_detections_poses_and_image_sizes_are_a_value_error_that_names_them(wrist_view):
    view, T_world_tool = wrist_view
    searcher = of.Searcher(of.TASKS["ap"])
    sheared = view.T_world_camera.copy()
    sheared[:3, :3] = sheared[:3, :3] @ [[1, 0.1, 0], [0, 1, 0], [0, 0, 1]]
    nan_pose, nan_score, high_score = view.T_world_camera.copy(), view.detections.copy(), view.detections.copy()
    nan_pose[0, 3], nan_score[5, 5], high_score[5, 5] = np.nan, np.nan, 1.5
    for kwargs, named in ((dict(detections=nan_score), "detection score"), (dict(detections=high_score), "detection"),
                          (dict(detections=view.detections, T_world_depth=sheared), "rigid"),
                          (dict(detections=view.detections, T_world_depth=nan_pose), "finite"),
                          (dict(detections=view.detections[:-1]), "detections must be"),
                          (dict(rgb=view.rgb[:, :-1]), "rgb must be"), (dict(rgb=view.rgb.astype(float)), "rgb must"),
                          (dict(detections=view.detections, depth_m=view.depth_m[1:]), "depth_m must be"),
                          (dict(), "one of the two"), (dict(rgb=view.rgb, detections=view.detections), "one of")):
        args = {**dict(depth_m=view.depth_m, T_world_depth=view.T_world_camera), **kwargs}
        with pytest.raises(ValueError, match=named):
            searcher.observe(**args)
    assert searcher.views == 0 and searcher.volume.observed_count == 0   # nothing was fused
    with pytest.raises(ValueError, match="T_base_tool"):
        arm_search().step(view.depth_m, T_world_tool[:3], rgb=view.rgb)
    with pytest.raises(ValueError, match="T_base_workspace"):
        arm_search(T_base_workspace=np.diag([2.0, 1, 1, 1]))
    for area in (-1e-3, 0.0, float("nan"), True, "big"):
        with pytest.raises(ValueError, match="target_area_m2"):
            arm_search(target_area_m2=area)


def test_a_tool_far_outside_is_refused_and_one_just_outside_gets_a_goal_in_the_box_one_step_away(wrist_view):
    view, T_world_tool = wrist_view
    cfg = of.TASKS["ap"]
    above = T_world_tool.copy()
    above[2, 3] = cfg.ceiling_m + 1.0
    with pytest.raises(ValueError, match=r"1\.000 m outside the searched box"):
        arm_search().step(view.depth_m, above, rgb=view.rgb)
    far_workspace = np.eye(4)
    far_workspace[:3, 3] = [100.0, 0, 0]           # the base frame's box, 100 m away from the gripper
    with pytest.raises(ValueError, match="outside the searched box"):
        arm_search(T_base_workspace=far_workspace).step(view.depth_m, T_world_tool, rgb=view.rgb)
    pitched = T_world_tool.copy()
    pitched[:3, :3] = pitched[:3, :3] @ of.rotation(0.5, "x")   # about the gripper's right: a pitch
    with pytest.raises(ValueError, match="tool frame"):
        arm_search().step(view.depth_m, pitched, rgb=view.rgb)
    rng, half, moves = np.random.default_rng(0), cfg.workspace_m / 2, []
    for out_m in [0.004] * 60 + [0.04] * 60:   # a few millimetres, or most of a step, out of faces and corners
        T = T_world_tool.copy()
        T[:3, :3] = of.gripper_rotation(rng.uniform(-np.pi, np.pi), rng.uniform(-1, 1))
        T[:3, 3] = rng.uniform([-half, -half, 0], [half, half, cfg.ceiling_m])
        for axis in rng.choice(3, rng.integers(1, 3), replace=False):   # out across one or two faces
            T[axis, 3] = out_m + (half if axis < 2 else cfg.ceiling_m) if rng.random() < 0.5 or axis == 2 else \
                -half - out_m
        search = arm_search()
        search.agent.act = lambda searcher, T_tool: np.r_[rng.choice([-1.0, 1.0], of.ACTION_MOVES), -1.0]   # longest
        _, T_goal = search.step(view.depth_m, T, rgb=view.rgb)
        assert of.outside_box_m(search.searcher, T_goal) == 0 and np.isfinite(T_goal).all()
        moves.append(np.linalg.norm(T_goal[:3, 3] - T[:3, 3]))
    assert max(moves) <= np.sqrt(3) * cfg.max_step_m


def test_the_readmes_arm_loop_runs_as_written(wrist_view):
    """The README's "On your arm" loop, executed: a simulated arm in a turned base frame, the rig from the
    calibration, rgb= frames, the default target area."""
    code = re.search(r"## On your arm.*?```python\n(.*?)```", (HERE / "README.md").read_text(), re.S).group(1)
    env = of.ObjectFindingEnv("ap", "cubes")
    env.reset(seed=2)
    T_base_workspace = np.eye(4)
    T_base_workspace[:3, :3], T_base_workspace[:3, 3] = of.rotation(2.0, "z"), [0.5, 0.1, 0.2]

    class SimulatedArm:
        goals = []

        def observe(self):
            return env.view.depth_m, env.view.rgb, T_base_workspace @ env.gripper_pose()

        def move_to(self, T_base_goal):
            self.goals.append(T_base_goal)
            env._drive_gripper(env.gripper_pose(), np.linalg.inv(T_base_workspace) @ T_base_goal)
            env._observe()

    rig = env.searcher.rig
    names = dict(objfind=of, depth_camera=rig.depth, rgb_camera=rig.rgb, T_tool_depth=rig.T_tool_depth,
                 T_depth_rgb=rig.T_depth_rgb, T_base_workspace=T_base_workspace, target_area_m2=None,
                 arm=SimulatedArm())
    exec(code, names)
    env.close()
    assert 1 <= len(SimulatedArm.goals) < of.TASKS["ap"].horizon and names["T_base_goal"] is None   # it stopped
    assert names["search"].searcher.target_area_m2 == of.TASKS["ap"].nominal_target_area_m2


# --- the rig's sensing -----------------------------------------------------------------------------

def test_the_sensor_model_at_zero_is_the_ideal_sensor_and_draws_nothing():
    cfg, rng = of.TASKS["ap"], np.random.default_rng(0)
    before = rng.bit_generator.state
    depth = np.random.default_rng(1).uniform(0.2, 0.8, (60, 80)).astype(np.float32)
    assert of.time_of_flight(depth, rng, cfg) is depth
    rig = of.wrist_rig(cfg)
    assert of.mounted_rig(rig, rng, cfg) is rig and rig.one_camera
    assert rng.bit_generator.state == before   # the episode's other draws are untouched


def test_a_step_edge_through_the_time_of_flight_model():
    """Flat sides keep their mean (the noise is unbiased); pixels along the edge are dropped or mixed."""
    depth = np.full((100, 100), 0.4, np.float32)
    depth[:, 50:] = 0.6
    cfg = dataclasses.replace(of.TASKS["ap"], tof_noise_ratio=0.01, tof_missing_share=0.02, tof_edge_jump_m=0.02,
                              tof_edge_drop_share=0.5)
    out = of.time_of_flight(depth, np.random.default_rng(0), cfg)
    left, right = out[:, :48], out[:, 52:]
    assert abs(left[left > 0].mean() - 0.4) < 0.001 and abs(right[right > 0].mean() - 0.6) < 0.001
    assert 0.01 < np.mean(left == 0) < 0.03                       # missing returns at their share
    assert 0.003 < left[left > 0].std() < 0.005                   # 1 % of 0.4 m
    edge_cfg = dataclasses.replace(cfg, tof_noise_ratio=0.0, tof_missing_share=0.0)
    edge = of.time_of_flight(depth, np.random.default_rng(1), edge_cfg)[:, 49:51]
    mixed = (edge > 0.4) & (edge < 0.6)
    assert np.all((edge == 0) | mixed | np.isin(edge, (0.4, 0.6)))
    assert 0.3 < np.mean(edge == 0) < 0.7 and mixed.mean() > 0.3   # half dropped, the rest fly
    assert np.array_equal(of.time_of_flight(depth, np.random.default_rng(1), edge_cfg)[:, 52:], depth[:, 52:])


def test_nothing_closer_than_the_minimum_range_returns():
    depth = np.linspace(0.02, 0.5, 80 * 60, dtype=np.float32).reshape(60, 80)
    cfg = dataclasses.replace(of.TASKS["ap"], depth_min_range_m=0.1, tof_noise_ratio=0.02)
    out = of.time_of_flight(depth, np.random.default_rng(0), cfg)
    assert np.all(out[out > 0] >= 0.1) and np.all(out[depth < 0.09] == 0)


def test_the_hand_eye_error_has_the_stated_size_and_stays_for_the_episode():
    cfg = dataclasses.replace(of.TASKS["ap"], hand_eye_error_m=0.003, hand_eye_error_rad=0.0175)
    believed = of.wrist_rig(cfg)
    error = np.linalg.inv(believed.T_tool_depth) @ of.mounted_rig(believed, np.random.default_rng(3), cfg).T_tool_depth
    assert np.isclose(np.linalg.norm(error[:3, 3]), 0.003)
    assert np.isclose(np.arccos((np.trace(error[:3, :3]) - 1) / 2), 0.0175)
    env = of.ObjectFindingEnv("ap", "cubes", hand_eye_error_m=0.003, hand_eye_error_rad=0.0175)
    env.reset(seed=0)
    mounted = env.true_rig.T_tool_depth
    env.step(np.array([0.5, 0, 0, 0, 0, -1.0]))
    assert np.array_equal(env.true_rig.T_tool_depth, mounted) and not np.array_equal(mounted, env.searcher.rig.T_tool_depth)
    assert np.array_equal(env.view.T_world_camera, env.searcher.camera_pose(env.gripper_pose()))   # what it believes
    env.close()


def test_detections_of_an_offset_rgb_camera_land_on_the_target_in_the_depth_image():
    env = of.ObjectFindingEnv("ap", "cubes", rgb_offset_m=(0.03, 0.0, 0.0))
    rig = env.true_rig
    assert not rig.one_camera
    for seed in range(30):
        env.reset(seed=seed)
        T_depth = env.gripper_pose() @ rig.T_tool_depth
        truth = of.detect_target(of.render_rgbd(env.sim, T_depth, rig.depth)[0]) > 0.5   # the depth camera's own view
        if truth.sum() > 40:
            break
    rgb, views = env._render(T_depth)
    depth = views[0][2]
    from_rgb = of.detect_target(rgb)
    mapped = rig.detections_in_depth_image(from_rgb, depth) > 0.5
    naive = from_rgb > 0.5                         # the RGB image taken as if it were the depth camera's
    iou = lambda a, b: (a & b).sum() / (a | b).sum()
    assert iou(mapped, truth) > 0.7 and iou(mapped, truth) > iou(naive, truth) + 0.1
    env.close()


def test_a_depth_pixel_on_the_rgb_cameras_outline_of_the_detections_counts_half():
    # the depth camera has twice the RGB camera's pixels per side, the same field of view and no offset:
    # each RGB pixel covers 2 x 2 depth pixels, and a 20 x 20 RGB-pixel detection covers 40 x 40
    cfg = dataclasses.replace(of.TASKS["ap"], depth_width=160, depth_height=120, depth_fov_y_deg=45.0)
    searcher = of.Searcher(cfg)
    assert not searcher.rig.one_camera
    detections = np.zeros((60, 80), np.float32)
    detections[20:40, 30:50] = 1.0
    height_m = 0.3                      # above a target face 5 cm over the floor
    searcher.observe(np.full((120, 160), height_m, np.float32), looking_down(height_m + 0.05), detections=detections)
    pixel_m2 = (height_m / searcher.rig.depth.K[0, 0]) ** 2
    band = 40 * 40 - 36 * 36            # depth pixels under the RGB outline: the outer 2 of the 40 x 40 square
    depth_outline = 4 * 40 - 4          # what one RGB-D camera's outline would have been
    assert np.isclose(searcher.volume.seen_target_area_m2(), (40 * 40 - band / 2) * pixel_m2, rtol=0.01)
    assert not np.isclose(searcher.volume.seen_target_area_m2(), (40 * 40 - depth_outline / 2) * pixel_m2, rtol=0.02)


def test_flying_pixels_on_a_noisy_cameras_outline_add_no_target_area():
    # a 40 x 40-pixel target face 4 cm above the floor; its outline's pixels return depths between the two
    # surfaces, as a time-of-flight camera's do; on such a camera (area_median_px) they count their frontal
    # area at most, so the face's perceived area stays that of the clean image
    cfg = dataclasses.replace(of.TASKS["ap"], depth_width=160, depth_height=120, depth_fov_y_deg=45.0,
                              rgb_offset_m=(0.0, 0.0, 0.0), area_median_px=3)
    clean = np.full((120, 160), 0.34, np.float32)
    clean[40:80, 60:100] = 0.30
    flying = clean.copy()
    ring = of.outline_of(clean < 0.32)
    flying[ring] = np.random.default_rng(0).uniform(0.30, 0.34, ring.sum())
    detections = np.zeros((60, 80), np.float32)
    detections[20:40, 30:50] = 1.0
    areas = []
    for depth in (clean, flying):
        searcher = of.Searcher(cfg)
        searcher.observe(depth, looking_down(0.35), detections=detections)
        areas.append(searcher.volume.seen_target_area_m2())
    assert areas[0] > 0 and abs(areas[1] / areas[0] - 1) < 0.05


def test_rig_camera_share_draws_the_rigs_camera_for_that_share_of_episodes():
    env = of.ObjectFindingEnv("ip", "cubes", rig_camera_share=0.5)
    widths = []
    for seed in range(10):
        state, _ = env.reset(seed=seed)
        widths.append(env.searcher.rig.depth.width)
        assert state.shape == (of.STATE_SIZE,)
        if widths[-1] == of.RIG_SENSING["depth_width"]:
            assert env.sensing.tof_noise_ratio == of.RIG_SENSING["tof_noise_ratio"]
            assert env.view.depth_m.shape == (of.RIG_SENSING["depth_height"], of.RIG_SENSING["depth_width"])
        else:
            assert env.sensing.tof_noise_ratio == 0 and env.view.depth_m.shape == (60, 80)
    assert set(widths) == {80, of.RIG_SENSING["depth_width"]}
    env.reset(seed=3)
    assert env.searcher.rig.depth.width == widths[3]   # a seed's episode draws the same camera
    env.close()


@pytest.mark.parametrize("task", ["ap", "ap-real"])   # 6 mm voxels; 3.3 mm, the area in cells of 6 mm
def test_with_a_separate_rgb_camera_views_that_miss_a_cell_keep_its_target_area_until_one_sees_through(task):
    def view(volume, detection, rgb_camera, times=1, depth_m=0.25):
        depth, detections = np.full((60, 80), depth_m, np.float32), np.zeros((60, 80), np.float32)
        detections[20:40, 25:55] = detection     # the target in the middle of the view
        for _ in range(times):
            volume.integrate(depth, detections, K, looking_down(0.3),
                             np.zeros((60, 80), bool) if rgb_camera else None)
    for rgb_camera in (True, False):
        volume = of.TSDFVolume(of.TASKS[task])
        view(volume, 1.0, rgb_camera)
        seen = volume.seen_target_area_m2()
        view(volume, 0.0, rgb_camera)            # one view registered a few mm off
        kept = volume.seen_target_area_m2() / seen     # one RGB-D camera: forgotten at once
        assert kept > 0.95 if rgb_camera else kept == 0.0
        view(volume, 0.0, rgb_camera, times=3)   # misses where the target lies: the rig keeps it
        assert volume.seen_target_area_m2() / seen > 0.95 if rgb_camera else volume.seen_target_area_m2() == 0.0
        view(volume, 0.0, rgb_camera, times=3, depth_m=0.3)   # the target pushed away: seen through
        assert volume.seen_target_area_m2() == 0.0


def test_on_the_rig_the_truth_counts_only_what_the_rgb_camera_sees_too(monkeypatch):
    """A point the RGB camera never saw cannot have been detected: with its view blocked, nothing is seen."""
    render = of.ObjectFindingEnv._render_world
    def rgb_camera_blocked(self, T_world_camera, camera):
        rgb, depth_m = render(self, T_world_camera, camera)
        if camera.width != self.true_rig.depth.width:      # the RGB camera: something just before its lens
            depth_m = np.full_like(depth_m, 0.02)
        return rgb, depth_m
    env = of.ObjectFindingEnv("ap-real", "cubes-and-cuboids")
    seen = {}
    for blocked in (False, True):
        if blocked:
            monkeypatch.setattr(of.ObjectFindingEnv, "_render_world", rgb_camera_blocked)
        agent = of.make_agent("gnbv", env.cfg, 0, None)
        _, info = env.reset(seed=0)
        agent.reset(env.searcher, env.gripper_pose())
        for _ in range(5):
            _, _, done, _, info = env.step(agent.act(env.searcher, env.gripper_pose()))
        seen[blocked] = info["target_seen_fraction"]
    env.close()
    assert seen[False] > 0.05 and seen[True] == 0.0, seen


def test_gnbv_counts_the_same_volumes_at_any_voxel_size():
    for task in ("ap", "ap-large", "ip"):   # the presets' volumes have the state's voxels: the counts as set
        gnbv = of.GreedyNextBestView(of.TASKS[task], 0)
        assert (gnbv.min_detections, gnbv.stall_voxels) == (3, 50)
    finer = dataclasses.replace(of.TASKS["ap"], voxels_per_side=200)    # 3 mm voxels, the state's 6 mm
    gnbv = of.GreedyNextBestView(finer, 0)
    assert gnbv.min_detections == 3 * 2 ** 3 and gnbv.stall_voxels == 50 * 2


# --- the real setup's presets ------------------------------------------------------------------------

def scene_fingerprint(task: str, scene: str, seeds) -> str:
    """16 hex digits of every object's resting pose over some seeds: a scene's identity, bit for bit."""
    digest = of.hashlib.sha256()
    env = of.ObjectFindingEnv(task, scene)
    for seed in seeds:
        env.reset(seed=seed)
        for o in env.objects:
            position, orientation = env.sim.getBasePositionAndOrientation(o.body)
            digest.update(np.array(position + orientation).tobytes())
    env.close()
    return digest.hexdigest()[:16]


@pytest.mark.parametrize("task, scene, fingerprint", [
    ("ap", "cubes", "149b2f49a8dc437f"), ("ip", "cubes", "d80256a05f7b2a1f"),
    ("ip", "variable-primitives", "56206f65369384be"), ("ap-large", "cubes", "4a2ffdbd8e6beedc")])
def test_scene_generation_for_small_workspaces_leaves_the_simulation_presets_exactly(task, scene, fingerprint):
    """Pile margins and spacing scale with the workspace; at 0.6 m and 1.2 m the scenes are those of world 7."""
    assert scene_fingerprint(task, scene, range(3)) == fingerprint


def test_scattered_primitives_are_placed_at_rest_on_the_floor(ap_env):
    """A cube scene that found every cube room skips settling: woken and stepped for a second, no cube moves."""
    for seed in range(3):
        ap_env.reset(seed=seed)
        before = [ap_env.sim.getBasePositionAndOrientation(o.body)[0] for o in ap_env.objects]
        assert all(abs(z - o.half_height_m) < 1e-9 for (_, _, z), o in zip(before, ap_env.objects))
        for o in ap_env.objects:
            ap_env.sim.changeDynamics(o.body, -1, activationState=of.pb.ACTIVATION_STATE_WAKE_UP)
        for _ in range(ap_env.cfg.physics_hz):
            ap_env.sim.stepSimulation()
        after = [ap_env.sim.getBasePositionAndOrientation(o.body)[0] for o in ap_env.objects]
        assert np.abs(np.subtract(after, before)).max() < 5e-4


def test_the_drawn_floor_is_the_floor_tinyrenderer_drew():
    """draw_floor against the floor as a visual box: the same pixels, colour and depth (to 1e-5 m)."""
    env = of.ObjectFindingEnv("ap", "cubes")
    cfg = env.cfg
    for seed in range(3):
        env.reset(seed=seed)
        T = env.gripper_pose() @ env.true_rig.T_tool_depth
        rgb, ((_, _, depth),) = env._render(T)
        floor = env.sim.createMultiBody(0, -1, env.sim.createVisualShape(
            of.pb.GEOM_BOX, halfExtents=[of.floor_half_m(cfg)] * 2 + [cfg.wall_thickness_m],
            visualFramePosition=[0, 0, -cfg.wall_thickness_m], rgbaColor=of.FLOOR_RGBA))
        rgb_drawn, depth_drawn = of.render_rgbd(env.sim, T, of.dataclasses.replace(env.true_rig.depth, near_m=cfg.near_m))
        env.sim.removeBody(floor)
        assert np.array_equal(depth > 0, depth_drawn > 0) and np.array_equal(rgb, rgb_drawn)
        assert np.abs(depth - depth_drawn).max() < 1e-5 and (depth > 0).mean() > 0.5
    env.close()


@pytest.mark.parametrize("task", ["ap-real", "ip-real"])
def test_the_real_presets_build_table_one_scenes_inside_the_small_floor(task, monkeypatch):
    env = of.ObjectFindingEnv(task, "cubes-and-cuboids")
    cfg, half = env.cfg, env.cfg.workspace_m / 2
    assert (cfg.workspace_m, cfg.horizon, cfg.no_target_prob, cfg.gnbv_samples) == (0.33, 50, 0.0, 30)
    assert (cfg.min_objects, cfg.max_objects, cfg.num_piles) == (15, 30, 4 if task == "ip-real" else 0)
    assert all(getattr(cfg, name) == value for name, value in of.RIG_SENSING.items())   # the rig's sensing
    piles, real_pile_positions = [], of.pile_positions
    monkeypatch.setattr(of, "pile_positions", lambda objects, cfg, rng: piles.append(cfg.num_piles) or
                        real_pile_positions(objects, cfg, rng))
    for seed in range(3):
        env.reset(seed=seed)
        assert 15 <= len(env.objects) <= 30 and env.target_present
        tops = [env.sim.getBasePositionAndOrientation(o.body)[0][2] for o in env.objects]
        assert env.heaped == (task == "ip-real") and piles == [4] * (seed + 1) * (task == "ip-real")   # 0.1 unheaped
        assert not env.heaped or max(tops) > 1.2 * cfg.object_size_m   # a pile: an object stands on others
        for o in env.objects:
            (x, y, z), _ = env.sim.getBasePositionAndOrientation(o.body)
            assert abs(x) < half and abs(y) < half and 0 < z < cfg.wall_height_m
            assert np.linalg.norm(env.sim.getBaseVelocity(o.body)[0]) < 2 * cfg.settle_speed   # at rest
    if task == "ip-real":   # 30 objects' drop spots over the four piles: all inside the walls
        spots = np.array([xyz[:2] for xyz, _ in of.pile_positions([env.objects[0]] * 30, cfg, np.random.default_rng(0))])
        assert np.all(np.abs(spots) < half - env.objects[0].radius_m / 2)
    env.close()


def test_one_scene_fused_at_two_voxel_sizes_gives_the_same_share_and_nearly_the_same_state():
    """The real presets' 0.33 m at 100 voxels has 3.3 mm voxels, the policies were trained at 6 mm: the state's
    detection sum and the perceived share are counted in cells of state_voxel_m, so the voxel size hardly
    matters. Tolerances: share 0.03 absolute, bins 0.05, the two sums 10 % (measured: 0.006, 0.005, 1 %)."""
    env = of.ObjectFindingEnv("ap", "cubes")
    checked = 0
    for seed in (4, 7, 8, 14):
        env.reset(seed=seed)
        views, rng = [(env.view, env.gripper_pose())], np.random.default_rng(seed)
        for _ in range(4):
            if env.step(np.r_[rng.uniform(-1, 1, 5), -1.0])[2]:
                break
            views.append((env.view, env.gripper_pose()))
        fused = []
        for voxels in (100, 180):    # 6 mm, and 3.3 mm as on the real presets' floor
            searcher = of.Searcher(dataclasses.replace(env.cfg, voxels_per_side=voxels))
            searcher.reset(env.searcher.target_area_m2)
            for view, _ in views:
                searcher.observe(view.depth_m, view.T_world_camera, detections=view.detections)
            fused.append((searcher.perceived_target_share(), searcher.state(views[-1][1])))
        (share_a, a), (share_b, b) = fused
        assert abs(share_a - share_b) < 0.03 and share_a > 0.1
        assert np.abs(a[:68] - b[:68]).max() < 0.05
        assert np.allclose(a[68:70], b[68:70], rtol=0.1)
        checked += 1
    assert checked == 4
    env.close()


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds worker processes through /proc")
def test_a_scheduler_stop_ends_an_eval_and_its_workers(tmp_path):
    """SIGTERM (what a cluster scheduler or `kill` sends) ends the command as Ctrl-C does: exit 130, no
    worker process left running."""
    import signal
    import time
    run = subprocess.Popen([sys.executable, str(HERE / "objfind.py"), "eval", "--agent", "gnbv", "--episodes", "200",
                            "--workers", "2"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not (workers := worker_processes(run.pid)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert workers, "no worker process started"
    time.sleep(2)
    run.send_signal(signal.SIGTERM)
    run.communicate(timeout=60)
    assert run.returncode == 130
    time.sleep(1)
    for pid in workers:   # gone, or a zombie waiting for a container's init to reap it
        status = Path(f"/proc/{pid}/status")
        assert not status.exists() or "\nState:\tZ" in status.read_text(), f"worker {pid} still runs"


def test_a_scheduler_stop_saves_a_training_run_that_resumes(tmp_path):
    """SIGTERM during train: exit 130, the last finished update in the checkpoint and the log, one line
    saying how to resume, and the resumed run goes on from there."""
    import signal
    import time
    small = ["--set", "batch_steps=60", "--set", "minibatch=30", "--set", "checkpoint_every=1000", "--workers", "1"]
    run = subprocess.Popen([sys.executable, str(HERE / "objfind.py"), "train", "--steps", "100000", *small,
                            "--out", "run"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log, deadline = tmp_path / "run" / "log.csv", time.monotonic() + 120
    while not (log.exists() and len(log.read_text().splitlines()) >= 3) and time.monotonic() < deadline:
        time.sleep(0.2)                                          # two updates logged, none checkpointed yet
    run.send_signal(signal.SIGTERM)
    _, err = run.communicate(timeout=60)
    assert run.returncode == 130, err[-500:]
    said = [line for line in err.replace("\r", "\n").splitlines() if line.startswith("objfind:")]
    assert len(said) == 1 and "resume with" in said[0], said
    checkpoint = of.read_checkpoint(tmp_path / "run" / "checkpoint.pt", run=True)
    assert checkpoint["update"] >= 2 and len(of.read_train_log(log, checkpoint["update"])) == checkpoint["update"]
    assert of.main(["train", "--resume", "--out", str(tmp_path / "run"), "--workers", "1",
                    "--steps", str(checkpoint["env_steps"] + 60)]) == 0
    assert of.read_checkpoint(tmp_path / "run" / "checkpoint.pt")["update"] == checkpoint["update"] + 1


def test_a_bad_init_checkpoint_leaves_no_run_folder(tmp_path, capsys):
    err = one_line_exit_two(capsys, ["train", "--init", str(tmp_path / "missing.pt"), "--out", str(tmp_path / "r")])
    assert "not found" in err and not (tmp_path / "r").exists()


def test_a_randomised_sensor_draws_each_episodes_errors_within_its_range():
    errors = dict(tof_noise_ratio=0.01, tof_missing_share=0.02, hand_eye_error_m=0.003, hand_eye_error_rad=0.0175)
    cfg = dataclasses.replace(of.TASKS["ap"], sensor_error_scale=(0.0, 2.0), **errors)
    drawn = [of.episode_sensing(cfg, np.random.default_rng(seed)) for seed in range(40)]
    factors = np.array([s.tof_noise_ratio / 0.01 for s in drawn])
    assert 0 <= factors.min() < 0.3 and 1.7 < factors.max() <= 2.0   # the whole range is drawn
    for sensing, factor in zip(drawn, factors):   # one factor per episode scales every error alike
        assert all(np.isclose(getattr(sensing, name), value * factor) for name, value in errors.items())
    rng = np.random.default_rng(0)
    before = rng.bit_generator.state
    assert of.episode_sensing(of.TASKS["ap"], rng) is of.TASKS["ap"] and rng.bit_generator.state == before
    with pytest.raises(ValueError, match="sensor_error_scale"):   # its high end must keep each error in range
        of.checked_settings("ap", dict(tof_noise_ratio=0.1, sensor_error_scale=(0.0, 3.0)))


def test_a_training_world_is_kept_in_the_checkpoint_and_by_a_resumed_run(tmp_path, monkeypatch, capsys):
    made = []

    def spy_train(make_env, out, *args, **kwargs):
        made.append(make_env.keywords)
        model = of.ActorCritic(of.STATE_SIZE, of.PPOSettings())
        of.save_checkpoint(out / "checkpoint.pt", dict(
            format="objfind-ppo", model=model.state_dict(), optimizer=torch.optim.Adam(model.parameters()).state_dict(),
            settings=vars(of.PPOSettings()), obs_dim=of.STATE_SIZE, update=1, env_steps=1, wall_s=1.0, seed=0,
            **kwargs["meta"]))
        return dict(update=1, env_steps=1)
    monkeypatch.setattr(of, "train", spy_train)
    out = str(tmp_path / "run")
    assert of.main(["train", "--task", "ip", "--world", "tof_noise_ratio=0.01", "--world", "sensor_error_scale=0,2",
                    "--out", out]) == 0
    assert made[-1] == dict(tof_noise_ratio=0.01, sensor_error_scale=(0.0, 2.0))
    assert of.read_checkpoint(Path(out) / "checkpoint.pt", run=True)["world"] == made[-1]
    assert of.main(["train", "--resume", "--out", out]) == 0 and made[-1] == made[-2]
    capsys.readouterr()
    assert of.main(["train", "--world", "tof_noise_ratio=0.5", "--out", str(tmp_path / "other")]) == 2   # range
    assert of.main(["train", "--resume", "--world", "tof_noise_ratio=0.01", "--out", out]) == 2   # a run keeps its own
    with pytest.raises(SystemExit):
        of.main(["train", "--world", "no_such_field=1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and "tof_noise_ratio" in err[0] and "keeps its own" in err[1] and "Settings field" in err[2]


def test_the_median_filter_keeps_a_noisy_cameras_perceived_share_from_swelling():
    """1 % depth noise on the real preset's camera roughens the target's faces: without the filter the
    perceived share runs well above the ideal sensor's; with area_median_px=3 it stays near it
    (measured over these views: 1.26x and 0.86x the ideal's; a pixel too oblique by either one-sided
    difference counts nothing, which drops the noisiest already)."""
    def share_ratio(**overrides):
        env = of.ObjectFindingEnv("ap-real", "cubes-and-cuboids", tof_missing_share=0.0, tof_edge_jump_m=0.0,
                                  hand_eye_error_m=0.0, hand_eye_error_rad=0.0, **overrides)
        perceived, truth = [], []
        for seed in range(12):
            _, info = env.reset(seed=seed)
            if info["target_seen_fraction"] > 0.05:
                perceived.append(env.searcher.perceived_target_share())
                truth.append(info["target_seen_fraction"])
        env.close()
        return np.sum(perceived) / np.sum(truth)
    ideal = share_ratio(tof_noise_ratio=0.0, area_median_px=0)
    assert share_ratio(area_median_px=0) > 1.15 * ideal
    assert abs(share_ratio() / ideal - 1) < 0.2


def test_the_sensor_study_writes_every_point_and_reads_finished_ones_back(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sensors, "SENSOR_SWEEPS", sensors.SENSOR_SWEEPS[:1])    # one sweep, the active agents:
    monkeypatch.setattr(sensors, "SENSOR_AGENTS", sensors.SENSOR_AGENTS[:1])    # the machinery, not the figures
    monkeypatch.setattr(sensors, "SENSOR_BASELINES", sensors.SENSOR_BASELINES[:1])
    out = tmp_path / "sensors"
    assert sensors.main(["--episodes", "1", "--workers", "1", "--out", str(out)]) == 0
    points = len(sensors.sensor_points())
    assert len(list(out.glob("*.csv"))) == points * len(sensors.SENSOR_AGENTS) + 2 * len(sensors.SENSOR_BASELINES)
    table = (out / "sensors.md").read_text().splitlines()
    assert len([line for line in table if line.startswith("| ")]) == 1 + points   # the header and a row per point
    assert cv2.imread(str(out / "sensors.png")) is not None
    monkeypatch.setattr(sensors, "evaluate", lambda *a, **k: pytest.fail("a finished point was run again"))
    capsys.readouterr()
    assert sensors.main(["--episodes", "1", "--workers", "1", "--out", str(out)]) == 0
    assert capsys.readouterr().out.splitlines()[:len(table)] == table
    # one tampered stored point and one missing: refused before the missing one runs
    last = sorted(out.glob("*.csv"))[-1]
    last.write_text(last.read_text().replace(",True,", ",False,", 1))
    sorted(out.glob("*.csv"))[0].unlink()
    assert sensors.main(["--episodes", "1", "--workers", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and last.name in err[0], err


# --- past one machine: Ray (skipped where Ray is not installed) --------------------------------------

@pytest.fixture(scope="session")
def local_ray():
    """One local Ray instance for the session, with this folder as its workers' working directory."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, log_to_driver=False, include_dashboard=False,
             runtime_env={"working_dir": str(HERE), "excludes": of.RAY_EXCLUDES})
    yield ray
    ray.shutdown()


def test_episodes_on_ray_equal_the_process_pools(local_ray, tmp_path):
    for backend, extra in (("pool", ["--workers", "2"]), ("ray", ["--ray"])):
        assert of.main(["eval", "--agent", "gnbv", "--episodes", "4", "--seed", "7", *extra,
                        "--out", str(tmp_path / f"{backend}.csv")]) == 0
    timeless = lambda path: [{k: v for k, v in row.items() if k != "decision_ms"} for row in of.read_episodes(path)]
    assert timeless(tmp_path / "pool.csv") == timeless(tmp_path / "ray.csv")   # all but the measured time


def test_training_on_ray_gives_the_weights_of_processes_with_another_worker_count(local_ray, tmp_path):
    tiny = ["--task", "ap", "--steps", "60", "--set", "batch_steps=30", "--set", "minibatch=16", "--set", "hidden=16",
            "--streams", "3"]
    assert of.main(["train", *tiny, "--workers", "1", "--out", str(tmp_path / "pool")]) == 0
    assert of.main(["train", *tiny, "--workers", "2", "--ray", "--out", str(tmp_path / "ray")]) == 0
    a, b = (of.read_checkpoint(tmp_path / run / "checkpoint.pt", run=True) for run in ("pool", "ray"))
    assert a["update"] == b["update"] == 2 and a["rollout_streams"] == b["rollout_streams"] == 3
    for name, tensor in a["model"].items():
        assert torch.equal(tensor, b["model"][name]), name


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds Ray's worker processes through /proc")
@pytest.mark.parametrize("command, victim", [
    (["eval", "--agent", "gnbv", "--episodes", "200"], b"evaluate_chunk"),
    (["train", "--steps", "200000", "--set", "batch_steps=400", "--workers", "2"], b"RolloutActor")])
def test_a_killed_ray_worker_ends_the_command_with_one_line(local_ray, command, victim, tmp_path, capsys):
    import os
    import signal
    import threading
    import time

    missed = []

    def kill_one():
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            for proc in Path("/proc").iterdir():
                try:
                    if proc.name.isdigit() and (proc / "cmdline").read_bytes().startswith(b"ray::" + victim):
                        time.sleep(2)
                        os.kill(int(proc.name), signal.SIGKILL)
                        return
                except OSError:
                    continue
            time.sleep(0.2)
        missed.append(True)                      # no victim found: end the command now, not after the whole job
        os.kill(os.getpid(), signal.SIGINT)
    killer = threading.Thread(target=kill_one)
    killer.start()
    code = of.main([*command, "--ray", "--out", str(tmp_path / ("run" if command[0] == "train" else "x.csv"))])
    killer.join()
    said = [line for line in capsys.readouterr().err.replace("\r", "\n").splitlines() if line.startswith("objfind:")]
    assert not missed and code == 2 and len(said) == 1 and "worker process died" in said[0], said


def test_a_ray_address_nobody_answers_is_refused_within_thirty_seconds(tmp_path):
    pytest.importorskip("ray")
    t0 = of.time.perf_counter()
    done = subprocess.run([sys.executable, str(HERE / "objfind.py"), "eval", "--agent", "gnbv", "--episodes", "1",
                           "--ray", "127.0.0.1:1"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and of.time.perf_counter() - t0 < 30, done.stderr[-300:]
    assert done.stderr.strip().splitlines() == [done.stderr.strip()] and "nothing answers" in done.stderr


# --- tools/: each a script that imports objfind ------------------------------------------------------

@pytest.mark.parametrize("tool", ["replay.py", "sensors.py", "bench.py", "soak.py", "stops.py", "moves.py"])
def test_each_tool_runs_as_a_script_with_help(tool):
    done = subprocess.run([sys.executable, str(HERE / "tools" / tool), "--help"], capture_output=True, text=True,
                          timeout=300, cwd="/")
    assert done.returncode == 0 and done.stdout.startswith(f"usage: tools/{tool}"), done.stderr[-500:]


def test_moves_counts_a_greedy_move_at_the_bound_as_saturated_and_a_small_one_not():
    model = of.ActorCritic(of.STATE_SIZE, of.PPOSettings())
    policy = dict(model=model.state_dict(), settings=dataclasses.asdict(of.PPOSettings()), obs_dim=of.STATE_SIZE)
    with torch.no_grad():
        model.actor[-1].bias[-1] = 10.0   # stop after one step
    small = moves.greedy_moves(policy, "ap", "cubes", range(2))
    with torch.no_grad():   # the state dict holds the model's own tensors: the policy follows
        model.actor[-1].bias[:of.ACTION_MOVES] = torch.tensor([3.0, -3.0, 3.0, -3.0, 3.0])
    full = moves.greedy_moves(policy, "ap", "cubes", range(2))
    assert small.shape == full.shape == (2, of.ACTION_MOVES)
    assert (np.abs(small) < moves.SATURATED).all() and (np.abs(full) >= moves.SATURATED).all()
    assert (np.sign(full) == [1, -1, 1, -1, 1]).all()


@pytest.mark.parametrize("tool, args", [
    (replay_tool, ["play"]), (replay_tool, ["record", "x", "--seed", "-1"]), (replay_tool, ["fly"]),
    (sensors, ["--episodes", "0"]), (bench, ["--steps", "-5"]), (bench, ["--workers", "two"]),
    (soak, ["--episodes", "many"]), (soak, ["--seed", "4294967295", "--episodes", "2"])])
def test_a_bad_argument_to_a_tool_is_one_line_and_exit_two(tool, args, capsys):
    with pytest.raises(SystemExit) as stop:
        tool.main(args)
    err = capsys.readouterr().err.strip().splitlines()
    assert stop.value.code == 2 and len(err) == 1 and err[0].startswith("objfind: error:"), err


def test_a_recording_into_a_folder_in_use_is_refused_before_the_episode(tmp_path, capsys, monkeypatch):
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "notes.txt").write_text("an earlier recording")
    monkeypatch.setattr(replay_tool, "ObjectFindingEnv", lambda *a, **k: pytest.fail("an episode ran"))
    for folder in (tmp_path / "used", tmp_path / "no" / "parent"):
        assert replay_tool.main(["record", str(folder), "--agent", "random"]) == 2
        assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert (tmp_path / "used" / "notes.txt").read_text() == "an earlier recording"
