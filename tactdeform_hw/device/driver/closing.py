"""Closing a device: every channel off, proved, before the port is let go.

Nothing after ``close`` could stop the board, so the all-off must be proved read: a proof that fails is
followed by the recovery (with the reset line if need be) and the all-off again, and a link that fails
under it is reopened (up to :data:`CLOSE_RECONNECTS` times) before the close gives up and says so.
"""

from __future__ import annotations

from collections.abc import Callable

from tactdeform_hw.device.driver.wire import Wire
from tactdeform_hw.device.links.recovery import RECOVERY_ATTEMPTS, LinkRecovery, LinkState
from tactdeform_hw.errors import NotStoppedError, ReplyLengthError, TactDeformError, TransportError

#: Times ``close`` reopens a link that failed under its all-off before it gives up and says so.
CLOSE_RECONNECTS = 3


def stop_and_prove(
    link: LinkRecovery,
    *,
    configured: Callable[[], bool],
    all_off: Callable[[], None],
    prove_stopped: Callable[[], None],
    recover: Callable[[], None],
) -> None:
    """All off (when ``configured``), and proof that nothing stimulates (``prove_stopped``: v1.2 the
    readings of the all-off, v2 count 0 proved by the sync reply's value).  A proof that fails (a board
    that rebooted or hung under the all-off, or one whose answer shows current still flowing) is followed
    by ``recover`` — with the reset line if need be — and the all-off and its proof again."""
    for attempt in range(1, RECOVERY_ATTEMPTS + 2):
        if configured():
            all_off()
        if link.state is not LinkState.IN_STEP:
            return
        try:
            prove_stopped()
            return
        except (ReplyLengthError, NotStoppedError):
            if attempt > RECOVERY_ATTEMPTS:
                raise
            recover()


def close_link(wire: Wire, *, stop: Callable[[], None], reconnect: Callable[[], None]) -> None:
    """``stop`` (the proved all-off), reopening the link with ``reconnect`` when it fails under it; the
    wire is closed and the port released whatever happens (the first failure is the one raised)."""
    if wire.closed:
        return
    try:
        try:
            stop()
        except TransportError as failed:
            for attempt in range(CLOSE_RECONNECTS):
                try:
                    reconnect()
                    stop()
                    break
                except TransportError:
                    if attempt == CLOSE_RECONNECTS - 1:
                        raise failed from None
                except TactDeformError:
                    raise failed from None
    finally:
        wire.closed = True
        wire.port_link.close()


__all__ = ["CLOSE_RECONNECTS", "close_link", "stop_and_prove"]
