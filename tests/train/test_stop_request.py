"""How the training loop takes a stop (detbench.train.stop_request.StopRequest): the first Ctrl-C or SIGTERM asks for a
checkpoint and a clean stop; the study's SIGTERM after a terminal's Ctrl-C (one keypress reaching the whole
group) does not cut that short; a second Ctrl-C later aborts."""
from __future__ import annotations

import os
import signal

import pytest

from detbench.train import stop_request


def deliver(sig: int) -> None:
    os.kill(os.getpid(), sig)  # Python runs the handler before the next bytecode of this thread


@pytest.mark.parametrize("first", [signal.SIGINT, signal.SIGTERM], ids=["ctrl_c", "sigterm"])
def test_the_first_signal_asks_for_a_stop_and_the_study_s_sigterm_after_it_is_absorbed(first):
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    with stop_request.StopRequest(announce=False) as stop:
        deliver(first)
        assert stop.requested
        deliver(signal.SIGTERM)  # the driver passing the stop on: no abort, the checkpoint still gets written
        assert stop.requested
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before  # handlers restored


def test_a_second_ctrl_c_after_two_seconds_aborts_but_the_same_keypress_forwarded_does_not(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(stop_request.time, "monotonic", lambda: now[0])
    with stop_request.StopRequest(announce=False) as stop:
        deliver(signal.SIGINT)
        now[0] += 0.5
        deliver(signal.SIGINT)  # within 2 s: the same keypress, forwarded
        assert stop.requested
        now[0] += 5.0
        with pytest.raises(KeyboardInterrupt):
            deliver(signal.SIGINT)
