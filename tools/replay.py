"""Recordings: an episode as a real RGB-D logger writes it, replayed through `ArmSearch`, the loop an arm runs.

    python tools/replay.py record DIR [--agent a3de --task ap --scene cubes --seed 0]   # a simulated episode
    python tools/replay.py play DIR [--agent a3de] [--depth png] [--masks MASKS]          # any recording

A recording (this file is its format's one home): recording.json (task, settings, both cameras'
intrinsics, T_depth_rgb, T_tool_depth, T_base_workspace, the workspace box, the tool frame, the target's
area) and per frame frames/NNNNNN-color.png, -depth.png (16-bit mm, 0: no return), -pose.json
(T_base_tool, T_base_depth), and from the simulation -depth.npy, -detections.npy (what the searcher fused).
"""
import csv
import dataclasses
import json
import os
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from objfind import (ACTION_NAMES, BASELINES, LEARNED, MAX_SEED, PANEL, TASKS, ArgumentParser,  # noqa: E402
                     ArmSearch, Camera, ObjectFindingEnv, Rig, Searcher, Settings, UsageError, add_agent_args,
                     agent_policy, bins_panel, checked_settings, default_task, detect_target, field_kind, label,
                     make_agent, policy_fingerprint, quat_of, run_cli, seed_arg, volume_panel,
                     wrist_panel, write_contact_sheet, write_csv, writable_folder)

RECORDING_FORMAT = "objfind-recording/1"
DEPTH_PNG_M = 0.001   # a 16-bit depth PNG holds millimetres (0: no return), as RealSense and ROS loggers write
TOOL_FRAME = ("tool frame: origin between the fingertips; x to the gripper's right, y away from its front, z along "
              "the approach axis (out of the palm); the workspace frame: the floor's centre, z up")
FRAME_FILES = {"color": "color.png", "depth": "depth.png", "pose": "pose.json",    # what a logger writes
               "depth_m": "depth.npy", "detections": "detections.npy"}           # what the searcher consumed


def frame_file(folder: Path, index: int, kind: str) -> Path:
    return folder / "frames" / f"{index:06d}-{FRAME_FILES[kind]}"


def camera_json(camera: Camera) -> dict:
    return dict(width=camera.width, height=camera.height, K=camera.K.tolist(), near_m=camera.near_m,
                far_m=None if np.isinf(camera.far_m) else camera.far_m)


def recording_meta(env: ObjectFindingEnv, agent_name: str, seed: int) -> dict:
    """Everything of a recording but its frames: the rig, the workspace and the told target size."""
    rig, cfg = env.searcher.rig, env.cfg   # the calibration the robot believes
    half = cfg.workspace_m / 2
    return dict(format=RECORDING_FORMAT, source=f"objfind simulation: {agent_name} on {env.task}/{env.scene}",
                task=env.task, settings={}, seed=seed, target_area_m2=env.searcher.target_area_m2,
                depth_camera=camera_json(rig.depth), rgb_camera=camera_json(rig.rgb),
                T_depth_rgb=rig.T_depth_rgb.tolist(), T_tool_depth=rig.T_tool_depth.tolist(),
                T_base_workspace=np.eye(4).tolist(),
                workspace_box_m=dict(lo=[-half, -half, 0.0], hi=[half, half, cfg.ceiling_m]),
                tool_frame=TOOL_FRAME, depth_png_m=DEPTH_PNG_M)


