"""Opening a device's board, and the guardian that watches it.

A :class:`~tactdeform_hw.device.driver.base.Device` is driven only once its board has proved which
firmware it runs; what comes before — the port opened with its lines low, the pacer that port needs, the
identification (:mod:`.firmware_probe`), the version asked for checked, the guardian started and the
proof at open — is an :class:`Opener`'s, so the device keeps only the operations on a board it drives.
Whatever fails on the way gives the board up the same way (:meth:`Opener.refuse`): guardian let go, port
closed, nothing more written.

The guardian process (:mod:`~tactdeform_hw.device.safety.guardian`) outlives a reopened port and is told
every configuration; :class:`GuardianSlot` holds it for the device's whole life.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from tactdeform_hw.clock import Clock
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.dialect import Dialect
from tactdeform_hw.device.driver.firmware_probe import (
    Detection,
    FirmwareMismatchError,
    check_firmware,
    identify,
)
from tactdeform_hw.device.driver.pacing import Pacer, default_pacer
from tactdeform_hw.device.driver.wire import Wire
from tactdeform_hw.device.links.port import no_delay
from tactdeform_hw.device.links.recovery import LinkRecovery
from tactdeform_hw.device.safety.guardian import Guardian, pace_for, start_guardian
from tactdeform_hw.errors import ConfigurationError, TactDeformError
from tactdeform_hw.ports import is_instant, loses_bytes

logger = logging.getLogger("tactdeform_hw.device")

#: What the driver says when a port declares a link that can lose bytes and the plain encoding is in force.
PLAIN_ON_LOSSY_LINK = (
    "{port}: the link can lose bytes without telling (a UART) and the plain encoding is in force: one lost "
    "byte can turn a zero into a full-scale pulse (DAC code 4095) until the fail-safe's recovery; use the "
    "loss-tolerant encoding (--encoding robust, or open_device(..., robust_encoding=True))"
)


def check_encoding_choice(pacer: Pacer | None, robust_encoding: bool | None) -> None:
    """A pacer given with an encoding it does not use is refused before the port is opened: which of the
    two the caller meant cannot be guessed, and the encoding decides what a lost byte can do."""
    if pacer is not None and robust_encoding is not None and pacer.robust != robust_encoding:
        raise ConfigurationError(
            f"robust_encoding={robust_encoding} disagrees with the pacer given "
            f"(its policy's robust_encoding is {pacer.robust}): give one or the other"
        )


class GuardianSlot:
    """The guardian process watching a device's owner, if any (``who()`` names the device to it)."""

    def __init__(self, who: Callable[[], str]) -> None:
        self.guardian: Guardian | None = None
        #: Whether this device runs a guardian (decided at open; a reopened port gets a new one).
        self.wanted = False
        self.who = who

    def start(self, wire: Wire) -> None:
        self.guardian = start_guardian(wire.port_link.port, self.who())

    def tell(self, dialect: Dialect, cfg: StimConfig | None) -> None:
        """The guardian's stop packet and pace for the configuration in force."""
        g = self.guardian
        if g is None or cfg is None:
            return
        drain_s, zeros_s = pace_for(
            cfg.rate_hz, cfg.electrode_count, cfg.pulse_width_us, cfg.discharge_us, cfg.sense_width_us
        )
        g.configure(dialect.guardian_stop(cfg.electrode_count), drain_s, zeros_s)

    def set_stop(self, stop: bytes | None) -> None:
        if stop is not None and self.guardian is not None:
            self.guardian.set_stop(stop)

    def reopen(self, wire: Wire) -> None:
        """Reopen the port: the guardian shares the old descriptor (and its lock), so it is let try to
        switch off through it, then a new one is started on the new descriptor."""
        g, self.guardian = self.guardian, None
        if g is not None:
            g.abandon()
        wire.port_link.reopen()
        if self.wanted:
            self.start(wire)

    def let_go(self, *, switched_off: bool) -> None:
        """The owner is done: released when it switched off itself, else abandoned (it switches off)."""
        g, self.guardian = self.guardian, None
        if g is not None:
            if switched_off:
                g.release()
            else:
                g.abandon()


