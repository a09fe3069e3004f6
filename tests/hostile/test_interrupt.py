"""A model that never finishes (issue #27, part B, item 8): Ctrl-C stops it with one line and
exit code 130. ONNX Runtime held the call until SIGKILL; now every engine call runs where a
signal can reach it and the engine is told to stop (engines/interrupt.py).

The children start with SIGINT at its default (a background pytest job ignores it, and an
ignored signal stays ignored across exec)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack, tiny_msfnet_onnx

from msfnet.runtime.stack import save_stack

TRIPS = 10**15  # a Loop that would run for years


def spinning_model(path: Path) -> Path:
    """tiny_msfnet_onnx whose normals pass through a Loop of TRIPS iterations (each adds 0)."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    tiny_msfnet_onnx(path)
    model = onnx.load(str(path))
    graph = model.graph
    graph.node[-1].output[0] = "normals_raw"
    body = helper.make_graph(
        [
            helper.make_node("Identity", ["cond_in"], ["cond_out"]),
            helper.make_node("Add", ["x_in", "zero_f"], ["x_out"]),
        ],
        "spin",
        [
            helper.make_tensor_value_info("i", TensorProto.INT64, []),
            helper.make_tensor_value_info("cond_in", TensorProto.BOOL, []),
            helper.make_tensor_value_info("x_in", TensorProto.FLOAT, None),
        ],
        [
            helper.make_tensor_value_info("cond_out", TensorProto.BOOL, []),
            helper.make_tensor_value_info("x_out", TensorProto.FLOAT, None),
        ],
        [numpy_helper.from_array(np.array(0.0, np.float32), "zero_f")],
    )
    graph.initializer.extend(
        [
            numpy_helper.from_array(np.array(TRIPS, np.int64), "trips"),
            numpy_helper.from_array(np.array(True), "go"),
        ]
    )
    graph.node.append(
        helper.make_node("Loop", ["trips", "go", "normals_raw"], ["normals"], body=body)
    )
    onnx.save(model, str(path))
    return path


CHILD = """
import sys
import numpy as np
from msfnet.common.cli import run_command
from msfnet.runtime.engines.dispatch import EngineChoice, open_engine

engine = open_engine(EngineChoice(sys.argv[2], "fp32", "test", sys.argv[1]), 1)
images = np.ones((1, 4, 3, 8, 8), np.float32)
lights = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (1, 4, 1))

def body():
    print("running", flush=True)
    engine.run(images, lights)
    return 0

sys.exit(run_command("msf-spin", body))
"""


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _interrupt(proc: subprocess.Popen, wait_s: float = 30) -> tuple[int, str]:
    """SIGINT ``proc`` and collect its exit code and stderr; kill it if it does not end."""
    proc.send_signal(signal.SIGINT)
    try:
        _out, err = proc.communicate(timeout=wait_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        pytest.fail(f"Ctrl-C did not stop the inference within {wait_s} s")
    return proc.returncode, err


@pytest.mark.parametrize(
    "engine",
    [
        "onnxruntime",
        pytest.param("openvino", marks=pytest.mark.slow),  # stops at the grace period's end
    ],
)
def test_ctrl_c_stops_a_model_that_never_finishes(tmp_path: Path, engine: str) -> None:
    if engine == "openvino":
        pytest.importorskip("openvino", reason="openvino not installed")
    model = spinning_model(tmp_path / "spin.onnx")
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(model), engine],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_default_sigint,
    )
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "running", proc.communicate()
    time.sleep(0.5)  # inside the Loop by now
    assert proc.poll() is None, "the model finished: it was meant to spin"
    started = time.monotonic()
    code, err = _interrupt(proc)
    assert code == 130, err
    assert err == "msf-spin: interrupted; nothing was written\n"
    if engine == "onnxruntime":  # told to terminate: stops at its next node, at once
        assert time.monotonic() - started < 5


