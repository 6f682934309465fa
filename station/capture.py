"""The bus as the analysis sees it, live: ICD frames kept in memory during a run.

A calibration decides its next trim points from what it has measured so far,
so it cannot wait for the recording to be written and read back. This
listener keeps exactly the frames the offline reader keeps (same table,
``icd_frames``), and hands any stretch of them to ``build_timeline``: the
live procedure and ``station analyze`` of its recording therefore segment and
demodulate the very same samples the same way.

It runs on the bus reader's thread, once per frame, so it only appends bytes.
"""

from __future__ import annotations

import threading

import can
import numpy as np

from station.analysis.commanded import commanded_timeline
from station.analysis.timeline import (
    PAYLOAD_BYTES,
    FrameKind,
    Timeline,
    build_timeline,
    icd_frames,
)
from station.commands import CommandLog
from station.errors import DeviceError
from station.recording import RecordingMetadata

_PADDING = bytes(PAYLOAD_BYTES)


class FrameCapture(can.Listener):
    """Every ICD frame since it was attached, in bus order; ``timeline`` reads a stretch."""

    def __init__(self, metadata: RecordingMetadata) -> None:
        self.metadata = metadata
        self._table = icd_frames(metadata.drive_node, metadata.sensor_node)
        self._lock = threading.Lock()
        self._kinds = bytearray()
        self._payloads = bytearray()
        self._malformed = 0
        self._syncs = 0

    def on_message_received(self, msg: can.Message) -> None:
        spec = self._table.get(msg.arbitration_id)
        if spec is None or msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            return
        kind, size = spec
        data = msg.data
        with self._lock:
            if len(data) != size:
                self._malformed += 1
                return
            self._kinds.append(kind)
            if kind is FrameKind.SYNC:
                self._syncs += 1
            # Rows of 8 bytes whatever the kind: a SYNC's counter sits in column 0.
            self._payloads += data
            if size < PAYLOAD_BYTES:
                self._payloads += _PADDING[size:]

    def stop(self) -> None:
        """can.Listener protocol: nothing to release."""

    def syncs_seen(self) -> int:
        """SYNCs seen since attached: the recording's sample index of the next SYNC."""
        with self._lock:
            return self._syncs

    def mark(self) -> int:
        """A bookmark: ``timeline(since=mark)`` covers only what comes after it."""
        with self._lock:
            return len(self._kinds)

    def timeline(self, since: int = 0, commands: CommandLog | None = None) -> Timeline:
        """Samples from the first SYNC at or after ``since`` up to now.

        With ``commands`` (a drive that reports nothing on the bus) the drive's
        columns come from the station's own write log instead.
        """
        with self._lock:
            kinds = np.frombuffer(bytes(self._kinds[since:]), dtype=np.uint8)
            start = since * PAYLOAD_BYTES
            payloads = np.frombuffer(bytes(self._payloads[start:]), dtype=np.uint8)
            malformed = self._malformed
            syncs_total = self._syncs
        syncs = np.flatnonzero(kinds == FrameKind.SYNC)
        if syncs.size == 0:
            raise DeviceError("bus", "no SYNC frame was seen: the bench produced no samples")
        first = int(syncs[0])
        timeline = build_timeline(
            self.metadata,
            kinds[first:],
            payloads.reshape(-1, PAYLOAD_BYTES)[first:],
            frames_malformed=malformed,
        )
        if commands is None:
            return timeline
        # The log counts samples from the capture's first SYNC; this stretch starts later.
        before = syncs_total - int(syncs.size)
        return commanded_timeline(timeline, commands.entries(), commands.timing,
                                  first_sample=before)