def write_recording(folder: Path, meta: dict, views: list, actions: list) -> None:
    """The frames (WristView, T_world_tool) and the agent's actions into a new folder, made complete under a
    temporary name and then renamed: an interrupted run leaves no half recording."""
    folder = Path(folder)
    check_new_folder(folder)
    tmp = folder.with_name(f".{folder.name}.{os.getpid()}.partial")
    try:
        (tmp / "frames").mkdir(parents=True)
        for i, (view, T_world_tool) in enumerate(views):
            depth_mm = np.clip(np.round(view.depth_m / DEPTH_PNG_M), 0, 65535).astype(np.uint16)
            written = [cv2.imwrite(str(frame_file(tmp, i, "color")), cv2.cvtColor(view.rgb, cv2.COLOR_RGB2BGR)),
                       cv2.imwrite(str(frame_file(tmp, i, "depth")), depth_mm)]
            if not all(written):
                raise OSError("OpenCV could not write an image")
            np.save(frame_file(tmp, i, "depth_m"), view.depth_m)
            np.save(frame_file(tmp, i, "detections"), view.detections)
            pose = dict(T_base_tool=T_world_tool.tolist(), T_base_depth=view.T_world_camera.tolist())
            frame_file(tmp, i, "pose").write_text(json.dumps(pose))
        (tmp / "recording.json").write_text(json.dumps(dict(meta, frames=len(views)), indent=1))
        with open(tmp / "actions.csv", "w", newline="") as f:   # what the recording's own agent did
            writer = csv.writer(f)
            writer.writerow(("frame",) + ACTION_NAMES)
            writer.writerows([i, *map(float, action)] for i, action in enumerate(actions))
        if folder.exists():
            folder.rmdir()
        os.rename(tmp, folder)
    except OSError as error:
        shutil.rmtree(tmp, ignore_errors=True)
        raise UsageError(f"could not write the recording {str(folder)!r} ({error.strerror or error})") from None


def checked_matrix(value, name: str, shape: tuple) -> np.ndarray:
    """A JSON value as a finite float64 array of `shape`, or a ValueError naming it."""
    try:
        array = np.array(value, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} is not a {shape[0]} x {shape[1]} matrix of numbers") from None
    if array.shape != shape or not np.all(np.isfinite(array)):
        raise ValueError(f"{name} is not a {shape[0]} x {shape[1]} matrix of finite numbers")
    return array


def checked_transform(value, name: str) -> np.ndarray:
    """A 4 x 4 rigid transform: rotation orthonormal with determinant 1, last row 0 0 0 1."""
    T = checked_matrix(value, name, (4, 4))
    R = T[:3, :3]
    if not (np.allclose(T[3], [0, 0, 0, 1]) and np.allclose(R @ R.T, np.eye(3), atol=1e-4)
            and np.linalg.det(R) > 0):
        raise ValueError(f"{name} is not a rigid transform (a rotation and a translation, last row 0 0 0 1)")
    return T


def checked_camera(value, name: str) -> Camera:
    """A camera's JSON: whole width and height, fx and fy above 0, the principal point on the image."""
    if not isinstance(value, dict) or not {"width", "height", "K"} <= set(value):
        raise ValueError(f"{name} needs width, height and K")
    width, height = value["width"], value["height"]
    if not all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 10_000 for v in (width, height)):
        raise ValueError(f"{name}: width and height must be whole numbers of pixels")
    K = checked_matrix(value["K"], f"{name}.K", (3, 3))
    if not (K[0, 0] >= 1 and K[1, 1] >= 1 and 0 <= K[0, 2] <= width and 0 <= K[1, 2] <= height
            and np.allclose(K[2], [0, 0, 1])):
        raise ValueError(f"{name}.K does not fit a {width} x {height} image (fx, fy >= 1 pixel, the principal "
                         "point on it)")
    near, far = value.get("near_m", 0.0), value.get("far_m")
    far = np.inf if far is None else far
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (near, far)) or not 0 <= near < far:
        raise ValueError(f"{name}: near_m and far_m must be numbers with 0 <= near_m < far_m")
    return Camera(width, height, K, float(near), float(far))


MAX_JSON_BYTES = 2 ** 20   # recording.json and a frame's pose.json are a few kB


