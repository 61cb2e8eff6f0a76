"""Gradient-map sequences: frames that already carry slopes and contact masks.

Two layouts (method.md section 9.1):

* a folder (or its ``gradient_maps.npy``) with ``gradient_maps.npy`` ``(N, H, W, 2)`` and
  ``contact_masks.npy`` ``(N, H, W)``: the NormalFlow tracking dataset. Both are
  memory-mapped, so long sequences are read frame by frame;
* an ``.npz`` with ``gradients`` ``(N, H, W, 2)`` (float16/32/64) and ``contact``
  ``(N, H, W)``, e.g. the simulator's ``gt_gradients.npz``, or with the ``.npy`` layout's
  names ``gradient_maps`` and ``contact_masks``. Compressed or not, each array
  is read frame by frame from its zip stream (:class:`NpzFrames`): in order it streams,
  nothing ahead of the read frame is decompressed, and a read behind the last one
  decompresses the member again from its start (for random access over long sequences
  prefer the ``.npy`` layout).

Gradients are delivered as float32, masks as bool; a frame with NaN or Inf raises when
it is read.
"""

from __future__ import annotations

import os
import threading
import zipfile
import zlib
from pathlib import Path

import numpy as np

from tactile_slam.geometry.frame import InputError
from tactile_slam.io.frames import RawFrame, SequenceSource

GRADIENTS_NPY = "gradient_maps.npy"
CONTACT_NPY = "contact_masks.npy"
EPISODE_NPZ = "gt_gradients.npz"  # a simulated episode's gradient record (tactile_slam.sim.episode)
GRADIENTS_KEY = "gradients"
CONTACT_KEY = "contact"
NPZ_KEYS = ((GRADIENTS_KEY, CONTACT_KEY), (GRADIENTS_NPY[:-4], CONTACT_NPY[:-4]))
"""The ``.npz`` member pairs read as (gradients, contact), in order of preference."""


def _load_npy(path: Path) -> np.ndarray:
    if not path.is_file():
        raise InputError(f"gradient sequence file not found: {path}")
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise InputError(f"cannot read {path}: {exc}") from exc


class NpzFrames:
    """One array of an ``.npz`` file, read along its first axis from the zip stream.

    Behaves as far as :class:`GradientSequence` needs like the array: ``shape``,
    ``dtype``, ``ndim``, ``len`` and ``[i]`` (one frame, a fresh ``ndarray``). Reads are
    serialised by a lock (the stream has one cursor); a pickled copy reopens the file,
    and so does a forked process (DataLoader workers) at its first read, because a file
    handle inherited through fork shares its position with the parent's.

    Raises:
        InputError: no such member, not an ``.npy`` member numpy can stream (object
            dtype, Fortran order), a truncated or corrupt stream (when read).
    """

    def __init__(self, path: Path, key: str):
        self.path, self.key = Path(path), key
        self._open()

    def _open(self) -> None:
        self._pid = os.getpid()
        try:
            self._zip = zipfile.ZipFile(self.path)
            names = [n[:-4] for n in self._zip.namelist() if n.endswith(".npy")]
            if self.key not in names:
                raise InputError(f"{self.path} has no array {self.key!r} (found {sorted(names)})")
            self._stream = self._zip.open(self.key + ".npy")
            version = np.lib.format.read_magic(self._stream)
            if version not in ((1, 0), (2, 0)):
                raise InputError(f"{self.path}: array {self.key!r} has .npy format {version}, expected 1.0 or 2.0")
            fmt = np.lib.format
            read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            shape, fortran, dtype = read_header(self._stream)
        except (ValueError, OSError, zipfile.BadZipFile, EOFError) as exc:
            raise InputError(f"cannot read {self.path}: {exc}") from exc
        if fortran or dtype.hasobject or len(shape) == 0:
            raise InputError(f"{self.path}: array {self.key!r} cannot be read frame by frame "
                             f"(shape {shape}, {'Fortran order' if fortran else dtype})")
        self.shape, self.dtype = tuple(int(n) for n in shape), dtype
        self._first = self._stream.tell()
        self._frame_bytes = int(np.prod(self.shape[1:], dtype=np.int64)) * dtype.itemsize
        self._next = 0  # frame the stream's cursor is at
        self._lock = threading.Lock()

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, i: int) -> np.ndarray:
        n = self.shape[0]
        i = int(i) + n if int(i) < 0 else int(i)
        if not 0 <= i < n:
            raise IndexError(f"frame {i} of {n}")
        if self._pid != os.getpid():  # forked: never read through the parent's file handle
            self._open()
        with self._lock:
            try:
                if i != self._next:
                    self._stream.seek(self._first + i * self._frame_bytes)
                data = self._stream.read(self._frame_bytes)
            except (OSError, EOFError, ValueError, zipfile.BadZipFile, zlib.error) as exc:
                raise InputError(f"{self.path}: cannot read frame {i} of {self.key!r}: {exc}") from exc
            self._next = i + 1 if len(data) == self._frame_bytes else -1
        if len(data) != self._frame_bytes:
            raise InputError(f"{self.path}: array {self.key!r} ends inside frame {i} (truncated file)")
        return np.frombuffer(data, dtype=self.dtype).reshape(self.shape[1:])

    def __getstate__(self) -> dict:
        return {"path": self.path, "key": self.key}

    def __setstate__(self, state: dict) -> None:
        self.path, self.key = state["path"], state["key"]
        self._open()


