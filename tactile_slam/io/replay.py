"""Real-time frame delivery for the online pipeline: replay of a recording at its
native frame rate, or a live camera, through a bounded buffer that counts every frame
it has to drop.

:class:`RealtimeFeed` reads its source in a background thread. A recording is paced:
frame ``k`` becomes available at ``t0 + k / (fps * rate)`` on the feed's clock, as if a
sensor produced it then; a live source paces itself. Frames wait in a buffer of
``capacity`` frames; when a new frame arrives and the buffer is full (the consumer,
i.e. the tracker, is busy), the *oldest* waiting frame is discarded and counted in
:attr:`RealtimeFeed.dropped` with its video index, never silently lost. ``rate=None``
turns pacing and dropping off: the reader waits for the consumer, so every frame is
delivered (the lossless mode used to compare with the offline pipeline).

Iteration yields :class:`Arrival` records: the frame and the clock time at which it
arrived (its due time for a paced recording, the read time otherwise), from which the
pipeline measures per-frame latency.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from tactile_slam.geometry.frame import InputError
from tactile_slam.io.frames import FrameSource, RawFrame, SequenceSource


@dataclass
class Arrival:
    """A delivered frame and when it arrived (seconds on the feed's clock)."""

    frame: RawFrame
    arrival: float


@dataclass
class FeedStats:
    """What the feed did so far.

    Attributes:
        read: frames read from the source.
        delivered: frames handed to the consumer.
        dropped_indices: video indices of the frames discarded because the buffer was full.
        late: paced frames read after their due time (the source itself was too slow).
    """

    read: int = 0
    delivered: int = 0
    dropped_indices: list[int] = field(default_factory=list)
    late: int = 0

    @property
    def dropped(self) -> int:
        return len(self.dropped_indices)


class RealtimeFeed:
    """Frames of ``source`` at real-time pace through a bounded, drop-counting buffer.

    Args:
        source: a recording (:class:`SequenceSource`, paced at ``fps * rate``) or a
            live stream (any other :class:`FrameSource`, read as fast as it delivers).
        rate: replay speed as a multiple of the native frame rate (1.0: native);
            ``None``: lossless, the reader waits for the consumer and nothing is dropped.
        capacity: frames the buffer holds before it drops the oldest (>= 1).
        clock: monotonic clock in seconds.

    The feed is single-use: iterate it once. :meth:`close` stops the reader thread; the
    source itself stays open (its owner closes it).

    Raises:
        InputError: bad ``rate`` or ``capacity``; a read error of the source is re-raised
            by the iteration after the frames read before it.
    """

    def __init__(self, source: FrameSource, rate: float | None = 1.0, capacity: int = 3,
                 clock: Callable[[], float] = time.monotonic):
        if rate is not None and not rate > 0:
            raise InputError(f"replay rate must be > 0 (or None for lossless), got {rate}")
        if capacity < 1:
            raise InputError(f"feed capacity must be >= 1 frame, got {capacity}")
        self.source = source
        self.rate = rate
        self.capacity = int(capacity)
        self.clock = clock
        self.paced = rate is not None and isinstance(source, SequenceSource)
        self.stats = FeedStats()
        self._buffer: deque[Arrival] = deque()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._done = False
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None

    @property
    def dropped(self) -> int:
        """Frames discarded so far because the consumer was busy."""
        return self.stats.dropped

    # ------------------------------------------------------------------ reader
    def _put(self, item: Arrival) -> None:
        with self._cond:
            if self.rate is None:  # lossless: wait for room
                while len(self._buffer) >= self.capacity and not self._stop.is_set():
                    self._cond.wait(0.1)
            elif len(self._buffer) >= self.capacity:
                self.stats.dropped_indices.append(self._buffer.popleft().frame.index)
            self._buffer.append(item)
            self._cond.notify_all()

    def _read(self) -> None:
        try:
            period = 1.0 / (self.source.fps * self.rate) if self.paced else 0.0
            t0 = self.clock()
            for k, frame in enumerate(self.source):
                if self._stop.is_set():
                    break
                self.stats.read += 1
                if self.paced:
                    due = t0 + k * period
                    wait = due - self.clock()
                    if wait > 0:
                        self._stop.wait(wait)
                    else:
                        self.stats.late += 1
                    arrival = due
                else:
                    arrival = self.clock()
                self._put(Arrival(frame, arrival))
        except BaseException as exc:  # handed to the consumer
            self._error = exc
        finally:
            with self._cond:
                self._done = True
                self._cond.notify_all()

    # ------------------------------------------------------------------ consumer
    def __iter__(self) -> Iterator[Arrival]:
        if self._thread is not None:
            raise InputError("a RealtimeFeed can be iterated only once")
        self._thread = threading.Thread(target=self._read, name="realtime-feed", daemon=True)
        self._thread.start()
        try:
            while True:
                with self._cond:
                    while not self._buffer and not self._done:
                        self._cond.wait(0.1)
                    if not self._buffer:
                        break
                    item = self._buffer.popleft()
                    self._cond.notify_all()
                self.stats.delivered += 1
                yield item
            if self._error is not None:
                raise self._error
        finally:
            self.close()

    def close(self) -> None:
        """Stop the reader thread (frames still buffered are not delivered)."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)


class LoopedSource(SequenceSource):
    """A recording played ``length`` frames long, starting over at its end (a soak
    test from a short scan).

    Position ``k`` is pass ``p = k // n`` over ``source[k % n]`` (``n = len(source)``).
    The first pass is the source itself: same video indices and timestamps (a scan's
    start after its background window). Each later pass is shifted by the source's
    index span ``s = last index - first index + 1`` (``n`` for a recording without
    gaps): its frames have index ``source[k % n].index + p * s`` and timestamp
    ``source[k % n].timestamp + p * s / fps``, so indices keep increasing with no
    repeat and, without gaps, run on contiguously (a scan with 10 background frames
    and 50 data frames gives indices 10-59, 60-109, ...; rows 0-9 of the outputs
    are the background window, as for the scan).

    Attributes:
        background: the source's background (``(H, W, 3)`` float32 BGR), or ``None``
            when it has none (the pipeline then takes it from the first frames).
        background_check: the source's :class:`~tactile_slam.io.scan.BackgroundCheck`,
            or ``None``.
        span: the index shift ``s`` from one pass to the next.

    Raises:
        InputError: empty source or ``length < 1``.
    """

    def __init__(self, source: SequenceSource, length: int):
        if len(source) == 0 or length < 1:
            raise InputError(f"cannot loop {source.name} ({len(source)} frames) to {length} frames")
        self.source, self.length = source, int(length)
        self.fps, self.shape, self.name = source.fps, source.shape, f"{source.name} (looped to {length} frames)"
        self.background = getattr(source, "background", None)
        self.background_check = getattr(source, "background_check", None)
        self.span = source[-1].index - source[0].index + 1

    def __len__(self) -> int:
        return self.length

    def frame(self, position: int) -> RawFrame:
        loop, row = divmod(position, len(self.source))
        f = self.source[row]
        shift = loop * self.span
        return RawFrame(f.index + shift, f.timestamp + shift / self.fps, f.bgr, f.gradients, f.contact)
