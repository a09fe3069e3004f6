"""What every part of msfnet shares: errors, the atomic writer, CLI plumbing, signals, image
files, the camera model and CPU features. Depends on no other msfnet part."""