@pytest.mark.slow
def test_msf_run_with_a_spinning_model_stops_on_ctrl_c(tmp_path: Path) -> None:
    model = spinning_model(tmp_path / "spin.onnx")
    folder = save_stack(sphere_stack(n=6, h=24, w=28), tmp_path / "s")
    out = tmp_path / "o"
    proc = subprocess.Popen(
        [
            *(sys.executable, "-m", "msfnet.runtime.cli.run", str(folder), "--onnx", str(model)),
            *("--engine", "onnxruntime", "--no-maps", "-o", str(out)),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_default_sigint,
    )
    time.sleep(6)  # loaded and spinning (the stack is tiny; msf-run starts in ~2 s)
    assert proc.poll() is None, proc.communicate()
    code, err = _interrupt(proc)
    assert code == 130, err
    assert err.strip().splitlines()[-1].startswith("msf-run: interrupted"), err
    assert not out.exists()


def slow_compiling_model(path: Path, nodes: int = 10_000) -> Path:
    """tiny_msfnet_onnx whose normals pass through ``nodes`` multiplications by one: ONNX
    Runtime opens it in a second; OpenVINO's compile grows faster than the node count (here
    2,000 nodes 1.4 s, 8,000 nodes 47 s on 2 AMD EPYC Zen 4 cores; 10,000 leaves a faster CPU
    compiling well past the test's signal)."""
    onnx = pytest.importorskip("onnx")
    from onnx import helper, numpy_helper

    tiny_msfnet_onnx(path)
    model = onnx.load(str(path))
    graph = model.graph
    graph.node[-1].output[0] = "t0"
    graph.initializer.append(numpy_helper.from_array(np.array(1.0, np.float32), "one"))
    names = [f"t{i}" for i in range(nodes)] + ["normals"]
    graph.node.extend(
        helper.make_node("Mul", [names[i], "one"], [names[i + 1]]) for i in range(nodes)
    )
    onnx.save(model, str(path))
    return path


@pytest.mark.slow
def test_ctrl_c_stops_an_openvino_compile_that_takes_minutes(tmp_path: Path) -> None:
    """Issue #48: a valid model that OpenVINO compiles for minutes held msf-run on that engine,
    deaf to Ctrl-C (the compile ran on the main thread, where Python's handler waits for it)."""
    pytest.importorskip("openvino", reason="openvino not installed")
    model = slow_compiling_model(tmp_path / "slow.onnx")
    folder = save_stack(sphere_stack(n=6, h=24, w=28), tmp_path / "s")
    out = tmp_path / "o"
    env = {**os.environ, "MSFNET_OPENVINO_CACHE": "off"}  # compiled afresh, not from a cache
    proc = subprocess.Popen(
        [
            *(sys.executable, "-m", "msfnet.runtime.cli.run", str(folder), "--onnx", str(model)),
            *("--engine", "openvino", "--no-maps", "-o", str(out)),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_default_sigint,
        env=env,
    )
    time.sleep(8)  # started (~2 s) and compiling (over a minute on an idle Zen 4)
    assert proc.poll() is None, proc.communicate()
    code, err = _interrupt(proc, wait_s=25)  # the grace period (5 s) and the exit
    assert code == 130, err
    assert err.strip().splitlines()[-1].startswith("msf-run: interrupted"), err
    assert not out.exists()


@pytest.mark.parametrize("command", ["run", "inspect"])
def test_a_model_that_never_ends_stops_at_the_time_limit(tmp_path: Path, command: str) -> None:
    """Issue #48: a model with an endless Loop hung msf-run and msf-inspect --onnx for good;
    --timeout bounds every compile and call: one line, exit 2, nothing written."""
    model = spinning_model(tmp_path / "spin.onnx")
    folder = save_stack(sphere_stack(n=6, h=24, w=28), tmp_path / "s")
    out = tmp_path / "o"
    extra = ["--depth", "0.1"] if command == "inspect" else ["--no-maps"]
    proc = subprocess.run(
        [
            *(sys.executable, "-m", f"msfnet.runtime.cli.{command}", str(folder), "--onnx"),
            *(str(model), "--engine", "onnxruntime", "--timeout", "2", "-o", str(out), *extra),
        ],
        capture_output=True,
        text=True,
        timeout=120,  # a hang guard: without the limit it spins for years
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert "did not finish within the time limit (2 s)" in lines[-1], lines
    assert lines[-1].startswith(f"msf-{command}: error:"), lines
    assert not out.exists()


def test_the_time_limit_is_a_positive_number_of_seconds() -> None:
    from msfnet.common.errors import InputError
    from msfnet.runtime.options import ModelOptions

    with pytest.raises(InputError, match="timeout"):
        ModelOptions(timeout_s=0)
    assert ModelOptions(timeout_s=1.5).timeout_s == 1.5


@pytest.mark.slow
def test_msf_bench_holds_each_format_to_its_time_limit(ball_dir: Path, tmp_path: Path) -> None:
    """Issue #48: a model with an endless Loop hung `msf-bench --onnx` (no per-format limit);
    with --timeout each format's row fails at its limit and the report is written."""
    model = spinning_model(tmp_path / "spin.onnx")
    out = tmp_path / "bench"
    argv = ["--onnx", str(model), "--timeout", "3", "--data", str(ball_dir.parents[1])]
    proc = subprocess.run(
        [sys.executable, "-m", "msfnet.bench.cli", *argv, "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=300,  # a hang guard: without the limit the first row never ends
    )
    assert proc.returncode == 0, proc.stderr
    report = (out / "REPORT.md").read_text()
    assert report.count("did not finish within the time limit (3 s)") >= 1, report


def test_a_time_limit_belongs_to_its_thread_and_pickles_whole() -> None:
    """Review: the limits were one process-wide list; a 0.05 s block in another thread
    cancelled the main thread's unlimited call, and a limit did nothing off the main thread."""
    import pickle
    import threading

    from msfnet.runtime.engines.interrupt import TimeLimit, run_interruptible, time_limit

    inside = threading.Event()
    leave = threading.Event()

    def other() -> None:
        with time_limit(0.05):
            inside.set()
            leave.wait(5)

    thread = threading.Thread(target=other)
    thread.start()
    inside.wait(5)
    try:  # the main thread has no limit: its 0.6 s call runs to its end
        assert run_interruptible(lambda: time.sleep(0.6) or "done", lambda: None) == "done"
    finally:
        leave.set()
        thread.join()
    seen: list[BaseException] = []

    def limited() -> None:  # off the main thread, the limit holds too
        with time_limit(0.2):
            try:
                run_interruptible(lambda: time.sleep(1.0), lambda: None)
            except TimeLimit as exc:
                seen.append(exc)

    worker = threading.Thread(target=limited)
    worker.start()
    worker.join(10)
    assert len(seen) == 1 and seen[0].seconds == 0.2
    copy = pickle.loads(pickle.dumps(seen[0]))
    assert isinstance(copy, TimeLimit) and str(copy) == str(seen[0])
