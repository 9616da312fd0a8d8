"""`radarpc demo --tiny` end to end, as a user runs it: every step, a report that names every
figure (each a readable PNG), the frame its figures draw, and reruns that reuse finished steps."""
import contextlib
import csv
import io
import json
import math
import re
import shutil
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from radarpc.cli import main
from radarpc.cli.demo import STEPS_DIR, DemoConfig, _most_labelled, fftradnet_spec
from radarpc.data.pointstore import PointStore
from radarpc.models import build_model

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
DATA_ROOTS = ("sim_radial", "sim_colo")          # dataset roots: their PNGs are data (freespace), not figures
STEP_NAMES = ("simulate RADIal", "check RADIal", "point clouds at 2 %", "point clouds at 5.7 %",
              "point clouds at 20 %", "frame figure", "train SpectralPillars", "train FFTRadNet",
              "evaluate SpectralPillars at 2 %", "evaluate SpectralPillars at 5.7 %",
              "evaluate SpectralPillars at 20 %", "evaluate FFTRadNet", "classical detector at 2 %",
              "classical detector at 5.7 %", "classical detector at 20 %", "simulate ColoRadar", "check ColoRadar",
              "OS-CFAR baseline", "Chamfer / EMD")


def _demo(out: Path, *flags: str) -> str:
    """Stdout of ``radarpc demo --tiny --out OUT FLAGS`` (exit code 0 checked)."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["demo", "--tiny", "--out", str(out), *flags])
    assert code == 0, buf.getvalue()[-3000:]
    return buf.getvalue()


def _mtimes(out: Path) -> dict[str, int]:
    return {str(p.relative_to(out)): p.stat().st_mtime_ns for p in sorted(out.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The tiny demo run once; run again after losing the record of its 15th step (as if killed
    before it could write it); then run a third time, with progress bars (which write nothing)."""
    out = tmp_path_factory.mktemp("demo") / "demo"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)            # tiny models on 2 shared cores: a second thread only contends
    try:
        stdout = _demo(out, "--no-progress")
        report = (out / "REPORT.md").read_text()
        (out / STEPS_DIR / "classical-200.json").unlink()
        stdout_resumed = _demo(out, "--no-progress")
        report_resumed = (out / "REPORT.md").read_text()
        before = _mtimes(out)
        stdout_rerun = _demo(out)
    finally:
        torch.set_num_threads(threads)
    return SimpleNamespace(out=out, stdout=stdout, report=report, stdout_resumed=stdout_resumed,
                           report_resumed=report_resumed, before=before, stdout_rerun=stdout_rerun)


def test_tiny_demo_runs_every_step(demo):
    # its duration is the suite's to measure (README: the test time), never asserted
    import shlex

    records = [json.loads(p.read_text()) for p in sorted((demo.out / STEPS_DIR).glob("*.json"))]
    assert len(records) == len(STEP_NAMES) and all(r["seconds"] > 0 for r in records)
    commands = {shlex.join(r["argv"]) for r in records}
    for k, name in enumerate(STEP_NAMES, 1):
        m = re.search(rf"^\[{k}/{len(STEP_NAMES)}\] {re.escape(name)}\n\$ radarpc (.*)$", demo.stdout, re.M)
        assert m and m.group(1) in commands, name             # printed before it ran, recorded after
        assert f"| {k} | {name} |" in demo.report and f"   `radarpc {m.group(1)}`" in demo.report
    assert "0 of 19 steps reused, 19 run" in demo.stdout
    assert "**`--tiny`**" in demo.report                  # says its numbers mean nothing
    assert "| hallway | 1 |" in demo.report               # the per-scene CD/EMD table made it in


def test_report_names_every_figure_and_each_is_a_readable_png(demo):
    from matplotlib.image import imread

    section = demo.report[demo.report.index("## Every figure"):]
    named = set(re.findall(r"^- `([^`]+\.png)`: ", section, re.M))
    drawn = {p.relative_to(demo.out).as_posix() for p in demo.out.rglob("*.png")
             if p.relative_to(demo.out).parts[0] not in DATA_ROOTS}
    assert named == drawn and len(drawn) == 19
    linked = set(re.findall(r"!\[[^]]*\]\(([^)]+)\)", demo.report))
    assert linked <= named and {"frame.png", "f1_density.png", "preds/oscfar/figures/hallway.png"} <= linked
    for name in named:
        path = demo.out / name
        assert path.read_bytes()[:8] == PNG_SIGNATURE, name
        image = imread(path)
        assert image.ndim == 3 and image.shape[2] in (3, 4) and min(image.shape[:2]) >= 200, (name, image.shape)
        assert np.ptp(image[..., :3]) > 0.5, name               # drawn, not blank


