"""The sensor study (Sec. III-D): A3DE and I3DE as depth noise, missing returns and hand-eye error grow, and
GNBV and GES at the rig's camera, on the 0.6 m cube presets; a table (sensors.md) and a figure (sensors.png).

    python tools/sensors.py [--episodes 200] [--workers 2] [--out results/sensors]
"""
import os
import sys
import time
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from objfind import (RIG_SENSING, ArgumentParser, cell_origin,  # noqa: E402
                     episodes_arg, evaluate, learned_policy, replace_atomically, run_cli, save_figure, seed_arg,
                     stored_cell, summarise, workers_arg, write_csv, writable_folder)


RIG_ERRORS = {k: RIG_SENSING[k] for k in ("tof_noise_ratio", "tof_missing_share", "tof_edge_jump_m",
                                          "tof_edge_drop_share", "hand_eye_error_m", "hand_eye_error_rad",
                                          "area_median_px")}   # the rig's errors, on the presets' own camera
SENSOR_SWEEPS = (   # (name, axis title, a level in words, what it sets, four levels: none, the rig's, 2x, 4x or more)
    ("depth noise", "depth noise (% of the distance)", lambda x: f"{x:g} % of the distance",
     lambda x: dict(tof_noise_ratio=x / 100), (0, 1, 2, 4)),
    ("missing returns", "missing returns (% of the pixels)", lambda x: f"{x:g} % of the pixels",
     lambda x: dict(tof_missing_share=x / 100), (0, 2, 10, 30)),
    ("hand-eye error", "hand-eye error (mm, and mm / 3 degrees)", lambda x: f"{x:g} mm, {x / 3:g} deg",
     lambda x: dict(hand_eye_error_m=x / 1000, hand_eye_error_rad=np.radians(x / 3)), (0, 3, 6, 12)),
)
SENSOR_AGENTS = (("a3de", "ap"), ("i3de", "ip"))                # Table II's weights
SENSOR_BASELINES = (("gnbv", "ap"), ("ges", "ip"))               # with the ideal camera and the rig's


def sensor_points() -> list:
    """Every (sweep, level, overrides) of the study: the ideal camera (level 0 of every sweep), the sweeps'
    other levels, the rig's errors on the presets' camera, and the rig's camera as the real presets have it."""
    points = [("ideal", 0, {})]
    for name, _, _, overrides, levels in SENSOR_SWEEPS:
        points += [(name, level, overrides(level)) for level in levels[1:]]
    return points + [("rig errors", 1, RIG_ERRORS), ("rig camera", 1, RIG_SENSING)]


def point_file(agent: str, task: str, sweep: str, level: float) -> str:
    return f"{agent}-{task}-{sweep.replace(' ', '-')}-{level:g}.csv"


def run_sensor_study(out: Path, episodes: int, seed: int, workers: int) -> dict:
    """Every point's episodes (a CSV each, read back when already there), as {(row, sweep, level): summary}."""
    seeds, cells = list(range(seed, seed + episodes)), {}
    runs = [(row, point) for row in SENSOR_AGENTS for point in sensor_points()]
    runs += [(row, point) for row in SENSOR_BASELINES
             for point in sensor_points() if point[0] in ("ideal", "rig camera")]
    policies = {row: learned_policy(*row) for row in SENSOR_AGENTS}   # each checkpoint read once
    stored = [stored_cell(out / point_file(agent, task, sweep, level), seeds,   # every CSV checked first
                          cell_origin(agent, task, "cubes", policies.get((agent, task)), overrides))
              for (agent, task), (sweep, level, overrides) in runs]
    for ((agent, task), (sweep, level, overrides)), rows in zip(runs, stored):
        path = out / point_file(agent, task, sweep, level)
        if rows is None:
            rows = evaluate(agent, task, "cubes", episodes, seed, workers, policy=policies.get((agent, task)),
                            overrides=overrides)
            write_csv(rows, path)
        cells[(agent, task), sweep, level] = summarise(rows)
    return cells


