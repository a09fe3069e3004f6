"""Run by tests/runtime/batch/test_ray_client.py inside a private network namespace
(``unshare -n``): a Ray head reachable on loopback only, msf-run through its ``ray://`` client
address, and the same batch run locally.

Ray's GCS and raylet listen on every interface whatever ``--node-ip-address`` says (127.0.0.1
is replaced by the machine's address), so the only way to keep a test's head off the network is
a namespace whose one interface is ``lo``. Usage::

    unshare -n python ray_loopback.py WORKDIR MODEL STACK [STACK ...]

Prints one JSON line: the listening addresses seen in the namespace and the two exit codes.
"""

from __future__ import annotations

import fcntl
import json
import os
import secrets
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SIOCGIFFLAGS, SIOCSIFFLAGS, IFF_UP = 0x8913, 0x8914, 0x1
START_TIMEOUT_S = 180.0


def loopback_up() -> None:
    """A new network namespace has ``lo`` down: bring it up (what ``ip link set lo up`` does,
    without needing iproute2)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        flags = struct.unpack("16sh", fcntl.ioctl(s, SIOCGIFFLAGS, struct.pack("16sh", b"lo", 0)))
        fcntl.ioctl(s, SIOCSIFFLAGS, struct.pack("16sh", b"lo", flags[1] | IFF_UP))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def listening() -> list[str]:
    """Local addresses of the listening TCP sockets in this namespace (from /proc/net/tcp*),
    as hex strings: 0100007F is 127.0.0.1, ...0100000000 is ::1."""
    found = []
    for name in ("tcp", "tcp6"):
        path = Path("/proc/net") / name
        if not path.exists():
            continue
        for line in path.read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A":  # TCP_LISTEN
                found.append(fields[1].split(":")[0])
    return found


def is_loopback(hex_addr: str) -> bool:
    if len(hex_addr) == 8:  # IPv4, little-endian bytes: the first octet is the last pair
        return hex_addr[-2:] == "7F"
    # IPv6: ::1, or an IPv4-mapped loopback (::ffff:127.x.x.x)
    return hex_addr == "00000000000000000000000001000000" or (
        hex_addr[:24] == "0000000000000000FFFF0000" and hex_addr[-2:] == "7F"
    )


def wait_for(port: int, head: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if head.poll() is not None:
            raise SystemExit(f"the Ray head exited with {head.returncode}")
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return
        except OSError:
            time.sleep(0.5)
    raise SystemExit(f"the Ray client server did not listen within {START_TIMEOUT_S:.0f} s")


PROBE = (
    "import sys, ray; ray.init(sys.argv[1], logging_level='ERROR'); "
    "assert ray.cluster_resources().get('CPU'); ray.shutdown()"
)


def wait_for_client(address: str, log: Path) -> None:
    """The client server listens before the cluster behind it answers (on a loaded machine,
    long enough for Ray's own connection retries to give up): connect once, as a probe,
    until it works."""
    deadline = time.monotonic() + START_TIMEOUT_S
    with log.open("w") as out:
        while True:
            probe = subprocess.run([sys.executable, "-c", PROBE, address], stdout=out, stderr=out)
            if probe.returncode == 0:
                return
            if time.monotonic() > deadline:
                raise SystemExit(f"no Ray client connection to {address} (see {log})")
            time.sleep(1.0)


def refused_without_token(address: str, log: Path) -> bool:
    """Whether a client with another token is turned away."""
    env = {**os.environ, "RAY_AUTH_TOKEN": secrets.token_hex(32)}
    with log.open("w") as out:
        try:
            probe = subprocess.run(
                [sys.executable, "-c", PROBE, address], stdout=out, stderr=out, env=env, timeout=120
            )
        except subprocess.TimeoutExpired:
            return True  # it never got in
    return probe.returncode != 0


def stop(head: subprocess.Popen[bytes]) -> None:
    """SIGTERM to the head's process group (it stops what it started), then SIGKILL to
    whatever of that group is still there after a grace period."""
    try:
        os.killpg(head.pid, signal.SIGTERM)
    except ProcessLookupError:  # it had already stopped, with everything it started
        return
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline:
        head.poll()
        try:
            os.killpg(head.pid, 0)  # anyone left in the group?
        except ProcessLookupError:
            return
        time.sleep(0.2)
    os.killpg(head.pid, signal.SIGKILL)
    head.wait()


def msf_run(args: list[str], log: Path) -> int:
    code = "import sys; from msfnet.runtime.cli.run import main; sys.exit(main(sys.argv[1:]))"
    with log.open("w") as out:
        return subprocess.run(
            [sys.executable, "-c", code, *args], stdout=out, stderr=subprocess.STDOUT
        ).returncode


def main(argv: list[str]) -> int:
    work, model, stacks = Path(argv[0]), argv[1], argv[2:]
    loopback_up()
    client = free_port()
    env = {
        **os.environ,
        "RAY_USAGE_STATS_ENABLED": "0",
        "RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S": "0",  # stop at once, nothing to drain here
        # token authentication, as docs/run.md advises, with a token of this run only (in the
        # environment: nothing written to ~/.ray); explicit for head and drivers alike, since
        # with RAY_AUTH_MODE unset Ray's choice depends on whether ~/.ray/auth_token exists
        "RAY_AUTH_MODE": "token",
        "RAY_AUTH_TOKEN": secrets.token_hex(32),
    }
    os.environ.update(env)  # the probes and msf-run inherit it
    # Ray's Unix sockets live under --temp-dir, and their paths may not exceed 107 bytes: a
    # short folder of our own rather than pytest's long tmp_path
    session = tempfile.mkdtemp(prefix="msfray-")
    with (work / "head.log").open("w") as log:
        head = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "ray.scripts.scripts",
                "start",
                "--head",
                "--block",
                f"--port={free_port()}",
                f"--ray-client-server-port={client}",
                "--num-cpus=2",
                "--include-dashboard=false",
                "--disable-usage-stats",
                f"--temp-dir={session}",
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,  # one process group: the head and everything it starts
        )
    try:
        wait_for(client, head)
        wait_for_client(f"ray://127.0.0.1:{client}", work / "probe.log")
        refused = refused_without_token(f"ray://127.0.0.1:{client}", work / "refused.log")
        common = [*stacks, "--onnx", model, "--engine", "onnxruntime", "--threads", "1"]
        ray_rc = msf_run(
            [*common, "--ray", f"ray://127.0.0.1:{client}", "-o", str(work / "ray")],
            work / "ray.log",
        )
        sockets = listening()  # while the head still runs
        local_rc = msf_run([*common, "-o", str(work / "local")], work / "local.log")
    finally:
        stop(head)
        shutil.rmtree(session, ignore_errors=True)
    print(
        json.dumps(
            {
                "interfaces": [name for _, name in socket.if_nameindex()],
                "listening": sockets,
                "all_loopback": all(is_loopback(a) for a in sockets),
                "refused_without_token": refused,
                "ray_rc": ray_rc,
                "local_rc": local_rc,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
