"""Reliability round three (issue #48): `--ray HOST:PORT` to a closed port retried forever
(Ray's own warnings, 11 lines), and ray:// addresses that cannot be valid gave up after ~34 s.
Addresses are checked before any work, and one bounded TCP connection decides reachability."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import pytest
from _runtime_helpers import sphere_stack

from msfnet.common.errors import InputError
from msfnet.runtime.batch.ray_cluster import (
    RAY_CLIENT_PORT,
    check_reachable,
    cluster_endpoint,
)
from msfnet.runtime.stack import save_stack


@pytest.mark.parametrize(
    ("address", "endpoint"),
    [
        ("", None),
        ("auto", None),
        ("127.0.0.1:6379", ("127.0.0.1", 6379)),
        ("head.example:6379", ("head.example", 6379)),
        ("ray://head", ("head", RAY_CLIENT_PORT)),
        ("ray://[::1]:10001", ("::1", 10001)),
        ("ray_head:6379", ("ray_head", 6379)),  # a Docker service name
        ("head.example.com.:6379", ("head.example.com.", 6379)),  # absolute
    ],
)
def test_addresses_ray_takes(address: str, endpoint: tuple[str, int] | None) -> None:
    assert cluster_endpoint(address) == endpoint


@pytest.mark.parametrize(
    "address",
    ["ray://:::::", "ray://head:99999", "256.1.1.1:6379", "ray://256.1.1.1", "head", "h:0"],
)
def test_addresses_that_cannot_be_valid(address: str) -> None:
    with pytest.raises(InputError, match="not a cluster address"):
        cluster_endpoint(address)


def _closed_port() -> int:
    with socket.socket() as s:  # a port just freed: nothing listens there
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_closed_port_is_one_line_not_endless_retries(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="nothing listens there"):
        check_reachable(f"127.0.0.1:{_closed_port()}")
    stacks = [save_stack(sphere_stack(n=6, h=16, w=16), tmp_path / k) for k in "ab"]
    out = tmp_path / "out"
    argv = [*map(str, stacks), "--method", "l2", "--ray", f"127.0.0.1:{_closed_port()}"]
    proc = subprocess.run(
        [sys.executable, "-m", "msfnet.runtime.cli.run", *argv, "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=120,  # a hang guard: Ray's own retries never ended
    )
    if "needs Ray" in proc.stderr:
        pytest.skip("Ray is not installed (the [ray] extra)")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "nothing listens there" in lines[0], lines
    assert not out.exists()
