"""Frames and seconds: which frame every image shows, and which frames were observed.

Datasets give ``time`` in [0, 1]; the frames of a video are its sorted unique times over all splits. With ``fps``
in the dataset a frame lasts 1/fps s; without it the whole video is taken to last one second.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from causalgs.dataset import Dataset, Frame
from causalgs.errors import DataError


@dataclass
class Timeline:
    times: np.ndarray  # sorted unique dataset times of all splits
    fps: float
    train_frames: int  # frames 0 .. train_frames - 1 are observed (the training split's last frame + 1)

    @classmethod
    def of(cls, data: Dataset) -> Timeline:
        times = data.times()
        if len(times) < 2:
            raise DataError(f"{data.root}: a video needs at least two distinct frame times, found {len(times)}")
        fps = float(data.fps) if data.fps else float(len(times) - 1)
        tl = cls(times, fps, 0)
        tl.train_frames = max(tl.index(f) for f in data.train) + 1
        if tl.train_frames < 2:
            raise DataError(f"{data.root}: the training split covers a single frame time; nothing moves to learn from")
        return tl

    def index(self, frame: Frame) -> int:
        k = int(np.searchsorted(self.times, frame.time))
        return min(k, len(self.times) - 1)

    def by_frame(self, frames: list[Frame]) -> dict[int, list[Frame]]:
        out: dict[int, list[Frame]] = {}
        for f in frames:
            out.setdefault(self.index(f), []).append(f)
        return out

    def seconds(self, k: int) -> float:
        return k / self.fps
