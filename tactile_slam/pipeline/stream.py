"""Pose stream: per-frame poses from the online pipeline for policies and robot code.

The pipeline :meth:`PoseStream.publish`-es one :class:`PoseEvent` per tracked frame.
Consumers never slow the tracker down:

* :meth:`PoseStream.latest` returns the newest event at once (or ``None``): the call a
  control loop makes every tick;
* iterating the stream (or :meth:`PoseStream.get`) blocks for the next event; a consumer
  that falls behind loses the oldest events from its bounded queue (counted in
  :attr:`PoseStream.missed`) rather than stalling the producer;
* callbacks (:meth:`PoseStream.add_callback`) and JSON lines (``jsonl=`` a path or
  ``"-"`` for stdout) run on a separate dispatcher thread.

Poses are float64 metres. ``map_T_sensor`` is the sensor pose in the *map* frame: the
start frame of the frame's group (the sensor frame of the group's anchor keyframe,
method.md 7.1), using the back end's latest keyframe poses. The object is static in
the map, so ``sensor_T_object = inv(map_T_sensor)`` is the object pose in the sensor
frame. When a loop closure moves the group (or merges it into another), the pose
jumps: ``loop_corrected`` marks the first event after such a correction.
"""

from __future__ import annotations

import json
import sys
import threading
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import torch


@dataclass
class PoseEvent:
    """One frame's output.

    Attributes:
        index: video index of the frame.
        timestamp: seconds (the source's timestamp).
        in_contact: whether the frame was tracked; the pose fields are ``None`` otherwise.
        map_T_sensor: ``(4, 4)`` float64 metres, sensor pose in the map frame.
        sensor_T_object: ``(4, 4)`` float64 metres, object (map) pose in the sensor frame.
        keyframe_id / session / group: the frame's keyframe, tracking session and map
            group (``-1`` without contact).
        is_keyframe: the frame became a keyframe when it was tracked: true only for a
            session head (the first frame of a touch, or a frame at which registration
            broke). Most keyframes are made one frame late, by the lazy keyframe rule:
            when a frame's registration against the current keyframe fails or is
            refused (speed, tilt or cross-check limits), the *previous* frame becomes
            one, and its own event, already published, keeps ``False``.
        new_keyframes: video indices of the keyframes made while tracking this frame, in
            id order: this frame's own index for a session head, the previous frame's
            when the lazy rule (or, at a contact loss, the flush of the session's tail)
            made it one ("previous": the previous frame delivered, dropped frames aside).
            Over all events these are the keyframes of ``keyframes.json``, except a tail
            flushed when the run ends (end of stream, stop, Ctrl+C): no event follows it.
        ccs / scr: registration quality (NaN for a session head or without contact).
        conditioning: the registration's conditioning (``TrackStep.conditioning``): small
            where the contact leaves a motion weakly constrained; NaN where ``ccs`` is.
        loop_corrected: the back end moved this group's poses since the previous event.
        latency_ms: arrival of the frame to publication of its pose.
        frames_dropped: frames dropped by the feed so far.
    """

    index: int
    timestamp: float
    in_contact: bool
    map_T_sensor: torch.Tensor | None = None
    sensor_T_object: torch.Tensor | None = None
    keyframe_id: int = -1
    session: int = -1
    group: int = -1
    is_keyframe: bool = False
    new_keyframes: list[int] = field(default_factory=list)
    ccs: float = float("nan")
    scr: float = float("nan")
    conditioning: float = float("nan")
    loop_corrected: bool = False
    latency_ms: float = float("nan")
    frames_dropped: int = 0

    def to_dict(self) -> dict:
        """JSON-ready dict (poses as nested lists in metres, NaN as ``None``)."""
        out = {}
        for k, v in self.__dict__.items():
            if isinstance(v, torch.Tensor):
                v = v.tolist()
            elif isinstance(v, float) and v != v:
                v = None
            out[k] = v
        return out


