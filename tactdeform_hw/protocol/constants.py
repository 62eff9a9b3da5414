"""Numbers fixed by the eTactileKit firmware and board.

Those a firmware version's table holds (:mod:`.firmware`) are read from the v1.2 table, the default
firmware, so each is written down once; the rest (board, link, current transfer) are written here."""

from __future__ import annotations

from .firmware import V1_2
from .firmware import Opcode as Opcode  # the v1.2 command bytes, re-exported for existing callers

#: Payload kinds: "u8", "u16" (little-endian, read only when both bytes wait), "pattern" (electrode_num
#: bytes, taken from the value at the moment the command byte is read), None (no payload, immediate reply).
PAYLOAD_KIND: dict[int, str | None] = V1_2.payload_kind

#: Fixed payload sizes in bytes (the pattern's size depends on electrode_num and is absent here).
PAYLOAD_SIZE: dict[int, int] = V1_2.payload_size

# --- firmware registers and limits ----------------------------------------------------------------------
PATTERN_BUFFER_SIZE = V1_2.pattern_buffer_size  # stim_pattern[] entries
MAX_ELECTRODES = V1_2.max_electrodes  # electrode_num is a u8
DAC_MAX_CODE = V1_2.dac_max_code  # 12-bit current DAC; the firmware clamps pulse height here
SENSE_HEIGHT_SHIFT = V1_2.command(Opcode.SENSE_HEIGHT).shift  # sense_pulse_height = v << 2
U8_MAX = 0xFF
U16_MAX = 0xFFFF

# Pattern byte values
PATTERN_SENSE = 0  # also every value other than 1 and 2: a sense pulse
PATTERN_MONOPHASIC = 1
PATTERN_BIPHASIC = 2

# Polarity register values
POLARITY_CATHODIC = 0
POLARITY_ANODIC = 1

# --- power-on state ---------------------------------------------------------------------------------------
POWER_ON_PERIOD_US = float(V1_2.power_on["period_us"])  # 100 Hz
POWER_ON_POLARITY = int(V1_2.power_on["polarity"])  # POLARITY_ANODIC

# --- the stimulation timer --------------------------------------------------------------------------------
TIMER_TICKS_PER_US = V1_2.timing.timer_ticks_per_us  # 80 MHz APB / 40 = 2 MHz

# --- the link ------------------------------------------------------------------------------------------
BAUD_RATE = 921_600
UART_BITS_PER_BYTE = 10  # 8N1
RX_QUEUE_SIZE = V1_2.rx_queue_bytes
USB_PACKET_SIZE = V1_2.usb_packet_bytes
USB_FRAME_US = 1000
ESPRESSIF_VID = 0x303A
ESP32S3_USB_JTAG_PID = 0x1001

# --- the current transfer ---------------------------------------------------------------------------------
DEFAULT_UA_PER_CODE = 10  # one DAC code = 10 µA unless a board calibration says otherwise
CURRENT_STEP_UA = 10
MAX_CURRENT_UA = 10_000  # the TactDeform hardware's ceiling: 10 mA

# --- stacked switching boards ---------------------------------------------------------------------------
OUTPUTS_PER_HV513 = 8
STACK_SENSE_NUMERATOR = 9368.8636
STACK_SENSE_OFFSET = 1.51
