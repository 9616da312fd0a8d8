"""Simulated RADIal datasets: written to disk in the real layout, or generated on the fly.

Every frame is a pure function of ``(sensor, scene config, seed, sequence, index, device)``: the
scene of sequence ``q`` is drawn from ``numpy.random.default_rng([seed, q])`` and the thermal
noise of frame ``i`` from a ``torch.Generator`` on the synthesis device seeded with
:func:`frame_noise_seed` ``(seed, q, i)``. Hence :func:`write_radial_dataset` can resume an
interrupted run frame by frame, and :class:`SimulatedRADIal` returns, for the same seed on the
same device, bit-identical frames to what the reader :class:`radarpc.data.radial.RADIal` loads
from the written root.

Root layout: see :mod:`radarpc.data.radial_format`. ``sensor.json`` holds ``cfg.to_dict()`` plus
``seed``, ``n_sequences``, ``frames_per_sequence`` and ``radarpc_version``; ``scene.json`` holds
the :class:`radarpc.sim.scenes.SceneMix` (:meth:`SceneMix.to_dict`: the mix's weights and every
preset's :class:`radarpc.sim.road.RoadSceneConfig`). Both are written first; all their keys but ``radarpc_version`` (a
package upgrade does not change the frames) identify a partial run that may be resumed.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import torch
from PIL import Image
from tqdm import tqdm

from radarpc import __version__
from radarpc.data.radial import (
    SPLIT_CHOICES,
    LabelTable,
    RadialFrames,
    check_cube,
    load_freespace,
    load_rd,
    read_sensor_json,
    select_frames,
)
from radarpc.data.radial_format import (
    LABEL_COLUMNS,
    LASER_PCL_COLUMNS,
    camera_path,
    fft_path,
    freespace_path,
    laser_pcl_path,
    save_calibration,
    save_fft_npz,
    simulated_sequence_name,
)
from radarpc.data.radial_truth import SIM_FRAME_COLUMNS, SIM_FRAMES_FILE, SIM_VEHICLE_COLUMNS, SIM_VEHICLES_FILE
from radarpc.io import DataFileError, atomic_write, save_npy_atomic
from radarpc.runs import RunFolder
from radarpc.sensors.radial import Calibration, DDMARadarConfig
from radarpc.sim.radial_calibration import make_calibration
from radarpc.sim.radial_camera import IMAGE_SIZE, jpeg_bytes, render_camera
from radarpc.sim.radial_lidar import laser_scan
from radarpc.sim.radial_labels import frame_label_rows, freespace_mask, labelled_vehicles, reference_points
from radarpc.sim.rd import synthesize_rd
from radarpc.sim.road import KIND_NAMES, STATE_NAMES, RoadFrame, RoadScene, RoadSceneConfig
from radarpc.sim.scenes import DEFAULT_MIX, SceneMix

__all__ = [
    "CUBE_FORMATS",
    "SimulatedFrame",
    "RadialSimulator",
    "frame_noise_seed",
    "write_radial_dataset",
    "SimulatedRADIal",
]

def frame_noise_seed(seed: int, sequence: int, index: int) -> int:
    """63-bit seed of the noise generator of frame ``index`` of sequence ``sequence``."""
    s = np.random.SeedSequence([int(seed), int(sequence), int(index)]).generate_state(2, np.uint32)
    return (int(s[0]) << 31) ^ int(s[1])


@dataclass
class SimulatedFrame:
    """One simulated frame: what the writer puts on disk.

    Attributes
    ----------
    num_sample : int
    rd : Tensor complex64 ``(n_range, n_doppler, n_rx)`` on the simulator's device
    label_rows : list of tuple
        ``labels.csv`` rows in :data:`LABEL_COLUMNS` order.
    freespace : ndarray uint8 ``FREESPACE_SHAPE`` (255 = free)
    scene : RoadFrame
    """

    num_sample: int
    rd: torch.Tensor
    label_rows: list[tuple]
    freespace: np.ndarray
    scene: RoadFrame


class RadialSimulator:
    """Frames of a simulated RADIal run, addressed by ``(sequence, index)``.

    Parameters
    ----------
    cfg : DDMARadarConfig
    n_sequences, frames_per_sequence : int
    seed : int
    scenes : SceneMix, optional
        The scene presets and their shares (default :data:`radarpc.sim.scenes.DEFAULT_MIX`); each
        sequence gets one (:meth:`SceneMix.preset`).
    device : torch.device or str, optional
        Where the RD cube is synthesised (default CPU).
    """

    def __init__(self, cfg: DDMARadarConfig, n_sequences: int, frames_per_sequence: int, seed: int, *,
                 scenes: SceneMix | None = None,
                 device: torch.device | str | None = None) -> None:
        if int(n_sequences) < 1:
            raise ValueError(f"n_sequences must be >= 1, got {n_sequences}")
        if int(frames_per_sequence) < 1:
            raise ValueError(f"frames_per_sequence must be >= 1, got {frames_per_sequence}")
        if int(seed) < 0:
            raise ValueError(f"seed must be >= 0, got {seed}")
        self.cfg = cfg
        self.n_sequences, self.frames_per_sequence, self.seed = int(n_sequences), int(frames_per_sequence), int(seed)
        self.scenes = scenes if scenes is not None else DEFAULT_MIX
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self._scenes: dict[int, RoadScene] = {}

    @classmethod
    def from_root(cls, root: str | os.PathLike, device: torch.device | str | None = None) -> "RadialSimulator":
        """The simulator that wrote the root ``root`` (from its ``sensor.json`` and ``scene.json``),
        e.g. to regenerate the scene truth (scatterers and their owners) behind its frames.

        Raises
        ------
        DataFileError
            Either file is missing or unreadable, or ``sensor.json`` lacks the run keys (seed,
            sequences, frames per sequence) that a root written by the simulator holds.
        """
        root = Path(root)
        cfg, meta = read_sensor_json(root / "sensor.json")
        if None in (meta.seed, meta.n_sequences, meta.frames_per_sequence):
            raise DataFileError(root / "sensor.json", "lacks seed, n_sequences or frames_per_sequence: "
                                "not a root written by `radarpc simulate radial`")
        path = root / "scene.json"
        if not path.is_file():
            raise DataFileError(path, "scene mix is missing (a root written by `radarpc simulate radial` has one)")
        try:
            scenes = SceneMix.from_dict(json.loads(path.read_text(encoding="utf-8")), where=str(path))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise DataFileError(path, f"is not readable JSON ({e})") from e
        except ValueError as e:
            raise DataFileError(path, f"does not describe a scene mix ({e})") from e
        return cls(cfg, meta.n_sequences, meta.frames_per_sequence, meta.seed, scenes=scenes, device=device)

    @property
    def n_frames(self) -> int:
        return self.n_sequences * self.frames_per_sequence

    def locate(self, num_sample: int) -> tuple[int, int]:
        """``(sequence, index)`` of global frame ``num_sample``."""
        if not 0 <= int(num_sample) < self.n_frames:
            raise ValueError(f"numSample {num_sample} outside [0, {self.n_frames})")
        return divmod(int(num_sample), self.frames_per_sequence)

    def scene(self, sequence: int) -> RoadScene:
        """The road scene of ``sequence`` (kept for the few most recent sequences)."""
        if not 0 <= int(sequence) < self.n_sequences:
            raise ValueError(f"sequence {sequence} outside [0, {self.n_sequences})")
        q = int(sequence)
        if q not in self._scenes:
            if len(self._scenes) >= 4:
                self._scenes.pop(next(iter(self._scenes)))
            self._scenes[q] = RoadScene(self.preset(q), self.seed, q, self.frames_per_sequence,
                                        self.cfg.max_range_m)
        return self._scenes[q]

    def scene_frame(self, sequence: int, index: int) -> RoadFrame:
        """The scene (scatterers and objects) of frame ``index`` of ``sequence``."""
        if not 0 <= int(index) < self.frames_per_sequence:
            raise ValueError(f"frame index {index} outside [0, {self.frames_per_sequence})")
        scene = self.scene(sequence)
        return scene.frame(scene.frame_time(index))

    def label_rows(self, sequence: int, index: int, fr: RoadFrame | None = None) -> list[tuple]:
        """``labels.csv`` rows of a frame (from its scene frame ``fr`` if given)."""
        fr = fr if fr is not None else self.scene_frame(sequence, index)
        return frame_label_rows(self.cfg, fr, seed=self.seed, sequence=sequence, index=index,
                                frames_per_sequence=self.frames_per_sequence)

    def preset(self, sequence: int) -> RoadSceneConfig:
        """The scene preset of ``sequence`` (:meth:`radarpc.sim.scenes.SceneMix.preset`)."""
        return self.scenes.preset(self.seed, sequence)

    def frame_truth_row(self, sequence: int, index: int, fr: RoadFrame | None = None) -> tuple:
        """The ``sim_frames.csv`` row of a frame (:data:`radarpc.data.radial_truth.SIM_FRAME_COLUMNS`)."""
        fr = fr if fr is not None else self.scene_frame(sequence, index)
        return (int(sequence) * self.frames_per_sequence + int(index), simulated_sequence_name(self.seed, sequence),
                int(index), fr.scene, round(float(fr.ego_speed_mps), 4))

    def vehicle_truth_rows(self, sequence: int, index: int, fr: RoadFrame | None = None) -> list[tuple]:
        """The ``sim_vehicles.csv`` rows of a frame (:data:`radarpc.data.radial_truth.SIM_VEHICLE_COLUMNS`): one per label
        row of a vehicle, in the same order; none for a frame without vehicles."""
        fr = fr if fr is not None else self.scene_frame(sequence, index)
        num = int(sequence) * self.frames_per_sequence + int(index)
        veh = fr.vehicles
        ref = reference_points(veh)
        speed = veh.ground_speed_mps()
        out = []
        for v in labelled_vehicles(self.cfg, fr):
            x, y = float(ref[v, 0]), float(ref[v, 1])
            out.append((num, int(veh.ids[v]), KIND_NAMES[int(veh.kind[v])], STATE_NAMES[int(veh.state[v])],
                        round(float(speed[v]), 4), round(math.hypot(x, y), 4),
                        round(math.degrees(math.atan2(y, x)), 4)))
        return out

    def geometry(self, sequence: int, index: int) -> tuple[RoadFrame, list[tuple], np.ndarray]:
        """Scene frame, label rows and freespace mask of a frame (no RD synthesis: cheap)."""
        fr = self.scene_frame(sequence, index)
        return fr, self.label_rows(sequence, index, fr), freespace_mask(self.cfg, fr)

    def rd(self, sequence: int, index: int, fr: RoadFrame | None = None) -> torch.Tensor:
        """RD cube of a frame, complex64 ``cfg.rd_shape`` on :attr:`device`, noise included."""
        fr = fr if fr is not None else self.scene_frame(sequence, index)
        return synthesize_rd(self.cfg, fr.scatterers, generator=self.noise_generator(sequence, index),
                             device=self.device)

    def noise_generator(self, sequence: int, index: int) -> torch.Generator:
        """The noise generator of a frame, on the synthesis device."""
        return torch.Generator(device=self.device).manual_seed(frame_noise_seed(self.seed, sequence, index))

    def frame(self, sequence: int, index: int) -> SimulatedFrame:
        """Everything of frame ``index`` of ``sequence``."""
        fr, rows, fs = self.geometry(sequence, index)
        rd = self.rd(sequence, index, fr)
        return SimulatedFrame(num_sample=int(sequence) * self.frames_per_sequence + int(index),
                              rd=rd, label_rows=rows, freespace=fs, scene=fr)


# ---- on disk ------------------------------------------------------------------------------------
def _sensor_json(cfg: DDMARadarConfig, seed: int, n_sequences: int, frames_per_sequence: int) -> dict:
    d = cfg.to_dict()
    d.update(seed=int(seed), n_sequences=int(n_sequences), frames_per_sequence=int(frames_per_sequence),
             radarpc_version=__version__)
    return d


def _format_cell(v) -> str:
    # repr of a float is the shortest text that parses back to the same float64
    return repr(float(v)) if isinstance(v, float) else str(v)


def _csv(columns: tuple[str, ...], rows: list[tuple]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([_format_cell(v) for v in r])
    return buf.getvalue()


def _labels_csv(rows: list[tuple]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(LABEL_COLUMNS)
    for r in rows:
        w.writerow([_format_cell(v) for v in r])
    return buf.getvalue()


def _png_bytes(mask: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(mask, dtype=np.uint8)).save(buf, format="PNG")  # 2-D uint8 -> mode L
    return buf.getvalue()


def _fft_complete(path: Path, cfg: DDMARadarConfig) -> bool:
    # a frame is complete only if its cube loads and validates fully (shape, complex, finite):
    # a file damaged after its atomic write is regenerated
    try:
        load_rd(path, cfg, validate=True)
    except DataFileError:
        return False
    return True


def _png_complete(path: Path) -> bool:
    try:
        load_freespace(path, validate=True)                 # decodes; 512 x 900, values 0 / 255
    except DataFileError:
        return False
    return True


def _jpeg_complete(path: Path) -> bool:
    # decodes the whole image (a truncated file fails) and checks the release's size
    try:
        with Image.open(path) as im:
            im.load()
            return im.format == "JPEG" and im.mode == "RGB" and im.size == IMAGE_SIZE
    except (OSError, ValueError):
        return False


def _laser_complete(path: Path) -> bool:
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError):
        return False
    return a.ndim == 2 and a.shape[1] == len(LASER_PCL_COLUMNS) and a.dtype == np.float32 and bool(np.isfinite(a).all())


CUBE_FORMATS: tuple[str, ...] = ("npy", "npz")
"""``cube_format`` choices: ``radar_FFT/fft_*.npy`` (FFTRadNet's loader) or ``.npz`` holding ``arr_0``
(RADIal's ready-to-use release, read by its ``loader/dataset.py``)."""

# what the writer owns in the root: ``overwrite`` deletes these (and only these); radar_PCL is
# derived from the cubes (radarpc.pipelines.radial_pcl), so new cubes make it stale
_OUTPUTS = ("radar_FFT", "radar_Freespace", "labels.csv", "calibration.npz", "sensor.json", "scene.json",
            SIM_FRAMES_FILE, SIM_VEHICLES_FILE,
            "camera", "laser_PCL", "radar_PCL", "outputs.json")


def write_radial_dataset(out: str | os.PathLike, cfg: DDMARadarConfig, n_sequences: int,
                         frames_per_sequence: int, seed: int, *, overwrite: bool = False,
                         progress: bool = True, device: torch.device | str | None = None,
                         scenes: SceneMix | None = None,
                         on_finish: Callable[[int, int], None] | None = None,
                         cube_format: str = "npy", camera: bool = True, laser: bool = True) -> Path:
    """Write a simulated RADIal root (resumable, atomic per file).

    ``on_finish(written, kept)``, when given, is told how many frames were simulated now and how
    many were kept from an earlier, interrupted run.

    The root is a :class:`radarpc.runs.RunFolder` keyed by ``sensor.json`` and ``scene.json``:
    it is locked against a second concurrent writer, and the temp files a killed run left are
    removed when a rerun takes it.

    Parameters
    ----------
    out : path-like
        Root folder. Without ``overwrite``, a non-empty folder must be a partial run of the same
        sensor, seed, sizes and scene config (its ``sensor.json`` and ``scene.json`` match, the
        package version aside), which is then completed: a frame is kept only if its cube loads
        and validates fully (shape, complex, finite) and its PNG decodes as a valid mask; any
        other frame is regenerated. ``overwrite=True`` always starts over: it deletes the dataset
        files (``radar_FFT/``, ``radar_Freespace/``, ``camera/``, ``laser_PCL/``, ``radar_PCL/``,
        ``labels.csv``, ``calibration.npz``, ``sensor.json``, ``scene.json``, ``outputs.json``),
        even of a matching run.
    cfg : DDMARadarConfig
    n_sequences, frames_per_sequence, seed : int
    overwrite : bool
        Start over (see ``out``).
    progress : bool
        Show a tqdm progress bar.
    device : torch.device or str, optional
        Synthesis device (frames are reproducible per device).
    scenes : SceneMix, optional
        Scene presets and shares (default :data:`radarpc.sim.scenes.DEFAULT_MIX`).
    cube_format : {"npy", "npz"}
        :data:`CUBE_FORMATS`: ``radar_FFT/fft_*.npy``, or ``.npz`` (uncompressed, one array
        ``arr_0``, as RADIal's ready-to-use release).
    camera : bool
        Write ``camera/image_*.jpg`` (:func:`radarpc.sim.radial_camera.render_camera`); the
        ``x1_pix .. y2_pix`` label columns are filled either way.
    laser : bool
        Write ``laser_PCL/pcl_*.npy`` (:func:`radarpc.sim.radial_lidar.laser_scan`).

    These three are recorded in ``outputs.json``; a partial run is resumed only with the same.
    A kept frame also needs a camera image that decodes at 960 x 540 and a laser file of
    ``(N, 8)`` finite float32 (when written); a missing or damaged one is rendered again alone.

    Returns
    -------
    Path
        The root.

    Raises
    ------
    radarpc.runs.RunMismatchError
        (a ``FileExistsError``) ``out`` is not empty and is not a matching partial run, without
        ``overwrite``.
    radarpc.runs.OutputBusyError
        (a ``FileExistsError``) another process is writing ``out``.
    NotADirectoryError
        ``out`` is a file.
    """
    if cube_format not in CUBE_FORMATS:
        raise ValueError(f"cube_format must be one of {CUBE_FORMATS}, got {cube_format!r}")
    sim = RadialSimulator(cfg, n_sequences, frames_per_sequence, seed, scenes=scenes,
                          device=device)
    meta = _sensor_json(cfg, seed, n_sequences, frames_per_sequence)
    # the package version is recorded but does not change the frames: it does not block a resume
    manifests = {"sensor.json": meta, "scene.json": sim.scenes.to_dict(),
                 "outputs.json": {"cube_format": cube_format, "camera": bool(camera), "laser_PCL": bool(laser)}}
    run = RunFolder(out, manifests, what="dataset root", ignore_keys=("radarpc_version",), indent=2,
                    owned=_OUTPUTS)
    with run.start(overwrite=overwrite, resume=not overwrite, write_manifests=False):
        root = run.path
        for name, content in manifests.items():      # on resume too: a root names the version that completed it
            run.write_manifest(name, content)
        save_calibration(root / "calibration.npz", make_calibration(cfg))
        rows: list[tuple] = []
        truth_frames: list[tuple] = []
        truth_vehicles: list[tuple] = []
        written = 0
        with tqdm(total=sim.n_frames, desc=f"simulate {cfg.name}", unit="frame", disable=not progress) as bar:
            for q in range(sim.n_sequences):
                for i in range(sim.frames_per_sequence):
                    num = q * sim.frames_per_sequence + i
                    fr, frame_rows, fs = sim.geometry(q, i)
                    rows.extend(frame_rows)
                    truth_frames.append(sim.frame_truth_row(q, i, fr))
                    truth_vehicles.extend(sim.vehicle_truth_rows(q, i, fr))
                    fpath, ppath = fft_path(root, num, "." + cube_format), freespace_path(root, num)
                    wrote = False
                    if not (run.done(fpath, check=lambda p: _fft_complete(p, cfg))
                            and run.done(ppath, check=_png_complete)):
                        cube = sim.rd(q, i, fr).cpu().numpy()
                        if cube_format == "npz":
                            save_fft_npz(root, num, cube, compress=False)
                        else:
                            save_npy_atomic(fpath, cube)
                        with atomic_write(ppath, "wb") as f:
                            f.write(_png_bytes(fs))
                        wrote = True
                    cpath = camera_path(root, num)
                    if camera and not run.done(cpath, check=_jpeg_complete):
                        with atomic_write(cpath, "wb") as f:
                            f.write(jpeg_bytes(render_camera(fr, lane_width_m=sim.preset(q).lane_width_m)))
                        wrote = True
                    lpath = laser_pcl_path(root, num)
                    if laser and not run.done(lpath, check=_laser_complete):
                        save_npy_atomic(lpath, laser_scan(fr))
                        wrote = True
                    written += wrote
                    bar.update(1)
        with atomic_write(root / "labels.csv", "w") as f:
            f.write(_labels_csv(rows))
        with atomic_write(root / SIM_FRAMES_FILE, "w") as f:
            f.write(_csv(SIM_FRAME_COLUMNS, truth_frames))
        with atomic_write(root / SIM_VEHICLES_FILE, "w") as f:
            f.write(_csv(SIM_VEHICLE_COLUMNS, truth_vehicles))
    if on_finish is not None:
        on_finish(written, sim.n_frames - written)
    return root


# ---- on the fly ---------------------------------------------------------------------------------
class SimulatedRADIal(RadialFrames):
    """Simulated RADIal frames generated on the fly, interchangeable with the on-disk reader.

    The same public interface as :class:`radarpc.data.radial.RADIal` (both are
    :class:`radarpc.data.radial.RadialFrames`): ``cube(i)``, ``frame_ids``, ``sequences``,
    ``sensor``, ``calibration``, ``split``, ``labels``, ``frame_labels(i)``, ``index_of(n)``,
    and ``ds[i] = (rd, labels, freespace)``, with the frames chosen by the same
    :func:`radarpc.data.radial.select_frames`. For the same arguments on the same device it
    returns bit-identical items to ``RADIal`` on the root :func:`write_radial_dataset` writes.

    Parameters
    ----------
    cfg : DDMARadarConfig
    n_sequences, frames_per_sequence, seed : int
        The run (``seed`` is the simulator seed).
    split : {"train", "val", "test", "all"}
        As for ``RADIal``; an empty split raises ``ValueError``.
    device : torch.device or str, optional
        Synthesis device and device of the returned tensors (default CPU).
    scenes : SceneMix, optional
        Scene presets and shares (default :data:`radarpc.sim.scenes.DEFAULT_MIX`).
    difficult, skip, random_split :
        As for ``RADIal``.
    split_seed : int
        Seed of ``random_split`` (``RADIal``'s ``seed`` argument).

    Notes
    -----
    The label rows of every frame of the run are computed at construction (scene geometry
    only, a few ms a frame), since the split, ``difficult`` and ``random_split`` rules need
    them; cubes and freespace masks are generated per item.
    """

    def __init__(self, cfg: DDMARadarConfig, n_sequences: int, frames_per_sequence: int, seed: int,
                 split: str = "train", device: torch.device | str | None = None, *,
                 scenes: SceneMix | None = None, difficult: bool = True,
                 skip: Iterable[int] | str | os.PathLike | None = None,
                 random_split: tuple[float, float, float] | None = None,
                 split_seed: int = 0) -> None:
        if split not in SPLIT_CHOICES:
            raise ValueError(f"split must be one of {SPLIT_CHOICES}, got {split!r}")
        self.sim = RadialSimulator(cfg, n_sequences, frames_per_sequence, seed,
                                   scenes=scenes, device=device)
        self.split = split
        self.sensor = cfg
        self.difficult = bool(difficult)
        self.device = self.sim.device
        rows = [r for q in range(self.sim.n_sequences) for i in range(self.sim.frames_per_sequence)
                for r in self.sim.label_rows(q, i)]
        self.labels = LabelTable.from_rows(rows, path=f"<simulated {cfg.name} seed {seed}>")
        self._set_selection(select_frames(
            self.labels, split, difficult=self.difficult, skip=skip, random_split=random_split,
            seed=split_seed, n_sequences=self.sim.n_sequences, source=repr(self)))
        self._calibration: Calibration | None = None
        self._last: tuple[int, RoadFrame] | None = None        # scene frame of the last item

    @property
    def calibration(self) -> Calibration:
        """The sensor's calibration table (what ``calibration.npz`` holds)."""
        if self._calibration is None:
            self._calibration = make_calibration(self.sensor)
        return self._calibration

    def _scene_frame(self, i: int) -> tuple[int, int, RoadFrame]:
        num = self.frame_ids[self._index(i)]
        q, k = self.sim.locate(num)
        if self._last is None or self._last[0] != num:
            self._last = (num, self.sim.scene_frame(q, k))
        return q, k, self._last[1]

    def cube(self, i: int) -> torch.Tensor:
        """RD cube of item ``i``, synthesised on :attr:`device` (complex64, validated)."""
        q, k, fr = self._scene_frame(i)
        return check_cube(self.sim.rd(q, k, fr), self.sensor,
                          f"simulated frame {self.frame_ids[self._index(i)]}")

    def freespace_mask(self, i: int) -> np.ndarray:
        """Freespace mask of item ``i`` from the scene geometry, uint8 512 x 900."""
        _, _, fr = self._scene_frame(i)
        return freespace_mask(self.sensor, fr)

    def __repr__(self) -> str:
        n = len(self.frame_ids) if hasattr(self, "frame_ids") else "?"
        return (f"SimulatedRADIal(sensor={self.sensor.name!r}, split={self.split!r}, frames={n}, "
                f"seed={self.sim.seed}, {self.sim.n_sequences} x {self.sim.frames_per_sequence})")
