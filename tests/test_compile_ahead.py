"""The cold start's second process (``minretarget._compile_ahead``)."""
import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from minretarget import _compile_ahead
from minretarget.pipeline import preset
from minretarget.retargeter import Retargeter
from minretarget.sources import load_sample

# A fresh process with an empty numba cache: the real trigger (numba's first compile in
# set_target) starts the second process; the stages after the cloud's must then compile
# nothing in the first one (they come from the cache the second one wrote).
COLD_START = textwrap.dedent("""
    import json, sys
    from numba.core import event
    from minretarget import _compile_ahead
    from minretarget.retargeter import Retargeter
    from minretarget.sources import load_sample

    _compile_ahead._cores = lambda: 2          # the mechanism, whatever this machine has
    started, tail, compiled = [], [False], []
    start = _compile_ahead.start
    _compile_ahead.start = lambda config: started.append(start(config)) or started[-1]

    class Compiles(event.Listener):
        def on_start(self, ev):
            if tail[0]:
                compiled.append(ev.data["dispatcher"].py_func.__qualname__)

        def on_end(self, ev):
            pass

    event.register("numba:compile", Compiles())
    source, target, faces, _ = load_sample()
    retargeter = Retargeter.from_weights(None, sys.argv[1], warn=False)
    retargeter.set_target(target, faces)
    for stage in retargeter.stages:            # mark where the cloud's stages end
        def step(state, frame, stage=stage, inner=stage.step):
            tail[0] = tail[0] or not stage.reads_cloud
            return inner(state, frame)
        stage.step = step
    retargeter.step(next(source.frames))
    print(json.dumps({"started": [p is not None for p in started],
                      "joined": retargeter._compiler is None,
                      "returncode": started[0].returncode if started and started[0] else None,
                      "tail_compiled": compiled}))
""")


@pytest.mark.parametrize("name", ["fitted", "regressed"])
def test_cold_start_takes_the_later_stages_from_the_second_process(tmp_path, name):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    env.pop(_compile_ahead.SWITCH, None)
    env.pop("NUMBA_DISABLE_JIT", None)
    result = subprocess.run([sys.executable, "-c", COLD_START, name], env=env,
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    run = json.loads(result.stdout.splitlines()[-1])
    assert run["started"] == [True] and run["joined"] and run["returncode"] == 0, run
    assert run["tail_compiled"] == [], run


def test_start_is_switched_off_by_the_environment_and_once_per_config(monkeypatch):
    config = preset("paper")
    monkeypatch.setattr(_compile_ahead, "_started", set())
    monkeypatch.setenv(_compile_ahead.SWITCH, "0")
    assert _compile_ahead.start(config) is None
    monkeypatch.delenv(_compile_ahead.SWITCH)
    monkeypatch.setattr(_compile_ahead, "_cores", lambda: 1)
    assert _compile_ahead.start(config) is None                 # one core: nothing to gain
    monkeypatch.setattr(_compile_ahead, "_cores", lambda: 2)
    launched = []
    monkeypatch.setattr(_compile_ahead.subprocess, "Popen",
                        lambda argv, **kwargs: launched.append((argv, kwargs)) or "process")
    assert _compile_ahead.start(config) == "process"
    assert _compile_ahead.start(config) is None                 # once per config
    (argv, kwargs), = launched
    assert argv[1:] == ["-m", "minretarget._compile_ahead", config.to_json()]
    assert kwargs["env"][_compile_ahead.SWITCH] == "0"          # it starts none of its own
    package_root = str(Path(_compile_ahead.__file__).resolve().parents[1])
    assert kwargs["env"]["PYTHONPATH"].split(os.pathsep)[0] == package_root   # this package


def test_join_stops_a_process_that_overruns(monkeypatch):
    monkeypatch.setattr(_compile_ahead, "WAIT_S", 0.2)
    process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    began = time.perf_counter()
    _compile_ahead.join(process)
    assert process.returncode is not None and time.perf_counter() - began < 30


def test_a_stream_waits_for_it_before_the_first_stage_after_the_cloud(monkeypatch):
    source, target, faces, _ = load_sample()
    clouds = [next(source.frames) for _ in range(2)]
    retargeter = Retargeter.from_weights(None, "regressed", warn=False)
    retargeter.set_target(target, faces)
    seen = []
    for stage in retargeter.stages:
        def step(state, frame, stage=stage, inner=stage.step):
            seen.append(stage.name)
            return inner(state, frame)
        stage.step = step
    waits = []
    retargeter._compiler = type("Process", (), {"wait": lambda self, timeout=None:
                                                waits.append(list(seen))})()
    retargeter.step(clouds[0])
    cloud_stages = [stage.name for stage in retargeter.stages if stage.reads_cloud]
    assert waits == [cloud_stages] and retargeter._compiler is None
    retargeter.step(clouds[1])                            # once only
    assert len(waits) == 1
