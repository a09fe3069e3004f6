"""msf-run --ray ray://HOST:PORT, the documented cluster address, against a real Ray head.

The head runs in a private network namespace (``unshare -n``, whose only interface is
loopback): Ray's GCS and raylet listen on every interface and take no bind address, so this is
how the test keeps its cluster off the network. It runs with token authentication (a token
of its own, in the environment), and checks that a client with another token is refused. The
batch goes through Ray's client (the ``ray[client]`` extra) and must give what the same batch
gives locally.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.runtime.api import default_model_path
from msfnet.runtime.stack import save_stack

SCRIPT = Path(__file__).with_name("ray_loopback.py")


def _private_network() -> None:
    """Skip unless this process may create a network namespace (root, or user namespaces)."""
    unshare = shutil.which("unshare")
    if unshare is None:
        pytest.skip("needs util-linux's unshare for a loopback-only network namespace")
    probe = subprocess.run([unshare, "-n", "true"], capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"cannot create a network namespace here: {probe.stderr.strip()}")


@pytest.mark.slow
def test_a_batch_through_the_ray_client_equals_a_local_run(tmp_path: Path) -> None:
    pytest.importorskip("ray", reason="msf-run --ray needs the [ray] extra")
    pytest.importorskip("grpc", reason="ray:// addresses need Ray's client: msfnet[ray]")
    _private_network()
    stacks = [
        save_stack(sphere_stack(n=5 + i, h=24 + 4 * i, w=28, seed=i), tmp_path / "in" / f"s{i}")
        for i in range(3)
    ]
    # a model file of the driver's own: its bytes travel to the workers with the job
    model = shutil.copy(default_model_path(), tmp_path / "deployed.onnx")
    work = tmp_path / "work"
    work.mkdir()
    proc = subprocess.run(
        ["unshare", "-n", sys.executable, str(SCRIPT), str(work), str(model), *map(str, stacks)],
        capture_output=True,
        text=True,
        timeout=540,
    )
    logs = "\n".join(f"--- {p.name}\n{p.read_text()[-3000:]}" for p in sorted(work.glob("*.log")))
    assert proc.returncode == 0, proc.stdout + proc.stderr + logs
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    print(report)  # the test's record: interfaces, listening sockets, exit codes
    assert report["interfaces"] == ["lo"]
    assert report["listening"] and report["all_loopback"], report
    assert report["refused_without_token"], "a client with another token got in"
    assert report["ray_rc"] == 0 and report["local_rc"] == 0, logs

    summary = json.loads((work / "ray" / "summary.json").read_text())
    assert summary["mode"] == "ray" and summary["totals"]["failed"] == 0
    assert [row["name"] for row in summary["stacks"]] == ["s0", "s1", "s2"]
    assert all(row["worker"] for row in summary["stacks"])  # each ran on a Ray worker
    for s in stacks:
        remote = np.load(work / "ray" / s.name / "normals.npy")
        local = np.load(work / "local" / s.name / "normals.npy")
        # the same model, engine and thread count: equal up to float rounding
        np.testing.assert_allclose(remote, local, rtol=0, atol=1e-6)
        remote_metrics = json.loads((work / "ray" / s.name / "metrics.json").read_text())
        local_metrics = json.loads((work / "local" / s.name / "metrics.json").read_text())
        assert remote_metrics["mae_deg"] == pytest.approx(local_metrics["mae_deg"], abs=1e-5)
        profile = json.loads((work / "ray" / s.name / "profile.json").read_text())
        assert profile["model"] == str(model)  # the driver's file, not the worker's copy
