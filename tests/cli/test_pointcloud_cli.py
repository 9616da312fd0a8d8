"""``radarpc pointcloud`` and ``radarpc show`` on a tiny simulated root: smoke runs and bad input."""
from __future__ import annotations

import argparse

import numpy as np
import pytest
import torch
from PIL import Image

from radarpc import viz
from radarpc.cli import pointcloud, show
from radarpc.data.pointstore import PointStore
from radarpc.data.radial import RADIal
from radarpc.io import DataFileError
from radarpc.sensors.radial import TINY
from testkit import TINY_ROOT


def run_cli(argv: list[str]) -> int:
    """Parse ``argv`` with the two commands' own parsers and run it (as ``radarpc`` does)."""
    parser = argparse.ArgumentParser(prog="radarpc")
    sub = parser.add_subparsers(dest="command", required=True)
    pointcloud.add_parser(sub)
    show.add_parser(sub)
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.fixture
def root(tiny_root):
    # 3 sequences (train, val, test) x 2 frames of the TINY sensor (tests/conftest.py), read-only
    return tiny_root


@pytest.fixture(scope="module")
def density_store(tiny_root, tmp_path_factory):
    """``(store, stdout, stderr)`` of one ``pointcloud ROOT --density 0.1 --quiet`` run, which two tests read."""
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    store = tmp_path_factory.mktemp("density") / "pc.parquet"
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        assert run_cli(["pointcloud", str(tiny_root), "--density", "0.1", "--out", str(store), "--quiet"]) == 0
    return store, out.getvalue(), err.getvalue()


def test_pointcloud_density_enrich(root, tmp_path, capsys):
    out = tmp_path / "pc.parquet"
    assert run_cli(["pointcloud", str(root), "--density", "0.1", "--enrich", "rd3,sector8", "--out", str(out),
                    "--batch-size", "3", "--chunk-frames", "4", "--quiet"]) == 0
    msg = capsys.readouterr().out
    assert f"wrote {out}: 6 frames" in msg and "achieved density" in msg and "(target 0.1)" in msg
    store = PointStore(out)
    assert store.frames == RADIal(root, split="all").frame_ids
    assert store.metadata.enrich == ("rd3", "sector8") and store.metadata.density_mode == "per-frame"
    assert store.schema.field("sector").type.list_size == 8 and store.schema.field("rd_patch").type.list_size == 9
    c = store[0]
    assert c.sector.shape == (int(c.offset[0]), 8) and bool(c.is_neighbour.any())
    # with rd3 the target applies to the encoded set S*(tau); the CFAR peaks S(tau) are printed apart
    printed = float(msg.split("achieved density ")[1].split()[0])
    assert printed == pytest.approx(store.metadata.achieved_density, abs=1e-5)
    assert printed == pytest.approx(0.1, rel=0.1)                   # per-frame control hits the target
    assert "of S*(tau) with rd3 neighbourhoods" in msg
    peaks = float(msg.split("CFAR peaks S(tau) alone ")[1].split(";")[0])
    assert peaks == pytest.approx(store.metadata.peak_density, abs=1e-5) and peaks < printed
    np.testing.assert_allclose(store.frame_table.density, 0.1, rtol=0.1)


def test_pointcloud_snr_and_sparse_rd(root, tmp_path, capsys):
    out, srd = tmp_path / "pc.parquet", tmp_path / "srd"
    assert run_cli(["pointcloud", str(root), "--snr", "2.0", "--split", "val", "--out", str(out),
                    "--sparse-rd-out", str(srd), "--window", "7,5", "--guard", "3,1", "--quiet"]) == 0
    msg = capsys.readouterr().out
    assert "tau 2" in msg and "wrote sparse-RD root" in msg
    store = PointStore(out)
    assert store.metadata.tau == 2.0 and store.metadata.window == (7, 5) and store.metadata.guard == (3, 1)
    val = RADIal(root, split="val")
    sparse = RADIal(srd, split="all")
    assert store.frames == val.frame_ids == sparse.frame_ids
    offsets = torch.as_tensor(TINY.doppler_offsets)
    for i in range(len(val)):
        rd, sp = val[i][0], sparse[i][0]
        cloud = store[i]
        # the kept cells are exactly the stored points' range bins x their replica Doppler bins
        kept = torch.zeros(TINY.n_range, TINY.n_doppler, dtype=torch.bool)
        bins = (cloud.doppler_full[:, None] + offsets) % TINY.n_doppler
        kept[cloud.range_bin[:, None].expand_as(bins), bins] = True
        assert torch.equal(sp, torch.where(kept[..., None], rd, torch.zeros((), dtype=rd.dtype)))