def _load_npz(path: Path) -> tuple[NpzFrames, NpzFrames]:
    """The gradients and contact members of an ``.npz``: the first pair of :data:`NPZ_KEYS`
    that it holds both of."""
    if not path.is_file():
        raise InputError(f"gradient sequence file not found: {path}")
    try:
        with zipfile.ZipFile(path) as z:
            names = {n[:-4] for n in z.namelist() if n.endswith(".npy")}
    except (OSError, zipfile.BadZipFile) as exc:
        raise InputError(f"cannot read {path}: {exc}") from exc
    for gradients, contact in NPZ_KEYS:
        if gradients in names and contact in names:
            return NpzFrames(path, gradients), NpzFrames(path, contact)
    pairs = " or ".join(f"{g!r} + {c!r}" for g, c in NPZ_KEYS)
    raise InputError(f"{path} needs the arrays {pairs} (found {sorted(names)})")


def check_sequence(gradients: np.ndarray, contact: np.ndarray, where: str) -> None:
    """Raise :class:`InputError` unless ``gradients`` is ``(N, H, W, 2)`` floating,
    ``contact`` is ``(N, H, W)`` bool or integer, and ``N > 0``."""
    if gradients.ndim != 4 or gradients.shape[-1] != 2:
        raise InputError(f"{where}: gradients must be (N, H, W, 2), got {gradients.shape}")
    if not np.issubdtype(gradients.dtype, np.floating):
        raise InputError(f"{where}: gradients must be floating point, got {gradients.dtype}")
    if contact.ndim != 3 or contact.shape != gradients.shape[:3]:
        raise InputError(
            f"{where}: contact masks {contact.shape} do not match gradients {gradients.shape[:3]}"
        )
    if not (contact.dtype == np.bool_ or np.issubdtype(contact.dtype, np.integer)):
        raise InputError(f"{where}: contact masks must be bool or integer, got {contact.dtype}")
    if gradients.shape[0] == 0:
        raise InputError(f"{where}: the sequence is empty (0 frames)")


class GradientSequence(SequenceSource):
    """Frames ``0..N-1`` of gradient maps and contact masks, timestamps ``index / fps``.

    Args:
        path: a folder with ``gradient_maps.npy`` + ``contact_masks.npy``, the
            ``gradient_maps.npy`` itself, or an ``.npz`` with ``gradients`` + ``contact``.
        fps: frame rate of the sequence.
        shape: expected ``(H, W)``; ``None`` accepts the files' size. Gradient maps are
            never resized (resampling changes slopes).

    Raises:
        InputError: missing or unreadable files, shape mismatch between gradients and
            masks, an empty sequence, the wrong size; NaN or Inf in a frame, or a
            truncated ``.npz`` stream (when that frame is read).
    """

    def __init__(self, path: str | Path, fps: float, shape: tuple[int, int] | None = None):
        path = Path(path)
        self.name = str(path)
        if not fps > 0:
            raise InputError(f"fps must be > 0, got {fps}")
        self._npy_paths: tuple[Path, Path] | None = None
        if path.suffix.lower() == ".npz":
            self.gradients, self.contact = _load_npz(path)
            check_sequence(self.gradients, self.contact, str(path))
        else:
            if path.is_dir():
                folder, grad_path = path, path / GRADIENTS_NPY
            elif path.suffix.lower() == ".npy":
                folder, grad_path = path.parent, path
            else:
                raise InputError(f"not a gradient sequence (folder, .npy or .npz): {path}")
            self._npy_paths = (grad_path, folder / CONTACT_NPY)
            self.gradients, self.contact = (_load_npy(p) for p in self._npy_paths)
            check_sequence(self.gradients, self.contact, str(path))
        self.fps = float(fps)
        native = (int(self.gradients.shape[1]), int(self.gradients.shape[2]))
        if shape is not None and tuple(shape) != native:
            raise InputError(
                f"{path}: gradient maps are {native[1]}x{native[0]} but the working size is {shape[1]}x{shape[0]}"
            )
        self.shape = native

    def __len__(self) -> int:
        return int(self.gradients.shape[0])

    def frame(self, position: int) -> RawFrame:
        gradients = np.array(self.gradients[position], dtype=np.float32)
        if not np.isfinite(gradients).all():
            raise InputError(f"{self.name}: gradients of frame {position} contain NaN or Inf")
        contact = np.array(self.contact[position], dtype=bool)
        return RawFrame(index=position, timestamp=position / self.fps, gradients=gradients, contact=contact)

    def __getstate__(self) -> dict:
        # Memory-mapped files are reopened, not copied, in DataLoader worker processes.
        state = self.__dict__.copy()
        if self._npy_paths is not None:
            state["gradients"] = state["contact"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        if self._npy_paths is not None:
            self.gradients, self.contact = (_load_npy(p) for p in self._npy_paths)
