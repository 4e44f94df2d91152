"""An emulated Benewake TFMini-family LiDAR: the frames the part streams on its UART, from the simulated
world, so the payload's unchanged driver (`firmware_py.drivers.tfmini`) reads them.

Two ports, one frame model:
- `EmulatedTfminiPort`: lockstep. An in-memory serial port on the simulated clock: frame k starts on
  the wire at t0 + k/f + output latency, its bytes become readable one byte time (10 bits at the baud
  rate) apart, its range is sampled at t0 + k/f. Nothing runs between reads: the bytes due by `now`
  are made when the driver reads.
- `PtyTfmini`: networked. The same frames written by a thread, in real time, into the master side of
  a pseudo-terminal; the payload opens the slave side (`serial:/dev/pts/N`) with pyserial, so the real
  serial code path runs in the loop.

The frame model (`frame_for`, per `TfminiVariant`): the signal strength falls as 1/r^2 and reaches
the model's weak threshold at its rated maximum range (the manuals rate range on a 90 % reflective
board), so a target beyond range, or no target at all, reads as the model's "weak" code (-1 on the
S/Plus/Luna, 0xFFFF on the TFmini); closer than the minimum range the S/Plus/Luna report -2 with a
saturated strength of 65535. Range noise (`range_noise`, a sensor-noise model from
`sitl.sensing.noise`, `--sensor-noise`: its reported range, or no return; or a plain Gaussian of
`range_noise_sigma_m`) is added before the 1 cm quantisation.

Faults: `bad_frames` (a probability that a frame's checksum byte is wrong), `garbage` (a probability
that a few random bytes follow a frame on the line, as a loose wire or a booting part sends) and
`unplugged` (the sensor's cable pulled off the UART pins: the line is silent, the frames of that
time are lost; put back, the part streams again). `PtyTfmini.remove_adapter()` is the other kind of
unplugging: a USB serial adapter pulled out, whose port then fails on every read.

Nobody reading: a real TFMini streams whether or not anyone listens, and a UART whose buffer is full
loses what comes next. `PtyTfmini` writes the pty's master without blocking: once the kernel's buffer
is full (about 20 KB, some 20 s of frames, when no payload has the port open or one has exited) the
bytes that do not fit are dropped and counted (`frames_dropped`, `bytes_dropped`), and stopping never
waits on a write (a blocking write there hung `serve` on SIGTERM).
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
import tty
from collections.abc import Callable

import numpy as np

from firmware_py.drivers.tfmini import BITS_PER_BYTE, FRAME_LEN, TfminiModel, TfminiVariant, encode_frame
from firmware_py.hal import Clock
from sitl.sensing.noise import RangeNoise

log = logging.getLogger(__name__)

MAX_GARBAGE_BYTES = 8
"""The most random bytes the garbage fault puts after one frame."""

STOP_TIMEOUT_S = 2.0
"""The longest `PtyTfmini.close()` waits for its writer (it never blocks: a frame period and a ray cast)."""


SATURATED_STRENGTH = 0xFFFF
TEMPERATURE_AUX = (25 + 256) * 8  # 25 deg C in the S/Plus/Luna encoding (T / 8 - 256)
SHORT_MODE_MAX_M = 5.0  # where the original TFmini's mode byte reads 02 (short) rather than 07 (an assumption)


def frame_for(variant: TfminiVariant, range_m: float | None, noise_m: float = 0.0) -> bytes:
    """The frame the part sends for a true range (None: nothing in the beam)."""
    weak = variant.weak_strength
    if range_m is None or not math.isfinite(range_m) or range_m <= 0.0:
        strength = 0
    else:
        strength = min(SATURATED_STRENGTH - 1, round(weak * (variant.max_range_m / range_m) ** 2))
    if variant.signed_dist:
        aux = TEMPERATURE_AUX
        if strength < weak:
            return encode_frame(-1, strength, aux)
        if range_m < variant.min_range_m:
            return encode_frame(-2, SATURATED_STRENGTH, aux)
    else:
        if strength < weak:
            return encode_frame(0xFFFF, strength, 0x0007)
        # The TFmini switches between its short (02) and long (07) distance modes by itself, which
        # keeps a usable echo inside its reliable strength window (20-2000).
        aux = 0x0002 if range_m < SHORT_MODE_MAX_M else 0x0007
        strength = min(strength, variant.max_strength or strength)
    cm = max(0, min(0x7FFF, math.floor((range_m + noise_m) * 100.0 + 0.5)))
    return encode_frame(cm, strength, aux)


class _FrameSource:
    """Frame k's bytes and when each is on the wire: shared by the lockstep and the pty ports."""

    def __init__(self, range_at: Callable[[int], float | None], model: TfminiModel, baud: int, rate_hz: float,
                 t0_ns: int, output_latency_ns: int, range_noise_sigma_m: float, bad_frames: float,
                 rng: np.random.Generator | None, range_noise: RangeNoise | None = None,
                 garbage: float = 0.0) -> None:
        if not callable(range_at):
            raise ValueError(f"range_at must be a callable t_ns -> range in m or None, got {range_at!r}")
        if not (math.isfinite(range_noise_sigma_m) and range_noise_sigma_m >= 0.0):
            raise ValueError(f"range noise sigma must be finite and >= 0 m, got {range_noise_sigma_m!r}")
        if range_noise is not None and not callable(getattr(range_noise, "measure", None)):
            raise ValueError(f"range_noise must be a sensor-noise model with measure(range_m), got {range_noise!r}")
        for name, p in (("bad frame", bad_frames), ("garbage", garbage)):
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} probability must be in [0, 1], got {p!r}")
        self.range_at, self.variant = range_at, model.value
        self.period_ns = round(1e9 / rate_hz)
        self.byte_ns = round(BITS_PER_BYTE * 1e9 / baud)
        if 9 * self.byte_ns > self.period_ns:
            raise ValueError(f"{rate_hz:g} Hz frames do not fit in {baud} baud")
        self.t0_ns, self.latency_ns = int(t0_ns), int(output_latency_ns)
        self.range_noise, self.bad_frames, self.garbage = range_noise, float(bad_frames), float(garbage)
        self.max_garbage = min(MAX_GARBAGE_BYTES, self.period_ns // self.byte_ns - FRAME_LEN)  # fits the period
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.noise_sigma_m = float(range_noise_sigma_m)
        self.frames_sent = 0
        self.bad_frames_sent = 0
        self.garbage_bursts = 0

    def measure_ns(self, k: int) -> int:
        return self.t0_ns + k * self.period_ns

    def wire_start_ns(self, k: int) -> int:
        return self.measure_ns(k) + self.latency_ns

    def frame(self, k: int) -> bytes:
        """Frame k's bytes on the line: the frame, and any garbage after it (before frame k+1)."""
        noise = float(self.rng.normal(0.0, self.noise_sigma_m)) if self.noise_sigma_m > 0.0 else 0.0
        r = self.range_at(self.measure_ns(k))
        if self.range_noise is not None and r is not None and math.isfinite(r) and r > 0.0:
            r = self.range_noise.measure(r)  # the sensor-noise model (None: no return: a weak frame)
        data = frame_for(self.variant, r, noise)
        self.frames_sent += 1
        if self.bad_frames > 0.0 and self.rng.random() < self.bad_frames:
            self.bad_frames_sent += 1
            data = data[:8] + bytes(((data[8] + 1) & 0xFF,))
        if self.garbage > 0.0 and self.max_garbage > 0 and self.rng.random() < self.garbage:
            self.garbage_bursts += 1
            n = int(self.rng.integers(1, self.max_garbage + 1))
            data += self.rng.integers(0, 256, size=n, dtype=np.uint8).tobytes()
        return data


class EmulatedTfminiPort:
    """A TFMini streaming into an in-memory serial port on the simulated clock (module docstring).

    Args:
        clock: the simulated clock; a read returns the bytes on the wire by `clock.now_ns()`.
        range_at: true range in m along the beam at a time in ns, or None for no target.
        model: the family member emulated.
        baud, rate_hz: the part's UART and frame rates.
        t0_ns: when the first frame is measured (default: now).
        output_latency_ns: from the measurement to the frame's first byte.
        range_noise_sigma_m: Gaussian range noise before the 1 cm quantisation.
        range_noise: a sensor-noise model (`sitl.sensing.noise.RangeNoiser`, built for TFMINI_S): the
            reported range, None for a no-return (a weak frame); before the 1 cm quantisation.
        bad_frames: probability that a frame's checksum is wrong.
        rng: noise and fault draws (default seeded 0, so runs repeat).
        range_noise: the range error as a function of the true range (`RangeNoise`).
        garbage: probability that random bytes follow a frame.
    """

    def __init__(self, clock: Clock, range_at: Callable[[int], float | None], *,
                 model: TfminiModel = TfminiModel.TFMINI_S, baud: int = 115_200, rate_hz: float = 100.0,
                 t0_ns: int | None = None, output_latency_ns: int = 0, range_noise_sigma_m: float = 0.0,
                 bad_frames: float = 0.0, rng: np.random.Generator | None = None,
                 range_noise: RangeNoise | None = None, garbage: float = 0.0) -> None:
        self.clock = clock
        self.source = _FrameSource(range_at, model, baud, rate_hz, clock.now_ns() if t0_ns is None else t0_ns,
                                   output_latency_ns, range_noise_sigma_m, bad_frames, rng, range_noise, garbage)
        self._k = 0  # the next frame to put on the wire
        self._pending = b""  # its bytes, made when its first byte was due
        self._sent = 0  # of those, already read
        self.unplugged = False
        self.closed = False

    def read(self, n: int) -> bytes:
        """Up to n bytes that are on the wire by now (never blocks)."""
        if self.closed:
            raise OSError("read on a closed serial port")
        now, src, out = self.clock.now_ns(), self.source, bytearray()
        if self.unplugged:  # a UART with nothing on its RX line reads as silence; those frames are lost
            self._pending, self._sent = b"", 0
            while src.wire_start_ns(self._k) <= now:
                self._k += 1
            return b""
        while len(out) < n:
            if self._sent == len(self._pending):
                if src.wire_start_ns(self._k) + src.byte_ns > now:
                    break  # not even the next frame's first byte is complete
                self._pending, self._sent = src.frame(self._k), 0
                self._k += 1
            start = src.wire_start_ns(self._k - 1)
            due = min(len(self._pending), (now - start) // src.byte_ns)  # bytes complete by now
            take = min(due - self._sent, n - len(out))
            if take <= 0:
                break
            out += self._pending[self._sent:self._sent + take]
            self._sent += take
        return bytes(out)

    def close(self) -> None:
        self.closed = True


class PtyTfmini:
    """A TFMini on a pseudo-terminal, in real time (module docstring). `path` is the serial port to
    open (`serial:{path}`); `start()` begins streaming, `unplugged` silences it (the sensor's cable),
    `remove_adapter()` closes the master side (a USB adapter gone), `close()` stops. Args as
    `EmulatedTfminiPort`, times in the monotonic clock's ns. Writes never block: what does not fit in
    the pty's buffer (nobody reads the port) is lost, counted in `frames_dropped` and `bytes_dropped`."""

    def __init__(self, range_at: Callable[[int], float | None], *, model: TfminiModel = TfminiModel.TFMINI_S,
                 baud: int = 115_200, rate_hz: float = 100.0, output_latency_ns: int = 0,
                 range_noise_sigma_m: float = 0.0, bad_frames: float = 0.0,
                 rng: np.random.Generator | None = None, range_noise: RangeNoise | None = None,
                 garbage: float = 0.0) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no line discipline: bytes pass as sent (0x0a stays 0x0a)
        os.set_blocking(self._master, False)  # a full buffer loses bytes, as a UART nobody reads: never waits
        self.path = os.ttyname(self._slave)
        self.source = _FrameSource(range_at, model, baud, rate_hz, time.monotonic_ns(), output_latency_ns,
                                   range_noise_sigma_m, bad_frames, rng, range_noise, garbage)
        self.unplugged = False  # the sensor's cable off the UART pins: silence, its frames lost
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pty-tfmini", daemon=True)
        self._lock = threading.Lock()
        self.frames_written = 0  # whole frames into the pty
        self.frames_dropped = 0  # frames lost, whole or in part, to a full buffer (nobody reading)
        self.bytes_dropped = 0  # the bytes lost so (frames and injected bytes)

    def start(self) -> PtyTfmini:
        self.source.t0_ns = time.monotonic_ns()
        self._thread.start()
        return self

    @property
    def running(self) -> bool:
        """Whether its writer thread is still going (false again once close() has returned)."""
        return self._thread.is_alive()

    def _write(self, data: bytes) -> int:
        """Put what fits of data on the line now (the caller holds the lock); the rest is lost. Returns the
        bytes written."""
        try:
            n = os.write(self._master, data)
        except BlockingIOError:  # the buffer is full: nobody reads the slave
            n = 0
        self.bytes_dropped += len(data) - n
        return n

    def _run(self) -> None:
        src, k = self.source, 0
        try:
            while not self._stop.is_set():
                wait_s = (src.wire_start_ns(k) - time.monotonic_ns()) / 1e9
                if wait_s > 0 and self._stop.wait(wait_s):
                    break
                if not self.unplugged:
                    data = src.frame(k)  # ray cast outside the lock: inject() never waits on it
                    with self._lock:
                        if self._master < 0:
                            break
                        whole = self._write(data) == len(data)
                    if whole:
                        self.frames_written += 1
                    else:
                        self.frames_dropped += 1
                k += 1
        except OSError:
            pass  # the master was closed under us (unplug): nothing more to send

    def inject(self, data: bytes) -> None:
        """Raw bytes on the line between two frames (a loose wire, a part booting); what does not fit is lost."""
        with self._lock:
            if self._master >= 0:
                self._write(data)

    def remove_adapter(self) -> None:
        """A USB serial adapter pulled out: the master side closes, the slave fails as a vanished port does."""
        if not self._lock.acquire(timeout=STOP_TIMEOUT_S):  # never hangs on a writer that cannot go on
            log.warning("the emulated TFMini's writer is stuck: its pseudo-terminal %s is left open", self.path)
            return
        try:
            if self._master >= 0:
                os.close(self._master)
                self._master = -1
        finally:
            self._lock.release()

    def close(self) -> None:
        """Stop streaming and close the pty, within about STOP_TIMEOUT_S whatever the reader does."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=STOP_TIMEOUT_S)
        self.remove_adapter()
        if self._slave >= 0:
            os.close(self._slave)
            self._slave = -1

    def __enter__(self) -> PtyTfmini:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
