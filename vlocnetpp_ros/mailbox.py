"""A one-slot mailbox between a subscription callback and an inference worker: the newest wins.

``put`` never blocks (it only takes a lock held for a pointer swap) and replaces an item the
worker has not taken yet (the caller counts it as dropped); ``take`` waits for an item. When the camera is
faster than the model, frames are dropped instead of queued, so memory and latency stay bounded.
"""

from __future__ import annotations

import threading
from typing import Any


class LatestMailbox:
    """Holds at most one item."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: Any = None
        self._full = False
        self._closed = False

    def put(self, item: Any) -> bool:
        """Store ``item``; returns True when it replaced an unread one (a dropped frame)."""
        with self._cond:
            replaced = self._full
            self._item, self._full = item, True
            self._cond.notify()
        return replaced

    def take(self, timeout: float | None = None) -> Any:
        """The newest item, waiting up to ``timeout`` seconds; None on timeout or once closed."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._full or self._closed, timeout):
                return None
            if self._closed:
                return None
            item, self._item, self._full = self._item, None, False
            return item

    def close(self) -> None:
        """Wake a waiting ``take`` (it returns None) and make every later ``take`` return None."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
