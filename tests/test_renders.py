"""benchmarks/renders.py's count of twisted frames, on hand-made bone angles."""
import sys
from pathlib import Path

import numpy as np
import pytest

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


def test_a_failed_run_leaves_the_pictures_as_they_were(tmp_path, monkeypatch, capsys):
    """No data: refused at once. A run that fails midway moves nothing in: the old PNGs and
    renders.json stay a matching set, and no staging folder is left."""
    out = tmp_path / "out"
    with pytest.raises(SystemExit):
        renders.main(["--data", str(tmp_path / "nodata"), "--out", str(out), "--report"])
    assert "build the test data first" in capsys.readouterr().err and not out.exists()
    (tmp_path / "data" / "test").mkdir(parents=True)
    for name, _ in renders.SEQUENCES:
        (tmp_path / "data" / "test" / f"{name}.npz").write_bytes(b"")
    out.mkdir()
    (out / "old.png").write_bytes(b"old picture")
    (out / "renders.json").write_text("{}")

    def fails_midway(weights, sequences, paths, staging, out):
        (staging / "new.png").write_bytes(b"half the set")
        raise ValueError("indian_04: damaged")
    monkeypatch.setattr(renders, "draw", fails_midway)
    with pytest.raises(ValueError, match="indian_04"):
        renders.main(["--data", str(tmp_path / "data"), "--out", str(out), "--report"])
    assert sorted(p.name for p in out.iterdir()) == ["old.png", "renders.json"]


def test_a_run_moves_its_pictures_in(tmp_path, monkeypatch):
    (tmp_path / "data" / "test").mkdir(parents=True)
    for name, _ in renders.SEQUENCES:
        (tmp_path / "data" / "test" / f"{name}.npz").write_bytes(b"")

    def draws(weights, sequences, paths, staging, out):
        (staging / "new.png").write_bytes(b"a picture")
        return [{"png": str(out / "new.png")}], 1.0
    monkeypatch.setattr(renders, "draw", draws)
    renders.main(["--data", str(tmp_path / "data"), "--out", str(tmp_path / "out"), "--report"])
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["new.png", "renders.json"]
    assert (tmp_path / "out" / "new.png").read_bytes() == b"a picture"