def test_the_reports_links_to_the_results_pages_resolve(demo):
    import radarpc.cli.demo_report as demo_report

    # the results pages beside the radarpc that ran (a source checkout); an installed wheel has none
    # and the report names them as text, which must not look like a link
    docs = Path(demo_report.__file__).resolve().parents[3] / "docs" / "results"
    links = re.findall(r"\[`docs/results/([^`]+)`\]\(([^)]+)\)", demo.report)
    if not (docs / "README.md").is_file():
        assert links == [] and "`docs/results/study.md`" in demo.report
        return
    assert {name for name, _ in links} >= {"README.md", "detection.md", "study.md", "pointcloud.md", "coloradar.md"}
    for name, target in links:
        assert (demo.out / target).resolve() == (docs / name).resolve()


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


def test_figures_draw_the_test_frame_with_the_most_vehicles(demo):
    # seed 75 (--tiny's): the test sequence's frames hold 2, 2 and 3 vehicles, so the frame is its last
    counts, seq = _vehicles_per_frame(demo.out / "sim_radial" / "labels.csv")
    test = sorted(n for n in counts if seq[n] == max(seq.values()))
    want = max(test, key=lambda n: (counts[n], -n))
    assert counts[want] > 0 and want != test[0]
    assert f"frame {want}, the test frame with the most labelled vehicles, {counts[want]}." in demo.report
    assert re.search(rf"`radarpc show \S+ --frame {want} ", demo.report)
    for run in ("spectralpillars", "fftradnet"):
        assert f"runs/{run}/figures/eval_test_easy_frame{want:06d}.png" in demo.report
        assert f"--show-frames {want} " in demo.report


def test_data_runs_the_radial_part_on_the_given_root(demo, tmp_path):
    root = tmp_path / "user" / "RADIal"                  # a root the demo did not simulate
    shutil.copytree(demo.out / "sim_radial", root)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        stdout = _demo(tmp_path / "demo", "--no-progress", "--data", str(root))
    finally:
        torch.set_num_threads(threads)
    assert f"the RADIal root {root}" in stdout and "simulate RADIal" not in stdout
    assert f"0 of {len(STEP_NAMES) - 1} steps reused, {len(STEP_NAMES) - 1} run" in stdout
    assert not (tmp_path / "demo" / "sim_radial").exists()
    for tag in ("020", "057", "200"):                  # the same frames: the stores the simulating demo made
        ours, theirs = (PointStore(o / "points" / f"pc_{tag}.parquet") for o in (tmp_path / "demo", demo.out))
        assert Path(ours.metadata.source_root).resolve() == root.resolve()
        assert len(ours) == len(theirs) == 9
        assert ours.metadata.tau == pytest.approx(theirs.metadata.tau, rel=1e-4)
    assert "The given (`--data`) RADIal root `../user/RADIal`" in (tmp_path / "demo" / "REPORT.md").read_text()


