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
the :class:`RoadSceneConfig`. Both are written first and identify a partial run that may be
resumed.
"""
from __future__ import annotations

import csv
import dataclasses
import io
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from tqdm import tqdm

from radarpc import __version__
from radarpc.data.radial import freespace_to_model
from radarpc.data.radial_format import (
    FREESPACE_SHAPE,
    LABEL_COLUMNS,
    LABEL_TENSOR_COLUMNS,
    fft_path,
    freespace_path,
    simulated_sequence_name,
    simulated_split,
)
from radarpc.io import atomic_write, save_npy_atomic
from radarpc.sensors.radial import Calibration, DDMARadarConfig, make_calibration, save_calibration
from radarpc.sim.radial_labels import frame_label_rows, freespace_mask
from radarpc.sim.rd import synthesize_rd
from radarpc.sim.road import RoadFrame, RoadScene, RoadSceneConfig

__all__ = [
    "SimulatedFrame",
    "RadialSimulator",
    "frame_noise_seed",
    "write_radial_dataset",
    "SimulatedRADIal",
]

_SPLITS = ("train", "val", "test", "all")
# a row is a vehicle unless all of these are -1 (RADIal's row for a frame without vehicles)
_EMPTY_MARKER_COLUMNS = ("laser_X_m", "laser_Y_m", "laser_Z_m", "radar_X_m", "radar_Y_m",
                         "radar_R_m", "radar_A_deg", "radar_D", "radar_P_db")


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
    scene_config : RoadSceneConfig, optional
    device : torch.device or str, optional
        Where the RD cube is synthesised (default CPU).
    """

    def __init__(self, cfg: DDMARadarConfig, n_sequences: int, frames_per_sequence: int, seed: int, *,
                 scene_config: RoadSceneConfig | None = None,
                 device: torch.device | str | None = None) -> None:
        if int(n_sequences) < 1:
            raise ValueError(f"n_sequences must be >= 1, got {n_sequences}")
        if int(frames_per_sequence) < 1:
            raise ValueError(f"frames_per_sequence must be >= 1, got {frames_per_sequence}")
        if int(seed) < 0:
            raise ValueError(f"seed must be >= 0, got {seed}")
        self.cfg = cfg
        self.n_sequences, self.frames_per_sequence, self.seed = int(n_sequences), int(frames_per_sequence), int(seed)
        self.scene_config = scene_config if scene_config is not None else RoadSceneConfig()
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self._scenes: dict[int, RoadScene] = {}

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
            self._scenes[q] = RoadScene(self.scene_config, self.seed, q, self.frames_per_sequence,
                                        self.cfg.max_range_m)
        return self._scenes[q]

    def geometry(self, sequence: int, index: int) -> tuple[RoadFrame, list[tuple], np.ndarray]:
        """Scene frame, label rows and freespace mask of a frame (no RD synthesis: cheap)."""
        if not 0 <= int(index) < self.frames_per_sequence:
            raise ValueError(f"frame index {index} outside [0, {self.frames_per_sequence})")
        scene = self.scene(sequence)
        fr = scene.frame(scene.frame_time(index))
        rows = frame_label_rows(self.cfg, fr, seed=self.seed, sequence=sequence, index=index,
                                frames_per_sequence=self.frames_per_sequence)
        return fr, rows, freespace_mask(self.cfg, fr)

    def noise_generator(self, sequence: int, index: int) -> torch.Generator:
        """The noise generator of a frame, on the synthesis device."""
        return torch.Generator(device=self.device).manual_seed(frame_noise_seed(self.seed, sequence, index))

    def frame(self, sequence: int, index: int) -> SimulatedFrame:
        """Everything of frame ``index`` of ``sequence``."""
        fr, rows, fs = self.geometry(sequence, index)
        rd = synthesize_rd(self.cfg, fr.scatterers, generator=self.noise_generator(sequence, index),
                           device=self.device)
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
    # writes are atomic, so a file under its final name is whole unless damaged afterwards:
    # check the header (shape, dtype) and the size without reading the data.
    if not path.is_file():
        return False
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError):
        return False
    ok = arr.shape == cfg.rd_shape and arr.dtype == np.complex64
    del arr
    return ok


def _png_complete(path: Path) -> bool:
    if not path.is_file():
        return False
    try:
        with Image.open(path) as im:
            im.load()
            return im.size == (FREESPACE_SHAPE[1], FREESPACE_SHAPE[0]) and im.mode == "L"
    except (OSError, ValueError, SyntaxError):
        return False


