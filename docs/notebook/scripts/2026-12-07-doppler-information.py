"""How much each point axis tells vehicle points from the rest, on a simulated `radial` point store.

Why the axis ablation's + d arm adds little (docs/results/study.md): a model-free check of what a
point's axes carry. A point is a "vehicle point" if it lies within RADIUS_M (ground plane) of a
labelled vehicle's reference point (labels.csv, radar_X/Y_m). For each set of axes, a histogram
classifier (P(vehicle | bin) on the training sequences' points, quantile bins per axis) scores the
test sequences' points; AUROC says how well those axes alone separate vehicle points (0.5: not at
all). The axes: r, a, e as the models see them; d the consolidated Doppler index (the + d arm's
feature); v the resolved radial velocity; v_c that velocity with the ego's motion removed
(v + v_ego cos a cos e folded back into the radar's +-v_max, the simulator's ego speed from
sim_frames.csv; 0 on static surfaces, whose radial velocity is -v_ego cos a cos e); log Ae.
Integer axes (d) are binned by value, real ones by quantiles. Caveat: a point is labelled by its
distance to the labelled face centre, so the far parts of long or side-on vehicles, and vehicles
outside the labelled field of view, count as "rest".

    python this.py STORE.parquet ROOT [--bins 12] [--radius 3.0]       # prints JSON
"""
import argparse
import json

import numpy as np
import pyarrow.parquet as pq
from scipy.stats import rankdata

from radarpc.data.radial import read_labels, root_sensor, split_of_sequence
from radarpc.data.radial_truth import read_sim_frames
from radarpc.models.classical import wrap_velocity


def auroc(score, y):
    """Area under the ROC curve, ties counted half (Mann-Whitney U / (n_pos n_neg))."""
    r = rankdata(score)                                            # ties get their mean rank
    n1 = int(y.sum())
    n0 = len(y) - n1
    if n1 == 0 or n0 == 0:
        raise ValueError(f"AUROC needs both classes; got {n1} positive and {n0} negative points")
    return float((r[y].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def histogram_score(train_cols, y_train, test_cols, bins):
    """P(vehicle | bin) from the training points (add-one smoothed), looked up for the test points."""
    key_tr = np.zeros(len(y_train), dtype=np.int64)
    key_te = np.zeros(len(test_cols[0]), dtype=np.int64)
    for xt, xe in zip(train_cols, test_cols):
        if np.issubdtype(xt.dtype, np.integer):                        # one bin a value
            edges = np.unique(xt)[1:] - 0.5
        else:
            edges = np.unique(np.quantile(xt, np.linspace(0, 1, bins + 1)[1:-1]))
        key_tr = key_tr * (bins + 1) + np.searchsorted(edges, xt)
        key_te = key_te * (bins + 1) + np.searchsorted(edges, xe)
    keys, inv = np.unique(key_tr, return_inverse=True)
    pos = np.bincount(inv, weights=y_train.astype(float), minlength=len(keys))
    tot = np.bincount(inv, minlength=len(keys))
    p = (pos + y_train.mean()) / (tot + 1.0)
    idx = np.searchsorted(keys, key_te)
    idx = np.clip(idx, 0, len(keys) - 1)
    seen = keys[idx] == key_te
    return np.where(seen, p[idx], y_train.mean())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("store")
    ap.add_argument("root")
    ap.add_argument("--bins", type=int, default=12)
    ap.add_argument("--radius", type=float, default=3.0)
    args = ap.parse_args()

    t = pq.read_table(args.store, columns=["frame", "sequence", "range_m", "azimuth_deg", "elevation_deg",
                                           "doppler_bin", "velocity_mps", "amplitude", "x", "y"])
    col = {n: t.column(n).to_numpy() if n != "sequence" else np.asarray(t.column(n).to_pylist())
           for n in t.column_names}
    frame = col["frame"]

    sim = read_sim_frames(f"{args.root}/sim_frames.csv")
    ego = dict(zip(sim.num_sample.tolist(), sim.ego_speed_mps.tolist()))
    missing = sorted(set(np.unique(frame).tolist()) - set(ego))
    if missing:
        raise ValueError(f"{args.root}/sim_frames.csv has no ego speed for frames {missing[:5]}")
    v_ego = np.array([ego[int(i)] for i in frame])

    labels = read_labels(f"{args.root}/labels.csv")
    veh = {}
    has = labels.has_vehicle
    for i, x, y in zip(labels.num_sample[has], labels.column("radar_X_m")[has], labels.column("radar_Y_m")[has]):
        veh.setdefault(int(i), []).append((x, y))
    is_vehicle = np.zeros(len(frame), dtype=bool)
    order = np.argsort(frame, kind="stable")
    uniq, starts = np.unique(frame[order], return_index=True)
    for i, lo, hi in zip(uniq, starts, np.r_[starts[1:], len(frame)]):
        if int(i) not in veh:
            continue
        sel = order[lo:hi]
        c = np.asarray(veh[int(i)])
        d2 = (col["x"][sel, None] - c[None, :, 0]) ** 2 + (col["y"][sel, None] - c[None, :, 1]) ** 2
        is_vehicle[sel] = d2.min(axis=1) < args.radius ** 2

    a = np.deg2rad(col["azimuth_deg"])
    e = np.deg2rad(col["elevation_deg"])
    v_max = root_sensor(args.root)[0].max_velocity_mps
    v_c = wrap_velocity(col["velocity_mps"] + v_ego * np.cos(a) * np.cos(e), v_max)
    axes = {"r": col["range_m"], "a": col["azimuth_deg"], "e": col["elevation_deg"],
            "d": col["doppler_bin"].astype(np.int64), "v": col["velocity_mps"], "v_c": v_c,
            "Ae": np.log1p(col["amplitude"])}

    names = sorted(set(col["sequence"]))
    split_of = {s: split_of_sequence(s, names) for s in names}
    split = np.array([split_of[s] for s in col["sequence"]])
    tr, te = split == "train", split == "test"
    sets = [("r",), ("a",), ("e",), ("d",), ("v",), ("v_c",), ("Ae",), ("r", "a"), ("r", "a", "e"),
            ("r", "a", "d"), ("r", "a", "v"), ("r", "a", "v_c"), ("r", "a", "Ae"),
            ("r", "a", "e", "d"), ("r", "a", "e", "v"), ("r", "a", "e", "v_c"), ("r", "a", "e", "Ae")]
    out = {"store": args.store, "points": int(len(frame)), "vehicle_fraction": float(is_vehicle.mean()),
           "radius_m": args.radius, "bins": args.bins, "v_max": v_max,
           "static_points_abs_v_c_median": float(np.median(np.abs(axes["v_c"][~is_vehicle]))),
           "vehicle_points_abs_v_c_median": float(np.median(np.abs(axes["v_c"][is_vehicle]))),
           "train_points": int(tr.sum()), "test_points": int(te.sum()), "auroc": {}}
    for s in sets:
        score = histogram_score([axes[n][tr] for n in s], is_vehicle[tr], [axes[n][te] for n in s], args.bins)
        out["auroc"]["+".join(s)] = round(auroc(score, is_vehicle[te]), 4)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
