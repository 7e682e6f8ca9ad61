"""Frame sources: image sequences (PNG, JPG, EXR) and video files (mp4, ... through OpenCV).

Frames come back as float32 RGB (H, W, 3) in [0, 1] (EXR: the stored linear values, unclipped).
Masks come back as bool (H, W), true where the object is (>127 for 8-bit images).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .errors import InputError

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".exr")
VIDEO_EXTS = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v")

# FFmpeg's own log ("moov atom not found", ...) would precede our one-line errors; OpenCV reads
# this once, when its FFmpeg backend first opens a video (reading or writing)
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")


def _natural_key(p: Path):
    import re

    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]


def list_images(folder: str | os.PathLike) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "folder not found")
    files = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS and p.is_file()),
                   key=_natural_key)
    return files


def read_image(path: str | os.PathLike) -> np.ndarray:
    """One image as float32 RGB (H, W, 3)."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    if path.suffix.lower() == ".exr":
        return _read_exr(path)
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(path, "image cannot be decoded")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = img[:, :, :3]
    img = img[:, :, ::-1]  # BGR -> RGB
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    return np.ascontiguousarray(img, dtype=np.float32) / scale


def _read_exr(path: Path) -> np.ndarray:
    import OpenEXR

    try:
        with OpenEXR.File(str(path)) as f:
            ch = f.channels()
            if "RGB" in ch:
                img = np.asarray(ch["RGB"].pixels, dtype=np.float32)
            elif "RGBA" in ch:
                img = np.asarray(ch["RGBA"].pixels, dtype=np.float32)[:, :, :3]
            elif all(c in ch for c in "RGB"):
                img = np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in "RGB"], -1)
            elif "Y" in ch:
                y = np.asarray(ch["Y"].pixels, dtype=np.float32)
                img = np.repeat(y[:, :, None], 3, axis=2)
            else:
                raise InputError(path, f"EXR has no RGB channels (has {', '.join(ch)})")
    except InputError:
        raise
    except Exception as exc:
        raise InputError(path, f"EXR cannot be decoded ({exc})") from None
    return np.ascontiguousarray(img)


def write_image(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """Write float RGB in [0, 1] as PNG/JPG (8-bit) or EXR (float)."""
    path = Path(path)
    rgb = np.asarray(rgb, dtype=np.float32)
    if path.suffix.lower() == ".exr":
        import OpenEXR

        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        with OpenEXR.File(header, {"RGB": np.ascontiguousarray(rgb[:, :, :3])}) as f:
            f.write(str(path))
        return
    import cv2

    img = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if img.ndim == 3:
        img = img[:, :, ::-1]
    if not cv2.imwrite(str(path), img):
        raise OSError(f"{path}: cannot write image")


class FrameSource:
    """A sequence of RGB frames."""

    path: Path

    def __len__(self) -> int:
        raise NotImplementedError

    @property
    def size(self) -> tuple[int, int]:
        """(width, height)."""
        raise NotImplementedError

    def read(self, k: int) -> np.ndarray:
        raise NotImplementedError

    def read_all(self) -> np.ndarray:
        return np.stack([self.read(k) for k in range(len(self))])

    @property
    def fps(self) -> float | None:
        return None


class ImageSequence(FrameSource):
    def __init__(self, paths: list[Path], folder: Path | None = None):
        self.paths = [Path(p) for p in paths]
        self.path = folder if folder is not None else (self.paths[0].parent if self.paths else Path("."))
        if not self.paths:
            raise InputError(self.path, "no frame images (PNG, JPG or EXR) found")
        first = read_image(self.paths[0])
        self._size = (first.shape[1], first.shape[0])
        self._cache = {0: first}

    @staticmethod
    def from_folder(folder) -> "ImageSequence":
        return ImageSequence(list_images(folder), Path(folder))

    def __len__(self):
        return len(self.paths)

    @property
    def size(self):
        return self._size

    def read(self, k: int) -> np.ndarray:
        if k in self._cache:
            return self._cache[k]
        img = read_image(self.paths[k])
        if (img.shape[1], img.shape[0]) != self._size:
            raise InputError(self.paths[k], f"frame is {img.shape[1]}x{img.shape[0]} but the first "
                             f"frame is {self._size[0]}x{self._size[1]}")
        return img

    def check_sizes(self) -> None:
        """Read every header-equivalent (the full image: PNGs are small) to validate sizes early."""
        import cv2

        for p in self.paths[1:]:
            if p.suffix.lower() == ".exr":
                img = read_image(p)
                shape = img.shape
            else:
                img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
                if img is None:
                    raise InputError(p, "image cannot be decoded")
                shape = img.shape
            if (shape[1], shape[0]) != self._size:
                raise InputError(p, f"frame is {shape[1]}x{shape[0]} but the first frame is "
                                 f"{self._size[0]}x{self._size[1]}")


class VideoFile(FrameSource):
    """A video decoded with OpenCV; frames are decoded once, on first use, and kept."""

    def __init__(self, path):
        import cv2

        self.path = Path(path)
        if not self.path.exists():
            raise InputError(self.path, "file not found")
        cap = cv2.VideoCapture(str(self.path))
        ok, frame = (cap.read() if cap.isOpened() else (False, None))
        if not ok or frame is None:
            cap.release()
            raise InputError(self.path, "video cannot be decoded (OpenCV read no frame)")
        fps = cap.get(cv2.CAP_PROP_FPS)
        self._fps = float(fps) if fps and np.isfinite(fps) and fps > 0 else None
        frames = [frame]
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            frames.append(frame)
        cap.release()
        self._frames = frames
        self._size = (frames[0].shape[1], frames[0].shape[0])

    def __len__(self):
        return len(self._frames)

    @property
    def size(self):
        return self._size

    @property
    def fps(self):
        return self._fps

    def read(self, k: int) -> np.ndarray:
        return np.ascontiguousarray(self._frames[k][:, :, ::-1], dtype=np.float32) / 255.0


def read_mask(path: str | os.PathLike) -> np.ndarray:
    import cv2

    path = Path(path)
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise InputError(path, "mask cannot be decoded")
    if m.ndim == 3:
        m = m[:, :, :3].max(axis=2)
    thr = 32767 if m.dtype == np.uint16 else 127
    return m > thr


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), np.where(mask, 255, 0).astype(np.uint8)):
        raise OSError(f"{path}: cannot write mask")


def write_video(path: str | os.PathLike, frames, fps: float) -> None:
    """Write float RGB frames (T, H, W, 3) in [0, 1] as an mp4 (mp4v)."""
    import cv2

    frames = np.asarray(frames)
    h, w = frames.shape[1:3]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
    if not vw.isOpened():
        raise OSError(f"{path}: cannot open a video writer")
    for f in frames:
        vw.write(np.clip(f * 255 + 0.5, 0, 255).astype(np.uint8)[:, :, ::-1])
    vw.release()
