"""benchmarks/renders.py's count of twisted frames, on hand-made bone angles."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import renders  # noqa: E402


def test_twisted_frames_count_the_frames_past_the_limit_and_their_longest_run():
    angles = np.full((12, 21), 5.0)
    angles[[1, 4, 5, 6, 9, 11], 3] = 61.0        # runs of 1, 3, 1 and 1 frames
    angles[7, 20] = 60.0                          # at the limit: not past it
    assert renders.twisted_frames(angles) == (6, 3)
    assert renders.twisted_frames(angles, limit=61.0) == (0, 0)
    angles[:, 0] = 90.0                           # every frame: one run
    assert renders.twisted_frames(angles) == (12, 12)
