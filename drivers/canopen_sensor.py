"""The bench's MEMS acceleration sensor over CANopen (ICD.md §3).

Samples arrive as one synchronous TPDO per SYNC, thousands per second, on the
notifier thread; the capture path therefore only copies the 8 raw bytes into
a preallocated buffer (doubled when full) and decodes everything at the end
with one numpy view. Losses are not guessed from timing but read from the
sensor's own sample counter, so a capture says exactly how many samples the
bus dropped.
"""

from __future__ import annotations

import logging
import threading
from enum import IntEnum

import canopen
import numpy as np
import numpy.typing as npt

from drivers.base import LIVENESS_TIMEOUT_S, AccelerationSensor, DeviceIdentity, SensorCapture
from drivers.canbus import (
    HeartbeatWatch,
    SdoChannel,
    attach_remote_node,
    check_alive,
    check_node_id,
    detach_remote_node,
    start_node,
)
from drivers.eds import DeviceKind, load_od
from station.cia301 import TPDO1_COB_BASE
from station.core import SENSOR_COUNTER_MODULUS, SENSOR_RANGES_G
from station.errors import DeviceStateError, InputError

log = logging.getLogger(__name__)


class SensorObject(IntEnum):
    """Object indices of ICD.md §3."""

    RANGE = 0x2000
    SENSITIVITY = 0x2001
    SAMPLE_COUNTER = 0x2010


SAMPLE_FRAME_BYTES = 8
SAMPLE_DTYPE = np.dtype([("counter", "<u2"), ("x", "<i2"), ("y", "<i2"), ("z", "<i2")])
"""TPDO1 layout: sample counter U16, then X, Y, Z as I16, little-endian."""
DEFAULT_INITIAL_CAPACITY = 1 << 16


def decode_samples(
    raw: bytes | bytearray | memoryview,
) -> tuple[npt.NDArray[np.uint16], npt.NDArray[np.int16]]:
    """Split concatenated TPDO1 payloads into counters and (n, 3) X/Y/Z counts."""
    if len(raw) % SAMPLE_FRAME_BYTES:
        raise ValueError(
            f"{len(raw)} bytes is not a whole number of {SAMPLE_FRAME_BYTES}-byte samples"
        )
    records = np.frombuffer(raw, dtype=SAMPLE_DTYPE)
    counter = records["counter"].astype(np.uint16)
    counts = np.stack([records["x"], records["y"], records["z"]], axis=1).astype(np.int16)
    return counter, counts


def count_lost_samples(counter: npt.NDArray[np.uint16]) -> int:
    """Samples missing between consecutive counters (they advance by 1 per SYNC, mod 65536).

    A repeated counter is a duplicate, not 65535 losses.
    """
    if counter.size < 2:
        return 0
    steps = np.remainder(np.diff(counter.astype(np.int64)), SENSOR_COUNTER_MODULUS)
    gaps = steps[steps != 0] - 1
    return int(gaps.sum())


class SampleBuffer:
    """Raw TPDO1 payloads in arrival order; append is what the notifier thread pays per frame."""

    def __init__(self, initial_capacity: int = DEFAULT_INITIAL_CAPACITY) -> None:
        if initial_capacity < 1:
            raise InputError("sample buffer capacity must be at least 1")
        self._initial_capacity = initial_capacity
        self._allocate(initial_capacity)
        self._count = 0

    def _allocate(self, capacity: int) -> None:
        self._storage = np.zeros(capacity * SAMPLE_FRAME_BYTES, dtype=np.uint8)
        self._view = self._storage.data
        self._capacity = capacity

    def __len__(self) -> int:
        return self._count

    def clear(self) -> None:
        """Forget the samples; shrink back if a long capture grew the buffer."""
        if self._capacity != self._initial_capacity:
            self._allocate(self._initial_capacity)
        self._count = 0

    def append(self, payload: bytes | bytearray) -> None:
        if self._count == self._capacity:
            grown = np.zeros(self._capacity * 2 * SAMPLE_FRAME_BYTES, dtype=np.uint8)
            grown[: self._storage.size] = self._storage
            self._storage = grown
            self._view = grown.data
            self._capacity *= 2
        start = self._count * SAMPLE_FRAME_BYTES
        self._view[start : start + SAMPLE_FRAME_BYTES] = payload
        self._count += 1

    def decode(self) -> tuple[npt.NDArray[np.uint16], npt.NDArray[np.int16]]:
        return decode_samples(self._view[: self._count * SAMPLE_FRAME_BYTES])


