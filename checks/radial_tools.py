"""RADIal's own tools on simulated roots: what loads, and whether it matches radarpc's reader.

Simulates small roots (``radial`` and ``radial-s``; ``.npy`` cubes for FFTRadNet's loader,
``.npz`` cubes for the generic loader), writes ``radar_PCL/`` from a point store of each root
(:func:`radarpc.pipelines.radial_pcl.write_radial_pcl`), then runs, unchanged, from a local clone
of valeoai/RADIal given by ``--radial-repo``:

* ``FFTRadNet/dataset/dataset.py`` ``RADIal`` with its encoder (``dataset/encoder.py``) and the
  collate of ``dataset/dataloader.py`` over a ``DataLoader``; on ``radial`` also the official
  ``FFTRadNet`` forward pass and ``pixor_loss`` + BCE freespace loss on one batch;
* ``loader/dataset.py`` ``RADIal`` with the collate of ``loader/loader.py``.

and compares every item with radarpc: :class:`radarpc.data.radial.RADIal` (radar input, labels,
freespace), :func:`radarpc.models.targets.encode_targets` (encoded maps), the point store (radar
points), :func:`radarpc.sim.radial_lidar.laser_scan` and :func:`radarpc.sim.radial_camera.render_camera`
of the same scene frame (laser points, camera image). Prints one JSON object.

The tools' dependencies (pandas, torchvision) must be installed. The PyPI torchvision wheel is a
CUDA build whose C operators do not load on a CPU-only torch, and its import then fails on
registering ``torchvision::nms``; in that case this script declares the two operator schemas that
torchvision's import needs (the tools only use its PIL transforms), and says so in the output.

Usage::

    python checks/radial_tools.py --radial-repo path/to/RADIal [--frames 2] [--sensors radial radial-s] [--no-forward]
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from radarpc.data.radial import RADIal as RadarpcRADIal
from radarpc.pipelines.pointclouds import convert_dataset
from radarpc.pipelines.radial_pcl import write_radial_pcl
from radarpc.sensors.radial import radial_sensor
from radarpc.sim.radial_camera import IMAGE_SIZE, render_camera
from radarpc.sim.radial_lidar import laser_scan
from radarpc.sim.radial_writer import RadialSimulator, write_radial_dataset


def _import_torchvision() -> str:
    """Import torchvision; on a CUDA wheel over a CPU torch, declare the ops its import registers."""
    try:
        import torchvision  # noqa: F401
        return "imported"
    except RuntimeError as e:
        if "torchvision::nms" not in str(e):
            raise
    for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
        del sys.modules[name]
    lib = torch.library.Library("torchvision", "DEF")
    lib.define("nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
    lib.define("qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
    _import_torchvision.lib = lib                      # keep the definitions alive
    import torchvision  # noqa: F401,F811
    return "imported after declaring torchvision::nms/qnms (CUDA wheel on a CPU torch)"


def _load(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _max_abs(a, b) -> float:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        return float("inf")
    return float(np.abs(a - b).max()) if a.size else 0.0


def _labels_diff(official: np.ndarray, ours: np.ndarray) -> float:
    # a frame without vehicles: the tools return the -1 row of labels.csv, radarpc no row
    if ours.shape[0] == 0:
        return 0.0 if official.shape[0] == 1 and bool((np.asarray(official) == -1).all()) else float("inf")
    return _max_abs(official, ours)


def _simulate(out: Path, sensor: str, frames: int, cube_format: str) -> Path:
    cfg = radial_sensor(sensor)
    # 3 sequences of `frames` frames: enough for Difficult == 0 vehicles in most frames
    return write_radial_dataset(out, cfg, 3, frames, seed=0, progress=False, cube_format=cube_format)


def _store(root: Path) -> Path:
    out = root.parent / f"{root.name}.parquet"
    convert_dataset(root, out, density=0.05, split="all", progress=False)
    write_radial_pcl(out, root, progress=False)
    return out


def check_fftradnet(repo: Path, root: Path, sensor: str, forward: bool) -> dict:
    """FFTRadNet's dataset + encoder + collate (+ forward and loss) against radarpc's reader."""
    ffr = repo / "FFTRadNet"
    sys.path.insert(0, str(ffr))
    try:
        ds_mod = _load(ffr / "dataset" / "dataset.py", "fftradnet_dataset")
        dl_mod = _load(ffr / "dataset" / "dataloader.py", "fftradnet_dataloader")
        enc_mod = _load(ffr / "dataset" / "encoder.py", "fftradnet_encoder")
        config = json.loads((ffr / "config" / "config_FFTRadNet_192_56.json").read_text())
        enc = enc_mod.ra_encoder(geometry=config["dataset"]["geometry"],
                                 statistics=config["dataset"]["statistics"], regression_layer=2)
        official = ds_mod.RADIal(root_dir=str(root), statistics=None, encoder=enc.encode, difficult=True)
        ours = RadarpcRADIal(root, split="all", difficult=True)
        res = {"items": len(official), "radarpc_items": len(ours)}
        from radarpc.models.targets import encode_targets
        worst = {"radar_input": 0.0, "labels": 0.0, "freespace_mismatch": 0, "encoded_map": 0.0}
        img_shapes = set()
        for k in range(len(official)):
            fft, seg, enc_map, box, image = official[k]
            num = int(official.sample_keys[k])
            i = ours.index_of(num)
            rd, lab, fs = ours[i]
            rd = rd.numpy()
            worst["radar_input"] = max(worst["radar_input"], _max_abs(fft, np.concatenate([rd.real, rd.imag], 2)))
            # official columns: R, A, D, laser XYZ, pixels; radarpc's tensor: R, A, D, X, Y, P, laser, pixels
            ours_box = lab.numpy()[:, [0, 1, 2, 6, 7, 8, 9, 10, 11, 12]]
            worst["labels"] = max(worst["labels"], _labels_diff(box, ours_box))
            worst["freespace_mismatch"] += int((np.asarray(seg) != fs.numpy()).sum())
            if sensor == "radial":
                worst["encoded_map"] = max(worst["encoded_map"], _max_abs(enc_map, encode_targets(lab).numpy()))
            img_shapes.add(tuple(image.shape))
        res.update({f"max_abs_diff_{k}" if k != "freespace_mismatch" else "freespace_pixels_differing": v
                    for k, v in worst.items() if not (k == "encoded_map" and sensor != "radial")})
        res["image_shapes"] = sorted(img_shapes)
        loader = torch.utils.data.DataLoader(official, batch_size=2, shuffle=False, num_workers=0,
                                             collate_fn=dl_mod.RADIal_collate)
        batch = next(iter(loader))
        res["collate_shapes"] = [list(t.shape) for t in batch if isinstance(t, torch.Tensor)]
        if forward and sensor == "radial":
            model_mod = _load(ffr / "model" / "FFTRadNet.py", "fftradnet_model")
            loss_mod = _load(ffr / "loss" / "loss.py", "fftradnet_loss")
            m = config["model"]
            net = model_mod.FFTRadNet(blocks=m["backbone_block"], mimo_layer=m["MIMO_output"],
                                      channels=m["channels"], regression_layer=2, detection_head=True,
                                      segmentation_head=True)
            torch.manual_seed(0)
            t0 = time.perf_counter()
            with torch.no_grad():
                out = net(batch[0].float())
            cls, reg = loss_mod.pixor_loss(out["Detection"], batch[1].float(), config["losses"])
            seg_loss = torch.nn.BCEWithLogitsLoss(reduction="mean")(
                out["Segmentation"].contiguous().flatten(), batch[2].double().contiguous().flatten())
            res["forward"] = {"detection": list(out["Detection"].shape), "segmentation": list(out["Segmentation"].shape),
                              "classif_loss": float(cls), "reg_loss": float(reg), "freespace_loss": float(seg_loss),
                              "finite": bool(all(np.isfinite([float(cls), float(reg), float(seg_loss)]))),
                              "seconds": round(time.perf_counter() - t0, 2)}
        return res
    finally:
        sys.path.remove(str(ffr))


def check_loader(repo: Path, root: Path, store: Path, sensor: str) -> dict:
    """RADIal's generic loader (loader/dataset.py + loader.py collate) against radarpc."""
    from radarpc.data.pointstore import PointStore

    ds_mod = _load(repo / "loader" / "dataset.py", "radial_loader_dataset")
    ld_mod = _load(repo / "loader" / "loader.py", "radial_loader_loader")
    official = ds_mod.RADIal(root_dir=str(root), difficult=True)
    ours = RadarpcRADIal(root, split="all", difficult=True)
    meta = json.loads((root / "sensor.json").read_text())
    sim = RadialSimulator(radial_sensor(sensor), meta["n_sequences"], meta["frames_per_sequence"], meta["seed"])
    st = PointStore(store)
    pos = {int(f): i for i, f in enumerate(st.frames)}
    res = {"items": len(official)}
    worst = {"radar_input": 0.0, "labels": 0.0, "radar_points": 0.0, "laser_points": 0.0,
             "camera_mean_abs_vs_render": 0.0}
    fs_diff, n_radar, n_laser, label_to_laser = 0, 0, 0, []
    for k in range(len(official)):
        image, fft, radar_pc, laser_pc, segmap, box = official[k]
        num = int(official.sample_keys[k])
        i = ours.index_of(num)
        rd, lab, fs = ours[i]
        rd = rd.numpy()
        worst["radar_input"] = max(worst["radar_input"], _max_abs(fft, np.concatenate([rd.real, rd.imag], 2)))
        # official box: x1 y1 x2 y2, laser XYZ, radar X Y R A D P (radarpc's tensor order differs)
        l = lab.numpy()
        ours_box = l[:, [9, 10, 11, 12, 6, 7, 8, 3, 4, 0, 1, 2, 5]]
        worst["labels"] = max(worst["labels"], _labels_diff(box, ours_box))
        fs_diff += int(((np.asarray(segmap) == 255) != fs.numpy()).sum())
        t = st.frame_rows(pos[num])
        xyz = np.stack([t.column(c).to_numpy() for c in ("x", "y", "z")], 1)
        worst["radar_points"] = max(worst["radar_points"], _max_abs(radar_pc, xyz))
        n_radar += len(xyz)
        q, f = sim.locate(num)
        fr = sim.scene_frame(q, f)
        las = laser_scan(fr)[:, :3]
        worst["laser_points"] = max(worst["laser_points"], _max_abs(laser_pc, las))
        n_laser += len(las)
        ref = render_camera(fr, lane_width_m=sim.preset(q).lane_width_m).astype(np.float64)
        worst["camera_mean_abs_vs_render"] = max(worst["camera_mean_abs_vs_render"],
                                                 float(np.abs(np.asarray(image, np.float64) - ref).mean()))
        # each labelled vehicle's laser reference point against its nearest laser point
        for row in box:
            if row[4] != -1 and len(laser_pc):
                label_to_laser.append(float(np.linalg.norm(laser_pc - row[4:7], axis=1).min()))
    res.update({f"max_abs_diff_{k}" if not k.startswith("camera") else k: v for k, v in worst.items()})
    res.update(freespace_pixels_differing=fs_diff, radar_points=n_radar, laser_points=n_laser,
               image_shape=list(np.asarray(image).shape),
               label_to_nearest_laser_point_m_median=float(np.median(label_to_laser)) if label_to_laser else None)
    loader = torch.utils.data.DataLoader(official, batch_size=2, shuffle=False, num_workers=0,
                                         collate_fn=ld_mod.RADIal_collate)
    b = next(iter(loader))
    res["collate"] = {"images": list(b[0].shape), "ffts": list(b[1].shape), "segmaps": list(b[2].shape),
                      "laser_clouds": [list(x.shape) for x in b[3]], "radar_clouds": [list(x.shape) for x in b[4]]}
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--radial-repo", type=Path, required=True, help="local clone of valeoai/RADIal")
    ap.add_argument("--frames", type=int, default=2, help="frames per sequence (3 sequences)")
    ap.add_argument("--sensors", nargs="+", default=["radial", "radial-s"])
    ap.add_argument("--no-forward", action="store_true", help="skip the official forward pass + loss")
    ap.add_argument("--work", type=Path, default=None, help="folder for the roots (default: a temp dir)")
    args = ap.parse_args()
    repo = args.radial_repo
    if not (repo / "FFTRadNet" / "dataset" / "dataset.py").is_file() or not (repo / "loader" / "dataset.py").is_file():
        ap.error(f"--radial-repo {repo}: expected a clone of valeoai/RADIal (FFTRadNet/dataset/dataset.py, "
                 f"loader/dataset.py)")
    report = {"radial_repo": str(repo), "torchvision": _import_torchvision()}
    try:
        report["radial_commit"] = subprocess.run(["git", "-C", str(repo), "log", "-1", "--format=%H"],
                                                 capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        report["radial_commit"] = None
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        for sensor in args.sensors:
            t0 = time.perf_counter()
            npy_root = _simulate(work / f"{sensor}_npy", sensor, args.frames, "npy")
            npz_root = _simulate(work / f"{sensor}_npz", sensor, args.frames, "npz")
            store = _store(npz_root)
            report[sensor] = {
                "simulate_seconds": round(time.perf_counter() - t0, 1),
                "fftradnet_dataset": check_fftradnet(repo, npy_root, sensor, not args.no_forward),
                "loader_dataset": check_loader(repo, npz_root, store, sensor),
                "camera_image_size": list(IMAGE_SIZE),
            }
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
