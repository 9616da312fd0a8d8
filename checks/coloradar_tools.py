"""azinke/coloradar on a simulated ColoRadar root: what loads, and whether it matches radarpc's reader.

Simulates a small root (:func:`radarpc.sim.coloradar_writer.write_coloradar`: one run, ``--frames``
frames, the full calibration) and runs, unchanged, the ``core`` package of a local clone of
azinke/coloradar given by ``--coloradar-repo``, as its README describes:

* ``Coloradar()`` (``core/dataset.py``): the tool opens ``dataset/dataset.json`` relative to the
  working directory. The script makes a scratch working directory whose ``dataset/`` holds the
  tool's own ``dataset.json`` with ``datastore.folders`` naming the simulated run, and links to the
  root's ``calib/`` and run folder. Construction reads every calibration file and transform;
* ``getRecord(codename, i).load(sensor)`` for ``scradar`` (raw ADC, cast to float16 by the tool),
  ``ccradar`` (heatmaps) and ``lidar``;
* raw ADC processing of the single chip: ``_process_raw_adc`` (the power cube behind
  ``--scradar --raw``), ``showHeatmapFromRaw`` and ``getPointcloudFromRaw`` (``--raw -pcl``),
  rendered with matplotlib's Agg backend; heatmaps: ``_heatmap_to_pointcloud`` of the cascade
  heatmap (behind ``--ccradar --heatmap``); LiDAR ``getPointCloud``.

and compares with radarpc: :func:`radarpc.data.coloradar_format.load_calib` (waveform, antenna
layout, heatmap grids, coupling size, transforms), :class:`radarpc.data.coloradar.ColoRadarRun`
(ADC frames, heatmaps, LiDAR scans, element for element) and
:func:`radarpc.dsp.tdm.tdm_spectrum` with the tool's FFT sizes and no range crop (the power cube,
element for element, relative to its largest cell). Prints one JSON object; ``--md`` also
writes the findings as Markdown.

The tool imports OpenCV (``cv2``) and matplotlib: ``pip install opencv-python-headless`` if
``cv2`` is missing (not a radarpc dependency).

Usage::

    python checks/coloradar_tools.py --coloradar-repo path/to/coloradar [--frames 2] [--md out.md]
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

from radarpc.data.coloradar import ColoRadarRun
from radarpc.data.coloradar_format import load_calib
from radarpc.dsp.tdm import tdm_spectrum
from radarpc.sensors.coloradar import quaternion_to_matrix
from radarpc.sim.coloradar_writer import run_name, write_coloradar

CODENAME = "sim0"
# Elementwise agreement of two float32 FFT chains of the same frame: four FFT stages of at most
# 128 points each add a relative rounding error of order 4 * log2(128) * 6e-8 ~ 2e-6 of the
# largest amplitude, so 1e-4 of the largest power separates rounding from a different result.
POWER_RTOL = 1e-4


def _step(out: dict, name: str, fn):
    """Run one tool step; record ``ok`` or the error (type, message, last frame) under ``name``."""
    try:
        res = fn()
        out[name] = {"ok": True, **(res or {})}
    except Exception as e:                                   # the tool's failure is the finding
        tb = traceback.extract_tb(e.__traceback__)[-1]
        out[name] = {"ok": False, "error": f"{type(e).__name__}: {e}",
                     "at": f"{Path(tb.filename).name}:{tb.lineno}"}
    return out[name]


def _max_abs(a, b) -> float:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        return float("inf")
    return float(np.abs(a - b).max()) if a.size else 0.0


def _workspace(repo: Path, root: Path, run: str, work: Path) -> None:
    """``work/dataset/``: the tool's ``dataset.json`` naming ``run``, and links to the root."""
    cfg = json.loads((repo / "dataset" / "dataset.json").read_text())
    cfg["datastore"]["folders"] = [{"codename": CODENAME, "path": run}]
    ds = work / "dataset"
    ds.mkdir(parents=True)
    (ds / "dataset.json").write_text(json.dumps(cfg, indent=2))
    (ds / "calib").symlink_to(root / "calib")
    (ds / run).symlink_to(root / run)


