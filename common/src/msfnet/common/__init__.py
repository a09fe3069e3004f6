"""What every part of msfnet shares: errors, the atomic writer, CLI plumbing, signals, image
files, the camera model and CPU features. Depends on no other msfnet part."""

from msfnet.common.privacy import quiet_library_telemetry as _quiet_library_telemetry
from msfnet.common.signals import guard_startup as _guard_startup

# the first msfnet import of any program (every ``msfnet`` __init__ imports from here): the
# libraries' usage reports are off before any of them is loaded (msfnet.common.privacy)
_quiet_library_telemetry()
# the first msfnet import of a command's process: Ctrl-C from here on is one line, not a
# traceback (a no-op in any other program)
_guard_startup()
