"""The exact torch MSF-Net, checkpoint I/O and training."""
