"""The device interface the renderer uses, written once; transports implement a few private methods.

Every public method checks its input, passes currents through the safety guard, refuses any sequence
that would trigger a known firmware defect, and only then builds bytes with :mod:`tactdeform_hw.protocol`
and writes them — one write per command.  ``close`` is idempotent and leaves every channel off.
"""

from __future__ import annotations

import warnings
from abc import ABC, abstractmethod
from collections.abc import Sequence
from types import TracebackType

from .. import protocol as p
from ..errors import LimitError, PortNotOpenError, ProtocolMisuseError, ShortReplyError
from ..protocol.constants import PATTERN_BIPHASIC, PATTERN_MONOPHASIC, PATTERN_SENSE, RX_QUEUE_SIZE
from ..protocol.units import DEFAULT_TRANSFER, CurrentTransfer
from .config import POLARITY_CODE, StimConfig, sense_code
from .mapping import ChannelMapping
from .safety import SafetyGuard

#: Pattern levels a host may send: off (a sense pulse, 0 µA while sense current is 0), mono, biphasic.
ALLOWED_LEVELS = frozenset({PATTERN_SENSE, PATTERN_MONOPHASIC, PATTERN_BIPHASIC})


class Device(ABC):
    """An eTactileKit-compatible stimulator.

    ``mapping`` translates application electrode order to hardware channels (identity by default);
    ``transfer`` converts µA to DAC codes; ``guard`` enforces current limits.
    """

    def __init__(
        self,
        *,
        mapping: ChannelMapping | None = None,
        transfer: CurrentTransfer = DEFAULT_TRANSFER,
        guard: SafetyGuard | None = None,
    ) -> None:
        self.mapping = mapping
        self.transfer = transfer
        self.guard = guard if guard is not None else SafetyGuard()
        self._config: StimConfig | None = None
        self._current_ua = 0
        self._last_pattern: bytes | None = None
        self._closed = False

    # --- transport (implemented by subclasses) --------------------------------------------------------------

    @abstractmethod
    def _write(self, data: bytes) -> None:
        """Write one whole command."""

    @abstractmethod
    def _read(self, size: int) -> bytes:
        """Read up to ``size`` bytes, honouring the transport's timeout."""

    @abstractmethod
    def _close_transport(self) -> None:
        """Release the port."""

    def _discard_input(self) -> None:  # noqa: B027 - optional hook, a no-op by default
        """Drop stale bytes waiting from the device (optional for transports)."""

    # --- state ---------------------------------------------------------------------------------------------

    @property
    def config(self) -> StimConfig | None:
        """The configuration last sent (None until ``configure``)."""
        return self._config

    @property
    def current_ua(self) -> int:
        return self._current_ua

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def electrodes(self) -> int:
        """Application electrodes a pattern must have (0 until configured)."""
        if self._config is None:
            return 0
        return self.mapping.electrodes if self.mapping is not None else self._config.electrode_count

    # --- commands ------------------------------------------------------------------------------------------

    def configure(self, config: StimConfig) -> None:
        """Send a whole configuration in an order that never stimulates with a half-set state.

        The height goes to 0 and every channel off first (so no pulse uses a mixture of old and new
        settings), the electrode count is followed at once by an all-off pattern of the new length (so no
        stale channel above the old count comes back), polarity changes while all is off, and the
        participant's current comes last.
        """
        self._check_open()
        config = self.guard.check_config(config.validated(self.transfer))
        if self.mapping is not None and self.mapping.hw_channels != config.electrode_count:
            raise LimitError(
                "electrode_count",
                config.electrode_count,
                f"the channel mapping's hardware channel count {self.mapping.hw_channels}",
            )
        n = config.electrode_count
        self._send(p.encode_pulse_height(0))
        if self._config is not None:
            self._send(p.encode_pattern(bytes(self._config.electrode_count)))
        self._send(p.encode_sense_height(0))
        self._send(p.encode_electrode_num(n))
        self._send(p.encode_pattern(bytes(n)))
        self._last_pattern = bytes(n)
        self._send(p.encode_polarity(POLARITY_CODE[config.polarity]))
        self._send(p.encode_pulse_width(config.pulse_width_us))
        self._send(p.encode_sense_width(config.sense_width_us))
        self._send(p.encode_discharge(config.discharge_us))
        self._send(p.encode_frequency(config.rate_hz))
        self._send(p.encode_sense_height(sense_code(config.sense_current_ua, self.transfer)))
        self._send(p.encode_pulse_height(self.transfer.to_code(config.current_ua)))
        self._config = config
        self._current_ua = config.current_ua

    def set_current(self, current_ua: int) -> None:
        """Change the pulse height (one command); the guard sees the pattern it will apply to."""
        cfg = self._require_config("set_current")
        code = self.transfer.to_code(current_ua)
        levels = self._application_levels()
        allowed = self.guard.check_current(current_ua, levels)
        if allowed != current_ua:
            code = self.transfer.to_code(allowed)
        self._send(p.encode_pulse_height(code))
        self._current_ua = allowed
        self._config = cfg.with_current(allowed)

    def send_pattern(self, levels: Sequence[int]) -> None:
        """Send a pattern in application order: 0 off, 1 monophasic, 2 biphasic."""
        cfg = self._require_config("send_pattern")
        expected = self.electrodes
        try:
            count = len(levels)
        except TypeError as exc:
            raise LimitError("pattern", levels, "a sequence of levels") from exc
        if count != expected:
            raise ProtocolMisuseError(
                f"pattern has {count} level(s) but the device is configured for {expected} electrode(s); "
                "a short pattern would swallow the next command and a long one would leak into it"
            )
        for i, v in enumerate(levels):
            if isinstance(v, bool) or not isinstance(v, int) or v not in ALLOWED_LEVELS:
                raise LimitError(f"pattern[{i}]", v, "0 (off), 1 (monophasic) or 2 (biphasic)")
        self.guard.check_pattern(levels, self._current_ua)
        hw = self.mapping.to_hardware(levels) if self.mapping is not None else bytes(levels)
        self._send(p.encode_pattern(hw, electrode_num=cfg.electrode_count))
        self._last_pattern = hw

    def all_off(self) -> None:
        """Every channel off and the pulse height at 0 (safe to call at any time after configure)."""
        self._check_open()
        if self._config is None:
            return
        n = self._config.electrode_count
        self._send(p.encode_pattern(bytes(n)))
        self._send(p.encode_pulse_height(0))
        self._last_pattern = bytes(n)
        self._current_ua = 0
        self._config = self._config.with_current(0)

    def measure(self) -> list[int]:
        """ADC codes (``raw >> 2``) of each hardware channel's last pulse, in hardware channel order."""
        cfg = self._require_config("measure")
        n = cfg.electrode_count
        self._discard_input()
        self._send(p.MEASURE_REQUEST)
        data = self._read_exact(2 * n, "measure")
        return p.parse_measure_reply(data, n)

    def hv513_count(self) -> int:
        """Ask the board how many HV513 chips it detects (this re-initialises their outputs)."""
        self._check_open()
        self._discard_input()
        self._send(p.HV513_COUNT_REQUEST)
        return p.parse_hv513_reply(self._read_exact(1, "hv513_count"))

    def resync(self) -> None:
        """Bring a parser of unknown state back in step: 256 zeros finish any command in progress, then
        pulse height 0 and an all-off pattern (a zero may have landed as a half u16 or as electrode
        count 0), then the whole configuration again."""
        self._check_open()
        self._send(bytes(RX_QUEUE_SIZE))
        self._send(p.encode_pulse_height(0))
        cfg = self._config
        if cfg is not None:
            n = cfg.electrode_count
            self._send(p.encode_electrode_num(n))
            self._send(p.encode_pattern(bytes(n)))
            self._config = None
            self.configure(cfg.with_current(0))
            if cfg.current_ua:
                self.set_current(cfg.current_ua)

    def close(self) -> None:
        """All channels off, then release the port.  Safe to call twice."""
        if self._closed:
            return
        try:
            if self._config is not None:
                self.all_off()
        finally:
            self._closed = True
            self._close_transport()

    def __enter__(self) -> Device:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __del__(self) -> None:
        if not getattr(self, "_closed", True):
            warnings.warn(f"{type(self).__name__} was never closed", ResourceWarning, stacklevel=1)

    # --- helpers -------------------------------------------------------------------------------------------

    def _send(self, data: bytes) -> None:
        self._check_open()
        self._write(data)

    def _read_exact(self, size: int, what: str) -> bytes:
        data = self._read(size)
        if len(data) != size:
            raise ShortReplyError(what, size, data)
        return data

    def _check_open(self) -> None:
        if self._closed:
            raise PortNotOpenError(f"{type(self).__name__} is closed")

    def _require_config(self, what: str) -> StimConfig:
        self._check_open()
        if self._config is None:
            raise ProtocolMisuseError(
                f"{what} before configure(): the firmware's electrode count is still 0, and a pattern now "
                "would lock its parser"
            )
        return self._config

    def _application_levels(self) -> list[int] | None:
        if self._last_pattern is None:
            return None
        if self.mapping is not None:
            return self.mapping.to_application(self._last_pattern)
        return list(self._last_pattern)
