"""Figure files of ``radarpc show`` and ``radarpc info``: written in the format their suffix
names, refused before any work when the suffix names none."""
from __future__ import annotations

import pytest
from matplotlib.backend_bases import FigureCanvasBase

from radarpc import viz
from radarpc.cli import main
from radarpc.sensors.radial import TINY
from radarpc.sim.radial_writer import write_radial_dataset

# the first bytes of each format (its magic number), from the formats' specifications
MAGIC = {"png": b"\x89PNG\r\n\x1a\n", "pdf": b"%PDF-", "svg": b"<?xml", "jpg": b"\xff\xd8\xff",
         "eps": b"%!PS-Adobe", "tif": b"II*\x00"}


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    # 1 sequence x 2 frames of the TINY sensor
    return write_radial_dataset(tmp_path_factory.mktemp("show") / "root", TINY, 1, 2, seed=0, progress=False)


def test_figure_format_follows_the_suffix():
    assert viz.figure_format("a/b.png") == "png" and viz.figure_format("F.PDF") == "pdf"
    assert viz.figure_format("x.svg") == "svg" and viz.figure_format("x.jpeg") == "jpeg"
    with pytest.raises(ValueError) as e:
        viz.figure_format("out/x.txt")
    msg = str(e.value)
    assert msg.startswith("cannot write the figure out/x.txt: its suffix '.txt' names no figure format")
    # every format matplotlib writes by itself is offered, pgf (it needs LaTeX) is not
    offered = msg.split("ending in one of ")[1].split(", ")
    assert sorted(offered) == sorted(f".{f}" for f in FigureCanvasBase.get_supported_filetypes() if f != "pgf")
    with pytest.raises(ValueError, match="cannot write the figure frame: it has no suffix; give a path ending in"):
        viz.figure_format("frame")


def test_show_writes_the_format_of_the_suffix(root, tmp_path, capsys):
    for name, fmt in (("f.pdf", "pdf"), ("F.SVG", "svg")):
        out = tmp_path / name
        assert main(["show", str(root), "--frame", "1", "--snr", "3", "--out", str(out)]) == 0
        data = out.read_bytes()
        assert data.startswith(MAGIC[fmt]), (name, data[:16])
        assert f"wrote {out}: frame 1," in capsys.readouterr().out
    assert b"<svg" in (tmp_path / "F.SVG").read_bytes()[:1000]


def test_show_refuses_a_suffix_that_names_no_format_before_any_work(root, tmp_path, capsys):
    # frame 99 does not exist: the suffix is refused before the frame is looked for
    for name in ("x.txt", "frame"):
        out = tmp_path / name
        assert main(["show", str(root), "--frame", "99", "--snr", "3", "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"cannot write the figure {out}:" in err
        assert ".png, " in err and ".pdf" in err and ".svg" in err and "frame 99" not in err
    assert list(tmp_path.iterdir()) == []


def test_info_plot_follows_the_suffix(root, tmp_path, capsys):
    out = tmp_path / "info.pdf"
    assert main(["info", str(root), "--plot", str(out)]) == 0
    assert out.read_bytes().startswith(MAGIC["pdf"])
    assert f"plot:        {out}" in capsys.readouterr().out
    bad = tmp_path / "info.txt"
    assert main(["info", str(root), "--plot", str(bad)]) == 2
    err = capsys.readouterr()
    assert err.out == "" and f"cannot write the figure {bad}: its suffix '.txt' names no figure format" in err.err
    assert not bad.exists()
