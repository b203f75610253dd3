"""H.264 movies from PNG frames: the one encoder for ``render`` and ``view``."""

from __future__ import annotations

from pathlib import Path

from .atomic import atomic_path


def encode_mp4(pngs: list[Path], path: str | Path, fps: float = 30.0, quality: int = 8) -> Path:
    """Encode PNG frames to an H.264 MP4 with imageio-ffmpeg, atomically.

    yuv420p needs even sizes, so frames are cropped to even width and height
    (at most one pixel) rather than rescaled; alpha is dropped. ``quality`` is
    imageio's 0–10 scale (10 best)."""
    import imageio.v2 as imageio

    path = Path(path)
    with atomic_path(path) as tmp:
        with imageio.get_writer(str(tmp), fps=fps, codec="libx264", macro_block_size=2, quality=quality,
                                format="FFMPEG") as w:
            for p in pngs:
                img = imageio.imread(p)[..., :3]
                h, wd = img.shape[0] // 2 * 2, img.shape[1] // 2 * 2
                w.append_data(img[:h, :wd])  # type: ignore[attr-defined]  # typed as imageio's base class
    return path