_OUTPUTS = ("radar_FFT", "radar_Freespace", "labels.csv", "calibration.npz", "sensor.json", "scene.json")


def _read_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None


def write_radial_dataset(out: str | os.PathLike, cfg: DDMARadarConfig, n_sequences: int,
                         frames_per_sequence: int, seed: int, *, overwrite: bool = False,
                         progress: bool = True, device: torch.device | str | None = None,
                         scene_config: RoadSceneConfig | None = None) -> Path:
    """Write a simulated RADIal root (resumable, atomic per file).

    Parameters
    ----------
    out : path-like
        Root folder. If it is not empty it must be a partial run of the same sensor, seed,
        sizes and scene config (its ``sensor.json`` and ``scene.json`` match), which is then completed; otherwise ``overwrite=True``
        deletes the dataset files in it (``radar_FFT/``, ``radar_Freespace/``, ``labels.csv``,
        ``calibration.npz``, ``sensor.json``, ``scene.json``) and starts again.
    cfg : DDMARadarConfig
    n_sequences, frames_per_sequence, seed : int
    overwrite : bool
    progress : bool
        Show a tqdm progress bar.
    device : torch.device or str, optional
        Synthesis device (frames are reproducible per device).
    scene_config : RoadSceneConfig, optional

    Returns
    -------
    Path
        The root.

    Raises
    ------
    FileExistsError
        ``out`` is not empty and is not a matching partial run, without ``overwrite``.
    """
    sim = RadialSimulator(cfg, n_sequences, frames_per_sequence, seed, scene_config=scene_config,
                          device=device)
    root = Path(out)
    if root.exists() and not root.is_dir():
        raise FileExistsError(f"{root} exists and is not a folder")
    meta = _sensor_json(cfg, seed, n_sequences, frames_per_sequence)
    scene_meta = dataclasses.asdict(sim.scene_config)
    sensor_path, scene_path = root / "sensor.json", root / "scene.json"
    if root.is_dir() and any(root.iterdir()):
        matching = (_read_json(sensor_path) == json.loads(json.dumps(meta))
                    and _read_json(scene_path) == json.loads(json.dumps(scene_meta)))
        if not matching:
            if not overwrite:
                raise FileExistsError(
                    f"{root} is not empty and is not a partial run of this simulation (sensor "
                    f"{cfg.name!r}, seed {seed}, {n_sequences} x {frames_per_sequence} frames); "
                    "pass --overwrite (overwrite=True) to replace it")
            for name in _OUTPUTS:
                p = root / name
                if p.is_dir():
                    shutil.rmtree(p)
                elif p.exists():
                    p.unlink()
    root.mkdir(parents=True, exist_ok=True)
    with atomic_write(sensor_path, "w") as f:
        json.dump(meta, f, indent=2)
    with atomic_write(scene_path, "w") as f:
        json.dump(scene_meta, f, indent=2)
    save_calibration(root / "calibration.npz", make_calibration(cfg))

    rows: list[tuple] = []
    with tqdm(total=sim.n_frames, desc=f"simulate {cfg.name}", unit="frame", disable=not progress) as bar:
        for q in range(sim.n_sequences):
            for i in range(sim.frames_per_sequence):
                num = q * sim.frames_per_sequence + i
                fr, frame_rows, fs = sim.geometry(q, i)
                rows.extend(frame_rows)
                fpath, ppath = fft_path(root, num), freespace_path(root, num)
                if not (_fft_complete(fpath, cfg) and _png_complete(ppath)):
                    rd = synthesize_rd(cfg, fr.scatterers, generator=sim.noise_generator(q, i),
                                       device=sim.device)
                    save_npy_atomic(fpath, rd.cpu().numpy())
                    with atomic_write(ppath, "wb") as f:
                        f.write(_png_bytes(fs))
                bar.update(1)
    with atomic_write(root / "labels.csv", "w") as f:
        f.write(_labels_csv(rows))
    return root


# ---- on the fly ---------------------------------------------------------------------------------
def _rows_to_tensor(rows: list[tuple]) -> np.ndarray:
    """Vehicle rows as float32 ``(n, 14)`` in :data:`LABEL_TENSOR_COLUMNS` order (no -1 row)."""
    pos = {c: k for k, c in enumerate(LABEL_COLUMNS)}
    veh = [r for r in rows if any(float(r[pos[c]]) != -1.0 for c in _EMPTY_MARKER_COLUMNS)]
    out = np.empty((len(veh), len(LABEL_TENSOR_COLUMNS)), dtype=np.float32)
    for j, c in enumerate(LABEL_TENSOR_COLUMNS):
        out[:, j] = np.asarray([float(r[pos[c]]) for r in veh], dtype=np.float64)
    return out


