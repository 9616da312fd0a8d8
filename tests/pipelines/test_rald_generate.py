"""RaLD's generation for a split (radarpc.pipelines.rald_generate): layout, records, resume after a
kill, empty frames, ownership, PLY export, and clouds in the radar frame of the LiDAR truth."""
from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import torch

from radarpc.data.coloradar import ColoRadar, upsample_intensity
from radarpc.experiments.rald.config import LidarData
from radarpc.models import build_model
from radarpc.pipelines import rald_generate as job_module
from radarpc.pipelines.rald_generate import GenerationJob, file_digests, generate_predictions
from radarpc.rald.frustum import in_frustum
from radarpc.rald.generate import STAGES, GenerationConfig, frame_seed, generate_cloud
from radarpc.rald.guide import GuideConfig
from radarpc.rald.voxels import voxelize_points
from radarpc.runs import RunMismatchError

CUBE = (16, 8, 8)
CFG = GenerationConfig(random_queries=1200, guided_queries=800, refine_queries=2400, chunk=1024, num_steps=2)
GUIDE = GuideConfig(source="os-cfar")         # the peaks are tested in tests/rald/test_guide.py
MODEL = {"run": "tiny"}


@pytest.fixture(scope="module")
def root(colo_root):
    # the session's 3 lab runs; the test split is lab_run2, 2 radar frames
    return colo_root


@pytest.fixture(scope="module")
def whole(root, tmp_path_factory):
    """An uninterrupted generation of the test split (read-only for the tests: copy it to change it)."""
    out = tmp_path_factory.mktemp("rald") / "whole"
    ae, dit = _models()
    res = generate_predictions(_job(root, out), ae, dit, model_input=model_input, model=MODEL, progress=False)
    return out, res


def _models():
    torch.manual_seed(0)
    ae = build_model("rald-ae-tiny")
    dit = build_model("rald-dit-tiny", {"radar_shape": CUBE, "enc_ch_mult": (1, 2), "n_latents": 32, "latent_dim": 8})
    torch.nn.init.normal_(dit.denoiser.proj_out.weight, std=0.05)
    return ae.eval(), dit.eval()


def model_input(cube):
    return upsample_intensity(cube, CUBE).clamp(0, 45) / 45


def _job(root, out, **kw):
    return GenerationJob(root, out, "test", kw.pop("generation", CFG), kw.pop("guide", GUIDE), **kw)


def _files(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.glob("*/*.npy"))}