def read_json(path: Path, what: str):
    """A JSON file of at most MAX_JSON_BYTES (a link to /dev/zero is no file), or a ValueError."""
    if not path.is_file():
        raise ValueError(f"{what} {path.name} is missing or not a file")
    with open(path, "rb") as f:
        text = f.read(MAX_JSON_BYTES + 1)
    if len(text) > MAX_JSON_BYTES:
        raise ValueError(f"{what} {path.name} is over {MAX_JSON_BYTES // 1024} kB")
    try:
        return json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{what} {path.name} is unreadable ({error})") from None


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's header, read before the image is decoded; None if it is no PNG."""
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def read_image(path: Path, shape: tuple, dtype, what: str) -> np.ndarray:
    """A PNG of exactly `shape` and `dtype`, its size checked before it is decoded, or a ValueError saying how
    it differs."""
    size = png_size(path) if path.is_file() else None
    if size is None:
        raise ValueError(f"{what} {path.name} is missing or not a PNG")
    if size != (shape[1], shape[0]):
        raise ValueError(f"{what} {path.name} is {size[0]} x {size[1]} pixels, the recording's camera "
                         f"{shape[1]} x {shape[0]}")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{what} {path.name} is missing or not an image")
    if image.dtype != dtype or image.shape != shape:
        raise ValueError(f"{what} {path.name} is {image.shape} {image.dtype}, the recording's camera needs "
                         f"{shape} {np.dtype(dtype)}")
    return image


def read_array(path: Path, shape: tuple, low: float, high: float, what: str) -> np.ndarray:
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:
        raise ValueError(f"{what} {path.name} is missing or unreadable ({error or type(error).__name__})") from None
    if not isinstance(array, np.ndarray):   # an .npz archive
        raise ValueError(f"{what} {path.name} is not one .npy array")
    if array.shape != shape or array.dtype.kind != "f" or not np.all((array >= low) & (array <= high)):
        raise ValueError(f"{what} {path.name} must be {shape} floats in [{low}, {high}]")
    return array.astype(np.float32)


def depth_source_of(folder: Path, asked: str | None) -> str:
    """The depth a replay reads: the one asked for, else the exact float depth where it is stored, else the PNGs."""
    return asked or ("exact" if frame_file(folder, 0, "depth_m").is_file() else "png")


