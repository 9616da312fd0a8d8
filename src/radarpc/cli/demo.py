"""``radarpc demo``: the main job end to end on the embedded simulator.

RADIal side: simulate a RADIal-layout dataset -> summarize and check it -> spectral point clouds
at RADIal's default density with both enrichments (SpectralPillars input) -> a frame figure (the
test frame with the most labelled vehicles).
ColoRadar side: simulate ColoRadar-layout runs -> OS-CFAR baseline tuned on val -> Chamfer / EMD
on test. Every step is the same ``radarpc`` command a user would type (printed before it runs),
so the demo doubles as a tour; the run folder ends with ``REPORT.md``. Re-running resumes.
"""
from __future__ import annotations

import json
import shlex
import time
from dataclasses import dataclass, field
from pathlib import Path

from radarpc import __version__

__all__ = ["DemoConfig", "figure_frame", "run_demo", "add_parser"]


@dataclass(frozen=True)
class DemoConfig:
    """Sizes of the demo run (defaults: a few minutes on 2 CPU cores)."""

    out: Path = Path("demo")                # run folder
    sensor: str = "radial-s"                # RADIal-like sensor: radial-s (fast) or radial (full size)
    sequences: int = 6                      # simulated RADIal sequences (4 train, 1 val, 1 test)
    frames_per_sequence: int = 16           # frames per sequence
    density: float = 0.057                  # RADIal's default point-cloud density
    enrich: str = "rd3,sector32"            # SpectralPillars enrichments
    colo_scenes: str = "hallway,outdoor"     # ColoRadar scenes (3 runs each: train, val, test)
    colo_runs_per_scene: int = 3            # runs per scene
    colo_frames: int = 6                    # frames per run
    colo_lidar_beams: int = 32              # LiDAR beams (64 for the real sensor's pattern)
    seed: int = 0                           # simulator seed
    device: str = "cpu"                     # torch device for synthesis and DSP
    quick_tune: bool = False                # OS-CFAR tuned on a 3-setting grid (smoke tests)


@dataclass
class _Step:
    name: str
    argv: list[str]
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)


def _run(step: _Step) -> None:
    from radarpc.cli import baseline, evaluate_points, info, pointcloud, show, simulate
    from radarpc.cli.runner import build_parser, run_command

    print(f"\n$ radarpc {shlex.join(step.argv)}", flush=True)
    t0 = time.perf_counter()
    code = run_command(build_parser([simulate, info, pointcloud, show, baseline, evaluate_points]), step.argv)
    step.seconds = time.perf_counter() - t0
    if code != 0:
        raise RuntimeError(f"demo step {step.name!r} failed with exit code {code}: radarpc {shlex.join(step.argv)}")


def _most_labelled(ds) -> tuple[int, int]:
    """``(numSample, vehicles)`` of the frame of ``ds`` with the most labelled vehicles, the first
    in numSample order on a tie."""
    counts = [len(ds.label_tensor(i)) for i in range(len(ds.frame_ids))]
    best = max(range(len(counts)), key=lambda i: (counts[i], -i))       # frame_ids ascend
    return ds.frame_ids[best], counts[best]


def figure_frame(root: str | Path) -> tuple[int, int, str]:
    """The frame the demo draws: the test frame with the most labelled vehicles (the first such in
    numSample order on a tie); of every frame when the root has no test split or no test frame
    has a vehicle.

    Returns ``(numSample, number of labelled vehicles, split chosen from)``.
    """
    from radarpc.data.radial import RADIal

    try:
        test = RADIal(root, split="test")
    except ValueError:                                  # fewer than 3 sequences: no test split
        test = None
    if test is not None:
        frame, n = _most_labelled(test)
        if n > 0:
            return frame, n, "test"
    return (*_most_labelled(RADIal(root, split="all")), "all")


