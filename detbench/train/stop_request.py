"""How a training run takes a stop: the first Ctrl-C or SIGTERM becomes a request, checked between steps.

The loop finishes the step it is in, writes a checkpoint and returns (`TrainResult.interrupted`), so
`--resume` continues exactly. After the first, a SIGTERM is absorbed (the study's driver passes a stop
on to a job that got the terminal's Ctrl-C already), and so is a Ctrl-C within 2 s of the first (the
same keypress, forwarded by torchrun); a Ctrl-C later than that aborts at once, without a checkpoint.
"""
from __future__ import annotations

import signal
import threading
import time
from collections.abc import Iterator
from typing import Any

from torch.utils.data import DataLoader
from tqdm import tqdm

__all__ = ["StopRequest"]


class StopRequest:
    """Turns the first Ctrl-C / SIGTERM into a flag checked between steps; a second Ctrl-C aborts at once."""

    def __init__(self, announce: bool):
        self.requested = False
        self.announce = announce
        self._first = 0.0
        self._old: dict[int, Any] = {}

    def _handler(self, signum, frame):
        now = time.monotonic()
        if self.requested:
            # a second Ctrl-C aborts; one within 2 s of the first is the same keypress forwarded
            # again (torchrun passes the terminal's SIGINT on to its workers, which got it already)
            if signum == signal.SIGINT and now - self._first > 2.0:
                raise KeyboardInterrupt
            return
        self.requested, self._first = True, now
        if self.announce:
            tqdm.write(f"\n{signal.Signals(signum).name} received: finishing this step and saving a checkpoint "
                       f"(press Ctrl-C again to abort without saving)")

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                self._old[s] = signal.signal(s, self._handler)
        return self

    def __exit__(self, *exc) -> None:
        for s, old in self._old.items():
            signal.signal(s, old)

    def start_iter(self, loader: DataLoader) -> Iterator:
        """`iter(loader)` with SIGINT ignored while worker processes start, so they inherit the
        ignored disposition and a Ctrl-C (sent to the whole process group) reaches only this process."""
        if signal.SIGINT not in self._old:
            return iter(loader)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            return iter(loader)
        finally:
            signal.signal(signal.SIGINT, self._handler)