def read_recording(folder: Path, depth_source: str | None = None, masks: Path | None = None) -> tuple:
    """A recording, every file checked before anything runs: (settings, rig, meta, frames), each frame a dict
    of depth_m, rgb, detections (or None: the colour detector's) and the poses. depth_source "exact" reads
    the float depth the simulated searcher consumed, "png" the logger's millimetres (default: exact if there)."""
    folder = Path(folder)
    try:
        meta = read_json(folder / "recording.json", "the recording's")
        if not isinstance(meta, dict) or meta.get("format") != RECORDING_FORMAT:
            raise ValueError(f"recording.json is not in the format {RECORDING_FORMAT!r}")
        if not isinstance(meta.get("task"), str) or meta["task"] not in TASKS or not isinstance(
                meta.get("settings", {}), dict):
            raise ValueError(f"recording.json: task must be one of {', '.join(TASKS)}, settings an object")
        seed = meta.get("seed", 0)
        if not (isinstance(seed, int) and not isinstance(seed, bool) and 0 <= seed <= MAX_SEED):
            raise ValueError(f"recording.json: seed must be a whole number in [0, {MAX_SEED}]")
        tuples = {f.name for f in dataclasses.fields(Settings) if field_kind(f) == "tuple"}   # JSON has lists
        settings = {k: tuple(v) if k in tuples and isinstance(v, list) else v
                    for k, v in meta.get("settings", {}).items()}
        try:
            cfg = checked_settings(meta["task"], settings)
        except ValueError as error:
            raise ValueError(f"recording.json settings: {error}") from None
        depth = checked_camera(meta.get("depth_camera"), "depth_camera")
        rgb = checked_camera(meta.get("rgb_camera"), "rgb_camera")
        T_depth_rgb = checked_transform(meta.get("T_depth_rgb"), "T_depth_rgb")
        if camera_json(rgb) == camera_json(depth) and np.array_equal(T_depth_rgb, np.eye(4)):
            rgb = depth   # one RGB-D camera
        rig = Rig(depth, rgb, checked_transform(meta.get("T_tool_depth"), "T_tool_depth"), T_depth_rgb)
        meta["T_base_workspace"] = checked_transform(meta.get("T_base_workspace", np.eye(4).tolist()),
                                                     "T_base_workspace")
        half = cfg.workspace_m / 2
        box = meta.get("workspace_box_m", {})
        if not (isinstance(box, dict) and np.allclose(np.array([box.get("lo"), box.get("hi")], dtype=float),
                                                      [[-half, -half, 0], [half, half, cfg.ceiling_m]])):
            raise ValueError(f"workspace_box_m must be the task's box, lo [{-half}, {-half}, 0] and hi "
                             f"[{half}, {half}, {cfg.ceiling_m}] in the workspace frame: set settings.workspace_m")
        area = meta.get("target_area_m2")
        if area is not None and not (isinstance(area, (int, float)) and not isinstance(area, bool) and 0 < area < 1):
            raise ValueError("target_area_m2 must be a target's surface in m^2, in (0, 1), or null when not told")
        count = meta.get("frames")
        if not isinstance(count, int) or count < 1:
            raise ValueError("recording.json: frames must be the number of frames, at least 1")
        named = {int(p.name[:6]) for p in (folder / "frames").glob("[0-9]" * 6 + "-*")}
        if any(i >= count for i in named):
            raise ValueError(f"frames/{max(named):06d}-* lies beyond the {count} frames recording.json lists")
        depth_source = depth_source_of(folder, depth_source)
        scale = meta.get("depth_png_m", DEPTH_PNG_M)
        if not (isinstance(scale, (int, float)) and not isinstance(scale, bool) and 1e-6 <= scale <= 0.1):
            raise ValueError("depth_png_m must be the metres of one unit of a depth PNG, in [1e-6, 0.1]")
        frames = []
        for i in range(count):
            if i not in named:
                raise ValueError(f"frame {i} of {count} is missing (frames/{i:06d}-*)")
            try:
                pose = read_json(frame_file(folder, i, "pose"), f"frame {i}:")
                T_base_tool = checked_transform(pose["T_base_tool"], f"frame {i}: T_base_tool")
                T_base_depth = (checked_transform(pose["T_base_depth"], f"frame {i}: T_base_depth")
                                if "T_base_depth" in pose else None)
            except (KeyError, TypeError) as error:
                raise ValueError(f"frame {i}: {frame_file(folder, i, 'pose').name} is unreadable "
                                 f"({type(error).__name__}: {error})") from None
            colour = read_image(frame_file(folder, i, "color"), (rgb.height, rgb.width, 3), np.uint8, "colour image")
            depth_mm = read_image(frame_file(folder, i, "depth"), (depth.height, depth.width), np.uint16, "depth image")
            if depth_source == "exact":
                depth_m = read_array(frame_file(folder, i, "depth_m"), depth_mm.shape, 0, np.inf, "depth")
                detections = read_array(frame_file(folder, i, "detections"), colour.shape[:2], 0, 1, "detections")
            else:
                depth_m, detections = depth_mm.astype(np.float32) * np.float32(float(scale)), None
            if masks is not None:
                mask = read_image(Path(masks) / f"{i:06d}.png", colour.shape[:2], np.uint8, "detection mask")
                detections = mask.astype(np.float32) / 255
            frames.append(dict(rgb=cv2.cvtColor(colour, cv2.COLOR_BGR2RGB), depth_m=depth_m, detections=detections,
                               T_base_tool=T_base_tool, T_base_depth=T_base_depth))
    except ValueError as error:
        raise UsageError(f"recording {str(folder)!r}: {error}") from None
    return cfg, rig, meta, frames


def recorded_actions(folder: Path) -> list | None:
    """The recording's own agent's actions (a simulated recording has them), or None."""
    try:
        with open(Path(folder) / "actions.csv", newline="") as f:
            return [np.array([float(row[name]) for name in ACTION_NAMES]) for row in csv.DictReader(f)]
    except (OSError, KeyError, ValueError):
        return None