class PoseStream:
    """Thread-safe fan-out of :class:`PoseEvent` records.

    Args:
        maxlen: events kept for a blocking consumer (older ones are dropped and counted).
        jsonl: write every event as a JSON line to this path, or ``"-"`` for the standard
            output in force when the stream is built (kept, and never closed, also when
            ``sys.stdout`` is redirected later).
    """

    def __init__(self, maxlen: int = 64, jsonl: str | Path | None = None):
        if maxlen < 1:
            raise ValueError(f"PoseStream maxlen must be >= 1, got {maxlen}")
        self._queue: deque[PoseEvent] = deque(maxlen=maxlen)
        self._cond = threading.Condition()
        self._latest: PoseEvent | None = None
        self._closed = False
        self.published = 0
        self.missed = 0
        self._callbacks: list[Callable[[PoseEvent], None]] = []
        self._dispatch: deque[PoseEvent] = deque()
        self._dispatch_cond = threading.Condition()
        self._dispatcher: threading.Thread | None = None
        self.callback_errors: list[str] = []
        self._jsonl: TextIO | None = None
        self._owns_jsonl = jsonl is not None and str(jsonl) != "-"  # standard output is not ours to close
        if jsonl is not None:
            self._jsonl = open(jsonl, "w") if self._owns_jsonl else sys.stdout  # noqa: SIM115
            self._start_dispatcher()

    # ------------------------------------------------------------------ producer
    def publish(self, event: PoseEvent) -> None:
        """Hand out one event (never blocks on consumers)."""
        with self._cond:
            if len(self._queue) == self._queue.maxlen:
                self.missed += 1
            self._queue.append(event)
            self._latest = event
            self.published += 1
            self._cond.notify_all()
        if self._dispatcher is not None:
            with self._dispatch_cond:
                self._dispatch.append(event)
                self._dispatch_cond.notify()

    def close(self) -> None:
        """End of stream: blocked consumers return, the dispatcher flushes and stops."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._dispatcher is not None:
            with self._dispatch_cond:
                self._dispatch_cond.notify()
            self._dispatcher.join()
            self._dispatcher = None
        if self._owns_jsonl and self._jsonl is not None:
            self._jsonl.close()
        self._jsonl = None

    @property
    def closed(self) -> bool:
        return self._closed

    # ------------------------------------------------------------------ consumers
    def latest(self) -> PoseEvent | None:
        """The newest event, without waiting (``None`` before the first)."""
        return self._latest

    def get(self, timeout: float | None = None) -> PoseEvent | None:
        """The next queued event; waits up to ``timeout`` seconds (``None``: until one
        arrives or the stream closes). Returns ``None`` on timeout or end of stream."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._queue or self._closed, timeout):
                return None
            return self._queue.popleft() if self._queue else None

    def __iter__(self) -> Iterator[PoseEvent]:
        """Blocking iteration until the stream closes."""
        while True:
            event = self.get()
            if event is None:
                return
            yield event

    def add_callback(self, fn: Callable[[PoseEvent], None]) -> None:
        """Call ``fn(event)`` for every later event on the dispatcher thread; an
        exception in ``fn`` is recorded in :attr:`callback_errors`, not raised."""
        self._callbacks.append(fn)
        self._start_dispatcher()

    # ------------------------------------------------------------------ dispatcher
    def _start_dispatcher(self) -> None:
        if self._dispatcher is None:
            self._dispatcher = threading.Thread(target=self._run_dispatch, name="pose-stream", daemon=True)
            self._dispatcher.start()

    def _run_dispatch(self) -> None:
        while True:
            with self._dispatch_cond:
                self._dispatch_cond.wait_for(lambda: self._dispatch or self._closed)
                if not self._dispatch:
                    return
                batch = list(self._dispatch)
                self._dispatch.clear()
            for event in batch:
                for fn in list(self._callbacks):
                    try:
                        fn(event)
                    except Exception as exc:  # a consumer's bug must not stop the stream
                        self.callback_errors.append(f"{type(exc).__name__}: {exc}")
                if self._jsonl is not None:
                    self._jsonl.write(json.dumps(event.to_dict()) + "\n")
            if self._jsonl is not None:
                self._jsonl.flush()