def run_tool(repo: Path, root: Path, frames: int) -> dict:
    """Every step of the module docstring; returns ``{step: {ok, ...}}``."""
    calib = load_calib(root / "calib")
    run = run_name("lab", 0)
    rp = ColoRadarRun(root / run, calib)
    steps: dict = {}
    with tempfile.TemporaryDirectory(prefix="coloradar_tool_") as tmp, contextlib.ExitStack() as stack:
        work = Path(tmp)
        _workspace(repo, root, run, work)
        old_cwd = os.getcwd()
        os.chdir(work)
        stack.callback(os.chdir, old_cwd)
        sys.path.insert(0, str(repo))
        stack.callback(sys.path.remove, str(repo))
        os.environ["MPLBACKEND"] = "Agg"
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.cm
        import matplotlib.pyplot as plt
        if not hasattr(matplotlib.cm, "get_cmap"):
            # removed in matplotlib 3.9 (the tool pins 3.9.1 and renders through plt.cm.get_cmap())
            matplotlib.cm.get_cmap = lambda name=None, lut=None: matplotlib.colormaps[name or plt.rcParams["image.cmap"]]
            steps["matplotlib"] = {"ok": True, "note": f"matplotlib {matplotlib.__version__} lacks cm.get_cmap "
                                   "(removed in 3.9); declared as matplotlib.colormaps[name] for the tool's rendering"}

        from core.dataset import Coloradar              # noqa: E402  (the tool, from --coloradar-repo)

        state: dict = {}

        def construct():
            ds = Coloradar()
            state["ds"] = ds
            c = ds.calibration
            sc, cc = calib.single_chip, calib.cascade
            wf = {k: getattr(c.scradar.waveform, k) == getattr(sc.waveform, k)
                  for k in ("num_tx", "num_rx", "num_adc_samples_per_chirp", "num_chirps_per_frame",
                            "adc_sample_frequency", "start_frequency", "idle_time", "adc_start_time",
                            "ramp_end_time", "frequency_slope")}
            ant = {name: (np.array_equal(cal.antenna.txl[:, 1:], np.asarray(chip.antenna.tx_positions))
                          and np.array_equal(cal.antenna.rxl[:, 1:], np.asarray(chip.antenna.rx_positions)))
                   for name, cal, chip in (("single_chip", c.scradar, sc), ("cascade", c.ccradar, cc))}
            hm = {}
            for name, cal, chip in (("single_chip", c.scradar, sc), ("cascade", c.ccradar, cc)):
                h = cal.heatmap
                hm[name] = {"bins_el_az_range": [h.num_elevation_bins, h.num_azimuth_bins, h.num_range_bins],
                            "matches": ([h.num_elevation_bins, h.num_azimuth_bins, h.num_range_bins]
                                        == [chip.heatmap.num_elevation_bins, chip.heatmap.num_azimuth_bins,
                                            chip.heatmap.num_range_bins]
                                        and h.range_bin_width == chip.heatmap.range_bin_width
                                        and _max_abs(h.azimuth_bins, chip.heatmap.azimuth_bins) == 0
                                        and _max_abs(h.elevation_bins, chip.heatmap.elevation_bins) == 0)}
            tf = {}
            for name, tool_tf, ours in (("base_to_single_chip", c.transform.to_scradar, calib.base_to_single_chip),
                                        ("base_to_cascade", c.transform.to_ccradar, calib.base_to_cascade),
                                        ("base_to_lidar", c.transform.to_lidar, calib.base_to_lidar),
                                        ("base_to_imu", c.transform.to_imu, calib.base_to_imu)):
                tf[name] = {"translation_max_abs": _max_abs(tool_tf.t, ours.translation),
                            "quaternion_max_abs": _max_abs(tool_tf.q, ours.quaternion),
                            "rotation_max_abs": _max_abs(tool_tf.r, quaternion_to_matrix(ours.quaternion))}
            return {"waveform_matches": all(wf.values()), "antenna_matches": ant, "heatmap_grid": hm,
                    "transforms": tf, "d_tool_vs_radarpc_element_spacing":
                        [float(c.scradar.d), float(sc.element_spacing)]}

        def coupling():
            ds = state["ds"]
            out = {}
            for name, cal in (("single_chip", ds.calibration.scradar), ("cascade", ds.calibration.ccradar)):
                n = len(cal.coupling.data)
                arr = cal.get_coupling_calibration()           # the tool's reshape (raw ADC processing)
                out[name] = {"values": n, "tool_shape": list(arr.shape),
                             "arpg_rule_2_tx_rx_rangebins": 2 * cal.coupling.num_tx * cal.coupling.num_rx
                             * cal.heatmap.num_range_bins}
            return out

        construct_res = _step(steps, "Coloradar()", construct)
        if construct_res["ok"]:
            _step(steps, "coupling calibration", coupling)
        frames_out = []
        for i in range(frames if construct_res["ok"] else 0):
            fr: dict = {"index": i}
            ds = state["ds"]

            def scradar():
                rec = ds.getRecord(CODENAME, i)
                rec.load("scradar")
                state["sc"] = rec.scradar
                raw = rec.scradar.raw
                ours = rp.adc(i)
                adc16 = np.fromfile(rp.adc_path(i), np.int16)
                return {"raw_shape": list(raw.shape), "max_abs_vs_radarpc": _max_abs(raw.real, ours.real)
                        + _max_abs(raw.imag, ours.imag),
                        "largest_abs_sample": int(np.abs(adc16.astype(np.int32)).max()),
                        "samples_beyond_2048": int((np.abs(adc16.astype(np.int32)) > 2048).sum())}

            def raw_processing():
                sc_tool = state["sc"]
                sc_tool.raw = sc_tool.raw.copy()                 # the tool subtracts the mean in place
                t0 = time.perf_counter()
                power = sc_tool._process_raw_adc()
                dt = time.perf_counter() - t0
                ne, na, nd, nr = power.shape
                ours = tdm_spectrum(rp.adc(i), calib.single_chip, n_range=nr, n_doppler=nd, n_azimuth=na,
                                    n_elevation=ne, crop=0.0).abs().double().numpy() ** 2
                err = _max_abs(power, ours) / float(ours.max())
                return {"power_shape_el_az_dopp_range": list(power.shape), "seconds": round(dt, 2),
                        "max_abs_diff_over_max_power": err, "matches": bool(err < POWER_RTOL)}

            def heatmap_from_raw():
                sc_tool = state["sc"]
                plt.figure(clear=True)
                sc_tool.showHeatmapFromRaw(0.15, no_sidelobe=True, show=False)
                plt.close("all")

            def pointcloud_from_raw():
                pcl = state["sc"].getPointcloudFromRaw()
                return {"points": int(len(pcl))}

            def ccradar():
                rec = ds.getRecord(CODENAME, i)
                rec.load("ccradar")
                hm = rec.ccradar.heatmap
                ours = rp.heatmap(i)
                pcl = rec.ccradar._heatmap_to_pointcloud(threshold=0.15)
                return {"heatmap_shape": list(hm.shape), "max_abs_vs_radarpc": _max_abs(hm, ours),
                        "heatmap_pointcloud_points": int(len(pcl))}

            def lidar():
                rec = ds.getRecord(CODENAME, i)
                rec.load("lidar")
                cld = rec.lidar.cld
                ours = rp.lidar(i, drop_zeros=False)
                xyz = rec.lidar.getPointCloud()
                return {"points": int(len(cld)), "max_abs_vs_radarpc": _max_abs(cld, ours),
                        "getPointCloud_shape": list(np.shape(xyz))}

            for name, fn in (("scradar raw ADC", scradar), ("scradar raw processing", raw_processing),
                             ("scradar heatmap from raw", heatmap_from_raw),
                             ("scradar pointcloud from raw", pointcloud_from_raw),
                             ("ccradar heatmap", ccradar), ("lidar", lidar)):
                if name.startswith("scradar ") and name != "scradar raw ADC" and not fr.get("scradar raw ADC", {}).get("ok"):
                    continue
                _step(fr, name, fn)
            frames_out.append(fr)
        steps["frames"] = frames_out
    return steps