def replay(cfg: Settings, rig: Rig, meta: dict, frames: list, agent_name: str, policy: dict | None = None,
           seed: int | None = None) -> tuple[list, list, list]:
    """The recording's frames through ArmSearch with an agent until it stops or the frames end:
    (rows of the replay CSV, states, contact-sheet pictures)."""
    searcher = Searcher(cfg, rig)
    agent = make_agent(agent_name, cfg, meta.get("seed", 0) if seed is None else seed, policy)
    arm = ArmSearch(searcher, agent, meta["T_base_workspace"], meta.get("target_area_m2"))
    rows, states, pictures = [], [], []
    for i, frame in enumerate(frames):
        detections = frame["detections"] if frame["detections"] is not None else detect_target(frame["rgb"])
        action, T_goal = arm.step(frame["depth_m"], frame["T_base_tool"], detections=detections,
                                  T_base_depth=frame["T_base_depth"])
        T_tool = arm.in_workspace(frame["T_base_tool"])
        states.append(searcher.state(T_tool))
        row = dict(frame=i, **{n: float(a) for n, a in zip(ACTION_NAMES, action)}, stop=T_goal is None)
        goal = dict(zip(("goal_x_m", "goal_y_m", "goal_z_m", "goal_qx", "goal_qy", "goal_qz", "goal_qw"),
                        [None] * 7 if T_goal is None else [*T_goal[:3, 3], *quat_of(T_goal[:3, :3])]))
        rows.append(row | {k: v if v is None else float(v) for k, v in goal.items()})
        command = ("stop: the search ends" if T_goal is None else
                   "move to ({:.3f}, {:.3f}, {:.3f}) m".format(*T_goal[:3, 3]))
        pictures.append(np.concatenate([
            wrist_panel(frame["rgb"], detections, searcher.detection_threshold),
            volume_panel(searcher, T_tool), bins_panel(states[-1]),
            label(np.full((PANEL[1], PANEL[0], 3), 255, np.uint8), f"frame {i}: {command}")], axis=1))
        if T_goal is None:
            break
    return rows, states, pictures


def check_new_folder(folder: Path) -> None:
    """A recording goes into a new or empty folder whose parent exists: checked before any episode runs."""
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise UsageError(f"{str(folder)!r} exists and is not an empty folder: a recording needs a new one")
    if not folder.parent.is_dir():
        raise UsageError(f"the parent of the recording folder {str(folder)!r} does not exist")


def record(agent_name: str, task: str, scene: str, seed: int, policy: dict | None, folder: Path) -> dict:
    """One simulated episode, as the demo plays it, into a recording: the views the searcher fused and the
    agent's actions. Returns the last step's info."""
    check_new_folder(folder)
    env = ObjectFindingEnv(task, scene, seed=seed)
    agent = make_agent(agent_name, env.cfg, seed, policy)
    env.reset()
    agent.reset(env.searcher, env.gripper_pose())
    views, actions, done = [(env.view, env.gripper_pose())], [], False
    while not done:
        actions.append(agent.act(env.searcher, env.gripper_pose()))
        _, _, done, _, info = env.step(actions[-1])
        if not info.get("terminated_by_agent"):
            views.append((env.view, env.gripper_pose()))
    meta = recording_meta(env, agent_name, seed)
    env.close()
    write_recording(folder, meta, views, actions)
    return info


def cmd_record(args) -> int:
    args.task, args.scene = args.task or default_task(args.agent), args.scene or "cubes"
    info = record(args.agent, args.task, args.scene, args.seed, agent_policy(args), Path(args.folder))
    outcome = "success" if info["success"] else "failure"
    print(f"{args.agent} on {args.task}/{args.scene} seed {args.seed}: {outcome} after {info['steps']} steps; "
          f"wrote the recording {args.folder}")
    return 0


REPLAY_ORIGIN = ("recording", "agent", "weights", "depth", "masks", "seed")   # on every row of a replay's CSV