def test_cfar_radial_preset_reproduces_rpl_settings(root, tmp_path, capsys):
    # one flag = RADIal rpl.py: 19 x 19 window, 7 x 7 guard (its (9, 9, 3, 3) half widths), all-slot envelope
    out, ref = tmp_path / "rpl.parquet", tmp_path / "explicit.parquet"
    assert run_cli(["pointcloud", str(root), "--snr", "1.585", "--cfar", "radial", "--out", str(out), "--quiet"]) == 0
    m = PointStore(out).metadata
    assert m.window == (19, 19) and m.guard == (7, 7) and m.envelope == "all-slots"
    assert m.settings["envelope"] == "all-slots" and m.settings["window"] == [19, 19]
    assert run_cli(["pointcloud", str(root), "--snr", "1.585", "--window", "19,19", "--guard", "7,7",
                    "--envelope", "all-slots", "--out", str(ref), "--quiet"]) == 0
    assert PointStore(ref).read_frames(range(6)).x.tolist() == PointStore(out).read_frames(range(6)).x.tolist()
    # the default envelope is the seed's replica sum
    default = tmp_path / "default.parquet"
    run_cli(["pointcloud", str(root), "--snr", "1.585", "--out", str(default), "--quiet"])
    assert PointStore(default).metadata.envelope == "replicas" and PointStore(default).metadata.window == (9, 9)
    # the --snr help documents the half-width reading of rpl.py's defaults
    parser = argparse.ArgumentParser(prog="radarpc")
    sub = parser.add_subparsers(dest="command")
    pointcloud.add_parser(sub)
    helptext = " ".join(sub.choices["pointcloud"].format_help().split())
    assert "half widths" in helptext and "--window 19,19 --guard 7,7" in helptext


def test_pointcloud_rd3_density_sparse_rd_matches_store(root, tmp_path, capsys):
    out, srd = tmp_path / "pc.parquet", tmp_path / "srd"
    assert run_cli(["pointcloud", str(root), "--density", "0.1", "--enrich", "rd3", "--out", str(out),
                    "--sparse-rd-out", str(srd), "--quiet"]) == 0
    store, sparse, src = PointStore(out), RADIal(srd, split="all"), RADIal(root, split="all")
    offsets = torch.as_tensor(TINY.doppler_offsets)
    for i in range(len(src)):
        cloud = store[i]
        kept = torch.zeros(TINY.n_range, TINY.n_doppler, dtype=torch.bool)
        bins = (cloud.doppler_full[:, None] + offsets) % TINY.n_doppler
        kept[cloud.range_bin[:, None].expand_as(bins), bins] = True
        rd = src[i][0]
        assert torch.equal(sparse[i][0], torch.where(kept[..., None], rd, torch.zeros((), dtype=rd.dtype))), i
    assert "per-frame taus and densities in sparse_rd.json" in capsys.readouterr().out


def test_show_writes_a_png(root, density_store, tmp_path, capsys):
    png = tmp_path / "frame1.png"
    assert run_cli(["show", str(root), "--frame", "1", "--density", "0.1", "--out", str(png)]) == 0
    assert "(linear SNR)" in capsys.readouterr().out
    with Image.open(png) as im:
        assert im.format == "PNG" and im.size[0] > 800 and im.size[1] > 300
        arr = np.asarray(im.convert("L"))
    assert arr.std() > 10                                # not a blank canvas
    # from a store: the same points as the store holds for that frame
    store = density_store[0]
    png2 = tmp_path / "frame1_store.png"
    assert run_cli(["show", str(root), "--frame", "1", "--store", str(store), "--color", "amplitude",
                    "--out", str(png2)]) == 0
    n = int(PointStore(store)[1].offset[0])
    assert f"{n} points" in capsys.readouterr().out and png2.is_file()