def _md(res: dict) -> str:
    """The findings as Markdown (for docs/results/compatibility.md)."""
    s = res["steps"]
    lines = [
        "## ColoRadar: azinke/coloradar on a simulated root",
        "",
        f"Tool: azinke/coloradar at commit `{res['tool_commit']}`, its `core` package run unchanged from "
        f"`{res['coloradar_repo']}` (working directory with the tool's `dataset/dataset.json` naming the "
        "simulated run). Command:",
        "",
        f"    {res['command']}",
        "",
        f"Root: `write_coloradar` with one run of {res['frames']} frames, the full calibration "
        f"(`DEFAULT_CALIB`), LiDAR {res['lidar']}. Load: {res['loadavg']}.",
        "",
        "| step | loaded | matched radarpc |",
        "|---|---|---|",
    ]
    if "matplotlib" in s:
        lines[-2:-2] = [f"Rendering: {s['matplotlib']['note']}.", ""]
    c = s.get("Coloradar()", {})
    if c.get("ok"):
        tf_ok = all(v["translation_max_abs"] == 0 and v["quaternion_max_abs"] == 0 for v in c["transforms"].values())
        hm_ok = all(v["matches"] for v in c["heatmap_grid"].values())
        lines.append(f"| `Coloradar()` (all calib files, transforms incl. `base_to_imu.txt`) | yes | waveform "
                     f"{'=' if c['waveform_matches'] else '!='}, antenna layouts "
                     f"{'=' if all(c['antenna_matches'].values()) else '!='}, heatmap grids "
                     f"{'=' if hm_ok else '!='} (single chip {c['heatmap_grid']['single_chip']['bins_el_az_range']}, "
                     f"cascade {c['heatmap_grid']['cascade']['bins_el_az_range']} el/az/range), transforms "
                     f"{'=' if tf_ok else '!='} |")
    else:
        lines.append(f"| `Coloradar()` | no: {c.get('error')} | - |")
    cp = s.get("coupling calibration")
    if cp:
        if cp.get("ok"):
            lines.append("| coupling calibration (`get_coupling_calibration`) | yes | "
                         + "; ".join(f"{k}: {v['values']} values -> tool shape {tuple(v['tool_shape'])}, "
                                     f"= 2 x tx x rx x heatmap range bins ({v['arpg_rule_2_tx_rx_rangebins']})"
                                     for k, v in cp.items() if isinstance(v, dict)) + " |")
        else:
            lines.append(f"| coupling calibration | no: {cp['error']} | - |")
    for fr in s.get("frames", []):
        i = fr["index"]
        for name, r in fr.items():
            if name == "index":
                continue
            if not r.get("ok"):
                lines.append(f"| frame {i}: {name} | no: {r['error']} ({r['at']}) | - |")
                continue
            if name == "scradar raw ADC":
                m = (f"ADC {'identical' if r['max_abs_vs_radarpc'] == 0 else 'max diff %g' % r['max_abs_vs_radarpc']}"
                     f" after the tool's float16 cast (largest I/Q magnitude {r['largest_abs_sample']} LSB, "
                     f"{r['samples_beyond_2048']} beyond 2048)")
            elif name == "scradar raw processing":
                m = (f"power cube {tuple(r['power_shape_el_az_dopp_range'])} vs `tdm_spectrum`: max diff "
                     f"{r['max_abs_diff_over_max_power']:.1e} of the largest cell "
                     f"({'match' if r['matches'] else 'differs'}, bound {POWER_RTOL:g})")
            elif name == "ccradar heatmap":
                m = (f"heatmap {'identical' if r['max_abs_vs_radarpc'] == 0 else 'max diff %g' % r['max_abs_vs_radarpc']}; "
                     f"tool's heatmap point cloud {r['heatmap_pointcloud_points']} points")
            elif name == "lidar":
                m = (f"scan {'identical' if r['max_abs_vs_radarpc'] == 0 else 'max diff %g' % r['max_abs_vs_radarpc']} "
                     f"({r['points']} points)")
            elif name == "scradar pointcloud from raw":
                m = f"runs ({r['points']} points; no radarpc counterpart)"
            else:
                m = "renders (no radarpc counterpart)"
            lines.append(f"| frame {i}: {name} | yes | {m} |")
    lines += ["", "Before this change the tool failed at `Coloradar()` (`calib/transforms/base_to_imu.txt` "
              "missing) and, past it, at the single-chip coupling reshape (3,072 values for 1,536).", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--coloradar-repo", required=True, type=Path, help="local clone of azinke/coloradar")
    ap.add_argument("--frames", type=int, default=2, help="radar frames to simulate and read (default 2)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None, help="where to simulate the root (default: a temp folder)")
    ap.add_argument("--md", type=Path, default=None, help="also write the findings as Markdown here")
    args = ap.parse_args(argv)
    repo = args.coloradar_repo.resolve()
    if not (repo / "core" / "dataset.py").is_file() or not (repo / "dataset" / "dataset.json").is_file():
        ap.error(f"--coloradar-repo {repo}: expected azinke/coloradar's core/dataset.py and dataset/dataset.json")
    if args.frames < 1:
        ap.error(f"--frames must be >= 1, got {args.frames}")
    commit = subprocess.run(["git", "-C", str(repo), "log", "-1", "--format=%H"], capture_output=True,
                            text=True).stdout.strip() or "unknown"
    lidar = dict(lidar_beams=16, lidar_azimuth_steps=256)
    with tempfile.TemporaryDirectory(prefix="coloradar_sim_") as tmp:
        root = (args.out or Path(tmp) / "root").resolve()
        t0 = time.perf_counter()
        write_coloradar(root, ["lab"], 1, args.frames, args.seed, progress=False, **lidar)
        sim_s = time.perf_counter() - t0
        steps = run_tool(repo, root, args.frames)
    with open("/proc/loadavg") as f:
        load = " ".join(f.read().split()[:3])
    res = {"coloradar_repo": str(repo), "tool_commit": commit, "frames": args.frames,
           "lidar": f"{lidar['lidar_beams']} beams x {lidar['lidar_azimuth_steps']} steps",
           "command": "python checks/coloradar_tools.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "simulate_s": round(sim_s, 1), "loadavg": load, "steps": steps}
    print(json.dumps(res, indent=1, default=float))
    if args.md:
        args.md.write_text(_md(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
