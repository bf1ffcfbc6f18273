"""Decoded training frames in one compact uint8 store (memory-mapped for long recordings).

Images are decoded once at the training resolution; a 10-minute two-camera recording at
640x480 is ~5.5 GB of uint8, so above `mmap_above_bytes` the store lives in a .npy file
under the run folder and the OS pages it in and out (docs/method.md 3.6: train within 8 GB of RAM).

A store also grows: `FrameStore.empty` and `append` / `append_rows` add frames one at a time
(mapping while driving, `engine.mapper.Mapper`). Its arrays stay exactly F rows long (views of
buffers whose capacity doubles), so the sampler and the sensor rays read a growing store like a
fixed one, and frames not yet appended cannot be drawn.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from virus_nerf.data.ethz import Recording, common_image_size
from virus_nerf.data.images import depth_to_mm
from virus_nerf.sampler import frame_cache
from virus_nerf.sensors import irs, uss
from virus_nerf.sensors.camera import Intrinsics, pixel_directions
from virus_nerf.sensors.irs import IRS_ZONE_COUNT
from virus_nerf.stereo.build import FrameList

MMAP_ABOVE_BYTES = 1 << 30  # a decoded store's images beyond this are memory-mapped from the run folder
# frames decoded into a memory-mapped file between handing its written pages back (release_pages):
# a 30-minute drive's source frames would otherwise all stay in the process's RSS
RELEASE_DECODED_EVERY = 256
SPILL_ABOVE_BYTES = 128 << 20  # a growing store's images beyond this go to a file (`FrameStore.spill_to`)


@dataclass
class StackFootprints:
    """Per-pixel sensor footprints of one stack's camera at training resolution."""

    dirs_cam: np.ndarray  # (H*W, 3) float32 unit directions, camera frame
    irs_zone: np.ndarray  # (H*W,) int16 zone id row*8+col, -1 outside the IRS field of view
    zone_pixels: np.ndarray  # (P,) int32 pixel ids sorted by zone
    zone_start: np.ndarray  # (65,) int64 offsets of each zone's pixels in zone_pixels
    uss_pixels: np.ndarray  # (Q,) int32 pixel ids inside the USS cone
    in_uss: np.ndarray  # (H*W,) bool

    @staticmethod
    def of(intr: Intrinsics) -> StackFootprints:
        v, u = np.mgrid[0 : intr.height, 0 : intr.width]
        dirs = pixel_directions(intr, u.ravel(), v.ravel())
        row, col = irs.zone_of_directions(dirs)
        zone = np.where(row >= 0, row * irs.IRS_ZONES + col, -1).astype(np.int16)
        inside = np.flatnonzero(zone >= 0)
        order = inside[np.argsort(zone[inside], kind="stable")]
        counts = np.bincount(zone[order], minlength=IRS_ZONE_COUNT)
        start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        in_cone = uss.in_cone(dirs)
        return StackFootprints(
            dirs_cam=dirs.astype(np.float32),
            irs_zone=zone,
            zone_pixels=order.astype(np.int32),
            zone_start=start,
            uss_pixels=np.flatnonzero(in_cone).astype(np.int32),
            in_uss=in_cone,
        )


