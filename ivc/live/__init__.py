"""Stage 5b: live correction over OpenIGTLink (docs/live.md).

``LiveCorrector`` connects to a tracking server (PLUS, a tracker daemon, anything that streams
OpenIGTLink TRANSFORM or NDARRAY messages), corrects (and optionally predicts) each sensor,
and serves the result to any number of OpenIGTLink clients (3D Slicer, PLUS, your own).
"""

from ivc.igtl import NDArrayMessage, TrackingDataMessage, parse_url
from ivc.live.loop import LiveCorrector, LiveStats, output_device_name

__all__ = ["LiveCorrector", "LiveStats", "NDArrayMessage", "TrackingDataMessage", "output_device_name", "parse_url"]
