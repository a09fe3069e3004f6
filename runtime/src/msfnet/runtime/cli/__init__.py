"""The runtime's commands: msf-run and msf-eval."""