class SpillFile:
    """The unlinked file behind one spilled (cap, ...) array of a growing store (issue 39, D63).

    It grows in place (ftruncate: the rows written stay where they are, no copy), and the
    training path writes a frame and reads its sampled pixels with pwrite / pread, so the file's
    pages live in the kernel's page cache only and never in the process's RSS. (Reading a mapping
    instead maps 16 cached pages around each faulting one: a step's 2048 random pixels mapped
    ~128 MB, and the RSS followed the drive, D55.) The store's array is still a map of the file
    (`resize`) for the rare whole-array readers (tests, a store copied whole)."""

    def __init__(self, folder: Path, name: str, dtype: np.dtype, row_shape: tuple[int, ...]):
        import tempfile

        folder.mkdir(parents=True, exist_ok=True)
        fd, path = tempfile.mkstemp(prefix=f".frames-{name}-", suffix=".bin", dir=folder)
        os.unlink(path)  # the open file keeps its blocks; the name is gone (no litter after a kill)
        self.file = os.fdopen(fd, "r+b")  # closed with the object
        self.dtype = np.dtype(dtype)
        self.row_shape = tuple(row_shape)  # (H, W[, C])
        self.pixel_shape = self.row_shape[2:]  # () for depth, (3,) for colour
        self.pixel_bytes = int(np.prod(self.pixel_shape, dtype=np.int64)) * self.dtype.itemsize
        self.row_bytes = self.pixel_bytes * self.row_shape[0] * self.row_shape[1]

    def resize(self, cap: int) -> np.ndarray:
        """Room for `cap` rows (new rows read as zeros: sparse, no disk written); its (cap, ...) map."""
        os.ftruncate(self.file.fileno(), cap * self.row_bytes)
        return np.memmap(self.file, dtype=self.dtype, mode="r+", shape=(cap,) + self.row_shape)

    def write(self, first_row: int, rows: np.ndarray) -> None:
        """Rows (k, ...) written from row `first_row` on, in pieces of at most 64 rows."""
        for k in range(0, len(rows), 64):
            data = np.ascontiguousarray(rows[k:k + 64], dtype=self.dtype).tobytes()
            os.pwrite(self.file.fileno(), data, (first_row + k) * self.row_bytes)

    def gather(self, rows: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """(n, *pixel_shape): pixel `pixels[i]` (v * W + u) of row `rows[i]`, one pread each."""
        fd, size = self.file.fileno(), self.pixel_bytes
        offsets = np.asarray(rows, dtype=np.int64) * self.row_bytes + np.asarray(pixels, dtype=np.int64) * size
        data = b"".join([os.pread(fd, size, off) for off in offsets.tolist()])
        return np.frombuffer(data, dtype=self.dtype).reshape((len(offsets),) + self.pixel_shape)


@dataclass
class FrameStore:
    """Frames of all stacks used for training, row f = one frame."""

    stack_ids: np.ndarray  # (F,) int
    rows: np.ndarray  # (F,) sample index within its stack
    times: np.ndarray  # (F,) s
    cam_to_world: np.ndarray  # (F, 4, 4) float64
    images: np.ndarray  # (F, H, W, 3) uint8, RGB (may be a np.memmap)
    depths_mm: np.ndarray | None  # (F, H, W) uint16 z-depth mm, 0 = invalid (RGB-D runs only)
    uss_range: np.ndarray  # (F,) m, NaN = no echo
    irs_range: np.ndarray  # (F, 8, 8) m z-depth, NaN = invalid
    intrinsics: dict[int, Intrinsics]  # per stack, at training resolution
    footprints: dict[int, StackFootprints]
    _capacity: dict[str, np.ndarray] | None = field(default=None, repr=False)  # buffers behind the views
    _spill: tuple[Path, int] | None = field(default=None, repr=False)  # (folder, bytes) of `spill_to`
    _spill_files: dict[str, SpillFile] = field(default_factory=dict, repr=False)  # the spilled arrays' files

    def __len__(self) -> int:
        return len(self.stack_ids)

    def add_stack(self, stack_id: int, intrinsics: Intrinsics) -> None:
        """A stack whose frames may come from now on (training-resolution intrinsics of the
        store's image size: the caller checked it)."""
        self.intrinsics[stack_id] = intrinsics
        self.footprints[stack_id] = StackFootprints.of(intrinsics)

    @staticmethod
    def empty(intrinsics: dict[int, Intrinsics], with_depth: bool = False) -> FrameStore:
        """A store without frames for stacks with these (training-resolution) intrinsics."""
        width, height = common_image_size(intrinsics)
        return FrameStore(
            stack_ids=np.zeros(0, dtype=np.int64), rows=np.zeros(0, dtype=np.int64), times=np.zeros(0),
            cam_to_world=np.zeros((0, 4, 4)), images=np.zeros((0, height, width, 3), dtype=np.uint8),
            depths_mm=np.zeros((0, height, width), dtype=np.uint16) if with_depth else None,
            uss_range=np.zeros(0), irs_range=np.zeros((0, 8, 8)), intrinsics=dict(intrinsics),
            footprints={s: StackFootprints.of(intr) for s, intr in intrinsics.items()},
        )

    def append(self, stack_id: int, row: int, time: float, cam_to_world: np.ndarray, image: np.ndarray,
               depth_mm: np.ndarray | None, uss_range: float, irs_range: np.ndarray) -> int:
        """Add one frame at training resolution (image (H, W, 3) uint8, depth_mm (H, W) uint16 or
        None = invalid everywhere, irs_range (8, 8) m); returns its row. Amortised O(1)."""
        if stack_id not in self.footprints:
            raise ValueError(f"stack {stack_id} is not one of the store's stacks {sorted(self.footprints)}")
        if image.shape != self.images.shape[1:]:
            raise ValueError(f"image shape {image.shape}: expected {self.images.shape[1:]}")
        f = len(self)
        self._grow(f + 1)
        self.stack_ids[f], self.rows[f], self.times[f] = stack_id, row, time
        self.cam_to_world[f] = cam_to_world
        self._put("images", f, image)
        if self.depths_mm is not None:
            self._put("depths_mm", f, np.zeros(self.depths_mm.shape[1:], np.uint16) if depth_mm is None else depth_mm)
        self.uss_range[f] = uss_range
        self.irs_range[f] = irs_range
        return f

    def append_rows(self, other: FrameStore, rows: np.ndarray) -> None:
        """Copy frames `rows` of `other` (same stacks and image size) to the end, in that order."""
        for r in np.asarray(rows, dtype=np.int64):
            depth = None if other.depths_mm is None else other.depths_mm[r]
            self.append(int(other.stack_ids[r]), int(other.rows[r]), float(other.times[r]), other.cam_to_world[r],
                        other.images[r], depth, float(other.uss_range[r]), other.irs_range[r])

    _ARRAYS = ("stack_ids", "rows", "times", "cam_to_world", "images", "depths_mm", "uss_range", "irs_range")
    _PIXELS = ("images", "depths_mm")  # the arrays that grow by a frame's pixels: the ones spilled

    def spill_to(self, folder: Path, above_bytes: int = SPILL_ABOVE_BYTES) -> None:
        """From now on, a growing store whose image (and depth) buffers would pass `above_bytes`
        keeps them in files under `folder` (`SpillFile`: unlinked at once, so nothing stays on disk
        when the process ends, however it ends) instead of in anonymous memory, and reads the
        sampled pixels back from the page cache: an hour-long drive does not hold its frames in
        the process's memory (issue 39)."""
        self._spill = (Path(folder), int(above_bytes))

    @property
    def spilled(self) -> tuple[str, ...]:
        """The arrays kept in files (`spill_to`)."""
        return tuple(self._spill_files)

    def pixels(self, name: str, rows: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """Array `name` ("images" or "depths_mm") at pixel `pixels[i]` (v * W + u) of frame
        `rows[i]`: (n, 3) uint8 colour or (n,) uint16 depth. A spilled array is read with one
        pread a pixel, which never maps its pages into the process."""
        spill = self._spill_files.get(name)
        if spill is not None and hasattr(os, "pread"):
            return spill.gather(rows, pixels)
        arr = getattr(self, name)
        return arr.reshape((len(arr), -1) + arr.shape[3:])[rows, pixels]

    def _put(self, name: str, row: int, value: np.ndarray) -> None:
        """Row `row` of array `name` = value; a spilled array's with pwrite (its map stays untouched)."""
        spill = self._spill_files.get(name)
        if spill is not None and hasattr(os, "pwrite"):
            spill.write(row, value[None])
        else:
            getattr(self, name)[row] = value

    def _buffer(self, name: str, arr: np.ndarray, cap: int) -> np.ndarray:
        """A (cap, ...) buffer for array `name` holding `arr`'s rows first: in memory, or a spilled
        file's map (a file once spilled grows in place, its rows already written)."""
        spill = self._spill_files.get(name)
        shape = (cap,) + arr.shape[1:]
        nbytes = int(np.prod(shape, dtype=np.int64)) * arr.dtype.itemsize
        if spill is None and (self._spill is None or name not in self._PIXELS or nbytes <= self._spill[1]):
            buf = np.zeros(shape, dtype=arr.dtype)
            buf[: len(arr)] = arr
            return buf
        if spill is None:
            spill = self._spill_files[name] = SpillFile(self._spill[0], name, arr.dtype, arr.shape[1:])
            spill.write(0, arr)  # the rows held in memory until now
        return spill.resize(cap)

    def _grow(self, n: int) -> None:
        """Make every array n rows long (views of buffers, reallocated at twice the size when full)."""
        buffers = self._capacity
        if buffers is None or len(buffers["times"]) < n:
            cap = max(16, 2 * n)
            fresh = {}
            for name in self._ARRAYS:
                arr = getattr(self, name)
                if arr is not None:
                    fresh[name] = self._buffer(name, arr, cap)
            self._capacity = buffers = fresh
        for name, buf in buffers.items():
            setattr(self, name, buf[:n])

    def frame_list(self) -> FrameList:
        """Which recording frames the store holds, row by row (for the stereo pass)."""
        return FrameList(self.stack_ids, self.rows, self.times, self.cam_to_world, dict(self.intrinsics))

    @property
    def height(self) -> int:
        return self.images.shape[1]

    @property
    def width(self) -> int:
        return self.images.shape[2]


def release_pages(arr: np.ndarray, rows: np.ndarray | None = None) -> None:
    """Hand rows `rows` (None: all) of a file-backed, shared `np.memmap` (F, ...) back to the OS page cache
    (madvise MADV_DONTNEED): the data stays in the file and is read back on the next access, but
    this process no longer holds the pages (its RSS). For a source read once, as `train --online`
    copies each recorded frame into the mapper. Nothing for an array in memory or a private map."""
    if not isinstance(arr, np.memmap) or arr.mode == "c" or not len(arr) or sys.platform != "linux":
        return
    import ctypes
    import mmap

    page = mmap.PAGESIZE
    row_bytes = arr[0].nbytes
    base = arr.ctypes.data
    libc = ctypes.CDLL(None, use_errno=True)
    spans = [(base, arr.nbytes)] if rows is None else \
        [(base + int(r) * row_bytes, row_bytes) for r in np.unique(np.asarray(rows, dtype=np.int64))]
    for start, length in spans:
        lo = start // page * page  # the pages the span touches (a neighbour's share is read back)
        hi = -(-(start + length) // page) * page
        libc.madvise(ctypes.c_void_p(lo), ctypes.c_size_t(hi - lo), mmap.MADV_DONTNEED)


def resize_rgb(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    from PIL import Image

    if (img.shape[1], img.shape[0]) == size:
        return img
    return np.asarray(Image.fromarray(img).resize(size, Image.Resampling.BOX))


def resize_depth_mm(depth_m: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resize (never mixes valid and invalid pixels) -> uint16 mm, 0 invalid
    (data/images.depth_to_mm)."""
    h, w = depth_m.shape
    ys = ((np.arange(size[1]) + 0.5) * h / size[1]).astype(int)
    xs = ((np.arange(size[0]) + 0.5) * w / size[0]).astype(int)
    return depth_to_mm(depth_m[np.ix_(ys, xs)])


def _decode(recording: Recording, entries: list[tuple[int, int]], size: tuple[int, int], with_depth: bool,
            cache_dir: Path | None, mmap_above_bytes: int, progress: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """Decode and resize every (stack, row) entry: images (F, H, W, 3) uint8, depths (F, H, W) uint16."""
    width, height = size
    n = len(entries)
    if cache_dir is not None and n * height * width * 3 > mmap_above_bytes:
        cache_dir.mkdir(parents=True, exist_ok=True)
        images = np.lib.format.open_memmap(cache_dir / "images.npy", mode="w+", dtype=np.uint8, shape=(n, height, width, 3))
    else:
        images = np.empty((n, height, width, 3), dtype=np.uint8)
    depths = np.zeros((n, height, width), dtype=np.uint16) if with_depth else None
    iterator = range(n)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc="decoding frames", unit="img", leave=False)
    for f in iterator:
        s, i = entries[f]
        stack = recording.stacks[s]
        images[f] = resize_rgb(stack.image(i), (width, height))
        if depths is not None:
            depths[f] = resize_depth_mm(stack.depth(i), (width, height))
        if (f + 1) % RELEASE_DECODED_EVERY == 0 or f + 1 == n:  # a file's written pages leave the process
            release_pages(images, np.arange(f - f % RELEASE_DECODED_EVERY, f + 1))  # this chunk's rows
    return images, depths


def build_frame_store(
    recording: Recording,
    labels: tuple[str, ...] = ("train",),
    image_scale: float = 0.5,
    with_depth: bool = False,
    cache_dir: Path | None = None,
    mmap_above_bytes: int = MMAP_ABOVE_BYTES,
    progress: bool = False,
    use_cache: bool = True,
) -> FrameStore:
    """Decode the frames with the given split labels of every stack, at `image_scale`.

    With `use_cache`, decoded frames are read from / written to the user cache across runs
    (sampler.frame_cache); otherwise, above `mmap_above_bytes` they are memory-mapped from
    `cache_dir`.
    """
    entries = [
        (s, int(i)) for s, stack in sorted(recording.stacks.items()) for i in np.flatnonzero(np.isin(stack.split, labels))
    ]
    intrinsics = {s: st.intrinsics.scaled(image_scale) for s, st in recording.stacks.items()}
    width, height = common_image_size(intrinsics, source=recording.root / "camera_intrinsics.CSV",
                                      shown={s: st.intrinsics for s, st in recording.stacks.items()})
    n = len(entries)
    files = [recording.stacks[s].image_paths[i] for s, i in entries]
    if with_depth:
        for s in sorted({s for s, _ in entries}):
            recording.stacks[s].require_depth()  # a stack without depth images: refused in one line
        files += [recording.stacks[s].depth_paths[i] for s, i in entries]
    key = frame_cache.frames_key(files, (width, height), with_depth) if use_cache and n else None
    cached = frame_cache.load_frames(key) if key is not None else None
    if cached is not None and cached[0].shape == (n, height, width, 3):
        images, depths = cached
    else:
        images, depths = _decode(recording, entries, (width, height), with_depth, cache_dir, mmap_above_bytes, progress)
        if key is not None:
            frame_cache.store_frames(key, images, depths)
            release_pages(images)  # the copy read every page back
    stack_ids = np.array([s for s, _ in entries], dtype=np.int64)
    rows = np.array([i for _, i in entries], dtype=np.int64)
    return FrameStore(
        stack_ids=stack_ids,
        rows=rows,
        times=np.array([recording.stacks[s].times[i] for s, i in entries]),
        cam_to_world=np.stack([recording.stacks[s].cam_to_world[i] for s, i in entries]) if n else np.zeros((0, 4, 4)),
        images=images,
        depths_mm=depths,
        uss_range=np.array([recording.stacks[s].uss_range[i] for s, i in entries]),
        irs_range=np.stack([recording.stacks[s].irs_range[i] for s, i in entries]) if n else np.zeros((0, 8, 8)),
        intrinsics=intrinsics,
        footprints={s: StackFootprints.of(intr) for s, intr in intrinsics.items()},
    )
