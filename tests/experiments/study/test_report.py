"""The report of a study from its result rows: tables checked against hand-computed means,
deviations and normalized AUCs, readable figures that say what made them, and bad rows refused."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from PIL import Image

from radarpc.cli import main
from radarpc.experiments.study.report import collect, write_report
from radarpc.experiments.study.results import ROW_FORMAT, read_rows

# F1 @ 0.2 per arm, density and seed (two seeds each); freespace mIoU = F1 / 2
F1 = {"pp": {0.01: [0.5, 0.6], 0.03: [0.7, 0.7], 0.1: [0.8, 0.9]},
      "sp": {0.01: [0.6, 0.6], 0.03: [0.8, 0.8], 0.1: [0.9, 0.9]},
      "fft": {None: [0.75, 0.77]}}
COMMAND = "radarpc experiment density-sweep configs/study/x.yaml --out runs/x"
COMMIT = "0123456789abcdef0123456789abcdef01234567"


def _row(arm: str, order: int, density: float | None, seed: int, f1: float) -> dict:
    folder = "dense" if density is None else f"density-{density * 1000:03.0f}"
    return {"format": ROW_FORMAT, "run": f"{folder}/{arm}/seed{seed}",
            "study": {"kind": "density-sweep", "name": "x", "config_file": "configs/study/x.yaml",
                      "config": {"name": "x", "densities": [0.01, 0.03, 0.1]}},
            "arm": {"name": arm, "label": f"{arm} label", "group": "models",
                    "input": "dense" if density is None else "points", "enrich": [], "variant": arm, "order": order},
            "density": density, "seed": seed, "key": {"seed": seed},
            "inputs": [] if density is None else [{"root": "r", "tau": 2.0 + seed, "achieved_density": density * 1.1,
                                                   "peak_density": density, "seconds": 1.0}],
            "metrics": {"f1_fixed": f1, "f1": f1 - 0.01, "freespace_miou": f1 / 2},
            "evaluation": {"split": "test", "easy": True, "fps_batch1": 50.0},
            "training": {"weights_epoch": 1, "weights_step": 10, "train_time_s": 120.0, "cut_at_time_limit": False},
            "times": {"finished_at": f"2026-12-06T00:00:0{seed}+00:00"},
            "software": {"radarpc": "0.1.0", "commit": COMMIT, "torch": "2.13.0"}, "command": COMMAND}


@pytest.fixture
def runs(tmp_path) -> Path:
    out = tmp_path / "runs"
    (out / "results").mkdir(parents=True)
    for order, (arm, per_density) in enumerate(F1.items()):
        for density, values in per_density.items():
            for seed, f1 in enumerate(values):
                row = _row(arm, order, density, seed, f1)
                (out / "results" / (row["run"].replace("/", "__") + ".json")).write_text(json.dumps(row))
    return out


def _table(text: str, heading: str) -> list[list[str]]:
    """The cells of the table under ``### heading``."""
    block = text[text.index(f"### {heading}\n"):].split("\n\n")[1]
    return [[c.strip() for c in line.strip("|").split("|")] for line in block.splitlines()]


def test_tables_hold_the_hand_computed_statistics(runs):
    text = write_report(runs, log=lambda s: None).read_text()
    f1 = _table(text, "F1 @ 0.2")
    assert f1[0] == ["arm", "1 %", "3 %", "10 %", "AUC_norm 1 %-10 %", "Δ AUC vs pp label",
                     "first density reaching fft label"]
    sd = math.sqrt(2 * 0.05 ** 2)                                     # two runs 0.1 apart
    # pp: (0.55 + 0.70) / 2 * 0.02 + (0.70 + 0.85) / 2 * 0.07 = 0.06675 over 0.09
    assert f1[2] == ["pp label", f"0.550 ± {sd:.3f} (2)", "0.700 ± 0.000 (2)", f"0.850 ± {sd:.3f} (2)",
                     f"{0.06675 / 0.09:.3f}", "0 (baseline)", "10 %"]
    # sp: (0.6 + 0.8) / 2 * 0.02 + (0.8 + 0.9) / 2 * 0.07 = 0.0735 over 0.09
    assert f1[3] == ["sp label", "0.600 ± 0.000 (2)", "0.800 ± 0.000 (2)", "0.900 ± 0.000 (2)",
                     f"{0.0735 / 0.09:.3f}", f"{(0.0735 - 0.06675) / 0.09:+.3f}", "3 %"]
    ref = f"0.760 ± {math.sqrt(2 * 0.01 ** 2):.3f} (2)"
    assert f1[4] == ["fft label (dense, every density)", ref, ref, ref, "-", "-", "-"]
    miou = _table(text, "freespace mIoU")
    assert miou[2][1] == f"0.275 ± {sd / 2:.3f} (2)" and miou[2][4] == f"{0.06675 / 0.09 / 2:.3f}"
    inputs = _table(text, "inputs: achieved density and CFAR threshold tau")
    assert inputs[2] == ["pp label", "1.1 %, tau 2", "3.3 %, tau 2", "11 %, tau 2"]
    runs_table = _table(text, "runs")
    assert len(runs_table) == 2 + 6 + 6 + 2 and runs_table[2][0] == "`density-010/pp/seed0`"


