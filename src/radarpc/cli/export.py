"""radarpc export: one point-cloud file per frame (npy, bin or ply) for OpenPCDet, KITTI-style tools, viewers.

  radarpc export STORE.parquet --out OUT [--format npy|bin|ply] [--columns x,y,z,...]
  radarpc export PRED_DIR --out OUT            (a ColoRadar prediction folder, as PLY)
  radarpc export STORE.parquet --radial-pcl [--root ROOT]   (RADIal's radar_PCL/ inside the root)
  radarpc export RUN/eval_test_detections.csv --out dets.npz|dets.jsonl   (an evaluation's detections)

A point store is written in OpenPCDet's custom-dataset layout:

  OUT/points/{frame:06d}.npy|.bin|.ply   one file per RADIal frame (numSample), float32
  OUT/ImageSets/{split}.txt              the sample ids, one a line
  OUT/columns.txt                        the column order, units and how to read a file
  OUT/export.json                        the settings, the store's metadata, an OpenPCDet
                                         POINT_FEATURE_ENCODING for these columns

Every file holds an (N, C) float32 little-endian table, one row per point. Default column order:

  x y z amplitude velocity_mps snr range_m azimuth_deg elevation_deg

(metres, x forward / y left / z up; amplitude is the linear beamformed amplitude, OpenPCDet's
intensity slot, not normalised; velocity in m/s; snr linear; angles in degrees, left/up positive).
npy is np.load-able; bin is the raw buffer like KITTI velodyne files, read it with
np.fromfile(path, dtype="<f4").reshape(-1, C); ply is binary little-endian PLY with one float
property per column. A frame without points gives a valid empty file.

A prediction folder ({run}/{frame:06d}.npy, from radarpc baseline) becomes OUT/{run}/{frame:06d}.ply
with float properties x, y, z.

An evaluation's detections file (radarpc evaluate writes RUN/eval_{split}..._detections.csv, one
row per detection, and lists the frames scored in the .json of the same stem) becomes, by --out's
suffix: .npz, offset-batched arrays root (F,), numSample (F,), offset (F,) cumulative counts and
detections (D, 3) range_m, azimuth_deg, score -- per frame the (N, 3) array RADIal's GetFullMetrics
takes as a frame's predictions (np.split(detections, offset[:-1])); or .jsonl, one object per frame
(frames without detections included) with each detection's score, range, azimuth, x, y and the
corners of RADIal's evaluation box in metres.

--radial-pcl writes the store's points in RADIal's own radar point-cloud layout into the RADIal
root the store was made from (or --root): ROOT/radar_PCL/pcl_{frame:06d}.npy, float32 (9, N), rows
range, azimuth, elevation, power, doppler, x, y, z, v as RADIal's loader reads them
(radarpc.pipelines.radial_pcl), so that RADIal's own loader finds the modality in a simulated root.

Every file is written atomically; a rerun with the same settings keeps the finished frames and
writes the rest; a folder holding anything else is refused unless --overwrite (which removes only
the export's own entries); a second job writing the same folder is refused.
"""
from __future__ import annotations

import argparse

__all__ = ["add_parser", "run_export"]


def run_export(args: argparse.Namespace) -> int:
    from radarpc.cli.text import plural

    if args.radial_pcl:
        from radarpc.pipelines.radial_pcl import write_radial_pcl

        if args.out is not None or args.format is not None or args.columns is not None:
            raise ValueError("--radial-pcl writes radar_PCL/ into the RADIal root (--root); it takes no "
                             "--out, --format or --columns")
        res = write_radial_pcl(args.source, args.root, progress=not args.no_progress)
        print(f"wrote radar_PCL for {plural(res.n_frames, 'frame')} ({plural(res.n_points, 'point')}) into "
              f"{res.root}")
        return 0
    if args.out is None:
        raise ValueError("--out is required (or --radial-pcl to write RADIal's radar_PCL/ into the root)")
    if args.source.endswith("_detections.csv"):
        from radarpc.pipelines.export import export_detections

        if args.columns is not None or args.root is not None:
            raise ValueError("an evaluation's detections file takes no --columns or --root")
        res = export_detections(args.source, args.out, args.format, overwrite=args.overwrite)
        print(f"wrote {plural(res.n_detections, 'detection')} of {plural(res.n_frames, 'frame')} to {res.out} "
              f"({res.fmt})")
        return 0
    if args.root is not None:
        raise ValueError("--root goes with --radial-pcl only")
    from radarpc.pipelines.export import export

    columns = None if args.columns is None else [c for c in args.columns.split(",") if c.strip()]
    res = export(args.source, args.out, args.format, columns, overwrite=args.overwrite,
                 progress=not args.no_progress)
    reused = f", kept {res.n_reused} from an earlier run" if res.n_reused else ""
    empty = f", {res.n_empty} without points" if res.n_empty else ""
    print(f"wrote {plural(res.n_new, f'{res.fmt} file')} ({plural(res.n_frames, 'frame')}{empty}{reused}) "
          f"to {res.out}")
    print(f"columns (float32, in order): {' '.join(res.columns)}  (see {res.out / 'columns.txt'})")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("export", help="per-frame point clouds (npy, bin, ply) from a point store or predictions; detections as npz/jsonl",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", help="a point store (.parquet, from radarpc pointcloud), a ColoRadar "
                                  "prediction folder (from radarpc baseline) or an evaluation's "
                                  "eval_{split}..._detections.csv (from radarpc evaluate)")
    p.add_argument("--out", default=None, help="export folder (required unless --radial-pcl)")
    p.add_argument("--format", default=None, choices=("npy", "bin", "ply", "npz", "jsonl"),
                   help="file format per frame (default: npy for a store, ply for a prediction folder, "
                        "its only format); a detections file goes to npz or jsonl, named by --out's suffix")
    p.add_argument("--columns", default=None, metavar="NAME,NAME,...",
                   help="column order for a store, starting with x,y,z (default: x,y,z,amplitude,velocity_mps,"
                        "snr,range_m,azimuth_deg,elevation_deg; also range_bin, doppler_bin, doppler_full, "
                        "is_neighbour)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an export with other settings in --out (removes only the export's own files)")
    p.add_argument("--radial-pcl", action="store_true",
                   help="write RADIal's radar_PCL/ (pcl_{frame:06d}.npy, 9 x N) into the store's RADIal root")
    p.add_argument("--root", default=None, help="with --radial-pcl: the RADIal root (default: the store's source)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run_export)
