"""The RaLD user path through the command line: `radarpc generate` with a run trained by `radarpc train`
(one readable cloud per frame, the run's own input, resume after a rerun and after a kill), with a
stage-1 run (the autoencoder's reconstruction: its training's input, resume after a kill, the
options of the other stage refused), the clouds scored beside OS-CFAR's by `radarpc evaluate-points`, `radarpc import-rald` of official-layout
checkpoints (a run `load_rald` loads with the official weights, that `generate` runs) and the
refusals, each one line."""
from __future__ import annotations

import csv
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from radarpc.cli import main
from radarpc.data.coloradar import ColoRadar
from radarpc.experiments.rald.config import LidarData
from radarpc.experiments.rald.official import OFFICIAL_LIDAR_DATA, read_official_rald
from radarpc.experiments.rald.runs import load_rald
from radarpc.experiments.rald.task import DiffusionFrames
from radarpc.models import build_model
from radarpc.pipelines import rald_generate as job_module
from radarpc.pipelines import rald_reconstruct as recon_module
from raldkit import ae_official_state, dit_official_state, save_official

# tiny generation settings: a few hundred queries, two Heun steps, OS-CFAR guide points
QUICK = ["--random-queries", "400", "--guided-queries", "300", "--refine-queries", "900", "--steps", "2",
         "--chunk", "256", "--guide", "os-cfar", "--no-progress"]


QUICK_AE = [a for a in QUICK if a not in ("--steps", "2")]          # a stage-1 run has no sampler


def _generate(run, root, out, *extra) -> int:
    return main(["generate", str(run), "--data", str(root), "--split", "test", "--out", str(out), *QUICK,
                 *map(str, extra)])


def _reconstruct(run, root, out, *extra) -> int:
    return main(["generate", str(run), "--data", str(root), "--split", "test", "--out", str(out), *QUICK_AE,
                 *map(str, extra)])


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.glob("*/*.npy"))}


@pytest.fixture(scope="module")
def generated(rald_run, colo_root, tmp_path_factory) -> tuple[Path, str]:
    """``(folder, stdout)`` of `radarpc generate` with the session's tiny stage-2 run on the test split
    (read-only for the tests: copy it to change it)."""
    import contextlib
    import io

    out = tmp_path_factory.mktemp("rald_gen") / "preds"
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        assert _generate(rald_run, colo_root, out) == 0
    return out, text.getvalue()


