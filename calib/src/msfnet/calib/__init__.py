"""Light calibration (mirror and matte spheres) and stack capture from cameras and light rigs.

Never imports torch; depthai and pyserial are imported lazily inside their back-ends.
"""

from msfnet.calib.directions import DirectionResult, LightEstimate, estimate_directions
from msfnet.calib.intensities import estimate_intensities
from msfnet.calib.sphere import Circle, fit_circles_from_images, fit_circles_from_mask

__all__ = [
    "Circle",
    "DirectionResult",
    "LightEstimate",
    "estimate_directions",
    "estimate_intensities",
    "fit_circles_from_images",
    "fit_circles_from_mask",
]