def test_one_cloud_per_frame_with_its_record(root, whole):
    out, res = whole
    ds = ColoRadar(root, "test", cube_size=None)
    assert (res.n_frames, res.n_new, res.empty, res.warnings) == (len(ds), len(ds), (), ())
    assert set(res.seconds) == set(STAGES)
    index = json.loads((out / "index.json").read_text())
    assert index["method"] == "rald" and index["split"] == "test" and index["root"] == str(root.resolve())
    assert index["generation"]["random_queries"] == 1200 and index["guide"]["source"] == "os-cfar"
    assert index["model"] == {"run": "tiny"} and index["empty_frames"] == [] and index["grid"]["kind"] == "frustum"
    key = json.loads((out / "generation.json").read_text())
    assert key["generation"] == index["generation"] and key["model"] == {"run": "tiny"}
    with open(out / "generation.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [(r["run"], int(r["frame"])) for r in rows] == [(e["run"], e["frame"]) for e in index["frames"]]
    for i, (e, row) in enumerate(zip(index["frames"], rows)):
        pts = np.load(out / e["file"], allow_pickle=False)
        assert pts.dtype == np.float32 and pts.shape == (e["n_points"], 3) and e["empty"] is False
        assert int(row["n_points"]) == e["n_points"] and row["empty"] == "False"
        assert int(row["seed"]) == frame_seed(CFG.seed, e["run"], e["frame"])
        assert all(float(row[f"seconds_{s}"]) >= 0 for s in STAGES)
        assert int(row["queries_random"]) == 1200 and int(row["queries_guided"]) == 800
    # the first file is the library's cloud of the frame: its cube, guide points and seed
    from radarpc.rald.guide import guide_points

    ae, dit = _models()
    k, ri, _ = ds.index[0]
    adc = ds.runs[k].adc(ri)
    cube = ds.cube(0)
    want = generate_cloud(ae, dit, model_input(cube), guide_points(GUIDE, adc, ds.calib.single_chip, cube), CFG,
                          frame_seed(CFG.seed, ds.runs[k].name, ri))
    np.testing.assert_array_equal(np.load(out / index["frames"][0]["file"]), want.points)


def test_a_killed_job_resumes_to_the_files_of_an_uninterrupted_one(root, whole, tmp_path, monkeypatch):
    ae, dit = _models()
    whole = whole[0]

    # killed while generating the second frame: the first is written, the second left a temp file
    out = tmp_path / "killed"
    real = job_module.generate_cloud
    calls = []

    def dies_on_the_second(*a, **kw):
        calls.append(1)
        if len(calls) == 2:
            (out / "lab_run2" / ".000001.npy.x1.tmp").write_bytes(b"half a cloud")
            raise KeyboardInterrupt
        return real(*a, **kw)

    monkeypatch.setattr(job_module, "generate_cloud", dies_on_the_second)
    with pytest.raises(KeyboardInterrupt):
        generate_predictions(_job(root, out), ae, dit, model_input=model_input, model=MODEL, progress=False)
    monkeypatch.undo()
    assert sorted(_files(out)) == ["lab_run2/000000.npy"] and not (out / "index.json").exists()
    with open(out / "generation.csv", newline="") as f:
        assert [r["frame"] for r in csv.DictReader(f)] == ["0"]          # the finished frame's record is kept

    res = generate_predictions(_job(root, out), ae, dit, model_input=model_input, model=MODEL, progress=False)
    assert (res.n_new, res.n_reused) == (1, 1)
    assert not list(out.rglob("*.tmp"))
    assert _files(out) == _files(whole)
    assert json.loads((out / "index.json").read_text()) == json.loads((whole / "index.json").read_text())
    with open(out / "generation.csv", newline="") as f:
        assert [r["frame"] for r in csv.DictReader(f)] == ["0", "1"]

    # a cloud written without its record (killed between the two) is generated again, unchanged
    rows = (out / "generation.csv").read_text().splitlines()
    (out / "generation.csv").write_text("\n".join(rows[:2]) + "\n")
    again = generate_predictions(_job(root, out), ae, dit, model_input=model_input, model=MODEL, progress=False)
    assert (again.n_new, again.n_reused) == (1, 1) and _files(out) == _files(whole)


def test_other_settings_or_weights_are_refused_and_empty_decodings_recorded(root, whole, tmp_path):
    import shutil

    out = tmp_path / "rald"
    shutil.copytree(whole[0], out)
    ae, dit = _models()
    weights = tmp_path / "w.bin"
    weights.write_bytes(b"other weights")
    other = {"run": "tiny", "weights": file_digests([weights])}
    with pytest.raises(RunMismatchError, match="generation.json:model.weights"):
        generate_predictions(_job(root, out), ae, dit, model_input=model_input, model=other, progress=False)
    with pytest.raises(RunMismatchError, match="generation.json:generation.seed"):
        generate_predictions(_job(root, out, generation=GenerationConfig(**{**vars(CFG), "seed": 1})), ae, dit,
                             model_input=model_input, model=MODEL, progress=False)
    assert _files(out) == _files(whole[0])                               # refused before anything was written

    # overwritten by weights that decode nothing: every frame written empty, recorded and reported
    with torch.no_grad():
        ae.to_logit.bias.fill_(-1e4)
    seen = []
    res = generate_predictions(_job(root, out, overwrite=True), ae, dit, model_input=model_input, model=other,
                               progress=False, on_warning=seen.append)
    assert res.n_new == res.n_frames == 2
    assert res.empty == (("lab_run2", 0), ("lab_run2", 1)) and len(res.warnings) == 2 and seen == list(res.warnings)
    assert res.warnings[0].startswith("run lab_run2 frame 0: empty decoding: none of the 2,000 queries")
    index = json.loads((out / "index.json").read_text())
    assert index["empty_frames"] == [{"run": "lab_run2", "frame": 0}, {"run": "lab_run2", "frame": 1}]
    assert all(e["empty"] and e["n_points"] == 0 for e in index["frames"])
    with open(out / "generation.csv", newline="") as f:
        assert [r["empty"] for r in csv.DictReader(f)] == ["True", "True"]
    assert np.load(out / "lab_run2" / "000000.npy").shape == (0, 3)
    # a rerun keeps them and still lists them (no warning: nothing new)
    again = generate_predictions(_job(root, out), ae, dit, model_input=model_input, model=other, progress=False)
    assert again.empty == res.empty and again.warnings == () and again.n_new == 0 and again.seconds == {}


def test_a_generated_folder_exports_as_ply(whole, tmp_path):
    from radarpc.pipelines.export import export

    out = whole[0]
    res = export(out, tmp_path / "ply", progress=False)
    assert (res.fmt, res.n_frames, res.n_new) == ("ply", 2, 2)
    for name, raw in _files(out).items():
        pts = np.load(out / name)
        ply = (tmp_path / "ply" / name).with_suffix(".ply").read_bytes()
        # an independent parse: the ASCII header, then N rows of three little-endian float32
        head, body = ply.split(b"end_header\n", 1)
        lines = head.decode("ascii").splitlines()
        assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
        assert f"element vertex {len(pts)}" in lines and [ln for ln in lines if ln.startswith("property")] == [
            "property float x", "property float y", "property float z"]
        np.testing.assert_array_equal(np.frombuffer(body, dtype="<f4").reshape(-1, 3), pts)


class PerfectAutoencoder(torch.nn.Module):
    """A stand-in autoencoder that decodes exactly the occupancy stage 1 trains on: a query is occupied
    (logit +1, else -1) when its cell of ``grid`` is one of ``cells``, the cells holding the frames'
    LiDAR points in the model's frame (``voxelize_points(grid, data.model_frame(lidar))``, as
    radarpc.experiments.rald.task.AutoencoderFrames labels its queries)."""

    def __init__(self, grid, cells: torch.Tensor):
        super().__init__()
        self.grid, self.cells = grid, cells
        self.w = torch.nn.Parameter(torch.zeros(1))
        self.eval()

    def latent_tokens(self, z):
        return z

    def occupancy_logits(self, tokens, q):
        from radarpc.rald.frustum import cell_indices

        index, inside = cell_indices(self.grid, q.to(torch.float64), coords="normalized")
        return torch.where(inside & torch.isin(index, self.cells), 1.0, -1.0) + 0 * self.w


@pytest.mark.parametrize("data", [LidarData(), LidarData(max_range_m=15.8, mirror_azimuth=True)],
                         ids=["radarpc-frame", "official-frame"])
def test_clouds_land_on_the_lidar_truth_in_the_radar_frame(root, tmp_path, monkeypatch, data):
    # The model coordinates of the LiDAR are what stage 1 trains on (LidarData: the model's frame,
    # mirrored for the official checkpoints, then the grid's normalised polar coordinates). An
    # autoencoder that decodes exactly those occupied cells, with the guide points placed on the LiDAR
    # truth itself, must give clouds on the truth that evaluate-points scores them against: in the
    # radar frame, in metres. A cloud left in the model's frame lands on the mirror image.
    ds = ColoRadar(root, "test", cube_size=None)
    grid = data.grid(ds.fov)
    truth = [ds.lidar_points(i) for i in range(len(ds))]                       # (M, 3) radar frame, metres
    cells = torch.cat([voxelize_points(grid, data.model_frame(torch.from_numpy(t))).cells for t in truth]).unique()
    guides = iter(truth)
    monkeypatch.setattr(job_module, "guide_points", lambda *a, **kw: next(guides))   # called frame by frame, in order
    _, dit = _models()
    cfg = GenerationConfig(random_queries=100, guided_queries=4000, refine_queries=8000, chunk=4096, num_steps=2)
    out = tmp_path / "preds"
    generate_predictions(_job(root, out, generation=cfg), PerfectAutoencoder(grid, cells), dit,
                         model_input=model_input, grid=grid, mirror_azimuth=data.mirror_azimuth, model=MODEL,
                         progress=False)
    union = torch.from_numpy(np.concatenate(truth)).double()
    # two points of one cell are at most |dr| + r_max (da + de) apart (chord <= arc, angles in radians)
    dr, da, de = grid.cell
    bound = dr + grid.range_m[1] * math.radians(da + de)                      # 0.26 m
    for e, t in zip(json.loads((out / "index.json").read_text())["frames"], truth):
        pts = torch.from_numpy(np.load(out / e["file"])).double()
        in_grid = int(in_frustum(grid, data.model_frame(torch.from_numpy(t).double())).sum())
        assert len(pts) >= in_grid > 100                                        # every truth point is a guided query
        assert float(torch.cdist(pts, union).min(dim=1).values.max()) <= bound
        mirrored = pts * pts.new_tensor((1.0, -1.0, 1.0))
        assert float(torch.cdist(mirrored, union).min(dim=1).values.max()) > 10 * bound