def test_generate_writes_one_cloud_per_frame_from_the_runs_own_input(generated, rald_run, colo_root):
    out, stdout = generated
    ds = ColoRadar(colo_root, "test", cube_size=None)
    index = json.loads((out / "index.json").read_text())
    assert [(e["run"], e["frame"]) for e in index["frames"]] == [(ds.runs[k].name, ri) for k, ri, _ in ds.index]
    with open(out / "generation.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(ds) == 2
    for e, row in zip(index["frames"], rows):
        pts = np.load(out / e["file"], allow_pickle=False)
        assert pts.dtype == np.float32 and pts.shape == (e["n_points"], 3) and int(row["n_points"]) == e["n_points"]
        assert int(row["queries_random"]) == 400 and int(row["queries_guided"]) <= 300
    # the key names the run (resolved) and the SHA-256 of its weights, the grid and frame of its autoencoder
    key = json.loads((out / "generation.json").read_text())
    best = rald_run / "best.safetensors"
    assert key["model"] == {"run": str(rald_run.resolve()),
                            "weights": {"best.safetensors": hashlib.sha256(best.read_bytes()).hexdigest()}}
    assert key["grid"]["kind"] == "frustum" and key["grid"]["hi"][0] == pytest.approx(15.9)
    assert key["mirror_azimuth"] is False and key["root"] == str(colo_root.resolve()) and key["split"] == "test"
    assert key["generation"]["num_steps"] == 2 and key["guide"]["source"] == "os-cfar"
    lines = stdout.splitlines()
    assert lines[-2].startswith("seconds per frame (2 new frames): condition ")
    assert all(s in lines[-2] for s in ("sampler", "decoding", "refinement"))
    assert lines[-1].startswith("wrote 2 new point clouds (2 frames") and lines[-1].endswith(str(out))

    # what the model read is what its training read: DiffusionFrames' radar item of the same frame
    from radarpc.experiments.rald.generation import model_input

    run = load_rald(rald_run)
    frames = DiffusionFrames(colo_root, "test", run.ae_config.data, run.dit.cfg.radar_shape,
                             run.config.radar.max_intensity_db, training=False)
    for i in range(len(ds)):
        assert torch.equal(model_input(run)(ds.cube(i)), frames[i][0])


def test_a_rerun_keeps_every_frame(generated, rald_run, colo_root, tmp_path, capsys):
    out = tmp_path / "preds"
    shutil.copytree(generated[0], out)
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*.npy")}
    assert _generate(rald_run, colo_root, out) == 0
    assert capsys.readouterr().out.splitlines()[-1] == f"wrote 0 new point clouds (2 frames) to {out}"
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*.npy")} == before
    assert _files(out) == _files(generated[0])
    # the run moved (the same weights elsewhere): still this folder's model, its new place recorded
    moved = tmp_path / "moved" / "run"
    shutil.copytree(rald_run, moved)
    assert _generate(moved, colo_root, out) == 0
    assert capsys.readouterr().out.splitlines()[-1] == f"wrote 0 new point clouds (2 frames) to {out}"
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*.npy")} == before
    key = json.loads((out / "generation.json").read_text())
    assert key["model"]["run"] == str(moved.resolve()) and key["model"]["weights"] == json.loads(
        (generated[0] / "generation.json").read_text())["model"]["weights"]


def test_a_killed_generation_resumes_to_the_same_files(generated, rald_run, colo_root, tmp_path, monkeypatch,
                                                       capsys):
    out = tmp_path / "killed"
    real, calls = job_module.generate_cloud, []

    def killed_on_the_second(*a, **kw):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **kw)

    monkeypatch.setattr(job_module, "generate_cloud", killed_on_the_second)
    assert _generate(rald_run, colo_root, out) == 130
    assert "interrupted; finished work is kept, run the same command again to resume" in capsys.readouterr().err
    monkeypatch.undo()
    assert len(_files(out)) == 1
    assert _generate(rald_run, colo_root, out) == 0
    assert "wrote 1 new point cloud (2 frames" in capsys.readouterr().out
    assert _files(out) == _files(generated[0])
    assert (json.loads((out / "index.json").read_text())["frames"]
            == json.loads((generated[0] / "index.json").read_text())["frames"])


