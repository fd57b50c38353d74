"""Records of a segmentation: per-beam labels and per-segment line fits (scanner frame)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Segment:
    """One linear segment of a scanline, in the scanner frame.

    ``first_beam``/``last_beam`` are inclusive beam indices. The line is
    ``normal . p = offset`` (offset >= 0); ``endpoints`` are the first and last
    points projected onto it; ``cov`` is the covariance of (angle of the
    normal, offset) propagated from the point noise.
    """

    index: int
    first_beam: int
    last_beam: int
    normal: FloatArray
    offset: float
    centroid: FloatArray
    direction: FloatArray
    endpoints: FloatArray
    n_points: int
    rms: float
    cov: FloatArray

    @property
    def angle(self) -> float:
        """Direction of the normal (rad)."""
        return float(np.arctan2(self.normal[1], self.normal[0]))

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.endpoints[1] - self.endpoints[0]))


@dataclass(frozen=True, eq=False)
class Segmentation:
    """Result of a segmenter on one scanline.

    ``labels`` has one int per beam: -1 = unsegmented (or invalid), segments
    numbered 0, 1, ... in scan order. The per-segment arrays are stored
    column-wise (k rows); ``segments`` builds the ``Segment`` records.
    """

    labels: NDArray[np.int64]
    first_beam: NDArray[np.int64]
    last_beam: NDArray[np.int64]
    n_points: NDArray[np.int64]
    normal: FloatArray
    offset: FloatArray
    centroid: FloatArray
    direction: FloatArray
    endpoints: FloatArray
    rms: FloatArray
    cov: FloatArray
    method: str = ""
    params: dict[str, Any] = field(default_factory=dict)

    @property
    def n_segments(self) -> int:
        return int(self.first_beam.shape[0])

    def __len__(self) -> int:
        return self.n_segments

    @property
    def segments(self) -> list[Segment]:
        return [self.segment(k) for k in range(self.n_segments)]

    def segment(self, k: int) -> Segment:
        return Segment(
            index=k,
            first_beam=int(self.first_beam[k]),
            last_beam=int(self.last_beam[k]),
            normal=self.normal[k],
            offset=float(self.offset[k]),
            centroid=self.centroid[k],
            direction=self.direction[k],
            endpoints=self.endpoints[k],
            n_points=int(self.n_points[k]),
            rms=float(self.rms[k]),
            cov=self.cov[k],
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "method": self.method,
            "params": self.params,
            "labels": self.labels.tolist(),
            "segments": [
                {
                    "first_beam": s.first_beam,
                    "last_beam": s.last_beam,
                    "n_points": s.n_points,
                    "normal": s.normal.tolist(),
                    "offset": s.offset,
                    "centroid": s.centroid.tolist(),
                    "direction": s.direction.tolist(),
                    "endpoints": s.endpoints.tolist(),
                    "rms": s.rms,
                    "cov_angle_offset": s.cov.tolist(),
                }
                for s in self.segments
            ],
        }
