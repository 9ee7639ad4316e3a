"""Simulated datasets on disk: write one from the highway simulator, or reuse the cached default.

`plan_frames` turns the frame / scene counts a user gives into (frames, frames per scene).
`simulate_dataset` streams `HighwaySimulator` frames (every height from the same traffic)
into a `DatasetWriter`. `default_dataset` is what every command uses when no `--data` is
given: the dataset described by a config's `data:` section, generated once into a cache
folder named by a digest of everything that shapes it (preset, overrides, frames, scene
length, heights, seed, split) and reused afterwards. Generation holds the dataset's lock (one
builder, even among machines sharing the cache; the others wait and reuse it) and goes to a staged
folder swapped into place when complete, so an interrupted run never leaves a half dataset that
later runs would trust; a failed generation (a full disk) removes its folder, and one whose
process was killed is removed by the next `default_dataset` call (only folders detbench marked
as its builds, and only when no process holds their destination).
`estimate_dataset_bytes` and `check_space` size a dataset before it is simulated, so a run the
disk cannot hold stops at once instead of after hours. `write_simulation` (every simulated dataset,
tools/simulate.py's included) builds beside its
`root` and swaps the finished dataset in whole (`detbench.utils.staged_folders.staged_folder`), so a kill
during `--overwrite` leaves the old dataset as it was.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
from pathlib import Path
from collections.abc import Callable, Sequence

from tqdm import tqdm

from detbench.config import shipped_default, shipped_defaults
from detbench.data.frame import data_key, is_rig_key
from detbench.data.layout import DATASET_FOLDER, sim_calibration
from detbench.data.writer import DatasetWriter
from detbench.sim.lidar import lidar_preset
from detbench.sim.rigs import Rig
from detbench.sim.simulator import HighwaySimulator, load_sim_config
from detbench.utils.atomic import DiskFullError
from detbench.utils.cli import UserError
from detbench.utils.folder_ownership import check_replaceable
from detbench.utils.staged_folders import hold_destination, recover_marked, recover_staged, staged_folder

DATA_DEFAULTS: dict = shipped_defaults("data")  # configs/default.yaml `data:`, each key documented there


def cache_root(cache_dir: str | os.PathLike | None = None) -> Path:
    """Where simulated datasets are cached: `cache_dir`, else $DETBENCH_CACHE, else ~/.cache/detbench.
    UserError when that path is a file (or under one), naming where it came from."""
    env = os.environ.get("DETBENCH_CACHE")
    if cache_dir:
        path, named = Path(cache_dir).expanduser(), f"data.cache_dir {cache_dir}"
    elif env:
        path, named = Path(env).expanduser(), f"DETBENCH_CACHE={env}"
    else:
        return Path.home() / ".cache" / "detbench"
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir():
                raise UserError(f"{named}: {p} is a file, not a folder; point it at a folder for the cache of "
                                f"simulated datasets (or leave it unset for ~/.cache/detbench)")
            break
    return path


def plan_frames(frames: int | None, scenes: int | None, fps: int | None, default_fps: int) -> tuple[int, int]:
    """(total frames, frames per scene) from the counts a user gives; raises ValueError if inconsistent.

    frames: total frames (instants) or None; scenes: number of scenes or None (one of the two
    is needed); fps: frames per scene or None (then `default_fps`, or frames / scenes rounded
    up when both are given).
    """
    for name, v in (("--frames", frames), ("--scenes", scenes), ("--frames-per-scene", fps)):
        if v is not None and v < 1:
            raise ValueError(f"{name} must be a positive integer, got {v}")
    if frames is None and scenes is None:
        raise ValueError("give --frames N or --scenes K (or both)")
    if fps is None:
        fps = default_fps if (frames is None or scenes is None) else math.ceil(frames / scenes)
    if frames is None:
        frames = scenes * fps
    elif scenes is not None and frames > scenes * fps:
        raise ValueError(f"--frames {frames} does not fit in --scenes {scenes} of {fps} frames; raise one of them")
    return int(frames), int(fps)


# Bytes on disk per simulated instant, measured on this tree: tools/simulate.py --frames 4 (paper preset, seed 0,
# heights 0.5 1.0 1.8; 128 channels x 480 azimuth steps = 61440 rays each) wrote 37.4k / 35.0k / 34.8k points per
# frame (61 / 57 / 57 % of the rays; points/ 6.88 MB in all) and labels/ + meta/ of 1.8 kB + 2.0 kB per instant.
POINT_BYTES = 16           # x, y, z, intensity as float32
POINTS_FILE_BYTES = 128    # the .npy header of one points file
RETURN_FRACTION = 0.65     # share of a LiDAR's rays that return a point (measured <= 0.61, rounded up)
INSTANT_BYTES = 4096       # labels/<id>.txt + meta/<id>.json (+ the ImageSets line) of one instant, rounded up
SPACE_MARGIN = 1.10        # free space must exceed the estimate by this factor ...
SPACE_RESERVE = 64 << 20   # ... plus this many bytes, for dataset.json, the summary and everything else on the disk


def estimate_dataset_bytes(lidars: Sequence, frames: int) -> int:
    """About how many bytes a simulated dataset of `frames` instants at every LiDAR of `lidars` takes on disk:
    per instant, each LiDAR's channels x h_samples rays times the measured `RETURN_FRACTION` times 16 bytes,
    plus the labels and meta of the instant (`INSTANT_BYTES`). A LiDAR cannot write more than its rays, so
    `RETURN_FRACTION` = 1 would be an upper bound."""
    per_instant = INSTANT_BYTES
    for lid in lidars:
        if isinstance(lid, Rig):  # every sensor's returns in one points file, and a 2-byte sensor index a point
            rays = sum(int(s.lidar.channels) * int(s.lidar.h_samples) for s in lid.sensors)
            per_instant += 2 * POINTS_FILE_BYTES + (POINT_BYTES + 2) * math.ceil(RETURN_FRACTION * rays)
        else:
            per_instant += POINTS_FILE_BYTES + POINT_BYTES * math.ceil(RETURN_FRACTION * int(lid.channels)
                                                                       * int(lid.h_samples))
    return int(frames) * per_instant


def human_bytes(n: float) -> str:
    """`n` bytes as "1.5 GB", "12.0 TB" (powers of 1000, as df -H)."""
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000.0
    return f"{n:.1f} PB"


def existing_parent(path: str | os.PathLike) -> Path:
    """`path` if it exists, else its nearest existing parent folder (the filesystem a new folder there lands on)."""
    p = Path(path).expanduser().absolute()
    for cand in (p, *p.parents):
        if cand.exists():
            return cand
    return Path(p.anchor)


def check_space(root: str | os.PathLike, nbytes: int, *, what: str, fix: str) -> int:
    """Raise DiskFullError when the filesystem `root` is built on (the nearest existing parent of its
    staging folder beside it) has less free space than `nbytes` times `SPACE_MARGIN` plus `SPACE_RESERVE`;
    the message names that folder, the estimate, the free space and `fix`. Returns the free bytes."""
    where = existing_parent(Path(root).expanduser().absolute().parent)
    free = shutil.disk_usage(where).free
    need = int(nbytes * SPACE_MARGIN) + SPACE_RESERVE
    if free < need:
        err = DiskFullError(f"{root}: {what} needs about {human_bytes(nbytes)} on disk but the filesystem of "
                            f"{where} has {human_bytes(free)} free; {fix}")
        err.path, err.reason = Path(root), "not enough free space"
        raise err
    return free


def write_simulation(root: str | os.PathLike, sim, lidars: Sequence, frames: int, *, source: dict,
                     frames_per_scene: int | None = None, test_fraction: float | None = None, overwrite: bool = False,
                     progress: bool = True, on_step: Callable[[list], None] | None = None,
                     finish: Callable[[Path], None] | None = None, drop_frames_without: str | None = None,
                     wait: Callable[[str], None] | None = None) -> Path:
    """Stream `frames` time steps of `sim` (a HighwaySimulator) at every LiDAR into a DatasetWriter.

    `lidars` holds LidarConfigs (one points folder per height) or rigs (detbench.sim.rigs.Rig: one points
    folder per rig, named after it, and its sensor indices; dataset.json records each rig).

    The dataset is built in a sibling folder `.tmp-new-<name>-<pid>` and swapped in whole when
    complete (`detbench.utils.staged_folders.staged_folder`): an interrupted or failed run leaves `root` as it
    was (the old dataset, with `overwrite`, or nothing), and the next run removes its leftovers.
    `root` must be new or empty, or hold only a dataset's files and `overwrite` be set
    (`detbench.utils.folder_ownership.check_replaceable`; FileExistsError otherwise, before anything is simulated,
    and again under `root`'s lock). A second writer of `root` is refused while this one runs (`FolderInUse`),
    or with `wait` (called once with words naming the other writer) waits for it.
    `on_step(frames_of_one_step)` is called after each step is written (e.g. for statistics);
    `finish(folder)` once the dataset is complete, before the swap (e.g. to add a report to it).
    `test_fraction` None: configs/default.yaml `data.test_fraction` (read by the DatasetWriter);
    `drop_frames_without`: see `DatasetWriter`.
    """
    root = Path(root)
    heights = [lid.name if isinstance(lid, Rig) else float(lid.height) for lid in lidars]
    rigs = {lid.name: lid.describe() for lid in lidars if isinstance(lid, Rig)}
    recover_staged(root)
    check_replaceable(root, overwrite, DATASET_FOLDER)
    with staged_folder(root, what="a simulation", check=lambda: check_replaceable(root, overwrite, DATASET_FOLDER),
                       wait=wait) as staged:
        with DatasetWriter(staged, heights, source, test_fraction, drop_frames_without=drop_frames_without,
                           rigs=rigs) as writer:
            stream = sim.run(int(frames), list(lidars), frames_per_scene=frames_per_scene, with_points=True)
            for step in tqdm(stream, total=int(frames), desc="simulate", unit="frame", disable=not progress,
                             dynamic_ncols=True):
                writer.add(list(step))
                if on_step is not None:
                    on_step(step)
        if finish is not None:
            finish(staged)
    return root


def sensor_sets(heights: Sequence[float | str]) -> list:
    """The LiDARs of `heights`: a Table II sensor per height in metres, the rig of configs/rigs.yaml per name."""
    from detbench.sim.rigs import rig_by_name

    return [rig_by_name(h) if isinstance(h, str) and is_rig_key(h) else lidar_preset(float(h)) for h in heights]


def strided_overrides(preset: str, overrides: Sequence[str], frame_stride: int) -> list[str]:
    """`overrides` with, for `frame_stride` k > 1, the simulator preset's `scene.frame_rate_hz` divided by k (every
    k-th frame kept: a scene of n frames spans n * k frames of time). ValueError unless k is an integer >= 1."""
    if isinstance(frame_stride, bool) or int(frame_stride) != frame_stride or frame_stride < 1:
        raise ValueError(f"frame_stride must be an integer >= 1, got {frame_stride!r}")
    overrides = list(overrides)
    if frame_stride > 1:
        rate = float(load_sim_config(preset, overrides)["scene"]["frame_rate_hz"])
        overrides.append(f"scene.frame_rate_hz={rate / int(frame_stride)!r}")
    return overrides


def simulate_dataset(root: str | os.PathLike, *, frames: int, heights: Sequence[float | str], seed: int = 0,
                     preset: str = "paper", overrides: Sequence[str] = (), frames_per_scene: int | None = None,
                     test_fraction: float | None = None, frame_stride: int | None = None, overwrite: bool = False,
                     progress: bool = True, drop_frames_without: str | None = None) -> Path:
    """Simulate `frames` time steps at every height in `heights` (Table II sensors; a name: that rig of
    configs/rigs.yaml) under `root`.

    Returns `root`. The simulator config is `load_sim_config(preset, overrides)`; the
    dataset.json records it with the seed, so the data can be regenerated byte for byte.
    `frame_stride` k keeps every k-th frame of the simulator's frame rate (its `scene.frame_rate_hz`
    divided by k): a scene of n frames then spans n * k frames of time, so a few frames per scene
    sample the whole course of a scene, as the ability study's long scenes do (None:
    configs/default.yaml `data.frame_stride`). `drop_frames_without` (a range name or None): frames
    with no vehicle in that range join neither split (`DatasetWriter`; None: keep every frame).
    """
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    frame_stride = shipped_default("data.frame_stride", frame_stride)
    overrides = strided_overrides(preset, overrides, frame_stride)
    cfg = load_sim_config(preset, overrides)
    lidars = sensor_sets(heights)
    source = {"kind": "simulator", "preset": preset, "calibration": sim_calibration(cfg),
              "overrides": overrides, "seed": int(seed),
              "frames": int(frames), "frames_per_scene": frames_per_scene, "config": cfg}
    if frame_stride > 1:
        source["frame_stride"] = int(frame_stride)
    return write_simulation(root, HighwaySimulator(cfg, seed=int(seed)), lidars, frames, source=source,
                            frames_per_scene=frames_per_scene, test_fraction=test_fraction, overwrite=overwrite,
                            progress=progress, drop_frames_without=drop_frames_without)


def dataset_digest(data_cfg: dict) -> str:
    """A short digest of everything that shapes the simulated default dataset."""
    keys = ("sim_preset", "sim_overrides", "frames", "frames_per_scene", "heights", "seed", "test_fraction")
    desc = {k: data_cfg.get(k, DATA_DEFAULTS[k]) for k in keys}
    stride = int(data_cfg.get("frame_stride", DATA_DEFAULTS["frame_stride"]) or 1)
    if stride != 1:  # named only when it is set, so the digests of datasets without a stride stay as they are
        desc["frame_stride"] = stride
    drop = data_cfg.get("drop_frames_without", DATA_DEFAULTS["drop_frames_without"])
    if drop:  # likewise named only when set
        desc["drop_frames_without"] = str(drop)
    desc["heights"] = [data_key(h) for h in desc["heights"]]
    rigs = [r for r in sensor_sets(desc["heights"]) if isinstance(r, Rig)]
    if rigs:  # named only with rigs, so the digests of datasets of heights stay as they are
        desc["rigs"] = {r.name: r.describe() for r in rigs}
    desc["test_fraction"] = round(float(desc["test_fraction"]), 6)
    desc["sim_config"] = load_sim_config(desc["sim_preset"], list(desc["sim_overrides"]))
    text = json.dumps(desc, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def remove_abandoned_builds(cache: Path) -> list[str]:
    """Finish the interrupted builds in the cache folder `cache`: the staged folders that carry detbench's
    build marker and whose destination no process holds (`detbench.utils.staged_folders.recover_marked`).
    A live build, on this machine or on another sharing the cache, holds its destination's lock and is left
    alone; a folder detbench did not mark is never touched. Returns one note per thing done."""
    return recover_marked(cache)


def _waiting(final: Path) -> Callable[[str], None]:
    def note(holder: str) -> None:
        tqdm.write(f"waiting for {holder}, which simulates {final}; this run reuses it when it is done")
    return note


def default_dataset(data_cfg: dict | None = None, progress: bool = True) -> Path:
    """The dataset a command runs on: `data_cfg["root"]` if set, else the cached simulated one.

    The simulated dataset is generated on first use (with a progress bar) into
    `cache_root()/sim-<preset>-<frames>f-<digest>` and reused afterwards. One process builds it, holding its
    lock (`detbench.utils.staged_folders.hold_destination`; the cache may be shared by several machines):
    another that needs it at the same time waits and then reuses it.
    """
    cfg = {**DATA_DEFAULTS, **(data_cfg or {})}
    for key in ("root", "cache_dir"):
        if cfg[key] is not None and not isinstance(cfg[key], (str, os.PathLike)):
            raise UserError(f"data.{key} is {cfg[key]!r}, not a folder path (YAML reads yes, no, on and off as "
                            f"true and false, and digits as numbers); give a path, quoted if it looks like one of "
                            f"those: --set 'data.{key}=\"yes\"'")
    if cfg["root"]:
        root = Path(cfg["root"]).expanduser()
        if not (root / "dataset.json").is_file():
            raise FileNotFoundError(f"{root}: no dataset.json; is this a detbench dataset (docs/data-format.md)? "
                                    f"Write one with tools/simulate.py, convert one with python -m "
                                    f"detbench.data.convert, or leave --data out to use the simulated default")
        return root
    name = f"sim-{cfg['sim_preset']}-{int(cfg['frames'])}f-{dataset_digest(cfg)}"
    final = cache_root(cfg["cache_dir"]) / name
    if (final / "dataset.json").is_file():
        return final
    with hold_destination(final, "a build of the simulated default dataset", out="data.cache_dir",
                          wait=_waiting(final)):
        if (final / "dataset.json").is_file():  # built by the process this one waited for
            return final
        remove_abandoned_builds(final.parent)
        check_space(final, estimate_dataset_bytes(sensor_sets(cfg["heights"]),
                                                  int(cfg["frames"])),
                    what=f"the simulated default dataset ({cfg['frames']} frames x {len(cfg['heights'])} heights)",
                    fix="free some space there, point $DETBENCH_CACHE (or data.cache_dir) at a larger disk, or "
                        "lower data.frames")
        if progress:
            tqdm.write(f"simulating the default dataset once into {final} ({cfg['frames']} frames x "
                       f"{len(cfg['heights'])} heights; later runs reuse it)")
        simulate_dataset(final, frames=int(cfg["frames"]), heights=cfg["heights"], seed=int(cfg["seed"]),
                         preset=cfg["sim_preset"], overrides=cfg["sim_overrides"],
                         frames_per_scene=cfg["frames_per_scene"], test_fraction=float(cfg["test_fraction"]),
                         frame_stride=int(cfg.get("frame_stride") or 1),
                         progress=progress, drop_frames_without=cfg.get("drop_frames_without"))
    return final
