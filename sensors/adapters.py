"""Registers the built-in source adapters with :func:`sensors.source.open_source`, most specific
first. Optional adapters (rosbags, OpenNI) import their heavy libraries only when opening."""

from __future__ import annotations

from sensors.recording_source import RecordingSource
from sensors.source import register_opener

register_opener("rgbdnav recording", RecordingSource.try_open)