def test_show_geometry_and_encoded_density(root, tmp_path):
    # the RD image rows, the peak markers and the points' range_m agree (no half-bin offset)
    x0, x1, y0, y1 = viz.rd_extent(TINY, TINY.slot_width)
    row_h = (y1 - y0) / TINY.n_range
    r = np.arange(TINY.n_range)
    centres = y0 + (r + 0.5) * row_h
    np.testing.assert_allclose(centres, viz.peak_marker_range_m(TINY, r), atol=1e-9)
    cloud = PointStore(_store(root, tmp_path))[1]
    np.testing.assert_allclose(viz.peak_marker_range_m(TINY, cloud.range_bin.numpy()), cloud.range_m.numpy(),
                               rtol=1e-6)
    w, dv = TINY.slot_width, TINY.velocity_res_mps
    np.testing.assert_allclose((x0, x1), ((-w // 2 - 0.5) * dv, (w - w // 2 - 0.5) * dv))   # m/s, Doppler-centred
    # FramePlot.density is the encoded set's (S* with rd3), the CFAR peaks' S apart
    from radarpc.pipelines.frames import frame_view
    from radarpc.pipelines.pointclouds import ConvertSettings

    res = viz.plot_frame_view(frame_view(root, 1, ConvertSettings(density=0.1, enrich=("rd3",))), tmp_path / "f.png")
    assert res.density == pytest.approx(0.1, rel=0.1) and res.peak_density < res.density
    assert res.peak_density == pytest.approx(res.n_peaks * TINY.n_tx / (TINY.n_range * TINY.n_doppler))


def _store(root, tmp_path):
    out = tmp_path / "geo.parquet"
    run_cli(["pointcloud", str(root), "--snr", "2", "--out", str(out), "--quiet"])
    return out


def test_bad_input(root, tmp_path):
    out = str(tmp_path / "pc.parquet")
    with pytest.raises(ValueError, match=r"--density: density must be in \(0, 1\] \(fraction of RD cells kept\), got 1.5"):
        run_cli(["pointcloud", str(root), "--density", "1.5", "--out", out])
    with pytest.raises(ValueError, match="--snr: tau must be a finite linear SNR threshold > 0"):
        run_cli(["pointcloud", str(root), "--snr", "0", "--out", out])
    with pytest.raises(SystemExit):                      # --density and --snr are exclusive
        run_cli(["pointcloud", str(root), "--density", "0.1", "--snr", "2", "--out", out])
    with pytest.raises(SystemExit):                      # one of them is required
        run_cli(["pointcloud", str(root), "--out", out])
    with pytest.raises(SystemExit):
        run_cli(["pointcloud", str(root), "--snr", "2", "--window", "9", "--out", out])
    with pytest.raises(ValueError, match="nothing to write"):
        run_cli(["pointcloud", str(root), "--snr", "2"])
    with pytest.raises(ValueError, match="unknown enrichment 'rdx'"):
        run_cli(["pointcloud", str(root), "--snr", "2", "--enrich", "rdx", "--out", out, "--quiet"])
    with pytest.raises(ValueError, match="on a RADIal root give one of --density, --snr or --store"):
        run_cli(["show", str(root), "--frame", "1", "--out", str(tmp_path / "f.png")])
    with pytest.raises(ValueError, match="--run and --pred apply to ColoRadar roots"):
        run_cli(["show", str(root), "--frame", "1", "--snr", "2", "--run", "x", "--out", str(tmp_path / "f.png")])
    with pytest.raises(ValueError, match="frame 99 is not in"):
        run_cli(["show", str(root), "--frame", "99", "--snr", "2", "--out", str(tmp_path / "f.png")])
    bad = tmp_path / "bad.parquet"
    bad.write_text("not parquet")
    with pytest.raises(DataFileError, match="bad.parquet: is not a readable Parquet file"):
        run_cli(["show", str(root), "--frame", "0", "--store", str(bad), "--out", str(tmp_path / "f.png")])
    with pytest.raises(ValueError, match="unreachable for sensor 'tiny'"):
        run_cli(["pointcloud", str(root), "--density", "0.9", "--out", out, "--quiet"])
    with pytest.raises(ValueError, match=r"--cfar radial sets window \(19, 19\).*contradicts --window \(9, 9\)"):
        run_cli(["pointcloud", str(root), "--snr", "2", "--cfar", "radial", "--window", "9,9", "--out", out])
    with pytest.raises(SystemExit):
        run_cli(["pointcloud", str(root), "--snr", "2", "--envelope", "sum", "--out", out])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.parquet"]     # nothing half-written


def test_pointcloud_beamforming_flag(root, tmp_path, capsys):
    exact, fast = tmp_path / "exact.parquet", tmp_path / "fast.parquet"
    for out, mode in ((exact, "exact"), (fast, "screened")):
        assert run_cli(["pointcloud", str(root), "--snr", "1.585", "--out", str(out), "--quiet",
                        "--beamforming", mode]) == 0
    a, b = PointStore(exact), PointStore(fast)
    assert a.metadata.settings["beamforming"] == "exact" and b.metadata.settings["beamforming"] == "screened"
    for i in range(len(a)):
        ca, cb = a[i], b[i]
        # detection is identical; the screened direction is the exact argmax, its amplitude the exact one
        assert torch.equal(ca.range_bin, cb.range_bin) and torch.equal(ca.doppler_full, cb.doppler_full)
        assert torch.equal(ca.azimuth_deg, cb.azimuth_deg)
        torch.testing.assert_close(ca.amplitude, cb.amplitude, rtol=1e-5, atol=1e-6)
    # the mode is a recorded setting: another mode on the same --out is refused, not silently
    # replaced (one clear line, exit 2), and replaces the store with --overwrite
    from radarpc.cli import main

    capsys.readouterr()
    assert main(["pointcloud", str(root), "--snr", "1.585", "--out", str(exact), "--quiet",
                 "--beamforming", "screened"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "other settings" in err and "--overwrite" in err
    assert PointStore(exact).metadata.settings["beamforming"] == "exact"
    assert run_cli(["pointcloud", str(root), "--snr", "1.585", "--out", str(exact), "--quiet",
                    "--beamforming", "screened", "--overwrite"]) == 0
    assert PointStore(exact).metadata.settings["beamforming"] == "screened"


def test_density_far_off_target_is_warned(root, density_store, tmp_path, capsys):
    # on TINY, 0.007 with rd5 is out of reach (one peak's 5x5 neighbourhood overshoots it)
    run_cli(["pointcloud", str(root), "--density", "0.007", "--enrich", "rd5", "--out",
             str(tmp_path / "a.parquet"), "--quiet"])
    err = capsys.readouterr().err
    achieved = PointStore(tmp_path / "a.parquet").metadata.achieved_density
    assert abs(achieved - 0.007) / 0.007 > pointcloud.DENSITY_WARN_REL
    assert f"warning: the achieved density {achieved:.5f} is" in err and "with rd5" in err
    store, _, store_err = density_store                    # pointcloud ROOT --density 0.1 --quiet
    achieved = PointStore(store).metadata.achieved_density
    assert abs(achieved - 0.1) / 0.1 <= pointcloud.DENSITY_WARN_REL and store_err == ""
    assert pointcloud.density_warning(0.1, 0.13, ()) is not None
    assert pointcloud.density_warning(0.1, 0.12, ()) is None and pointcloud.density_warning(None, 0.5, ()) is None


def test_show_refuses_a_store_of_another_root_and_a_directory_as_figure(root, tmp_path):
    import shutil
    store = tmp_path / "pc.parquet"
    run_cli(["pointcloud", str(root), "--snr", "3", "--out", str(store), "--quiet"])
    other = tmp_path / "other"
    shutil.copytree(root, other)
    with pytest.raises(ValueError, match=f"was made from {root.resolve()}, not from {other}"):
        run_cli(["show", str(other), "--frame", "0", "--store", str(store), "--out", str(tmp_path / "f.png")])
    # a store made from the dataset object that wrote ROOT records its repr, not a path: accepted
    from radarpc.pipelines.pointclouds import convert_dataset
    from radarpc.sim.radial_writer import SimulatedRADIal

    obj_store = tmp_path / "obj.parquet"
    convert_dataset(SimulatedRADIal(TINY, **TINY_ROOT, split="all"), obj_store, tau=3.0, progress=False)
    assert not PointStore(obj_store).metadata.source_root.startswith("/")
    run_cli(["show", str(root), "--frame", "0", "--store", str(obj_store), "--out", str(tmp_path / "g.png")])
    (tmp_path / "figs").mkdir()
    with pytest.raises(IsADirectoryError, match="is a directory; give the path of a .png file"):
        run_cli(["show", str(root), "--frame", "0", "--snr", "3", "--out", str(tmp_path / "figs")])


def test_interrupt_and_bad_device_are_one_line_messages(root, tmp_path, capsys, monkeypatch):
    from radarpc import cli

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("radarpc.pipelines.pointclouds.convert_dataset", interrupted)   # imported by run()
    assert cli.main(["pointcloud", str(root), "--snr", "3", "--out", str(tmp_path / "pc.parquet")]) == 130
    assert "interrupted; finished work is kept, run the same command again to resume" in capsys.readouterr().err
    monkeypatch.undo()
    assert cli.main(["pointcloud", str(root), "--snr", "3", "--out", str(tmp_path / "pc.parquet"),
                     "--device", "nodevice"]) == 2
    assert "device 'nodevice' is not a torch device" in capsys.readouterr().err


def test_the_summary_says_what_was_reused(root, tmp_path, capsys, monkeypatch):
    # an interrupted conversion, resumed: the line says how many frames were converted now and how
    # many were reused; a finished one says there was nothing to do
    import radarpc.pipelines.pointclouds as pipeline
    from radarpc import cli

    out = tmp_path / "pc.parquet"
    real = pipeline.convert_dataset
    n_frames = len(RADIal(root, split="all"))

    def killed_after_first_chunk(*args, **kwargs):
        def stop(k):
            raise KeyboardInterrupt
        return real(*args, **kwargs, on_chunk_done=stop)

    monkeypatch.setattr(pipeline, "convert_dataset", killed_after_first_chunk)
    argv = ["pointcloud", str(root), "--snr", "3", "--out", str(out), "--chunk-frames", "2", "--quiet"]
    assert cli.main(argv) == 130
    monkeypatch.undo()
    capsys.readouterr()
    assert cli.main(argv) == 0
    line = capsys.readouterr().out
    assert f"wrote {out}: {n_frames - 2} frames converted now, 2 reused from an earlier run" in line
    assert cli.main(argv) == 0
    assert f"{out} already holds this conversion (nothing to do)" in capsys.readouterr().out


def test_a_nan_cube_under_workers_is_one_line(root, tmp_path, capsys):
    # the worker's error reaches the command line as in one process: one line naming the file
    import shutil

    import numpy as np

    from radarpc import cli
    from radarpc.data.radial_format import fft_path

    bad = tmp_path / "bad"
    shutil.copytree(root, bad)
    cube = np.load(fft_path(bad, 3))
    cube[0, 0, 0] = np.nan
    np.save(fft_path(bad, 3), cube)
    capsys.readouterr()
    assert cli.main(["pointcloud", str(bad), "--snr", "3", "--out", str(tmp_path / "pc.parquet"), "--quiet",
                     "--workers", "2", "--chunk-frames", "2"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "fft_000003.npy" in err[0] and "NaN" in err[0] and "Traceback" not in err[0]


def test_a_sparse_rd_rerun_prints_the_roots_density(root, tmp_path, capsys):
    # a rerun that reuses every cube (or all but one) prints the density of the whole root: the mean of
    # the per-frame densities sparse_rd.json records, each the fraction of (range, Doppler) cells the
    # stored cube keeps
    import json

    from radarpc.data.radial_format import stored_fft_path

    srd = tmp_path / "srd"
    argv = ["pointcloud", str(root), "--snr", "2.0", "--sparse-rd-out", str(srd), "--quiet"]

    def printed() -> float:
        line = capsys.readouterr().out
        assert "n/a" not in line
        return float(line.split("achieved density ")[1].split()[0])

    assert run_cli(argv) == 0
    first = printed()
    sparse = RADIal(srd, split="all")
    kept = [float((sparse[i][0] != 0).any(-1).double().mean()) for i in range(len(sparse))]
    records = json.loads((srd / "sparse_rd.json").read_text())["frames"]
    assert [records[str(n)]["density"] for n in sparse.frame_ids] == pytest.approx(kept, abs=1e-12)
    assert first == pytest.approx(np.mean(kept), abs=5e-6)             # printed with 5 decimals
    assert run_cli(argv) == 0                                           # every cube exists
    assert printed() == first
    stored_fft_path(srd, sparse.frame_ids[-1]).unlink()                 # one cube to write again
    assert run_cli(argv) == 0
    assert printed() == first
