"""Numbers fixed by the eTactileKit firmware and board; the single place they are written down."""

from __future__ import annotations

from enum import IntEnum


class Opcode(IntEnum):
    """Command bytes, host to device.  Any other byte is ignored by the firmware (one byte consumed)."""

    MEASURE = 0xFF
    PATTERN = 0xFE
    POLARITY = 0xFD
    ELECTRODE_NUM = 0xFC
    PULSE_HEIGHT = 0xFB
    PULSE_WIDTH = 0xFA
    SENSE_HEIGHT = 0xF9
    SENSE_WIDTH = 0xF8
    DISCHARGE = 0xF7
    FREQUENCY = 0xF6
    HV513_COUNT = 0xF5


#: Payload kinds: "u8", "u16" (little-endian, read only when both bytes wait), "pattern" (electrode_num
#: bytes, taken from the value at the moment the command byte is read), None (no payload, immediate reply).
PAYLOAD_KIND: dict[int, str | None] = {
    Opcode.MEASURE: None,
    Opcode.PATTERN: "pattern",
    Opcode.POLARITY: "u8",
    Opcode.ELECTRODE_NUM: "u8",
    Opcode.PULSE_HEIGHT: "u16",
    Opcode.PULSE_WIDTH: "u16",
    Opcode.SENSE_HEIGHT: "u8",
    Opcode.SENSE_WIDTH: "u8",
    Opcode.DISCHARGE: "u8",
    Opcode.FREQUENCY: "u16",
    Opcode.HV513_COUNT: None,
}

#: Fixed payload sizes in bytes (the pattern's size depends on electrode_num and is absent here).
PAYLOAD_SIZE: dict[int, int] = {op: {"u8": 1, "u16": 2, None: 0}[k] for op, k in PAYLOAD_KIND.items() if k != "pattern"}

# --- firmware registers and limits ----------------------------------------------------------------------
PATTERN_BUFFER_SIZE = 256  # stim_pattern[] entries
MAX_ELECTRODES = 255  # electrode_num is a u8
DAC_MAX_CODE = 4095  # 12-bit current DAC; the firmware clamps pulse height here
SENSE_HEIGHT_SHIFT = 2  # sense_pulse_height = v << 2
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
POWER_ON_PERIOD_US = 10_000.0  # 100 Hz
POWER_ON_POLARITY = POLARITY_ANODIC

# --- the stimulation timer --------------------------------------------------------------------------------
TIMER_TICKS_PER_US = 2  # 80 MHz APB / 40 = 2 MHz

# --- the link ------------------------------------------------------------------------------------------
BAUD_RATE = 921_600
UART_BITS_PER_BYTE = 10  # 8N1
RX_QUEUE_SIZE = 256
USB_PACKET_SIZE = 64
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
