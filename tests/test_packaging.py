"""What `pip install` puts into a user's environment: the runtime, never `training`.

`training` (the torch reference, data generation, training loops) runs from the checkout:
`python -m training...` from the repository root; tests and benchmarks import it from there.
"""
import os
import runpy
import subprocess
import sys
from pathlib import Path

import pytest
import setuptools

ROOT = Path(__file__).resolve().parent.parent


def setup_arguments(monkeypatch):
    """The keyword arguments setup.py gives ``setuptools.setup`` (run with setup stubbed)."""
    captured = {}
    monkeypatch.setattr(setuptools, "setup", lambda **kwargs: captured.update(kwargs))
    monkeypatch.chdir(ROOT)
    runpy.run_path(str(ROOT / "setup.py"), run_name="__main__")
    return captured


def test_setup_installs_only_minretarget(monkeypatch):
    packages = setup_arguments(monkeypatch)["packages"]
    assert "minretarget" in packages and "minretarget.formats" in packages
    assert all(p == "minretarget" or p.startswith("minretarget.") for p in packages), packages
    # every runtime subpackage is listed (none is lost by the filter)
    assert set(packages) == set(setuptools.find_packages(str(ROOT), include=["minretarget*"]))


def test_the_type_hints_ship_with_the_package(monkeypatch):
    """PEP 561: the marker file goes into the wheel, so users' type checkers read the hints."""
    data = setup_arguments(monkeypatch)["package_data"]["minretarget"]
    assert "py.typed" in data and (ROOT / "minretarget" / "py.typed").is_file()


CHECK = """
import importlib.metadata, importlib.util
try:
    distribution = importlib.metadata.distribution("minretarget")
except importlib.metadata.PackageNotFoundError:
    print("not installed")
else:
    import minretarget
    print((distribution.read_text("top_level.txt") or "").split(),
          importlib.util.find_spec("training"))
"""


def test_installed_environment_has_no_training(tmp_path):
    """After `pip install [-e] .`, `import training` fails outside the checkout. Run outside
    the checkout: a stale minretarget.egg-info there would answer for the install. (An install
    made before setup.py stopped listing training still maps it: reinstall.)"""
    environment = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    result = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True,
                            cwd=tmp_path, env=environment, timeout=120)
    assert result.returncode == 0, result.stderr
    if result.stdout.strip() == "not installed":
        pytest.skip("minretarget is not installed here (pip install -e .)")
    assert result.stdout.strip() == "['minretarget'] None", result.stdout
