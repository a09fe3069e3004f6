"""What every part of msfnet shares: errors, the atomic writer, CLI plumbing, signals, image
files, the camera model and CPU features. Depends on no other msfnet part."""

from msfnet.common.signals import guard_startup as _guard_startup

# the first msfnet import of a command's process: Ctrl-C from here on is one line, not a
# traceback (a no-op in any other program)
_guard_startup()