def sensor_markdown(cells: dict, episodes: int) -> str:
    """The study as a table: a row per point, a column per agent, success % [95 %] / steps."""
    rows = SENSOR_AGENTS + SENSOR_BASELINES
    words = {name: describe for name, _, describe, _, _ in SENSOR_SWEEPS}
    header = ["depth camera"] + [f"{a.upper()}, {t}" for a, t in rows]
    lines = [f"Success % [95 %] / average steps over {episodes} paired episodes per point on cubes (episode i is "
             "scene seed + i at every point).", "", "| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for sweep, level, _ in sensor_points():
        name = {"ideal": "ideal", "rig errors": "the rig's errors on this camera (README)",
                "rig camera": "the rig's camera (`RIG_SENSING`)"}.get(sweep) or f"{sweep} {words[sweep](level)}"
        values = [cells.get((row, sweep, level)) for row in rows]
        lines.append(f"| {name} | " + " | ".join("" if c is None else f"{c['success']:.1f} [{c['success_lo']:.1f}, "
                                                 f"{c['success_hi']:.1f}] / {c['steps']:.2f}" for c in values) + " |")
    return "\n".join(lines)


def plot_sensor_study(cells: dict, path: Path) -> None:
    """Per sweep, and for the rig as a whole, success % (with its 95 % interval) and average steps of each
    learned agent against the level: a column of two panels each."""
    panels = [(title, [(f"{level:g}", ("ideal", 0) if level == 0 else (sweep, level)) for level in levels])
              for sweep, title, _, _, levels in SENSOR_SWEEPS]
    panels.append(("the rig (RIG_SENSING)", [("ideal", ("ideal", 0)), ("its errors", ("rig errors", 1)),
                                             ("its camera", ("rig camera", 1))]))
    figure = Figure(figsize=(10.4, 5.6), layout="constrained")
    axes = figure.subplots(2, len(panels), sharey="row")
    for p, (title, levels) in enumerate(panels):
        for r, row in enumerate(SENSOR_AGENTS):
            found = [(i, cells.get((row, *point))) for i, (_, point) in enumerate(levels)]
            x = np.array([i for i, c in found if c]) + 0.04 * r
            label = f"{row[0].upper()} on {row[1]}"
            success = np.array([[c["success"], c["success_lo"], c["success_hi"]] for _, c in found if c]).reshape(-1, 3)
            axes[0, p].errorbar(x, success[:, 0], yerr=np.abs(success[:, 1:].T - success[:, 0]), color=f"C{r}",
                                label=label, capsize=2)
            axes[1, p].plot(x, [c["steps"] for _, c in found if c], color=f"C{r}", marker="o")
        for ax in axes[:, p]:
            ax.set_xticks(range(len(levels)), [text for text, _ in levels], fontsize=8)
            ax.grid(alpha=0.3)
        axes[0, p].set_title(title, fontsize=8)
    axes[0, 0].set_ylim(50, 100)
    axes[0, 0].set_ylabel("success %")
    axes[1, 0].set_ylabel("average steps")
    figure.legend(*axes[0, 0].get_legend_handles_labels(), loc="outside upper center",
                  ncol=len(SENSOR_AGENTS))
    save_figure(figure, path)


def cmd_sensors(args) -> int:
    """The sensor study: every point's CSV in --out (finished ones read back), then sensors.md and sensors.png."""
    out, t0 = writable_folder(Path(args.out)), time.perf_counter()
    cells = run_sensor_study(out, args.episodes, args.seed, args.workers)
    markdown = sensor_markdown(cells, args.episodes)
    replace_atomically(out / "sensors.md", lambda tmp: tmp.write_text(markdown + "\n"))
    plot_sensor_study(cells, out / "sensors.png")
    print(markdown)
    print(f"wrote {out / 'sensors.md'}, {out / 'sensors.png'} and one CSV per point; {time.perf_counter() - t0:.0f} s")
    return 0


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="tools/sensors.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=episodes_arg, default=200, help="paired episodes per point (default 200)")
    parser.add_argument("--workers", type=workers_arg, default=os.cpu_count() or 1, help="worker processes")
    parser.add_argument("--seed", type=seed_arg, default=0, help="episode i uses scene seed + i at every point")
    parser.add_argument("--out", default="results/sensors", help="folder for the CSVs, sensors.md and sensors.png "
                        "(default results/sensors; a point whose CSV is there is read back)")
    parser.set_defaults(func=cmd_sensors)
    return parser


def main(argv: list | None = None) -> int:
    return run_cli(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
