"""Registers the built-in source adapters with :func:`sensors.source.open_source`, most specific
first. Optional adapters (rosbags, OpenNI, RealSense, libfreenect) load their libraries on open."""

from __future__ import annotations

from sensors.carmen import CarmenSource
from sensors.recording_source import RecordingSource
from sensors.source import register_opener
from sensors.tum_folder import TumFolderSource

register_opener("rgbdnav recording", RecordingSource.try_open)
register_opener("TUM RGB-D folder", TumFolderSource.try_open)
register_opener("CARMEN log", CarmenSource.try_open)

# Optional adapters: their try_open only looks at the path; rosbags/openni load when opening.
from sensors.freenect_source import FreenectSource  # noqa: E402
from sensors.openni_source import OpenNISource  # noqa: E402
from sensors.realsense_source import RealSenseSource  # noqa: E402
from sensors.rosbag_source import RosbagSource  # noqa: E402

register_opener("rosbag", RosbagSource.try_open)
register_opener("OpenNI2", OpenNISource.try_open, uri=True)
register_opener("RealSense", RealSenseSource.try_open, uri=True)
register_opener("libfreenect", FreenectSource.try_open, uri=True)
