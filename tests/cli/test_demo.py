"""`radarpc demo` end to end, shrunk to a tiny sensor and a handful of frames."""
import csv
import json
import re
from collections import Counter
from types import SimpleNamespace

import torch

from radarpc.cli.demo import DemoConfig, _most_labelled, run_demo
from radarpc.data.pointstore import PointStore


def _vehicles_per_frame(labels_csv) -> tuple[dict[int, int], dict[int, str]]:
    """``{numSample: labelled vehicles}`` and ``{numSample: sequence}`` read from ``labels.csv``
    with the csv module (a frame without vehicles has one row of -1)."""
    counts, seq = Counter(), {}
    with open(labels_csv, newline="") as f:
        for row in csv.DictReader(f):
            n = int(row["numSample"])
            seq[n] = row["dataset"]
            counts[n] += float(row["radar_R_m"]) != -1.0
    return {n: counts[n] for n in seq}, seq


def test_demo_runs_every_stage_and_reports(tmp_path, capsys):
    # seed 70: the test sequence's only labelled vehicle is in its last frame (its first has none)
    cfg = DemoConfig(out=tmp_path / "demo", sensor="tiny", sequences=3, frames_per_sequence=3, seed=70,
                     colo_scenes="hallway", colo_runs_per_scene=3, colo_frames=1, colo_lidar_beams=8,
                     quick_tune=True)
    report = run_demo(cfg)
    text = report.read_text()
    for step in ("simulate RADIal", "spectral point clouds", "OS-CFAR baseline", "Chamfer / EMD"):
        assert step in text
    assert "| hallway |" in text                       # the per-scene CD/EMD table made it in
    out = cfg.out
    # the frame figure draws the test frame (the last of the 3 sequences) with the most labelled
    # vehicles, the first such on a tie, and the report names it
    counts, seq = _vehicles_per_frame(out / "sim_radial" / "labels.csv")
    test = sorted(n for n in counts if seq[n] == max(seq.values()))
    want = max(test, key=lambda n: (counts[n], -n))
    assert counts[want] > 0 and want != test[0]
    assert f"`frame.png` draws frame {want} (numSample), the test frame with the most labelled vehicles " \
           f"({counts[want]})" in text
    assert re.search(rf"`radarpc show \S+ --frame {want} ", text)
    for fig in ("radial_info.png", "frame.png", "coloradar_info.png"):
        assert (out / fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    store = PointStore(out / "pointcloud_0.057.parquet")
    assert len(store) == 9 and store.metadata.enrich == ("rd3", "sector32")
    metrics = json.loads((out / "preds" / "oscfar" / "metrics.json").read_text())
    overall = metrics["overall"]
    assert overall["n_frames"] == 1 and 0 < overall["chamfer_mean"] < 20 and overall["emd_mean"] > 0
    # a second run resumes: every step finds its outputs and succeeds again
    assert run_demo(cfg) == report
    assert '"total_seconds"' in capsys.readouterr().out


def test_most_labelled_frame_is_the_first_of_the_largest_count():
    ds = SimpleNamespace(frame_ids=[4, 7, 9, 12], label_tensor=lambda i: torch.zeros((0, 2, 2, 1)[i], 14))
    assert _most_labelled(ds) == (7, 2)                  # a tie: the first in numSample order
    ds.frame_ids, ds.label_tensor = [3, 5], (lambda i: torch.zeros(0, 14))
    assert _most_labelled(ds) == (3, 0)