class Opener:
    """Opens the board behind ``wire`` (its port, pacer and audit log) with ``guardians``."""

    def __init__(self, wire: Wire, guardians: GuardianSlot) -> None:
        self.wire = wire
        self.guardians = guardians

    def open_port(
        self, *, own_pacer: bool, offline_clock: Clock | None, robust_encoding: bool | None = None
    ) -> None:
        """Open the port if it is not (lines low first), and with ``own_pacer`` give the wire the pacer
        that port needs — known only once it is open (a URL builds its device then) — in the encoding
        ``robust_encoding`` chooses (None: the port's own)."""
        link = self.wire.port_link
        if not link.port.is_open:
            try:
                link.open()
            except BaseException:
                self.wire.closed = True
                raise
        no_delay(link.port)
        if own_pacer:
            self.wire.pacer = default_pacer(link.port, robust_encoding)
            if offline_clock is not None and is_instant(link.port):
                # a port that answers at once (the in-process emulator) runs the session on the caller's clock
                self.wire.pacer = Pacer(clock=offline_clock, policy=self.wire.pacer.policy)

    def warn_plain_on_lossy_link(self) -> None:
        """A port that declares a link that can lose bytes (``loses_bytes``: a UART) driven in the plain
        encoding: one lost byte can set a full-scale pulse until the recovery (docs/safety.md), and the
        loss-tolerant encoding is the caller's to choose (the default stays plain, which every figure of
        a USB board depends on), so the choice is said in the log and recorded in the audit log."""
        wire = self.wire
        if wire.pacer.robust or not loses_bytes(wire.port_link.port):
            return
        message = PLAIN_ON_LOSSY_LINK.format(port=wire.port_link.name)
        logger.warning(message)
        if wire.audit is not None:
            wire.audit.event("plain_encoding_on_lossy_link", port=wire.port_link.name, message=message)

    def identify(self, link: LinkRecovery, *, settle_s: float | None, boot_s: float) -> Detection:
        """Prove which firmware runs the board (:func:`~.firmware_probe.identify`); refuse it otherwise."""
        wire = self.wire
        link.unproved_since = wire.pacer.clock.now()
        try:
            return identify(wire.port_link, wire.pacer.clock, wire.audit, settle_s=settle_s, boot_s=boot_s)
        except BaseException:
            self.refuse()
            raise

    def accept(self, probe: Detection, firmware: str, guardian: bool | None) -> None:
        """The identification's bytes counted and logged, the version asked for checked (a board that
        proved another is refused), and the guardian started (default: when the port is ``guardable``)."""
        wire = self.wire
        # the identification wrote before anything else: its bytes are this device's own
        wire.pacer.stats.bytes_written += probe.bytes_sent
        if wire.audit is not None:
            wire.audit.event(
                "firmware_probe",
                firmware=probe.name,
                attempts=probe.attempts,
                bytes=probe.bytes_sent,
                reply=probe.reply.hex(),
                settle_s=probe.settle_s,
            )
        self.warn_plain_on_lossy_link()
        if firmware != "auto" and probe.name != firmware:
            self.refuse()
            check_firmware(firmware, probe, wire.port_link.name)
        port = wire.port_link.port
        self.guardians.wanted = bool(getattr(port, "guardable", False)) if guardian is None else guardian
        if self.guardians.wanted:
            try:
                self.guardians.start(wire)
            except BaseException:
                wire.closed = True
                wire.port_link.close()
                raise

    def prove(
        self, lock: threading.RLock, recover: Callable[[], None], suspect: Callable[[str], None]
    ) -> None:
        """Right after opening, prove the parser in step (best effort: a board that does not answer yet is
        proved by the first command, which raises if it still cannot be).  A board that answers as another
        firmware is stopped, refused and released: nothing is sent before it proves its parser."""
        try:
            with lock:
                try:
                    recover()  # a locked or hung board (perhaps still stimulating) gets the reset line
                except FirmwareMismatchError:
                    raise  # another firmware than the one this device speaks: refused, never driven
                except TactDeformError:
                    suspect("no proof at open")
        except FirmwareMismatchError:
            self.refuse()
            raise

    def refuse(self) -> None:
        """Give up a board before driving it: the guardian let go, the port closed, nothing more written."""
        self.wire.closed = True
        g, self.guardians.guardian = self.guardians.guardian, None
        if g is not None:
            g.release()
        self.wire.port_link.close()


__all__ = ["GuardianSlot", "Opener"]