class CanopenSensor(AccelerationSensor):
    """The MEMS node: configuration by SDO, samples from its synchronous TPDO1.

    Like the drive, the constructor attaches the node and starts it (NMT
    OPERATIONAL, confirmed by heartbeat): a silent sensor is found at once.
    """

    def __init__(
        self,
        network: canopen.Network,
        node_id: int = 16,
        *,
        name: str = "sensor",
        sdo_timeout_s: float = 0.5,
        nmt_timeout_s: float = 1.0,
        initial_capacity: int = DEFAULT_INITIAL_CAPACITY,
        object_dictionary: canopen.ObjectDictionary | None = None,
    ) -> None:
        self.name = name
        self._network = network
        self._node_id = node_id
        self._closed = False
        self._lock = threading.Lock()
        self._buffer = SampleBuffer(initial_capacity)
        self._capturing = False
        self._malformed = 0
        self._capture_lsb = 0.0
        self._cob_id = TPDO1_COB_BASE + node_id
        check_node_id(node_id, name)
        od = (
            object_dictionary
            if object_dictionary is not None
            else load_od(DeviceKind.SENSOR, node_id)
        )
        self._node = attach_remote_node(network, node_id, od, name)
        try:
            self._sdo = SdoChannel(self._node, name, sdo_timeout_s)
            self._heartbeat = HeartbeatWatch(self._node)
            network.subscribe(self._cob_id, self._on_sample)
            start_node(network, node_id, self._heartbeat, name, timeout_s=nmt_timeout_s)
            self._boots_expected = self._heartbeat.boots
        except BaseException:
            self._detach()
            raise

    @property
    def node_id(self) -> int:
        return self._node_id

    def identity(self) -> DeviceIdentity:
        return self._sdo.identity()

    def range_g(self) -> int:
        return self._sdo.read_int(SensorObject.RANGE)

    def set_range_g(self, range_g: int) -> None:
        if range_g not in SENSOR_RANGES_G:
            raise InputError(
                f"{self.name}: range {range_g} g is not one of {list(SENSOR_RANGES_G)} g"
            )
        with self._lock:
            capturing = self._capturing
        if capturing:
            # Samples of one capture share one LSB; a range change would split them.
            raise DeviceStateError(self.name, "cannot change the range during a capture")
        self._sdo.write(SensorObject.RANGE, 0, range_g)

    def lsb_mps2(self) -> float:
        return self._sdo.read_float(SensorObject.SENSITIVITY)

    def sample_counter(self) -> int:
        """The sensor's current sample counter (0x2010)."""
        return self._sdo.read_int(SensorObject.SAMPLE_COUNTER)

    def heartbeat_age_s(self) -> float | None:
        return self._heartbeat.age_s()

    def check_alive(self, max_age_s: float = LIVENESS_TIMEOUT_S) -> None:
        """Raise if the node fell silent, or rebooted (its range is back to the default)."""
        check_alive(self._heartbeat, self._sdo, self.name, max_age_s=max_age_s,
                    boots_expected=self._boots_expected)

    def _on_sample(self, can_id: int, data: bytearray, timestamp: float) -> None:
        # Notifier thread, once per SYNC: copy the payload and nothing else.
        with self._lock:
            if len(data) != SAMPLE_FRAME_BYTES:
                self._malformed += 1
                return
            if self._capturing:
                self._buffer.append(data)

    def start_capture(self) -> None:
        lsb = self.lsb_mps2()
        with self._lock:
            self._buffer.clear()
            self._malformed = 0
            self._capture_lsb = lsb
            self._capturing = True

    def stop_capture(self) -> SensorCapture:
        with self._lock:
            if not self._capturing:
                raise DeviceStateError(self.name, "stop_capture without start_capture")
            self._capturing = False
            counter, counts = self._buffer.decode()
            malformed = self._malformed
            self._buffer.clear()
        if malformed:
            log.warning("%s: %d TPDO1 frames of the wrong length ignored", self.name, malformed)
        return SensorCapture(
            counter=counter,
            counts=counts,
            lsb_mps2=self._capture_lsb,
            lost=count_lost_samples(counter),
        )

    def _detach(self) -> None:
        if self._on_sample in self._network.subscribers.get(self._cob_id, []):
            self._network.unsubscribe(self._cob_id, self._on_sample)
        detach_remote_node(self._network, self._node)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        with self._lock:
            self._capturing = False
        self._detach()
