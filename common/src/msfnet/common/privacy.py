"""No usage reports from the libraries msfnet runs on, unless the user asks for them.

Four of them report usage by default:
- ONNX Runtime 1.32 (Linux builds since 1.29) opens an event store and a device id under
  ``~/.cache/Microsoft/DeveloperTools/.onnxruntime`` (and a ``$TMPDIR/.ses``) in every
  process that imports it, to upload from (process, session, model, execution-provider and
  error events, per the change that added it); ``ORT_DISABLE_TELEMETRY=1`` before it
  initialises creates nothing.
- depthai 3 looks up its collector (a DNS query for b.luxonis.com) on ``import depthai``;
  ``DEPTHAI_TELEMETRY=0`` stops it.
- OpenVINO sends an event on ``import openvino`` (see msfnet.runtime.engines.openvino's
  import_openvino, which has no switch to set and hides the telemetry package instead).
- Ray (the ``[ray]`` extra, for cluster batches) collects usage stats from a cluster it
  starts (its docs: opt-out, ``RAY_USAGE_STATS_ENABLED=0``). Ray 2.60's dashboard process
  still probes the cloud metadata services (169.254.169.254, metadata.google.internal) before
  it reads that switch; no switch stops it: docs/run.md says so.

An inspection station or a lab machine should not talk to the network on its own, so the
first msfnet import sets the switches above for this process and its children, where the
user has not set them. ``MSFNET_TELEMETRY=1`` leaves every library as it is configured.
Standard library only: this runs before anything heavy is imported.
"""

from __future__ import annotations

import os

OPT_IN_ENV = "MSFNET_TELEMETRY"  # "1": leave the libraries' telemetry as they configure it

# each library's own switch, read when the library initialises
LIBRARY_SWITCHES = {
    "ORT_DISABLE_TELEMETRY": "1",
    "DEPTHAI_TELEMETRY": "0",
    "RAY_USAGE_STATS_ENABLED": "0",
}


def telemetry_allowed() -> bool:
    """Whether the user asked for the libraries' usage reports (MSFNET_TELEMETRY=1)."""
    return os.environ.get(OPT_IN_ENV) == "1"


def quiet_library_telemetry() -> None:
    """Set each library's telemetry switch to off, unless the user set it (to a non-empty
    value) or allowed telemetry."""
    if telemetry_allowed():
        return
    for name, value in LIBRARY_SWITCHES.items():
        # empty counts as unset: what `ENV X=` or `export X=` leave, and both libraries read
        # it as telemetry on
        if not os.environ.get(name, "").strip():
            os.environ[name] = value


__all__ = ["LIBRARY_SWITCHES", "OPT_IN_ENV", "quiet_library_telemetry", "telemetry_allowed"]
