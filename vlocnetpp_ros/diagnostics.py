"""Counters, rates and latency of the localizer node, reported as ``diagnostic_msgs/DiagnosticStatus``.

Thread-safe: the subscription callback records arrivals, the inference worker records results.
Rates and latency statistics cover the last ``window_s`` seconds; counters are totals since
start. Key names (``DiagnosticStatus.values``): ``input_rate_hz``, ``processing_rate_hz``,
``latency_ms_median``, ``latency_ms_max`` (callback -> outputs published), ``received``,
``processed``, ``dropped`` (replaced in the one-slot mailbox before inference), ``rejected``
(frames skipped, total) and ``rejected.<reason>``, ``ignored.<reason>`` (depth or camera
info not used, the frame still processed), ``resets`` (total) and ``reset.<reason>``, plus static
``info`` entries (checkpoint, device, input size, map). With refinement against a keyframe map
(``refinement``): ``refined``, the share of processed frames whose published pose is not the network's
own (refined or propagated), ``source.<source>`` (``network``, ``refined``, ``propagated``) and
``refine.<status>`` (the refinement tried per frame: ``refined``, or why not; see
:data:`vlocnetpp_core.mapping.refiner.STATUSES`) counts.

Memory is bounded whatever arrives: the rate and latency windows keep at most ``MAX_EVENTS``
entries (beyond that the rate is measured over the span they cover), and a counter or the
throttled log holds at most ``MAX_KEYS`` distinct keys (further ones are counted as ``other``);
log lines are cut at ``MAX_LINE`` characters.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

MAX_EVENTS = 10_000  # arrivals / finished frames kept for the rate and latency windows
MAX_KEYS = 64  # distinct reasons per counter (and keys of a ThrottledLog); the rest are "other"
MAX_LINE = 500  # characters of one log line


def _bounded_key(keys, key: str) -> str:
    """``key``, or ``"other"`` once ``keys`` (a dict) already holds ``MAX_KEYS`` others."""
    return key if key in keys or len(keys) < MAX_KEYS else "other"


class NodeStats:
    """What the node did, for ``/diagnostics``."""

    def __init__(self, window_s: float = 5.0, info: dict[str, str] | None = None, refinement: bool = False):
        self.window_s = window_s
        self.info = dict(info or {})
        self.refinement = refinement
        self._lock = threading.Lock()
        self._arrivals: deque[float] = deque(maxlen=MAX_EVENTS)
        self._done: deque[tuple[float, float]] = deque(maxlen=MAX_EVENTS)  # (finish time, latency s)
        self.received = 0
        self.processed = 0
        self.dropped = 0
        self.rejected: Counter[str] = Counter()
        self.ignored: Counter[str] = Counter()
        self.resets: Counter[str] = Counter()
        self.sources: Counter[str] = Counter()  # of the published pose, per processed frame
        self.refine_statuses: Counter[str] = Counter()

    def arrived(self, now: float, replaced: bool) -> None:
        with self._lock:
            self.received += 1
            self.dropped += int(replaced)
            self._arrivals.append(now)
            self._trim(now)

    def processed_frame(
        self,
        now: float,
        latency_s: float,
        reset_reason: str | None,
        source: str = "network",
        refine_status: str | None = None,
    ) -> None:
        """A frame answered; ``source`` of its published pose and ``refine_status`` of the refinement tried on it
        (``LocalizerResult``; None: none tried)."""
        with self._lock:
            self.processed += 1
            self._done.append((now, latency_s))
            if reset_reason is not None and reset_reason != "start":
                self.resets[_bounded_key(self.resets, reset_reason)] += 1
            self.sources[_bounded_key(self.sources, source)] += 1
            if refine_status is not None:
                self.refine_statuses[_bounded_key(self.refine_statuses, refine_status)] += 1
            self._trim(now)

    def reject(self, reason: str) -> None:
        """A camera frame skipped for ``reason``."""
        with self._lock:
            self.rejected[_bounded_key(self.rejected, reason)] += 1

    def ignore(self, reason: str) -> None:
        """A side input (depth, camera info) not used for ``reason``; frames still processed."""
        with self._lock:
            self.ignored[_bounded_key(self.ignored, reason)] += 1

    def _trim(self, now: float) -> None:
        while self._arrivals and self._arrivals[0] < now - self.window_s:
            self._arrivals.popleft()
        while self._done and self._done[0][0] < now - self.window_s:
            self._done.popleft()

    def _rate(self, count: int, oldest: float, now: float) -> float:
        """Events per second in the window; over the span the kept events cover once ``MAX_EVENTS`` are kept."""
        if count < MAX_EVENTS:
            return count / self.window_s
        return count / max(now - oldest, 1e-9)

    def snapshot(self, now: float | None = None) -> dict[str, float | int | str]:
        """Every reported value by key (numbers stay numbers here)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self._trim(now)
            lat = sorted(d[1] for d in self._done)
            out: dict[str, float | int | str] = {
                "input_rate_hz": self._rate(len(self._arrivals), self._arrivals[0] if self._arrivals else now, now),
                "processing_rate_hz": self._rate(len(self._done), self._done[0][0] if self._done else now, now),
                "latency_ms_median": 1000.0 * lat[len(lat) // 2] if lat else 0.0,
                "latency_ms_max": 1000.0 * lat[-1] if lat else 0.0,
                "received": self.received,
                "processed": self.processed,
                "dropped": self.dropped,
                "rejected": sum(self.rejected.values()),
                "resets": sum(self.resets.values()),
            }
            out.update({f"rejected.{k}": v for k, v in sorted(self.rejected.items())})
            out.update({f"ignored.{k}": v for k, v in sorted(self.ignored.items())})
            out.update({f"reset.{k}": v for k, v in sorted(self.resets.items())})
            if self.refinement:
                not_network = self.processed - self.sources.get("network", 0)
                out["refined"] = not_network / self.processed if self.processed else 0.0
                out.update({f"source.{k}": v for k, v in sorted(self.sources.items())})
                out.update({f"refine.{k}": v for k, v in sorted(self.refine_statuses.items())})
            out.update(self.info)
            return out

    def status(self, name: str, hardware_id: str, now: float | None = None) -> DiagnosticStatus:
        """``DiagnosticStatus``: OK while frames are processed, WARN when none arrive or none get through."""
        values = self.snapshot(now)
        if values["input_rate_hz"] == 0:
            level, message = DiagnosticStatus.WARN, "no camera frames received"
        elif values["processing_rate_hz"] == 0:
            level, message = DiagnosticStatus.WARN, "frames arrive but none are processed (see rejected.*)"
        else:
            level, message = (
                DiagnosticStatus.OK,
                f"{values['processing_rate_hz']:.1f} Hz, median latency {values['latency_ms_median']:.0f} ms",
            )
        return DiagnosticStatus(
            level=level,
            name=name,
            message=message,
            hardware_id=hardware_id,
            values=[KeyValue(key=k, value=_fmt(v)) for k, v in values.items()],
        )


def _fmt(v: float | int | str) -> str:
    return f"{v:.3f}" if isinstance(v, float) else str(v)


class ThrottledLog:
    """At most one log line per key every ``period_s`` seconds, telling how many were suppressed."""

    def __init__(self, log, period_s: float = 5.0):
        self._log = log
        self.period_s = period_s
        self._last: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()
        self._lock = threading.Lock()

    def __call__(self, key: str, message: str, now: float | None = None) -> bool:
        """Log ``message`` (cut at ``MAX_LINE`` characters) unless ``key`` was logged less than ``period_s``
        ago; True when logged. Keys beyond ``MAX_KEYS`` share the key ``other``."""
        now = time.monotonic() if now is None else now
        if len(message) > MAX_LINE:
            message = message[:MAX_LINE] + f"... ({len(message) - MAX_LINE} more characters)"
        with self._lock:
            key = _bounded_key(self._last, key)
            if key in self._last and now - self._last[key] < self.period_s:
                self._suppressed[key] += 1
                return False
            self._last[key] = now
            skipped = self._suppressed.pop(key, 0)
        self._log(message + (f" ({skipped} more like this in the last {self.period_s:g} s)" if skipped else ""))
        return True