def test_every_generates_and_predicts_a_subset(generated, rald_run, colo_root, tmp_path, capsys):
    # the test run's two paired frames: --every 2 keeps the first, the same file the full job wrote
    out = tmp_path / "every2"
    assert _generate(rald_run, colo_root, out, "--every", "2") == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith("wrote 1 new point cloud (1 frame")
    first = json.loads((generated[0] / "index.json").read_text())["frames"][0]
    index = json.loads((out / "index.json").read_text())
    assert index["every"] == 2 and [e["file"] for e in index["frames"]] == [first["file"]]
    assert (out / first["file"]).read_bytes() == (generated[0] / first["file"]).read_bytes()
    assert json.loads((out / "generation.json").read_text())["every"] == 2
    # another subset into the same folder is another job: refused without --overwrite
    assert _generate(rald_run, colo_root, out) == 2
    capsys.readouterr()
    oscfar = tmp_path / "oscfar"
    assert main(["baseline", "os-cfar", str(colo_root), "--split", "test", "--every", "2", "--out", str(oscfar),
                 "--quick-tune", "--max-tune-frames", "2"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == f"wrote 1 new point cloud (1 frame) to {oscfar}"
    index = json.loads((oscfar / "index.json").read_text())
    assert index["every"] == 2 and [e["file"] for e in index["frames"]] == [first["file"]]
    # another subset into the folder would leave clouds the index does not list: refused, naming it
    assert main(["baseline", "os-cfar", str(colo_root), "--split", "test", "--out", str(oscfar), "--quick-tune",
                 "--max-tune-frames", "2"]) != 0
    assert "(split test, every 2), not of" in capsys.readouterr().err
    # a bad K is refused by the parser, before any model or frame is read
    for cmd in (["generate", str(rald_run), "--out", str(tmp_path / "x")],
                ["baseline", "os-cfar", str(colo_root), "--out", str(tmp_path / "y")]):
        with pytest.raises(SystemExit) as e:
            main([*cmd, "--every", "0"])
        assert e.value.code == 2
        assert "--every: expected a positive integer (1: every frame), got '0'" in capsys.readouterr().err


@pytest.fixture(scope="module")
def reconstructed(rald_ae_run, colo_root, tmp_path_factory) -> tuple[Path, str, str]:
    """``(folder, stdout, stderr)`` of `radarpc generate` with the session's tiny stage-1 run on the test
    split: the autoencoder's reconstruction (read-only for the tests)."""
    import contextlib
    import io

    out = tmp_path_factory.mktemp("rald_ae_rec") / "preds"
    text, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(text), contextlib.redirect_stderr(err):
        assert _reconstruct(rald_ae_run, colo_root, out) == 0
    return out, text.getvalue(), err.getvalue()


def test_generate_with_a_stage_1_run_reconstructs_each_frames_lidar(reconstructed, rald_ae_run, colo_root):
    from radarpc.experiments.rald.generation import encoder_input
    from radarpc.experiments.rald.runs import load_rald_ae
    from radarpc.experiments.rald.task import AutoencoderFrames
    from radarpc.rald.generate import frame_seed
    from radarpc.rald.reconstruct import points_generator

    out, stdout, stderr = reconstructed
    ds = ColoRadar(colo_root, "test", cube_size=None)
    index = json.loads((out / "index.json").read_text())
    assert index["method"] == "rald-ae" and index["kind"] == "reconstruction"
    assert [(e["run"], e["frame"]) for e in index["frames"]] == [(ds.runs[k].name, ri) for k, ri, _ in ds.index]
    with open(out / "generation.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    for e, row in zip(index["frames"], rows):
        pts = np.load(out / e["file"], allow_pickle=False)
        assert pts.dtype == np.float32 and pts.shape == (e["n_points"], 3) and int(row["n_points"]) == e["n_points"]
        assert int(row["queries_random"]) == 400 and "seconds_encoding" in row and "seconds_sampler" not in row
        assert row["empty"] == str(e["n_points"] == 0) == str(e["empty"])
    key = json.loads((out / "generation.json").read_text())
    best = rald_ae_run / "best.safetensors"
    assert key["model"] == {"run": str(rald_ae_run.resolve()),
                            "weights": {"best.safetensors": hashlib.sha256(best.read_bytes()).hexdigest()}}
    assert key["reconstruction"] == {"posterior": "sample"} and "num_steps" not in key["generation"]
    assert key["grid"]["kind"] == "frustum" and key["mirror_azimuth"] is False
    lines = stdout.splitlines()
    assert lines[-2].startswith("seconds per frame (2 new frames): encoding ")
    assert lines[-1].startswith("wrote 2 new point clouds (2 frames") and lines[-1].endswith(str(out))
    err = stderr.splitlines()
    assert err[0] == (f"{rald_ae_run}: a stage-1 run: each frame's LiDAR is encoded and decoded by the "
                      f"autoencoder (a reconstruction, posterior sample), not generated from the radar")
    # the 4-step autoencoder decodes nothing occupied yet: its empty clouds are flagged as a generation's
    empty = [{"run": e["run"], "frame": e["frame"]} for e in index["frames"] if e["empty"]]
    assert index["empty_frames"] == empty and len(err) == 1 + len(empty)
    assert all(line.startswith("warning: run lab_run2 frame ") and "empty decoding" in line for line in err[1:])
    # what the encoder read is what its training reads: AutoencoderFrames' points (its item's first
    # draws) when its generator is the frame's (points_generator of the frame's seed)
    run = load_rald_ae(rald_ae_run)
    frames = AutoencoderFrames(colo_root, "test", run.config.data, training=False)
    for i, (k, ri, _) in enumerate(ds.index):
        seed = frame_seed(0, ds.runs[k].name, ri)
        frames._rng = lambda _, seed=seed: points_generator(seed)          # the item's generator, replaced
        assert torch.equal(encoder_input(run)(ds.lidar_points(i), points_generator(seed)), frames[i][0])


def test_a_killed_reconstruction_resumes_to_the_same_files(reconstructed, rald_ae_run, colo_root, tmp_path,
                                                           monkeypatch, capsys):
    out = tmp_path / "killed"
    real, calls = recon_module.reconstruct_cloud, []

    def killed_on_the_second(*a, **kw):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **kw)

    monkeypatch.setattr(recon_module, "reconstruct_cloud", killed_on_the_second)
    assert _reconstruct(rald_ae_run, colo_root, out) == 130
    assert "interrupted; finished work is kept, run the same command again to resume" in capsys.readouterr().err
    monkeypatch.undo()
    assert len(_files(out)) == 1
    assert _reconstruct(rald_ae_run, colo_root, out) == 0
    assert "wrote 1 new point cloud (2 frames" in capsys.readouterr().out
    assert _files(out) == _files(reconstructed[0])


def test_generated_and_oscfar_clouds_side_by_side(generated, imported, colo_root, tmp_path, capsys):
    gen, rec = tmp_path / "rald", tmp_path / "rald-ae"
    shutil.copytree(generated[0], gen)
    # the reconstruction of an imported autoencoder (OUT/ae: a stage-1 run in the official frame)
    assert _reconstruct(imported / "ae", colo_root, rec) == 0
    assert json.loads((rec / "generation.json").read_text())["mirror_azimuth"] is True
    oscfar = tmp_path / "oscfar"
    assert main(["baseline", "os-cfar", str(colo_root), "--split", "test", "--out", str(oscfar), "--quick-tune",
                 "--max-tune-frames", "2"]) == 0
    capsys.readouterr()
    assert main(["evaluate-points", str(gen), str(rec), str(oscfar), "--data", str(colo_root), "--split", "test",
                 "--emd-points", "64", "--out", str(tmp_path / "cmp")]) == 0
    stdout = capsys.readouterr().out
    assert "## side by side" in stdout
    cmp = json.dumps(json.loads((tmp_path / "cmp" / "comparison.json").read_text()))
    assert '"rald"' in cmp and '"rald-ae"' in cmp and '"os-cfar"' in cmp
    for folder in (gen, rec, oscfar):
        metrics = json.loads((folder / "metrics.json").read_text())
        assert len(metrics["frames"]) == 2


# ---- the official weights -----------------------------------------------------------------------

@pytest.fixture(scope="module")
def official_files(tmp_path_factory) -> tuple[Path, Path, dict]:
    """Official-layout checkpoints of tiny radarpc models (8 heads, as every official factory builds):
    the autoencoder's with EMA weights (half its weights), the generation model's without."""
    folder = tmp_path_factory.mktemp("official")
    torch.manual_seed(0)
    ae = build_model("rald-ae-tiny", {"n_latents": 16, "latent_dim": 4, "heads": 8, "head_dim": 8}).eval()
    dit = build_model("rald-dit-tiny", {"heads": 8, "enc_channels": 32, "enc_groups": 32, "enc_ch_mult": (1, 1),
                                        "radar_shape": (8, 8, 4)}).eval()
    with torch.no_grad():
        dit.denoiser.proj_out.weight.normal_(std=0.05)
    ae_off = ae_official_state(ae)
    ema = {k: v if k == "point_embed.basis" else 0.5 * v for k, v in ae_off.items()}   # the basis is a buffer
    ae_path = save_official(folder / "ae.pth", ae_off, ema=ema)
    gen_path = save_official(folder / "gen.pth", dit_official_state(dit))
    return ae_path, gen_path, {"ae": ae.state_dict(), "dit": dit.state_dict()}


@pytest.fixture(scope="module")
def imported(official_files, tmp_path_factory) -> Path:
    """`radarpc import-rald` of :func:`official_files` (read-only for the tests)."""
    ae_path, gen_path, _ = official_files
    out = tmp_path_factory.mktemp("imported") / "rald-official"
    assert main(["import-rald", str(ae_path), str(gen_path), "--out", str(out)]) == 0
    return out


def test_import_rald_writes_a_run_with_the_official_weights(official_files, imported, capsys):
    ae_path, gen_path, models = official_files
    run = load_rald(imported)
    official = read_official_rald(ae_path, gen_path)
    assert run.finished is None and run.ae_status == "same" and run.ae_dir == imported / "ae"
    for mine, theirs in ((run.ae.state_dict(), official.ae_state), (run.dit.state_dict(), official.dit_state)):
        assert mine.keys() == theirs.keys() and all(torch.equal(mine[k], theirs[k]) for k in mine)
    # EMA where the file has it (the autoencoder: half the weights), the model's where not
    assert torch.equal(run.ae.state_dict()["to_logit.weight"], 0.5 * models["ae"]["to_logit.weight"])
    assert torch.equal(run.dit.state_dict()["denoiser.proj_out.weight"], models["dit"]["denoiser.proj_out.weight"])
    # the official data: range normalised to 15.8 m, azimuth right positive
    assert run.ae_config.data == OFFICIAL_LIDAR_DATA == LidarData(max_range_m=15.8, mirror_azimuth=True)
    assert run.grid.range_m == (0.0, 15.8) and run.grid.shape == (316, 720, 80)
    assert run.config.model.variant == "rald-dit" and run.ae_config.model.variant == "rald-ae"
    # provenance in both keys
    key = json.loads((imported / "run.json").read_text())
    assert key["data"] is None and key["ae"]["path"] == "ae"
    for stage, path, weights in (("autoencoder", ae_path, "model_ema"), ("diffusion", gen_path, "model")):
        rec = key["imported"][stage]
        assert rec["file"] == str(path.resolve()) and rec["weights"] == weights and rec["epoch"] == 99
        assert rec["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert key["imported"]["weights"] == "ema"
    assert json.loads((imported / "ae" / "run.json").read_text())["imported"]["autoencoder"] == key["imported"]["autoencoder"]
    for name in ("config.yaml", "ae/config.yaml"):
        assert (imported / name).is_file()


def test_import_rald_model_weights_rerun_and_refusals(official_files, imported, colo_root, tmp_path, capsys):
    ae_path, gen_path, models = official_files
    out = tmp_path / "imp"
    argv = ["import-rald", str(ae_path), str(gen_path), "--out", str(out), "--data", str(colo_root)]
    assert main(argv + ["--weights", "model"]) == 0
    assert "autoencoder model, diffusion model" in capsys.readouterr().out
    run = load_rald(out)
    assert torch.equal(run.ae.state_dict()["to_logit.weight"], models["ae"]["to_logit.weight"])
    assert run.key["data"] == str(colo_root.resolve())
    assert main(argv + ["--weights", "model"]) == 0                     # the same import again: rewritten
    assert main(argv) == 2                                               # another one into it: refused
    err = capsys.readouterr().err
    assert "does not hold a run with these settings" in err and "--overwrite" in err and len(err.splitlines()) == 1
    assert main(argv + ["--overwrite"]) == 0
    assert load_rald(out).key["imported"]["weights"] == "ema"
    # the stage files swapped, or not a checkpoint at all: the reader's refusal, one line
    bad = tmp_path / "bad.pth"
    bad.write_bytes(b"not a checkpoint")
    for a, b in ((gen_path, ae_path), (bad, gen_path)):
        assert main(["import-rald", str(a), str(b), "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("radarpc import-rald: error: ") and str(a) in err and len(err.splitlines()) == 1
    assert not (tmp_path / "x").exists()
    assert main(["import-rald", str(ae_path), str(gen_path), "--out", str(tmp_path / "y"), "--data",
                 str(tmp_path)]) == 2
    assert not (tmp_path / "y").exists()


def test_generate_runs_an_imported_run_in_its_official_frame(imported, colo_root, tmp_path, capsys):
    out = tmp_path / "official"
    assert _generate(imported, colo_root, out) == 0
    key = json.loads((out / "generation.json").read_text())
    assert key["mirror_azimuth"] is True and key["grid"]["hi"][0] == pytest.approx(15.8)
    assert len(json.loads((out / "index.json").read_text())["frames"]) == 2
    # without --data: the import names no root
    assert main(["generate", str(imported), "--out", str(tmp_path / "nodata"), *QUICK]) == 2
    assert "the run names no ColoRadar root (an import without --data); give --data ROOT" in capsys.readouterr().err


def test_generate_refusals(rald_run, rald_ae_run, colo_root, generated, tmp_path, capsys, monkeypatch):
    cases = [
        ((tmp_path / "none", colo_root, tmp_path / "a"), f"{tmp_path / 'none'}: no RaLD training run here"),
        ((rald_ae_run, colo_root, tmp_path / "b", "--steps", "18"),                     # even the default
         f"{rald_ae_run}: a stage-1 (autoencoder) run reconstructs the LiDAR without the diffusion sampler; "
         f"generation.num_steps (--steps) applies to a stage-2 run only"),
        ((rald_run, colo_root, tmp_path / "g", "--posterior", "mean"),
         f"{rald_run}: a stage-2 (diffusion) run generates from the radar; reconstruction.posterior (--posterior) "
         f"applies to a stage-1 (autoencoder) run only"),
        ((tmp_path / "detection", colo_root, tmp_path / "h"), "a detection training run, not a RaLD one"),
        ((rald_run, colo_root, tmp_path / "c", "--steps", "1"), "GenerationConfig.num_steps must be >= 2, got 1"),
        ((rald_run, tmp_path, tmp_path / "d"), str(tmp_path)),
    ]
    (tmp_path / "detection").mkdir()
    (tmp_path / "detection" / "run.json").write_text('{"experiment": {"name": "fftradnet"}}')
    bad_yaml = tmp_path / "gen.yaml"
    bad_yaml.write_text("generation: {random_queries: 10, queries: 5}\n")
    cases.append(((rald_run, colo_root, tmp_path / "e", "--config", bad_yaml), str(bad_yaml)))
    sampler_yaml = tmp_path / "sampler.yaml"
    sampler_yaml.write_text("generation: {sigma_max: 40.0, rho: 5.0}\n")
    cases.append(((rald_ae_run, colo_root, tmp_path / "i", "--config", sampler_yaml),
                  "generation.sigma_max, generation.rho apply to a stage-2 run only"))
    for argv, message in cases:
        assert (_reconstruct if argv[0] == rald_ae_run else _generate)(*argv) == 2, message
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not any((tmp_path / n).exists() for n in "abcdeghi")
    # other settings into a generated folder (a config file's, the options applied over it): refused,
    # nothing changed
    out = tmp_path / "preds"
    shutil.copytree(generated[0], out)
    config = tmp_path / "seed1.yaml"
    config.write_text("generation: {seed: 1, num_steps: 7}\nguide: {source: peaks}\n")
    assert _generate(rald_run, colo_root, out, "--config", config) == 2
    err = capsys.readouterr().err
    assert "differs in generation.json:generation.seed" in err and "num_steps" not in err and "guide" not in err
    assert _files(out) == _files(generated[0])

    # an unfinished run: refused, or generated with its best weights so far and a notice; a stage-1
    # folder changed since: a notice (the autoencoder stored with the run generates)
    from radarpc.experiments.rald import generation

    real = generation.load_rald

    def unfinished(run_dir, **kw):
        run = real(run_dir, **kw)
        return type(run)(**{**vars(run), "status": {**run.status, "finished": False, "steps_done": 3},
                            "ae_status": "changed"})

    monkeypatch.setattr(generation, "load_rald", unfinished)
    assert _generate(rald_run, colo_root, tmp_path / "f") == 2
    assert "the diffusion run has not finished (step 3, best weights of step" in capsys.readouterr().err
    assert not (tmp_path / "f").exists()
    assert _generate(rald_run, colo_root, out, "--allow-unfinished") == 0          # the same clouds: all kept
    err = capsys.readouterr().err.splitlines()
    assert err[0].endswith("generating with its best weights so far")
    assert err[1] == (f"{rald_run}: its stage-1 folder {rald_ae_run} holds another run or other weights now; the "
                      f"autoencoder stored with the run (the one the diffusion model was trained on) is used")
    assert _files(out) == _files(generated[0])


def test_empty_decodings_are_reported(rald_run, colo_root, tmp_path, monkeypatch, capsys):
    from radarpc.rald.generate import STAGES, GeneratedCloud

    def nothing_occupied(ae, dit, cube, guide, cfg, seed, **kw):
        return GeneratedCloud(np.zeros((0, 3), np.float32), {s: 0.0 for s in STAGES},
                              {"random": cfg.random_queries, "guided": 0, "refinement": 0}, seed=seed)

    monkeypatch.setattr(job_module, "generate_cloud", nothing_occupied)
    out = tmp_path / "empty"
    assert _generate(rald_run, colo_root, out) == 0
    captured = capsys.readouterr()
    assert captured.out.splitlines()[-1] == f"wrote 2 new point clouds (2 frames, 2 empty) to {out}"
    warnings = captured.err.splitlines()
    assert len(warnings) == 2 and warnings[0].startswith("warning: run lab_run2 frame 0: empty decoding: none of the "
                                                         "400 queries decoded as occupied")
    assert [np.load(p).shape for p in sorted(out.glob("*/*.npy"))] == [(0, 3), (0, 3)]