class SimulatedRADIal(torch.utils.data.Dataset):
    """Simulated RADIal frames generated on the fly, interchangeable with the on-disk reader.

    ``ds[i]`` is ``(rd, labels, freespace)`` exactly as :class:`radarpc.data.radial.RADIal`
    returns it for the root that :func:`write_radial_dataset` writes with the same arguments on
    the same device: ``rd`` complex64 ``(n_range, n_doppler, n_rx)`` on ``device``, ``labels``
    float32 ``(n_vehicles, 14)`` with columns :data:`LABEL_TENSOR_COLUMNS` (``(0, 14)`` when none),
    ``freespace`` bool ``(256, 224)``. Every vehicle row is kept (the reader's default
    ``difficult=True``).

    Parameters
    ----------
    cfg : DDMARadarConfig
    n_sequences, frames_per_sequence, seed : int
    split : {"train", "val", "test", "all"}
        Sequences by :func:`radarpc.data.radial_format.simulated_split`.
    device : torch.device or str, optional
        Synthesis device and device of the returned tensors (default CPU).
    scene_config : RoadSceneConfig, optional

    Attributes
    ----------
    frame_ids : list of int         numSample of each item
    sequence_names : list of str    sequence name (``dataset`` column) of each item
    sensor : DDMARadarConfig
    calibration : Calibration
    """

    def __init__(self, cfg: DDMARadarConfig, n_sequences: int, frames_per_sequence: int, seed: int,
                 split: str = "train", device: torch.device | str | None = None, *,
                 scene_config: RoadSceneConfig | None = None) -> None:
        if split not in _SPLITS:
            raise ValueError(f"split must be one of {_SPLITS}, got {split!r}")
        self.sim = RadialSimulator(cfg, n_sequences, frames_per_sequence, seed,
                                   scene_config=scene_config, device=device)
        self.split = split
        self.sensor = cfg
        self.device = self.sim.device
        seqs = [q for q in range(self.sim.n_sequences)
                if split == "all" or simulated_split(q, self.sim.n_sequences) == split]
        f = self.sim.frames_per_sequence
        self.frame_ids: list[int] = [q * f + i for q in seqs for i in range(f)]
        self.sequence_names: list[str] = [simulated_sequence_name(seed, q) for q in seqs for _ in range(f)]
        self.sequences = self.sequence_names
        self._calibration: Calibration | None = None

    @property
    def calibration(self) -> Calibration:
        """The sensor's calibration table (what ``calibration.npz`` holds)."""
        if self._calibration is None:
            self._calibration = make_calibration(self.sensor)
        return self._calibration

    def __len__(self) -> int:
        return len(self.frame_ids)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        n = len(self)
        if not -n <= int(i) < n:
            raise IndexError(f"index {i} out of range for a simulated RADIal split of {n} frames")
        q, k = self.sim.locate(self.frame_ids[int(i) % n])
        fr = self.sim.frame(q, k)
        labels = torch.from_numpy(_rows_to_tensor(fr.label_rows)).to(self.device)
        fs = torch.from_numpy(np.ascontiguousarray(freespace_to_model(fr.freespace))).to(self.device)
        return fr.rd, labels, fs

    def frame_labels(self, i: int) -> list[dict[str, int | float | str]]:
        """The raw ``labels.csv`` rows (all :data:`LABEL_COLUMNS`) of item ``i``, -1 row included."""
        q, k = self.sim.locate(self.frame_ids[int(i)])
        return [dict(zip(LABEL_COLUMNS, r)) for r in self.sim.geometry(q, k)[1]]

    def index_of(self, num_sample: int) -> int:
        """Position of frame ``num_sample`` in this split."""
        try:
            return self.frame_ids.index(int(num_sample))
        except ValueError:
            raise KeyError(f"frame {num_sample} is not in this {self.split!r} split") from None

    def __repr__(self) -> str:
        return (f"SimulatedRADIal(sensor={self.sensor.name!r}, split={self.split!r}, frames={len(self)}, "
                f"seed={self.sim.seed})")
