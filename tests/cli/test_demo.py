"""`radarpc demo` end to end, shrunk to a tiny sensor and a handful of frames."""
import json

from radarpc.cli.demo import DemoConfig, run_demo
from radarpc.data.pointstore import PointStore


def test_demo_runs_every_stage_and_reports(tmp_path, capsys):
    cfg = DemoConfig(out=tmp_path / "demo", sensor="tiny", sequences=3, frames_per_sequence=2,
                     colo_scenes="hallway", colo_runs_per_scene=3, colo_frames=1, colo_lidar_beams=8,
                     quick_tune=True)
    report = run_demo(cfg)
    text = report.read_text()
    for step in ("simulate RADIal", "spectral point clouds", "OS-CFAR baseline", "Chamfer / EMD"):
        assert step in text
    assert "| hallway |" in text                       # the per-scene CD/EMD table made it in
    out = cfg.out
    for fig in ("radial_info.png", "frame.png", "coloradar_info.png"):
        assert (out / fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    store = PointStore(out / "pointcloud_0.057.parquet")
    assert len(store) == 6 and store.metadata.enrich == ("rd3", "sector32")
    metrics = json.loads((out / "preds" / "oscfar" / "metrics.json").read_text())
    overall = metrics["overall"]
    assert overall["n_frames"] == 1 and 0 < overall["chamfer_mean"] < 20 and overall["emd_mean"] > 0
    # a second run resumes: every step finds its outputs and succeeds again
    assert run_demo(cfg) == report
    assert '"total_seconds"' in capsys.readouterr().out
