"""benchmarks/speed.py refuses at once, naming them, when the engines it compares with are
not installed (not after minutes of timing, with nothing written)."""
import importlib.util
import re
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import speed  # noqa: E402


def test_missing_engines_are_named_before_any_timing(monkeypatch, capsys, tmp_path):
    found = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "onnxruntime" else found(name, *a))
    monkeypatch.setattr(speed, "load_measured", lambda *a: pytest.fail("timing started"))
    out = tmp_path / "speed.json"
    monkeypatch.setattr(sys, "argv", ["speed.py", "--quick", "--json", str(out)])
    with pytest.raises(SystemExit) as raised:
        speed.main()
    assert raised.value.code == 2
    message = capsys.readouterr().err
    # onnxruntime among the engines named (the others are named too where they are missing)
    assert re.search(r"not installed \([^)]*\bonnxruntime\b", message) and ".[bench]" in message
    assert not out.exists()