def test_the_report_and_its_figures_say_what_made_them(runs):
    path = write_report(runs, command="radarpc report runs", log=lambda s: None)
    text = path.read_text()
    assert f"study command: `{COMMAND}`" in text and "config file: `configs/study/x.yaml`" in text
    assert f"`{COMMIT}`" in text and "Made by `radarpc report runs`" in text
    assert "```yaml\nname: x\ndensities:" in text                       # the config itself
    assert "![models against density" in text and "(figures/models.png)" in text
    png = path.parent / "figures" / "models.png"
    with Image.open(png) as im:
        im.load()
        assert im.format == "PNG" and im.size[0] > 1000 and im.size[1] > 400
        assert COMMAND in im.text["Description"] and COMMIT in im.text["Description"]
        assert "radarpc report runs" in im.text["Description"]
        # not blank: the curves and their bands are drawn in colour
        colours = im.convert("RGB").getcolors(1 << 20)
        assert len(colours) > 50


def test_groups_keep_the_study_order(runs):
    groups = collect(read_rows(runs))
    assert [g.group for g in groups] == ["models"]
    assert [a.name for a in groups[0].curves] == ["pp", "sp"] and [a.name for a in groups[0].references] == ["fft"]
    assert groups[0].interval() == (0.01, 0.1)
    curve = groups[0].curves[0].curve("f1_fixed", (0.01, 0.1))
    assert curve.density == (0.01, 0.03, 0.1) and curve.runs[0] == (0.5, 0.6)


def test_an_arm_without_the_whole_interval_has_no_auc(runs):
    for p in (runs / "results").glob("density-100__sp__*.json"):
        p.unlink()
    text = write_report(runs, log=lambda s: None).read_text()
    f1 = _table(text, "F1 @ 0.2")
    assert f1[0][4] == "AUC_norm 1 %-3 %"                                # the interval both arms span
    assert f1[2][4] == f"{(0.55 + 0.70) / 2:.3f}" and f1[3][3] == "-"


def test_report_command_and_bad_rows(runs, tmp_path, capsys):
    assert main(["report", str(runs), "--out", str(tmp_path / "rep")]) == 0
    assert (tmp_path / "rep" / "report.md").is_file() and (tmp_path / "rep" / "figures" / "models.png").is_file()
    assert "radarpc report" in (tmp_path / "rep" / "report.md").read_text()
    capsys.readouterr()
    assert main(["report", str(tmp_path / "empty")]) == 2
    assert "no result rows" in capsys.readouterr().err
    bad = runs / "results" / "density-010__pp__seed0.json"
    bad.write_text("{")
    assert main(["report", str(runs)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "invalid JSON" in err and err.count("\n") == 1
    bad.write_text(json.dumps({**_row("pp", 0, 0.01, 0, 0.5), "format": "something else"}))
    assert main(["report", str(runs)]) == 2
    assert "format 'something else'" in capsys.readouterr().err
    bad.write_text(json.dumps(_row("pp", 0, 0.01, 1, 0.5)))            # seed 1's row under seed 0's name
    assert main(["report", str(runs)]) == 2
    assert "holds run 'density-010/pp/seed1'" in capsys.readouterr().err