def stored_replay_origin(path: Path) -> dict | None:
    """What made the replay CSV at `path` (its first row's REPLAY_ORIGIN), or None if there is none yet."""
    if not path.exists():
        return None
    try:
        with open(path, newline="") as f:
            row = next(csv.DictReader(f), None)
        return {k: row[k] for k in REPLAY_ORIGIN}
    except (OSError, UnicodeDecodeError, csv.Error, KeyError, TypeError):
        raise UsageError(f"{str(path)!r} is there and is not a replay's CSV: pass another --out") from None


def cmd_play(args) -> int:
    """Check the whole recording and the output, then run it through ArmSearch and write the contact sheet
    and the CSV, whose rows say what made them; a replay never replaces another experiment's."""
    folder = Path(args.folder)
    cfg, rig, meta, frames = read_recording(folder, args.depth, args.masks)
    args.task = meta["task"]
    policy = agent_policy(args)
    depth = depth_source_of(folder, args.depth)
    origin = dict(recording=str(folder.resolve()), agent=args.agent, weights=policy_fingerprint(policy), depth=depth,
                  masks=str(Path(args.masks).resolve()) if args.masks else "none",
                  seed=str(meta.get("seed", 0) if args.seed is None else args.seed))
    out = writable_folder(Path(args.out))
    stem = out / f"replay-{folder.resolve().name}-{args.agent}-{depth}{'-masks' * bool(args.masks)}"
    made = stored_replay_origin(stem.with_suffix(".csv"))
    if made not in (None, origin):
        raise UsageError(f"{stem.with_suffix('.csv')} was made by another replay ({made['recording']}, "
                         f"{made['agent']}, weights {made['weights']}): pass another --out, or delete it")
    rows, states, pictures = replay(cfg, rig, meta, frames, args.agent, policy, args.seed)
    write_contact_sheet(stem.with_suffix(".png"), pictures)
    write_csv([dict(row, **origin) for row in rows], stem.with_suffix(".csv"))
    ending = "stopped" if rows[-1]["stop"] else "had not stopped when the frames ended"
    print(f"{args.agent} on {len(rows)} of {len(frames)} frames of {args.folder}: {ending}")
    recorded = recorded_actions(Path(args.folder))
    if recorded:
        same = sum(np.array_equal([row[n] for n in ACTION_NAMES], a) for row, a in zip(rows, recorded))
        print(f"actions equal to the recording's own: {same} of {min(len(rows), len(recorded))}")
    print(f"wrote {stem.with_suffix('.png')} and {stem.with_suffix('.csv')}")
    return 0


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="tools/replay.py", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    recording = commands.add_parser("record", help="a simulated episode into a new recording folder")
    recording.add_argument("folder", help="the new (or empty) folder")
    add_agent_args(recording, "a3de")
    recording.add_argument("--seed", type=seed_arg, default=0, help="the scene's seed (default 0)")
    recording.set_defaults(func=cmd_record)
    playing = commands.add_parser("play", help="a recording (simulated, or a real rig's) through an agent")
    playing.add_argument("folder", help="the recording's folder (recording.json, frames/)")
    playing.add_argument("--agent", choices=list(BASELINES) + list(LEARNED), default="a3de",
                         help="the agent that decides at each frame (default a3de)")
    playing.add_argument("--weights", help="a learned agent's checkpoint (default: its shipped weights)")
    playing.add_argument("--seed", type=seed_arg, help="a baseline's random seed (default: the recording's)")
    playing.add_argument("--depth", choices=("exact", "png"),
                         help="exact: the float depth and detections the simulation gave the searcher; png: "
                              "the 16-bit millimetre depth and the colour detector (default exact where stored)")
    playing.add_argument("--masks", metavar="DIR", help="your detector's masks, DIR/NNNNNN.png per frame "
                         "(8-bit, the score x 255, the colour image's size): they replace the colour detector")
    playing.add_argument("--out", default="out", help="folder for replay-NAME-AGENT-DEPTH.png and .csv (default out)")
    playing.set_defaults(func=cmd_play)
    return parser


def main(argv: list | None = None) -> int:
    return run_cli(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