def test_data_that_is_not_a_radial_root_is_refused_before_any_work(tmp_path, capsys):
    assert main(["demo", "--tiny", "--out", str(tmp_path / "demo"), "--data", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err
    assert f"radarpc demo: error: --data {tmp_path / 'nothing'}: not a RADIal root (no labels.csv)" in err
    assert not (tmp_path / "demo").exists()                  # refused before the demo's folder is made


def test_stores_and_scores_in_the_report_are_the_outputs(demo):
    out = demo.out
    achieved = []
    for d, tag in ((0.02, "020"), (0.057, "057"), (0.2, "200")):
        store = PointStore(out / "points" / f"pc_{tag}.parquet")
        m = store.metadata
        assert len(store) == 9 and m.enrich == ("rd3", "sector32") and m.density_mode == "per-dataset"
        assert m.target_density == d
        achieved.append(m.achieved_density)
        tau = f"{m.tau:.3g} ({10 * math.log10(m.tau):.1f} dB)"
        assert f"| `points/pc_{tag}.parquet`" in demo.report and f"| {tau} | {100 * m.achieved_density:.3g} % |" \
            in demo.report
    assert achieved == sorted(achieved)
    ev = json.loads((out / "runs" / "fftradnet" / "eval_test_easy.json").read_text())
    assert ev["easy"] and ev["metrics"]["n_frames"] == 3 and ev["training"]["finished"]
    m = ev["metrics"]
    assert (f"| FFTRadNet | RD cube | 100 % | {m['ap']:.3f} | {m['ar']:.3f} | **{m['f1']:.3f}** | "
            f"{m['precision_fixed']:.3f} | {m['recall_fixed']:.3f} | **{m['f1_fixed']:.3f}** |") in demo.report
    sp = json.loads((out / "runs" / "spectralpillars" / "eval_test_on_pc_200_easy.json").read_text())
    assert sp["points"][0].endswith("pc_200.parquet")
    metrics = json.loads((out / "preds" / "oscfar" / "metrics.json").read_text())["overall"]
    assert metrics["n_frames"] == 1 and 0 < metrics["chamfer_mean"] < 20 and metrics["emd_mean"] > 0
    assert f"CD {metrics['chamfer_mean']:.3f} m, EMD {metrics['emd_mean']:.3f} m" in demo.report
    # the paper's numbers are there, labelled as the paper's on real data
    assert "| FFTRadNet (dense RD) F1 @ 0.2 |" in demo.report and "0.915 (Table 2) |" in demo.report
    assert "**The RaLD paper's numbers on the real ColoRadar dataset**" in demo.report


def test_a_killed_demo_resumes_at_its_first_unfinished_step(demo):
    assert "[15/19] classical detector at 20 %\n$ radarpc baseline detect" in demo.stdout_resumed
    assert "[14/19] classical detector at 5.7 %: reused, finished earlier in " in demo.stdout_resumed
    assert "[16/19] simulate ColoRadar: reused, " in demo.stdout_resumed        # the other part's chain
    assert "18 of 19 steps reused, 1 run" in demo.stdout_resumed

    # the classical detector is deterministic: the same scores as the uninterrupted demo
    def scores(text: str) -> list[str]:               # the table rows without their frames/s (timed anew)
        part = text[text.index("### Scores on the test split"):text.index("### What good values")]
        return [line.rsplit(" | ", 1)[0] for line in part.splitlines() if line.startswith("| ")]

    assert scores(demo.report_resumed) == scores(demo.report)


def test_a_rerun_reuses_every_step_and_writes_the_same_report(demo):
    for k, name in enumerate(STEP_NAMES, 1):
        assert f"[{k}/19] {name}: reused, finished earlier in " in demo.stdout_rerun
    assert "19 of 19 steps reused, 0 run" in demo.stdout_rerun
    assert (demo.out / "REPORT.md").read_text() == demo.report_resumed
    after = _mtimes(demo.out)
    changed = sorted(k for k in after if after[k] != demo.before.get(k))
    assert changed == ["REPORT.md", "f1_density.png"]          # only what the report step writes


def test_fftradnet_reads_the_roots_sensor():
    from radarpc.sensors.radial import RADIAL, RADIAL_S, TINY

    assert fftradnet_spec("fftradnet-s", RADIAL_S).overrides == {}
    full = fftradnet_spec("fftradnet-s", RADIAL)               # radial-s: 128 x 64 cubes, slot width 4
    assert full.overrides == {"n_range": 512, "n_doppler": 256, "slot_width": 16, "range_strides": [2, 2]}
    official = build_model("fftradnet", device="meta").cfg        # the official model reads radial cubes
    for name in ("n_range", "n_doppler", "n_rx", "n_tx", "slot_width", "range_strides"):
        assert getattr(full.config, name) == getattr(official, name), name
    with pytest.raises(ValueError, match="has 64 range bins"):
        fftradnet_spec("fftradnet-tiny", TINY)


def test_demo_config_refuses_bad_densities():
    with pytest.raises(ValueError, match="three increasing"):
        DemoConfig(densities=(0.057, 0.02, 0.2))


def test_step_and_batch_options_reach_the_config(monkeypatch, tmp_path, capsys):
    import radarpc.cli.demo as demo_cli

    seen = []
    monkeypatch.setattr(demo_cli, "run_demo", lambda cfg: seen.append(cfg))
    assert main(["demo", "--out", str(tmp_path), "--pillars-steps", "500", "--fftradnet-steps", "1000",
                 "--batch-size", "8"]) == 0
    assert (seen[0].pillars_steps, seen[0].fftradnet_steps, seen[0].batch_size) == (500, 1000, 8)
    assert main(["demo", "--tiny", "--out", str(tmp_path)]) == 0     # unset: the preset's
    tiny = DemoConfig.preset(tiny=True)
    assert (seen[1].pillars_steps, seen[1].fftradnet_steps, seen[1].batch_size) == \
        (tiny.pillars_steps, tiny.fftradnet_steps, tiny.batch_size)
    assert main(["demo", "--out", str(tmp_path), "--fftradnet-steps", "0"]) != 0
    assert "fftradnet_steps must be >= 1, got 0" in capsys.readouterr().err


def test_default_budgets_reach_the_training_configs():
    from radarpc.cli.demo import experiment_configs
    from radarpc.sensors.radial import radial_sensor

    d = DemoConfig()
    assert (d.pillars_steps, d.fftradnet_steps, d.batch_size) == (200, 60, 4)
    configs = experiment_configs(DemoConfig(fftradnet_steps=1000, batch_size=8), radial_sensor("radial-s"))
    assert configs["fftradnet"].train.max_steps == 1000 and configs["spectralpillars"].train.max_steps == 200
    for c in configs.values():
        assert c.train.batch_size == c.train.eval_batch_size == 8


def test_fftradnet_note_only_when_it_found_nothing():
    from radarpc.cli.demo_report import LONG_FFTRADNET_FRAMES, fftradnet_note

    link = "`docs/results/detection.md`"
    short = fftradnet_note(DemoConfig(), {"steps": 60, "best_f1": 0.0}, link)
    assert "found no vehicle" in short[1] and "in its 60 steps of 4 frames" in short[1]
    assert "`radarpc demo --fftradnet-steps 1000 --batch-size 8`" in short[1]
    long = fftradnet_note(DemoConfig(fftradnet_steps=1000, batch_size=8),
                          {"steps": 1000, "best_f1": 0.0}, link)
    assert "found no vehicle" in long[1] and "--fftradnet-steps" not in long[1]      # no advice to do it again
    below = fftradnet_note(DemoConfig(batch_size=8), {"steps": LONG_FFTRADNET_FRAMES // 8 - 1, "best_f1": 0.0}, link)
    at = fftradnet_note(DemoConfig(batch_size=8), {"steps": LONG_FFTRADNET_FRAMES // 8, "best_f1": 0.0}, link)
    assert "--fftradnet-steps" in below[1] and "--fftradnet-steps" not in at[1]       # the boundary
    assert fftradnet_note(DemoConfig(), {"steps": 60, "best_f1": 0.01}, link) == []
    assert fftradnet_note(DemoConfig.preset(tiny=True), {"steps": 2, "best_f1": 0.0}, link) == []


def test_a_training_finished_with_other_settings_is_replaced_not_refused(tmp_path, monkeypatch):
    """The demo's own run folder holding a finished run of other settings: the step passes
    --overwrite (else `radarpc train` refuses it) and drops the stale record first; without such
    a record the command runs as given (a killed run of the same settings resumes)."""
    import radarpc.cli.runner as runner
    from radarpc.cli.demo import DemoPaths, DemoStep, _execute, _record_path

    out = tmp_path / "run"
    out.mkdir()
    (out / "best.safetensors").write_bytes(b"")
    ran = []
    monkeypatch.setattr(runner, "run_command", lambda parser, argv: ran.append(argv) or 0)
    paths = DemoPaths(DemoConfig(out=tmp_path))
    step = DemoStep("train X", "train-x", "radial", ["train", "cfg.yaml", "--out", str(out)], "why",
                    outputs=[out / "best.safetensors"], key={"steps": 2}, replaces_stale=True)
    _execute(step, paths, "1/1", True, lambda s: None)                      # no record: as given
    assert ran[-1] == step.argv and not step.reused
    _execute(step, paths, "1/1", True, lambda s: None)                      # its own record: reused
    assert len(ran) == 1 and step.reused
    changed = DemoStep("train X", "train-x", "radial", step.argv, "why", outputs=step.outputs, key={"steps": 3},
                       replaces_stale=True)
    _execute(changed, paths, "1/1", True, lambda s: None)                   # other settings: replaced
    assert ran[-1] == [*step.argv, "--overwrite"]
    record = json.loads(_record_path(paths, changed).read_text())
    assert record["argv"] == step.argv and record["key"] == {"steps": 3}   # the record keeps the plain command
    plain = DemoStep("show", "show", "radial", ["show", "x"], "why", outputs=step.outputs)
    _record_path(paths, plain).write_text(json.dumps({"argv": ["show", "y"], "key": {}}))
    _execute(plain, paths, "1/1", True, lambda s: None)                     # no replaces_stale: as given
    assert ran[-1] == ["show", "x"]


def test_most_labelled_frame_is_the_first_of_the_largest_count():
    ds = SimpleNamespace(frame_ids=[4, 7, 9, 12], label_tensor=lambda i: torch.zeros((0, 2, 2, 1)[i], 14))
    assert _most_labelled(ds) == (7, 2)                  # a tie: the first in numSample order
    ds.frame_ids, ds.label_tensor = [3, 5], (lambda i: torch.zeros(0, 14))
    assert _most_labelled(ds) == (3, 0)


def test_evaluate_refuses_to_draw_a_frame_outside_the_split_before_scoring(demo):
    from radarpc.experiments.radial_detection.evaluation import evaluate_run

    run = demo.out / "runs" / "spectralpillars"
    before = {p.name: p.stat().st_mtime_ns for p in run.glob("eval_*")}
    with pytest.raises(ValueError, match=r"frame 0 \(numSample\) is not among the 3 frames of the test split"):
        evaluate_run(run, "test", show_frames=(0,), timed=False, log=lambda s: None)    # frame 0 trains
    assert {p.name: p.stat().st_mtime_ns for p in run.glob("eval_*")} == before