def run_demo(cfg: DemoConfig) -> Path:
    """Run every step of the demo into ``cfg.out``; return the path of ``REPORT.md``."""
    import torch

    from radarpc.cli.text import plural
    from radarpc.io import atomic_write
    from radarpc.machine import cpu_model

    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    radial_root = out / "sim_radial"
    store = out / f"pointcloud_{cfg.density:g}.parquet"
    colo_root = out / "sim_colo"
    preds = out / "preds" / "oscfar"
    frame_step = _Step("frame figure", [])         # its frame is chosen once the root exists
    steps = [
        _Step("simulate RADIal", ["simulate", "radial", "--out", str(radial_root), "--sensor", cfg.sensor,
                                  "--sequences", str(cfg.sequences), "--frames-per-sequence",
                                  str(cfg.frames_per_sequence), "--seed", str(cfg.seed), "--device", cfg.device]),
        _Step("check RADIal", ["info", str(radial_root), "--check", "--plot", str(out / "radial_info.png")]),
        _Step("spectral point clouds", ["pointcloud", str(radial_root), "--density", str(cfg.density),
                                        "--enrich", cfg.enrich, "--out", str(store), "--device", cfg.device]),
        frame_step,
        _Step("simulate ColoRadar", ["simulate", "coloradar", "--out", str(colo_root), "--scenes", cfg.colo_scenes,
                                     "--runs-per-scene", str(cfg.colo_runs_per_scene), "--frames", str(cfg.colo_frames),
                                     "--seed", str(cfg.seed), "--lidar-beams", str(cfg.colo_lidar_beams)]),
        _Step("check ColoRadar", ["info", str(colo_root), "--plot", str(out / "coloradar_info.png")]),
        _Step("OS-CFAR baseline", ["baseline", "os-cfar", str(colo_root), "--split", "test", "--out", str(preds)]
              + (["--quick-tune"] if cfg.quick_tune else [])),
        _Step("Chamfer / EMD", ["evaluate-points", str(preds), "--data", str(colo_root), "--split", "test"]),
    ]
    t_all = time.perf_counter()
    for step in steps:
        if step is frame_step:
            frame, n_vehicles, split = figure_frame(radial_root)
            step.argv = ["show", str(radial_root), "--frame", str(frame), "--density", str(cfg.density),
                         "--out", str(out / "frame.png"), "--device", cfg.device]
            where = "test frame" if split == "test" else "frame of any split"
            step.notes.append(f"`frame.png` draws frame {frame} (numSample), the {where} with the most "
                              f"labelled vehicles ({n_vehicles})")
        _run(step)
    total = time.perf_counter() - t_all

    # ---- what the steps produced ---------------------------------------------------------------
    from radarpc.data.pointstore import PointStore

    ps = PointStore(store)
    n_points = int(ps.frame_table.n_points.sum())
    steps[2].notes.append(f"{plural(len(ps), 'frame')}, {plural(n_points, 'point')}, target density {cfg.density}, "
                          f"achieved mean density {ps.metadata.achieved_density:.4f} (of the encoded set S*(tau); "
                          f"CFAR peaks S(tau) alone {ps.metadata.peak_density:.4f})")
    metrics_md = preds / "metrics.md"
    report = out / "REPORT.md"
    lines = [
        "# radarpc demo report", "",
        f"radarpc {__version__}, torch {torch.__version__}, device {cfg.device}, "
        f"{plural(torch.get_num_threads(), 'thread')}, {cpu_model()}, "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}", "",
        "| step | command | seconds |", "|---|---|---|",
    ]
    lines += [f"| {s.name} | `radarpc {shlex.join(s.argv)}` | {s.seconds:.1f} |" for s in steps]
    lines += ["", f"Total: {total:.1f} s.", ""]
    for s in steps:
        lines += [f"- {s.name}: {n}" for n in s.notes]
    lines += ["", "Figures: `radial_info.png`, `frame.png`, `coloradar_info.png`.", ""]
    if metrics_md.is_file():
        lines += ["## OS-CFAR baseline on the simulated ColoRadar test split", "", metrics_md.read_text()]
    with atomic_write(report, "w") as f:
        f.write("\n".join(lines) + "\n")
    summary = {"total_seconds": round(total, 1), "steps": {s.name: round(s.seconds, 1) for s in steps},
               "report": str(report)}
    print("\n" + json.dumps(summary, indent=1))
    return report


def add_parser(sub) -> None:
    p = sub.add_parser("demo", help="run the main job end to end on the embedded simulator",
                       description=__doc__)
    d = DemoConfig()
    p.add_argument("--out", default=str(d.out), help=f"run folder (default {d.out})")
    p.add_argument("--sensor", choices=("radial-s", "radial"), default=d.sensor,
                   help=f"RADIal-like sensor (default {d.sensor}; radial = full 512x256x16 cubes)")
    p.add_argument("--sequences", type=int, default=d.sequences,
                   help=f"simulated RADIal sequences (default {d.sequences}: 4 train, 1 val, 1 test)")
    p.add_argument("--frames-per-sequence", type=int, default=d.frames_per_sequence,
                   help=f"frames per RADIal sequence (default {d.frames_per_sequence})")
    p.add_argument("--colo-frames", type=int, default=d.colo_frames,
                   help=f"radar frames per ColoRadar run (default {d.colo_frames}; scenes {d.colo_scenes}, "
                        f"{d.colo_runs_per_scene} runs each)")
    p.add_argument("--seed", type=int, default=d.seed, help=f"simulator seed (default {d.seed})")
    p.add_argument("--device", default=d.device, help=f"torch device: cpu, cuda, cuda:1, ... (default {d.device})")
    p.set_defaults(func=lambda a: run_demo(DemoConfig(
        out=Path(a.out), sensor=a.sensor, sequences=a.sequences, frames_per_sequence=a.frames_per_sequence,
        colo_frames=a.colo_frames, seed=a.seed, device=a.device)) and 0)
