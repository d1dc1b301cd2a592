"""A day's LWATV views as one movie (H.264 MP4), as the station makes its daily LWATV movie.

imageio-ffmpeg (the ``service`` extra) supplies an ffmpeg binary and the frame pipe, so no system ffmpeg
is needed. The frames are the PNGs of one ``lwatv/<MJD>/`` folder in name (time) order; names starting
``nomovie+`` are left out, as Orville leaves them out of its movie.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["movie_frames", "write_movie"]


def movie_frames(folder) -> list[Path]:
    """The PNGs of ``folder`` that go into its movie, in time order (their names start with MJD_HHMMSS)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"no such folder of LWATV views: {folder}")
    return sorted(p for p in folder.glob("*.png") if not p.name.startswith("nomovie+"))


def _rgb(path, shape=None):
    from matplotlib.image import imread
    img = imread(path)
    if img.dtype != np.uint8:
        img = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
    img = img[..., :3] if img.ndim == 3 else np.repeat(img[..., None], 3, axis=2)
    if shape is not None and img.shape != shape:
        raise ValueError(f"{path}: {img.shape[1]} x {img.shape[0]} pixels, the movie's frames are "
                         f"{shape[1]} x {shape[0]}")
    return img


def write_movie(frames, path, fps: float = 10.0) -> dict:
    """Write ``frames`` (PNG paths, all one size) as an H.264 MP4 at ``fps`` frames a second (yuv420p, so
    that browsers play it); the size is padded to even numbers of pixels, as H.264 needs.

    Returns {``path``, ``frames``, ``width``, ``height``}. Raises ValueError for no frames or frames of
    different sizes (naming the first that differs)."""
    import imageio_ffmpeg
    frames = [Path(p) for p in frames]
    if not frames:
        raise ValueError("no frames: the folder holds no LWATV views")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps!r}")
    first = _rgb(frames[0])
    h, w = first.shape[:2]
    H, W = h + h % 2, w + w % 2
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.mp4")
    writer = imageio_ffmpeg.write_frames(str(tmp), (W, H), fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                                         macro_block_size=1, ffmpeg_log_level="error")
    writer.send(None)
    try:
        for k, p in enumerate(frames):
            img = first if k == 0 else _rgb(p, first.shape)
            if (H, W) != (h, w):
                img = np.pad(img, ((0, H - h), (0, W - w), (0, 0)))
            writer.send(np.ascontiguousarray(img))
    except BaseException:
        writer.close()
        tmp.unlink(missing_ok=True)
        raise
    writer.close()
    tmp.replace(path)
    return {"path": str(path), "frames": len(frames), "width": W, "height": H}
