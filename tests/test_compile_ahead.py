"""The cold start's second process (``minretarget._compile_ahead``)."""
import json
import os
import signal
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
# set_target) starts the second process; let it finish first, and the stages after the
# cloud's must then compile nothing in the first one: the second one's frames and target
# have the stream's types, so what it wrote to the cache is what the stream asks for.
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
    started[0].process.wait()
    for stage in retargeter.stages:            # mark where the cloud's stages end
        def step(state, frame, stage=stage, inner=stage.step):
            tail[0] = tail[0] or not stage.reads_cloud
            return inner(state, frame)
        stage.step = step
    retargeter.step(next(source.frames))
    print(json.dumps({"started": [p is not None for p in started],
                      "stopped": retargeter._compiler is None,
                      "returncode": started[0].process.returncode if started and started[0]
                                    else None,
                      "tail_compiled": compiled}))
""")


@pytest.mark.parametrize("name", ["fitted", "regressed"])
def test_the_second_process_compiles_the_later_stages_of_the_stream(tmp_path, name):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    env.pop(_compile_ahead.SWITCH, None)
    env.pop("NUMBA_DISABLE_JIT", None)
    result = subprocess.run([sys.executable, "-c", COLD_START, name], env=env,
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    run = json.loads(result.stdout.splitlines()[-1])
    assert run["started"] == [True] and run["stopped"] and run["returncode"] == 0, run
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
    launched, real_popen = [], subprocess.Popen

    def popen(argv, **kwargs):
        launched.append((argv, kwargs))
        return real_popen([sys.executable, "-c", ""], stdout=subprocess.PIPE, text=True)
    monkeypatch.setattr(_compile_ahead.subprocess, "Popen", popen)
    second = _compile_ahead.start(config)
    assert isinstance(second, _compile_ahead.SecondProcess)
    assert _compile_ahead.start(config) is None                 # once per config
    second.stop()
    (argv, kwargs), = launched
    assert argv[1:] == ["-m", "minretarget._compile_ahead", config.to_json()]
    assert kwargs["env"][_compile_ahead.SWITCH] == "0"          # it starts none of its own
    package_root = str(Path(_compile_ahead.__file__).resolve().parents[1])
    assert kwargs["env"]["PYTHONPATH"].split(os.pathsep)[0] == package_root   # this package


def _saying(script):
    """A SecondProcess around a Python script (its lines on standard output are what the
    stream hears)."""
    return _compile_ahead.SecondProcess(subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(script)], stdout=subprocess.PIPE, text=True))


def test_a_stream_waits_only_for_a_stage_being_compiled_there():
    second = _saying("""
        import time
        print("end lbs", flush=True)
        print("begin foot_lock", flush=True)
        time.sleep(1.0)
        print("end foot_lock", flush=True)
        time.sleep(60)
    """)
    heard = time.perf_counter() + 30
    while "foot_lock" not in second._begun:       # until it has said its first two lines
        assert time.perf_counter() < heard, "the second process said nothing"
        time.sleep(0.01)
    began = time.perf_counter()
    second.await_stage("smrm")      # not begun there: the stream compiles it
    second.await_stage("lbs")       # done there
    assert time.perf_counter() - began < 0.3
    second.await_stage("foot_lock")     # being compiled: wait for its end
    assert "foot_lock" in second._ended and time.perf_counter() - began < 30
    second.stop()
    gone = _saying("""
        print("begin smrm", flush=True)
    """)
    gone.process.wait()
    began = time.perf_counter()
    gone.await_stage("smrm")        # begun, never ended, gone: no wait for WAIT_S
    assert time.perf_counter() - began < _compile_ahead.WAIT_S / 2
    assert gone._gone and "smrm" not in gone._ended
    gone.stop()


def test_stop_asks_then_kills(monkeypatch):
    # Asked: the second process's SIGTERM handler raises, so it leaves as an exception does
    # (numba then removes a cache file it was writing), not killed.
    listening = subprocess.Popen([sys.executable, "-c", textwrap.dedent("""
        import signal, sys, time
        from minretarget._compile_ahead import _raise_stopped
        signal.signal(signal.SIGTERM, _raise_stopped)
        print("ready", file=sys.stderr, flush=True)
        time.sleep(60)
    """)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert listening.stderr.readline() == "ready\n"
    _compile_ahead.SecondProcess(listening).stop()
    assert listening.returncode == 1 and "_Stopped" in listening.stderr.read()
    # Deaf to it: killed after STOP_S.
    monkeypatch.setattr(_compile_ahead, "STOP_S", 0.2)
    deaf = subprocess.Popen([sys.executable, "-c", textwrap.dedent("""
        import signal, sys, time
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        print("ready", file=sys.stderr, flush=True)
        time.sleep(60)
    """)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert deaf.stderr.readline() == "ready\n"
    began = time.perf_counter()
    _compile_ahead.SecondProcess(deaf).stop()
    assert deaf.returncode == -signal.SIGKILL and time.perf_counter() - began < 30


def test_a_stream_asks_before_each_later_stage_and_stops_it_after_its_first_frame():
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
    calls = []

    class Second:
        def await_stage(self, name):
            calls.append(("await", name, len(seen)))

        def stop(self):
            calls.append(("stop", len(seen)))

    retargeter._compiler = Second()
    retargeter.step(clouds[0])
    names = [stage.name for stage in retargeter.stages]
    later = [(place, name) for place, name in enumerate(names)
             if not retargeter.stages[place].reads_cloud]
    assert calls == [("await", name, place) for place, name in later] + [("stop", len(names))]
    assert retargeter._compiler is None
    retargeter.step(clouds[1])                            # once only
    assert len(calls) == len(later) + 1
